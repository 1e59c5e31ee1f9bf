//! Indexing, selection, casts and constant tensors: `index_select` / `embedding`
//! (`torch.index_select`, `F.embedding`, `table[index]`) with the indices as attributes,
//! `where` (`torch.where`), casts (`x.float()`, `x.to(dtype)`) and the constant
//! generators `arange`, `zeros`, `ones`, `full`.
//!
//! The runtime computes only f32: integer and bool tensors exist at compile time, and
//! the compiler folds everything computed from constants into stored f32 tensors. What a
//! plan may hold of these is an [`IndexSelect`] of a computed tensor (its indices, from an
//! int64 buffer, stored in the step and checked against the axis they select from when
//! the plan loads, so a crafted index cannot read out of bounds), a `where` and a cast (a
//! copy: every value is an f32 already, a bool one 0 or 1). A [`Fill`] has no inputs; the
//! compiler always folds it.

use serde::{Deserialize, Serialize};

use super::{DType, Operator, ShapeError, ShapeResult, TensorType, broadcast, float, list};
use crate::dim::Dim;

/// `numpy.take(x, index, axis)`: the slices of `x` along `axis` at the positions
/// `index` holds, the index's shape in place of the axis. A 1-D index is
/// `torch.index_select(x, axis, index)`; `F.embedding(index, weight)` is axis 0 of the
/// weight; `table[index]` is axis 0.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct IndexSelect {
    pub axis: usize,
    /// The positions, flattened in row-major order.
    pub index: Vec<i64>,
    /// The index tensor's shape (its product is `index.len()`).
    pub index_shape: Vec<usize>,
}

impl IndexSelect {
    /// The output shape for an input of shape `x`: the index's shape in place of `axis`.
    pub fn out_shape<T: Clone>(x: &[T], axis: usize, index_shape: &[T]) -> Vec<T> {
        let mut s = x[..axis].to_vec();
        s.extend(index_shape.iter().cloned());
        s.extend(x[axis + 1..].iter().cloned());
        s
    }
}

impl Operator for IndexSelect {
    fn kind_name(&self) -> &'static str {
        "index_select"
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        super::axis_in_range(self.axis, x)?;
        if self.index_shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)) != Some(self.index.len()) {
            return Err(ShapeError::new(format!(
                "index_select has {} indices for an index of shape {}",
                self.index.len(),
                list(&self.index_shape)
            )));
        }
        let size = x.known_dim(self.axis).ok_or_else(|| {
            ShapeError::new(format!("index_select along axis {} of {x}, which is symbolic", self.axis))
        })?;
        if let Some((i, &v)) = self.index.iter().enumerate().find(|&(_, &v)| v < 0 || v >= size) {
            return Err(ShapeError::new(format!(
                "index {v} (at flat position {i}) is out of range for axis {} of {x}, of size {size}",
                self.axis
            )));
        }
        let index: Vec<Dim> = self.index_shape.iter().map(|&d| Dim::known(d as i64)).collect();
        Ok(TensorType::new(x.dtype, IndexSelect::out_shape(&x.shape, self.axis, &index)))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let shown = if self.index.len() <= 8 {
            list(&self.index)
        } else {
            format!(
                "[{}, ... {} values]",
                self.index[..4].iter().map(|v| v.to_string()).collect::<Vec<_>>().join(", "),
                self.index.len()
            )
        };
        vec![("axis", self.axis.to_string()), ("index", shown), ("index_shape", list(&self.index_shape))]
    }
}

/// `torch.where(cond, a, b)`: `a` where `cond` is true (non-zero), else `b`, the three
/// broadcast together; `a` and `b` of one type.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Where;

impl Operator for Where {
    fn kind_name(&self) -> &'static str {
        "where"
    }

    fn arity(&self) -> Option<usize> {
        Some(3)
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (c, a, b) = (inputs[0], inputs[1], inputs[2]);
        if a.dtype != b.dtype {
            return Err(ShapeError::new(format!("where of different element types: {a} and {b}")));
        }
        let ab = broadcast(&a.shape, &b.shape)
            .map_err(|e| ShapeError::new(format!("cannot broadcast {a} with {b}")).note(e))?;
        let shape = broadcast(&c.shape, &ab)
            .map_err(|e| ShapeError::new(format!("cannot broadcast the condition {c} with {a}")).note(e))?;
        Ok(TensorType::new(a.dtype, shape))
    }
}

/// A cast to another element type: to f32 a copy (an integer or bool value is an f32
/// already), to i64 rounded towards zero, to bool whether non-zero.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Cast {
    pub to: DType,
}

impl Operator for Cast {
    fn kind_name(&self) -> &'static str {
        "to"
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        if !matches!(self.to, DType::F32 | DType::I64 | DType::Bool) {
            return Err(ShapeError::new(format!("casts go to f32, i64 or bool, not {}", self.to.as_str())));
        }
        Ok(TensorType::new(self.to, inputs[0].shape.clone()))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("dtype", self.to.as_str().into())]
    }
}

