//! `linear` (`y = x W^T + b` over the last axis) and `matmul` (batched, broadcasting).

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, broadcast};
use crate::dim::Dim;

/// A linear layer's sizes; its weight is `[out, in]`. The bias is the IR's and the plan
/// kernel's business (an epilogue shift).
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Linear {
    pub in_features: i64,
    pub out_features: i64,
}

/// Output columns per panel of a linear weight stored in panels (`Kernel::Linear {
/// panels }`): two AVX-512 vectors.
pub const PANEL: usize = 32;

impl Linear {
    /// Floats of this layer's weight stored in panels: `ceil(out / PANEL) * PANEL * in`,
    /// `None` for a negative size or on overflow.
    pub fn panel_len(&self) -> Option<usize> {
        let (fin, fout) = (usize::try_from(self.in_features).ok()?, usize::try_from(self.out_features).ok()?);
        fout.div_ceil(PANEL).checked_mul(PANEL)?.checked_mul(fin)
    }
}

impl Operator for Linear {
    fn kind_name(&self) -> &'static str {
        "linear"
    }

    /// Each output element sums `in` products.
    fn multiply_adds(&self, _inputs: &[&[usize]], output: &[usize]) -> u64 {
        super::count(output).saturating_mul(self.in_features.max(0) as u64)
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        let last = x.rank().checked_sub(1).ok_or_else(|| ShapeError::new("linear needs at least one axis"))?;
        let fin = self.in_features;
        if x.known_dim(last) != Some(fin) {
            return Err(ShapeError::new(format!("linear expects {fin} input features on the last axis, got {x}")));
        }
        if fin < 1 || self.out_features < 1 {
            return Err(ShapeError::new(format!(
                "linear from {fin} to {} features: both must be at least 1",
                self.out_features
            )));
        }
        let mut shape = x.shape.clone();
        shape[last] = Dim::known(self.out_features);
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("in", self.in_features.to_string()), ("out", self.out_features.to_string())]
    }
}

/// Batched matrix product with broadcasting over leading axes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct MatMul;

impl Operator for MatMul {
    fn kind_name(&self) -> &'static str {
        "matmul"
    }

    /// Each output element sums as many products as the left side has columns.
    fn multiply_adds(&self, inputs: &[&[usize]], output: &[usize]) -> u64 {
        let k = inputs.first().and_then(|a| a.last()).copied().unwrap_or(0) as u64;
        super::count(output).saturating_mul(k)
    }

    fn arity(&self) -> Option<usize> {
        Some(2)
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (a, b) = (inputs[0], inputs[1]);
        if a.rank() < 2 || b.rank() < 2 {
            return Err(ShapeError::new(format!("matmul needs at least 2 axes on both sides, got {a} and {b}")));
        }
        if a.dtype != b.dtype {
            return Err(ShapeError::new(format!("matmul of different element types: {a} and {b}")));
        }
        let (ra, rb) = (a.rank(), b.rank());
        if a.shape[ra - 1] != b.shape[rb - 2] {
            return Err(ShapeError::new(format!(
                "matmul inner sizes differ: {a} @ {b} ({} vs {})",
                a.shape[ra - 1],
                b.shape[rb - 2]
            )));
        }
        let mut shape = broadcast(&a.shape[..ra - 2], &b.shape[..rb - 2])
            .map_err(|e| ShapeError::new(format!("matmul batch axes of {a} and {b} do not broadcast")).note(e))?;
        shape.push(a.shape[ra - 2].clone());
        shape.push(b.shape[rb - 1].clone());
        Ok(TensorType::new(a.dtype, shape))
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    // Output elements x the reduced length, by hand.
    #[test]
    fn multiply_adds_count_each_output_s_products() {
        let l = Linear { in_features: 5, out_features: 3 };
        assert_eq!(l.multiply_adds(&[&[2, 7, 5]], &[2, 7, 3]), 42 * 5);
        assert_eq!(MatMul.multiply_adds(&[&[2, 3, 4, 5], &[3, 5, 6]], &[2, 3, 4, 6]), 144 * 5);
    }

    #[test]
    fn matmul_batches_and_checks_inner_size() {
        assert_eq!(run(&MatMul, &[t(&[2, 3, 4, 5]), t(&[3, 5, 6])]), Ok(t(&[2, 3, 4, 6])));
        let e = run(&MatMul, &[t(&[4, 5]), t(&[4, 5])]).expect_err("an error");
        assert!(e.message.contains("inner sizes"), "{e:?}");
    }

    #[test]
    fn linear_maps_the_last_axis() {
        let l = Linear { in_features: 5, out_features: 3 };
        assert_eq!(run(&l, &[t(&[2, 7, 5])]), Ok(t(&[2, 7, 3])));
        assert!(run(&l, &[t(&[2, 4])]).is_err());
        assert!(run(&Linear { in_features: 0, out_features: 3 }, &[t(&[2, 0])]).is_err());
    }
}
