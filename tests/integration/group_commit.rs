//! The disk store's commit log and group commit, on real files: acknowledged commits
//! survive a crash (the store dropped without any flush; a real server killed with
//! SIGKILL), a torn last group (never acknowledged) is dropped at every byte offset, an
//! acknowledged one cut short and an earlier corrupt one are reported, concurrent commits lose nothing, compaction and migration keep everything;
//! and the ends that streams on ONE task send at the same moment share syncs (Shape
//! streams on the real binary, killed with SIGKILL after; Follow streams in process).

use std::path::Path;
use std::sync::Arc;

use crate::common::*;
use tamrm::core::{ActionSeq, Pool, TaskConfig, TaskConfigInput};
use tamrm::store::{Counters, DiskStore, PoolOp, Store, StoreError, StoredTask};

const LOG: &str = "commits.log";
const LOG_HEADER: u64 = 44;

fn config(capacity: u32) -> TaskConfig {
    TaskConfig::resolve(&TaskConfigInput {
        num_actions: 5,
        pool_capacity: Some(capacity),
        ..Default::default()
    })
    .unwrap()
}

fn offer(actions: &[u32], score: f64) -> PoolOp {
    PoolOp::Offer {
        actions: ActionSeq::Discrete(actions.to_vec()),
        score,
        end: None,
    }
}

fn counters(n: u64) -> Counters {
    Counters {
        episodes_completed: n,
        steps_shaped: 10 * n,
    }
}

async fn open(dir: &Path) -> (DiskStore, Vec<StoredTask>) {
    let s = DiskStore::open(dir).unwrap();
    let tasks = s.load().await.unwrap();
    (s, tasks)
}

/// A pool's full content, floats as bits, for exact comparisons.
type PoolState = (u64, u64, Vec<(u64, u64, Vec<u32>)>);

fn state(p: &Pool) -> PoolState {
    let trajs = p
        .trajectories()
        .iter()
        .map(|t| {
            let acts = match &t.actions {
                ActionSeq::Discrete(v) => v.clone(),
                ActionSeq::Continuous { data, .. } => data.iter().map(|x| x.to_bits()).collect(),
            };
            (t.seq, t.score.to_bits(), acts)
        })
        .collect();
    (p.version(), p.next_seq(), trajs)
}

