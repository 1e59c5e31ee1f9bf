//! Switching a session's variant: [`VariantSwitch`], the key lookup behind it and
//! [`Session::set_variant`], and the nearest-key suggestion of an unknown key.
//!
//! A key given as text is looked up exactly first: the plan's keys are canonical
//! [`VariantKey`] text, so a canonical key (as [`Plan::variant_keys`] lists it) is found by
//! a binary search that allocates nothing. Only on a miss is the text read as a
//! [`VariantKey`] and looked up by meaning, so `fog=0.010` names `fog=0.01` and
//! `gamma=0.5+blur=15` names `blur=15+gamma=0.5`; a key that is still unknown, or a text
//! that is not a key at all, is a [`RunError::UnknownVariant`] with the nearest known key.
//! A parsed key (a [`Selection`](crate::conditions::Selection)'s) is compared with the
//! plan's parsed keys, which allocates nothing either.

use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use readi_plan::VariantKey;

use crate::plan::Plan;

use super::RunError;
#[cfg(doc)]
use super::Session;

/// Switches the variant of the session it was taken from ([`Session::switch_handle`]),
/// from any thread, while that session runs or not. Cheap to clone; every clone switches
/// the same session.
#[derive(Clone)]
pub struct VariantSwitch {
    pub(super) plan: Arc<Plan>,
    pub(super) active: Arc<AtomicUsize>,
}

impl VariantSwitch {
    /// Makes variant `key` active for the runs that start from now on: a lookup that
    /// allocates nothing and an atomic store. A run in progress keeps its variant.
    /// A key written another way than the plan's (`fog=0.010`, parts of a meld in another
    /// order) is read as a [`VariantKey`] and found by meaning, which allocates.
    pub fn set(&self, key: &str) -> Result<(), RunError> {
        self.active.store(lookup(&self.plan, key)?, Ordering::Release);
        Ok(())
    }

    /// As [`set`](VariantSwitch::set), by parsed key; allocates nothing (except for the
    /// error of an unknown key).
    pub fn set_key(&self, key: &VariantKey) -> Result<(), RunError> {
        self.active.store(lookup_key(&self.plan, key)?, Ordering::Release);
        Ok(())
    }

    /// As [`set`](VariantSwitch::set), by index (0 is the base).
    pub fn set_index(&self, index: usize) -> Result<(), RunError> {
        let count = self.plan.variant_count();
        if index >= count {
            return Err(RunError::VariantIndex { index, count });
        }
        self.active.store(index, Ordering::Release);
        Ok(())
    }

    /// The active variant's index.
    pub fn index(&self) -> usize {
        self.active.load(Ordering::Acquire)
    }

    /// The active variant's key.
    pub fn key(&self) -> &str {
        self.plan.variant_key(self.index())
    }
}

impl fmt::Debug for VariantSwitch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VariantSwitch").field("active", &self.key()).finish()
    }
}

/// The index of the variant `key` names: its exact text first (a binary search over the
/// plan's keys, which allocates nothing), then the text read as a [`VariantKey`].
pub(super) fn lookup(plan: &Plan, key: &str) -> Result<usize, RunError> {
    if let Some(i) = plan.variant_index(key) {
        return Ok(i);
    }
    match VariantKey::parse(key) {
        Ok(parsed) => plan.variant_index_of(&parsed).ok_or_else(|| unknown(plan, key, &parsed.to_string(), None)),
        Err(e) => Err(unknown(plan, key, key, Some(e.reason))),
    }
}

/// The index of the variant of key `key`; allocates nothing unless it is unknown.
pub(super) fn lookup_key(plan: &Plan, key: &VariantKey) -> Result<usize, RunError> {
    plan.variant_index_of(key).ok_or_else(|| {
        let text = key.to_string();
        unknown(plan, &text, &text, None)
    })
}

/// The error for a key the plan does not have, given as `key`; the suggestion is the
/// known key nearest `canonical` (the key's canonical text when it is a key).
fn unknown(plan: &Plan, key: &str, canonical: &str, malformed: Option<String>) -> RunError {
    let known: Vec<String> = plan.variant_keys().map(str::to_string).collect();
    let nearest = nearest_key(canonical, &known).map(str::to_string);
    RunError::UnknownVariant { key: key.to_string(), known, nearest, malformed }
}

/// The known key closest to `key` by edit distance (ignoring case), if it is close: at
/// most a third of the key's length, and at least 1, edits away.
fn nearest_key<'a>(key: &str, known: &'a [String]) -> Option<&'a str> {
    let key = key.to_lowercase();
    let limit = (key.chars().count() / 3).max(1);
    known
        .iter()
        .map(|k| (edit_distance(&key, &k.to_lowercase()), k.as_str()))
        .filter(|&(d, _)| d <= limit)
        .min_by_key(|&(d, _)| d)
        .map(|(_, k)| k)
}

/// Levenshtein distance over chars.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diag = row[0];
        row[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let next = (diag + usize::from(ca != cb)).min(row[j] + 1).min(row[j + 1] + 1);
            diag = row[j + 1];
            row[j + 1] = next;
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_keys_are_suggested() {
        assert_eq!(edit_distance("fog=0.05", "fog=0.5"), 1);
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        let known: Vec<String> = ["base", "fog=0.05", "fog=0.1", "gamma=0.25"].map(String::from).to_vec();
        assert_eq!(nearest_key("fog=0.11", &known), Some("fog=0.1"));
        assert_eq!(nearest_key("Gamma=0.25", &known), Some("gamma=0.25"));
        assert_eq!(nearest_key("bas", &known), Some("base"));
        assert_eq!(nearest_key("snow=1", &known), None);
        assert_eq!(nearest_key("", &known), None);
    }
}
