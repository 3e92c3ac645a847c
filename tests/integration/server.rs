//! The Shaping API end to end: a real server on a real socket, driven by the generated
//! tonic client, checked against a small naive reference model written from SPEC §2–§6.

use crate::common;
use crate::common::*;
use tamrm::proto::{self, StepBatch};
use tonic::Code;

// ---------------------------------------------------------------------------------------
// A naive reference model, straight from the SPEC formulas (from-scratch distances).
// ---------------------------------------------------------------------------------------

#[derive(Clone, Debug, PartialEq)]
enum Act {
    D(u32),
    C(Vec<f32>),
}

/// δ(a, a') = ‖e(a) − e(a')‖² (SPEC §2), with the one-hot encoding written out.
fn delta(a: &Act, b: &Act, n: u32) -> f64 {
    match (a, b) {
        (Act::D(x), Act::D(y)) => {
            let onehot = |v: u32| (0..n).map(move |i| if i == v { 1.0 } else { 0.0 });
            onehot(*x)
                .zip(onehot(*y))
                .map(|(p, q): (f64, f64)| (p - q) * (p - q))
                .sum()
        }
        (Act::C(x), Act::C(y)) => x
            .iter()
            .zip(y)
            .map(|(&p, &q)| {
                let d = f64::from(p) - f64::from(q);
                d * d
            })
            .sum(),
        _ => panic!("mixed action kinds"),
    }
}

#[derive(Clone, Copy, Debug)]
struct Cfg {
    n: u32,
    m: u32,
    cap: usize,
    k: usize,
    start: usize,
    min_pool: usize,
    alpha: f64,
    beta: f64,
    gamma: f64,
    max_len: usize,
    /// `require_score_spread` (SPEC v1.3).
    spread: bool,
}