fn states(tasks: &[StoredTask]) -> Vec<(String, PoolState, Counters)> {
    let mut v: Vec<_> = tasks
        .iter()
        .map(|t| (t.id.clone(), state(&t.pool), t.counters))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

/// Copies a data dir (a crashed server's: the copy is what a restart would find). In
/// process, not with `cp`: a child process forked while a store is open shares its
/// LOCK until it execs, which would make a parallel test's reopen fail.
fn copy_dir(src: &Path, dst: &Path) {
    let mut todo = vec![(src.to_path_buf(), dst.to_path_buf())];
    while let Some((from, to)) = todo.pop() {
        std::fs::create_dir_all(&to).unwrap();
        for e in std::fs::read_dir(&from).unwrap().map(Result::unwrap) {
            let target = to.join(e.file_name());
            if e.file_type().unwrap().is_dir() {
                todo.push((e.path(), target));
            } else {
                std::fs::copy(e.path(), target).unwrap();
            }
        }
    }
}

/// Rewrites the log header's acknowledged end (bytes 28..36, then the CRC-32 of the 40
/// bytes before 40..44; docs/storage.md): as if the server had died after writing the
/// groups past `end` but before acknowledging them.
pub(crate) fn set_acked_end(log: &Path, end: u64) {
    let mut b = std::fs::read(log).unwrap();
    b[28..36].copy_from_slice(&end.to_le_bytes());
    let crc = crc32fast::hash(&b[..40]);
    b[40..44].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(log, b).unwrap();
}

/// A copy of the data dir `dir` whose log is cut to `len` bytes.
fn copy_with_log_cut(dir: &Path, len: u64) -> tempfile::TempDir {
    let copy = tempfile::tempdir().unwrap();
    copy_dir(dir, copy.path());
    std::fs::OpenOptions::new()
        .write(true)
        .open(copy.path().join(LOG))
        .unwrap()
        .set_len(len)
        .unwrap();
    copy
}

fn log_len(dir: &Path) -> u64 {
    std::fs::metadata(dir.join(LOG)).unwrap().len()
}

/// Commits `ops` against `pool`, returning the new pool.
async fn commit(s: &DiskStore, id: &str, pool: &Arc<Pool>, ops: Vec<PoolOp>, n: u64) -> Arc<Pool> {
    s.commit(id, pool.clone(), ops, counters(n))
        .await
        .unwrap()
        .pool
}

/// A store with tasks "a" (capacity 2, with a replacement and a reset) and "b", every
/// change acknowledged; returns the expected state.
async fn populate(s: &DiskStore) -> Vec<(String, PoolState, Counters)> {
    s.create_task("a", &config(2)).await.unwrap();
    s.create_task("b/x", &config(3)).await.unwrap();
    let mut a = Arc::new(Pool::new(2));
    let mut b = Arc::new(Pool::new(3));
    a = commit(s, "a", &a, vec![offer(&[0, 1], 1.0), offer(&[2], -0.0)], 1).await;
    b = commit(s, "b/x", &b, vec![offer(&[4, 4, 4], f64::MIN_POSITIVE)], 2).await;
    a = commit(s, "a", &a, vec![offer(&[3, 3], 5.0)], 3).await; // replaces -0.0
    a = commit(s, "a", &a, vec![PoolOp::Reset], 4).await;
    a = commit(s, "a", &a, vec![offer(&[1], 0.1 + 0.2)], 5).await;
    b = commit(s, "b/x", &b, vec![offer(&[0], 1e300)], 6).await;
    assert_eq!((a.version(), b.version()), (5, 2));
    let mut v = vec![
        ("a".to_string(), state(&a), counters(5)),
        ("b/x".to_string(), state(&b), counters(6)),
    ];
    v.sort_by(|x, y| x.0.cmp(&y.0));
    v
}

#[tokio::test]
async fn acknowledged_commits_survive_dropping_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    let expected = populate(&s).await;
    assert!(
        log_len(dir.path()) > LOG_HEADER,
        "the changes are in the log"
    );
    // A crash: no save_counters, no flush; the writer thread stops with the store.
    drop(s);
    let (s, tasks) = open(dir.path()).await;
    assert_eq!(states(&tasks), expected);
    assert!(
        log_len(dir.path()) > LOG_HEADER,
        "a start keeps the log (it writes no snapshot)"
    );
    // Seqs and versions go on.
    let a = tasks.iter().find(|t| t.id == "a").unwrap().pool.clone();
    let a2 = commit(&s, "a", &Arc::new(a), vec![offer(&[2, 2], 9.0)], 7).await;
    assert_eq!((a2.version(), a2.seqs()), (6, &[4, 5][..]));
    drop(s);
    let (_, tasks) = open(dir.path()).await;
    let a = tasks.iter().find(|t| t.id == "a").unwrap();
    assert_eq!(state(&a.pool), state(&a2));
}

#[tokio::test]
async fn one_sync_per_change_with_one_stream() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    s.create_task("t", &config(100)).await.unwrap();
    let mut pool = Arc::new(Pool::new(100));
    let before = s.commit_stats();
    for i in 0..20u32 {
        let next = commit(&s, "t", &pool, vec![offer(&[i % 5], f64::from(i))], 0).await;
        assert_eq!(next.version(), pool.version() + 1);
        pool = next;
    }
    // A commit that changes nothing costs nothing.
    let stale = s
        .commit("t", pool.clone(), vec![offer(&[1], -1.0)], counters(0))
        .await;
    assert_eq!(stale.unwrap().changed, vec![true], "not full yet");
    let after = s.commit_stats();
    assert_eq!(after.changes - before.changes, 21);
    assert_eq!(after.syncs - before.syncs, 21, "one fdatasync per change");
    assert_eq!(after.groups - before.groups, 21);
    assert_eq!(s.sync_count(), after.syncs);
}

