//! Durability and process behaviour: restarts restore everything, acknowledged changes
//! survive a crash, corrupt state is refused naming the file, graceful shutdown, and the
//! settings sources of the real binary.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use crate::common::*;
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest, ShapeResponse, StepBatch};
use tamrm::settings::Settings;
use tonic::Code;

// ---------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------

const ENV_VARS: &[&str] = &[
    "TAMRM_CONFIG",
    "TAMRM_LISTEN",
    "TAMRM_DATA_DIR",
    "TAMRM_PORT_FILE",
    "TAMRM_MAX_TASKS",
    "TAMRM_MAX_ENVS_PER_STREAM",
    "TAMRM_MAX_BATCH_ENTRIES",
    "TAMRM_MAX_MESSAGE_BYTES",
    "TAMRM_MAX_POOL_CAPACITY",
    "TAMRM_SHUTDOWN_GRACE_SECS",
];

/// The real binary with full control over arguments and environment; stderr goes to a
/// file so that it can be read at any time and never blocks the child.
struct Proc {
    child: Child,
    stderr: PathBuf,
    _dir: tempfile::TempDir,
}

impl Proc {
    fn spawn(args: &[&str], envs: &[(&str, &str)]) -> Proc {
        let dir = tempfile::tempdir().unwrap();
        let stderr = dir.path().join("stderr");
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_tamrm"));
        for v in ENV_VARS {
            cmd.env_remove(v);
        }
        cmd.env("RUST_LOG", "info")
            .args(args)
            .envs(envs.iter().copied())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&stderr).unwrap());
        Proc {
            child: cmd.spawn().expect("spawn tamrm"),
            stderr,
            _dir: dir,
        }
    }

    fn stderr(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }

    fn wait(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                return Some(s);
            }
            if Instant::now() > deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn sigterm(&self) {
        sigterm(self.child.id());
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn sigterm(pid: u32) {
    let ok = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -TERM {pid}");
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

pub(crate) fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for entry in std::fs::read_dir(src).unwrap() {
        let entry = entry.unwrap();
        let to = dst.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &to);
        } else {
            std::fs::copy(entry.path(), &to).unwrap();
        }
    }
}

