//! Cost of one shaped step (`Episode::step`) as a function of the pool size |D| and of the
//! step index t, and cost of the first step after the pool changed (the O(t) catch-up).
//!
//! Every measured step is at index t..t+CHUNK of an episode that was advanced to t
//! outside the timing, against a full pool of trajectories longer than every measured t,
//! with start_step 0: the kNN term is active at every measured step (asserted once per
//! benchmark before timing).
//!
//! Timing: by default the benchmark times with the calling thread's CPU clock
//! (`CLOCK_THREAD_CPUTIME_ID`, Linux 64-bit), so time the thread spends descheduled on a
//! shared, loaded machine is not counted; `TAMRM_BENCH_CLOCK=wall` uses the wall clock
//! (`Instant`) instead, as does every other platform. Each timed region covers many steps
//! (~1000 steps over several clones), so the clock's own cost is negligible.
//!
//! Run: `cargo bench --bench shaping`; see docs/benchmarks.md.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use tamrm::core::{
    ActionRef, ActionSeq, Episode, KnnScratch, Pool, StepInput, TaskConfig, TaskConfigInput, Values,
};

#[path = "common/workload.rs"]
mod workload;
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
use workload::thread_cpu_time;

/// Discrete actions of the main benchmarks.
const NUM_ACTIONS: u32 = 4;
/// Dimension of the continuous benchmark.
const ACTION_DIM: usize = 6;
/// Length of every stored trajectory: more than the largest t plus a chunk.
const TRAJ_LEN: usize = 12_000;
/// Pool sizes and step indices measured.
const POOL_SIZES: [usize; 3] = [10, 30, 100];
const STEPS: [usize; 3] = [10, 1_000, 10_000];
/// Steps timed back to back from one clone of the episode at t: the measured steps are
/// t+1 ..= t+CHUNK, so t drifts by at most CHUNK.
const CHUNK: usize = 64;

/// A small deterministic generator (SplitMix64), so the bench needs no extra crate.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u32) -> u32 {
        (self.next() % u64::from(n)) as u32
    }
    fn unit(&mut self) -> f32 {
        // Uniform in [-1, 1).
        (self.next() >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    }
}

/// The actions of one space, either kind.
#[derive(Clone)]
enum Actions {
    Discrete(Vec<u32>),
    Continuous(Vec<f32>),
}

impl Actions {
    fn random(rng: &mut Rng, len: usize, dim: usize) -> Actions {
        if dim == 0 {
            Actions::Discrete((0..len).map(|_| rng.below(NUM_ACTIONS)).collect())
        } else {
            Actions::Continuous((0..len * dim).map(|_| rng.unit()).collect())
        }
    }
    fn get(&self, j: usize) -> ActionRef<'_> {
        match self {
            Actions::Discrete(v) => ActionRef::Discrete(v[j]),
            Actions::Continuous(v) => {
                ActionRef::Continuous(&v[j * ACTION_DIM..(j + 1) * ACTION_DIM])
            }
        }
    }
    fn to_seq(&self) -> ActionSeq {
        match self {
            Actions::Discrete(v) => ActionSeq::Discrete(v.clone()),
            Actions::Continuous(v) => ActionSeq::Continuous {
                dim: ACTION_DIM,
                data: v.clone(),
            },
        }
    }
}

/// Steps per timed region (at most 256 clones of the episode are prepared for one).
const STEPS_PER_REGION: usize = 1024;

/// The clock the measurements use (see the module docs).
#[derive(Clone, Copy)]
enum Clock {
    Wall(Instant),
    #[cfg(all(target_os = "linux", target_pointer_width = "64"))]
    ThreadCpu,
}

impl Clock {
    fn from_env() -> Clock {
        #[cfg(all(target_os = "linux", target_pointer_width = "64"))]
        if std::env::var("TAMRM_BENCH_CLOCK").as_deref() != Ok("wall") {
            return Clock::ThreadCpu;
        }
        Clock::Wall(Instant::now())
    }