#[tokio::test]
async fn a_stale_base_is_a_conflict_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    s.create_task("t", &config(3)).await.unwrap();
    let base = Arc::new(Pool::new(3));
    let p1 = commit(&s, "t", &base, vec![offer(&[1], 1.0)], 1).await;
    let e = s
        .commit("t", base, vec![offer(&[2], 2.0)], counters(2))
        .await
        .unwrap_err();
    assert!(
        matches!(
            e,
            StoreError::Conflict {
                expected: 0,
                found: 1,
                ..
            }
        ),
        "{e}"
    );
    drop(s);
    let (_, tasks) = open(dir.path()).await;
    assert_eq!(state(&tasks[0].pool), state(&p1));
    assert_eq!(tasks[0].counters, counters(1));
}

/// Eight tasks committing at once, each 40 changes: nothing lost, versions one per
/// change, and the syncs shared (never more syncs than changes).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_commits_lose_nothing_and_share_syncs() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    let (tasks, per_task) = (8usize, 40u32);
    for i in 0..tasks {
        s.create_task(&format!("t{i}"), &config(per_task))
            .await
            .unwrap();
    }
    let before = s.commit_stats();
    let mut joins = Vec::new();
    for i in 0..tasks {
        let s = s.clone();
        joins.push(tokio::spawn(async move {
            let id = format!("t{i}");
            let mut pool = Arc::new(Pool::new(per_task as usize));
            for j in 0..per_task {
                let ops = vec![offer(&[j % 5, i as u32 % 5], f64::from(j))];
                let next = commit(&s, &id, &pool, ops, u64::from(j) + 1).await;
                assert_eq!(
                    next.version(),
                    pool.version() + 1,
                    "{id}: one version per change"
                );
                pool = next;
            }
            state(&pool)
        }));
    }
    let mut expected = Vec::new();
    for (i, j) in joins.into_iter().enumerate() {
        expected.push((
            format!("t{i}"),
            j.await.unwrap(),
            counters(u64::from(per_task)),
        ));
    }
    let after = s.commit_stats();
    let changes = after.changes - before.changes;
    let syncs = after.syncs - before.syncs;
    assert_eq!(changes, tasks as u64 * u64::from(per_task));
    assert!(syncs <= changes, "{syncs} syncs for {changes} changes");
    eprintln!(
        "{changes} changes from {tasks} concurrent tasks: {} groups, {syncs} syncs ({:.2} per change)",
        after.groups - before.groups,
        syncs as f64 / changes as f64
    );
    drop(s);
    let (_, restored) = open(dir.path()).await;
    assert_eq!(states(&restored), expected);
    for (_, (version, _, trajs), _) in &expected {
        assert_eq!(*version, u64::from(per_task));
        assert_eq!(trajs.len(), per_task as usize);
    }
}

/// A crashed data dir whose log holds `populate`'s changes and then one more (a
/// trajectory into "b/x"), with the log offsets before and after that last group and
/// the states before and after it.
async fn crashed_with_a_last_group() -> (
    tempfile::TempDir,
    (u64, u64),
    Vec<(String, PoolState, Counters)>,
    Vec<(String, PoolState, Counters)>,
) {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    let before = populate(&s).await;
    let start = log_len(dir.path());
    // "b/x" as populate left it: version 2, seqs 1 and 2.
    let mut b = Pool::new(3);
    for (acts, score) in [(&[4u32, 4, 4][..], f64::MIN_POSITIVE), (&[0], 1e300)] {
        b = tamrm::store::apply_ops(&b, vec![offer(acts, score)]).0;
    }
    let b = commit(&s, "b/x", &Arc::new(b), vec![offer(&[1, 2, 3, 4], -7.5)], 7).await;
    let end = log_len(dir.path());
    drop(s);
    let mut after = before.clone();
    after[1] = ("b/x".to_string(), state(&b), counters(7));
    assert_ne!(before, after);
    (dir, (start, end), before, after)
}

