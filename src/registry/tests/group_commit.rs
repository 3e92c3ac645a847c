//! Group commit within one task: the changes planned while a commit is in flight are
//! committed together, and decide exactly what committing them one by one would have
//! (a property test over random pools, requesters and operations); a failure fails every
//! change planned on top of it; a cancelled leader still commits; the record of ends in
//! flight keeps a re-sent end from being offered twice.

use std::sync::atomic::Ordering;

use proptest::prelude::*;

use super::*;
use crate::core::ActionSeq;
use crate::store::testing::TestStore;
use crate::store::{apply_ops, Committed, EndMark, PoolOp};

async fn held_task(capacity: u32) -> (Arc<TestStore>, Registry, Arc<TaskHandle>) {
    let store = TestStore::new(false);
    let r = Registry::open(store.clone(), Limits::default())
        .await
        .unwrap()
        .0;
    let t = r
        .create(DEFAULT_TENANT, "t", &discrete(3, capacity), None)
        .await
        .unwrap();
    (store, r, t)
}

fn offer(a: u32, score: f64) -> PoolOp {
    PoolOp::Offer {
        actions: acts(&[a, a]),
        score,
        end: None,
    }
}

/// A pool's whole content, scores as bits.
type PoolState = (u64, u64, Vec<(u64, u64, ActionSeq)>);

fn state(p: &Pool) -> PoolState {
    let trajs = p
        .trajectories()
        .iter()
        .map(|t| (t.seq, t.score.to_bits(), t.actions.clone()))
        .collect();
    (p.version(), p.next_seq(), trajs)
}

/// Plans and commits `ops` on `t` in a task of its own (its writer lock taken before it
/// returns, so requests are planned in the order they are spawned).
async fn spawn_commit(
    t: &Arc<TaskHandle>,
    ops: Vec<PoolOp>,
) -> tokio::task::JoinHandle<Result<Committed, Error>> {
    let w = t.writer().await.unwrap();
    let t = t.clone();
    tokio::spawn(async move { t.commit(w, ops).await })
}

/// [`spawn_commit`] for the episode ends `marks` of client "c".
async fn spawn_ends(
    t: &Arc<TaskHandle>,
    ops: Vec<PoolOp>,
    marks: Vec<(u32, u64)>,
) -> tokio::task::JoinHandle<Result<Committed, Error>> {
    let w = t.writer().await.unwrap();
    let t = t.clone();
    tokio::spawn(async move { t.commit_ends(w, ops, Some(("c", &marks))).await })
}

/// Yields until `n` requests are queued behind the group in flight (panics after 10 s).
async fn queued(t: &TaskHandle, n: usize) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while t.queued() < n {
        assert!(
            std::time::Instant::now() < deadline,
            "{n} requests never queued"
        );
        tokio::task::yield_now().await;
    }
}

#[tokio::test]
async fn changes_queued_behind_a_commit_are_committed_together() {
    let (store, _r, t) = held_task(2).await;
    store.hold();
    let first = spawn_commit(&t, vec![offer(0, 1.0)]).await;
    store.started(1).await;
    // Planned against the pool with the first change, before it is acknowledged.
    let w = t.writer().await.unwrap();
    assert_eq!(
        w.base().version(),
        1,
        "the planned pool holds the change in flight"
    );
    assert_eq!(
        t.published_version(),
        0,
        "nothing is published before the store acks"
    );
    drop(w);
    let mut later = Vec::new();
    for (a, score) in [(1, 2.0), (2, 0.5), (1, 3.0)] {
        later.push(spawn_commit(&t, vec![offer(a, score)]).await);
    }
    let empty = spawn_commit(&t, Vec::new()).await;
    queued(&t, 4).await;
    store.release();
    let c = first.await.unwrap().unwrap();
    assert_eq!((c.changed, c.version), (vec![true], 1));
    let got: Vec<_> = futures::future::join_all(later)
        .await
        .into_iter()
        .map(|j| {
            let c = j.unwrap().unwrap();
            (c.changed, c.version, c.pool.version())
        })
        .collect();
    // Full at 2: 2.0 inserts, 0.5 is discarded, 3.0 replaces 1.0; one version per change.
    assert_eq!(
        got,
        vec![(vec![true], 2, 3), (vec![false], 2, 3), (vec![true], 3, 3)]
    );
    let e = empty.await.unwrap().unwrap();
    assert_eq!((e.version, e.pool.version()), (3, 3));
    assert_eq!(
        store.commits.load(Ordering::SeqCst),
        2,
        "the four queued requests made one commit"
    );
    let pool = t.snapshot();
    assert_eq!(pool.version(), 3);
    assert_eq!(pool.seqs(), &[2, 3]);
    // Idle again: the next writer plans against the published pool itself.
    let w = t.writer().await.unwrap();
    assert!(Arc::ptr_eq(w.base(), &pool));
}