    /// Time since an arbitrary origin fixed per clock.
    fn now(self) -> Duration {
        match self {
            Clock::Wall(origin) => origin.elapsed(),
            #[cfg(all(target_os = "linux", target_pointer_width = "64"))]
            Clock::ThreadCpu => thread_cpu_time(),
        }
    }
}

/// Runs `iters` timed calls of `run(episode, j)` for j in 0..per_clone on fresh clones
/// made by `prepare` outside the timing (about STEPS_PER_REGION calls per timed region), and
/// returns the time they took.
fn measure(
    iters: u64,
    clock: Clock,
    per_clone: usize,
    mut prepare: impl FnMut() -> Episode,
    mut run: impl FnMut(&mut Episode, usize),
) -> Duration {
    let mut total = Duration::ZERO;
    let mut done = 0u64;
    while done < iters {
        let clones = (STEPS_PER_REGION / per_clone).clamp(1, 256);
        let todo = (iters - done).min((clones * per_clone) as u64) as usize;
        let mut episodes: Vec<Episode> = (0..todo.div_ceil(per_clone)).map(|_| prepare()).collect();
        let start = clock.now();
        let mut left = todo;
        for ep in &mut episodes {
            for j in 0..per_clone.min(left) {
                run(ep, j);
            }
            left = left.saturating_sub(per_clone);
        }
        total += clock.now() - start;
        done += todo as u64;
        drop(episodes);
    }
    total
}