/// The last group written but not acknowledged (the header's acknowledged end before
/// it), then the log cut at every byte offset of that group: reopening gives exactly the
/// state before that group (the full length: after it), never an error, never half of
/// it; the torn part is cut off, so changes after it are kept.
#[tokio::test]
async fn a_torn_last_group_is_dropped_at_every_offset() {
    let (dir, (start, end), before, after) = crashed_with_a_last_group().await;
    assert!(end - start > 60, "a group of {} bytes", end - start);
    set_acked_end(&dir.path().join(LOG), start);
    for cut in start..=end {
        let copy = copy_with_log_cut(dir.path(), cut);
        let s = DiskStore::open(copy.path()).unwrap();
        let tasks = s
            .load()
            .await
            .unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        let want = if cut == end { &after } else { &before };
        assert_eq!(&states(&tasks), want, "cut at {cut} of {start}..={end}");
        let kept = if cut == end { end } else { start };
        assert_eq!(
            log_len(copy.path()),
            kept,
            "the torn tail is cut off, the rest kept"
        );
        // A change appended after the cut is restored with the rest (appended after a
        // torn tail left in place, it would make the log corrupt).
        let a = tasks.iter().find(|t| t.id == "a").unwrap().pool.clone();
        let a2 = commit(&s, "a", &Arc::new(a), vec![offer(&[4], 2.5)], 9).await;
        drop(s);
        let (_, again) = open(copy.path()).await;
        let mut want = want.clone();
        want[0] = ("a".to_string(), state(&a2), counters(9));
        assert_eq!(states(&again), want, "cut at {cut}");
    }
}

/// The acknowledged last group cut at every byte offset (a crash cannot do that: its
/// acknowledgement came after its sync): load refuses, naming the log, the offset where
/// the valid part ends and the version each task can be restored at; the log is left as
/// found.
#[tokio::test]
async fn an_acknowledged_last_group_cut_short_is_refused_at_every_offset() {
    let (dir, (start, end), _, _) = crashed_with_a_last_group().await;
    for cut in start..end {
        let copy = copy_with_log_cut(dir.path(), cut);
        let log = copy.path().join(LOG);
        let s = DiskStore::open(copy.path()).unwrap();
        let e = s
            .load()
            .await
            .expect_err("a cut acknowledged group")
            .to_string();
        assert!(e.contains(log.to_str().unwrap()), "cut at {cut}: {e}");
        assert!(e.contains(&format!("offset {start}")), "cut at {cut}: {e}");
        assert!(e.contains(&format!("ends at offset {end}")), "{e}");
        assert!(e.contains("\"b/x\" at version 2"), "cut at {cut}: {e}");
        drop(s);
        assert_eq!(log_len(copy.path()), cut, "a refused log is left as found");
    }
}

/// A flipped byte anywhere in a group that is not the last one is corruption: load
/// fails naming the log file.
#[tokio::test]
async fn a_flipped_byte_in_an_earlier_group_is_reported() {
    let (dir, (start, _), _, _) = crashed_with_a_last_group().await;
    let bytes = std::fs::read(dir.path().join(LOG)).unwrap();
    // The first group: from the header to the second group's magic.
    let h = LOG_HEADER as usize;
    let second = h
        + 4
        + bytes[h + 4..]
            .windows(4)
            .position(|w| w == b"TGRP")
            .unwrap();
    assert!(second < start as usize);
    for at in LOG_HEADER as usize..second {
        let copy = tempfile::tempdir().unwrap();
        copy_dir(dir.path(), copy.path());
        let mut b = bytes.clone();
        b[at] ^= 0x01;
        let log = copy.path().join(LOG);
        std::fs::write(&log, &b).unwrap();
        let s = DiskStore::open(copy.path()).unwrap();
        let e = s
            .load()
            .await
            .expect_err(&format!("flip at {at} is accepted"));
        let msg = e.to_string();
        assert!(msg.contains(log.to_str().unwrap()), "flip at {at}: {msg}");
        assert!(msg.contains("damaged"), "flip at {at}: {msg}");
        drop(s);
        assert_eq!(
            std::fs::read(&log).unwrap(),
            b,
            "a refused log is left as found"
        );
    }
}