#[tokio::test]
async fn the_planned_pool_keeps_only_what_is_not_committed_yet() {
    let (store, _r, t) = held_task(8).await;
    assert_eq!(
        t.planned_parts(),
        None,
        "idle: the published pool is the planned one"
    );
    store.hold();
    let a = spawn_commit(&t, vec![offer(0, 1.0)]).await;
    store.started(1).await;
    assert_eq!(t.planned_parts(), Some((0, vec![1])));
    // Two writers that only queue (no base asked for): their operations wait in the tail.
    let b = spawn_commit(&t, vec![offer(1, 2.0)]).await;
    let c = spawn_commit(&t, vec![offer(2, 3.0)]).await;
    queued(&t, 2).await;
    assert_eq!(t.planned_parts(), Some((0, vec![1, 2, 3])));
    // The first group commits; the second is held in the store.
    store.release();
    store.hold();
    store.started(2).await;
    assert_eq!(
        t.planned_parts(),
        Some((1, vec![2, 3])),
        "based on the committed pool, the committed request out of the tail"
    );
    // A writer that looks applies the tail once and keeps it as the base.
    let w = t.writer().await.unwrap();
    assert_eq!((w.base().version(), w.base().len()), (3, 3));
    assert_eq!(t.planned_parts(), Some((3, vec![])));
    drop(w);
    store.release();
    for j in [a, b, c] {
        j.await.unwrap().unwrap();
    }
    assert_eq!(t.planned_parts(), None);
    assert_eq!(t.published_version(), 3);
}

#[tokio::test]
async fn a_failed_group_fails_every_change_planned_on_top_of_it() {
    let (store, _r, t) = held_task(3).await;
    t.offer(acts(&[0]), 1.0).await.unwrap();
    store.hold();
    let a = spawn_commit(&t, vec![offer(1, 2.0)]).await;
    store.started(2).await;
    let b = spawn_commit(&t, vec![offer(2, 3.0)]).await;
    queued(&t, 1).await;
    // A writer holding the lock while the group fails: its base assumed both changes.
    let w = t.writer().await.unwrap();
    assert_eq!(w.base().version(), 3);
    store.fail.store(true, Ordering::SeqCst);
    store.release();
    assert!(matches!(a.await.unwrap(), Err(Error::Storage(_))));
    assert!(matches!(b.await.unwrap(), Err(Error::Storage(_))));
    store.fail.store(false, Ordering::SeqCst);
    assert!(matches!(
        t.commit(w, vec![offer(0, 9.0)]).await,
        Err(Error::Storage(_))
    ));
    assert_eq!(t.published_version(), 1, "nothing published");
    // Planning starts again from the published pool, and commits.
    let w = t.writer().await.unwrap();
    assert_eq!(w.base().version(), 1);
    let c = t.commit(w, vec![offer(2, 3.0)]).await.unwrap();
    assert_eq!((c.changed, c.version), (vec![true], 2));
    assert_eq!(t.snapshot().seqs(), &[1, 2]);
}

#[tokio::test]
async fn a_cancelled_leader_still_commits_and_answers_the_changes_behind_it() {
    let (store, _r, t) = held_task(3).await;
    store.hold();
    let leader = spawn_commit(&t, vec![offer(0, 1.0)]).await;
    store.started(1).await;
    let behind = spawn_commit(&t, vec![offer(1, 2.0)]).await;
    queued(&t, 1).await;
    // The leader's caller goes away (a cancelled AddTrajectory) mid-commit.
    leader.abort();
    assert!(leader.await.unwrap_err().is_cancelled());
    store.release();
    let c = behind.await.unwrap().unwrap();
    assert_eq!((c.changed, c.version), (vec![true], 2));
    assert_eq!(t.snapshot().seqs(), &[1, 2], "the leader's change stands");
    assert_eq!(t.offer(acts(&[2]), 3.0).await.unwrap(), (true, 3));
}

