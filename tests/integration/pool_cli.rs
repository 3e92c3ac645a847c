//! `tamrm tasks` and `tamrm pool` (the real binary) against real servers on 127.0.0.1:0:
//! a pool exported from a data-dir server and imported into a Redis-backed one shapes
//! every step as the original did; an import refuses what docs/storage.md says it
//! refuses; the tables, the JSON and the API key.

use std::process::{Command, Output};

use crate::common::{
    connect, create, get_pool, get_task, start_server, Client, RedisServer, Stream,
};
use tamrm::proto;

/// `tamrm ARGS`, without the clients' variables of this environment.
fn tamrm(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .args(args)
        .env_remove("TAMRM_ADDRESS")
        .env_remove("TAMRM_API_KEY")
        .output()
        .expect("run tamrm")
}

/// `tamrm ARGS` off the async runtime.
async fn run(args: &[&str]) -> Output {
    let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
    tokio::task::spawn_blocking(move || tamrm(&args.iter().map(String::as_str).collect::<Vec<_>>()))
        .await
        .unwrap()
}

/// The command failed with exit status `code` and said `needle`.
#[track_caller]
fn refused(out: &Output, code: i32, needle: &str) {
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(code), "{err}");
    assert!(err.contains(needle), "expected {needle:?} in: {err}");
}

/// The command succeeded.
#[track_caller]
fn done(out: &Output) {
    assert!(out.status.success(), "{}", text(&out.stderr));
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A small deterministic generator (an LCG), so a failing case can be replayed.
struct Rng(u64);
impl Rng {
    fn next(&mut self, m: u64) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) % m.max(1)
    }
    fn real(&mut self) -> f64 {
        self.next(1 << 24) as f64 / (1u64 << 20) as f64 - 8.0
    }
}

/// A random config: discrete (`dim` 0) or continuous.
fn random_config(r: &mut Rng, dim: u32) -> proto::TaskConfig {
    let capacity = 1 + r.next(8) as u32;
    proto::TaskConfig {
        num_actions: if dim == 0 { 2 + r.next(4) as u32 } else { 0 },
        action_dim: dim,
        pool_capacity: Some(capacity),
        k: Some(1 + r.next(u64::from(capacity)) as u32),
        start_step: Some(r.next(3) as u32),
        min_pool_size: Some(1 + r.next(u64::from(capacity)) as u32),
        alpha: Some(r.real()),
        beta: Some(r.real() / 4.0),
        gamma: Some(r.next(1001) as f64 / 1000.0),
        max_trajectory_len: Some(1 + r.next(12) as u32),
        gate_potential: Some(r.next(2) == 1),
        require_score_spread: Some(r.next(2) == 1),
    }
}

fn random_trajectory(r: &mut Rng, c: &proto::TaskConfig) -> proto::Trajectory {
    let len = 1 + r.next(u64::from(c.max_trajectory_len.unwrap()) + 2) as usize;
    let score = if r.next(4) == 0 { 1.0 } else { r.real() };
    if c.action_dim == 0 {
        let actions = (0..len).map(|_| r.next(u64::from(c.num_actions)) as u32);
        crate::common::dtraj(&actions.collect::<Vec<_>>(), score)
    } else {
        let n = len * c.action_dim as usize;
        let v: Vec<f32> = (0..n).map(|_| (r.real() / 3.0) as f32 + 1e-7).collect();
        crate::common::ctraj(&v, score)
    }
}

/// One batch of steps of `envs` environments.
fn random_batch(r: &mut Rng, c: &proto::TaskConfig, envs: usize) -> proto::StepBatch {
    let mut b = proto::StepBatch {
        rewards: (0..envs).map(|_| r.real()).collect(),
        terminated: (0..envs).map(|_| r.next(5) == 0).collect(),
        values: (0..envs).map(|_| r.real() as f32).collect(),
        next_values: (0..envs).map(|_| r.real() as f32).collect(),
        ..Default::default()
    };
    if c.action_dim == 0 {
        b.actions = (0..envs)
            .map(|_| r.next(u64::from(c.num_actions)) as u32)
            .collect();
    } else {
        let n = envs * c.action_dim as usize;
        b.action_vectors = (0..n).map(|_| (r.real() / 3.0) as f32).collect();
    }
    b
}