/// A small log limit: the writer compacts many times; everything survives, and so it
/// does when a compaction is interrupted between the snapshots and the truncation.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compaction_keeps_everything_and_is_crash_safe() {
    let dir = tempfile::tempdir().unwrap();
    let s = DiskStore::open_with_log_limit(dir.path(), 2048).unwrap();
    s.load().await.unwrap();
    let mut pools = Vec::new();
    for i in 0..3 {
        s.create_task(&format!("t{i}"), &config(4)).await.unwrap();
        pools.push(Arc::new(Pool::new(4)));
    }
    for j in 0..60u32 {
        for (i, p) in pools.iter_mut().enumerate() {
            let acts: Vec<u32> = (0..(j % 7 + 1)).map(|x| (x + i as u32) % 5).collect();
            *p = commit(
                &s,
                &format!("t{i}"),
                p,
                vec![offer(&acts, f64::from(j))],
                j.into(),
            )
            .await;
        }
    }
    let stats = s.commit_stats();
    assert!(stats.compactions >= 3, "{stats:?}");
    assert!(log_len(dir.path()) < 4096);
    let expected: Vec<_> = pools
        .iter()
        .enumerate()
        .map(|(i, p)| (format!("t{i}"), state(p), counters(59)))
        .collect();
    // An interrupted compaction: the snapshots are written but the old log comes back,
    // as if its truncation never reached the disk; its records are skipped by version.
    let p0 = commit(&s, "t0", &pools[0], vec![offer(&[3; 8], 100.0)], 60).await;
    let mut want = expected.clone();
    want[0] = ("t0".into(), state(&p0), counters(60));
    let old_log = std::fs::read(dir.path().join(LOG)).unwrap();
    assert!(old_log.len() as u64 > LOG_HEADER);
    s.compact().await.unwrap();
    assert_eq!(log_len(dir.path()), LOG_HEADER, "compacted");
    drop(s);
    std::fs::write(dir.path().join(LOG), &old_log).unwrap();
    let (s, tasks) = open(dir.path()).await;
    assert_eq!(states(&tasks), want);
    // A stop's counters record goes into the log, and a start replays it.
    let before = log_len(dir.path());
    s.stopping();
    s.save_counters("t1", pools[1].clone(), counters(70))
        .await
        .unwrap();
    assert!(log_len(dir.path()) > before, "the counters are logged");
    drop(s);
    let (_, tasks) = open(dir.path()).await;
    want[1] = ("t1".into(), state(&pools[1]), counters(70));
    assert_eq!(states(&tasks), want);
}

/// A format-1 data dir (no log) opens and is migrated; a format-2 dir without its log
/// is refused, naming it.
#[tokio::test]
async fn format_1_dirs_are_migrated_and_a_missing_log_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    let expected = populate(&s).await;
    s.compact().await.unwrap();
    drop(s);
    // Now exactly the format-1 layout, once the log is gone, the marker says 1 and the
    // JSON files carry no seal (checksum, data dir id).
    std::fs::remove_file(dir.path().join(LOG)).unwrap();
    let marker = dir.path().join("tamrm.json");
    std::fs::write(&marker, b"{\"format\": 1}").unwrap();
    for task in std::fs::read_dir(dir.path().join("tasks")).unwrap() {
        for f in std::fs::read_dir(task.unwrap().path()).unwrap() {
            let f = f.unwrap().path();
            if f.extension().is_some_and(|x| x == "json") {
                let mut v: serde_json::Value =
                    serde_json::from_slice(&std::fs::read(&f).unwrap()).unwrap();
                let o = v.as_object_mut().unwrap();
                assert!(o.remove("checksum").is_some() && o.remove("dir_id").is_some());
                std::fs::write(&f, serde_json::to_vec(&v).unwrap()).unwrap();
            }
        }
    }
    let copy = tempfile::tempdir().unwrap();
    copy_dir(dir.path(), copy.path());
    let (s, tasks) = open(dir.path()).await;
    assert_eq!(states(&tasks), expected);
    let m: serde_json::Value = serde_json::from_slice(&std::fs::read(&marker).unwrap()).unwrap();
    assert_eq!(m["format"], tamrm::store::FORMAT_VERSION);
    assert_eq!(log_len(dir.path()), LOG_HEADER);
    drop(s);
    // A format-2 marker without a log.
    std::fs::write(copy.path().join("tamrm.json"), b"{\"format\": 2}").unwrap();
    let e = DiskStore::open(copy.path()).unwrap_err().to_string();
    assert!(
        e.contains(copy.path().join(LOG).to_str().unwrap()) && e.contains("missing"),
        "{e}"
    );
}

