//! Tensor dimensions: known integers or products with symbolic factors (`N`, `6*N`).

use std::fmt;

/// One dimension of a tensor shape: `coef * s1 * s2 * ...` where the `s` are symbolic
/// dimensions declared by inputs (the batch size `N`). A dimension without symbols is a
/// known size. Products and exact quotients stay in this form, which is what shape
/// inference needs for reshapes around a symbolic batch (`[N, 6, C, H, W]` to
/// `[6*N, C, H, W]`); sums of symbolic dimensions are not representable and are rejected.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Dim {
    coef: i64,
    /// Sorted symbol names, with repetition for powers.
    syms: Vec<String>,
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
}

impl fmt::Display for Dim {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.syms.is_empty() {
            return write!(f, "{}", self.coef);
        }
        let mut first = true;
        if self.coef != 1 {
            write!(f, "{}", self.coef)?;
            first = false;
        }
        for s in &self.syms {
            if !first {
                f.write_str("*")?;
            }
            f.write_str(s)?;
            first = false;
        }
        Ok(())
    }
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
    }
}
