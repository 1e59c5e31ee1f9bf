//! Variant keys: the one way to read, write and compare the name of a variant.
//!
//! A key is `base` (the base model), one condition (`fog=0.03`, `gamma=4`,
//! `missing=lidar`), or a meld of conditions on different axes joined by `+`
//! (`fog=0.06+gamma=0.5`). Keys are compared by meaning: levels are numbers
//! (`fog=0.030` is `fog=0.03`) and the parts of a meld are unordered
//! (`gamma=0.5+fog=0.06` is `fog=0.06+gamma=0.5`). [`VariantKey`]'s `Display` writes the
//! canonical text, which is what plans store and what the runtime looks up.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

/// The key of the base model.
pub const BASE_KEY: &str = "base";

/// The axis name that marks a missing-modality part: `missing=lidar`.
pub const MISSING_AXIS: &str = "missing";

/// One condition of a key.
#[derive(Clone, Debug, PartialEq)]
pub enum KeyPart {
    /// An axis at a level: `fog=0.03`.
    Level { axis: String, level: f64 },
    /// A modality whose inputs are absent: `missing=lidar`.
    Missing { modality: String },
}

impl KeyPart {
    /// The axis the part is on (`missing` for a missing modality).
    pub fn axis(&self) -> &str {
        match self {
            KeyPart::Level { axis, .. } => axis,
            KeyPart::Missing { .. } => MISSING_AXIS,
        }
    }
}

impl fmt::Display for KeyPart {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            KeyPart::Level { axis, level } => write!(f, "{axis}={}", fmt_level(*level)),
            KeyPart::Missing { modality } => write!(f, "{MISSING_AXIS}={modality}"),
        }
    }
}

/// A variant's key: no part (the base), one, or several (a meld). Parts are kept in the
/// order of their canonical text, so equal keys have equal parts.
#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct VariantKey {
    parts: Vec<KeyPart>,
}

/// Why a text is not a key.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct KeyError {
    pub text: String,
    pub reason: String,
}

impl fmt::Display for KeyError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "`{}` is not a variant key: {}", self.text, self.reason)
    }
}

impl std::error::Error for KeyError {}

fn is_name(s: &str) -> bool {
    let mut chars = s.chars();
    chars.next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

impl VariantKey {
    /// The base model's key.
    pub fn base() -> VariantKey {
        VariantKey { parts: Vec::new() }
    }

    /// One axis at one level.
    pub fn level(axis: &str, level: f64) -> VariantKey {
        VariantKey { parts: vec![KeyPart::Level { axis: axis.to_string(), level }] }
    }

    /// A missing modality.
    pub fn missing(modality: &str) -> VariantKey {
        VariantKey { parts: vec![KeyPart::Missing { modality: modality.to_string() }] }
    }

    /// Reads a key: `base`, `axis=level`, `missing=modality`, or parts joined by `+`.
    pub fn parse(text: &str) -> Result<VariantKey, KeyError> {
        let err = |reason: String| KeyError { text: text.to_string(), reason };
        let t = text.trim();
        if t == BASE_KEY {
            return Ok(VariantKey::base());
        }
        if t.is_empty() {
            return Err(err("it is empty".into()));
        }
        let mut parts = Vec::new();
        for p in t.split('+') {
            let p = p.trim();
            let Some((axis, value)) = p.split_once('=') else {
                return Err(err(format!("`{p}` has no `=` (write `axis=level`, `missing=modality` or `base`)")));
            };
            let (axis, value) = (axis.trim(), value.trim());
            if !is_name(axis) {
                return Err(err(format!("`{axis}` is not an axis name")));
            }
            let part = if axis == MISSING_AXIS {
                if !is_name(value) {
                    return Err(err(format!("`{value}` is not a modality name")));
                }
                KeyPart::Missing { modality: value.to_string() }
            } else {
                match value.parse::<f64>() {
                    Ok(level) if level.is_finite() => KeyPart::Level { axis: axis.to_string(), level },
                    _ => return Err(err(format!("the level `{value}` of `{axis}` is not a finite number"))),
                }
            };
            parts.push(part);
        }
        VariantKey::from_parts(parts).map_err(err)
    }

    /// The key of several conditions at once; an error when two are on one axis (two
    /// `missing` parts are fine when their modalities differ).
    pub fn from_parts(mut parts: Vec<KeyPart>) -> Result<VariantKey, String> {
        parts.sort_by_cached_key(|p| p.to_string());
        parts.dedup();
        for w in parts.windows(2) {
            if w[0].axis() == w[1].axis() && w[0].axis() != MISSING_AXIS {
                return Err(format!("`{}` and `{}` are on the same axis", w[0], w[1]));
            }
        }
        Ok(VariantKey { parts })
    }

    /// The meld of several keys (their parts together).
    pub fn meld(keys: &[VariantKey]) -> Result<VariantKey, String> {
        VariantKey::from_parts(keys.iter().flat_map(|k| k.parts.iter().cloned()).collect())
    }

    pub fn parts(&self) -> &[KeyPart] {
        &self.parts
    }

    /// Each part as a key of its own.
    pub fn part_keys(&self) -> impl Iterator<Item = VariantKey> + '_ {
        self.parts.iter().map(|p| VariantKey { parts: vec![p.clone()] })
    }

    pub fn is_base(&self) -> bool {
        self.parts.is_empty()
    }

    /// Whether the key melds two or more conditions.
    pub fn is_meld(&self) -> bool {
        self.parts.len() > 1
    }
}

