use super::*;
use crate::core::{ActionSeq, Trajectory};
use std::sync::Arc;

fn pools() -> (Pool, Pool) {
    let t = |seq, score| Trajectory {
        actions: ActionSeq::Discrete(vec![1, 2, seq as u32]),
        score,
        seq,
    };
    let base = Pool::restore(3, vec![t(1, 1.0), t(2, 2.0)], 2, 3).unwrap();
    let after = Pool::restore(3, vec![t(2, 2.0), t(3, 3.0)], 3, 4).unwrap();
    (base, after)
}

const H: usize = 12;

fn log_of(groups: &[Vec<u8>]) -> Vec<u8> {
    let mut b = vec![0u8; H];
    groups.iter().for_each(|g| b.extend_from_slice(g));
    b
}

/// The log's groups, which must all be valid.
fn valid(b: &[u8]) -> Scan {
    let s = scan(b, H);
    assert!(s.damage.is_none(), "{:?}", s.damage);
    s
}

/// Where and why the log stops being valid.
fn damage(b: &[u8]) -> Damage {
    scan(b, H).damage.expect("damage")
}

#[test]
fn records_round_trip() {
    let (base, after) = pools();
    let c = Counters {
        episodes_completed: 7,
        steps_shaped: 99,
    };
    let r = encode_commit("a/b", &base, &after, c);
    let g = encode_group(&[&r, &r]);
    let s = valid(&log_of(&[g]));
    let Record::Commit(rec) = &s.groups[0].records[1] else {
        panic!("a commit record")
    };
    assert_eq!(
        (
            rec.task.as_str(),
            rec.base_version,
            rec.version,
            rec.next_seq
        ),
        ("a/b", 2, 3, 4)
    );
    assert_eq!((rec.counters, rec.seqs.clone()), (c, vec![2, 3]));
    let t3: &Arc<Trajectory> = &after.trajectories()[1];
    assert_eq!(rec.added, vec![encode_trajectory(t3)]);
}

#[test]
fn ends_records_round_trip_beside_commits() {
    let (base, after) = pools();
    let c = encode_commit("t", &base, &after, Counters::default());
    let e = encode_ends("t", "client-1", &[(0, 3), (7, u64::MAX)]);
    let s = valid(&log_of(&[encode_group(&[&c, &e])]));
    let records = &s.groups[0].records;
    assert!(matches!(&records[0], Record::Commit(r) if r.version == 3));
    assert_eq!(
        records[1],
        Record::Ends(Ends {
            task: "t".into(),
            client: "client-1".into(),
            counts: vec![(0, 3), (7, u64::MAX)],
        })
    );
    assert_eq!(records[1].task(), "t");
    let mut unknown = e.clone();
    unknown[0] = 9;
    let d = damage(&log_of(&[encode_group(&[&unknown])]));
    assert!(
        d.undecodable && d.why.contains("unknown record kind 9"),
        "{d:?}"
    );
}

#[test]
fn a_cut_last_group_is_a_damaged_tail_and_an_earlier_bad_one_has_groups_after_it() {
    let (base, after) = pools();
    let c = encode_commit("t", &base, &after, Counters::default());
    let e = encode_ends("t", "client", &[(0, 1), (1, 2)]);
    let g = encode_group(&[&c, &e]);
    let full = log_of(&[g.clone(), g.clone()]);
    let first_end = H + g.len();
    for cut in first_end..full.len() {
        let s = scan(&full[..cut], H);
        assert_eq!(s.groups.len(), 1, "cut {cut}");
        match &s.damage {
            Some(d) => {
                assert!(cut > first_end && d.offset == first_end as u64 && d.later.is_empty())
            }
            None => assert_eq!(cut, first_end),
        }
    }
    for i in H..first_end {
        let mut b = full.clone();
        b[i] ^= 0x10;
        let d = damage(&b);
        assert_eq!((d.offset, d.later.len()), (H as u64, 1), "flip at {i}");
        assert_eq!(d.later[0].offset, first_end as u64);
    }
}

#[test]
fn counters_records_round_trip_and_truncations_fail() {
    let c = Counters {
        episodes_completed: u64::MAX - 1,
        steps_shaped: 12_345,
    };
    let r = encode_counters("a/b:c", 17, c);
    let s = valid(&log_of(&[encode_group(&[&r])]));
    assert_eq!(
        s.groups[0].records,
        vec![Record::Counters(CountersAt {
            task: "a/b:c".into(),
            version: 17,
            counters: c,
        })]
    );
    assert_eq!(s.groups[0].records[0].task(), "a/b:c");
    // A record cut short inside a valid group is corruption, not a torn tail.
    for cut in 1..r.len() {
        let d = damage(&log_of(&[encode_group(&[&r[..cut]])]));
        assert!(
            d.undecodable && d.why.contains("record 0"),
            "cut {cut}: {d:?}"
        );
    }
}
