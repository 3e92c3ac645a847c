//! Reading a pool file: every rule of docs/storage.md ("What a reader refuses"), the
//! first line at fault from the top named in the error.

use std::path::Path;

use super::json::{parse_line, Json};
use super::{PoolFile, PoolFileError, FORMAT, V1_CONFIG_FIELDS, VERSION};
use crate::core::{TaskConfig, TaskConfigInput};
use crate::proto;

/// The problem with one line, before the file and line number are added.
type Refused = String;

/// Reads and checks the whole file at `path`.
pub fn read(path: &Path) -> Result<PoolFile, ReadError> {
    let data = std::fs::read(path).map_err(|e| ReadError::Io(path.display().to_string(), e))?;
    read_bytes(&path.display().to_string(), &data).map_err(ReadError::Refused)
}

/// Why a file could not be read: it cannot be opened, or it is refused.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file cannot be read.
    #[error("cannot read {0}: {1}")]
    Io(String, std::io::Error),
    /// The file is malformed.
    #[error(transparent)]
    Refused(PoolFileError),
}

/// Reads and checks a whole file's bytes; `source` names it in the error.
pub fn read_bytes(source: &str, data: &[u8]) -> Result<PoolFile, PoolFileError> {
    let mut lines: Vec<&[u8]> = data.split(|b| *b == b'\n').collect();
    if data.ends_with(b"\n") {
        lines.pop(); // the last line's terminator, not an empty line after it
    }
    let refuse = |line: usize, problem: Refused| PoolFileError {
        file: source.to_string(),
        line,
        problem,
    };
    if data.is_empty() {
        return Err(refuse(
            1,
            "the file is empty (a pool file starts with its header)".into(),
        ));
    }
    let n = lines.len();
    let header = object(lines[0], n == 1).map_err(|p| refuse(1, p))?;
    let (task_id, config, pool_version, count) = read_header(&header).map_err(|p| refuse(1, p))?;
    let mut trajectories: Vec<proto::Trajectory> = Vec::with_capacity(count.min(n));
    for (i, raw) in lines[1..].iter().enumerate() {
        let line = i + 2;
        if trajectories.len() == count {
            return Err(refuse(
                line,
                format!("more trajectory lines than the {count} the header announces"),
            ));
        }
        let after = trajectories.last().map(|t| t.seq);
        let t = object(raw, line == n)
            .and_then(|obj| read_trajectory(&obj, &config, after))
            .map_err(|p| refuse(line, p))?;
        trajectories.push(t);
    }
    if trajectories.len() < count {
        return Err(refuse(
            n + 1,
            format!(
                "the file ends after {} of the {count} trajectories the header announces: it is cut short",
                trajectories.len()
            ),
        ));
    }
    Ok(PoolFile {
        task_id,
        config,
        pool_version,
        trajectories,
    })
}

fn object(raw: &[u8], last: bool) -> Result<Vec<(String, Json)>, Refused> {
    let text = std::str::from_utf8(raw)
        .map_err(|e| format!("not UTF-8 (byte {} of the line)", e.valid_up_to() + 1))?;
    parse_line(text, last)
}

fn get<'a>(obj: &'a [(String, Json)], key: &str) -> Option<&'a Json> {
    obj.iter().find(|(k, _)| k == key).map(|(_, v)| v)
}

/// `expected` all present, nothing else.
fn keys(obj: &[(String, Json)], expected: &[&str], what: &str) -> Result<(), Refused> {
    let missing: Vec<String> = expected
        .iter()
        .filter(|k| get(obj, k).is_none())
        .map(|k| format!("{k:?}"))
        .collect();
    if !missing.is_empty() {
        return Err(format!("{what} lacks {}", missing.join(", ")));
    }
    if let Some((k, _)) = obj.iter().find(|(k, _)| !expected.contains(&k.as_str())) {
        return Err(format!("{what} has an unknown key {k:?}"));
    }
    Ok(())
}

