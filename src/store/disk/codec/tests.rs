use super::*;
use crate::core::TaskConfigInput;

fn cfg(n: u32, m: u32) -> TaskConfig {
    TaskConfig::resolve(&TaskConfigInput {
        num_actions: n,
        action_dim: m,
        pool_capacity: Some(3),
        ..Default::default()
    })
    .unwrap()
}

#[test]
fn trajectories_round_trip_bit_for_bit() {
    let t = Trajectory {
        actions: ActionSeq::Continuous {
            dim: 2,
            data: vec![1.5, -0.0, f32::MIN_POSITIVE, 3.25],
        },
        score: -0.1,
        seq: 42,
    };
    let bytes = encode_trajectory(&t);
    let path = traj_path(Path::new("x"), 42);
    assert_eq!(decode_trajectory(&path, &bytes, &cfg(0, 2)).unwrap(), t);
    // Every truncation and every single-byte flip is detected.
    for cut in 0..bytes.len() {
        assert!(
            decode_trajectory(&path, &bytes[..cut], &cfg(0, 2)).is_err(),
            "cut {cut}"
        );
    }
    for i in 0..bytes.len() {
        let mut b = bytes.clone();
        b[i] ^= 0x40;
        assert!(
            decode_trajectory(&path, &b, &cfg(0, 2)).is_err(),
            "flip {i}"
        );
    }
    // Wrong kind for the task.
    assert!(decode_trajectory(&path, &bytes, &cfg(4, 0)).is_err());
    // Another file name.
    assert!(decode_trajectory(&traj_path(Path::new("x"), 7), &bytes, &cfg(0, 2)).is_err());
}

#[test]
fn well_formed_files_with_invalid_actions_are_reported() {
    let path = traj_path(Path::new("x"), 1);
    let discrete = Trajectory {
        actions: ActionSeq::Discrete(vec![0, 5]),
        score: 1.0,
        seq: 1,
    };
    let e = decode_trajectory(&path, &encode_trajectory(&discrete), &cfg(3, 0)).unwrap_err();
    assert!(
        e.contains("actions[1]") && e.contains("out of range"),
        "{e}"
    );
    let nan = Trajectory {
        actions: ActionSeq::Continuous {
            dim: 1,
            data: vec![f32::NAN],
        },
        score: 1.0,
        seq: 1,
    };
    let e = decode_trajectory(&path, &encode_trajectory(&nan), &cfg(0, 1)).unwrap_err();
    assert!(e.contains("must be finite"), "{e}");
}
