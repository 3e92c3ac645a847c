use super::*;

#[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct F {
    format: u32,
    alpha: f64,
    seqs: Vec<u64>,
}

fn sample() -> F {
    F {
        format: 1,
        alpha: 0.1 + 0.2,
        seqs: vec![3, 8, 11],
    }
}

#[test]
fn a_sealed_file_reads_back_with_its_dir_id() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pool.json");
    std::fs::write(&p, seal(&p, &sample(), Some("ab")).unwrap()).unwrap();
    let u: Unsealed<F> = read_sealed(&p).unwrap();
    assert_eq!(
        (u.value, u.dir_id.as_deref(), u.sealed),
        (sample(), Some("ab"), true)
    );
    assert!(read_own::<F>(&p, "ab").is_ok());
    let e = read_own::<F>(&p, "cd").unwrap_err().to_string();
    assert!(
        e.contains("pool.json") && e.contains("another data dir"),
        "{e}"
    );
}

#[test]
fn every_flipped_byte_is_named_as_damage() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("task.json");
    let bytes = seal(&p, &sample(), Some("ab")).unwrap();
    for i in 0..bytes.len() {
        for bit in [0x01, 0x02, 0x10] {
            let mut b = bytes.clone();
            b[i] ^= bit;
            std::fs::write(&p, &b).unwrap();
            match read_sealed::<F>(&p) {
                Err(e) => assert!(e.to_string().contains("task.json"), "{e}"),
                // Only a flip that changes nothing read (whitespace that stays
                // whitespace, a digit past a float's precision) reads as valid.
                Ok(u) => assert!(
                    u.value == sample() && u.dir_id.as_deref() == Some("ab"),
                    "flip {bit:#x} at {i} read as valid"
                ),
            }
        }
    }
}

#[test]
fn an_unsealed_older_file_is_read_as_it_is() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pool.json");
    std::fs::write(&p, serde_json::to_vec(&sample()).unwrap()).unwrap();
    let u: Unsealed<F> = read_sealed(&p).unwrap();
    assert_eq!((u.value, u.dir_id, u.sealed), (sample(), None, false));
}

#[test]
fn dir_ids_are_random_and_round_trip_as_bytes() {
    let (a, b) = (new_dir_id().unwrap(), new_dir_id().unwrap());
    assert_ne!(a, b);
    assert_eq!(dir_id_text(&dir_id_bytes(&a).unwrap()), a);
    assert_eq!(dir_id_bytes("xyz"), None);
    assert_eq!(dir_id_bytes(&"g".repeat(32)), None);
}