/// A constant tensor of known shape: `start + i * step` at flat position `i` (`arange`
/// with `step` non-zero; `zeros`, `ones`, `full` with `step` zero).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fill {
    pub shape: Vec<i64>,
    pub start: f64,
    pub step: f64,
    pub dtype: DType,
}

impl Operator for Fill {
    fn kind_name(&self) -> &'static str {
        if self.step != 0.0 { "arange" } else { "full" }
    }

    fn arity(&self) -> Option<usize> {
        Some(0)
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, _: &[&TensorType]) -> ShapeResult<TensorType> {
        if self.shape.iter().any(|&d| d < 0) {
            return Err(ShapeError::new(format!("a constant of shape {} has a negative axis", list(&self.shape))));
        }
        if !self.start.is_finite() || !self.step.is_finite() {
            return Err(ShapeError::new("a constant's values must be finite"));
        }
        Ok(TensorType::new(self.dtype, self.shape.iter().map(|&d| Dim::known(d)).collect()))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![
            ("shape", list(&self.shape)),
            ("start", float(self.start)),
            ("step", float(self.step)),
            ("dtype", self.dtype.as_str().into()),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    fn take(axis: usize, index: Vec<i64>, index_shape: Vec<usize>) -> IndexSelect {
        IndexSelect { axis, index, index_shape }
    }

    #[test]
    fn index_select_puts_the_index_shape_in_place_of_the_axis() {
        // [169, 3] taken at 2401 positions along 0: [2401, 3] (Swin's bias table).
        let y = run(&take(0, vec![0; 2401], vec![2401]), &[t(&[169, 3])]).expect("valid");
        assert_eq!(y, t(&[2401, 3]));
        // A 2-D index along the middle axis of [2, 5, 4]: [2, 3, 2, 4].
        let y = run(&take(1, vec![0, 1, 2, 3, 4, 0], vec![3, 2]), &[t(&[2, 5, 4])]).expect("valid");
        assert_eq!(y, t(&[2, 3, 2, 4]));
        // An empty index selects nothing.
        let y = run(&take(0, vec![], vec![0]), &[t(&[7, 2])]).expect("valid");
        assert_eq!(y, t(&[0, 2]));
    }

    #[test]
    fn index_select_refuses_an_index_out_of_range() {
        let e = run(&take(0, vec![0, 169], vec![2]), &[t(&[169, 3])]).expect_err("169 is past the end");
        assert!(e.message.contains("index 169 (at flat position 1) is out of range"), "{e}");
        assert!(run(&take(0, vec![-1], vec![1]), &[t(&[4])]).is_err());
        assert!(run(&take(2, vec![0], vec![1]), &[t(&[4, 4])]).is_err(), "axis out of range");
        assert!(run(&take(0, vec![0, 1], vec![3]), &[t(&[4])]).is_err(), "index shape and count disagree");
        let n = TensorType::f32(vec![Dim::symbol("N"), Dim::known(3)]);
        assert!(run(&take(0, vec![0], vec![1]), &[n]).is_err(), "a symbolic axis cannot be checked");
    }

    #[test]
    fn where_broadcasts_its_three_inputs() {
        let c = TensorType::new(DType::Bool, vec![Dim::known(4), Dim::known(1)]);
        let y = run(&Where, &[c.clone(), t(&[1, 5]), t(&[4, 5])]).expect("valid");
        assert_eq!(y, t(&[4, 5]));
        let i = TensorType::new(DType::I64, vec![Dim::known(5)]);
        assert!(run(&Where, &[c.clone(), t(&[5]), i]).is_err(), "branches of different types");
        let c2 = TensorType::new(DType::Bool, vec![Dim::known(2)]);
        assert!(run(&Where, &[c2, t(&[3]), t(&[3])]).is_err(), "a condition of 2 with branches of 3");
        let y = run(&Where, &[c, t(&[3]), t(&[3])]).expect("[4, 1] with [3]");
        assert_eq!(y, t(&[4, 3]));
    }

    #[test]
    fn casts_and_fills_have_their_dtype() {
        let b = TensorType::new(DType::Bool, vec![Dim::known(3)]);
        assert_eq!(run(&Cast { to: DType::F32 }, &[b]).expect("valid"), t(&[3]));
        let a = Fill { shape: vec![7], start: 0.0, step: 1.0, dtype: DType::I64 };
        assert_eq!(run(&a, &[]).expect("valid"), TensorType::new(DType::I64, vec![Dim::known(7)]));
        assert_eq!(a.kind_name(), "arange");
        let z = Fill { shape: vec![2, 3], start: 0.0, step: 0.0, dtype: DType::F32 };
        assert_eq!(run(&z, &[]).expect("valid"), t(&[2, 3]));
        assert!(run(&Fill { shape: vec![-1], ..z }, &[]).is_err());
    }
}
