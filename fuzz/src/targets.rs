//! The three fuzz targets, as functions of the raw input (the `fuzz_targets/` binaries
//! call them; the regression tests in `tests/` replay inputs through them).

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use prost::Message;
use tamrm::proto::{self, shape_request, ShapeRequest};
use tamrm::store::{DiskStore, Store, StoredTask};
use tonic::Code;

use crate::{assert_not_ours, check_answer, check_pool, chunks, Harness};

/// (a) A `Shape` stream: the input is a sequence of length-prefixed raw `ShapeRequest`
/// messages ([`chunks`]), sent one at a time. After every message the pools are checked;
/// a message that ended the stream with an error changed no pool, and the next message
/// goes to a new stream.
pub async fn shape_stream(data: &[u8]) {
    let mut h = Harness::new().await;
    let mut stream = h.stream().await;
    for msg in chunks(data) {
        let before = h.check();
        match stream.send(msg).await {
            Some(answer) => {
                check_answer(&answer);
                h.check();
            }
            None => {
                let status = stream
                    .ended
                    .clone()
                    .unwrap_or_else(|| tonic::Status::ok(""));
                assert_not_ours("Shape", &status);
                assert_eq!(
                    before,
                    h.check(),
                    "a refused message changed a pool: {status:?}"
                );
                stream = h.stream().await;
            }
        }
    }
    let status = stream.close().await;
    assert_not_ours("Shape (closed)", &status);
    h.check();
}

/// The unary methods, chosen by the first byte of a call. The order is part of the
/// input format (the corpus depends on it); [`unary`] checks once that the list is
/// `tamrm::auth::unary_rpcs()` (from the one table, itself checked against the proto).
pub const UNARY: [&str; 7] = [
    "CreateTask",
    "GetTask",
    "ListTasks",
    "DeleteTask",
    "ResetPool",
    "GetPool",
    "AddTrajectory",
];

/// (b) Unary calls: the input is a sequence of length-prefixed calls, each a method byte
/// ([`UNARY`], modulo) and the raw request. A call that fails changes no pool; an answer
/// decodes as the method's response type.
pub async fn unary(data: &[u8]) {
    static LISTED: std::sync::Once = std::sync::Once::new();
    LISTED.call_once(|| {
        let mut table: Vec<&str> = tamrm::auth::unary_rpcs().collect();
        let mut ours = UNARY.to_vec();
        table.sort_unstable();
        ours.sort_unstable();
        assert_eq!(ours, table, "UNARY must list every unary RPC");
    });
    let mut h = Harness::new().await;
    for call in chunks(data) {
        let Some((&which, request)) = call.split_first() else {
            continue;
        };
        let method = UNARY[usize::from(which) % UNARY.len()];
        let before = h.check();
        let answer = h.unary(method, request).await;
        assert_not_ours(method, &answer.status);
        let after = h.check();
        if answer.status.code() != Code::Ok {
            assert_eq!(
                before, after,
                "{method} failed and changed a pool: {:?}",
                answer.status
            );
            continue;
        }
        assert_eq!(answer.messages.len(), 1, "{method}: one answer");
        let m = answer.messages[0].clone();
        let decodes = match method {
            "CreateTask" | "GetTask" | "ResetPool" => proto::Task::decode(m).is_ok(),
            "ListTasks" => proto::ListTasksResponse::decode(m).is_ok(),
            "DeleteTask" => proto::DeleteTaskResponse::decode(m).is_ok(),
            "GetPool" => proto::Pool::decode(m).is_ok(),
            _ => proto::AddTrajectoryResponse::decode(m).is_ok(),
        };
        assert!(decodes, "{method}: the answer decodes");
    }
}

/// A data dir written by the disk store: its files (path relative to the dir, bytes), as
/// they are after every acknowledged change (snapshots, trajectory files, the log).
pub fn disk_template() -> &'static [(PathBuf, Vec<u8>)] {
    static T: OnceLock<Vec<(PathBuf, Vec<u8>)>> = OnceLock::new();
    T.get_or_init(|| {
        let dir = tempfile::tempdir().expect("a temp dir");
        crate::runtime().block_on(async {
            // A first server: tasks created, episodes committed, then its log folded
            // into snapshots (as a compaction does).
            {
                let store = Arc::new(DiskStore::open(dir.path()).expect("open"));
                let mut h = Harness::with_store(store.clone()).await;
                write_history(&mut h, 0).await;
                store.compact().await.expect("compact");
            }
            // A second one: its changes stay in the log (as after a kill -9).
            let store = Arc::new(DiskStore::open(dir.path()).expect("reopen"));
            let mut h = Harness::over(store).await;
            write_history(&mut h, 1).await;
            let mut files = Vec::new();
            collect(dir.path(), dir.path(), &mut files);
            files.sort();
            files
        })
    })
}