#[tokio::test]
async fn deletion_waits_for_the_group_in_flight() {
    let (store, r, t) = held_task(3).await;
    store.hold();
    let a = spawn_commit(&t, vec![offer(0, 1.0)]).await;
    store.started(1).await;
    let r = Arc::new(r);
    let deleting = {
        let r = r.clone();
        tokio::spawn(async move { r.delete(DEFAULT_TENANT, "t").await })
    };
    for _ in 0..50 {
        tokio::task::yield_now().await;
    }
    assert!(
        t.check_live().is_ok(),
        "not deleted under a commit in flight"
    );
    store.release();
    assert_eq!(a.await.unwrap().unwrap().version, 1);
    deleting.await.unwrap().unwrap();
    assert!(t.check_live().is_err());
    assert!(matches!(t.writer().await, Err(Error::TaskNotFound { .. })));
}

#[tokio::test]
async fn ends_in_flight_count_as_ended_until_their_group_fails() {
    let (store, _r, t) = held_task(3).await;
    let client: Arc<str> = Arc::from("c");
    let end = |env, episode, score| PoolOp::Offer {
        actions: acts(&[0]),
        score,
        end: Some(EndMark {
            client: client.clone(),
            env,
            episode,
        }),
    };
    let commit_ends = |ops, marks| spawn_ends(&t, ops, marks);
    store.hold();
    let a = commit_ends(vec![end(0, 0, 1.0)], vec![(0, 0)]).await;
    store.started(1).await;
    assert!(
        t.already_ended("c", 0, 0),
        "in flight: not to be offered again"
    );
    assert!(!t.already_ended("c", 0, 1) && !t.already_ended("d", 0, 0));
    // The same client's next end, queued behind it (a second stream of the client).
    let b = commit_ends(vec![end(0, 1, 2.0)], vec![(0, 1)]).await;
    queued(&t, 1).await;
    assert!(t.already_ended("c", 0, 1));
    store.release();
    a.await.unwrap().unwrap();
    b.await.unwrap().unwrap();
    assert!(t.already_ended("c", 0, 1), "committed now");
    assert_eq!(t.ended_counts("c"), vec![(0, 2)]);
    // A failed group's ends are not ended.
    store.hold();
    let c = commit_ends(vec![end(1, 0, 3.0)], vec![(1, 0)]).await;
    store.started(3).await;
    assert!(t.already_ended("c", 1, 0));
    store.fail.store(true, Ordering::SeqCst);
    store.release();
    assert!(c.await.unwrap().is_err());
    assert!(!t.already_ended("c", 1, 0));
}

/// One operation of a random request.
#[derive(Debug, Clone)]
enum OpSpec {
    /// An offer: the length and first action of its actions, and a score from a small
    /// set (ties are common).
    Offer(usize, u32, u8),
    Reset,
}

fn op_spec() -> impl Strategy<Value = OpSpec> {
    prop_oneof![
        12 => (1usize..4, 0u32..3, 0u8..4).prop_map(|(l, a, s)| OpSpec::Offer(l, a, s)),
        1 => Just(OpSpec::Reset),
    ]
}

/// A random request: which requester plans it, and its operations (maybe none: a batch
/// whose only end was re-sent still waits for the changes under its base). Requesters 0
/// and 1 look at the base they plan against, 2 and 3 do not.
fn request() -> impl Strategy<Value = (usize, Vec<OpSpec>)> {
    (0usize..4, proptest::collection::vec(op_spec(), 0..4))
}

/// The operations of request `i` of `requester`; offers of requester 0 and 1 are episode
/// ends of named clients.
fn ops_of(requester: usize, i: usize, spec: &[OpSpec]) -> Vec<PoolOp> {
    spec.iter()
        .enumerate()
        .map(|(j, op)| match *op {
            OpSpec::Offer(len, a, score) => PoolOp::Offer {
                actions: ActionSeq::Discrete((0..len as u32).map(|k| (a + k) % 3).collect()),
                score: f64::from(score),
                end: (requester < 2).then(|| EndMark {
                    client: Arc::from(format!("c{requester}")),
                    env: j as u32,
                    episode: i as u64,
                }),
            },
            OpSpec::Reset => PoolOp::Reset,
        })
        .collect()
}

fn marks_of(ops: &[PoolOp]) -> Vec<(u32, u64)> {
    ops.iter()
        .filter_map(|op| match op {
            PoolOp::Offer { end: Some(m), .. } => Some((m.env, m.episode)),
            _ => None,
        })
        .collect()
}

