//! What the throughput benchmarks share (`loadgen.rs`, `session_path.rs`, `shaping.rs`):
//! the loadgen's workload, so that `session_path` replays exactly the loadgen's batches,
//! and the thread CPU clock. Each bench uses part of it.
#![allow(dead_code)]

use std::time::Duration;

use tamrm::proto;

/// A tiny deterministic PRNG (xorshift64*), so runs are repeatable without extra deps.
pub struct Rng(pub u64);
impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// One `StepBatch` of `n` entries: random discrete actions (n = 2), reward 1, episodes
/// ending with probability 1/`episode_len`, values sent.
pub fn step_batch(
    rng: &mut Rng,
    n: usize,
    episode_len: u64,
    episodes: &mut u64,
) -> proto::StepBatch {
    let mut terminated = Vec::with_capacity(n);
    for _ in 0..n {
        let end = rng.below(episode_len) == 0;
        *episodes += u64::from(end);
        terminated.push(end);
    }
    proto::StepBatch {
        actions: (0..n).map(|_| rng.below(2) as u32).collect(),
        rewards: (0..n).map(|_| 1.0).collect(),
        terminated,
        values: (0..n).map(|_| 0.5).collect(),
        next_values: (0..n).map(|_| 0.6).collect(),
        ..Default::default()
    }
}

/// CPU time of the calling thread (`CLOCK_THREAD_CPUTIME_ID`, 64-bit Linux): time spent
/// descheduled on a shared machine is not counted.
/// The echo floor's answer to a batch (`loadgen.rs`'s `Echo::shape`): a `ShapedBatch` of
/// the same size built from the request's columns, no session, no core.
pub fn echo(b: proto::StepBatch) -> proto::ShapedBatch {
    proto::ShapedBatch {
        knn_rewards: b.rewards.clone(),
        potentials: b.values.iter().map(|&v| f64::from(v)).collect(),
        steps: b.actions,
        knn_active: b.terminated,
        rewards: b.rewards,
        pool_version: 1,
    }
}

#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
pub fn thread_cpu_time() -> Duration {
    #[repr(C)]
    struct Timespec {
        tv_sec: i64,
        tv_nsec: i64,
    }
    extern "C" {
        fn clock_gettime(clock_id: i32, tp: *mut Timespec) -> i32;
    }
    const CLOCK_THREAD_CPUTIME_ID: i32 = 3;
    let mut ts = Timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime only writes the struct it is given, which has the layout of
    // `struct timespec` on 64-bit Linux (two 64-bit fields).
    let rc = unsafe { clock_gettime(CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID) failed");
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}
