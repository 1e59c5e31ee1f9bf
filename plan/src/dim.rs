//! Tensor dimensions: known sizes or products with symbolic factors (`N`, `6*N`).
//!
//! One type for the compiler's shape inference and the plan's value shapes: the runtime
//! reads the shapes the compiler inferred, checks them with the same shape rules
//! ([`crate::ops`]) and evaluates them once the inputs bind the symbols.

use std::collections::HashMap;
use std::fmt;

use serde::{Deserialize, Serialize};

/// One dimension of a tensor shape: `coef * s1 * s2 * ...` where the `s` are symbolic
/// dimensions declared by inputs (the batch size `N`). A dimension without symbols is a
/// known size. Products and exact quotients stay in this form, which is what shape
/// inference needs for reshapes around a symbolic batch (`[N, 6, C, H, W]` to
/// `[6*N, C, H, W]`); sums of symbolic dimensions are not representable and are rejected.
///
/// In a plan file a dimension is `{"coef": 6, "syms": ["N"]}` (`syms` left out when
/// empty); the symbols are kept sorted, so equal dimensions compare equal.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(from = "RawDim")]
pub struct Dim {
    coef: i64,
    /// Sorted symbol names, with repetition for powers.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    syms: Vec<String>,
}

/// A dimension as a file spells it, symbols in any order.
#[derive(Deserialize)]
struct RawDim {
    coef: i64,
    #[serde(default)]
    syms: Vec<String>,
}

impl From<RawDim> for Dim {
    fn from(raw: RawDim) -> Dim {
        let mut syms = raw.syms;
        syms.sort();
        Dim { coef: raw.coef, syms }
    }
}

impl Dim {
    /// A known size.
    pub fn known(n: i64) -> Dim {
        Dim { coef: n, syms: Vec::new() }
    }

    /// A symbolic dimension.
    pub fn symbol(name: &str) -> Dim {
        Dim { coef: 1, syms: vec![name.to_string()] }
    }

    /// The constant factor.
    pub fn coef(&self) -> i64 {
        self.coef
    }

    /// The size, if it has no symbolic factor.
    pub fn as_known(&self) -> Option<i64> {
        self.syms.is_empty().then_some(self.coef)
    }

    pub fn is_symbolic(&self) -> bool {
        !self.syms.is_empty()
    }

    /// The symbols of this dimension.
    pub fn symbols(&self) -> &[String] {
        &self.syms
    }

    /// The product, or `None` on overflow.
    pub fn checked_mul(&self, other: &Dim) -> Option<Dim> {
        let coef = self.coef.checked_mul(other.coef)?;
        let mut syms = self.syms.clone();
        syms.extend(other.syms.iter().cloned());
        syms.sort();
        Some(Dim { coef, syms })
    }

    /// The exact quotient, or `None` if `other` does not divide `self` (or is zero).
    pub fn checked_div(&self, other: &Dim) -> Option<Dim> {
        if other.coef == 0 || self.coef % other.coef != 0 {
            return None;
        }
        let mut syms = self.syms.clone();
        for s in &other.syms {
            let pos = syms.iter().position(|x| x == s)?;
            syms.remove(pos);
        }
        Some(Dim { coef: self.coef / other.coef, syms })
    }

    /// The product of several dimensions, or `None` on overflow.
    pub fn product<'a>(dims: impl IntoIterator<Item = &'a Dim>) -> Option<Dim> {
        dims.into_iter().try_fold(Dim::known(1), |acc, d| acc.checked_mul(d))
    }

    /// The size under the given symbol values, or `None` if a symbol is unbound or the
    /// result overflows or is negative.
    pub fn eval(&self, bindings: &HashMap<String, usize>) -> Option<usize> {
        let mut v = usize::try_from(self.coef).ok()?;
        for s in &self.syms {
            v = v.checked_mul(*bindings.get(s)?)?;
        }
        Some(v)
    }
}

impl From<usize> for Dim {
    /// A known size; sizes beyond `i64::MAX` saturate (no real tensor has them, and the
    /// shape rules then reject the result as too large).
    fn from(n: usize) -> Dim {
        Dim::known(i64::try_from(n).unwrap_or(i64::MAX))
    }
}

impl fmt::Display for Dim {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.syms.is_empty() {
            return write!(f, "{}", self.coef);
        }
        if self.coef != 1 {
            write!(f, "{}*", self.coef)?;
        }
        // Symbols from an untrusted plan may be anything until validation: printed escaped.
        for (i, s) in self.syms.iter().enumerate() {
            if i > 0 {
                f.write_str("*")?;
            }
            f.write_str(&crate::format::escaped(s))?;
        }
        Ok(())
    }
}

/// Shows a shape: `[N, 3, 224, 224]`.
pub fn show_shape(shape: &[Dim]) -> String {
    let parts: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    format!("[{}]", parts.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn symbolic_products_and_quotients() {
        let n = Dim::symbol("N");
        let six_n = n.checked_mul(&Dim::known(6)).expect("no overflow");
        assert_eq!(six_n.to_string(), "6*N");
        assert_eq!(six_n.checked_div(&Dim::known(6)), Some(n.clone()));
        assert_eq!(six_n.checked_div(&n), Some(Dim::known(6)));
        assert_eq!(six_n.checked_div(&Dim::known(4)), None);
        assert_eq!(Dim::known(6).checked_div(&n), None);
        assert_eq!(n.checked_mul(&n).map(|d| d.to_string()), Some("N*N".into()));
    }

    #[test]
    fn overflow_is_reported_not_wrapped() {
        let big = Dim::known(i64::MAX / 2 + 1);
        assert_eq!(big.checked_mul(&Dim::known(2)), None);
        assert_eq!(Dim::known(5).checked_div(&Dim::known(0)), None);
        let b = HashMap::from([("N".to_string(), usize::MAX)]);
        assert_eq!(Dim::known(2).checked_mul(&Dim::symbol("N")).and_then(|d| d.eval(&b)), None);
        assert_eq!(Dim::known(-1).eval(&b), None);
    }

    #[test]
    fn files_spell_dimensions_as_coefficient_and_symbols() {
        let d = Dim::symbol("N").checked_mul(&Dim::known(6)).expect("no overflow");
        assert_eq!(serde_json::to_string(&d).expect("json"), r#"{"coef":6,"syms":["N"]}"#);
        assert_eq!(serde_json::to_string(&Dim::known(3)).expect("json"), r#"{"coef":3}"#);
        // Symbols in any order read as the same dimension.
        let a: Dim = serde_json::from_str(r#"{"coef":2,"syms":["N","M"]}"#).expect("parses");
        let b = Dim::symbol("M").checked_mul(&Dim::symbol("N")).and_then(|d| d.checked_mul(&Dim::known(2)));
        assert_eq!(Some(a), b);
    }
}
