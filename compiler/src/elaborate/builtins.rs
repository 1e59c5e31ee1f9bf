//! The builtin functions of the language: computed while elaborating, they make no node
//! (`dim(x, 1)`, `rank(x)`, `len(list)`, `min(a, b)`, `max(a, b)`). Builtin ops are in
//! [`crate::ops`]; `min` and `max` with a tensor argument are the reduction ops.

use crate::ops::{P, Sig, req};

const X_AXIS: &[P] = &[req("x"), req("axis")];
const X: &[P] = &[req("x")];
const LIST: &[P] = &[req("list")];
const AB: &[P] = &[req("a"), req("b")];

/// Every builtin function.
pub(super) static FUNCTIONS: &[Sig] = &[
    Sig { name: "dim", params: X_AXIS },
    Sig { name: "rank", params: X },
    Sig { name: "len", params: LIST },
    Sig { name: "min", params: AB },
    Sig { name: "max", params: AB },
];

/// The builtin function called `name`.
pub(super) fn function(name: &str) -> Option<&'static Sig> {
    FUNCTIONS.iter().find(|s| s.name == name)
}

/// Whether `name` is a builtin op or function.
pub(super) fn is_builtin(name: &str) -> bool {
    crate::ops::builtin(name).is_some() || function(name).is_some()
}

/// Every builtin's name, ops first, for suggestions.
pub(super) fn names() -> impl Iterator<Item = &'static str> {
    crate::ops::builtins().iter().map(|b| b.sig.name).chain(FUNCTIONS.iter().map(|s| s.name))
}
