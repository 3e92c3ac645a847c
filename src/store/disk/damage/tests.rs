use super::*;
use crate::store::disk::log::{encode_counters, encode_group};
use crate::store::Counters;

const ID: [u8; 16] = [3; 16];

/// A log of three groups whose header says it ends at `acked` (`None`: after the last
/// group) in `state`; and the offsets where each group starts and the log ends.
fn log(acked: Option<usize>, state: u32) -> (Vec<u8>, Vec<u64>) {
    let groups: Vec<Vec<u8>> = (1..=3)
        .map(|v| encode_group(&[&encode_counters("t", v, Counters::default())]))
        .collect();
    let mut offsets = vec![HEADER_LEN];
    for g in &groups {
        offsets.push(offsets.last().unwrap() + g.len() as u64);
    }
    let end = acked.map_or(*offsets.last().unwrap(), |i| offsets[i]);
    let h = Header {
        dir_id: ID,
        acked_end: end,
        state,
    };
    let mut b = h.encode();
    groups.iter().for_each(|g| b.extend_from_slice(g));
    (b, offsets)
}

#[test]
fn a_whole_log_is_valid_after_a_crash_and_after_a_clean_stop() {
    for state in [header::OPEN, header::STOPPED_CLEANLY] {
        let (b, offsets) = log(None, state);
        let j = judge(&b, &ID);
        assert!(j.refusal.is_none() && j.torn.is_none(), "{j:?}");
        assert_eq!((j.valid_end, j.scan.groups.len()), (offsets[3], 3));
    }
}

#[test]
fn a_log_cut_inside_its_acknowledged_part_is_refused_naming_the_offset() {
    for state in [header::OPEN, header::STOPPED_CLEANLY] {
        let (b, offsets) = log(None, state);
        for cut in offsets[0] as usize..b.len() {
            let j = judge(&b[..cut], &ID);
            let why = j.refusal.unwrap_or_else(|| panic!("cut at {cut} accepted"));
            let at = offsets.iter().rev().find(|&&o| o <= cut as u64).unwrap();
            assert!(why.contains(&format!("offset {at}")), "cut at {cut}: {why}");
            assert!(
                why.contains(&format!("ends at offset {}", offsets[3])),
                "{why}"
            );
        }
    }
}

#[test]
fn after_a_crash_a_torn_group_past_the_acknowledged_end_is_cut() {
    let (b, offsets) = log(Some(2), header::OPEN);
    for cut in offsets[2] as usize + 1..b.len() {
        let j = judge(&b[..cut], &ID);
        assert!(j.refusal.is_none(), "cut at {cut}: {:?}", j.refusal);
        let (at, _, why) = j.torn.expect("a torn tail");
        assert_eq!((at, j.valid_end), (offsets[2], offsets[2]));
        assert!(why.contains("never acknowledged"), "{why}");
    }
}

#[test]
fn after_a_clean_stop_anything_past_its_end_is_refused() {
    let (b, offsets) = log(Some(2), header::STOPPED_CLEANLY);
    for cut in offsets[2] as usize + 1..=b.len() {
        let why = judge(&b[..cut], &ID).refusal.expect("refused");
        assert!(why.contains("after a clean stop"), "{why}");
    }
}

#[test]
fn a_flipped_byte_in_a_middle_group_is_refused_and_later_versions_are_named() {
    let (b, offsets) = log(None, header::OPEN);
    let mut d = b.clone();
    d[offsets[1] as usize + 5] ^= 1;
    let j = judge(&d, &ID);
    let why = j.refusal.expect("refused");
    assert!(why.contains(&format!("offset {}", offsets[1])), "{why}");
    assert_eq!(j.valid_end, offsets[1]);
    assert_eq!(j.scan.damage.as_ref().unwrap().later.len(), 1);
}

#[test]
fn another_data_dirs_log_is_refused_and_contributes_nothing() {
    let (b, _) = log(None, header::OPEN);
    let j = judge(&b, &[4; 16]);
    assert!(j.refusal.unwrap().contains("another data dir"));
    assert!(j.scan.groups.is_empty());
    assert_eq!(j.valid_end, 0);
}

#[test]
fn a_format_3_log_keeps_todays_torn_tail_rule() {
    let (b, offsets) = log(None, header::OPEN);
    let mut v1 = b"TAMRMLOG".to_vec();
    v1.extend_from_slice(&1u32.to_le_bytes());
    v1.extend_from_slice(&b[HEADER_LEN as usize..b.len() - 3]);
    let j = judge(&v1, &ID);
    assert!(j.v1 && j.refusal.is_none());
    let cut = offsets[2] - HEADER_LEN + header::HEADER_V1_LEN;
    assert_eq!(j.torn.as_ref().map(|t| t.0), Some(cut));
    assert!(j.torn.unwrap().2.contains("format-3 log"));
}
