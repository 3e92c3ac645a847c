//! One line of a pool file as a JSON value, read strictly: an object with a key twice is
//! refused, and an integer (no fraction, no exponent) stays apart from a real number, so
//! that `2.0` can be refused where the format wants an integer.

use std::fmt;

use serde::de::{self, Deserialize, Deserializer, MapAccess, SeqAccess, Visitor};

/// A JSON value as the pool format reads it.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Json {
    Null,
    Bool(bool),
    /// A JSON integer in `0..=u64::MAX`.
    UInt(u64),
    /// A negative JSON integer in `i64`'s range.
    NegInt(i64),
    /// Any other JSON number (a fraction, an exponent, or an integer past 64 bits), as
    /// the nearest binary64.
    Real(f64),
    Str(String),
    Array(Vec<Json>),
    /// The keys in the order written; no key twice.
    Object(Vec<(String, Json)>),
}

impl Json {
    /// The value as a binary64, if it is a number.
    pub(super) fn as_f64(&self) -> Option<f64> {
        match *self {
            Json::UInt(u) => Some(u as f64),
            Json::NegInt(i) => Some(i as f64),
            Json::Real(x) => Some(x),
            _ => None,
        }
    }

    /// The value for a message, cut to 40 characters.
    pub(super) fn show(&self) -> String {
        let text = match self {
            Json::Null => "null".to_string(),
            Json::Bool(b) => b.to_string(),
            Json::UInt(u) => u.to_string(),
            Json::NegInt(i) => i.to_string(),
            Json::Real(x) => serde_json::to_string(x).unwrap_or_else(|_| x.to_string()),
            Json::Str(s) => serde_json::to_string(s).unwrap_or_else(|_| s.clone()),
            Json::Array(a) => {
                let items: Vec<String> = a.iter().take(8).map(Json::show).collect();
                format!("[{}]", items.join(", "))
            }
            Json::Object(_) => "{...}".to_string(),
        };
        if text.chars().count() <= 40 {
            text
        } else {
            let cut: String = text.chars().take(37).collect();
            format!("{cut}...")
        }
    }
}

/// Parses one line: `Err` holds the problem, worded for the line's message.
pub(super) fn parse_line(text: &str, last: bool) -> Result<Vec<(String, Json)>, String> {
    if text.trim().is_empty() {
        return Err("an empty line (every line is one JSON object)".into());
    }
    match serde_json::from_str::<Json>(text) {
        Ok(Json::Object(fields)) => Ok(fields),
        Ok(other) => Err(format!(
            "a JSON {}, expected an object",
            match other {
                Json::Array(_) => "array",
                Json::Str(_) => "string",
                Json::Null => "null",
                Json::Bool(_) => "boolean",
                _ => "number",
            }
        )),
        Err(e) if e.is_eof() => Err(if last {
            "the line ends before its JSON object does: the file is cut short".into()
        } else {
            "the line ends before its JSON object does".into()
        }),
        Err(e) => {
            let full = e.to_string();
            let what = full
                .rsplit_once(" at line ")
                .map_or(full.as_str(), |(what, _)| what);
            if e.is_data() {
                Err(what.to_string())
            } else {
                Err(format!("not JSON: {what} at column {}", e.column()))
            }
        }
    }
}

struct JsonVisitor;

impl<'de> Visitor<'de> for JsonVisitor {
    type Value = Json;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a JSON value")
    }
    fn visit_unit<E>(self) -> Result<Json, E> {
        Ok(Json::Null)
    }
    fn visit_bool<E>(self, b: bool) -> Result<Json, E> {
        Ok(Json::Bool(b))
    }
    fn visit_u64<E>(self, u: u64) -> Result<Json, E> {
        Ok(Json::UInt(u))
    }
    fn visit_i64<E>(self, i: i64) -> Result<Json, E> {
        Ok(if i >= 0 {
            Json::UInt(i as u64)
        } else {
            Json::NegInt(i)
        })
    }
    fn visit_f64<E>(self, x: f64) -> Result<Json, E> {
        Ok(Json::Real(x))
    }
    fn visit_str<E>(self, s: &str) -> Result<Json, E> {
        Ok(Json::Str(s.to_string()))
    }
    fn visit_string<E>(self, s: String) -> Result<Json, E> {
        Ok(Json::Str(s))
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Json, A::Error> {
        let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0));
        while let Some(v) = seq.next_element()? {
            out.push(v);
        }
        Ok(Json::Array(out))
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Json, A::Error> {
        let mut out: Vec<(String, Json)> = Vec::new();
        while let Some(key) = map.next_key::<String>()? {
            if out.iter().any(|(k, _)| *k == key) {
                return Err(de::Error::custom(format!(
                    "the key {key:?} appears twice in one object"
                )));
            }
            let value = map.next_value()?;
            out.push((key, value));
        }
        Ok(Json::Object(out))
    }
}

impl<'de> Deserialize<'de> for Json {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Json, D::Error> {
        d.deserialize_any(JsonVisitor)
    }
}