/// A task deleted and created again while the log holds the old one's changes: the new
/// task never gets them.
#[tokio::test]
async fn a_recreated_task_never_replays_the_deleted_ones_changes() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = open(dir.path()).await;
    s.create_task("x", &config(3)).await.unwrap();
    let mut p = Arc::new(Pool::new(3));
    for i in 0..3 {
        p = commit(&s, "x", &p, vec![offer(&[i], f64::from(i))], 1).await;
    }
    s.delete_task("x").await.unwrap();
    s.create_task("x", &config(3)).await.unwrap();
    let p = commit(
        &s,
        "x",
        &Arc::new(Pool::new(3)),
        vec![offer(&[4, 4], 8.0)],
        2,
    )
    .await;
    assert_eq!((p.version(), p.seqs()), (1, &[1][..]));
    drop(s);
    let (_, tasks) = open(dir.path()).await;
    assert_eq!(
        states(&tasks),
        vec![("x".to_string(), state(&p), counters(2))]
    );
}

/// A real server killed with SIGKILL while 8 clients add trajectories to 4 tasks at
/// once: every acknowledged add is restored, and each task's version is its number of
/// trajectories (one per change, seqs 1..=n without gaps).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_acknowledged_adds_survive_sigkill() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap().to_string();
    let bin = Binary::start(&["--data-dir", &data]);
    let mut c = connect(bin.addr).await;
    let ntasks = 4u32;
    for t in 0..ntasks {
        create(&mut c, &format!("t{t}"), discrete(3, 1000, 1, 0, 1)).await;
    }
    let acked = Arc::new(parking_lot::Mutex::new(Vec::<(String, u64)>::new()));
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut clients = Vec::new();
    for k in 0..8u32 {
        let (mut c, acked, stop) = (connect(bin.addr).await, acked.clone(), stop.clone());
        clients.push(tokio::spawn(async move {
            let mut j = 0u32;
            while !stop.load(std::sync::atomic::Ordering::SeqCst) && j < 100 {
                let id = format!("t{}", (k + j) % ntasks);
                let score = f64::from(k * 1000 + j);
                let req = tamrm::proto::AddTrajectoryRequest {
                    task_id: id.clone(),
                    trajectory: Some(dtraj(&[k % 3, j % 3], score)),
                };
                match c.add_trajectory(req).await {
                    Ok(r) => {
                        assert!(r.into_inner().inserted);
                        acked.lock().push((id, score.to_bits()));
                    }
                    Err(_) => return, // the server is gone
                }
                j += 1;
            }
        }));
    }
    // Kill once a good number are acknowledged, while the clients are still adding.
    while acked.lock().len() < 200 {
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    }
    drop(bin); // SIGKILL
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    for j in clients {
        j.await.unwrap();
    }
    let acked = acked.lock().clone();
    let bin = Binary::start(&["--data-dir", &data]);
    let mut c = connect(bin.addr).await;
    let mut total = 0;
    for t in 0..ntasks {
        let id = format!("t{t}");
        let pool = get_pool(&mut c, &id).await;
        let n = pool.trajectories.len() as u64;
        total += n;
        assert_eq!(pool.pool_version, n, "{id}: one version per change");
        let seqs: Vec<u64> = pool.trajectories.iter().map(|t| t.seq).collect();
        assert_eq!(seqs, (1..=n).collect::<Vec<_>>(), "{id}");
        let have: std::collections::HashSet<u64> = pool
            .trajectories
            .iter()
            .map(|t| t.score.to_bits())
            .collect();
        for (_, s) in acked.iter().filter(|(i, _)| *i == id) {
            assert!(
                have.contains(s),
                "{id}: acknowledged score {} lost",
                f64::from_bits(*s)
            );
        }
    }
    assert!(total >= acked.len() as u64);
    let (status, _) = bin.terminate();
    assert!(status.success());
}

/// A free port on 127.0.0.1 (for the real binary's metrics endpoint).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .unwrap()
        .port()
}