/// The shaped answers of `batches` on `task`, as bits.
async fn shape_bits(c: &mut Client, task: &str, batches: &[proto::StepBatch]) -> Vec<Vec<u64>> {
    let (mut stream, _) = Stream::open(c, task, 2).await.expect("open");
    let mut out = Vec::new();
    for b in batches {
        let s = stream.step(b.clone()).await.expect("step");
        let mut bits: Vec<u64> = s.rewards.iter().map(|x| x.to_bits()).collect();
        bits.extend(s.knn_rewards.iter().map(|x| x.to_bits()));
        bits.extend(s.potentials.iter().map(|x| x.to_bits()));
        bits.extend(s.knn_active.iter().map(|x| u64::from(*x)));
        out.push(bits);
    }
    out
}

fn without_seqs(p: &proto::Pool) -> Vec<proto::Trajectory> {
    let mut t = p.trajectories.clone();
    t.iter_mut().for_each(|t| t.seq = 0);
    t
}

#[tokio::test(flavor = "multi_thread")]
async fn an_exported_pool_imported_into_a_redis_server_shapes_every_step_as_the_original() {
    let data = tempfile::tempdir().unwrap();
    let redis = RedisServer::start();
    let url = redis.url();
    let from = start_server(Some(data.path()), |_| {}).await;
    let to = start_server(None, move |s| s.store = Some(url)).await;
    let (mut a, mut b) = (connect(from.addr()).await, connect(to.addr()).await);
    let files = tempfile::tempdir().unwrap();
    for case in 0..8u64 {
        let mut r = Rng(case * 7919 + 1);
        let dim = if case % 2 == 0 {
            0
        } else {
            1 + r.next(3) as u32
        };
        let config = random_config(&mut r, dim);
        let id = format!("case-{case}");
        create(&mut a, &id, config).await;
        for _ in 0..r.next(20) {
            crate::common::add(&mut a, &id, random_trajectory(&mut r, &config)).await;
        }
        let file = files.path().join(format!("{id}.jsonl"));
        let (f, s) = (file.to_str().unwrap(), from.addr().to_string());
        done(&run(&["pool", "export", &id, "-o", f, "--server", &s]).await);
        done(&run(&["pool", "import", f, "--server", &to.addr().to_string()]).await);
        let (pa, pb) = (get_pool(&mut a, &id).await, get_pool(&mut b, &id).await);
        assert_eq!(
            without_seqs(&pa),
            without_seqs(&pb),
            "{id}: the pools differ"
        );
        let (ta, tb) = (get_task(&mut a, &id).await, get_task(&mut b, &id).await);
        assert_eq!(ta.config, tb.config, "{id}");
        let batches: Vec<_> = (0..30).map(|_| random_batch(&mut r, &config, 2)).collect();
        let (sa, sb) = (
            shape_bits(&mut a, &id, &batches).await,
            shape_bits(&mut b, &id, &batches).await,
        );
        assert_eq!(sa, sb, "{id}: shaped differently after the import");
        assert!(
            sa.iter().flatten().any(|x| *x != 0),
            "{id}: nothing shaped: is the test blind?"
        );
    }
    from.shutdown().await;
    to.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn an_import_refuses_another_config_a_full_pool_and_a_bad_file_unless_told() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let addr = server.addr().to_string();
    let fixtures = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/clients/python/tests/fixtures/pool"
    );
    let good = format!("{fixtures}/discrete.jsonl");
    let import = |extra: &[&str]| {
        let mut v = vec!["pool", "import", good.as_str(), "--server", addr.as_str()];
        v.extend(extra);
        v.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let run_import = |extra: &[&str]| {
        let args = import(extra);
        async move { run(&args.iter().map(String::as_str).collect::<Vec<_>>()).await }
    };
    // A bad file: exit 2, the line named, nothing created.
    let bad = format!("{fixtures}/bad-action-range.jsonl");
    let out = run(&["pool", "import", &bad, "--server", &addr]).await;
    refused(&out, 2, "bad-action-range.jsonl, line 3: ");
    assert!(c
        .list_tasks(proto::ListTasksRequest {})
        .await
        .unwrap()
        .into_inner()
        .tasks
        .is_empty());
    // Into a new id, then again: the pool is not empty.
    done(&run_import(&["--task", "copy"]).await);
    assert_eq!(get_task(&mut c, "copy").await.stats.unwrap().pool_size, 4);
    let out = run_import(&["--task", "copy"]).await;
    refused(&out, 1, "already holds 4 trajectories");
    done(&run_import(&["--task", "copy", "--replace"]).await);
    let stats = get_task(&mut c, "copy").await.stats.unwrap();
    assert_eq!(
        (stats.pool_size, stats.pool_version),
        (4, 9),
        "reset (1) then 4 adds"
    );
    // Another config: refused, naming the field; replaced when told.
    let mut other = crate::common::discrete(4, 4, 2, 1, 2);
    other.alpha = Some(0.75);
    create(&mut c, "fixture.discrete", other).await;
    let out = run_import(&[]).await;
    refused(&out, 1, "exists with another config");
    refused(&out, 1, "alpha: task 0.75, file 0.5");
    assert_eq!(
        get_task(&mut c, "fixture.discrete")
            .await
            .stats
            .unwrap()
            .pool_size,
        0
    );
    done(&run_import(&["--replace"]).await);
    let task = get_task(&mut c, "fixture.discrete").await;
    assert_eq!(task.config.unwrap().alpha, Some(0.5));
    // Export to standard output is the file -o writes.
    let out = run(&["pool", "export", "copy", "--server", &addr]).await;
    done(&out);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.jsonl");
    let p = path.to_str().unwrap().to_string();
    done(&run(&["pool", "export", "copy", "-o", &p, "--server", &addr]).await);
    assert_eq!(std::fs::read(&path).unwrap(), out.stdout);
    assert!(text(&out.stdout)
        .starts_with("{\"format\": \"tamrm-pool\", \"version\": 1, \"task_id\": \"copy\""));
    // An unknown task: the server's answer, exit 1.
    let out = run(&["pool", "export", "nope", "--server", &addr]).await;
    refused(&out, 1, "GetTask on");
    refused(&out, 1, "nope");
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn tasks_list_and_get_show_a_table_text_and_json_with_the_api_key() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.toml");
    std::fs::write(
        &keys,
        format!(
            "[[keys]]\ntenant = \"a\"\nrole = \"reader\"\nsha256 = \"{}\"\n[[keys]]\ntenant = \"a\"\nrole = \"writer\"\nsha256 = \"{}\"\n",
            tamrm::auth::hash_key(b"reader-key"),
            tamrm::auth::hash_key(b"writer-key")
        ),
    )
    .unwrap();
    let server = start_server(None, |s| s.api_keys = Some(keys)).await;
    let addr = server.addr().to_string();
    let fixtures = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/clients/python/tests/fixtures/pool"
    );
    let with = |key: &str, args: &[&str]| {
        let mut v: Vec<String> = args.iter().map(|s| s.to_string()).collect();
        v.extend(["--server", &addr, "--api-key", key].map(String::from));
        async move { run(&v.iter().map(String::as_str).collect::<Vec<_>>()).await }
    };
    refused(
        &run(&["tasks", "list", "--server", &addr]).await,
        1,
        "ListTasks",
    );
    let file = format!("{fixtures}/continuous.jsonl");
    let out = with("reader-key", &["pool", "import", &file]).await;
    refused(&out, 1, "needs role");
    done(&with("writer-key", &["pool", "import", &file]).await);
    let out = with("reader-key", &["tasks", "list"]).await;
    done(&out);
    let table = text(&out.stdout);
    let lines: Vec<&str> = table.lines().collect();
    assert!(
        lines[0].starts_with("TASK") && lines[0].contains("BEST"),
        "{table}"
    );
    assert!(
        lines[1].starts_with("fixture.continuous  continuous 3  3/3"),
        "{table}"
    );
    let out = with("reader-key", &["tasks", "list", "--json"]).await;
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let task = &json["tasks"][0];
    assert_eq!(task["task_id"], "fixture.continuous");
    assert_eq!(task["config"]["action_dim"], 3);
    assert_eq!(task["stats"]["pool_size"], 3);
    assert_eq!(
        task["stats"]["best_score"].as_f64().unwrap().to_bits(),
        0x419d6f34547df3b6
    );
    let out = with("reader-key", &["tasks", "get", "fixture.continuous"]).await;
    let shown = text(&out.stdout);
    assert!(
        shown.contains("pool_capacity") && shown.contains("pool_size"),
        "{shown}"
    );
    let out = with(
        "reader-key",
        &["tasks", "get", "fixture.continuous", "--json"],
    )
    .await;
    let one: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(&one, task);
    server.shutdown().await;
}

#[test]
fn completions_are_printed_for_each_shell_and_an_unknown_shell_is_refused() {
    let out = tamrm(&["completions", "bash"]);
    assert!(out.status.success());
    let script = text(&out.stdout);
    assert!(
        script.contains("tamrm") && script.contains("import"),
        "{script}"
    );
    let out = tamrm(&["completions", "tcsh"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("tcsh"));
}