/// A JSON integer (no fraction, no exponent) in `0..=most`.
fn uint(v: &Json, name: &str, most: u64) -> Result<u64, Refused> {
    match *v {
        Json::UInt(u) if u <= most => Ok(u),
        Json::UInt(u) => Err(format!("{name}: must be in 0..={most}, got {u}")),
        Json::NegInt(i) => Err(format!("{name}: must be in 0..={most}, got {i}")),
        _ => Err(format!("{name}: must be an integer, got {}", v.show())),
    }
}

/// A config field's value from JSON.
trait FromJson: Sized {
    fn from_json(v: &Json, name: &str) -> Result<Self, Refused>;
}
impl FromJson for u32 {
    fn from_json(v: &Json, name: &str) -> Result<u32, Refused> {
        uint(v, name, u64::from(u32::MAX)).map(|u| u as u32)
    }
}
impl FromJson for f64 {
    fn from_json(v: &Json, name: &str) -> Result<f64, Refused> {
        v.as_f64()
            .ok_or_else(|| format!("{name}: must be a number, got {}", v.show()))
    }
}
impl FromJson for bool {
    fn from_json(v: &Json, name: &str) -> Result<bool, Refused> {
        match *v {
            Json::Bool(b) => Ok(b),
            _ => Err(format!("{name}: must be true or false, got {}", v.show())),
        }
    }
}

fn field<T: FromJson>(obj: &[(String, Json)], name: &str) -> Result<Option<T>, Refused> {
    get(obj, name)
        .map(|v| T::from_json(v, &format!("config.{name}")))
        .transpose()
}