/// The directory of the only task under `data`.
fn only_task_dir(data: &Path) -> PathBuf {
    let dirs: Vec<PathBuf> = std::fs::read_dir(data.join("tasks"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(dirs.len(), 1, "{dirs:?}");
    dirs[0].clone()
}

fn traj_files(task_dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(task_dir.join("traj"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

fn settings(dir: &Path) -> Settings {
    Settings {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: Some(dir.to_path_buf()),
        shutdown_grace_secs: 10,
        ..Settings::default()
    }
}

/// Every task (full protos, stats included) and every pool.
pub(crate) async fn snapshot(c: &mut Client) -> (Vec<proto::Task>, Vec<proto::Pool>) {
    let tasks = c
        .list_tasks(proto::ListTasksRequest {})
        .await
        .unwrap()
        .into_inner()
        .tasks;
    let mut pools = Vec::new();
    for t in &tasks {
        pools.push(get_pool(c, &t.task_id).await);
    }
    (tasks, pools)
}

/// Protos compare floats with ==, where -0.0 == 0.0: also compare every float bit for bit.
pub(crate) fn assert_bit_exact(a: &[proto::Pool], b: &[proto::Pool]) {
    assert_eq!(a, b);
    for (pa, pb) in a.iter().zip(b) {
        for (ta, tb) in pa.trajectories.iter().zip(&pb.trajectories) {
            assert_eq!(ta.score.to_bits(), tb.score.to_bits(), "{}", pa.task_id);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&ta.action_vectors), bits(&tb.action_vectors));
        }
    }
}

pub(crate) fn assert_configs_bit_exact(a: &[proto::Task], b: &[proto::Task]) {
    assert_eq!(a.len(), b.len());
    for (ta, tb) in a.iter().zip(b) {
        let (ca, cb) = (ta.config.unwrap(), tb.config.unwrap());
        assert_eq!(ca, cb);
        for (x, y) in [
            (ca.alpha, cb.alpha),
            (ca.beta, cb.beta),
            (ca.gamma, cb.gamma),
        ] {
            assert_eq!(x.unwrap().to_bits(), y.unwrap().to_bits(), "{}", ta.task_id);
        }
    }
}

const ODD_FLOATS: [f32; 9] = [
    -0.0,
    f32::MIN_POSITIVE,
    f32::from_bits(1),
    f32::MAX,
    f32::MIN,
    0.1,
    -1e-30,
    std::f32::consts::PI,
    1.0 + f32::EPSILON,
];

/// Creates a varied state: discrete and continuous tasks, odd floats, replacements, a
/// reset pool, an empty task, counters from a stream. Returns the number of seqs assigned
/// per task (the next seq is that + 1).
pub(crate) async fn populate(c: &mut Client) -> Vec<(String, u64)> {
    let mut d = discrete(4, 3, 2, 0, 1);
    d.max_trajectory_len = Some(5);
    d.alpha = Some(0.1 + 0.2);
    d.gamma = Some(1.0 / 3.0);
    create(c, "d", d).await;
    // A stream: two envs, episodes with replacements.
    let (mut s, _) = Stream::open(c, "d", 2).await.unwrap();
    let mut inserts = 0;
    for i in 0..12u32 {
        let out = s
            .step(StepBatch {
                env_ids: vec![0, 1, 0, 1],
                actions: vec![i % 4, (i + 1) % 4, (i + 2) % 4, 3],
                rewards: vec![0.5, f64::from(i) * 0.1, 1.0 / 3.0, -0.25],
                terminated: vec![false, false, i % 3 == 0, false],
                truncated: vec![false, false, false, i % 2 == 1],
                ..Default::default()
            })
            .await
            .unwrap();
        inserts = out.pool_version;
    }
    s.close();
    let r = add(c, "d", dtraj(&[3, 2, 1, 0, 0, 1, 2], 1e9)).await;
    assert!(r.inserted);
    inserts += 1;
    assert_eq!(r.pool_version, inserts);

    create(
        c,
        "c/1:x",
        proto::TaskConfig {
            action_dim: 3,
            pool_capacity: Some(4),
            beta: Some(-2.5e-7),
            ..Default::default()
        },
    )
    .await;
    add(c, "c/1:x", ctraj(&ODD_FLOATS, -0.0)).await;
    add(c, "c/1:x", ctraj(&[1.5, -2.5, 0.1], f64::MIN_POSITIVE)).await;
    add(c, "c/1:x", ctraj(&ODD_FLOATS[3..], -1e300)).await;

    create(c, "empty", discrete(2, 5, 5, 10, 5)).await;

    create(c, "reset", discrete(3, 2, 2, 0, 1)).await;
    add(c, "reset", dtraj(&[0, 1], 1.0)).await;
    add(c, "reset", dtraj(&[2], 2.0)).await;
    c.reset_pool(proto::ResetPoolRequest {
        task_id: "reset".into(),
    })
    .await
    .unwrap();
    // Ids that differ only in characters a directory name cannot hold, and the longest id.
    let long = format!("{}:/.-_", "L".repeat(123));
    for (i, id) in ["x/y", "x:y", long.as_str()].iter().enumerate() {
        create(c, id, discrete(3, 2, 2, 0, 1)).await;
        add(c, id, dtraj(&[i as u32], i as f64)).await;
    }
    wait_open_streams(c, "d", 0).await;
    vec![
        ("x/y".into(), 1),
        ("x:y".into(), 1),
        (long, 1),
        ("d".into(), inserts),
        ("c/1:x".into(), 3),
        ("empty".into(), 0),
        ("reset".into(), 2),
    ]
}

/// After a restart: new trajectories get the next seq, versions go on from where they were.
async fn check_seqs_continue(c: &mut Client, assigned: &[(String, u64)], bump: u64) {
    for (id, n) in assigned {
        let before = get_task(c, id).await.stats.unwrap().pool_version;
        let cfg = get_task(c, id).await.config.unwrap();
        let t = if cfg.action_dim > 0 {
            ctraj(&vec![0.5; cfg.action_dim as usize], 1e12)
        } else {
            dtraj(&[1], 1e12)
        };
        let r = add(c, id, t).await;
        assert!(r.inserted);
        assert_eq!(r.pool_version, before + 1, "{id}: pool_version goes on");
        let p = get_pool(c, id).await;
        let last = p.trajectories.last().unwrap();
        assert_eq!(last.score, 1e12);
        assert_eq!(last.seq, n + 1 + bump, "{id}: seq numbering continues");
    }
}

// ---------------------------------------------------------------------------------------
// Restarts
// ---------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn in_process_restart_restores_everything() {
    let dir = tempfile::tempdir().unwrap();
    let server = start_server(Some(dir.path()), |_| {}).await;
    let mut c = connect(server.addr()).await;
    let assigned = populate(&mut c).await;
    let (tasks, pools) = snapshot(&mut c).await;
    assert_eq!(tasks.len(), 7);
    server.shutdown().await;

    let server = start_server(Some(dir.path()), |_| {}).await;
    let mut c = connect(server.addr()).await;
    let (tasks2, pools2) = snapshot(&mut c).await;
    assert_eq!(
        tasks2, tasks,
        "tasks, configs and stats (counters included)"
    );
    assert_configs_bit_exact(&tasks, &tasks2);
    assert_bit_exact(&pools, &pools2);
    check_seqs_continue(&mut c, &assigned, 0).await;
    let (tasks3, pools3) = snapshot(&mut c).await;
    server.shutdown().await;

    // And once more: the post-restart changes are kept too.
    let server = start_server(Some(dir.path()), |_| {}).await;
    let mut c = connect(server.addr()).await;
    let (tasks4, pools4) = snapshot(&mut c).await;
    assert_eq!(tasks4, tasks3);
    assert_bit_exact(&pools3, &pools4);
    check_seqs_continue(&mut c, &assigned, 1).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binary_restart_after_sigterm_restores_everything() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap();
    let bin = Binary::start(&["--data-dir", data]);
    let mut c = connect(bin.addr).await;
    let assigned = populate(&mut c).await;
    let (tasks, pools) = snapshot(&mut c).await;
    drop(c);
    let (status, stderr) = bin.terminate();
    assert!(
        status.success(),
        "exit status {status:?}; stderr:\n{stderr}"
    );

    let bin = Binary::start(&["--data-dir", data]);
    let mut c = connect(bin.addr).await;
    let (tasks2, pools2) = snapshot(&mut c).await;
    assert_eq!(tasks2, tasks);
    assert_configs_bit_exact(&tasks, &tasks2);
    assert_bit_exact(&pools, &pools2);
    check_seqs_continue(&mut c, &assigned, 0).await;
    drop(c);
    let (status, stderr) = bin.terminate();
    assert!(status.success(), "{stderr}");
    assert!(
        stderr.contains(data),
        "the log names the data dir:\n{stderr}"
    );
}

/// Copies the data dir right after each acknowledged change while the server keeps
/// running, then kills it with SIGKILL: every copy, and the killed server's dir, hold the
/// acknowledged state (pools bit for bit; counters may lag after a crash).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acknowledged_changes_survive_a_crash() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let copies = tempfile::tempdir().unwrap();
    let bin = Binary::start(&["--data-dir", data.to_str().unwrap()]);
    let mut c = connect(bin.addr).await;
    let mut expected: Vec<(PathBuf, Vec<proto::Task>, Vec<proto::Pool>)> = Vec::new();
    macro_rules! checkpoint {
        ($c:expr) => {{
            let to = copies.path().join(expected.len().to_string());
            copy_dir(&data, &to);
            let (t, p) = snapshot($c).await;
            expected.push((to, t, p));
        }};
    }
    create(&mut c, "a", discrete(3, 2, 2, 0, 1)).await;
    checkpoint!(&mut c);
    add(&mut c, "a", dtraj(&[0, 1, 2], 1.0)).await;
    checkpoint!(&mut c);
    create(
        &mut c,
        "c",
        proto::TaskConfig {
            action_dim: 2,
            pool_capacity: Some(2),
            ..Default::default()
        },
    )
    .await;
    add(&mut c, "c", ctraj(&ODD_FLOATS[..8], 0.25)).await;
    checkpoint!(&mut c);
    // An episode end acknowledged by a ShapedBatch; the stream stays open.
    let (mut s, _) = Stream::open(&mut c, "a", 1).await.unwrap();
    let out = s
        .step(StepBatch {
            env_ids: vec![0, 0],
            actions: vec![2, 2],
            rewards: vec![1.0, 2.0],
            terminated: vec![false, true],
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(out.pool_version, 2);
    checkpoint!(&mut c);
    let out = s
        .step(StepBatch {
            env_ids: vec![0, 0, 0],
            actions: vec![1, 1, 0],
            rewards: vec![5.0, 5.0, 5.0],
            terminated: vec![false, false, true],
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(out.pool_version, 3, "replaced the worst");
    checkpoint!(&mut c);
    c.reset_pool(proto::ResetPoolRequest {
        task_id: "c".into(),
    })
    .await
    .unwrap();
    checkpoint!(&mut c);
    create(&mut c, "gone", discrete(2, 1, 1, 0, 1)).await;
    add(&mut c, "gone", dtraj(&[1], 1.0)).await;
    c.delete_task(proto::DeleteTaskRequest {
        task_id: "gone".into(),
    })
    .await
    .unwrap();
    checkpoint!(&mut c);
    add(&mut c, "c", ctraj(&[7.0, -7.0], -3.0)).await;
    checkpoint!(&mut c);
    // Crash: SIGKILL while a stream is open.
    drop(bin);
    drop(s);

    let same_pools = |a: &[proto::Task], b: &[proto::Task]| {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert_eq!(x.task_id, y.task_id);
            assert_eq!(x.config, y.config);
            let (sx, sy) = (x.stats.unwrap(), y.stats.unwrap());
            assert_eq!(
                (sx.pool_size, sx.pool_version, sx.min_length),
                (sy.pool_size, sy.pool_version, sy.min_length)
            );
            assert_eq!(
                (sx.best_score.to_bits(), sx.worst_score.to_bits()),
                (sy.best_score.to_bits(), sy.worst_score.to_bits())
            );
        }
    };
    for (i, (copy, tasks, pools)) in expected.iter().enumerate() {
        let server = tamrm::server::start(&settings(copy))
            .await
            .unwrap_or_else(|e| panic!("copy {i} does not start: {e}"));
        let mut c = connect(server.addr()).await;
        let (t, p) = snapshot(&mut c).await;
        same_pools(tasks, &t);
        assert_bit_exact(pools, &p);
        server.shutdown().await;
    }
    // The crashed server's own directory.
    let bin = Binary::start(&["--data-dir", data.to_str().unwrap()]);
    let mut c = connect(bin.addr).await;
    let (t, p) = snapshot(&mut c).await;
    let (_, tasks, pools) = expected.last().unwrap();
    same_pools(tasks, &t);
    assert_bit_exact(pools, &p);
    // Seqs go on after the crash: "a" used seqs 1..=3 (it holds 2, 3); "c" used 1, then
    // was reset, then 2.
    assert_eq!(add(&mut c, "a", dtraj(&[0], 99.0)).await.pool_version, 4);
    assert_eq!(get_pool(&mut c, "a").await.trajectories[1].seq, 4);
    add(&mut c, "c", ctraj(&[0.0, 0.0], 99.0)).await;
    assert_eq!(get_pool(&mut c, "c").await.trajectories[1].seq, 3);
    drop(c);
    let (status, _) = bin.terminate();
    assert!(status.success());
}

// ---------------------------------------------------------------------------------------
// Corrupt state is refused, naming the file; unfinished changes are cleaned up
// ---------------------------------------------------------------------------------------

/// A data dir with one task "t" holding three trajectories (seqs 1, 2, 3).
async fn base_data_dir(dir: &Path) {
    let server = start_server(Some(dir), |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(4, 3, 3, 0, 1)).await;
    for (a, s) in [(&[0u32, 1][..], 1.0), (&[2, 2, 2], 2.0), (&[3], 3.0)] {
        assert!(add(&mut c, "t", dtraj(a, s)).await.inserted);
    }
    server.shutdown().await;
    // Into the snapshot: the tests below break its files.
    let store = tamrm::store::DiskStore::open(dir).unwrap();
    tamrm::store::Store::load(&store).await.unwrap();
    store.compact().await.unwrap();
}

/// `tamrm serve` exits non-zero naming `file`, and `tamrm::server::start` returns an error
/// naming it (each on its own copy of `dir`).
async fn assert_refused(dir: &Path, file: &Path, what: &str) {
    let rel = file.strip_prefix(dir).unwrap();
    let copy = tempfile::tempdir().unwrap();
    copy_dir(dir, copy.path());

    let mut p = Proc::spawn(
        &[
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--data-dir",
            dir.to_str().unwrap(),
        ],
        &[],
    );
    let status = p.wait(Duration::from_secs(15));
    let stderr = p.stderr();
    let status = status.unwrap_or_else(|| panic!("{what}: the server started anyway:\n{stderr}"));
    assert!(!status.success(), "{what}: exit status {status:?}");
    let name = file.to_str().unwrap();
    assert!(
        stderr.contains(name),
        "{what}: stderr does not name {name}:\n{stderr}"
    );

    let copied = copy.path().join(rel);
    match tamrm::server::start(&settings(copy.path())).await {
        Ok(server) => {
            server.shutdown().await;
            panic!("{what}: server::start succeeded");
        }
        Err(e) => {
            let msg = e.to_string();
            assert!(
                msg.contains(copied.to_str().unwrap()),
                "{what}: error does not name {}: {msg}",
                copied.display()
            );
        }
    }
}

fn flip_byte(path: &Path, at: usize) {
    let mut b = std::fs::read(path).unwrap();
    b[at] ^= 0x01;
    std::fs::write(path, b).unwrap();
}

fn set_json_format(path: &Path, format: u64) {
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    v["format"] = serde_json::Value::from(format);
    std::fs::write(path, serde_json::to_vec(&v).unwrap()).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrupt_or_truncated_state_is_refused_naming_the_file() {
    let base = tempfile::tempdir().unwrap();
    base_data_dir(base.path()).await;
    let fresh = || {
        let d = tempfile::tempdir().unwrap();
        copy_dir(base.path(), d.path());
        let task = only_task_dir(d.path());
        (d, task)
    };

    // Truncated trajectory file.
    let (d, task) = fresh();
    let f = traj_files(&task)[1].clone();
    let len = std::fs::metadata(&f).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&f)
        .unwrap()
        .set_len(len - 3)
        .unwrap();
    assert_refused(d.path(), &f, "truncated trajectory").await;

    // Truncated to nothing.
    let (d, task) = fresh();
    let f = traj_files(&task)[0].clone();
    std::fs::write(&f, b"").unwrap();
    assert_refused(d.path(), &f, "empty trajectory").await;

    // One flipped byte in a trajectory's payload, and in its score.
    for at in [-8i64, 30] {
        let (d, task) = fresh();
        let f = traj_files(&task)[1].clone();
        let len = std::fs::read(&f).unwrap().len() as i64;
        flip_byte(&f, if at < 0 { len + at } else { at } as usize);
        assert_refused(d.path(), &f, "flipped byte").await;
    }

    // A listed trajectory file is missing.
    let (d, task) = fresh();
    let f = traj_files(&task)[2].clone();
    std::fs::remove_file(&f).unwrap();
    assert_refused(d.path(), &f, "missing trajectory").await;

    // Corrupt / truncated pool.json and task.json.
    for (name, content) in [
        ("pool.json", &b"{\"format\": 1, \"pool_vers"[..]),
        ("pool.json", b""),
        ("pool.json", b"\x00\x01garbage"),
        ("task.json", b"not json at all"),
        ("task.json", b"{\"format\": 1}"),
    ] {
        let (d, task) = fresh();
        let f = task.join(name);
        std::fs::write(&f, content).unwrap();
        assert_refused(d.path(), &f, &format!("corrupt {name}")).await;
    }
    // A pool.json listing one seq twice.
    let (d, task) = fresh();
    let f = task.join("pool.json");
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&f).unwrap()).unwrap();
    v["seqs"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::Value::from(2u64));
    std::fs::write(&f, serde_json::to_vec(&v).unwrap()).unwrap();
    assert_refused(d.path(), &f, "duplicate seq in pool.json").await;

    // A task.json that parses but holds a config out of SPEC §1.1's ranges (found by the
    // `disk` fuzz target: `"k": 0` was used, and the first step panicked in the kNN
    // selection). Each is refused naming the file.
    for (field, value) in [
        ("k", serde_json::json!(0)),
        ("pool_capacity", serde_json::json!(0)),
        ("min_pool_size", serde_json::json!(0)),
        ("gamma", serde_json::json!(1.5)),
        ("max_trajectory_len", serde_json::json!(0)),
    ] {
        let (d, task) = fresh();
        let f = task.join("task.json");
        let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&f).unwrap()).unwrap();
        assert!(
            v["config"].get(field).is_some(),
            "task.json has config.{field}"
        );
        v["config"][field] = value;
        std::fs::write(&f, serde_json::to_vec(&v).unwrap()).unwrap();
        assert_refused(d.path(), &f, &format!("config.{field} out of range")).await;
    }

    // Unsupported format numbers.
    for name in ["pool.json", "task.json"] {
        let (d, task) = fresh();
        let f = task.join(name);
        set_json_format(&f, 2);
        assert_refused(d.path(), &f, &format!("format 2 in {name}")).await;
    }
    let (d, _) = fresh();
    let f = d.path().join("tamrm.json");
    set_json_format(&f, 99);
    assert_refused(d.path(), &f, "format 99 in tamrm.json").await;
    // A trajectory file of format 2 with a valid checksum.
    let (d, task) = fresh();
    let f = traj_files(&task)[0].clone();
    let mut b = std::fs::read(&f).unwrap();
    b[8..12].copy_from_slice(&2u32.to_le_bytes());
    let n = b.len() - 4;
    let crc = crc32fast::hash(&b[..n]);
    b[n..].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(&f, b).unwrap();
    assert_refused(d.path(), &f, "trajectory format 2").await;
}

