use super::*;

#[test]
fn counts_only_grow_and_clients_are_separate() {
    let mut t = EndedEpisodes::default();
    t.merge("a", [(0, 3), (2, 1)]);
    t.merge("a", [(0, 2), (2, 4)]);
    t.merge("b", [(0, 1)]);
    assert_eq!(t.counts("a"), vec![(0, 3), (2, 4)]);
    assert!(t.contains("a", 0, 2) && !t.contains("a", 0, 3));
    assert!(t.contains("b", 0, 0) && !t.contains("b", 1, 0) && !t.contains("c", 0, 0));
    let all: Vec<_> = t.all().map(|(c, v)| (c.to_string(), v)).collect();
    assert_eq!(all[1], ("b".to_string(), vec![(0, 1)]));
}

#[test]
fn the_client_that_committed_least_recently_is_forgotten_first() {
    let mut t = EndedEpisodes::default();
    for i in 0..MAX_REMEMBERED_CLIENTS {
        t.merge(&i.to_string(), [(0, 1)]);
    }
    // Client 0 commits again: client 1 is now the least recent.
    t.merge("0", [(0, 2)]);
    t.merge("new", [(0, 1)]);
    assert!(t.contains("0", 0, 1), "a client that commits is remembered");
    assert!(!t.contains("1", 0, 0));
    assert!(t.contains("2", 0, 0) && t.contains("new", 0, 0));
    assert_eq!(t.by_client.len(), MAX_REMEMBERED_CLIENTS);
    assert!(t.order.len() <= 2 * t.by_client.len() + 64);
    // The order survives a rebuild from `all` (a restart from ends.json).
    let mut again = EndedEpisodes::default();
    for (c, counts) in t.all() {
        again.merge(c, counts);
    }
    again.merge("newer", [(0, 1)]);
    assert!(!again.contains("2", 0, 0) && again.contains("3", 0, 0));
    assert!(again.contains("0", 0, 1));
}

#[test]
fn counts_are_bounded_whatever_the_env_counts() {
    let mut t = EndedEpisodes::default();
    let envs = 4096;
    let clients = MAX_REMEMBERED_ENDS / envs as usize;
    for c in 0..clients {
        t.merge(&c.to_string(), (0..envs).map(|e| (e, 1)));
    }
    assert_eq!(t.entries, MAX_REMEMBERED_ENDS);
    assert!(t.contains("0", envs - 1, 0));
    // One more env of a known client passes the bound: the least recent other one goes.
    t.merge("5", [(envs, 1)]);
    assert!(!t.contains("0", 0, 0));
    assert!(t.contains("5", envs, 0) && t.contains("1", 0, 0));
    assert_eq!(t.entries, MAX_REMEMBERED_ENDS + 1 - envs as usize);
    // A client alone past the bound is kept (nothing else to forget).
    let mut one = EndedEpisodes::default();
    one.merge("big", (0..MAX_REMEMBERED_ENDS as u32 + 1).map(|e| (e, 1)));
    assert!(one.contains("big", 0, 0));
}
