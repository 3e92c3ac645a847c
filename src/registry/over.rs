//! The limits a task's config must keep to: checked by CreateTask, and for tasks
//! restored from the store or adopted from another server (served read-only when past).

use crate::core::TaskConfig;
use crate::limits::Limits;

/// Why `config` is past `limits` (`max_pool_capacity`, `max_pool_bytes`), if it is:
/// CreateTask refuses such a config, and a task restored or adopted with one is served
/// read-only.
pub fn over_limits(limits: &Limits, config: &TaskConfig) -> Option<String> {
    if config.pool_capacity > limits.max_pool_capacity {
        return Some(format!(
            "config.pool_capacity: {} exceeds this server's limit max_pool_capacity = {}",
            config.pool_capacity, limits.max_pool_capacity
        ));
    }
    let bytes = config.pool_bytes_bound();
    (bytes > limits.max_pool_bytes).then(|| {
        format!(
            "config: a pool of pool_capacity {} trajectories of max_trajectory_len {} \
             actions of {} bytes holds up to {bytes} bytes, past this server's limit \
             max_pool_bytes = {}; lower pool_capacity or max_trajectory_len",
            config.pool_capacity,
            config.max_trajectory_len,
            config.action_space.action_bytes(),
            limits.max_pool_bytes
        )
    })
}