/// The commit log (`commits.log`) holds the changes since the snapshots: a flipped byte
/// in a group that is not the last one is corruption, refused naming the log.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_commit_log_is_refused_naming_it() {
    use std::sync::Arc;
    use tamrm::core::ActionSeq;
    use tamrm::store::{Counters, DiskStore, PoolOp, Store};
    let base = tempfile::tempdir().unwrap();
    base_data_dir(base.path()).await;
    {
        // Two changes left in the log by a crash: the store dropped without a flush.
        let s = DiskStore::open(base.path()).unwrap();
        let mut pool = Arc::new(s.load().await.unwrap().remove(0).pool);
        for score in [4.0, 5.0] {
            let ops = vec![PoolOp::Offer {
                actions: ActionSeq::Discrete(vec![1, 2]),
                score,
                end: None,
            }];
            pool = s
                .commit("t", pool, ops, Counters::default())
                .await
                .unwrap()
                .pool;
        }
    }
    let log = base.path().join("commits.log");
    // Header (44 bytes), then the first group's head and its first record.
    flip_byte(&log, 44 + 16);
    assert_refused(base.path(), &log, "flipped byte in the commit log").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unfinished_changes_are_cleaned_up_at_start() {
    let base = tempfile::tempdir().unwrap();
    base_data_dir(base.path()).await;
    let task = only_task_dir(base.path());
    let files = traj_files(&task);
    // A leftover temporary file of an interrupted trajectory write.
    let leftovers = [task.join("traj").join("00000000000000000004.traj.tmp")];
    for f in &leftovers {
        std::fs::write(f, b"TAMRMTRJ\x01").unwrap();
    }
    // Unlisted trajectory files: an insert whose pool.json commit never happened (valid
    // content) and a superseded one (garbage).
    let unlisted = [
        task.join("traj").join("00000000000000000004.traj"),
        task.join("traj").join("00000000000000000009.traj"),
    ];
    std::fs::copy(&files[0], &unlisted[0]).unwrap();
    std::fs::write(&unlisted[1], b"garbage").unwrap();
    // Unfinished task creation and deletion.
    let creating = base.path().join("tasks").join(".creating-x-0123");
    std::fs::create_dir_all(creating.join("traj")).unwrap();
    std::fs::write(creating.join("task.json"), b"{").unwrap();
    let deleting = base.path().join("tasks").join(".deleting-y-0123");
    std::fs::create_dir_all(deleting.join("traj")).unwrap();

    let mut p = Proc::spawn(
        &[
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--data-dir",
            base.path().to_str().unwrap(),
            "--port-file",
            base.path().join("port").to_str().unwrap(),
        ],
        &[],
    );
    let deadline = Instant::now() + Duration::from_secs(15);
    let addr = loop {
        if let Some(a) = std::fs::read_to_string(base.path().join("port"))
            .ok()
            .and_then(|s| s.trim().parse().ok())
        {
            break a;
        }
        if let Some(s) = p.child.try_wait().unwrap() {
            panic!("server exited with {s:?}:\n{}", p.stderr());
        }
        assert!(Instant::now() < deadline, "no port file");
        std::thread::sleep(Duration::from_millis(10));
    };
    let mut c = connect(addr).await;
    let pool = get_pool(&mut c, "t").await;
    let seqs: Vec<u64> = pool.trajectories.iter().map(|t| t.seq).collect();
    assert_eq!(seqs, vec![1, 2, 3]);
    assert_eq!(pool.pool_version, 3);
    // Checked before any write of the new server could overwrite them.
    let mut left: Vec<String> = Vec::new();
    for f in unlisted.iter().chain(&leftovers) {
        if f.exists() {
            left.push(f.display().to_string());
        }
    }
    for d in [&creating, &deleting] {
        if d.exists() {
            left.push(d.display().to_string());
        }
    }
    // The unfinished insert's seq is not clashed with: the next insert gets seq 4 and is
    // stored properly.
    let r = add(&mut c, "t", dtraj(&[1, 1], 9.0)).await;
    assert_eq!(r.pool_version, 4);
    assert_eq!(get_pool(&mut c, "t").await.trajectories[2].seq, 4);
    drop(c);
    p.sigterm();
    let status = p.wait(Duration::from_secs(15)).expect("exits");
    assert!(status.success(), "{}", p.stderr());
    // The state restarts cleanly (seq 4 is the new, committed one).
    let server = start_server(Some(base.path()), |_| {}).await;
    let mut c = connect(server.addr()).await;
    let pool = get_pool(&mut c, "t").await;
    assert_eq!(pool.trajectories[2].actions, vec![1, 1]);
    server.shutdown().await;
    assert!(left.is_empty(), "not cleaned up at start: {left:?}");
}