fn step_input(action: ActionRef<'_>) -> StepInput<'_> {
    StepInput {
        action,
        reward: 0.0,
        terminated: false,
        truncated: false,
        values: Values::None,
        score: None,
    }
}

/// A task, its full pool, and an episode's actions.
struct Fixture {
    cfg: TaskConfig,
    pool: Pool,
    episode_actions: Actions,
    rng: Rng,
}

impl Fixture {
    /// |D| = `pool_size` random trajectories of TRAJ_LEN actions with distinct scores.
    fn new(pool_size: usize, k: usize, dim: usize) -> Fixture {
        let cfg = TaskConfig::resolve(&TaskConfigInput {
            num_actions: if dim == 0 { NUM_ACTIONS } else { 0 },
            action_dim: dim as u32,
            pool_capacity: Some(pool_size as u32),
            k: Some(k as u32),
            start_step: Some(0),
            ..Default::default()
        })
        .expect("valid config");
        let mut rng = Rng(0x7A3D_0000 + pool_size as u64 * 31 + k as u64 + dim as u64 * 7);
        let mut pool = Pool::new(pool_size);
        for i in 0..pool_size {
            let actions = Actions::random(&mut rng, TRAJ_LEN, dim).to_seq();
            let change = pool.plan_offer(actions, i as f64).expect("pool not full");
            pool.apply(&change);
        }
        let episode_actions = Actions::random(&mut rng, TRAJ_LEN, dim);
        Fixture {
            cfg,
            pool,
            episode_actions,
            rng,
        }
    }

    /// An episode that has taken steps 0..t.
    fn episode_at(&self, t: usize) -> Episode {
        let mut ep = Episode::new(self.cfg.action_space);
        let mut scratch = KnnScratch::default();
        for j in 0..t {
            ep.step(
                &self.cfg,
                &self.pool,
                &step_input(self.episode_actions.get(j)),
                &mut scratch,
            );
        }
        assert_eq!(ep.t(), t as u64);
        ep
    }

    /// Checks, outside any timing, that the step at t is shaped with the kNN term on.
    fn assert_active(&self, base: &Episode, t: usize) {
        let mut ep = base.clone();
        let (out, _) = ep.step(
            &self.cfg,
            &self.pool,
            &step_input(self.episode_actions.get(t)),
            &mut KnnScratch::default(),
        );
        assert!(out.knn_active && out.knn_reward.is_finite(), "{out:?}");
        assert_eq!(out.step, t as u64);
    }
}

/// Times steps t+1 ..= t+CHUNK of clones of `base` (at t). The clone and one untimed step
/// at t (which also takes the growth of the recorded-actions vector a fresh clone would
/// otherwise pay on its first push) stay outside the timing.
fn bench_steps_at(c: &mut Criterion, group_name: &str, pool_size: usize, k: usize, dim: usize) {
    let clock = Clock::from_env();
    let mut group = c.benchmark_group(group_name);
    let fx = Fixture::new(pool_size, k, dim);
    for &t in &STEPS {
        let base = fx.episode_at(t);
        fx.assert_active(&base, t);
        let mut scratch = KnnScratch::default();
        group.bench_function(BenchmarkId::new(format!("D={pool_size}"), t), |b| {
            b.iter_custom(|iters| {
                let mut prep_scratch = KnnScratch::default();
                measure(
                    iters,
                    clock,
                    CHUNK,
                    || {
                        let mut ep = base.clone();
                        let input = step_input(fx.episode_actions.get(t));
                        ep.step(&fx.cfg, &fx.pool, &input, &mut prep_scratch);
                        ep
                    },
                    |ep, j| {
                        let input = step_input(fx.episode_actions.get(t + 1 + j));
                        black_box(ep.step(&fx.cfg, &fx.pool, &input, &mut scratch));
                    },
                )
            })
        });
    }
    group.finish();
}

fn discrete_k_eq_d(c: &mut Criterion) {
    for &d in &POOL_SIZES {
        bench_steps_at(c, "step/discrete_n4_k=D", d, d, 0);
    }
}

fn discrete_k_half_d(c: &mut Criterion) {
    for &d in &POOL_SIZES {
        bench_steps_at(c, "step/discrete_n4_k=D_over_2", d, d / 2, 0);
    }
}

fn continuous_m6(c: &mut Criterion) {
    bench_steps_at(c, "step/continuous_m6_k=D", 30, 30, ACTION_DIM);
}

/// The first step after another stream inserted a trajectory (replacing the worst one)
/// while this episode is at t = 1000: the episode re-aligns its distances by seq and
/// computes the new trajectory's distance over the 1000-action prefix once.
fn resync_after_insert(c: &mut Criterion) {
    const T: usize = 1_000;
    let clock = Clock::from_env();
    let mut group = c.benchmark_group("resync/discrete_n4_k=D_t=1000");
    for &d in &POOL_SIZES {
        let mut fx = Fixture::new(d, d, 0);
        let base = fx.episode_at(T);
        let mut changed = fx.pool.clone();
        let new_traj = Actions::random(&mut fx.rng, TRAJ_LEN, 0).to_seq();
        let change = changed
            .plan_offer(new_traj, 1e6)
            .expect("a better score replaces the worst");
        changed.apply(&change);
        assert_ne!(changed.version(), fx.pool.version());
        let mut ep = base.clone();
        let (out, _) = ep.step(
            &fx.cfg,
            &changed,
            &step_input(fx.episode_actions.get(T)),
            &mut KnnScratch::default(),
        );
        assert!(out.knn_active && out.step == T as u64, "{out:?}");
        let mut scratch = KnnScratch::default();
        for (name, pool) in [
            ("first_step_after_insert", &changed),
            // The same single step at t = 1000 without a pool change, measured the same way.
            ("step_without_change", &fx.pool),
        ] {
            group.bench_function(BenchmarkId::new(name, d), |b| {
                b.iter_custom(|iters| {
                    measure(
                        iters,
                        clock,
                        1,
                        || base.clone(),
                        |ep, _| {
                            let input = step_input(fx.episode_actions.get(T));
                            black_box(ep.step(&fx.cfg, pool, &input, &mut scratch));
                        },
                    )
                })
            });
        }
    }
    group.finish();
}

fn config() -> Criterion {
    Criterion::default()
        .sample_size(30)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
}

criterion_group! {
    name = benches;
    config = config();
    targets = discrete_k_eq_d, discrete_k_half_d, continuous_m6, resync_after_insert
}
criterion_main!(benches);
