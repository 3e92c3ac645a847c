use super::*;

fn group(changed: &[bool], version: u64, resent: Option<Vec<usize>>) -> GroupCommitted {
    GroupCommitted {
        committed: Committed {
            pool: Arc::new(Pool::new(3)),
            changed: changed.to_vec(),
            version,
            resent: resent.as_ref().map_or(1, |r| r.iter().sum()),
        },
        resent,
    }
}

#[test]
fn each_request_gets_its_slice_and_its_own_version() {
    // Three requests: [change, discard], [], [change, change]; the group ends at 9.
    let done = group(&[true, false, true, true], 9, Some(vec![0, 0, 0]));
    let answers = split(&done, &[2, 0, 2], &[false; 3]);
    let got: Vec<_> = answers
        .iter()
        .map(|a| (a.changed.clone(), a.version, a.resent))
        .collect();
    assert_eq!(
        got,
        vec![
            (vec![true, false], 7, 0),
            (vec![], 7, 0),
            (vec![true, true], 9, 0)
        ]
    );
}

#[test]
fn re_sent_ends_go_to_their_request_or_to_every_marked_one() {
    let done = group(&[false, true, false], 4, Some(vec![1, 0]));
    let answers = split(&done, &[1, 2], &[true, true]);
    assert_eq!((answers[0].resent, answers[1].resent), (1, 0));
    let unknown = group(&[false, true, false], 4, None);
    let answers = split(&unknown, &[1, 1, 1], &[true, false, true]);
    let resent: Vec<_> = answers.iter().map(|a| a.resent).collect();
    assert_eq!(resent, vec![1, 0, 1]);
}

#[test]
fn pending_ends_are_released_by_request_number() {
    let mut p = Pending::default();
    let a: Arc<str> = Arc::from("a");
    p.add(1, &a, &[(0, 4), (1, 0)]);
    p.add(2, &a, &[(0, 5)]);
    assert!(p.contains("a", 0, 5) && p.contains("a", 1, 0));
    assert!(!p.contains("a", 0, 6) && !p.contains("b", 0, 0));
    p.release(1);
    assert!(p.contains("a", 0, 5), "request 2 is still pending");
    assert!(!p.contains("a", 1, 0), "request 1's other end is committed");
    p.release(2);
    assert!(!p.contains("a", 0, 0));
    assert!(p.0.is_empty());
}