impl Cfg {
    fn proto(&self) -> proto::TaskConfig {
        proto::TaskConfig {
            num_actions: self.n,
            action_dim: self.m,
            pool_capacity: Some(self.cap as u32),
            k: Some(self.k as u32),
            start_step: Some(self.start as u32),
            min_pool_size: Some(self.min_pool as u32),
            alpha: Some(self.alpha),
            beta: Some(self.beta),
            gamma: Some(self.gamma),
            max_trajectory_len: Some(self.max_len as u32),
            gate_potential: Some(false),
            require_score_spread: Some(self.spread),
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
struct RefTraj {
    acts: Vec<Act>,
    score: f64,
    seq: u64,
}

#[derive(Clone, Debug)]
struct RefPool {
    cap: usize,
    trajs: Vec<RefTraj>,
    version: u64,
    next_seq: u64,
}

impl RefPool {
    fn new(cap: usize) -> RefPool {
        RefPool {
            cap,
            trajs: Vec::new(),
            version: 0,
            next_seq: 1,
        }
    }

    /// SPEC §6: insert while not full; else replace the lowest score (lowest seq among
    /// equals) if strictly better; else discard.
    fn offer(&mut self, acts: Vec<Act>, score: f64) -> bool {
        if self.trajs.len() >= self.cap {
            let mut worst = 0;
            for (i, t) in self.trajs.iter().enumerate() {
                let w = &self.trajs[worst];
                if t.score < w.score || (t.score == w.score && t.seq < w.seq) {
                    worst = i;
                }
            }
            if score > self.trajs[worst].score {
                self.trajs.remove(worst);
            } else {
                return false;
            }
        }
        self.trajs.push(RefTraj {
            acts,
            score,
            seq: self.next_seq,
        });
        self.next_seq += 1;
        self.version += 1;
        true
    }

    fn proto(&self, task_id: &str) -> proto::Pool {
        proto::Pool {
            task_id: task_id.into(),
            pool_version: self.version,
            trajectories: self.trajs.iter().map(traj_proto).collect(),
            next_seq: self.next_seq,
        }
    }
}

fn traj_proto(t: &RefTraj) -> proto::Trajectory {
    let mut p = proto::Trajectory {
        score: t.score,
        seq: t.seq,
        ..Default::default()
    };
    for a in &t.acts {
        match a {
            Act::D(x) => p.actions.push(*x),
            Act::C(v) => p.action_vectors.extend_from_slice(v),
        }
    }
    p
}

/// Value estimates for one entry, as sent.
#[derive(Clone, Debug)]
enum Vals {
    None,
    State(f32, f32),
    Q(Vec<f32>, Vec<f32>),
}

#[derive(Clone, Debug)]
struct Entry {
    env: usize,
    act: Act,
    reward: f64,
    terminated: bool,
    truncated: bool,
    vals: Vals,
    score: Option<f64>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Out {
    reward: f64,
    knn: f64,
    pot: f64,
    t: u32,
    active: bool,
}

#[derive(Clone, Debug, Default)]
struct RefEnv {
    acts: Vec<Act>,
    rewards: Vec<f64>,
}

/// r(t) from scratch (SPEC §3) for the prefix `prefix` (t = prefix.len() − 1).
fn knn_reward(cfg: &Cfg, pool: &RefPool, prefix: &[Act]) -> f64 {
    let t = prefix.len() - 1;
    let dis: Vec<f64> = pool
        .trajs
        .iter()
        .map(|tr| (0..=t).map(|j| delta(&tr.acts[j], &prefix[j], cfg.n)).sum())
        .collect();
    let zeros = dis.iter().filter(|&&d| d == 0.0).count();
    let p: Vec<f64> = if zeros > 0 {
        dis.iter()
            .map(|&d| if d == 0.0 { 1.0 / zeros as f64 } else { 0.0 })
            .collect()
    } else {
        // The paper's form: Rate_i = Σ_j dis_j / dis_i, P_i = Rate_i / Σ_j Rate_j.
        let total: f64 = dis.iter().sum();
        let rate: Vec<f64> = dis.iter().map(|d| total / d).collect();
        let rsum: f64 = rate.iter().sum();
        rate.iter().map(|r| r / rsum).collect()
    };
    let smin = pool
        .trajs
        .iter()
        .map(|t| t.score)
        .fold(f64::INFINITY, f64::min);
    let smax = pool
        .trajs
        .iter()
        .map(|t| t.score)
        .fold(f64::NEG_INFINITY, f64::max);
    let x: Vec<f64> = pool
        .trajs
        .iter()
        .map(|t| {
            if smax == smin {
                1.0
            } else {
                (t.score - smin) / (smax - smin)
            }
        })
        .collect();
    // Order by P descending, ties by x descending, then seq ascending. P is a strictly
    // decreasing function of dis (or 1/|Z| vs 0 with exact matches), so the order is taken
    // on dis, where equal probabilities are exactly equal (the test's action values are
    // binary fractions, so every dis is exact).
    let key = |i: usize| {
        if zeros > 0 {
            if dis[i] == 0.0 {
                0.0
            } else {
                1.0
            }
        } else {
            dis[i]
        }
    };
    let mut idx: Vec<usize> = (0..dis.len()).collect();
    idx.sort_by(|&a, &b| {
        key(a)
            .total_cmp(&key(b))
            .then(x[b].total_cmp(&x[a]))
            .then(pool.trajs[a].seq.cmp(&pool.trajs[b].seq))
    });
    let f: f64 = idx
        .iter()
        .take(cfg.k.min(dis.len()))
        .map(|&i| x[i] * p[i])
        .sum();
    f.exp() - 0.5f64.exp()
}

/// F = γ·V(s') − V(s) (SPEC §4): V(s') = 0 when terminated; V = max Q.
fn ref_potential(cfg: &Cfg, e: &Entry) -> f64 {
    let max = |q: &[f32]| {
        q.iter()
            .map(|&x| f64::from(x))
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let (v, vn) = match &e.vals {
        Vals::None => return 0.0,
        Vals::State(v, vn) => (f64::from(*v), f64::from(*vn)),
        Vals::Q(q, qn) => (max(q), max(qn)),
    };
    let vn = if e.terminated { 0.0 } else { vn };
    cfg.gamma * vn - v
}

/// One reference step (SPEC §3–§6); offers the episode at its end.
fn ref_step(cfg: &Cfg, pool: &mut RefPool, env: &mut RefEnv, e: &Entry) -> Out {
    let t = env.acts.len();
    env.acts.push(e.act.clone());
    env.rewards.push(e.reward);
    let l_min = pool.trajs.iter().map(|t| t.acts.len()).min().unwrap_or(0);
    let scores = || pool.trajs.iter().map(|t| t.score);
    let spread =
        scores().fold(f64::NEG_INFINITY, f64::max) > scores().fold(f64::INFINITY, f64::min);
    let active = pool.trajs.len() >= cfg.min_pool
        && t >= cfg.start
        && t < l_min
        && t < cfg.max_len
        && (!cfg.spread || spread);
    let knn = if active {
        knn_reward(cfg, pool, &env.acts)
    } else {
        0.0
    };
    let pot = ref_potential(cfg, e);
    let out = Out {
        reward: e.reward + cfg.alpha * knn + cfg.beta * pot,
        knn,
        pot,
        t: t as u32,
        active,
    };
    if e.terminated || e.truncated {
        let score = e
            .score
            .unwrap_or_else(|| env.rewards.iter().fold(0.0, |s, r| s + r));
        let mut acts = std::mem::take(&mut env.acts);
        acts.truncate(cfg.max_len);
        env.rewards.clear();
        pool.offer(acts, score);
    }
    out
}

/// A StepBatch for `entries`; `explicit_envs` false means env_ids is left empty (the
/// entries must then be envs 0..B-1 in order). Values: all entries must agree on the kind.
fn step_batch(entries: &[Entry], explicit_envs: bool) -> StepBatch {
    let mut b = StepBatch::default();
    for (i, e) in entries.iter().enumerate() {
        if explicit_envs {
            b.env_ids.push(e.env as u32);
        } else {
            assert_eq!(e.env, i);
        }
        match &e.act {
            Act::D(a) => b.actions.push(*a),
            Act::C(v) => b.action_vectors.extend_from_slice(v),
        }
        b.rewards.push(e.reward);
        b.terminated.push(e.terminated);
        b.truncated.push(e.truncated);
        match &e.vals {
            Vals::None => {}
            Vals::State(v, vn) => {
                b.values.push(*v);
                b.next_values.push(*vn);
            }
            Vals::Q(q, qn) => {
                b.q_values.extend_from_slice(q);
                b.next_q_values.extend_from_slice(qn);
            }
        }
        if let Some(s) = e.score {
            b.episode_scores.insert(i as u32, s);
        }
    }
    b
}

fn outs(b: &proto::ShapedBatch) -> Vec<Out> {
    let n = b.rewards.len();
    assert_eq!(b.knn_rewards.len(), n);
    assert_eq!(b.potentials.len(), n);
    assert_eq!(b.steps.len(), n);
    assert_eq!(b.knn_active.len(), n);
    (0..n)
        .map(|i| Out {
            reward: b.rewards[i],
            knn: b.knn_rewards[i],
            pot: b.potentials[i],
            t: b.steps[i],
            active: b.knn_active[i],
        })
        .collect()
}

fn assert_out(got: &Out, want: &Out, ctx: &str) {
    assert_eq!(got.t, want.t, "{ctx}: step");
    assert_eq!(
        got.active, want.active,
        "{ctx}: knn_active (t = {})",
        want.t
    );
    assert!(
        (got.knn - want.knn).abs() <= 1e-12,
        "{ctx}: knn_reward {} vs reference {}",
        got.knn,
        want.knn
    );
    assert!(
        (got.pot - want.pot).abs() <= 1e-12 * (1.0 + want.pot.abs()),
        "{ctx}: potential {} vs reference {}",
        got.pot,
        want.pot
    );
    assert!(
        (got.reward - want.reward).abs() <= 1e-12 * (1.0 + want.reward.abs()),
        "{ctx}: reward {} vs reference {}",
        got.reward,
        want.reward
    );
}

/// A reference stream: its envs, processing a batch against a shared reference pool.
struct RefStream {
    cfg: Cfg,
    envs: Vec<RefEnv>,
}

impl RefStream {
    fn new(cfg: Cfg, num_envs: usize) -> RefStream {
        RefStream {
            cfg,
            envs: vec![RefEnv::default(); num_envs],
        }
    }
    fn batch(&mut self, pool: &mut RefPool, entries: &[Entry]) -> Vec<Out> {
        entries
            .iter()
            .map(|e| ref_step(&self.cfg, pool, &mut self.envs[e.env], e))
            .collect()
    }
}

/// Small deterministic PRNG (SplitMix64).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn chance(&mut self, p: f64) -> bool {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64 <= p
    }
    fn pick<T: Copy>(&mut self, xs: &[T]) -> T {
        xs[self.below(xs.len() as u64) as usize]
    }
    fn f32_in(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * ((self.next() >> 40) as f32 / (1u64 << 24) as f32)
    }
}

/// Random entries for one batch. Rewards and client scores come from small sets, so that
/// equal scores (the tie rules of §6) and exact prefix matches (§3) happen often.
fn random_entries(
    rng: &mut Rng,
    cfg: &Cfg,
    num_envs: usize,
    explicit_envs: bool,
    lens: &mut [usize],
) -> Vec<Entry> {
    let b = if explicit_envs {
        1 + rng.below(3 * num_envs as u64) as usize
    } else {
        1 + rng.below(num_envs as u64) as usize
    };
    let vals_kind = if cfg.n > 0 {
        rng.below(3)
    } else {
        rng.below(2)
    };
    (0..b)
        .map(|i| {
            let env = if explicit_envs {
                rng.below(num_envs as u64) as usize
            } else {
                i
            };
            let act = if cfg.n > 0 {
                Act::D(rng.below(cfg.n as u64) as u32)
            } else {
                Act::C(
                    (0..cfg.m)
                        .map(|_| rng.pick(&[-1.0f32, 0.0, 0.5, 2.0]))
                        .collect(),
                )
            };
            lens[env] += 1;
            let ends = rng.chance(0.18) || lens[env] >= 12;
            let (terminated, truncated) = if ends {
                match rng.below(3) {
                    0 => (true, false),
                    1 => (false, true),
                    _ => (true, true),
                }
            } else {
                (false, false)
            };
            if ends {
                lens[env] = 0;
            }
            let score = if ends && rng.chance(0.4) {
                Some(rng.pick(&[0.0, 1.0, 2.0, 3.0, -1.5]))
            } else {
                None
            };
            let vals = match vals_kind {
                0 => Vals::None,
                1 => Vals::State(rng.f32_in(-2.0, 2.0), rng.f32_in(-2.0, 2.0)),
                _ => Vals::Q(
                    (0..cfg.n).map(|_| rng.f32_in(-3.0, 3.0)).collect(),
                    (0..cfg.n).map(|_| rng.f32_in(-3.0, 3.0)).collect(),
                ),
            };
            Entry {
                env,
                act,
                reward: rng.pick(&[-1.0, 0.0, 0.5, 1.0, 0.25]),
                terminated,
                truncated,
                vals,
                score,
            }
        })
        .collect()
}

/// Checks GetPool and the pool-derived stats against the reference pool.
async fn check_pool(c: &mut Client, id: &str, pool: &RefPool, ctx: &str) {
    let got = get_pool(c, id).await;
    assert_eq!(got, pool.proto(id), "{ctx}: pool");
    let stats = get_task(c, id).await.stats.unwrap();
    assert_eq!(
        stats.pool_size as usize,
        pool.trajs.len(),
        "{ctx}: pool_size"
    );
    assert_eq!(stats.pool_version, pool.version, "{ctx}: pool_version");
    let lmin = pool.trajs.iter().map(|t| t.acts.len()).min().unwrap_or(0);
    assert_eq!(stats.min_length as usize, lmin, "{ctx}: min_length");
    let (lo, hi) = if pool.trajs.is_empty() {
        (0.0, 0.0)
    } else {
        (
            pool.trajs
                .iter()
                .map(|t| t.score)
                .fold(f64::INFINITY, f64::min),
            pool.trajs
                .iter()
                .map(|t| t.score)
                .fold(f64::NEG_INFINITY, f64::max),
        )
    };
    assert_eq!(
        (stats.worst_score, stats.best_score),
        (lo, hi),
        "{ctx}: scores"
    );
}

// ---------------------------------------------------------------------------------------
// Task lifecycle
// ---------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn task_lifecycle() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;

    // Defaults filled in.
    let t = create(
        &mut c,
        "maze/v1:seed-0",
        proto::TaskConfig {
            num_actions: 4,
            ..Default::default()
        },
    )
    .await;
    assert_eq!(t.task_id, "maze/v1:seed-0");
    let want_config = proto::TaskConfig {
        num_actions: 4,
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
    assert_eq!(t.config.as_ref(), Some(&want_config));
    assert_eq!(
        t.stats,
        Some(proto::TaskStats::default()),
        "a new task has empty stats"
    );
    // k and min_pool_size default to the capacity given.
    let t2 = create(
        &mut c,
        "cont",
        proto::TaskConfig {
            action_dim: 3,
            pool_capacity: Some(7),
            ..Default::default()
        },
    )
    .await;
    let cfg2 = t2.config.unwrap();
    assert_eq!((cfg2.k, cfg2.min_pool_size), (Some(7), Some(7)));
    assert_eq!((cfg2.num_actions, cfg2.action_dim), (0, 3));

    // Idempotent: the same resolved config (defaults written out or left unset).
    add(&mut c, "maze/v1:seed-0", dtraj(&[1, 2], 3.0)).await;
    let again = create(&mut c, "maze/v1:seed-0", want_config).await;
    assert_eq!(again, get_task(&mut c, "maze/v1:seed-0").await);
    assert_eq!(again.stats.unwrap().pool_size, 1, "returned unchanged");
    let again = create(
        &mut c,
        "maze/v1:seed-0",
        proto::TaskConfig {
            num_actions: 4,
            ..Default::default()
        },
    )
    .await;
    assert_eq!(again.stats.unwrap().pool_version, 1);
    // A different config: ALREADY_EXISTS, nothing changed.
    let err = c
        .create_task(proto::CreateTaskRequest {
            task_id: "maze/v1:seed-0".into(),
            config: Some(proto::TaskConfig {
                num_actions: 4,
                gamma: Some(0.5),
                ..Default::default()
            }),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::AlreadyExists, "{err:?}");
    assert_eq!(
        get_task(&mut c, "maze/v1:seed-0")
            .await
            .config
            .unwrap()
            .gamma,
        Some(0.99)
    );

    // ListTasks ordered by id.
    for id in ["b", "a", "A", "c/1", "a.b", "Z-9"] {
        create(&mut c, id, discrete(2, 2, 1, 0, 1)).await;
    }
    let list = c
        .list_tasks(proto::ListTasksRequest {})
        .await
        .unwrap()
        .into_inner();
    let ids: Vec<&str> = list.tasks.iter().map(|t| t.task_id.as_str()).collect();
    let mut sorted = ids.clone();
    sorted.sort();
    assert_eq!(ids, sorted);
    assert_eq!(ids.len(), 8);
    for t in &list.tasks {
        assert_eq!(t, &get_task(&mut c, &t.task_id).await);
    }

    // DeleteTask, then NOT_FOUND everywhere.
    c.delete_task(proto::DeleteTaskRequest {
        task_id: "maze/v1:seed-0".into(),
    })
    .await
    .unwrap();
    let id = || "maze/v1:seed-0".to_string();
    let e = c
        .get_task(proto::GetTaskRequest { task_id: id() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let e = c
        .get_pool(proto::GetPoolRequest { task_id: id() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let e = c
        .reset_pool(proto::ResetPoolRequest { task_id: id() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let e = c
        .add_trajectory(proto::AddTrajectoryRequest {
            task_id: id(),
            trajectory: Some(dtraj(&[0], 1.0)),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let e = c
        .delete_task(proto::DeleteTaskRequest { task_id: id() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    let e = Stream::open(&mut c, &id(), 1)
        .await
        .err()
        .expect("NOT_FOUND");
    assert_eq!(e.code(), Code::NotFound);
    let list = c
        .list_tasks(proto::ListTasksRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(list.tasks.len(), 7);
    // The id can be created again, with a fresh empty pool and a different config.
    let t = create(&mut c, &id(), discrete(3, 2, 2, 0, 1)).await;
    assert_eq!(t.stats.unwrap().pool_size, 0);

    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reset_pool_empties_and_bumps_version_and_seqs_keep_increasing() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(3, 3, 3, 0, 1)).await;
    for (i, s) in [1.0, 2.0].iter().enumerate() {
        let r = add(&mut c, "t", dtraj(&[0, 1, 2], *s)).await;
        assert_eq!((r.inserted, r.pool_version), (true, i as u64 + 1));
    }
    let t = c
        .reset_pool(proto::ResetPoolRequest {
            task_id: "t".into(),
        })
        .await
        .unwrap()
        .into_inner();
    let s = t.stats.unwrap();
    assert_eq!(
        (s.pool_size, s.pool_version, s.min_length),
        (0, 3, 0),
        "{s:?}"
    );
    assert_eq!((s.best_score, s.worst_score), (0.0, 0.0));
    let p = get_pool(&mut c, "t").await;
    assert_eq!(p.pool_version, 3);
    assert!(p.trajectories.is_empty());
    // Resetting an empty pool still bumps the version.
    let t = c
        .reset_pool(proto::ResetPoolRequest {
            task_id: "t".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(t.stats.unwrap().pool_version, 4);
    // Seqs continue after the reset (by AddTrajectory and by a stream's episode end).
    let r = add(&mut c, "t", dtraj(&[2], 0.5)).await;
    assert_eq!((r.inserted, r.pool_version), (true, 5));
    let (mut s, _) = Stream::open(&mut c, "t", 1).await.unwrap();
    let out = s.step(batch(&[1], &[4.0], &[true])).await.unwrap();
    assert_eq!(out.pool_version, 6);
    let p = get_pool(&mut c, "t").await;
    let seqs: Vec<u64> = p.trajectories.iter().map(|t| t.seq).collect();
    assert_eq!(seqs, vec![3, 4]);
    assert_eq!(p.trajectories[1].score, 4.0);
    assert_eq!(p.trajectories[1].actions, vec![1]);
    drop(s);
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// AddTrajectory / GetPool
// ---------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn add_trajectory_insert_replace_discard() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let mut cfg = discrete(5, 3, 2, 0, 1);
    cfg.max_trajectory_len = Some(4);
    create(&mut c, "t", cfg).await;
    let mut reference = RefPool::new(3);
    let d = |v: &[u32]| v.iter().map(|&a| Act::D(a)).collect::<Vec<_>>();

    // (actions, score, expected inserted)
    let steps: &[(&[u32], f64, bool)] = &[
        (&[0, 1, 2], 1.0, true),
        (&[1, 1], 2.0, true),
        (&[4, 4, 4, 4, 4, 4, 4], 2.0, true), // truncated to 4 actions
        (&[3], 1.0, false),                  // equal to S_min: discarded
        (&[3], 0.5, false),                  // worse: discarded
        (&[3, 3], 3.0, true),                // replaces seq 1 (score 1)
        (&[2, 2], 2.5, true),                // replaces seq 2 (score 2, lower seq than 3)
        (&[2], 2.0, false),                  // equal to S_min (2.0 at seq 3)
        (&[1, 0, 1, 0, 1], 9.0, true),       // replaces seq 3; truncated
    ];
    for (i, (acts, score, inserted)) in steps.iter().enumerate() {
        let before = reference.version;
        let mut a = d(acts);
        a.truncate(4);
        let ref_inserted = reference.offer(a, *score);
        assert_eq!(ref_inserted, *inserted, "reference disagrees at {i}");
        let r = add(&mut c, "t", dtraj(acts, *score)).await;
        assert_eq!(r.inserted, *inserted, "step {i}");
        assert_eq!(r.pool_version, reference.version, "step {i}");
        if !inserted {
            assert_eq!(r.pool_version, before, "a discard leaves the version");
        }
        check_pool(&mut c, "t", &reference, &format!("step {i}")).await;
    }
    let p = get_pool(&mut c, "t").await;
    let seqs: Vec<u64> = p.trajectories.iter().map(|t| t.seq).collect();
    assert_eq!(seqs, vec![4, 5, 6]);
    assert_eq!(p.trajectories[2].actions, vec![1, 0, 1, 0]);
    let s = get_task(&mut c, "t").await.stats.unwrap();
    assert_eq!((s.min_length, s.best_score, s.worst_score), (2, 9.0, 2.5));
    assert_eq!((s.episodes_completed, s.steps_shaped), (0, 0));

    // Bad trajectories change nothing.
    for (t, field) in [
        (dtraj(&[], 5.0), "trajectory"),
        (dtraj(&[5], 5.0), "trajectory.actions[0]"),
        (dtraj(&[1], f64::NAN), "trajectory.score"),
    ] {
        let e = c
            .add_trajectory(proto::AddTrajectoryRequest {
                task_id: "t".into(),
                trajectory: Some(t),
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.message().contains(field), "{e:?}");
    }
    check_pool(&mut c, "t", &reference, "after bad input").await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn continuous_trajectories_round_trip_exactly() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(
        &mut c,
        "c",
        proto::TaskConfig {
            action_dim: 3,
            pool_capacity: Some(4),
            max_trajectory_len: Some(3),
            ..Default::default()
        },
    )
    .await;
    let odd = [
        -0.0f32,
        f32::MIN_POSITIVE,
        f32::from_bits(1), // smallest subnormal
        f32::MAX,
        f32::MIN,
        0.1,
        -1e-30,
        std::f32::consts::PI,
        1.0 + f32::EPSILON,
    ];
    let t1 = proto::Trajectory {
        action_vectors: odd.to_vec(),
        score: -0.1,
        ..Default::default()
    };
    assert!(add(&mut c, "c", t1).await.inserted);
    // Longer than max_trajectory_len = 3: keeps 3 × 3 floats.
    let long: Vec<f32> = (0..15).map(|i| i as f32 * 0.37 - 2.0).collect();
    let t2 = proto::Trajectory {
        action_vectors: long.clone(),
        score: 1e300,
        ..Default::default()
    };
    assert!(add(&mut c, "c", t2).await.inserted);
    let p = get_pool(&mut c, "c").await;
    assert_eq!(p.trajectories.len(), 2);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&p.trajectories[0].action_vectors), bits(&odd));
    assert!(p.trajectories[0].actions.is_empty());
    assert_eq!(p.trajectories[0].score.to_bits(), (-0.1f64).to_bits());
    assert_eq!(bits(&p.trajectories[1].action_vectors), bits(&long[..9]));
    assert_eq!(p.trajectories[1].score, 1e300);
    let s = get_task(&mut c, "c").await.stats.unwrap();
    assert_eq!((s.pool_size, s.min_length), (2, 3));
    // Not a multiple of action_dim.
    let e = c
        .add_trajectory(proto::AddTrajectoryRequest {
            task_id: "c".into(),
            trajectory: Some(proto::Trajectory {
                action_vectors: vec![1.0; 4],
                score: 1.0,
                ..Default::default()
            }),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("trajectory.action_vectors"), "{e:?}");
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Shape streams against the reference
// ---------------------------------------------------------------------------------------

/// Drives one stream of random batches on a fresh task and checks every returned entry
/// and, after every batch, the pool and stats against the reference.
async fn reference_scenario(cfg: Cfg, num_envs: usize, batches: usize, seed: u64) {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "ref", cfg.proto()).await;
    let mut pool = RefPool::new(cfg.cap);
    let mut rs = RefStream::new(cfg, num_envs);
    let mut rng = Rng(seed);
    let (mut s, opened) = Stream::open(&mut c, "ref", num_envs as u32).await.unwrap();
    assert_eq!(opened.stats.unwrap().open_streams, 1);
    let mut lens = vec![0usize; num_envs];
    let (mut ends, mut steps) = (0u64, 0u64);
    let (mut mid_batch_ends, mut same_env_repeats, mut active_seen, mut client_scores) =
        (0, 0, 0, 0);
    for bi in 0..batches {
        let explicit = rng.chance(0.7);
        let entries = random_entries(&mut rng, &cfg, num_envs, explicit, &mut lens);
        // Coverage bookkeeping.
        for (i, e) in entries.iter().enumerate() {
            if (e.terminated || e.truncated) && i + 1 < entries.len() {
                mid_batch_ends += 1;
            }
            if entries[..i].iter().any(|p| p.env == e.env) {
                same_env_repeats += 1;
            }
            client_scores += usize::from(e.score.is_some());
        }
        let want = rs.batch(&mut pool, &entries);
        let got = s.step(step_batch(&entries, explicit)).await.unwrap();
        for (i, (g, w)) in outs(&got).iter().zip(&want).enumerate() {
            assert_out(
                g,
                w,
                &format!("seed {seed} batch {bi} entry {i} ({:?})", entries[i]),
            );
        }
        assert_eq!(outs(&got).len(), entries.len());
        assert_eq!(got.pool_version, pool.version, "batch {bi}: pool_version");
        active_seen += want.iter().filter(|o| o.active).count();
        ends += entries
            .iter()
            .filter(|e| e.terminated || e.truncated)
            .count() as u64;
        steps += entries.len() as u64;
        check_pool(&mut c, "ref", &pool, &format!("after batch {bi}")).await;
        let st = get_task(&mut c, "ref").await.stats.unwrap();
        assert_eq!(
            (st.episodes_completed, st.steps_shaped, st.open_streams),
            (ends, steps, 1)
        );
    }
    // The scenario must actually exercise what it claims to.
    assert!(mid_batch_ends > 10, "{mid_batch_ends}");
    assert!(same_env_repeats > 10, "{same_env_repeats}");
    assert!(active_seen > 50, "{active_seen}");
    assert!(client_scores > 5, "{client_scores}");
    assert!(pool.version > cfg.cap as u64 + 3, "replacements happened");
    drop(s);
    wait_open_streams(&mut c, "ref", 0).await;
    // Unfinished episodes of the closed stream were discarded.
    check_pool(&mut c, "ref", &pool, "after close").await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reference_discrete_multi_env_stream() {
    let cfg = Cfg {
        n: 3,
        m: 0,
        cap: 4,
        k: 2,
        start: 1,
        min_pool: 2,
        alpha: 0.7,
        beta: 0.5,
        gamma: 0.9,
        max_len: 6,
        spread: false,
    };
    reference_scenario(cfg, 3, 150, 7).await;
    // k = capacity, start 0, min_pool_size 1, long trajectories.
    let cfg = Cfg {
        n: 2,
        k: 5,
        cap: 5,
        start: 0,
        min_pool: 1,
        max_len: 100,
        ..cfg
    };
    reference_scenario(cfg, 2, 100, 11).await;
    // The same with require_score_spread (SPEC v1.3): scores and rewards come from small
    // sets, so pools of equal scores (a pool of one, first) come and go.
    reference_scenario(
        Cfg {
            spread: true,
            ..cfg
        },
        2,
        100,
        13,
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reference_continuous_multi_env_stream() {
    let cfg = Cfg {
        n: 0,
        m: 2,
        cap: 5,
        k: 3,
        start: 2,
        min_pool: 3,
        alpha: 1.25,
        beta: 0.8,
        gamma: 0.99,
        max_len: 7,
        spread: false,
    };
    reference_scenario(cfg, 4, 150, 3).await;
}

/// Hand-written: an episode ends in the middle of a batch; its ending step is shaped
/// against the old pool, and later entries of the same batch see the new one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn episode_end_mid_batch_is_seen_by_later_entries() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(3, 2, 2, 0, 1)).await;
    let (mut s, _) = Stream::open(&mut c, "t", 2).await.unwrap();
    // env 0: [0, 1] ends (score 1 + 1 = 2) at entry 1; env 1 steps after it.
    let b = StepBatch {
        env_ids: vec![0, 0, 1, 1, 1],
        actions: vec![0, 1, 0, 2, 2],
        rewards: vec![1.0, 1.0, 0.0, 0.0, 0.0],
        terminated: vec![false, true, false, false, false],
        ..Default::default()
    };
    let out = s.step(b).await.unwrap();
    assert_eq!(out.steps, vec![0, 1, 0, 1, 2]);
    // Entries 0 and 1 saw the empty pool; entry 2 (env 1, t = 0) sees [0, 1]: exact match,
    // a single trajectory has x = 1, P = 1: r = e − e^0.5.
    assert_eq!(out.knn_active, vec![false, false, true, true, false]);
    let r1 = 1f64.exp() - 0.5f64.exp();
    assert!((out.knn_rewards[2] - r1).abs() < 1e-12);
    // t = 1: dis = 2 > 0, only trajectory: P = 1 again.
    assert!((out.knn_rewards[3] - r1).abs() < 1e-12);
    assert_eq!(out.knn_rewards[4], 0.0, "t = 2 = L_min: inactive");
    assert_eq!(out.pool_version, 1);
    assert_eq!(out.rewards[0], 1.0);
    assert!((out.rewards[2] - (0.8 * r1)).abs() < 1e-12);
    let p = get_pool(&mut c, "t").await;
    assert_eq!(p.trajectories.len(), 1);
    assert_eq!(p.trajectories[0].actions, vec![0, 1]);
    assert_eq!(p.trajectories[0].score, 2.0);

    // Two episodes of the same env end in one batch, with and without a client score;
    // the second is shaped after the first was inserted.
    let b = StepBatch {
        env_ids: vec![0, 0, 0],
        actions: vec![2, 2, 1],
        rewards: vec![5.0, 7.0, 1.0],
        truncated: vec![true, false, true],
        episode_scores: [(0u32, 0.5)].into_iter().collect(),
        ..Default::default()
    };
    let out = s.step(b).await.unwrap();
    assert_eq!(out.steps, vec![0, 0, 1]);
    assert_eq!(out.pool_version, 3);
    let p = get_pool(&mut c, "t").await;
    let got: Vec<(Vec<u32>, f64, u64)> = p
        .trajectories
        .iter()
        .map(|t| (t.actions.clone(), t.score, t.seq))
        .collect();
    // [2] score 0.5 inserted (pool not full); then [2, 1] score 8 replaces the 0.5.
    assert_eq!(got, vec![(vec![0, 1], 2.0, 1), (vec![2, 1], 8.0, 3)]);
    // Entry 1 (env 0, t = 0, action 2) was shaped against {[0, 1] s = 2, [2] s = 0.5}:
    // x = (1, 0), dis = (2, 0): an exact match, P = (0, 1), so f = 0.
    assert!((out.knn_rewards[1] - (1.0 - 0.5f64.exp())).abs() < 1e-12);
    drop(s);
    server.shutdown().await;
}

/// The potential term: terminated -> V(s') = 0, truncated -> the sent V(s') is used;
/// Q-values -> max.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn potential_term_terminated_vs_truncated() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let mut cfg = discrete(2, 1, 1, 0, 1);
    cfg.alpha = Some(0.0);
    cfg.gamma = Some(0.5);
    cfg.beta = Some(2.0);
    create(&mut c, "t", cfg).await;
    let (mut s, _) = Stream::open(&mut c, "t", 3).await.unwrap();
    let b = StepBatch {
        actions: vec![0, 1, 1],
        rewards: vec![1.0, 1.0, 1.0],
        terminated: vec![true, false, false],
        truncated: vec![false, true, false],
        values: vec![1.5, 1.5, 1.5],
        next_values: vec![3.0, 3.0, 3.0],
        ..Default::default()
    };
    let out = s.step(b).await.unwrap();
    assert_eq!(out.potentials, vec![-1.5, 0.0, 0.0]);
    assert_eq!(out.rewards, vec![1.0 - 3.0, 1.0, 1.0]);
    let b = StepBatch {
        actions: vec![0, 1, 0],
        rewards: vec![0.0, 0.0, 0.0],
        terminated: vec![true, false, true],
        truncated: vec![false, true, true],
        q_values: vec![0.25, -1.0, 2.0, 0.0, 0.1, 0.2],
        next_q_values: vec![4.0, 1.0, -2.0, -3.0, 9.0, 9.0],
        ..Default::default()
    };
    let out = s.step(b).await.unwrap();
    let v = |x: f32| f64::from(x);
    assert_eq!(
        out.potentials,
        vec![-v(0.25), 0.5 * -2.0 - 2.0, -v(0.2)],
        "terminated wins over truncated"
    );
    drop(s);
    server.shutdown().await;
}

/// SPEC v1.3 `require_score_spread` through gRPC: on a pool whose scores are all equal the
/// kNN term of a task with it is inactive (r = 0, and with `gate_potential` F = 0), where
/// the paper's rule pays the flat e − e^½ ≈ 1.07 (times α); once an episode with another
/// score is stored it is active, and both tasks shape alike.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn require_score_spread_waits_for_differing_scores() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let config = |spread: Option<bool>| proto::TaskConfig {
        beta: Some(1.0),
        gamma: Some(0.5),
        gate_potential: Some(true),
        require_score_spread: spread,
        ..discrete(2, 3, 3, 0, 1)
    };
    let paper = create(&mut c, "paper", config(None)).await;
    assert_eq!(paper.config.unwrap().require_score_spread, Some(false));
    let flat = create(&mut c, "flat", config(Some(true))).await;
    assert_eq!(flat.config.unwrap().require_score_spread, Some(true));
    assert_eq!(
        get_task(&mut c, "flat")
            .await
            .config
            .unwrap()
            .require_score_spread,
        Some(true)
    );
    // A different value is a different config, named in the error.
    let err = c
        .create_task(proto::CreateTaskRequest {
            task_id: "flat".into(),
            config: Some(config(Some(false))),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::AlreadyExists, "{err:?}");
    assert!(
        err.message().contains("require_score_spread"),
        "{}",
        err.message()
    );
    for id in ["paper", "flat"] {
        add(&mut c, id, dtraj(&[0, 0, 0, 0], 1.0)).await;
        add(&mut c, id, dtraj(&[1, 1, 1, 1], 1.0)).await;
    }
    let (mut p, _) = Stream::open(&mut c, "paper", 1).await.unwrap();
    let mut c2 = connect(server.addr()).await;
    let (mut f, _) = Stream::open(&mut c2, "flat", 1).await.unwrap();
    // F = 0.5 · 4 − 1 = 1 where it counts (an end by truncation keeps V(s')).
    let step = |a: u32, end: Option<f64>| proto::StepBatch {
        actions: vec![a],
        rewards: vec![0.0],
        truncated: vec![end.is_some()],
        values: vec![1.0],
        next_values: vec![4.0],
        episode_scores: end.map(|s| (0u32, s)).into_iter().collect(),
        ..Default::default()
    };
    let flat_bonus = 1f64.exp() - 0.5f64.exp();
    assert!((flat_bonus - 1.07).abs() < 0.01);
    // Equal scores: every x = 1, an exact prefix match with [0, 0, 0, 0], f = 1.
    // The ending step is shaped before its own episode is stored.
    for (t, end) in [(0, None), (1, Some(3.0))] {
        let got = p.step(step(0, end)).await.unwrap();
        assert_eq!(got.knn_active, vec![true], "t = {t}");
        assert_eq!(got.knn_rewards, vec![flat_bonus], "t = {t}");
        assert_eq!(got.potentials, vec![1.0], "t = {t}");
        assert_eq!(got.rewards, vec![0.8 * flat_bonus + 1.0], "t = {t}");
        let got = f.step(step(0, end)).await.unwrap();
        assert_eq!(got.knn_active, vec![false], "t = {t}");
        assert_eq!(got.knn_rewards, vec![0.0], "t = {t}");
        assert_eq!(got.potentials, vec![0.0], "gated F, t = {t}");
        assert_eq!(got.rewards, vec![0.0], "t = {t}");
    }
    // [0, 0] scored 3 is stored in both: S_min 1 < S_max 3. The next episode follows
    // [1, 1, 1, 1], whose x is now 0: f = 0, r = 1 − e^½ < 0 (what the equal scores could
    // not tell); at t = 2, L_min = 2 ends the kNN term.
    for id in ["paper", "flat"] {
        let stats = get_task(&mut c, id).await.stats.unwrap();
        assert_eq!(
            (stats.pool_size, stats.worst_score, stats.best_score),
            (3, 1.0, 3.0)
        );
    }
    for t in 0..3 {
        let (gp, gf) = (
            p.step(step(1, None)).await.unwrap(),
            f.step(step(1, None)).await.unwrap(),
        );
        assert_eq!(gp, gf, "t = {t}: both tasks shape alike");
        let active = t < 2;
        let r = if active { 1.0 - 0.5f64.exp() } else { 0.0 };
        assert_eq!(gf.knn_active, vec![active], "t = {t}");
        assert_eq!(gf.knn_rewards, vec![r], "t = {t}");
        assert_eq!(
            gf.potentials,
            vec![if active { 1.0 } else { 0.0 }],
            "t = {t}"
        );
    }
    drop((p, f));
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Several streams on one task
// ---------------------------------------------------------------------------------------

fn dentry(env: usize, a: u32, reward: f64, terminated: bool, score: Option<f64>) -> Entry {
    Entry {
        env,
        act: Act::D(a),
        reward,
        terminated,
        truncated: false,
        vals: Vals::None,
        score,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_streams_share_one_pool() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let cfg = Cfg {
        n: 4,
        m: 0,
        cap: 3,
        k: 2,
        start: 0,
        min_pool: 1,
        alpha: 0.8,
        beta: 0.8,
        gamma: 0.99,
        max_len: 100,
        spread: false,
    };
    create(&mut c, "shared", cfg.proto()).await;
    let mut pool = RefPool::new(cfg.cap);
    for (acts, score) in [
        (&[0u32, 1, 2, 3, 0, 1, 2, 3][..], 1.0),
        (&[3, 3, 3, 3, 3, 3][..], 2.0),
    ] {
        add(&mut c, "shared", dtraj(acts, score)).await;
        pool.offer(acts.iter().map(|&a| Act::D(a)).collect(), score);
    }
    let mut c2 = connect(server.addr()).await;
    let (mut a, _) = Stream::open(&mut c, "shared", 1).await.unwrap();
    let (mut b, opened) = Stream::open(&mut c2, "shared", 1).await.unwrap();
    assert_eq!(opened.stats.unwrap().open_streams, 2);
    assert_eq!(
        get_task(&mut c, "shared").await.stats.unwrap().open_streams,
        2
    );
    let mut ra = RefStream::new(cfg, 1);
    let mut rb = RefStream::new(cfg, 1);

    async fn run(
        s: &mut Stream,
        r: &mut RefStream,
        pool: &mut RefPool,
        entries: Vec<Entry>,
        ctx: &str,
    ) -> Vec<Out> {
        let want = r.batch(pool, &entries);
        let got = s.step(step_batch(&entries, true)).await.unwrap();
        let got = {
            assert_eq!(got.pool_version, pool.version, "{ctx}");
            outs(&got)
        };
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert_out(g, w, &format!("{ctx} entry {i}"));
        }
        got
    }
    // A: three steps of an episode.
    let e = vec![
        dentry(0, 0, 0.0, false, None),
        dentry(0, 1, 0.0, false, None),
        dentry(0, 3, 0.0, false, None),
    ];
    run(&mut a, &mut ra, &mut pool, e, "A1").await;
    // B: a whole episode [0, 1, 3, 3, 2, 2] with score 5 ends: inserted (pool not full).
    let e: Vec<Entry> = [0, 1, 3, 3, 2, 2]
        .iter()
        .enumerate()
        .map(|(i, &x)| dentry(0, x, 0.0, i == 5, (i == 5).then_some(5.0)))
        .collect();
    run(&mut b, &mut rb, &mut pool, e, "B1").await;
    assert_eq!(pool.version, 3);
    // A's next step (t = 3) sees B's trajectory with its from-scratch distance over
    // t = 0..3: A's prefix [0, 1, 3, 3] matches B's exactly (dis = 0): P concentrates on it.
    let got = run(
        &mut a,
        &mut ra,
        &mut pool,
        vec![dentry(0, 3, 0.0, false, None)],
        "A2",
    )
    .await;
    assert!(got[0].active);
    assert!((got[0].knn - (1f64.exp() - 0.5f64.exp())).abs() < 1e-12);
    // B again, replacing the worst (score 1) with a better episode; A sees it next step.
    let e: Vec<Entry> = [3, 3, 0, 0, 0]
        .iter()
        .enumerate()
        .map(|(i, &x)| dentry(0, x, 1.0, i == 4, None))
        .collect();
    run(&mut b, &mut rb, &mut pool, e, "B2").await;
    assert_eq!(
        pool.trajs.iter().map(|t| t.seq).collect::<Vec<_>>(),
        vec![2, 3, 4]
    );
    for x in [0, 0, 2] {
        run(
            &mut a,
            &mut ra,
            &mut pool,
            vec![dentry(0, x, 0.0, false, None)],
            "A3",
        )
        .await;
    }
    check_pool(&mut c, "shared", &pool, "end").await;

    // open_streams drops as the streams close.
    let rest = a.close();
    drop(rest);
    wait_open_streams(&mut c, "shared", 1).await;
    drop(b);
    wait_open_streams(&mut c, "shared", 0).await;
    // A's unfinished episode was discarded.
    check_pool(&mut c, "shared", &pool, "after close").await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reset_pool_while_a_stream_is_open() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(2, 2, 2, 0, 1)).await;
    add(&mut c, "t", dtraj(&[0, 0, 0, 0], 1.0)).await;
    add(&mut c, "t", dtraj(&[1, 1, 1, 1], 2.0)).await;
    let (mut s, _) = Stream::open(&mut c, "t", 1).await.unwrap();
    let out = s.step(batch(&[0], &[0.0], &[false])).await.unwrap();
    assert_eq!(out.knn_active, vec![true]);
    assert_eq!(out.pool_version, 2);
    let t = c
        .reset_pool(proto::ResetPoolRequest {
            task_id: "t".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(t.stats.unwrap().open_streams, 1);
    let out = s.step(batch(&[0], &[0.0], &[false])).await.unwrap();
    assert_eq!(
        out.knn_active,
        vec![false],
        "the next step sees the empty pool"
    );
    assert_eq!(out.knn_rewards, vec![0.0]);
    assert_eq!(out.steps, vec![1], "the episode goes on");
    assert_eq!(out.pool_version, 3);
    // The episode ends and is inserted into the empty pool with the next seq.
    let out = s.step(batch(&[1], &[3.0], &[true])).await.unwrap();
    assert_eq!(out.pool_version, 4);
    let p = get_pool(&mut c, "t").await;
    assert_eq!(p.trajectories.len(), 1);
    assert_eq!(p.trajectories[0].actions, vec![0, 0, 1]);
    assert_eq!((p.trajectories[0].seq, p.trajectories[0].score), (3, 3.0));
    // A new episode now sees the one trajectory.
    let out = s.step(batch(&[0], &[0.0], &[false])).await.unwrap();
    assert_eq!(out.knn_active, vec![true]);
    drop(s);
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delete_task_while_a_stream_is_open() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(2, 2, 2, 0, 1)).await;
    create(&mut c, "other", discrete(2, 2, 2, 0, 1)).await;
    let (mut s, _) = Stream::open(&mut c, "t", 1).await.unwrap();
    let (mut o, _) = Stream::open(&mut c, "other", 1).await.unwrap();
    s.step(batch(&[0], &[0.0], &[false])).await.unwrap();
    c.delete_task(proto::DeleteTaskRequest {
        task_id: "t".into(),
    })
    .await
    .unwrap();
    let e = s
        .step(batch(&[1], &[0.0], &[true]))
        .await
        .expect_err("NOT_FOUND at the next batch");
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    // The stream has ended.
    assert!(matches!(s.recv().await, Ok(None) | Err(_)));
    // Other tasks' streams are unaffected.
    let out = o.step(batch(&[1], &[0.0], &[true])).await.unwrap();
    assert_eq!(out.pool_version, 1);
    // Recreating the id gives a fresh task; the old episode did not leak into it.
    create(&mut c, "t", discrete(2, 2, 2, 0, 1)).await;
    assert!(get_pool(&mut c, "t").await.trajectories.is_empty());
    drop(o);
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Concurrency
// ---------------------------------------------------------------------------------------

/// A deterministic script of batches for one stream: entries and per-episode unique
/// scores (so that the final pool can be predicted whatever the interleaving).
fn script(cfg: &Cfg, num_envs: usize, batches: usize, seed: u64) -> Vec<Vec<Entry>> {
    let mut rng = Rng(seed);
    let mut lens = vec![0usize; num_envs];
    (0..batches)
        .map(|_| {
            let mut e = random_entries(&mut rng, cfg, num_envs, true, &mut lens);
            for x in &mut e {
                if x.terminated || x.truncated {
                    // Unique scores: seed-dependent, never equal across streams.
                    x.score = Some(rng.below(1 << 40) as f64 + seed as f64 / 1024.0);
                }
            }
            e
        })
        .collect()
}

/// What a stream returned, and the episodes it ended (actions, score).
struct Run {
    outs: Vec<Vec<Out>>,
    versions: Vec<u64>,
    episodes: Vec<(Vec<Act>, f64)>,
}

async fn run_script(
    addr: std::net::SocketAddr,
    task: String,
    cfg: Cfg,
    num_envs: usize,
    script: Vec<Vec<Entry>>,
) -> Run {
    let mut c = connect(addr).await;
    let (mut s, _) = Stream::open(&mut c, &task, num_envs as u32).await.unwrap();
    let mut run = Run {
        outs: Vec::new(),
        versions: Vec::new(),
        episodes: Vec::new(),
    };
    let mut envs = vec![Vec::new(); num_envs];
    for entries in &script {
        let got = s.step(step_batch(entries, true)).await.unwrap();
        run.outs.push(outs(&got));
        run.versions.push(got.pool_version);
        for e in entries {
            envs[e.env].push(e.act.clone());
            if e.terminated || e.truncated {
                let mut acts = std::mem::take(&mut envs[e.env]);
                acts.truncate(cfg.max_len);
                run.episodes.push((acts, e.score.unwrap()));
            }
        }
        tokio::task::yield_now().await;
    }
    run
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_streams_on_several_tasks() {
    let server = start_server(None, |_| {}).await;
    let addr = server.addr();
    let mut c = connect(addr).await;
    let cfg = Cfg {
        n: 3,
        m: 0,
        cap: 6,
        k: 3,
        start: 1,
        min_pool: 2,
        alpha: 0.8,
        beta: 0.8,
        gamma: 0.99,
        max_len: 8,
        spread: false,
    };
    let (num_envs, batches) = (4, 60);
    // Two tasks with one stream each (checked against running alone and the reference),
    // two tasks with three streams each (checked structurally): 8 streams in all.
    for id in [
        "solo-0", "solo-1", "shared-0", "shared-1", "alone-0", "alone-1",
    ] {
        create(&mut c, id, cfg.proto()).await;
    }
    let solo_scripts: Vec<_> = (0..2)
        .map(|i| script(&cfg, num_envs, batches, 100 + i))
        .collect();
    // Alone first.
    let mut alone = Vec::new();
    for (i, sc) in solo_scripts.iter().enumerate() {
        alone.push(run_script(addr, format!("alone-{i}"), cfg, num_envs, sc.clone()).await);
    }
    // Then all 8 at once.
    let mut handles = Vec::new();
    for (i, sc) in solo_scripts.iter().enumerate() {
        handles.push(tokio::spawn(run_script(
            addr,
            format!("solo-{i}"),
            cfg,
            num_envs,
            sc.clone(),
        )));
    }
    let mut shared_scripts = Vec::new();
    for t in 0..2 {
        for j in 0..3u64 {
            let sc = script(&cfg, num_envs, batches, 200 + 10 * t + j);
            shared_scripts.push((t, sc.clone()));
            handles.push(tokio::spawn(run_script(
                addr,
                format!("shared-{t}"),
                cfg,
                num_envs,
                sc,
            )));
        }
    }
    let mut runs = Vec::new();
    for h in handles {
        runs.push(h.await.expect("stream task"));
    }

    // Solo streams: identical to running alone, and to the reference.
    for i in 0..2 {
        let got = &runs[i];
        assert_eq!(
            got.outs, alone[i].outs,
            "solo-{i} differs from running alone"
        );
        assert_eq!(got.versions, alone[i].versions);
        let mut pool = RefPool::new(cfg.cap);
        let mut rs = RefStream::new(cfg, num_envs);
        for (bi, entries) in solo_scripts[i].iter().enumerate() {
            let want = rs.batch(&mut pool, entries);
            for (j, (g, w)) in got.outs[bi].iter().zip(&want).enumerate() {
                assert_out(g, w, &format!("solo-{i} batch {bi} entry {j}"));
            }
            assert_eq!(got.versions[bi], pool.version);
        }
        check_pool(&mut c, &format!("solo-{i}"), &pool, "solo final").await;
    }

    // Shared tasks: structural checks.
    let lo = 1.0 - 0.5f64.exp();
    let hi = 1f64.exp() - 0.5f64.exp();
    for t in 0..2usize {
        let id = format!("shared-{t}");
        let mut offered: Vec<(Vec<Act>, f64)> = Vec::new();
        let (mut total_steps, mut total_ends) = (0u64, 0u64);
        for (k, (tt, sc)) in shared_scripts.iter().enumerate() {
            if *tt != t as u64 {
                continue;
            }
            let run = &runs[2 + k];
            // pool_version never goes backwards within one stream.
            assert!(
                run.versions.windows(2).all(|w| w[0] <= w[1]),
                "{id}: versions {:?}",
                run.versions
            );
            // Steps and potentials do not depend on the pool; r is within its range.
            let mut tcount = vec![0u32; num_envs];
            for (bi, entries) in sc.iter().enumerate() {
                for (e, o) in entries.iter().zip(&run.outs[bi]) {
                    assert_eq!(o.t, tcount[e.env]);
                    tcount[e.env] += 1;
                    if e.terminated || e.truncated {
                        tcount[e.env] = 0;
                    }
                    if o.active {
                        assert!(o.knn >= lo - 1e-12 && o.knn <= hi + 1e-12, "{o:?}");
                        assert!(o.t >= cfg.start as u32);
                    } else {
                        assert_eq!(o.knn, 0.0);
                    }
                    let pot = ref_potential(&cfg, e);
                    assert!((o.pot - pot).abs() <= 1e-12 * (1.0 + pot.abs()));
                    let r = e.reward + cfg.alpha * o.knn + cfg.beta * o.pot;
                    assert!((o.reward - r).abs() <= 1e-12 * (1.0 + r.abs()));
                    total_steps += 1;
                    total_ends += u64::from(e.terminated || e.truncated);
                }
            }
            offered.extend(run.episodes.iter().cloned());
        }
        // The final pool keeps the `cap` best episodes (scores are unique).
        offered.sort_by(|a, b| b.1.total_cmp(&a.1));
        let mut want: Vec<(Vec<Act>, f64)> = offered.into_iter().take(cfg.cap).collect();
        want.sort_by(|a, b| a.1.total_cmp(&b.1));
        let p = get_pool(&mut c, &id).await;
        assert!(p.trajectories.len() <= cfg.cap);
        assert!(p.trajectories.windows(2).all(|w| w[0].seq < w[1].seq));
        let mut got: Vec<(Vec<Act>, f64)> = p
            .trajectories
            .iter()
            .map(|tr| (tr.actions.iter().map(|&a| Act::D(a)).collect(), tr.score))
            .collect();
        got.sort_by(|a, b| a.1.total_cmp(&b.1));
        assert_eq!(got, want, "{id}: the best episodes are kept");
        let st = get_task(&mut c, &id).await.stats.unwrap();
        assert_eq!(st.pool_version, p.pool_version);
        assert_eq!(
            (st.steps_shaped, st.episodes_completed),
            (total_steps, total_ends)
        );
        let max_seen = runs[2 + 3 * t..5 + 3 * t]
            .iter()
            .flat_map(|r| r.versions.iter().copied())
            .max()
            .unwrap();
        assert!(max_seen <= p.pool_version);
    }
    for id in ["solo-0", "shared-0", "shared-1"] {
        wait_open_streams(&mut c, id, 0).await;
    }
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Health and reflection
// ---------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let server = start_server(None, |_| {}).await;
    let addr = server.addr();
    connect(addr).await; // waits until it answers
    let channel = tonic::transport::Channel::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = HealthClient::new(channel.clone());
    for service in ["", "tamrm.v1.Shaping"] {
        let r = health
            .check(HealthCheckRequest {
                service: service.into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(r.status, ServingStatus::Serving as i32, "{service:?}");
    }
    let e = health
        .check(HealthCheckRequest {
            service: "no.such.Service".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);

    let mut refl = ServerReflectionClient::new(channel);
    let req = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut resp = refl
        .server_reflection_info(tokio_stream::iter(vec![req]))
        .await
        .unwrap()
        .into_inner();
    let msg = resp.message().await.unwrap().expect("a reflection answer");
    let Some(MessageResponse::ListServicesResponse(list)) = msg.message_response else {
        panic!("unexpected reflection answer {msg:?}");
    };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    for want in ["tamrm.v1.Shaping", "grpc.health.v1.Health"] {
        assert!(
            names.iter().any(|n| n == want),
            "{want} missing from {names:?}"
        );
    }
    server.shutdown().await;
}

/// SPEC §9 and §12 through the proto: `Open.resume`, `Open.client_id` and
/// `StepBatch.abandon` reach the session layer (the semantics are tested in
/// `src/session/tests.rs`).
#[tokio::test]
async fn resume_and_abandon_travel_through_the_proto() {
    let server = common::start_server(None, |_| {}).await;
    let mut c = common::connect(server.addr()).await;
    common::create(&mut c, "r", common::discrete(2, 4, 4, 0, 1)).await;
    let open = |resume: Vec<proto::EnvResume>| proto::ShapeRequest {
        kind: Some(proto::shape_request::Kind::Open(proto::Open {
            task_id: "r".into(),
            num_envs: 2,
            resume,
            client_id: "c-1".into(),
        })),
    };
    // An invalid resume: the stream ends with INVALID_ARGUMENT naming the field.
    let mut s = common::Stream::raw(&mut c).await.unwrap();
    s.send(open(vec![proto::EnvResume {
        env_id: 5,
        ..Default::default()
    }]))
    .await;
    let e = s.recv().await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(
        e.message().contains("open.resume[0].env_id"),
        "{}",
        e.message()
    );
    // A valid one: env 1 continues at t = 3, env 0 starts at t = 0.
    let mut s = common::Stream::raw(&mut c).await.unwrap();
    s.send(open(vec![proto::EnvResume {
        env_id: 1,
        actions: vec![0, 1, 1],
        reward_sum: 2.0,
        episode: 4,
        ..Default::default()
    }]))
    .await;
    assert!(matches!(
        s.recv().await.unwrap(),
        Some(proto::ShapeResponse {
            kind: Some(proto::shape_response::Kind::Opened(_))
        })
    ));
    let b = s
        .step(common::batch(&[0, 0], &[0.0, 0.0], &[]))
        .await
        .unwrap();
    assert_eq!(b.steps, [0, 3]);
    let b = s
        .step(StepBatch {
            abandon: vec![1],
            ..common::batch(&[0, 0], &[0.0, 0.0], &[])
        })
        .await
        .unwrap();
    assert_eq!(b.steps, [1, 0], "env 1 was abandoned before the entries");
}

/// Streams that never send `Open`, or go quiet after it, are closed after
/// `stream_idle_timeout_secs` with UNAVAILABLE, and stop counting as open.
#[tokio::test]
async fn idle_and_never_opened_streams_are_closed() {
    let server = common::start_server(None, |s| s.limits.stream_idle_timeout_secs = 1).await;
    let mut c = common::connect(server.addr()).await;
    common::create(&mut c, "idle", common::discrete(2, 2, 2, 0, 1)).await;
    let start = std::time::Instant::now();
    let mut never = common::Stream::raw(&mut c).await.unwrap();
    let (mut quiet, _) = common::Stream::open(&mut c, "idle", 1).await.unwrap();
    common::wait_open_streams(&mut c, "idle", 1).await;
    for s in [&mut never, &mut quiet] {
        let e = tokio::time::timeout(std::time::Duration::from_secs(10), async {
            loop {
                match s.recv().await {
                    Err(e) => return e,
                    Ok(Some(_)) => continue,
                    Ok(None) => panic!("stream ended without a status"),
                }
            }
        })
        .await
        .expect("closed within 10 s");
        assert_eq!(e.code(), tonic::Code::Unavailable);
        assert!(
            e.message().contains("stream_idle_timeout_secs"),
            "{}",
            e.message()
        );
    }
    assert!(start.elapsed() >= std::time::Duration::from_millis(900));
    common::wait_open_streams(&mut c, "idle", 0).await;
    // An active stream is not closed: each message resets its timer.
    let (mut busy, _) = common::Stream::open(&mut c, "idle", 1).await.unwrap();
    for _ in 0..4 {
        tokio::time::sleep(std::time::Duration::from_millis(400)).await;
        busy.step(common::batch(&[0], &[0.0], &[])).await.unwrap();
    }
}

/// A client that sends and never reads its answers is held back (HTTP/2 flow control
/// behind the server's bounded answer queue): its sends stop being taken after a bounded
/// number of batches, and the server goes on serving other streams, of the same
/// connection too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_never_reads_is_held_back_not_buffered() {
    use prost::Message;
    use std::time::Duration;
    let server = common::start_server(None, |_| {}).await;
    let mut c = common::connect(server.addr()).await;
    common::create(&mut c, "slow", common::discrete(4, 8, 2, 1, 2)).await;
    let (slow, _) = common::Stream::open(&mut c, "slow", 64).await.unwrap();
    let n = 64;
    let batch = common::batch(&vec![1; n], &vec![1.0; n], &vec![false; n]);
    let size = proto::ShapeRequest {
        kind: Some(proto::shape_request::Kind::Steps(batch.clone())),
    }
    .encoded_len();
    let mut taken = 0usize;
    loop {
        let send = slow.tx.send(proto::ShapeRequest {
            kind: Some(proto::shape_request::Kind::Steps(batch.clone())),
        });
        match tokio::time::timeout(Duration::from_secs(1), send).await {
            Ok(Ok(())) => taken += 1,
            Ok(Err(_)) => panic!("the server ended the stream"),
            Err(_) => break, // held back
        }
        assert!(
            taken * size < 64 << 20,
            "{taken} batches ({size} B each) taken without a read: no backpressure"
        );
    }
    assert!(taken > 0);
    // The server is not stuck: another stream on the same connection is served.
    let b = tokio::time::timeout(Duration::from_secs(10), async {
        let (mut other, _) = common::Stream::open(&mut c, "slow", 1).await.unwrap();
        other.step(common::batch(&[2], &[1.0], &[false])).await
    })
    .await
    .expect("another stream of the connection is served while one is stalled")
    .unwrap();
    assert_eq!(b.steps, [0]);
    // Reading the slow stream's answers lets it go on, in order.
    let mut slow = slow;
    let first = slow.recv().await.unwrap().unwrap();
    match first.kind {
        Some(proto::shape_response::Kind::Shaped(s)) => assert_eq!(s.steps, vec![0; n]),
        other => panic!("expected shaped, got {other:?}"),
    }
}