// ---------------------------------------------------------------------------------------
// Process behaviour
// ---------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_data_dir_the_server_says_state_is_in_memory_only() {
    let bin = Binary::start(&[]);
    let mut c = connect(bin.addr).await;
    create(&mut c, "t", discrete(2, 1, 1, 0, 1)).await;
    drop(c);
    let (status, stderr) = bin.terminate();
    assert!(status.success());
    assert!(
        stderr.contains("memory only"),
        "no in-memory notice at start:\n{stderr}"
    );
    // And with a data dir it does not say so.
    let dir = tempfile::tempdir().unwrap();
    let bin = Binary::start(&["--data-dir", dir.path().to_str().unwrap()]);
    let (status, stderr) = bin.terminate();
    assert!(status.success());
    assert!(!stderr.contains("memory only"), "{stderr}");
}

fn shaped(msg: Option<ShapeResponse>) -> proto::ShapedBatch {
    match msg {
        Some(ShapeResponse {
            kind: Some(shape_response::Kind::Shaped(b)),
        }) => b,
        other => panic!("expected shaped, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_finishes_the_batch_in_flight() {
    let dir = tempfile::tempdir().unwrap();
    let port_file = dir.path().join("port");
    let data = dir.path().join("data");
    let mut p = Proc::spawn(
        &[
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--port-file",
            port_file.to_str().unwrap(),
            "--data-dir",
            data.to_str().unwrap(),
        ],
        &[],
    );
    let addr = wait_port_file(&mut p, &port_file).await;
    let mut c = connect(addr).await;
    // |D| = 100 trajectories of 400 actions; 1000 envs x 60 steps = 60000 entries per
    // batch, all with the kNN term active (up to five batches: t < 300 < L_min).
    create(&mut c, "big", discrete(4, 100, 100, 0, 100)).await;
    for i in 0..100u32 {
        let acts: Vec<u32> = (0..400).map(|j| (i * 7 + j * (i % 5 + 1)) % 4).collect();
        add(&mut c, "big", dtraj(&acts, f64::from(i))).await;
    }
    let (envs, per_env) = (1000u32, 60u32);
    let b = envs * per_env;
    let big = StepBatch {
        env_ids: (0..b).map(|i| i % envs).collect(),
        actions: (0..b).map(|i| (i / 3) % 4).collect(),
        rewards: vec![0.5; b as usize],
        ..Default::default()
    };
    let (mut s, _) = Stream::open(&mut c, "big", envs).await.unwrap();
    // A first batch, timed, tells how long the one in flight will take.
    let t0 = Instant::now();
    let first = s.step(big.clone()).await.unwrap();
    let mut batch_time = t0.elapsed();
    assert_eq!(first.rewards.len(), b as usize);

    // The batch in flight: send it, then SIGTERM while the server is shaping it. If the
    // machine is so loaded that it was answered before the SIGTERM went out, try again.
    let mut attempt = 0u32;
    let (receiver, sent_at, killed_at) = loop {
        attempt += 1;
        s.send(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(big.clone())),
        })
        .await;
        let sent_at = Instant::now();
        // The stream stays open (no half-close): the receiver owns it.
        let receiver = tokio::spawn(async move {
            let first = s.recv().await;
            (first, Instant::now(), s)
        });
        // Halfway through: the server has received the batch and is shaping it.
        tokio::time::sleep(batch_time / 2).await;
        if receiver.is_finished() && attempt < 5 {
            let (first, at, back) = receiver.await.unwrap();
            assert_eq!(shaped(first.unwrap()).rewards.len(), b as usize);
            batch_time = batch_time.min(at - sent_at);
            s = back;
            continue;
        }
        let killed_at = Instant::now();
        p.sigterm();
        break (receiver, sent_at, killed_at);
    };
    // Once the server has logged that it is shutting down, it accepts no new connections.
    // (A liveness bound, generous for a loaded CI machine.)
    let deadline = Instant::now() + Duration::from_secs(30);
    while !p.stderr().contains("shutting down") {
        assert!(
            Instant::now() < deadline,
            "no shutdown log:\n{}",
            p.stderr()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let fresh = async {
        let mut c = tamrm::proto::shaping_client::ShapingClient::connect(format!("http://{addr}"))
            .await
            .ok()?;
        c.list_tasks(proto::ListTasksRequest {}).await.ok()
    };
    let late = tokio::time::timeout(Duration::from_secs(2), fresh).await;
    assert!(
        !matches!(late, Ok(Some(_))),
        "a new connection was served after SIGTERM"
    );

    let (first, answered_at, mut s) = receiver.await.unwrap();
    let second = match &first {
        Ok(_) => s.recv().await,
        Err(e) => Err(e.clone()),
    };
    let status = p.wait(Duration::from_secs(20));
    let stderr = p.stderr();
    let first = first.unwrap_or_else(|e| {
        panic!(
            "the batch in flight is not answered: {e:?}\nserver exit {status:?}, stderr:\n{stderr}"
        )
    });
    let out = shaped(first);
    assert_eq!(out.rewards.len(), b as usize, "answered completely");
    assert_eq!(out.steps.len(), b as usize);
    assert!(out.knn_active.iter().all(|&a| a));
    assert_eq!(
        out.steps[0],
        attempt * per_env,
        "batch {} of each env",
        attempt + 1
    );
    assert_eq!(out.steps[b as usize - 1], (attempt + 1) * per_env - 1);
    eprintln!(
        "a batch takes {batch_time:?}; the one in flight was answered {:?} after it was sent, {:?} after SIGTERM",
        answered_at - sent_at,
        answered_at.saturating_duration_since(killed_at)
    );
    assert!(
        answered_at > killed_at,
        "the batch was not in flight at SIGTERM; make it bigger"
    );
    let e = second.expect_err("the stream then ends with UNAVAILABLE");
    assert_eq!(e.code(), Code::Unavailable, "{e:?}\n{stderr}");
    let status = status.expect("exits after SIGTERM");
    assert!(status.success(), "{status:?}\n{stderr}");
    drop(c);
    // Nothing listens any more.
    assert!(std::net::TcpStream::connect(addr).is_err());
}

async fn wait_port_file(p: &mut Proc, port_file: &Path) -> std::net::SocketAddr {
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        if let Some(a) = std::fs::read_to_string(port_file)
            .ok()
            .and_then(|s| s.trim().parse().ok())
        {
            return a;
        }
        if let Some(s) = p.child.try_wait().unwrap() {
            panic!("server exited with {s:?}:\n{}", p.stderr());
        }
        assert!(Instant::now() < deadline, "no port file");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idle_open_stream_does_not_delay_exit() {
    let bin = Binary::start(&[]);
    let mut c = connect(bin.addr).await;
    create(&mut c, "t", discrete(2, 1, 1, 0, 1)).await;
    let (mut s, _) = Stream::open(&mut c, "t", 1).await.unwrap();
    s.step(batch(&[0], &[0.0], &[false])).await.unwrap();
    let t0 = Instant::now();
    let (status, stderr) = bin.terminate();
    assert!(status.success(), "{stderr}");
    // Well below the 30 s grace period the server would wait for a stream that
    // kept it from exiting; generous for a loaded machine.
    assert!(
        t0.elapsed() < Duration::from_secs(15),
        "exit took {:?} with an idle stream open",
        t0.elapsed()
    );
    match s.recv().await {
        Err(e) => assert_eq!(e.code(), Code::Unavailable, "{e:?}"),
        Ok(m) => panic!("expected UNAVAILABLE, got {m:?}"),
    }
}

// ---------------------------------------------------------------------------------------
// Settings sources of the binary
// ---------------------------------------------------------------------------------------

async fn wait_listening(p: &mut Proc, addr: std::net::SocketAddr) -> Client {
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        if let Some(s) = p.child.try_wait().unwrap() {
            panic!("server exited with {s:?}:\n{}", p.stderr());
        }
        if std::net::TcpStream::connect(addr).is_ok() {
            return connect(addr).await;
        }
        assert!(Instant::now() < deadline, "not listening on {addr}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn environment_variables_set_listen_and_data_dir() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("env-data");
    let port = free_port();
    let addr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let mut p = Proc::spawn(
        &["serve"],
        &[
            ("TAMRM_LISTEN", &addr.to_string()),
            ("TAMRM_DATA_DIR", data.to_str().unwrap()),
            ("TAMRM_MAX_TASKS", "1"),
        ],
    );
    let mut c = wait_listening(&mut p, addr).await;
    create(&mut c, "from-env", discrete(2, 1, 1, 0, 1)).await;
    let e = c
        .create_task(proto::CreateTaskRequest {
            task_id: "second".into(),
            config: Some(discrete(2, 1, 1, 0, 1)),
        })
        .await
        .unwrap_err();
    assert_eq!(
        e.code(),
        Code::ResourceExhausted,
        "TAMRM_MAX_TASKS=1: {e:?}"
    );
    drop(c);
    p.sigterm();
    assert!(p.wait(Duration::from_secs(15)).expect("exits").success());
    assert!(data.join("tamrm.json").exists(), "TAMRM_DATA_DIR was used");
    // Flags beat the environment: with TAMRM_LISTEN naming a taken port, --listen
    // 127.0.0.1:0 still starts; --data-dir finds the task created above.
    let taken = std::net::TcpListener::bind(addr).unwrap();
    let port_file = dir.path().join("port");
    let mut p = Proc::spawn(
        &[
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--port-file",
            port_file.to_str().unwrap(),
            "--data-dir",
            data.to_str().unwrap(),
        ],
        &[
            ("TAMRM_LISTEN", &addr.to_string()),
            ("TAMRM_DATA_DIR", "/nonexistent/never/used"),
        ],
    );
    let deadline = Instant::now() + Duration::from_secs(15);
    let bound: std::net::SocketAddr = loop {
        if let Some(a) = std::fs::read_to_string(&port_file)
            .ok()
            .and_then(|s| s.trim().parse().ok())
        {
            break a;
        }
        if let Some(s) = p.child.try_wait().unwrap() {
            panic!("server exited with {s:?}:\n{}", p.stderr());
        }
        assert!(Instant::now() < deadline, "no port file");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    assert_ne!(bound.port(), port);
    let mut c = connect(bound).await;
    assert_eq!(get_task(&mut c, "from-env").await.task_id, "from-env");
    drop(c);
    drop(taken);
    p.sigterm();
    assert!(p.wait(Duration::from_secs(15)).expect("exits").success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn config_file_sets_listen_data_dir_and_limits() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("file-data");
    let port = free_port();
    let addr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let file = dir.path().join("tamrm.toml");
    std::fs::write(
        &file,
        format!(
            "listen = \"{addr}\"\ndata_dir = {:?}\n\n[limits]\nmax_tasks = 2\nmax_batch_entries = 4\nmax_envs_per_stream = 8\nmax_pool_capacity = 50\n",
            data.to_str().unwrap()
        ),
    )
    .unwrap();
    for via_env in [false, true] {
        let file_s = file.to_str().unwrap();
        let mut p = if via_env {
            Proc::spawn(&["serve"], &[("TAMRM_CONFIG", file_s)])
        } else {
            Proc::spawn(&["serve", "--config", file_s], &[])
        };
        let mut c = wait_listening(&mut p, addr).await;
        if !via_env {
            create(&mut c, "a", discrete(2, 50, 1, 0, 1)).await;
            let e = c
                .create_task(proto::CreateTaskRequest {
                    task_id: "big".into(),
                    config: Some(discrete(2, 51, 1, 0, 1)),
                })
                .await
                .unwrap_err();
            assert_eq!(
                e.code(),
                Code::ResourceExhausted,
                "max_pool_capacity: {e:?}"
            );
            create(&mut c, "b", discrete(2, 1, 1, 0, 1)).await;
        }
        // The data dir from the file: both tasks are there on the second start.
        let e = c
            .create_task(proto::CreateTaskRequest {
                task_id: "c".into(),
                config: Some(discrete(2, 1, 1, 0, 1)),
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::ResourceExhausted, "max_tasks = 2: {e:?}");
        assert_eq!(get_task(&mut c, "a").await.task_id, "a");
        let e = Stream::open(&mut c, "a", 9).await.err().unwrap();
        assert_eq!(e.code(), Code::ResourceExhausted, "max_envs_per_stream");
        let (mut s, _) = Stream::open(&mut c, "a", 8).await.unwrap();
        s.step(batch(&[0, 1, 0, 1], &[0.0; 4], &[false; 4]))
            .await
            .unwrap();
        let e = s
            .step(batch(&[0, 1, 0, 1, 0], &[0.0; 5], &[false; 5]))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::ResourceExhausted, "max_batch_entries");
        drop(s);
        drop(c);
        p.sigterm();
        assert!(p.wait(Duration::from_secs(15)).expect("exits").success());
        assert!(data.join("tamrm.json").exists());
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn listen_port_zero_picks_a_free_port() {
    let a = Binary::start(&[]);
    let b = Binary::start(&[]);
    assert_ne!(a.addr.port(), 0);
    assert_ne!(a.addr.port(), b.addr.port());
    for bin in [&a, &b] {
        let mut c = connect(bin.addr).await;
        c.list_tasks(proto::ListTasksRequest {}).await.unwrap();
    }
    assert!(a.terminate().0.success());
    assert!(b.terminate().0.success());
}

/// Interrupted atomic writes of the JSON files leave `<name>.tmp` next to them; the server
/// starts with the committed state and removes the leftovers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leftover_tmp_files_of_json_writes_are_removed_at_start() {
    let base = tempfile::tempdir().unwrap();
    base_data_dir(base.path()).await;
    let task = only_task_dir(base.path());
    let leftovers = [
        task.join("pool.json.tmp"),
        task.join("task.json.tmp"),
        base.path().join("tamrm.json.tmp"),
    ];
    for f in &leftovers {
        std::fs::write(f, b"{\"format\": 1, \"half-writ").unwrap();
    }
    let server = start_server(Some(base.path()), |_| {}).await;
    let mut c = connect(server.addr()).await;
    let pool = get_pool(&mut c, "t").await;
    assert_eq!(pool.trajectories.len(), 3, "the committed state is used");
    let left: Vec<_> = leftovers.iter().filter(|f| f.exists()).collect();
    server.shutdown().await;
    assert!(left.is_empty(), "not cleaned up at start: {left:?}");
}
