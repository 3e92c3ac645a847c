//! SPEC §8, end to end: every malformed request gets a gRPC status (never a crash, a hang
//! or a changed pool), the status names the offending field, a rejected `StepBatch`
//! changes no episode and no pool, and a failing stream affects no other stream.
//!
//! Everything talks to a real in-process server over a real socket through the generated
//! tonic client. After each rejection the tests check that the task's pool and counters
//! are exactly what they were, and that a "witness" stream opened before the failure goes
//! on shaping with the expected numbers.
//!
//! Readings where SPEC §8 leaves room:
//! - "naming the field": the status message contains the proto path of the field
//!   (`steps.actions[1]`, `config.k`, `trajectory.score`, `open.task_id`, `task_id`);
//!   ALREADY_EXISTS names each differing field as `<field>:`; NOT_FOUND names the task
//!   id; RESOURCE_EXHAUSTED names the limit (`max_batch_entries`, ...).
//! - B is `len(rewards)`; a batch without rewards but with other columns is a length
//!   error whose message mentions `rewards`.
//! - A stream the client closes before sending anything is not a "missing Open": it
//!   just ends (no status, no change).
//! - An invalid config for an existing id is INVALID_ARGUMENT (validation comes first),
//!   not ALREADY_EXISTS.
//! - `max_message_bytes` is "either direction": an answer that cannot be sent under it
//!   (GetPool, ShapedBatch) must be RESOURCE_EXHAUSTED, and a batch whose answer cannot
//!   be sent must be refused before it is applied. The two tests at the end of the file
//!   check this and fail against the server as of this commit.

use crate::common::*;

use std::collections::HashMap;
use std::future::Future;
use std::time::Duration;

use tamrm::proto::{
    self, shape_request, shape_response, AddTrajectoryRequest, CreateTaskRequest,
    DeleteTaskRequest, GetPoolRequest, GetTaskRequest, ListTasksRequest, ResetPoolRequest,
    ShapeRequest, ShapedBatch, StepBatch, TaskConfig, TaskStats, Trajectory,
};
use tonic::{Code, Status};

/// Every wait on the server is bounded: a hang is a failure, not a stuck test run.
const WAIT: Duration = Duration::from_secs(10);

const BAD_F64: [(&str, f64); 3] = [
    ("NaN", f64::NAN),
    ("+inf", f64::INFINITY),
    ("-inf", f64::NEG_INFINITY),
];
const BAD_F32: [(&str, f32); 3] = [
    ("NaN", f32::NAN),
    ("+inf", f32::INFINITY),
    ("-inf", f32::NEG_INFINITY),
];

async fn bounded<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(WAIT, f)
        .await
        .unwrap_or_else(|_| panic!("{what}: no answer within {WAIT:?} (server hung)"))
}

/// Asserts that `r` failed with `code` and a message containing `field`.
#[track_caller]
fn expect_status<T: std::fmt::Debug>(what: &str, r: Result<T, Status>, code: Code, field: &str) {
    match r {
        Ok(v) => panic!("{what}: expected {code:?} naming {field:?}, got Ok({v:?})"),
        Err(s) => {
            assert_eq!(
                s.code(),
                code,
                "{what}: wrong status code (message {:?})",
                s.message()
            );
            assert!(
                s.message().contains(field),
                "{what}: status message {:?} does not name {field:?}",
                s.message()
            );
        }
    }
}

fn steps(b: StepBatch) -> ShapeRequest {
    ShapeRequest {
        kind: Some(shape_request::Kind::Steps(b)),
    }
}

fn open_msg(task_id: &str, num_envs: u32) -> ShapeRequest {
    ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task_id.into(),
            num_envs,
            ..Default::default()
        })),
    }
}

async fn open(c: &mut Client, id: &str, num_envs: u32) -> Result<(Stream, proto::Task), Status> {
    bounded(&format!("open {id}"), Stream::open(c, id, num_envs)).await
}

/// The next answer of a stream: `Ok(shaped)`, or the status the stream ended with.
/// A stream that ends without a status or answers something else fails the test.
async fn recv_shaped(what: &str, s: &mut Stream) -> Result<ShapedBatch, Status> {
    match bounded(what, s.recv()).await? {
        Some(proto::ShapeResponse {
            kind: Some(shape_response::Kind::Shaped(b)),
        }) => Ok(b),
        None => panic!("{what}: stream ended without a status"),
        other => panic!("{what}: expected shaped or a status, got {other:?}"),
    }
}

async fn step(what: &str, s: &mut Stream, b: StepBatch) -> Result<ShapedBatch, Status> {
    s.send(steps(b)).await;
    recv_shaped(what, s).await
}

/// After a stream failed: it answers nothing more, even to a valid batch.
async fn assert_stream_over(what: &str, s: &mut Stream, valid: StepBatch) {
    s.send(steps(valid)).await;
    let next = bounded(what, s.recv()).await;
    assert!(
        !matches!(next, Ok(Some(_))),
        "{what}: the stream answered after its error status: {next:?}"
    );
}

async fn try_add(
    c: &mut Client,
    id: &str,
    t: Trajectory,
) -> Result<proto::AddTrajectoryResponse, Status> {
    c.add_trajectory(AddTrajectoryRequest {
        task_id: id.into(),
        trajectory: Some(t),
    })
    .await
    .map(|r| r.into_inner())
}

/// What a rejected request must not change: the pool (with its version) and the
/// counters. `open_streams` is left out (it moves as the test opens streams).
#[derive(Debug, PartialEq)]
struct State {
    pool: proto::Pool,
    stats: TaskStats,
}

async fn state(c: &mut Client, id: &str) -> State {
    let pool = c
        .get_pool(GetPoolRequest { task_id: id.into() })
        .await
        .unwrap_or_else(|e| panic!("get_pool {id}: {e}"))
        .into_inner();
    let mut stats = get_task(c, id).await.stats.expect("stats");
    assert_eq!(stats.pool_version, pool.pool_version);
    stats.open_streams = 0;
    State { pool, stats }
}

async fn assert_serving(addr: std::net::SocketAddr) {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{health_client::HealthClient, HealthCheckRequest};
    let channel = tonic::transport::Channel::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .expect("connect for health check");
    let r = bounded(
        "health check",
        HealthClient::new(channel).check(HealthCheckRequest {
            service: "tamrm.v1.Shaping".into(),
        }),
    )
    .await
    .expect("health check")
    .into_inner();
    assert_eq!(r.status, ServingStatus::Serving as i32);
}

#[track_caller]
fn close(what: &str, got: f64, want: f64) {
    assert!(
        (got - want).abs() <= 1e-9 * want.abs().max(1.0),
        "{what}: got {got}, want {want}"
    );
}

/// r(t) when the current prefix matches the best-scored stored trajectory exactly:
/// P = 1 on it, x = 1, so f = 1.
fn knn_exact_best() -> f64 {
    1f64.exp() - 0.5f64.exp()
}

/// A stream opened before the failures, on the same task, that must keep shaping
/// normally: one env, always action 0 (or the zero vector), R = 0.5, V(s) = 1,
/// V(s') = 2, never ending its episode. Default alpha = beta = 0.8, gamma = 0.99.
struct Witness {
    s: Stream,
    dim: usize,
    t: u32,
    /// Whether the pool holds a best trajectory of all-zero actions covering every step
    /// (then r(t) = e - e^0.5), or is such that the kNN term is inactive.
    knn: bool,
}

