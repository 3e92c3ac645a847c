use super::*;

fn sample() -> Header {
    Header {
        dir_id: [7; 16],
        acked_end: 12_345,
        state: STOPPED_CLEANLY,
    }
}

#[test]
fn a_header_round_trips_and_is_as_long_as_documented() {
    let b = sample().encode();
    assert_eq!(b.len() as u64, HEADER_LEN);
    assert_eq!(decode(&b), Ok(Found::V2(sample())));
    assert!(sample().clean());
    let mut v1 = b"TAMRMLOG".to_vec();
    v1.extend_from_slice(&1u32.to_le_bytes());
    assert_eq!(decode(&v1), Ok(Found::V1));
}

#[test]
fn a_flipped_byte_or_a_cut_header_is_refused() {
    let b = sample().encode();
    for i in 0..b.len() {
        let mut d = b.clone();
        d[i] ^= 0x04;
        assert!(decode(&d).is_err(), "flip at {i}");
    }
    for cut in 0..b.len() {
        assert!(decode(&b[..cut]).is_err(), "cut at {cut}");
    }
}
