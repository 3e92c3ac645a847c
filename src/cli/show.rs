//! How `tamrm tasks` shows tasks: a table or text for people, JSON for scripts.

use serde_json::{json, Value};

use super::pool_file;
use crate::core::TaskConfig;
use crate::proto::Task;

/// A score for people: `-` while the pool is empty.
fn score(x: f64, empty: bool) -> String {
    if empty {
        "-".into()
    } else {
        x.to_string()
    }
}

fn actions(c: &TaskConfig) -> String {
    match c.action_space.action_dim() {
        0 => format!("discrete {}", c.action_space.num_actions()),
        m => format!("continuous {m}"),
    }
}

/// One task as JSON: `task_id`, `config` (every field) and `stats` (scores `null` while
/// the pool is empty).
pub fn task_json(task: &Task, config: &TaskConfig) -> Value {
    let s = task.stats.unwrap_or_default();
    let empty = s.pool_size == 0;
    let real = |x: f64| if empty { Value::Null } else { json!(x) };
    let config: Value =
        serde_json::from_str(&pool_file::config_object(config)).unwrap_or(Value::Null);
    json!({
        "task_id": task.task_id,
        "config": config,
        "stats": {
            "pool_size": s.pool_size,
            "pool_version": s.pool_version,
            "min_length": s.min_length,
            "best_score": real(s.best_score),
            "worst_score": real(s.worst_score),
            "episodes_completed": s.episodes_completed,
            "steps_shaped": s.steps_shaped,
            "open_streams": s.open_streams,
        },
    })
}

/// The tasks as a table, one row each, columns aligned.
pub fn task_table(tasks: &[(Task, TaskConfig)]) -> String {
    let mut rows: Vec<[String; 9]> = vec![[
        "TASK", "ACTIONS", "POOL", "BEST", "WORST", "VERSION", "EPISODES", "STEPS", "STREAMS",
    ]
    .map(String::from)];
    for (task, config) in tasks {
        let s = task.stats.unwrap_or_default();
        let empty = s.pool_size == 0;
        rows.push([
            task.task_id.clone(),
            actions(config),
            format!("{}/{}", s.pool_size, config.pool_capacity),
            score(s.best_score, empty),
            score(s.worst_score, empty),
            s.pool_version.to_string(),
            s.episodes_completed.to_string(),
            s.steps_shaped.to_string(),
            s.open_streams.to_string(),
        ]);
    }
    let mut widths = [0usize; 9];
    for row in &rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    for row in &rows {
        let cells: Vec<String> = row
            .iter()
            .zip(widths)
            .map(|(c, w)| format!("{c:<w$}"))
            .collect();
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    out
}

/// One task as text: its id, statistics and every config field.
pub fn task_text(task: &Task, config: &TaskConfig) -> String {
    let j = task_json(task, config);
    let mut out = format!("task {}\n", task.task_id);
    out.push_str(&format!("  actions {}\n", actions(config)));
    for (section, value) in [("stats", &j["stats"]), ("config", &j["config"])] {
        out.push_str(&format!("{section}:\n"));
        if let Value::Object(fields) = value {
            let width = fields.keys().map(String::len).max().unwrap_or(0);
            for (k, v) in fields {
                let v = if v.is_null() {
                    "-".into()
                } else {
                    v.to_string()
                };
                out.push_str(&format!("  {k:<width$}  {v}\n"));
            }
        }
    }
    out
}