/// Some episodes on every task of [`crate::task_configs`], and an `AddTrajectory`.
async fn write_history(h: &mut Harness, round: u32) {
    for (id, config) in crate::task_configs() {
        let dim = config.action_dim as usize;
        let mut s = h.stream().await;
        let open = ShapeRequest {
            kind: Some(shape_request::Kind::Open(proto::Open {
                task_id: id.into(),
                num_envs: 2,
                ..Default::default()
            })),
        };
        s.send(&open.encode_to_vec()).await.expect("opened");
        for t in 0..12u32 {
            let batch = proto::StepBatch {
                env_ids: vec![0, 1],
                actions: if dim == 0 {
                    vec![t % 3, (t + round) % 2]
                } else {
                    vec![]
                },
                action_vectors: vec![0.25 * t as f32; 2 * dim],
                rewards: vec![f64::from(t % 4), f64::from(round) - 1.5],
                terminated: vec![t % 4 == 3, t % 5 == 4],
                ..Default::default()
            };
            let msg = ShapeRequest {
                kind: Some(shape_request::Kind::Steps(batch)),
            };
            let answer = s.send(&msg.encode_to_vec()).await;
            assert!(answer.is_some(), "{id}: {:?}", s.ended);
        }
        s.close().await;
        if dim == 0 {
            let add = proto::AddTrajectoryRequest {
                task_id: id.into(),
                trajectory: Some(proto::Trajectory {
                    actions: vec![1, 2, 0],
                    score: 50.0 + f64::from(round),
                    ..Default::default()
                }),
            };
            let a = h.unary("AddTrajectory", &add.encode_to_vec()).await;
            assert_eq!(a.status.code(), Code::Ok, "{:?}", a.status);
        }
    }
}

fn collect(root: &std::path::Path, dir: &std::path::Path, out: &mut Vec<(PathBuf, Vec<u8>)>) {
    for e in std::fs::read_dir(dir).expect("read_dir").flatten() {
        let p = e.path();
        if p.is_dir() {
            collect(root, &p, out);
        } else if p.file_name().is_some_and(|n| n != "LOCK") {
            let bytes = std::fs::read(&p).expect("read");
            out.push((
                p.strip_prefix(root).expect("under root").to_path_buf(),
                bytes,
            ));
        }
    }
}

/// What a load restored, comparable.
fn restored(tasks: &[StoredTask]) -> Vec<String> {
    let mut v: Vec<String> = tasks
        .iter()
        .map(|t| {
            let scores: Vec<u64> = t
                .pool
                .trajectories()
                .iter()
                .map(|x| x.score.to_bits())
                .collect();
            format!(
                "{} {:?} v{} n{} {:?} {:?} {:?}",
                t.id,
                t.config,
                t.pool.version(),
                t.pool.next_seq(),
                t.pool.seqs(),
                scores,
                t.counters
            )
        })
        .collect();
    v.sort();
    v
}

/// (c) The on-disk decoder: the input's first byte picks a file of [`disk_template`], the
/// rest replaces its bytes. Opening the data dir either fails (the corruption reported) or
/// restores pools that satisfy §6 and fit their task's action space, the same on a second
/// start, and that a server can then shape on.
pub fn disk(data: &[u8]) {
    let Some((&which, bytes)) = data.split_first() else {
        return;
    };
    let files = disk_template();
    let target = usize::from(which) % files.len();
    let base = if std::path::Path::new("/dev/shm").is_dir() {
        tempfile::tempdir_in("/dev/shm")
    } else {
        tempfile::tempdir()
    };
    let dir = base.expect("a temp dir");
    for (i, (path, content)) in files.iter().enumerate() {
        let p = dir.path().join(path);
        if let Some(parent) = p.parent() {
            std::fs::create_dir_all(parent).expect("mkdir");
        }
        std::fs::write(&p, if i == target { bytes } else { content }).expect("write");
    }
    crate::runtime().block_on(async {
        let first = match load(dir.path()).await {
            Some(t) => t,
            None => return,
        };
        for t in &first {
            let c = &t.config;
            check_pool(
                &t.id,
                &t.pool,
                c.action_space,
                c.max_trajectory_len as usize,
            );
        }
        let again = load(dir.path())
            .await
            .expect("a data dir that opened once opens again");
        assert_eq!(
            restored(&first),
            restored(&again),
            "a second start restores the same"
        );
        // A server on the restored data shapes and commits on every task.
        let store = Arc::new(DiskStore::open(dir.path()).expect("opens a third time"));
        let mut h = Harness::over(store).await;
        h.check();
        for t in &again {
            let mut s = h.stream().await;
            let open = ShapeRequest {
                kind: Some(shape_request::Kind::Open(proto::Open {
                    task_id: t.id.clone(),
                    num_envs: 1,
                    ..Default::default()
                })),
            };
            if s.send(&open.encode_to_vec()).await.is_none() {
                let status = s.ended.clone().unwrap_or_else(|| tonic::Status::ok(""));
                assert_not_ours("Open on restored data", &status);
                continue;
            }
            let dim = t.config.action_space.action_dim();
            for step in 0..4u32 {
                let batch = proto::StepBatch {
                    env_ids: vec![0],
                    actions: if dim == 0 { vec![0] } else { vec![] },
                    action_vectors: vec![0.5; dim],
                    rewards: vec![f64::from(step)],
                    terminated: vec![step == 3],
                    ..Default::default()
                };
                let msg = ShapeRequest {
                    kind: Some(shape_request::Kind::Steps(batch)),
                };
                match s.send(&msg.encode_to_vec()).await {
                    Some(a) => check_answer(&a),
                    None => {
                        let status = s.ended.clone().unwrap_or_else(|| tonic::Status::ok(""));
                        assert_not_ours("Shape on restored data", &status);
                        break;
                    }
                }
                h.check();
            }
        }
    });
}

/// Opens and loads a data dir; `None` if it is reported corrupt.
async fn load(dir: &std::path::Path) -> Option<Vec<StoredTask>> {
    let store = DiskStore::open(dir).ok()?;
    store.load().await.ok()
}