impl Witness {
    async fn open(c: &mut Client, id: &str, dim: usize, knn: bool) -> Witness {
        let (s, _) = open(c, id, 1).await.expect("open witness stream");
        Witness { s, dim, t: 0, knn }
    }

    fn batch(&self) -> StepBatch {
        StepBatch {
            actions: if self.dim == 0 { vec![0] } else { vec![] },
            action_vectors: vec![0.0; self.dim],
            rewards: vec![0.5],
            values: vec![1.0],
            next_values: vec![2.0],
            ..Default::default()
        }
    }

    async fn check(&mut self, what: &str, pool_version: u64) {
        let what = format!("{what}: witness stream");
        let b = self.batch();
        let out = step(&what, &mut self.s, b)
            .await
            .unwrap_or_else(|e| panic!("{what} failed: {e:?}"));
        assert_eq!(out.steps, vec![self.t], "{what}: step index");
        assert_eq!(out.knn_active, vec![self.knn], "{what}: knn_active");
        assert_eq!(out.pool_version, pool_version, "{what}: pool_version");
        let knn = if self.knn { knn_exact_best() } else { 0.0 };
        let f = 0.99 * 2.0 - 1.0;
        close(&format!("{what} knn_rewards"), out.knn_rewards[0], knn);
        close(&format!("{what} potentials"), out.potentials[0], f);
        close(
            &format!("{what} rewards"),
            out.rewards[0],
            0.5 + 0.8 * knn + 0.8 * f,
        );
        self.t += 1;
    }
}

struct Case {
    name: String,
    batch: StepBatch,
    code: Code,
    field: String,
}

fn case(name: impl Into<String>, batch: StepBatch, code: Code, field: impl Into<String>) -> Case {
    Case {
        name: name.into(),
        batch,
        code,
        field: field.into(),
    }
}

/// Runs each malformed batch on a fresh stream of `num_envs` envs that has already shaped
/// `warmup` (so its episodes are mid-way), and checks: the status, that the stream is
/// over, that nothing changed (pool, version, counters — also as seen in the `opened`
/// answer of the fresh stream opened after the failure, which then runs the next case),
/// and that the witness stream goes on normally.
async fn run_cases(
    c: &mut Client,
    task: &str,
    num_envs: u32,
    warmup: &StepBatch,
    cases: Vec<Case>,
    witness: &mut Witness,
) {
    let (mut a, _) = open(c, task, num_envs).await.expect("open stream");
    for Case {
        name,
        batch,
        code,
        field,
    } in cases
    {
        let what = format!("[{task}] {name}");
        step(&format!("{what}: warm-up"), &mut a, warmup.clone())
            .await
            .unwrap_or_else(|e| panic!("{what}: warm-up batch rejected: {e:?}"));
        let before = state(c, task).await;

        let r = step(&what, &mut a, batch).await;
        expect_status(&what, r, code, &field);
        assert_stream_over(&what, &mut a, warmup.clone()).await;

        assert_eq!(
            state(c, task).await,
            before,
            "{what}: the rejected batch changed the task"
        );
        let (fresh, opened) = open(c, task, num_envs).await.expect("open fresh stream");
        let mut seen = opened.stats.expect("stats");
        assert_eq!(
            seen.open_streams, 2,
            "{what}: open_streams should count the witness and the fresh stream"
        );
        seen.open_streams = 0;
        assert_eq!(
            seen, before.stats,
            "{what}: a fresh stream sees changed stats"
        );
        a = fresh;
        witness.check(&what, before.pool.pool_version).await;
    }
}

/// Creates `id` and seeds its pool with a best trajectory of 200 zero actions (score 10)
/// and a worst one of 200 non-zero actions (score 0); capacity 4, so an episode end
/// applied by mistake would be inserted and show up in the pool.
async fn seeded_task(c: &mut Client, id: &str, num_actions: u32, action_dim: u32) {
    let config = TaskConfig {
        num_actions,
        action_dim,
        ..discrete(0, 4, 2, 0, 1)
    };
    create(c, id, config).await;
    let (best, worst) = if action_dim == 0 {
        (dtraj(&[0; 200], 10.0), dtraj(&[1; 200], 0.0))
    } else {
        let m = action_dim as usize;
        (
            ctraj(&vec![0.0; 200 * m], 10.0),
            ctraj(&vec![1.0; 200 * m], 0.0),
        )
    };
    assert!(try_add(c, id, best).await.unwrap().inserted);
    assert!(try_add(c, id, worst).await.unwrap().inserted);
}

/// A valid batch for the discrete task (n = 3, 2 envs) that ends env 0's episode with a
/// score: every malformed case below is this plus one defect, mostly in entry 1, so a
/// server applying entry 0 before validating entry 1 would insert into the pool.
fn discrete_base() -> StepBatch {
    StepBatch {
        env_ids: vec![0, 1],
        actions: vec![1, 2],
        rewards: vec![1.0, 2.0],
        terminated: vec![true, false],
        truncated: vec![false, false],
        episode_scores: HashMap::from([(0, 7.0)]),
        ..Default::default()
    }
}

fn with_values(mut b: StepBatch) -> StepBatch {
    let n = b.rewards.len();
    b.values = vec![0.5; n];
    b.next_values = vec![0.25; n];
    b
}

fn with_q(mut b: StepBatch) -> StepBatch {
    let n = b.rewards.len() * 3;
    b.q_values = vec![0.5; n];
    b.next_q_values = vec![0.25; n];
    b
}

