use super::*;
use crate::core::Trajectory;

fn pool(trajectories: Vec<(Vec<u32>, f64)>) -> Pool {
    let t = trajectories
        .into_iter()
        .enumerate()
        .map(|(i, (a, score))| Trajectory {
            actions: ActionSeq::Discrete(a),
            score,
            seq: i as u64 + 1,
        })
        .collect::<Vec<_>>();
    let n = t.len() as u64;
    Pool::restore(10, t, 7, n + 1).unwrap()
}

#[test]
fn a_bar_per_trajectory_in_score_order_and_the_version() {
    let p = pool(vec![
        (vec![0, 1], 1.0),
        (vec![2], 5.0),
        (vec![1, 1, 1], -2.0),
    ]);
    let svg = pool_svg(&p);
    assert_eq!(svg.matches(r#"<rect class="score""#).count(), 3);
    assert_eq!(svg.matches(r#"<rect class="length""#).count(), 3);
    assert!(svg.contains(r#"data-version="7""#) && svg.contains(r#"data-trajectories="3""#));
    let at = |s: &str| svg.find(s).unwrap();
    assert!(
        at("score 5 length 1") < at("score 1 length 2"),
        "best first"
    );
    assert!(at("score 1 length 2") < at("score -2 length 3"));
    assert!(svg.contains("data:image/bmp;base64,"));
}

#[test]
fn the_strip_is_a_bitmap_of_the_actions_colours() {
    let p = pool(vec![(vec![0, 1, 2, 3], 2.0), (vec![13, 13], 1.0)]);
    let order = ranked(&p);
    let b = bitmap(&p, &order, 4, 4);
    let offset = u32::from_le_bytes(b[10..14].try_into().unwrap()) as usize;
    assert_eq!(&b[offset..offset + 4], &[0, 1, 2, 3]);
    // Half as long: half the row, action 13 in colour 1; the rest is the background.
    assert_eq!(&b[offset + 4..offset + 8], &[1, 1, 12, 12]);
    assert_eq!(b.len(), offset + 8);
}

#[test]
fn base64_is_the_standard_alphabet_with_padding() {
    for (data, want) in [
        (&b""[..], ""),
        (b"f", "Zg=="),
        (b"fo", "Zm8="),
        (b"foo", "Zm9v"),
        (b"foob", "Zm9vYg=="),
        (&[0xff, 0xfe, 0x00][..], "//4A"),
    ] {
        let mut out = String::new();
        base64(data, &mut out);
        assert_eq!(out, want);
    }
}

#[test]
fn a_continuous_pool_is_drawn_as_a_sparkline_per_dimension() {
    let t = vec![Trajectory {
        actions: ActionSeq::Continuous {
            dim: 2,
            data: vec![0.0, 1.0, 0.5, -1.0, 1.0, 0.0],
        },
        score: 3.0,
        seq: 1,
    }];
    let p = Pool::restore(4, t, 1, 2).unwrap();
    let svg = pool_svg(&p);
    assert_eq!(svg.matches("<polyline").count(), 2);
    assert!(!svg.contains("image/bmp"));
}
