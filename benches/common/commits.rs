//! What the commit benchmarks share (`commits.rs`, `redis_store.rs`): the task, the
//! episodes, and one committer's loop.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::core::{ActionSeq, Pool, TaskConfig, TaskConfigInput};
use tamrm::store::{Counters, PoolOp, Store};

/// Actions per stored episode.
pub const EPISODE_LEN: u32 = 200;

/// A discrete task whose pool (capacity 1000) is never full in these runs.
pub fn config() -> TaskConfig {
    TaskConfig::resolve(&TaskConfigInput {
        num_actions: 4,
        pool_capacity: Some(1000),
        ..Default::default()
    })
    .expect("valid config")
}

/// Episode `i`: [`EPISODE_LEN`] actions.
pub fn episode(i: u32) -> ActionSeq {
    ActionSeq::Discrete((0..EPISODE_LEN).map(|j| (i + j) % 4).collect())
}

/// Commits `per` offers to task `id` one after another (each scores higher than the last,
/// so each changes the pool); every commit's latency.
pub async fn commit_episodes(store: Arc<dyn Store>, id: String, per: u32) -> Vec<Duration> {
    let mut pool = Arc::new(Pool::new(1000));
    let mut lat = Vec::with_capacity(per as usize);
    for i in 0..per {
        let ops = vec![PoolOp::Offer {
            actions: episode(i),
            score: f64::from(i),
            end: None,
        }];
        let t = Instant::now();
        let c = store
            .commit(&id, pool, ops, Counters::default())
            .await
            .expect("commit");
        lat.push(t.elapsed());
        pool = c.pool;
    }
    lat
}