/// `name`'s value in the metrics at `addr` (the series with exactly `labels`, as written
/// in the exposition, e.g. `{task="shared"}`; "" for none).
async fn metric(addr: std::net::SocketAddr, name: &str, labels: &str) -> f64 {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    let mut conn = loop {
        match tokio::net::TcpStream::connect(addr).await {
            Ok(c) => break c,
            Err(e) if std::time::Instant::now() > deadline => panic!("metrics at {addr}: {e}"),
            Err(_) => tokio::time::sleep(std::time::Duration::from_millis(20)).await,
        }
    };
    let req = format!("GET /metrics HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    conn.write_all(req.as_bytes()).await.unwrap();
    let mut raw = String::new();
    conn.read_to_string(&mut raw).await.unwrap();
    let series = format!("{name}{labels} ");
    raw.lines()
        .find_map(|l| l.strip_prefix(&series))
        .unwrap_or_else(|| panic!("no {series} in:\n{raw}"))
        .trim()
        .parse()
        .unwrap()
}

/// A batch of one env's single step that ends its episode with `score`.
fn ending(action: u32, score: f64) -> tamrm::proto::StepBatch {
    let mut b = batch(&[action], &[0.0], &[true]);
    b.episode_scores.insert(0, score);
    b
}

/// 8 Shape streams on ONE task of the real binary with `--data-dir`, each batch ending an
/// episode, the 8 batches of a round sent at the same moment, 25 rounds: every end is a
/// pool change (the pool is never full), and the changes share syncs (fewer
/// `fdatasync`s than changes, counted by the server itself: `tamrm_store_syncs_total`).
/// Then the streams go on and the server is killed with SIGKILL among their batches:
/// after a restart every acknowledged change is there, one version per change.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn ends_of_streams_on_one_task_share_syncs_and_survive_sigkill() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap().to_string();
    let port = free_port();
    let maddr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let listen = maddr.to_string();
    let bin = Binary::start(&["--data-dir", &data, "--metrics-listen", &listen]);
    let mut c = connect(bin.addr).await;
    create(&mut c, "shared", discrete(3, 1000, 1, 0, 1)).await;
    let (streams, rounds) = (8u32, 25u32);
    let mut opened = Vec::new();
    for _ in 0..streams {
        // A connection each, as separate learners have.
        let mut own = connect(bin.addr).await;
        opened.push(Stream::open(&mut own, "shared", 1).await.unwrap().0);
    }
    let syncs_before = metric(maddr, "tamrm_store_syncs_total", "").await;
    let barrier = Arc::new(tokio::sync::Barrier::new(streams as usize));
    // (score bits, pool version answered) of every acknowledged end.
    let acked = Arc::new(parking_lot::Mutex::new(Vec::<(u64, u64)>::new()));
    let counted = Arc::new(tokio::sync::Barrier::new(streams as usize + 1));
    let resume = Arc::new(tokio::sync::Barrier::new(streams as usize + 1));
    let mut joins = Vec::new();
    for (k, mut s) in opened.into_iter().enumerate() {
        let (barrier, acked) = (barrier.clone(), acked.clone());
        let (counted, resume) = (counted.clone(), resume.clone());
        joins.push(tokio::spawn(async move {
            let k = k as u32;
            for round in 0..rounds * 3 {
                if round == rounds {
                    // The measured rounds are over: wait while the syncs are read.
                    counted.wait().await;
                    resume.wait().await;
                }
                if round < rounds {
                    barrier.wait().await;
                }
                let score = f64::from(k * 1000 + round);
                match s.step(ending(k % 3, score)).await {
                    Ok(shaped) => acked.lock().push((score.to_bits(), shaped.pool_version)),
                    Err(_) => return, // killed
                }
            }
        }));
    }
    counted.wait().await;
    let syncs = metric(maddr, "tamrm_store_syncs_total", "").await - syncs_before;
    let changes = metric(maddr, "tamrm_pool_changes_total", "{task=\"shared\"}").await;
    assert_eq!(
        changes,
        f64::from(streams * rounds),
        "every end changed the pool"
    );
    eprintln!(
        "{changes} changes of one task from {streams} streams: {syncs} syncs ({:.2} per change)",
        syncs / changes
    );
    assert!(
        syncs < changes,
        "{syncs} syncs for {changes} changes: the task's changes share no sync"
    );
    {
        let acked = acked.lock();
        assert_eq!(acked.len(), (streams * rounds) as usize);
        let most = acked.iter().map(|a| a.1).max();
        assert_eq!(most, Some(u64::from(streams * rounds)));
    }
    // Go on, and kill the server among the batches.
    resume.wait().await;
    let target = (streams * rounds) as usize + 60;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while acked.lock().len() < target {
        assert!(std::time::Instant::now() < deadline, "the streams stalled");
        tokio::time::sleep(std::time::Duration::from_millis(2)).await;
    }
    drop(bin); // SIGKILL
    for j in joins {
        j.await.unwrap();
    }
    let acked = acked.lock().clone();
    let bin = Binary::start(&["--data-dir", &data]);
    let mut c = connect(bin.addr).await;
    let pool = get_pool(&mut c, "shared").await;
    let n = pool.trajectories.len() as u64;
    assert_eq!(pool.pool_version, n, "one version per change");
    let seqs: Vec<u64> = pool.trajectories.iter().map(|t| t.seq).collect();
    assert_eq!(seqs, (1..=n).collect::<Vec<_>>());
    let have: std::collections::HashSet<u64> = pool
        .trajectories
        .iter()
        .map(|t| t.score.to_bits())
        .collect();
    for (score, version) in &acked {
        assert!(
            have.contains(score),
            "acknowledged end {} (answered at version {version}) lost",
            f64::from_bits(*score)
        );
        assert!(
            *version <= n,
            "answered version {version} past the restored {n}"
        );
    }
    assert!(n >= acked.len() as u64);
    let (status, _) = bin.terminate();
    assert!(status.success());
}