#[rustfmt::skip]
fn discrete_cases() -> Vec<Case> {
    use Code::InvalidArgument as Inv;
    let b = discrete_base;
    let mut cases = vec![
        case("env_ids shorter than rewards", StepBatch { env_ids: vec![0], ..b() }, Inv, "steps.env_ids"),
        case("env_ids longer than rewards", StepBatch { env_ids: vec![0, 1, 1], ..b() }, Inv, "steps.env_ids"),
        case("env id == num_envs", StepBatch { env_ids: vec![0, 2], ..b() }, Inv, "steps.env_ids[1]"),
        case("env id u32::MAX", StepBatch { env_ids: vec![0, u32::MAX], ..b() }, Inv, "steps.env_ids[1]"),
        case("empty env_ids with B > num_envs", StepBatch { env_ids: vec![], actions: vec![1, 2, 0], rewards: vec![1.0, 2.0, 3.0], terminated: vec![true, false, false], truncated: vec![], ..b() }, Inv, "steps.env_ids"),
        case("rewards missing (B = 0, other columns not)", StepBatch { rewards: vec![], episode_scores: HashMap::new(), ..b() }, Inv, "rewards"),
        case("actions shorter than rewards", StepBatch { actions: vec![1], ..b() }, Inv, "steps.actions"),
        case("actions missing", StepBatch { actions: vec![], ..b() }, Inv, "steps.actions"),
        case("actions longer than rewards", StepBatch { actions: vec![1, 2, 0], ..b() }, Inv, "steps.actions"),
        case("action == num_actions", StepBatch { actions: vec![1, 3], ..b() }, Inv, "steps.actions[1]"),
        case("action u32::MAX", StepBatch { actions: vec![1, u32::MAX], ..b() }, Inv, "steps.actions[1]"),
        case("action_vectors on a discrete task", StepBatch { action_vectors: vec![0.0; 2], ..b() }, Inv, "steps.action_vectors"),
        case("terminated shorter than rewards", StepBatch { terminated: vec![true], ..b() }, Inv, "steps.terminated"),
        case("terminated longer than rewards", StepBatch { terminated: vec![true, false, false], ..b() }, Inv, "steps.terminated"),
        case("truncated shorter than rewards", StepBatch { truncated: vec![false], ..b() }, Inv, "steps.truncated"),
        case("truncated longer than rewards", StepBatch { truncated: vec![false; 3], ..b() }, Inv, "steps.truncated"),
        case("values without next_values", StepBatch { values: vec![0.5; 2], ..b() }, Inv, "steps.next_values"),
        case("next_values without values", StepBatch { next_values: vec![0.5; 2], ..b() }, Inv, "steps.values"),
        case("values shorter than rewards", StepBatch { values: vec![0.5], next_values: vec![0.5], ..b() }, Inv, "steps.values"),
        case("next_values longer than rewards", StepBatch { next_values: vec![0.5; 3], ..with_values(b()) }, Inv, "steps.next_values"),
        case("q_values one short of B x n", StepBatch { q_values: vec![0.5; 5], ..with_q(b()) }, Inv, "steps.q_values"),
        case("q_values B long instead of B x n", StepBatch { q_values: vec![0.5; 2], next_q_values: vec![0.5; 2], ..b() }, Inv, "steps.q_values"),
        case("next_q_values one too long", StepBatch { next_q_values: vec![0.5; 7], ..with_q(b()) }, Inv, "steps.next_q_values"),
        case("q_values without next_q_values", StepBatch { q_values: vec![0.5; 6], ..b() }, Inv, "steps.next_q_values"),
        case("next_q_values without q_values", StepBatch { next_q_values: vec![0.5; 6], ..b() }, Inv, "steps.q_values"),
        case("values together with q_values", with_q(with_values(b())), Inv, "q_values"),
        case("score on a non-final entry", StepBatch { episode_scores: HashMap::from([(1, 3.0)]), ..b() }, Inv, "steps.episode_scores[1]"),
        case("score on a non-final entry, other entry final", StepBatch { episode_scores: HashMap::from([(0, 7.0), (1, 3.0)]), ..b() }, Inv, "steps.episode_scores[1]"),
        case("score key == B", StepBatch { episode_scores: HashMap::from([(0, 7.0), (2, 3.0)]), ..b() }, Inv, "steps.episode_scores[2]"),
        case("score key u32::MAX", StepBatch { episode_scores: HashMap::from([(u32::MAX, 3.0)]), ..b() }, Inv, "steps.episode_scores[4294967295]"),
    ];
    for (label, x) in BAD_F64 {
        cases.push(case(format!("rewards[1] = {label}"), StepBatch { rewards: vec![1.0, x], ..b() }, Inv, "steps.rewards[1]"));
        cases.push(case(format!("episode_scores[0] = {label}"), StepBatch { episode_scores: HashMap::from([(0, x)]), ..b() }, Inv, "steps.episode_scores[0]"));
    }
    for (label, x) in BAD_F32 {
        let v = with_values(b());
        cases.push(case(format!("values[1] = {label}"), StepBatch { values: vec![0.5, x], ..v.clone() }, Inv, "steps.values[1]"));
        cases.push(case(format!("next_values[1] = {label}"), StepBatch { next_values: vec![0.5, x], ..v }, Inv, "steps.next_values[1]"));
        let q = with_q(b());
        let mut bad = q.q_values.clone();
        bad[4] = x;
        cases.push(case(format!("q_values[4] = {label}"), StepBatch { q_values: bad, ..q.clone() }, Inv, "steps.q_values[4]"));
        let mut bad = q.next_q_values.clone();
        bad[5] = x;
        cases.push(case(format!("next_q_values[5] = {label}"), StepBatch { next_q_values: bad, ..q }, Inv, "steps.next_q_values[5]"));
    }
    cases
}

/// The continuous counterpart (m = 2, 2 envs, env_ids empty = entry i is env i).
fn continuous_base() -> StepBatch {
    StepBatch {
        action_vectors: vec![0.1, 0.2, 0.3, 0.4],
        rewards: vec![1.0, 2.0],
        terminated: vec![true, false],
        episode_scores: HashMap::from([(0, 7.0)]),
        values: vec![0.5, 0.5],
        next_values: vec![0.25, 0.25],
        ..Default::default()
    }
}

