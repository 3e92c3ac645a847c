//! A learner in Rust: connect, create a task, open a session, step 8 environments of a
//! tiny environment, print the episodes and the pool size.
//!
//! ```text
//! target/release/tamrm serve --listen 127.0.0.1:50051 &
//! cargo run -p tamrm-client --example learner -- 127.0.0.1:50051
//! ```
//!
//! Options by environment: `TAMRM_API_KEY` (sent as `authorization: Bearer <key>`),
//! `TAMRM_CA` (a PEM file: TLS with that CA).

use std::time::Duration;

use tamrm_client::{proto, Batch, Channel, ChannelOptions};

const NUM_ENVS: usize = 8;

/// A tiny environment: walk right on a line of 5 cells; action 1 steps right, 0 stays,
/// 2 steps left. Reward 1 at the last cell, which ends the episode; 20 steps at most.
#[derive(Clone, Copy, Default)]
struct Line {
    cell: i32,
    t: u32,
}

impl Line {
    /// One step: (reward, terminated, truncated).
    fn step(&mut self, action: u32) -> (f64, bool, bool) {
        self.cell = (self.cell + [0, 1, -1][action as usize]).clamp(0, 4);
        self.t += 1;
        let done = self.cell == 4;
        let truncated = !done && self.t >= 20;
        if done || truncated {
            *self = Line::default();
        }
        (if done { 1.0 } else { 0.0 }, done, truncated)
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let addrs: Vec<String> = std::env::args().skip(1).collect();
    let addrs = if addrs.is_empty() {
        vec!["127.0.0.1:50051".to_string()]
    } else {
        addrs
    };
    let mut options = ChannelOptions::new();
    if let Ok(key) = std::env::var("TAMRM_API_KEY") {
        options = options.api_key(&key);
    }
    if let Ok(ca) = std::env::var("TAMRM_CA") {
        options = options.root_certificates(std::fs::read(ca)?)?;
    }
    // Several addresses: replicas, tried in turn.
    let channel = Channel::connect(&addrs, options)?;
    channel.wait_ready(Duration::from_secs(10))?;

    let task = channel.create_task(&proto::CreateTaskRequest {
        task_id: "rust-learner".into(),
        config: Some(proto::TaskConfig {
            num_actions: 3,
            pool_capacity: Some(16),
            k: Some(4),
            // The kNN term from the second step on, once 4 episodes are in the pool.
            start_step: Some(1),
            min_pool_size: Some(4),
            ..Default::default()
        }),
    })?;
    println!("task {:?}: {:?}", task.task_id, task.config);

    let mut session = channel.open("rust-learner", NUM_ENVS as u32, "rust-learner-1")?;
    let mut envs = [Line::default(); NUM_ENVS];
    let mut seed = 12345u64;
    let (mut episodes, mut env_sum, mut shaped_sum) = (0, 0.0, 0.0);
    for _ in 0..200 {
        // A random policy that prefers stepping right.
        let actions: Vec<u32> = (0..NUM_ENVS)
            .map(|_| {
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
                [1, 1, 0, 2][(seed >> 62) as usize]
            })
            .collect();
        let (mut rewards, mut terminated, mut truncated) = (vec![], vec![], vec![]);
        for (env, &a) in envs.iter_mut().zip(&actions) {
            let (r, done, cut) = env.step(a);
            rewards.push(r);
            terminated.push(done);
            truncated.push(cut);
        }
        let answer = session.step(&Batch {
            actions: &actions,
            rewards: &rewards,
            terminated: &terminated,
            truncated: &truncated,
            ..Batch::default()
        })?;
        episodes += terminated.iter().chain(&truncated).filter(|&&d| d).count();
        env_sum += rewards.iter().sum::<f64>();
        shaped_sum += answer.rewards.iter().sum::<f64>();
    }
    session.close();
    let pool = channel.get_pool("rust-learner")?;
    println!(
        "episodes: {episodes}, pool size: {} (version {}), reward sum: {env_sum:.3} from the \
         environments, {shaped_sum:.3} shaped",
        pool.trajectories.len(),
        pool.pool_version
    );
    Ok(())
}