/// Runs `requests` from concurrent requesters against a task seeded with `seed`, on a
/// store that yields `yields` times per commit (so that changes queue up behind it), and
/// checks every answer and the final pool against planning the requests one by one in
/// the order they were planned.
async fn grouped_equals_sequential(
    capacity: u32,
    seed: Vec<(usize, u32, u8)>,
    requests: Vec<(usize, Vec<OpSpec>)>,
    yields: usize,
) -> Result<(), TestCaseError> {
    let (store, _r, t) = held_task(capacity).await;
    for (len, a, score) in seed {
        let actions = (0..len as u32).map(|k| (a + k) % 3).collect::<Vec<_>>();
        t.offer(acts(&actions), f64::from(score)).await.unwrap();
    }
    let seeded = t.snapshot();
    store.yields.store(yields, Ordering::SeqCst);
    let commits_before = store.commits.load(Ordering::SeqCst);
    // Per requester, its requests in order: (index in `requests`, ops).
    let mut by_requester: Vec<Vec<(usize, Vec<PoolOp>)>> = vec![Vec::new(); 4];
    for (i, (who, spec)) in requests.iter().enumerate() {
        let n = by_requester[*who].len();
        by_requester[*who].push((i, ops_of(*who, n, spec)));
    }
    // (request index, the base it was planned against if it looked), in planning order.
    let planned = Arc::new(parking_lot::Mutex::new(Vec::new()));
    let mut joins = Vec::new();
    for (who, mine) in by_requester.into_iter().enumerate() {
        let (t, planned) = (t.clone(), planned.clone());
        joins.push(tokio::spawn(async move {
            let client = format!("c{who}");
            let mut answers = Vec::new();
            for (i, ops) in mine {
                let w = t.writer().await.unwrap();
                // Requesters 0 and 1 plan against the base (as a Shape stream's batch
                // does); 2 and 3 only queue operations (Follow ends, AddTrajectory).
                let base = (who < 2).then(|| w.base().clone());
                planned.lock().push((i, base));
                let marks = marks_of(&ops);
                let marks = (!marks.is_empty()).then_some((client.as_str(), marks.as_slice()));
                answers.push((i, t.commit_ends(w, ops, marks).await.unwrap()));
                tokio::task::yield_now().await;
            }
            answers
        }));
    }
    let mut answers = std::collections::HashMap::new();
    for j in joins {
        answers.extend(j.await.unwrap());
    }
    let order = std::mem::take(&mut *planned.lock());
    // The same requests, one by one, in planning order.
    let mut pool = (*seeded).clone();
    let mut per_requester = [0usize; 4];
    let mut ops_by_index = vec![Vec::new(); requests.len()];
    for (i, (who, spec)) in requests.iter().enumerate() {
        ops_by_index[i] = ops_of(*who, per_requester[*who], spec);
        per_requester[*who] += 1;
    }
    for (i, base) in order {
        if let Some(base) = base {
            prop_assert_eq!(state(&base), state(&pool), "request {} planned against", i);
        }
        let (next, changed) = apply_ops(&pool, ops_by_index[i].clone());
        let got = &answers[&i];
        prop_assert_eq!(&got.changed, &changed, "request {}: changed", i);
        prop_assert_eq!(got.version, next.version(), "request {}: version", i);
        prop_assert!(got.pool.version() >= next.version());
        pool = next;
    }
    prop_assert_eq!(state(&t.snapshot()), state(&pool), "the final pool");
    let commits = store.commits.load(Ordering::SeqCst) - commits_before;
    let with_ops = requests.iter().filter(|(_, s)| !s.is_empty()).count();
    prop_assert!(
        commits <= with_ops,
        "{} commits for {} requests",
        commits,
        with_ops
    );
    // Idle again: the next writer plans against the published pool.
    let w = t.writer().await.unwrap();
    prop_assert!(Arc::ptr_eq(w.base(), &t.snapshot()));
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn grouped_planning_equals_sequential_planning(
        capacity in 1u32..5,
        seed in proptest::collection::vec((1usize..4, 0u32..3, 0u8..4), 0..7),
        requests in proptest::collection::vec(request(), 1..16),
        yields in 0usize..4,
    ) {
        // One thread: the interleaving is decided by the yields alone, so a failure
        // replays exactly.
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        rt.block_on(grouped_equals_sequential(capacity, seed, requests, yields))?;
    }
}