#[rustfmt::skip]
fn continuous_cases() -> Vec<Case> {
    use Code::InvalidArgument as Inv;
    let b = continuous_base;
    let mut cases = vec![
        case("action_vectors one short of B x m", StepBatch { action_vectors: vec![0.1; 3], ..b() }, Inv, "steps.action_vectors"),
        case("action_vectors one too long", StepBatch { action_vectors: vec![0.1; 5], ..b() }, Inv, "steps.action_vectors"),
        case("action_vectors B long instead of B x m", StepBatch { action_vectors: vec![0.1; 2], ..b() }, Inv, "steps.action_vectors"),
        case("action_vectors missing", StepBatch { action_vectors: vec![], ..b() }, Inv, "steps.action_vectors"),
        case("actions on a continuous task", StepBatch { actions: vec![0, 0], ..b() }, Inv, "steps.actions"),
        case("actions instead of action_vectors", StepBatch { actions: vec![0, 0], action_vectors: vec![], ..b() }, Inv, "steps.actions"),
        case("q_values on a continuous task", StepBatch { values: vec![], next_values: vec![], q_values: vec![0.5; 4], next_q_values: vec![0.5; 4], ..b() }, Inv, "steps.q_values"),
        case("env id == num_envs", StepBatch { env_ids: vec![0, 2], ..b() }, Inv, "steps.env_ids[1]"),
        case("empty env_ids with B > num_envs", StepBatch { action_vectors: vec![0.1; 6], rewards: vec![1.0; 3], terminated: vec![true, false, false], values: vec![], next_values: vec![], ..b() }, Inv, "steps.env_ids"),
        case("values shorter than rewards", StepBatch { values: vec![0.5], ..b() }, Inv, "steps.values"),
        case("score on a non-final entry", StepBatch { episode_scores: HashMap::from([(1, 3.0)]), ..b() }, Inv, "steps.episode_scores[1]"),
    ];
    for (label, x) in BAD_F32 {
        cases.push(case(format!("action_vectors[3] = {label}"), StepBatch { action_vectors: vec![0.1, 0.2, 0.3, x], ..b() }, Inv, "steps.action_vectors[3]"));
        cases.push(case(format!("values[1] = {label}"), StepBatch { values: vec![0.5, x], ..b() }, Inv, "steps.values[1]"));
        cases.push(case(format!("next_values[0] = {label}"), StepBatch { next_values: vec![x, 0.5], ..b() }, Inv, "steps.next_values[0]"));
    }
    for (label, x) in BAD_F64 {
        cases.push(case(format!("rewards[1] = {label}"), StepBatch { rewards: vec![1.0, x], ..b() }, Inv, "steps.rewards[1]"));
        cases.push(case(format!("episode_scores[0] = {label}"), StepBatch { episode_scores: HashMap::from([(0, x)]), ..b() }, Inv, "steps.episode_scores[0]"));
    }
    cases
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_step_batches_are_rejected_whole() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;

    // Discrete: n = 3.
    seeded_task(&mut c, "disc", 3, 0).await;
    let mut w = Witness::open(&mut c, "disc", 0, true).await;
    let warmup = batch(&[2, 2], &[0.0, 0.0], &[]);
    run_cases(&mut c, "disc", 2, &warmup, discrete_cases(), &mut w).await;

    // Continuous: m = 2.
    seeded_task(&mut c, "cont", 0, 2).await;
    let mut wc = Witness::open(&mut c, "cont", 2, true).await;
    let warmup_c = StepBatch {
        action_vectors: vec![0.3; 4],
        rewards: vec![0.0, 0.0],
        ..Default::default()
    };
    run_cases(&mut c, "cont", 2, &warmup_c, continuous_cases(), &mut wc).await;

    // Controls: the unmodified base batches are valid, and applying one does show up in
    // the pool and the counters (so the "nothing changed" checks above can fail).
    for (task, base, warm) in [
        ("disc", discrete_base(), &warmup),
        ("disc", with_values(discrete_base()), &warmup),
        ("disc", with_q(discrete_base()), &warmup),
        ("cont", continuous_base(), &warmup_c),
    ] {
        let what = format!("[{task}] control");
        let before = state(&mut c, task).await;
        let (mut a, _) = open(&mut c, task, 2).await.unwrap();
        step(&what, &mut a, warm.clone()).await.unwrap();
        let out = step(&what, &mut a, base)
            .await
            .expect("base batch is valid");
        assert_eq!(out.steps, vec![1, 1], "{what}");
        let after = state(&mut c, task).await;
        assert_eq!(
            after.stats.pool_version,
            before.stats.pool_version + 1,
            "{what}"
        );
        assert_eq!(out.pool_version, after.stats.pool_version, "{what}");
        assert_eq!(
            after.stats.episodes_completed,
            before.stats.episodes_completed + 1,
            "{what}"
        );
        assert_eq!(
            after.stats.steps_shaped,
            before.stats.steps_shaped + 4,
            "{what}"
        );
        assert!(
            after.pool.trajectories.iter().any(|t| t.score == 7.0),
            "{what}"
        );
    }

    drop((w, wc));
    get_task(&mut c, "disc").await;
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

/// SPEC §8: a missing `Open` is INVALID_ARGUMENT, also when the stream is half-closed
/// before any message (not a quiet OK: the client learns its stream never opened).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_ended_before_any_message_is_told_open_is_missing() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    seeded_task(&mut c, "t", 3, 0).await;
    let before = state(&mut c, "t").await;
    let s = bounded("empty stream", Stream::raw(&mut c))
        .await
        .expect("raw stream");
    let mut rx = s.close();
    let got = bounded("empty stream", rx.message()).await;
    expect_status("empty stream", got, Code::InvalidArgument, "open");
    assert_eq!(state(&mut c, "t").await, before);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stream_protocol_errors() {
    let server = start_server(None, |s| s.limits.max_envs_per_stream = 4).await;
    let mut c = connect(server.addr()).await;
    seeded_task(&mut c, "t", 3, 0).await;
    let mut w = Witness::open(&mut c, "t", 0, true).await;
    let ending = batch(&[1, 2], &[1.0, 1.0], &[true, true]);

    // Each scenario: (name, messages to send, expected code, field substring).
    let none = ShapeRequest { kind: None };
    let scenarios: Vec<(&str, Vec<ShapeRequest>, Code, &str)> = vec![
        (
            "missing Open: first message is steps",
            vec![steps(ending.clone())],
            Code::InvalidArgument,
            "open",
        ),
        (
            "first message has no kind",
            vec![none.clone()],
            Code::InvalidArgument,
            "kind",
        ),
        (
            "double Open",
            vec![open_msg("t", 2), open_msg("t", 2)],
            Code::InvalidArgument,
            "open",
        ),
        (
            "Open after a batch",
            vec![open_msg("t", 2), steps(ending.clone()), open_msg("t", 2)],
            Code::InvalidArgument,
            "open",
        ),
        (
            "message with no kind after Open",
            vec![open_msg("t", 2), none.clone()],
            Code::InvalidArgument,
            "kind",
        ),
        (
            "num_envs 0",
            vec![open_msg("t", 0)],
            Code::InvalidArgument,
            "open.num_envs",
        ),
        (
            "num_envs > max_envs_per_stream",
            vec![open_msg("t", 5)],
            Code::ResourceExhausted,
            "max_envs_per_stream",
        ),
        (
            "num_envs u32::MAX",
            vec![open_msg("t", u32::MAX)],
            Code::ResourceExhausted,
            "max_envs_per_stream",
        ),
        (
            "Open on an unknown task",
            vec![open_msg("nope", 2)],
            Code::NotFound,
            "nope",
        ),
        (
            "Open with an invalid task id",
            vec![open_msg("a b", 2)],
            Code::InvalidArgument,
            "open.task_id",
        ),
        (
            "Open with an empty task id",
            vec![open_msg("", 2)],
            Code::InvalidArgument,
            "open.task_id",
        ),
    ];
    for (name, msgs, code, field) in scenarios {
        let before = state(&mut c, "t").await;
        let mut s = bounded(name, Stream::raw(&mut c))
            .await
            .expect("raw stream");
        let mut result = None;
        for m in msgs {
            let is_steps = matches!(m.kind, Some(shape_request::Kind::Steps(_)));
            let is_open = matches!(m.kind, Some(shape_request::Kind::Open(_)));
            s.send(m).await;
            // Every accepted Open / batch gets exactly one answer; read it before going on.
            let answer = bounded(name, s.recv()).await;
            match answer {
                Ok(Some(proto::ShapeResponse {
                    kind: Some(shape_response::Kind::Opened(_)),
                })) if is_open => {}
                Ok(Some(proto::ShapeResponse {
                    kind: Some(shape_response::Kind::Shaped(_)),
                })) if is_steps => {}
                Err(status) => {
                    result = Some(status);
                    break;
                }
                other => panic!("{name}: unexpected answer {other:?}"),
            }
        }
        let status = result.unwrap_or_else(|| panic!("{name}: no error status"));
        expect_status::<()>(name, Err(status), code, field);
        assert_stream_over(name, &mut s, batch(&[0], &[0.0], &[])).await;
        drop(s);
        let mut after = state(&mut c, "t").await;
        if name == "Open after a batch" {
            // The batch before the bad Open was valid and ended two episodes (2 steps,
            // 2 inserts); check that and nothing else changed.
            assert_eq!(
                after.stats.steps_shaped,
                before.stats.steps_shaped + 2,
                "{name}"
            );
            assert_eq!(
                after.stats.pool_version,
                before.stats.pool_version + 2,
                "{name}"
            );
            let t = get_task(&mut c, "t").await.stats.unwrap();
            assert_eq!(t.open_streams, 1, "{name}: only the witness is open");
            // Put the pool back to the seeded state so the witness expectations hold.
            c.reset_pool(ResetPoolRequest {
                task_id: "t".into(),
            })
            .await
            .unwrap();
            assert!(
                try_add(&mut c, "t", dtraj(&[0; 200], 10.0))
                    .await
                    .unwrap()
                    .inserted
            );
            assert!(
                try_add(&mut c, "t", dtraj(&[1; 200], 0.0))
                    .await
                    .unwrap()
                    .inserted
            );
            after = state(&mut c, "t").await;
        } else {
            assert_eq!(after, before, "{name}: the failed stream changed the task");
        }
        let t = get_task(&mut c, "t").await.stats.unwrap();
        assert_eq!(t.open_streams, 1, "{name}: only the witness is open");
        w.check(name, after.stats.pool_version).await;
    }

    // (A stream half-closed before any message: its own test above.)
    let before = state(&mut c, "t").await;

    // max_envs_per_stream itself is allowed.
    let (mut s, _) = open(&mut c, "t", 4).await.expect("num_envs == limit");
    step("4 envs", &mut s, batch(&[0, 0, 0, 0], &[0.0; 4], &[]))
        .await
        .unwrap();
    drop(s);

    w.check("end", before.stats.pool_version).await;
    drop(w);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_task_is_not_found_on_every_rpc() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    seeded_task(&mut c, "other", 3, 0).await;
    let mut w = Witness::open(&mut c, "other", 0, true).await;
    let before = state(&mut c, "other").await;

    for id in ["nope", "gone"] {
        if id == "gone" {
            create(&mut c, "gone", discrete(2, 2, 2, 0, 1)).await;
            c.delete_task(DeleteTaskRequest {
                task_id: "gone".into(),
            })
            .await
            .unwrap();
        }
        let r = c.get_task(GetTaskRequest { task_id: id.into() }).await;
        expect_status("GetTask", r, Code::NotFound, id);
        let r = c
            .delete_task(DeleteTaskRequest { task_id: id.into() })
            .await;
        expect_status("DeleteTask", r, Code::NotFound, id);
        let r = c.reset_pool(ResetPoolRequest { task_id: id.into() }).await;
        expect_status("ResetPool", r, Code::NotFound, id);
        let r = c.get_pool(GetPoolRequest { task_id: id.into() }).await;
        expect_status("GetPool", r, Code::NotFound, id);
        let r = try_add(&mut c, id, dtraj(&[0, 1], 1.0)).await;
        expect_status("AddTrajectory", r, Code::NotFound, id);
        let r = open(&mut c, id, 1).await.map(|_| ());
        expect_status("Shape Open", r, Code::NotFound, id);
    }

    // A task deleted under an open stream: its next batch ends the stream with NOT_FOUND.
    create(&mut c, "doomed", discrete(3, 2, 2, 0, 1)).await;
    let (mut s, _) = open(&mut c, "doomed", 2).await.unwrap();
    step("doomed", &mut s, batch(&[0, 1], &[1.0, 1.0], &[]))
        .await
        .unwrap();
    c.delete_task(DeleteTaskRequest {
        task_id: "doomed".into(),
    })
    .await
    .unwrap();
    let r = step(
        "doomed after delete",
        &mut s,
        batch(&[0, 1], &[1.0, 1.0], &[true, true]),
    )
    .await;
    expect_status("batch on a deleted task", r, Code::NotFound, "doomed");
    assert_stream_over("doomed", &mut s, batch(&[0], &[0.0], &[])).await;

    let list = c
        .list_tasks(ListTasksRequest {})
        .await
        .unwrap()
        .into_inner();
    let ids: Vec<_> = list.tasks.iter().map(|t| t.task_id.as_str()).collect();
    assert_eq!(ids, ["other"]);
    assert_eq!(state(&mut c, "other").await, before);
    w.check("after NOT_FOUNDs", before.stats.pool_version).await;
    drop(w);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_task_ids_on_every_rpc() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    seeded_task(&mut c, "ok", 3, 0).await;
    let mut w = Witness::open(&mut c, "ok", 0, true).await;
    let before = state(&mut c, "ok").await;

    let long = "a".repeat(129);
    let bad_ids = [
        "",
        long.as_str(),
        "a b",
        " ok",
        "ok ",
        "é",
        "caf\u{e9}",
        "a*b",
        "*",
        "a\nb",
        "a\0b",
        "ok?",
        "a\\b",
    ];
    for id in bad_ids {
        let what = |rpc: &str| format!("{rpc} with task id {id:?}");
        let r = c
            .create_task(CreateTaskRequest {
                task_id: id.into(),
                config: Some(discrete(2, 2, 2, 0, 1)),
            })
            .await;
        expect_status(&what("CreateTask"), r, Code::InvalidArgument, "task_id");
        let r = c.get_task(GetTaskRequest { task_id: id.into() }).await;
        expect_status(&what("GetTask"), r, Code::InvalidArgument, "task_id");
        let r = c
            .delete_task(DeleteTaskRequest { task_id: id.into() })
            .await;
        expect_status(&what("DeleteTask"), r, Code::InvalidArgument, "task_id");
        let r = c.reset_pool(ResetPoolRequest { task_id: id.into() }).await;
        expect_status(&what("ResetPool"), r, Code::InvalidArgument, "task_id");
        let r = c.get_pool(GetPoolRequest { task_id: id.into() }).await;
        expect_status(&what("GetPool"), r, Code::InvalidArgument, "task_id");
        let r = try_add(&mut c, id, dtraj(&[0], 1.0)).await;
        expect_status(&what("AddTrajectory"), r, Code::InvalidArgument, "task_id");
        let r = open(&mut c, id, 1).await.map(|_| ());
        expect_status(
            &what("Shape Open"),
            r,
            Code::InvalidArgument,
            "open.task_id",
        );
    }
    let list = c
        .list_tasks(ListTasksRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(list.tasks.len(), 1, "no task was created from a bad id");
    assert_eq!(state(&mut c, "ok").await, before);
    w.check("after invalid task ids", before.pool.pool_version)
        .await;
    drop(w);

    // The edges of the valid range are accepted.
    for id in ["a".repeat(128), "AZaz09._:/-".to_string(), "x".to_string()] {
        create(&mut c, &id, discrete(2, 2, 2, 0, 1)).await;
        get_task(&mut c, &id).await;
    }
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

fn cfg() -> TaskConfig {
    TaskConfig {
        num_actions: 3,
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_configs_name_their_field() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;

    let mut cases: Vec<(String, Option<TaskConfig>, &str)> = vec![
        ("no config at all".into(), None, "config.num_actions"),
        (
            "neither num_actions nor action_dim".into(),
            Some(TaskConfig::default()),
            "config.num_actions",
        ),
        (
            "both num_actions and action_dim".into(),
            Some(TaskConfig {
                action_dim: 2,
                ..cfg()
            }),
            "config.action_dim",
        ),
        (
            "pool_capacity 0".into(),
            Some(TaskConfig {
                pool_capacity: Some(0),
                ..cfg()
            }),
            "config.pool_capacity",
        ),
        (
            "k 0".into(),
            Some(TaskConfig {
                k: Some(0),
                ..cfg()
            }),
            "config.k",
        ),
        (
            "k > pool_capacity".into(),
            Some(TaskConfig {
                pool_capacity: Some(5),
                k: Some(6),
                ..cfg()
            }),
            "config.k",
        ),
        (
            "k > default pool_capacity".into(),
            Some(TaskConfig {
                k: Some(21),
                ..cfg()
            }),
            "config.k",
        ),
        (
            "min_pool_size 0".into(),
            Some(TaskConfig {
                min_pool_size: Some(0),
                ..cfg()
            }),
            "config.min_pool_size",
        ),
        (
            "min_pool_size > pool_capacity".into(),
            Some(TaskConfig {
                pool_capacity: Some(5),
                min_pool_size: Some(6),
                ..cfg()
            }),
            "config.min_pool_size",
        ),
        (
            "gamma < 0".into(),
            Some(TaskConfig {
                gamma: Some(-0.01),
                ..cfg()
            }),
            "config.gamma",
        ),
        (
            "gamma > 1".into(),
            Some(TaskConfig {
                gamma: Some(1.01),
                ..cfg()
            }),
            "config.gamma",
        ),
        (
            "max_trajectory_len 0".into(),
            Some(TaskConfig {
                max_trajectory_len: Some(0),
                ..cfg()
            }),
            "config.max_trajectory_len",
        ),
        (
            "continuous, both set".into(),
            Some(TaskConfig {
                num_actions: 1,
                action_dim: 1,
                ..Default::default()
            }),
            "config.action_dim",
        ),
    ];
    for (label, x) in BAD_F64 {
        cases.push((
            format!("alpha {label}"),
            Some(TaskConfig {
                alpha: Some(x),
                ..cfg()
            }),
            "config.alpha",
        ));
        cases.push((
            format!("beta {label}"),
            Some(TaskConfig {
                beta: Some(x),
                ..cfg()
            }),
            "config.beta",
        ));
        cases.push((
            format!("gamma {label}"),
            Some(TaskConfig {
                gamma: Some(x),
                ..cfg()
            }),
            "config.gamma",
        ));
    }
    for (name, config, field) in cases {
        let r = c
            .create_task(CreateTaskRequest {
                task_id: "t".into(),
                config,
            })
            .await;
        expect_status(&name, r, Code::InvalidArgument, field);
    }
    let list = c
        .list_tasks(ListTasksRequest {})
        .await
        .unwrap()
        .into_inner();
    assert!(
        list.tasks.is_empty(),
        "a rejected config created a task: {list:?}"
    );

    // The edges of every range are accepted.
    let edges = [
        TaskConfig {
            gamma: Some(0.0),
            ..cfg()
        },
        TaskConfig {
            gamma: Some(1.0),
            ..cfg()
        },
        TaskConfig {
            num_actions: 1,
            pool_capacity: Some(1),
            k: Some(1),
            min_pool_size: Some(1),
            max_trajectory_len: Some(1),
            start_step: Some(0),
            ..cfg()
        },
        TaskConfig {
            pool_capacity: Some(5),
            k: Some(5),
            min_pool_size: Some(5),
            ..cfg()
        },
        TaskConfig {
            num_actions: 0,
            action_dim: 1,
            alpha: Some(-3.0),
            beta: Some(0.0),
            ..Default::default()
        },
    ];
    for (i, config) in edges.into_iter().enumerate() {
        create(&mut c, &format!("edge{i}"), config).await;
    }
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn create_task_is_idempotent_only_for_the_same_resolved_config() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let created = create(&mut c, "t", cfg()).await;
    assert!(
        try_add(&mut c, "t", dtraj(&[0, 1, 2], 4.0))
            .await
            .unwrap()
            .inserted
    );
    let before = state(&mut c, "t").await;
    let current = get_task(&mut c, "t").await;

    let explicit_defaults = TaskConfig {
        num_actions: 3,
        action_dim: 0,
        pool_capacity: Some(20),
        k: Some(20),
        start_step: Some(10),
        min_pool_size: Some(20),
        alpha: Some(0.8),
        beta: Some(0.8),
        gamma: Some(0.99),
        max_trajectory_len: Some(100_000),
        gate_potential: Some(false),
        require_score_spread: Some(false),
    };
    assert_eq!(
        created.config.unwrap(),
        explicit_defaults,
        "every default filled in"
    );
    for (name, config) in [
        ("same partial config", cfg()),
        ("defaults passed explicitly", explicit_defaults),
        (
            "k = pool_capacity explicitly",
            TaskConfig {
                k: Some(20),
                ..cfg()
            },
        ),
        ("the returned config", created.config.unwrap()),
    ] {
        let again = create(&mut c, "t", config).await;
        assert_eq!(
            again, current,
            "{name}: must return the existing task unchanged"
        );
        assert_eq!(state(&mut c, "t").await, before, "{name}");
    }

    // A different resolved config: ALREADY_EXISTS, naming the differing field.
    let different: Vec<(&str, TaskConfig, &str)> = vec![
        (
            "k",
            TaskConfig {
                k: Some(5),
                ..cfg()
            },
            "k",
        ),
        (
            "num_actions",
            TaskConfig {
                num_actions: 4,
                ..cfg()
            },
            "num_actions",
        ),
        (
            "continuous",
            TaskConfig {
                num_actions: 0,
                action_dim: 3,
                ..cfg()
            },
            "action_dim",
        ),
        (
            "pool_capacity",
            TaskConfig {
                pool_capacity: Some(19),
                k: Some(19),
                min_pool_size: Some(19),
                ..cfg()
            },
            "pool_capacity",
        ),
        (
            "start_step",
            TaskConfig {
                start_step: Some(0),
                ..cfg()
            },
            "start_step",
        ),
        (
            "min_pool_size",
            TaskConfig {
                min_pool_size: Some(1),
                ..cfg()
            },
            "min_pool_size",
        ),
        (
            "alpha one ulp off",
            TaskConfig {
                alpha: Some(0.8 + f64::EPSILON),
                ..cfg()
            },
            "alpha",
        ),
        (
            "beta",
            TaskConfig {
                beta: Some(0.0),
                ..cfg()
            },
            "beta",
        ),
        (
            "gamma",
            TaskConfig {
                gamma: Some(1.0),
                ..cfg()
            },
            "gamma",
        ),
        (
            "max_trajectory_len",
            TaskConfig {
                max_trajectory_len: Some(99_999),
                ..cfg()
            },
            "max_trajectory_len",
        ),
    ];
    for (name, config, field) in different {
        // The message lists the differing fields as "<field>: existing .., requested ..".
        let field = format!("{field}:");
        let field = field.as_str();
        let r = c
            .create_task(CreateTaskRequest {
                task_id: "t".into(),
                config: Some(config),
            })
            .await;
        expect_status(name, r, Code::AlreadyExists, field);
        assert_eq!(state(&mut c, "t").await, before, "{name}");
    }
    // An invalid config for an existing id is still INVALID_ARGUMENT.
    let r = c
        .create_task(CreateTaskRequest {
            task_id: "t".into(),
            config: Some(TaskConfig {
                k: Some(0),
                ..cfg()
            }),
        })
        .await;
    expect_status(
        "invalid config on an existing id",
        r,
        Code::InvalidArgument,
        "config.k",
    );
    assert_eq!(get_task(&mut c, "t").await, current);
    assert_eq!(state(&mut c, "t").await, before);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_trajectories_are_rejected() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    seeded_task(&mut c, "d", 3, 0).await;
    seeded_task(&mut c, "c", 0, 2).await;
    let mut wd = Witness::open(&mut c, "d", 0, true).await;
    let mut wc = Witness::open(&mut c, "c", 2, true).await;

    let mut cases: Vec<(String, &str, Option<Trajectory>, &str)> = vec![
        ("missing trajectory".into(), "d", None, "trajectory"),
        (
            "empty trajectory".into(),
            "d",
            Some(Trajectory::default()),
            "trajectory",
        ),
        (
            "empty trajectory with a score".into(),
            "d",
            Some(dtraj(&[], 5.0)),
            "trajectory",
        ),
        (
            "action == num_actions".into(),
            "d",
            Some(dtraj(&[0, 3], 5.0)),
            "trajectory.actions[1]",
        ),
        (
            "action u32::MAX".into(),
            "d",
            Some(dtraj(&[0, 1, u32::MAX], 5.0)),
            "trajectory.actions[2]",
        ),
        (
            "action_vectors on a discrete task".into(),
            "d",
            Some(Trajectory {
                actions: vec![0],
                action_vectors: vec![0.0; 3],
                score: 5.0,
                seq: 0,
            }),
            "trajectory.action_vectors",
        ),
        (
            "continuous: empty".into(),
            "c",
            Some(ctraj(&[], 5.0)),
            "trajectory",
        ),
        ("continuous: missing".into(), "c", None, "trajectory"),
        (
            "continuous: actions".into(),
            "c",
            Some(dtraj(&[0, 0], 5.0)),
            "trajectory.actions",
        ),
        (
            "continuous: length not a multiple of action_dim".into(),
            "c",
            Some(ctraj(&[0.0; 3], 5.0)),
            "trajectory.action_vectors",
        ),
    ];
    for (label, x) in BAD_F64 {
        cases.push((
            format!("score {label}"),
            "d",
            Some(dtraj(&[0, 1], x)),
            "trajectory.score",
        ));
        cases.push((
            format!("continuous: score {label}"),
            "c",
            Some(ctraj(&[0.0; 2], x)),
            "trajectory.score",
        ));
    }
    for (label, x) in BAD_F32 {
        cases.push((
            format!("continuous: action_vectors[3] {label}"),
            "c",
            Some(ctraj(&[0.0, 0.0, 0.0, x], 5.0)),
            "trajectory.action_vectors[3]",
        ));
    }
    for (name, task, trajectory, field) in cases {
        let before = state(&mut c, task).await;
        let r = c
            .add_trajectory(AddTrajectoryRequest {
                task_id: task.into(),
                trajectory,
            })
            .await;
        expect_status(&name, r, Code::InvalidArgument, field);
        assert_eq!(state(&mut c, task).await, before, "{name}: pool changed");
        let w = if task == "d" { &mut wd } else { &mut wc };
        w.check(&name, before.pool.pool_version).await;
    }
    drop((wd, wc));
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limits_are_resource_exhausted() {
    let server = start_server(None, |s| {
        s.limits.max_tasks = 3;
        s.limits.max_envs_per_stream = 4;
        s.limits.max_batch_entries = 8;
        s.limits.max_message_bytes = 4096;
        s.limits.max_pool_capacity = 100;
    })
    .await;
    let mut c = connect(server.addr()).await;

    // max_pool_capacity (checked while there is room for tasks).
    let r = c
        .create_task(CreateTaskRequest {
            task_id: "big".into(),
            config: Some(TaskConfig {
                pool_capacity: Some(101),
                ..cfg()
            }),
        })
        .await;
    expect_status(
        "pool_capacity > max_pool_capacity",
        r,
        Code::ResourceExhausted,
        "max_pool_capacity",
    );
    // Tasks: a discrete one, a continuous one with large actions, and one at the
    // capacity limit.
    create(&mut c, "d", discrete(3, 4, 2, 0, 1)).await;
    create(
        &mut c,
        "c",
        TaskConfig {
            action_dim: 600,
            ..discrete(0, 4, 2, 0, 1)
        },
    )
    .await;
    create(
        &mut c,
        "x",
        TaskConfig {
            pool_capacity: Some(100),
            ..cfg()
        },
    )
    .await;

    // max_tasks: a fourth task is refused, re-creating an existing one is not.
    let r = c
        .create_task(CreateTaskRequest {
            task_id: "fourth".into(),
            config: Some(cfg()),
        })
        .await;
    expect_status("past max_tasks", r, Code::ResourceExhausted, "max_tasks");
    create(
        &mut c,
        "x",
        TaskConfig {
            pool_capacity: Some(100),
            ..cfg()
        },
    )
    .await;
    let list = c
        .list_tasks(ListTasksRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(list.tasks.len(), 3);

    // Witness streams ("c" keeps an empty pool: kNN inactive).
    assert!(
        try_add(&mut c, "d", dtraj(&[0; 200], 1.0))
            .await
            .unwrap()
            .inserted
    );
    let mut wd = Witness::open(&mut c, "d", 0, true).await;
    let mut wc = Witness::open(&mut c, "c", 600, false).await;

    // max_envs_per_stream.
    let r = open(&mut c, "d", 5).await.map(|_| ());
    expect_status(
        "num_envs > max_envs_per_stream",
        r,
        Code::ResourceExhausted,
        "max_envs_per_stream",
    );

    // max_batch_entries: 9 entries (with an episode end) refused whole, 8 accepted.
    let nine = StepBatch {
        env_ids: vec![0, 1, 2, 3, 0, 1, 2, 3, 0],
        actions: vec![0; 9],
        rewards: vec![1.0; 9],
        terminated: vec![true, false, false, false, false, false, false, false, false],
        ..Default::default()
    };
    let before = state(&mut c, "d").await;
    let (mut s, _) = open(&mut c, "d", 4).await.unwrap();
    let r = step("9 entries", &mut s, nine.clone()).await;
    expect_status(
        "batch > max_batch_entries",
        r,
        Code::ResourceExhausted,
        "max_batch_entries",
    );
    assert_stream_over("9 entries", &mut s, batch(&[0], &[0.0], &[])).await;
    assert_eq!(
        state(&mut c, "d").await,
        before,
        "batch > max_batch_entries changed the task"
    );
    wd.check("after max_batch_entries", before.pool.pool_version)
        .await;

    // max_message_bytes, unary: an AddTrajectory of ~5000 bytes.
    let before = state(&mut c, "d").await;
    let r = try_add(&mut c, "d", dtraj(&[1; 5000], 9.0)).await;
    expect_status(
        "unary request > max_message_bytes",
        r,
        Code::ResourceExhausted,
        "max_message_bytes",
    );
    assert_eq!(
        state(&mut c, "d").await,
        before,
        "oversized AddTrajectory changed the pool"
    );
    wd.check("after oversized AddTrajectory", before.pool.pool_version)
        .await;

    // max_message_bytes, stream: a batch of 2 x 600 floats (4800 bytes), with an episode end.
    let before = state(&mut c, "c").await;
    let (mut s, _) = open(&mut c, "c", 2).await.unwrap();
    let warm = StepBatch {
        action_vectors: vec![0.5; 600],
        rewards: vec![0.0],
        ..Default::default()
    };
    step("warm-up", &mut s, warm.clone()).await.unwrap();
    let before_big = state(&mut c, "c").await;
    assert_eq!(before_big.stats.steps_shaped, before.stats.steps_shaped + 1);
    let big = StepBatch {
        action_vectors: vec![0.5; 1200],
        rewards: vec![1.0, 1.0],
        terminated: vec![true, true],
        ..Default::default()
    };
    let r = step("oversized batch", &mut s, big).await;
    expect_status(
        "Shape batch > max_message_bytes",
        r,
        Code::ResourceExhausted,
        "max_message_bytes",
    );
    assert_stream_over("oversized batch", &mut s, warm.clone()).await;
    assert_eq!(
        state(&mut c, "c").await,
        before_big,
        "oversized batch changed the task"
    );
    wc.check("after oversized batch", before.pool.pool_version)
        .await;

    // The server keeps serving: new streams, the limits' edges.
    let (mut s, _) = open(&mut c, "d", 4)
        .await
        .expect("num_envs == max_envs_per_stream");
    let eight = StepBatch {
        env_ids: nine.env_ids[..8].to_vec(),
        actions: vec![0; 8],
        rewards: vec![1.0; 8],
        ..Default::default()
    };
    let out = step("8 entries", &mut s, eight)
        .await
        .expect("8 entries == max_batch_entries");
    assert_eq!(out.steps, vec![0, 0, 0, 0, 1, 1, 1, 1]);
    drop(s);
    let (mut s, _) = open(&mut c, "c", 1).await.unwrap();
    step("c after", &mut s, warm)
        .await
        .expect("a batch under max_message_bytes");
    drop(s);
    c.delete_task(DeleteTaskRequest {
        task_id: "x".into(),
    })
    .await
    .unwrap();
    create(&mut c, "fourth", cfg()).await;
    wd.check(
        "end",
        get_task(&mut c, "d").await.stats.unwrap().pool_version,
    )
    .await;
    drop((wd, wc));
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

/// Failing streams running at the same time as a healthy one, on the same task: the
/// healthy stream's numbers and the task's pool do not notice them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failing_streams_do_not_disturb_a_concurrent_stream() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    seeded_task(&mut c, "t", 3, 0).await;
    let mut w = Witness::open(&mut c, "t", 0, true).await;
    let before = state(&mut c, "t").await;

    let mut failing = Vec::new();
    for i in 0..4u32 {
        let mut c = c.clone();
        failing.push(tokio::spawn(async move {
            for j in 0..5u32 {
                let what = format!("failing stream {i}.{j}");
                let (mut s, _) = open(&mut c, "t", 2).await.expect("open");
                step(&what, &mut s, batch(&[1, 2], &[1.0, 1.0], &[]))
                    .await
                    .expect("valid batch");
                // Entry 0 ends an episode; entry 1 has an out-of-range action.
                let r = step(&what, &mut s, batch(&[1, 3], &[1.0, 1.0], &[true, false])).await;
                expect_status(&what, r, Code::InvalidArgument, "steps.actions[1]");
            }
        }));
    }
    for i in 0..100 {
        w.check(&format!("concurrent step {i}"), before.pool.pool_version)
            .await;
    }
    for f in failing {
        f.await.expect("failing-stream task");
    }
    let after = state(&mut c, "t").await;
    assert_eq!(after.pool, before.pool, "failing streams changed the pool");
    assert_eq!(
        after.stats.episodes_completed, before.stats.episodes_completed,
        "failing streams completed episodes"
    );
    // Only the valid batches count: 20 x 2 entries, plus the witness's 100.
    assert_eq!(
        after.stats.steps_shaped,
        before.stats.steps_shaped + 40 + 100
    );
    assert_eq!(get_task(&mut c, "t").await.stats.unwrap().open_streams, 1);
    drop(w);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

/// `max_message_bytes` applies "either direction" (`Limits`): a GetPool whose answer
/// would exceed it is past a configured limit, so RESOURCE_EXHAUSTED (SPEC §8).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn get_pool_answer_over_max_message_bytes_is_resource_exhausted() {
    let server = start_server(None, |s| s.limits.max_message_bytes = 4096).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "d", discrete(3, 10, 2, 0, 1)).await;
    // Each request is ~1.5 KB; the pool holding all three is ~4.5 KB.
    for i in 0..3 {
        let r = try_add(&mut c, "d", dtraj(&[1; 1500], f64::from(i))).await;
        assert!(r.expect("AddTrajectory under the limit").inserted);
    }
    let r = c
        .get_pool(GetPoolRequest {
            task_id: "d".into(),
        })
        .await;
    expect_status(
        "GetPool answer > max_message_bytes",
        r,
        Code::ResourceExhausted,
        "max_message_bytes",
    );
    assert_eq!(get_task(&mut c, "d").await.stats.unwrap().pool_size, 3);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

/// A StepBatch within every limit (380 entries, < 4 KB) whose ShapedBatch answer
/// (~10 KB) cannot be sent under `max_message_bytes`: the batch must be refused with
/// RESOURCE_EXHAUSTED before any of it is applied (SPEC §8: "a rejected batch changes no
/// episode and no pool"), not applied and then failed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shape_answer_over_max_message_bytes_is_refused_before_applying() {
    let server = start_server(None, |s| s.limits.max_message_bytes = 4096).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "d", discrete(3, 10, 2, 0, 1)).await;
    let (mut s, _) = open(&mut c, "d", 380).await.unwrap();
    let big = StepBatch {
        actions: vec![0; 380],
        rewards: vec![0.0; 380],
        terminated: vec![true; 380],
        ..Default::default()
    };
    let request_len = prost::Message::encoded_len(&steps(big.clone()));
    assert!(
        request_len < 4000,
        "the request itself is {request_len} bytes"
    );
    let before = get_task(&mut c, "d").await.stats.unwrap();
    let r = step("answer > max_message_bytes", &mut s, big).await;
    let after = get_task(&mut c, "d").await.stats.unwrap();
    let unchanged = (
        after.pool_version,
        after.episodes_completed,
        after.steps_shaped,
    ) == (
        before.pool_version,
        before.episodes_completed,
        before.steps_shaped,
    );
    let right_status = matches!(&r, Err(s) if s.code() == Code::ResourceExhausted
        && s.message().contains("max_message_bytes"));
    assert!(
        unchanged && right_status,
        "batch whose answer exceeds max_message_bytes: got {:?}; task stats before {before:?}, after {after:?}",
        r.map(|b| b.rewards.len())
    );
    drop(s);
    assert_serving(server.addr()).await;
    server.shutdown().await;
}

/// The memory limits: a pool's reckoned bytes at CreateTask, a stream's at Open, and every
/// open stream's together, which a closed stream gives back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn memory_limits_refuse_a_pool_or_stream_past_them_and_a_closed_stream_frees_its_share() {
    // One env of a task with max_trajectory_len 10 and pool_capacity 2 reckons
    // 10 × 4 + 2 × 24 = 88 bytes, and a stream its receive window on top; its pool
    // 2 × 10 × 4 = 80.
    let window = u64::from(tamrm::service::STREAM_WINDOW);
    let server = start_server(None, |s| {
        s.limits.max_pool_bytes = 80;
        s.limits.max_stream_bytes = 3 * 88 + window;
        s.limits.max_total_stream_bytes = 5 * 88 + 2 * window;
    })
    .await;
    let mut c = connect(server.addr()).await;
    let small = |capacity: u32| TaskConfig {
        max_trajectory_len: Some(10),
        ..discrete(2, capacity, 1, 0, 1)
    };
    let r = c
        .create_task(CreateTaskRequest {
            task_id: "big".into(),
            config: Some(small(3)),
        })
        .await;
    expect_status(
        "pool past max_pool_bytes",
        r,
        Code::ResourceExhausted,
        "max_pool_bytes = 80",
    );
    assert!(c
        .list_tasks(ListTasksRequest {})
        .await
        .unwrap()
        .into_inner()
        .tasks
        .is_empty());
    create(&mut c, "t", small(2)).await;

    let refused = |r: Result<(Stream, proto::Task), Status>, limit: &str| match r {
        Ok(_) => panic!("opened past {limit}"),
        Err(s) => {
            assert_eq!(s.code(), Code::ResourceExhausted, "{limit}: {s:?}");
            assert!(s.message().contains(limit), "{limit}: {s:?}");
        }
    };
    let limit = format!("max_stream_bytes = {}", 3 * 88 + window);
    refused(Stream::open(&mut c, "t", 4).await, &limit);
    let (mut three, _) = Stream::open(&mut c, "t", 3).await.unwrap();
    let (two, _) = Stream::open(&mut c, "t", 2).await.unwrap();
    refused(
        Stream::open(&mut c, "t", 1).await,
        &format!("max_total_stream_bytes = {}", 5 * 88 + 2 * window),
    );
    wait_open_streams(&mut c, "t", 2).await;
    // The open streams still shape.
    three
        .step(batch(&[0, 1, 0], &[0.0; 3], &[false; 3]))
        .await
        .unwrap();
    // Closing a stream gives its share back: a 3-env stream fits again.
    drop(three);
    wait_open_streams(&mut c, "t", 1).await;
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    let again = loop {
        match Stream::open(&mut c, "t", 3).await {
            Ok((s, _)) => break s,
            Err(e) => {
                assert!(
                    std::time::Instant::now() < deadline,
                    "share not given back: {e:?}"
                );
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    };
    drop((two, again));
    server.shutdown().await;
}
