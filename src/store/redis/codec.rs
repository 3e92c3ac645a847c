//! How a task is written into and read back from its Redis hashes: the config as
//! versioned JSON, scores as exact decimal text, and a whole task decoded from its meta
//! hash and trajectories, checked as the disk store checks its files.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use crate::core::{Pool, TaskConfig, Trajectory};
use crate::store::disk::decode_trajectory_bytes;
use crate::store::{Counters, StoredTask};

/// Version of the task's JSON config in Redis.
const CONFIG_FORMAT: u32 = 1;

/// The JSON of `meta.config`.
#[derive(Serialize, Deserialize)]
struct ConfigJson {
    format: u32,
    config: TaskConfig,
}

/// The JSON of `meta.config` for `config`.
pub(super) fn encode_config(config: &TaskConfig) -> Result<String, serde_json::Error> {
    serde_json::to_string(&ConfigJson {
        format: CONFIG_FORMAT,
        config: *config,
    })
}

/// A `meta.config` field as stored.
fn parse_config(json: &[u8]) -> Result<ConfigJson, String> {
    serde_json::from_slice(json).map_err(|e| format!("field \"config\": {e}"))
}

/// The config of a `meta.config` field as stored (the answer to a creation of a task
/// that exists already).
pub(super) fn stored_config(json: &[u8]) -> Result<TaskConfig, String> {
    parse_config(json).map(|j| j.config)
}

/// A score as Lua reads it back exactly (shortest round-trip digits).
pub(super) fn score_text(score: f64) -> String {
    format!("{score:e}")
}

/// A field of a meta hash, an error naming it if it is missing.
pub(super) fn field<'a>(
    meta: &'a HashMap<String, Vec<u8>>,
    name: &str,
) -> Result<&'a [u8], String> {
    meta.get(name)
        .map(Vec::as_slice)
        .ok_or_else(|| format!("field {name:?} is missing"))
}

fn number(meta: &HashMap<String, Vec<u8>>, name: &str) -> Result<u64, String> {
    std::str::from_utf8(field(meta, name)?)
        .ok()
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| format!("field {name:?} is not a number"))
}

/// A task from its meta hash and trajectories, checked as the disk store checks files.
pub(super) fn decode_task(
    task: &str,
    meta: &HashMap<String, Vec<u8>>,
    traj: HashMap<u64, Vec<u8>>,
) -> Result<StoredTask, String> {
    let json = parse_config(field(meta, "config")?)?;
    if json.format != CONFIG_FORMAT {
        return Err(format!(
            "config format {} is not supported by this build (format {CONFIG_FORMAT})",
            json.format
        ));
    }
    let config = json.config;
    config
        .check()
        .map_err(|e| format!("field \"config\": config.{}: {}", e.field, e.message))?;
    let trajectories = traj
        .into_iter()
        .map(|(seq, bytes)| {
            decode_trajectory_bytes(&bytes, &config)
                .map(|t| Trajectory { seq, ..t })
                .map_err(|e| format!("trajectory {seq}: {e}"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let pool = Pool::restore(
        config.pool_capacity as usize,
        trajectories,
        number(meta, "version")?,
        number(meta, "next_seq")?,
    )?;
    Ok(StoredTask {
        id: task.to_string(),
        config,
        pool,
        counters: Counters {
            episodes_completed: number(meta, "episodes_completed")?,
            steps_shaped: number(meta, "steps_shaped")?,
        },
    })
}
