//! The pool export format, `tamrm-pool` version 1 (docs/storage.md, "Pool export
//! format"): one task's resolved config and pool as JSON Lines. [`read`] checks a whole
//! file and refuses it with a [`PoolFileError`] naming the first line at fault;
//! [`write_lines`] writes one, [`write_path`] through a temporary file renamed over the
//! path. The Python client's `tamrm/_pool_file.py` reads and writes the same files; both
//! read the fixtures of `clients/python/tests/fixtures/pool/`.

mod json;
mod read;

use std::io::Write;
use std::path::Path;

use crate::core::TaskConfig;
use crate::proto;

pub use read::{read, read_bytes, ReadError};

/// The header's `format`.
pub const FORMAT: &str = "tamrm-pool";
/// The one version of the format written and read here.
pub const VERSION: u64 = 1;
/// How many `TaskConfig` fields (the first ones, in proto order) a version-1 header must
/// hold; a field added to `TaskConfig` later is optional (its default when missing).
pub const V1_CONFIG_FIELDS: usize = 12;

/// A checked pool file: its header's values and its trajectories in `seq` order (each
/// with its `seq`, `score` and `actions` or `action_vectors`, as `GetPool` gives them).
#[derive(Debug, Clone, PartialEq)]
pub struct PoolFile {
    /// The exported task's id.
    pub task_id: String,
    /// Its resolved config, checked against every range of SPEC §1.1.
    pub config: TaskConfig,
    /// The pool's version when exported (for the record).
    pub pool_version: u64,
    /// The trajectories, in increasing `seq`.
    pub trajectories: Vec<proto::Trajectory>,
}

/// A pool file refused: the file, the line at fault (from 1; the header is line 1) and
/// what is wrong with it. Nothing was imported.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{file}, line {line}: {problem}")]
pub struct PoolFileError {
    /// The file's path (or `<stdin>`).
    pub file: String,
    /// The line at fault.
    pub line: usize,
    /// What is wrong with it.
    pub problem: String,
}

macro_rules! config_writer {
    ($($(#[doc = $doc:literal])* $name:ident : $ty:ty,)*
     ; $($(#[doc = $ndoc:literal])* $new:ident : $nty:ty,)*) => {
        /// `{"num_actions": …, …}`: every field, in proto order.
        fn write_config(c: &TaskConfig, out: &mut String) {
            let i = c.to_input();
            out.push_str("{\"num_actions\": ");
            out.push_str(itoa::Buffer::new().format(i.num_actions));
            out.push_str(", \"action_dim\": ");
            out.push_str(itoa::Buffer::new().format(i.action_dim));
            $(
                out.push_str(concat!(", \"", stringify!($name), "\": "));
                i.$name.unwrap_or_default().write_json(out);
            )*
            $(
                out.push_str(concat!(", \"", stringify!($new), "\": "));
                i.$new.unwrap_or_default().write_json(out);
            )*
            out.push('}');
        }
    };
}
crate::task_config_fields!(config_writer);

/// A resolved config as the header's JSON object: every field, in proto order.
pub fn config_object(c: &TaskConfig) -> String {
    let mut out = String::with_capacity(300);
    write_config(c, &mut out);
    out
}

/// A config value as JSON.
trait WriteJson {
    fn write_json(&self, out: &mut String);
}
impl WriteJson for u32 {
    fn write_json(&self, out: &mut String) {
        out.push_str(itoa::Buffer::new().format(*self));
    }
}
impl WriteJson for bool {
    fn write_json(&self, out: &mut String) {
        out.push_str(if *self { "true" } else { "false" });
    }
}
impl WriteJson for f64 {
    fn write_json(&self, out: &mut String) {
        real(*self, out);
    }
}

/// A finite binary64 as the shortest text that reads back to its bits (ryu).
fn real(x: f64, out: &mut String) {
    out.push_str(ryu::Buffer::new().format_finite(x));
}

/// The header line (with its `\n`).
pub fn header_line(task_id: &str, config: &TaskConfig, pool_version: u64, count: usize) -> String {
    let mut out = String::with_capacity(400);
    out.push_str("{\"format\": \"");
    out.push_str(FORMAT);
    out.push_str("\", \"version\": 1, \"task_id\": ");
    out.push_str(&serde_json::Value::from(task_id).to_string());
    out.push_str(", \"config\": ");
    write_config(config, &mut out);
    out.push_str(", \"pool_version\": ");
    out.push_str(itoa::Buffer::new().format(pool_version));
    out.push_str(", \"trajectories\": ");
    out.push_str(itoa::Buffer::new().format(count));
    out.push_str("}\n");
    out
}

/// One trajectory line (with its `\n`) into `out`: a discrete task's actions as
/// integers, a continuous one's as `action_dim`-long lists of binary32 values widened to
/// binary64.
pub fn trajectory_line(t: &proto::Trajectory, action_dim: usize, out: &mut String) {
    out.push_str("{\"seq\": ");
    out.push_str(itoa::Buffer::new().format(t.seq));
    out.push_str(", \"score\": ");
    real(t.score, out);
    out.push_str(", \"actions\": [");
    if action_dim == 0 {
        let mut ints = itoa::Buffer::new();
        for (i, a) in t.actions.iter().enumerate() {
            if i > 0 {
                out.push_str(", ");
            }
            out.push_str(ints.format(*a));
        }
    } else {
        let mut reals = ryu::Buffer::new();
        for (i, row) in t.action_vectors.chunks(action_dim).enumerate() {
            out.push_str(if i > 0 { ", [" } else { "[" });
            for (j, v) in row.iter().enumerate() {
                if j > 0 {
                    out.push_str(", ");
                }
                out.push_str(reals.format_finite(f64::from(*v)));
            }
            out.push(']');
        }
    }
    out.push_str("]}\n");
}

/// Writes the export of `pool` (of a task of `config`) to `out`; returns the number of
/// trajectories. `GetPool` gives them in `seq` order, as the file holds them.
pub fn write_lines(
    out: &mut impl Write,
    task_id: &str,
    config: &TaskConfig,
    pool: &proto::Pool,
) -> std::io::Result<usize> {
    let count = pool.trajectories.len();
    out.write_all(header_line(task_id, config, pool.pool_version, count).as_bytes())?;
    let dim = config.action_space.action_dim();
    let mut line = String::new();
    for t in &pool.trajectories {
        line.clear();
        trajectory_line(t, dim, &mut line);
        out.write_all(line.as_bytes())?;
    }
    out.flush()?;
    Ok(count)
}

/// Writes the export to `path` whole or not at all: a temporary file beside it, synced,
/// then renamed over it (a reader never finds half a file there).
pub fn write_path(
    path: &Path,
    task_id: &str,
    config: &TaskConfig,
    pool: &proto::Pool,
) -> std::io::Result<usize> {
    let name = path
        .file_name()
        .ok_or_else(|| std::io::Error::other("the path names no file"))?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let tmp = dir.join(format!(
        ".{}.{}.tmp",
        name.to_string_lossy(),
        std::process::id()
    ));
    let written = (|| -> std::io::Result<usize> {
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)?;
        let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
        let count = write_lines(&mut out, task_id, config, pool)?;
        out.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        std::fs::rename(&tmp, path)?;
        Ok(count)
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

#[cfg(test)]
mod tests;
