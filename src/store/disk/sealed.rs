//! Sealed JSON files (data dir format 4): `tamrm.json`, `task.json`, `pool.json` and
//! `ends.json` carry a `"checksum"` (CRC-32 of the file's JSON without it) and, but the
//! marker, the `"dir_id"` of the data dir that wrote them, so that a flipped byte, or the
//! same file copied from another data dir, is named instead of read as valid. Files
//! written before format 4 have neither and are read as they are.

use std::path::Path;

use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;

use super::files::{err, read_json};
use crate::store::StoreError;

const CHECKSUM: &str = "checksum";
const DIR_ID: &str = "dir_id";

/// The CRC-32 of a JSON value's compact text, as 8 hex digits.
fn checksum(v: &Value) -> String {
    let text = serde_json::to_vec(v).unwrap_or_default();
    format!("{:08x}", crc32fast::hash(&text))
}

/// The bytes of `value` (a JSON object) sealed with `dir_id` (when given) and a checksum.
pub(super) fn seal<T: Serialize>(
    path: &Path,
    value: &T,
    dir_id: Option<&str>,
) -> Result<Vec<u8>, StoreError> {
    let mut v = serde_json::to_value(value).map_err(|e| err(path, e))?;
    let Some(obj) = v.as_object_mut() else {
        return Err(err(path, "a sealed file holds a JSON object"));
    };
    if let Some(id) = dir_id {
        obj.insert(DIR_ID.into(), Value::String(id.into()));
    }
    let sum = checksum(&v);
    if let Some(obj) = v.as_object_mut() {
        obj.insert(CHECKSUM.into(), Value::String(sum));
    }
    serde_json::to_vec_pretty(&v).map_err(|e| err(path, e))
}

/// A sealed file read back: its content and the data dir id it names (`None` in a file
/// written before format 4).
pub(super) struct Unsealed<T> {
    pub value: T,
    pub dir_id: Option<String>,
    /// It carried a checksum (and it matched).
    pub sealed: bool,
}

/// Reads a sealed file (or an older one without a seal): a checksum that does not match
/// its content is reported as damage, naming the file.
pub(super) fn read_sealed<T: DeserializeOwned>(path: &Path) -> Result<Unsealed<T>, StoreError> {
    let mut v: Value = read_json(path)?;
    let Some(obj) = v.as_object_mut() else {
        return Err(err(path, "damaged: not a JSON object"));
    };
    let sum = obj.remove(CHECKSUM);
    let sealed = match sum {
        None => false,
        Some(Value::String(found)) => {
            let expected = checksum(&v);
            if found != expected {
                return Err(err(
                    path,
                    format!("damaged: its checksum is {found}, its content sums to {expected} (a changed or flipped byte)"),
                ));
            }
            true
        }
        Some(_) => return Err(err(path, "damaged: its checksum is not a string")),
    };
    let dir_id = match v.as_object_mut().and_then(|o| o.remove(DIR_ID)) {
        None => None,
        Some(Value::String(s)) => Some(s),
        Some(_) => return Err(err(path, "damaged: its dir_id is not a string")),
    };
    let value = serde_json::from_value(v)
        .map_err(|e| err(path, format!("damaged: unexpected content: {e}")))?;
    Ok(Unsealed {
        value,
        dir_id,
        sealed,
    })
}

/// Reads a sealed file of the data dir `dir_id`: one that names another data dir is
/// refused (copied from it).
pub(super) fn read_own<T: DeserializeOwned>(path: &Path, dir_id: &str) -> Result<T, StoreError> {
    let u = read_sealed(path)?;
    match u.dir_id {
        Some(found) if found != dir_id => Err(err(
            path,
            format!("belongs to another data dir (its dir_id is {found}, this data dir's is {dir_id}): copied from elsewhere?"),
        )),
        _ => Ok(u.value),
    }
}

/// A new random data dir id: 32 hex digits.
pub(super) fn new_dir_id() -> Result<String, std::io::Error> {
    use std::io::Read;
    let mut b = [0u8; 16];
    std::fs::File::open("/dev/urandom")?.read_exact(&mut b)?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

/// A data dir id as the 16 bytes the log header holds (`None` if it is not 32 hex digits).
pub(super) fn dir_id_bytes(id: &str) -> Option<[u8; 16]> {
    if id.len() != 32 {
        return None;
    }
    let mut out = [0u8; 16];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(id.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

/// The id of a log header's 16 bytes.
pub(super) fn dir_id_text(b: &[u8; 16]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

#[cfg(test)]
mod tests;