/// The same with SPEC §13 Follow streams (in process, the store's own counts): 8 learners
/// on one task send their ends at the same moment; every end is acknowledged with the
/// version it produced (distinct, one per change), and the task's changes share syncs.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn ends_of_follow_streams_on_one_task_share_syncs() {
    let dir = tempfile::tempdir().unwrap();
    let server = start_server(Some(dir.path()), |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    })
    .await;
    let maddr = server.metrics_addr().unwrap();
    let mut c = connect(server.addr()).await;
    create(&mut c, "f", discrete(3, 1000, 1, 0, 1)).await;
    let (learners, rounds) = (8u32, 20u64);
    let mut followers = Vec::new();
    for k in 0..learners {
        let mut own = connect(server.addr()).await;
        let client = format!("learner-{k}");
        followers.push(Follower::open(&mut own, "f", 1, &client).await.unwrap().0);
    }
    let syncs_before = metric(maddr, "tamrm_store_syncs_total", "").await;
    let barrier = Arc::new(tokio::sync::Barrier::new(learners as usize));
    let mut joins = Vec::new();
    for (k, mut f) in followers.into_iter().enumerate() {
        let barrier = barrier.clone();
        joins.push(tokio::spawn(async move {
            let mut versions = Vec::new();
            for episode in 0..rounds {
                barrier.wait().await;
                let score = (k as u64 * 1000 + episode) as f64;
                let end = dend(0, episode, &[k as u32 % 3], Some(score), 0.0);
                let ack = f.ends(vec![end], 1).await.unwrap();
                assert_eq!(
                    (ack.changed.clone(), ack.resent.clone()),
                    (vec![true], vec![false])
                );
                assert!(ack.versions[0] <= ack.pool_version);
                versions.push(ack.versions[0]);
            }
            versions
        }));
    }
    let mut versions = Vec::new();
    for j in joins {
        versions.extend(j.await.unwrap());
    }
    versions.sort_unstable();
    let changes = u64::from(learners) * rounds;
    assert_eq!(
        versions,
        (1..=changes).collect::<Vec<_>>(),
        "one version per change"
    );
    let syncs = metric(maddr, "tamrm_store_syncs_total", "").await - syncs_before;
    eprintln!(
        "{changes} changes of one task from {learners} follow streams: {syncs} syncs ({:.2} per change)",
        syncs / changes as f64
    );
    assert!(
        syncs < changes as f64,
        "{syncs} syncs for {changes} changes"
    );
    assert_eq!(
        get_task(&mut c, "f").await.stats.unwrap().pool_version,
        changes
    );
    server.shutdown().await;
}
