//! `tamrm pool export` and `tamrm pool import` over the existing RPCs, as the Python
//! client's `export_pool` and `import_pool` make them (docs/storage.md, "Import"):
//! export reads `GetTask` then `GetPool`; import checks the whole file first, then
//! `GetTask`, `CreateTask` (or `DeleteTask` and `CreateTask`, or `ResetPool`) and one
//! `AddTrajectory` per trajectory in `seq` order, checking that each was stored and
//! moved the pool's version by one.

use tonic::Code;

use super::pool_file::PoolFile;
use super::remote::{CallError, Remote};
use crate::core::TaskConfig;
use crate::proto::{self, Task};
use crate::service::convert::{config_input, config_proto};

/// A task's resolved config as the server sent it, checked.
pub fn task_config(task: &Task) -> Result<TaskConfig, CallError> {
    TaskConfig::resolve(&config_input(task.config.as_ref())).map_err(|e| {
        CallError::new(
            Code::Internal,
            format!(
                "the server sent task {:?} with an invalid config: {e}",
                task.task_id
            ),
        )
    })
}

/// The task and its pool, to write as a pool file.
pub async fn export(
    remote: &mut Remote,
    task_id: &str,
) -> Result<(Task, TaskConfig, proto::Pool), CallError> {
    let task = remote.get_task(task_id).await?;
    let config = task_config(&task)?;
    let pool = remote.get_pool(task_id).await?;
    Ok((task, config, pool))
}

/// Each field in which the file's config and the task's differ, as
/// `name: task X, file Y` (floats bit for bit, as `CreateTask` compares them).
pub fn config_differences(file: &TaskConfig, task: &TaskConfig) -> Vec<String> {
    task.diff(file, &file.to_input())
        .into_iter()
        .map(|d| {
            d.replace(": existing ", ": task ")
                .replace(", requested ", ", file ")
        })
        .collect()
}

/// The task `task_id` with the file's config and an empty pool, made so if `replace`
/// allows.
async fn empty_task(
    remote: &mut Remote,
    task_id: &str,
    file: &PoolFile,
    replace: bool,
) -> Result<Task, CallError> {
    let task = match remote.get_task(task_id).await {
        Ok(t) => t,
        Err(e) if e.code == Some(Code::NotFound) => {
            return remote
                .create_task(task_id, config_proto(&file.config))
                .await
        }
        Err(e) => return Err(e),
    };
    let differences = config_differences(&file.config, &task_config(&task)?);
    if !differences.is_empty() {
        if !replace {
            return Err(CallError::new(
                Code::AlreadyExists,
                format!(
                    "task {task_id:?} exists with another config than the file's ({}); pass --replace to delete and re-create it",
                    differences.join("; ")
                ),
            ));
        }
        remote.delete_task(task_id).await?;
        return remote
            .create_task(task_id, config_proto(&file.config))
            .await;
    }
    let size = task.stats.as_ref().map_or(0, |s| s.pool_size);
    if size > 0 {
        if !replace {
            let what = if size == 1 {
                "trajectory"
            } else {
                "trajectories"
            };
            return Err(CallError::new(
                Code::FailedPrecondition,
                format!(
                    "task {task_id:?} already holds {size} {what}; pass --replace to reset its pool first"
                ),
            ));
        }
        return remote.reset_pool(task_id).await;
    }
    Ok(task)
}

fn changed_meanwhile(task_id: &str, when: &str) -> CallError {
    CallError::new(
        Code::FailedPrecondition,
        format!(
            "the pool of task {task_id:?} changed during the import ({when}): another writer (a session, another import) used the task; import again with --replace once nothing else writes to it"
        ),
    )
}

/// Imports a checked file into `task_id`; returns the task after the import.
pub async fn import(
    remote: &mut Remote,
    file: PoolFile,
    task_id: &str,
    replace: bool,
) -> Result<Task, CallError> {
    let base = empty_task(remote, task_id, &file, replace)
        .await?
        .stats
        .map_or(0, |s| s.pool_version);
    let count = file.trajectories.len();
    for (i, mut t) in file.trajectories.into_iter().enumerate() {
        t.seq = 0;
        let added = remote.add_trajectory(task_id, t).await?;
        if !added.inserted || added.pool_version != base + i as u64 + 1 {
            return Err(changed_meanwhile(
                task_id,
                &format!("after {i} of its {count} trajectories"),
            ));
        }
    }
    let task = remote.get_task(task_id).await?;
    let stats = task.stats.unwrap_or_default();
    if stats.pool_size as usize != count || stats.pool_version != base + count as u64 {
        return Err(changed_meanwhile(task_id, "after its last trajectory"));
    }
    Ok(task)
}