impl fmt::Display for VariantKey {
    /// The canonical text; width and alignment (`{:<12}`) apply to it as to a string.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.parts.is_empty() {
            return f.pad(BASE_KEY);
        }
        let parts: Vec<String> = self.parts.iter().map(|p| p.to_string()).collect();
        f.pad(&parts.join("+"))
    }
}

impl FromStr for VariantKey {
    type Err = KeyError;
    fn from_str(s: &str) -> Result<VariantKey, KeyError> {
        VariantKey::parse(s)
    }
}

impl TryFrom<String> for VariantKey {
    type Error = KeyError;
    fn try_from(s: String) -> Result<VariantKey, KeyError> {
        VariantKey::parse(&s)
    }
}

impl From<VariantKey> for String {
    fn from(k: VariantKey) -> String {
        k.to_string()
    }
}

/// A level as it appears in a key: `0.03`, `4`.
pub fn fmt_level(v: f64) -> String {
    if v.fract() == 0.0 && v.abs() < 1e15 { format!("{}", v as i64) } else { format!("{v}") }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(s: &str) -> String {
        VariantKey::parse(s).map(|k| k.to_string()).unwrap_or_else(|e| format!("error: {}", e.reason))
    }

    #[test]
    fn keys_are_read_by_meaning() {
        assert_eq!(key("fog=0.010"), "fog=0.01");
        assert_eq!(key(" fog = 0.01 "), "fog=0.01");
        assert_eq!(key("gamma=4.0"), "gamma=4");
        assert_eq!(key("gamma=0.5+blur=15"), "blur=15+gamma=0.5");
        assert_eq!(key("blur=15+gamma=.5"), "blur=15+gamma=0.5");
        assert_eq!(key("missing=lidar"), "missing=lidar");
        assert_eq!(key("base"), "base");
        assert_eq!(VariantKey::parse("fog=0.03").ok(), Some(VariantKey::level("fog", 0.03)));
        assert!(VariantKey::parse("base").is_ok_and(|k| k.is_base()));
        assert!(VariantKey::parse("fog=0.06+gamma=0.5").is_ok_and(|k| k.is_meld()));
    }

    #[test]
    fn malformed_keys_say_why() {
        assert!(key("fog").contains("no `=`"), "{}", key("fog"));
        assert!(key("fog=thick").contains("not a finite number"));
        assert!(key("fog=inf").contains("not a finite number"));
        assert!(key("fog=0.01+fog=0.03").contains("same axis"));
        assert!(key("").contains("empty"));
        assert!(key("9x=1").contains("axis name"));
        assert!(key("missing=").contains("modality"));
    }

    #[test]
    fn keys_travel_as_their_canonical_text() {
        let k = VariantKey::parse("gamma=0.50+fog=0.060").expect("a key");
        let json = serde_json::to_string(&k).expect("json");
        assert_eq!(json, r#""fog=0.06+gamma=0.5""#);
        assert_eq!(serde_json::from_str::<VariantKey>(&json).ok(), Some(k));
        assert!(serde_json::from_str::<VariantKey>(r#""fog=""#).is_err());
    }
}