macro_rules! config_reader {
    ($($(#[doc = $doc:literal])* $name:ident : $ty:ty,)*
     ; $($(#[doc = $ndoc:literal])* $new:ident : $nty:ty,)*) => {
        /// The fields present, typed (ranges are [`TaskConfig::resolve`]'s to check).
        fn config_input(obj: &[(String, Json)]) -> Result<TaskConfigInput, Refused> {
            Ok(TaskConfigInput {
                num_actions: field(obj, "num_actions")?.unwrap_or_default(),
                action_dim: field(obj, "action_dim")?.unwrap_or_default(),
                $($name: field(obj, stringify!($name))?,)*
                $($new: field(obj, stringify!($new))?,)*
            })
        }
    };
}
crate::task_config_fields!(config_reader);

fn read_config(v: &Json) -> Result<TaskConfig, Refused> {
    let Json::Object(obj) = v else {
        return Err(format!("config: must be an object, got {}", v.show()));
    };
    if let Some((name, _)) = obj
        .iter()
        .find(|(k, _)| !TaskConfig::FIELD_NAMES.contains(&k.as_str()))
    {
        return Err(format!(
            "config.{name}: an unknown TaskConfig field (a file of a newer server?)"
        ));
    }
    if let Some(name) = TaskConfig::FIELD_NAMES[..V1_CONFIG_FIELDS]
        .iter()
        .find(|n| get(obj, n).is_none())
    {
        return Err(format!(
            "config.{name}: missing (the config holds every TaskConfig field)"
        ));
    }
    TaskConfig::resolve(&config_input(obj)?).map_err(|e| e.to_string())
}

fn valid_task_id(id: &str) -> bool {
    (1..=128).contains(&id.len())
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"._:/-".contains(&b))
}

fn read_header(obj: &[(String, Json)]) -> Result<(String, TaskConfig, u64, usize), Refused> {
    match get(obj, "format") {
        Some(Json::Str(f)) if f == FORMAT => {}
        found => {
            let found = found.map_or("missing".to_string(), Json::show);
            return Err(format!(
                "not a tamrm pool export (format {found}, expected {FORMAT:?})"
            ));
        }
    }
    match get(obj, "version") {
        None | Some(Json::UInt(VERSION)) => {}
        Some(v) => {
            return Err(format!(
                "format version {} is not supported (this reader reads version {VERSION})",
                v.show()
            ))
        }
    }
    keys(
        obj,
        &[
            "format",
            "version",
            "task_id",
            "config",
            "pool_version",
            "trajectories",
        ],
        "the header",
    )?;
    let task_id = match get(obj, "task_id") {
        Some(Json::Str(id)) if valid_task_id(id) => id.clone(),
        v => {
            return Err(format!(
                "task_id: must be 1-128 characters of [A-Za-z0-9._:/-], got {}",
                v.map_or("missing".to_string(), Json::show)
            ))
        }
    };
    let config = read_config(get(obj, "config").unwrap_or(&Json::Null))?;
    let pool_version = uint(
        get(obj, "pool_version").unwrap_or(&Json::Null),
        "pool_version",
        u64::MAX,
    )?;
    let count = uint(
        get(obj, "trajectories").unwrap_or(&Json::Null),
        "trajectories",
        u64::from(u32::MAX),
    )?;
    if count > u64::from(config.pool_capacity) {
        return Err(format!(
            "trajectories: {count}, more than the pool_capacity {}",
            config.pool_capacity
        ));
    }
    Ok((task_id, config, pool_version, count as usize))
}

fn read_trajectory(
    obj: &[(String, Json)],
    config: &TaskConfig,
    after: Option<u64>,
) -> Result<proto::Trajectory, Refused> {
    keys(obj, &["seq", "score", "actions"], "a trajectory line")?;
    let null = Json::Null;
    let value = |k: &str| get(obj, k).unwrap_or(&null);
    let seq = uint(value("seq"), "seq", u64::MAX)?;
    if let Some(after) = after.filter(|a| seq <= *a) {
        return Err(format!(
            "seq: {seq}, not above the previous line's {after} (seqs increase)"
        ));
    }
    let score = f64::from_json(value("score"), "score")?;
    if !score.is_finite() {
        return Err(format!("score: must be finite, got {score}"));
    }
    let Json::Array(actions) = value("actions") else {
        return Err(format!(
            "actions: must be a list, got {}",
            value("actions").show()
        ));
    };
    if actions.is_empty() {
        return Err("actions: empty (a stored trajectory has at least one action)".into());
    }
    if actions.len() > config.max_trajectory_len as usize {
        return Err(format!(
            "actions: {} actions, more than max_trajectory_len {}",
            actions.len(),
            config.max_trajectory_len
        ));
    }
    let mut t = proto::Trajectory {
        seq,
        score,
        ..Default::default()
    };
    let dim = config.action_space.action_dim();
    if dim == 0 {
        let n = config.action_space.num_actions();
        t.actions = Vec::with_capacity(actions.len());
        for (i, a) in actions.iter().enumerate() {
            match *a {
                Json::UInt(u) if u < n as u64 => t.actions.push(u as u32),
                Json::UInt(_) | Json::NegInt(_) => {
                    return Err(format!(
                        "actions[{i}]: action {} out of range for num_actions {n}",
                        a.show()
                    ))
                }
                _ => {
                    return Err(format!(
                        "actions[{i}]: must be an integer action, got {}",
                        a.show()
                    ))
                }
            }
        }
    } else {
        t.action_vectors = Vec::with_capacity(actions.len() * dim);
        for (i, row) in actions.iter().enumerate() {
            let Json::Array(row) = row else {
                return Err(format!(
                    "actions[{i}]: must be a list of {dim} numbers, got {}",
                    row.show()
                ));
            };
            if row.len() != dim {
                return Err(format!(
                    "actions[{i}]: has {} values, expected action_dim {dim}",
                    row.len()
                ));
            }
            for (j, v) in row.iter().enumerate() {
                let x = f64::from_json(v, &format!("actions[{i}][{j}]"))?;
                // To the nearest binary32, ties to even; too large becomes infinite.
                let single = x as f32;
                if !single.is_finite() {
                    return Err(format!(
                        "actions[{i}][{j}]: must be a finite float32, got {}",
                        v.show()
                    ));
                }
                t.action_vectors.push(single);
            }
        }
    }
    Ok(t)
}
