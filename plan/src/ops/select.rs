//! Operators whose indices are values computed at run time: `argmax` / `argmin`
//! (`torch.argmax`), `topk` (`torch.topk`, one op per result), `gather`
//! (`torch.gather`) and `take_along_dim` (`torch.take_along_dim`), `index_select` with
//! an index tensor ([`IndexSelectAt`]; a constant index is baked into the step as
//! [`IndexSelect`](super::IndexSelect) instead), `one_hot` (`F.one_hot`) and `where`
//! with a number for a branch ([`WhereScalar`]).
//!
//! The runtime computes f32 buffers only, so an i64 tensor is f32 holding integers
//! (exact below 2^24) and a bool one 0 or 1. An index read at run time is checked by the
//! kernel (an integer in range, else the step refuses its data with an error naming the
//! value), so the shape rules here do not ask for an i64 index: a plan's values carry no
//! element type, and the compiler's builtins check the types.

use serde::{Deserialize, Serialize};

use super::{DType, IndexSelect, Operator, ShapeError, ShapeResult, TensorType, broadcast, float};
use crate::dim::Dim;

/// Which extreme an [`ArgReduce`] finds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ArgKind {
    Max,
    Min,
}

/// `torch.argmax(input, dim=None, keepdim=False)` / `argmin`: the position of the largest
/// (smallest) value along `axis`, or in the flattened input when `axis` is `None`; the
/// first such position on ties, a NaN counted as the extreme (as torch). An i64 tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ArgReduce {
    pub kind: ArgKind,
    pub axis: Option<usize>,
    pub keepdim: bool,
}

impl Operator for ArgReduce {
    fn kind_name(&self) -> &'static str {
        match self.kind {
            ArgKind::Max => "argmax",
            ArgKind::Min => "argmin",
        }
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        let name = self.kind_name();
        let shape = match self.axis {
            None => {
                if x.shape.iter().any(|d| d.as_known() == Some(0)) {
                    return Err(ShapeError::new(format!("{name} of the empty tensor {x}")));
                }
                if self.keepdim { vec![Dim::known(1); x.rank()] } else { Vec::new() }
            }
            Some(axis) => {
                super::axis_in_range(axis, x)?;
                if x.known_dim(axis) == Some(0) {
                    return Err(ShapeError::new(format!("{name} along axis {axis} of {x}, which is empty")));
                }
                let mut s = x.shape.clone();
                if self.keepdim {
                    s[axis] = Dim::known(1);
                } else {
                    s.remove(axis);
                }
                s
            }
        };
        Ok(TensorType::new(DType::I64, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let dim = self.axis.map_or("None".to_string(), |a| a.to_string());
        vec![("dim", dim), ("keepdim", self.keepdim.to_string())]
    }
}

/// `torch.topk(input, k, dim, largest, sorted)`: the `k` largest (smallest) values along
/// `axis` in order, largest (smallest) first, and their positions. One op per result:
/// `indices` selects the positions (i64) instead of the values. Ties go to the lower
/// position first; a NaN counts as larger than every number (as torch). `sorted=False`
/// gives the sorted order too (torch leaves it unspecified).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TopK {
    pub k: usize,
    pub axis: usize,
    pub largest: bool,
    pub sorted: bool,
    pub indices: bool,
}

impl Operator for TopK {
    fn kind_name(&self) -> &'static str {
        "topk"
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        super::axis_in_range(self.axis, x)?;
        let size = x
            .known_dim(self.axis)
            .ok_or_else(|| ShapeError::new(format!("topk along axis {} of {x}, which is symbolic", self.axis)))?;
        if self.k as i64 > size {
            return Err(ShapeError::new(format!(
                "topk of k = {} along axis {} of {x}, which has {size} values",
                self.k, self.axis
            )));
        }
        let mut s = x.shape.clone();
        s[self.axis] = Dim::known(self.k as i64);
        Ok(TensorType::new(if self.indices { DType::I64 } else { x.dtype }, s))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![
            ("k", self.k.to_string()),
            ("dim", self.axis.to_string()),
            ("largest", self.largest.to_string()),
            ("sorted", self.sorted.to_string()),
            ("output", if self.indices { "indices" } else { "values" }.into()),
        ]
    }
}

/// `torch.gather(input, dim, index)` (`broadcast` false) and
/// `torch.take_along_dim(input, indices, dim)` (`broadcast` true): the output at `o` is
/// `input` at `o` with axis `axis` replaced by `index[o]`. The two have one rank. For
/// `gather` the output has the index's shape, each of its axes but `axis` at most the
/// input's; for `take_along_dim` the axes but `axis` broadcast (an axis of 1 stands for
/// any size) and the output's `axis` is the index's. Every index is checked at run time:
/// an integer in `0..size`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Gather {
    pub axis: usize,
    pub broadcast: bool,
}

impl Gather {
    /// The output shape of `x` gathered at `index` (of `x`'s rank) along `axis`.
    pub fn out_shape(&self, x: &[Dim], index: &[Dim]) -> Result<Vec<Dim>, String> {
        if x.len() != index.len() {
            return Err(format!("the index has {} axes and the input {}", index.len(), x.len()));
        }
        if !self.broadcast {
            for (d, (a, i)) in x.iter().zip(index).enumerate() {
                if d != self.axis
                    && let (Some(a), Some(i)) = (a.as_known(), i.as_known())
                    && i > a
                {
                    return Err(format!("axis {d} of the index is {i}, more than the input's {a}"));
                }
            }
            return Ok(index.to_vec());
        }
        let one = Dim::known(1);
        let mut a = x.to_vec();
        let mut b = index.to_vec();
        a[self.axis] = one.clone();
        b[self.axis] = one;
        let mut s = broadcast(&a, &b)?;
        s[self.axis] = index[self.axis].clone();
        Ok(s)
    }
}

impl Operator for Gather {
    fn kind_name(&self) -> &'static str {
        if self.broadcast { "take_along_dim" } else { "gather" }
    }

    fn arity(&self) -> Option<usize> {
        Some(2)
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (x, index) = (inputs[0], inputs[1]);
        super::axis_in_range(self.axis, x)?;
        let shape = self.out_shape(&x.shape, &index.shape).map_err(|e| {
            ShapeError::new(format!("{} of {x} at an index {index} along axis {}", self.kind_name(), self.axis)).note(e)
        })?;
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("dim", self.axis.to_string())]
    }
}

/// `torch.index_select(input, dim, index)` at an index computed at run time (a 1-D
/// tensor, its second input): the slices of `input` along `axis` at the index's
/// positions, each checked at run time (an integer in `0..size`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct IndexSelectAt {
    pub axis: usize,
}

impl Operator for IndexSelectAt {
    fn kind_name(&self) -> &'static str {
        "index_select"
    }

    fn arity(&self) -> Option<usize> {
        Some(2)
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (x, index) = (inputs[0], inputs[1]);
        super::axis_in_range(self.axis, x)?;
        if index.rank() != 1 {
            return Err(ShapeError::new(format!("index_select needs a 1-D index, got {index}")));
        }
        Ok(TensorType::new(x.dtype, IndexSelect::out_shape(&x.shape, self.axis, &index.shape)))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("dim", self.axis.to_string())]
    }
}

/// `F.one_hot(tensor, num_classes)`: an i64 tensor of the input's shape and one more
/// axis of `num_classes`, 1 at each value's position and 0 elsewhere. Every value is
/// checked at run time (an integer in `0..num_classes`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct OneHot {
    pub num_classes: usize,
}

impl Operator for OneHot {
    fn kind_name(&self) -> &'static str {
        "one_hot"
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        if self.num_classes == 0 {
            return Err(ShapeError::new("one_hot needs at least one class"));
        }
        let mut s = inputs[0].shape.clone();
        s.push(Dim::known(self.num_classes as i64));
        Ok(TensorType::new(DType::I64, s))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("num_classes", self.num_classes.to_string())]
    }
}

/// `torch.where(condition, input, other)` with a number for `input`, `other` or both:
/// the tensor inputs are the condition and the branches that are tensors, in that order;
/// the output is of element type `dtype` (the compiler's promotion: a tensor branch's
/// type, f32 when a branch is a float and the other an integer tensor).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WhereScalar {
    pub input: Option<f64>,
    pub other: Option<f64>,
    pub dtype: DType,
}

impl Operator for WhereScalar {
    fn kind_name(&self) -> &'static str {
        "where"
    }

    fn arity(&self) -> Option<usize> {
        Some(1 + usize::from(self.input.is_none()) + usize::from(self.other.is_none()))
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        if self.input.is_none() && self.other.is_none() {
            return Err(ShapeError::new("a where with a number for a branch has none"));
        }
        if self.input.into_iter().chain(self.other).any(|v| !v.is_finite()) {
            return Err(ShapeError::new("where's numbers must be finite"));
        }
        let mut shape = inputs[0].shape.clone();
        for t in &inputs[1..] {
            shape = broadcast(&shape, &t.shape)
                .map_err(|e| ShapeError::new(format!("cannot broadcast {} with {t}", inputs[0])).note(e))?;
        }
        Ok(TensorType::new(self.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let show = |v: Option<f64>| v.map_or("tensor".to_string(), float);
        vec![("input", show(self.input)), ("other", show(self.other)), ("dtype", self.dtype.as_str().into())]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    fn i64s(shape: &[i64]) -> TensorType {
        TensorType::new(DType::I64, shape.iter().map(|&d| Dim::known(d)).collect())
    }

    #[test]
    fn argmax_removes_or_keeps_its_axis() {
        let a = |axis, keepdim| ArgReduce { kind: ArgKind::Max, axis, keepdim };
        assert_eq!(run(&a(Some(1), false), &[t(&[2, 5, 3])]).expect("valid"), i64s(&[2, 3]));
        assert_eq!(run(&a(Some(1), true), &[t(&[2, 5, 3])]).expect("valid"), i64s(&[2, 1, 3]));
        assert_eq!(run(&a(None, false), &[t(&[2, 5, 3])]).expect("valid"), i64s(&[]));
        assert_eq!(run(&a(None, true), &[t(&[2, 5])]).expect("valid"), i64s(&[1, 1]));
        assert!(run(&a(Some(3), false), &[t(&[2, 5, 3])]).is_err(), "axis out of range");
        let e = run(&a(Some(0), false), &[t(&[0, 4])]).expect_err("empty");
        assert!(e.message.contains("argmax along axis 0"), "{e}");
        let n = TensorType::f32(vec![Dim::symbol("N"), Dim::known(4)]);
        let y = run(&ArgReduce { kind: ArgKind::Min, axis: Some(1), keepdim: false }, &[n]).expect("valid");
        assert_eq!(y, TensorType::new(DType::I64, vec![Dim::symbol("N")]));
    }

    #[test]
    fn topk_has_k_along_its_axis() {
        let k = |k, axis, indices| TopK { k, axis, largest: true, sorted: true, indices };
        assert_eq!(run(&k(6, 1, false), &[t(&[1, 192])]).expect("valid"), t(&[1, 6]));
        assert_eq!(run(&k(6, 1, true), &[t(&[1, 192])]).expect("valid"), i64s(&[1, 6]));
        assert_eq!(run(&k(0, 0, false), &[t(&[3, 2])]).expect("valid"), t(&[0, 2]));
        let e = run(&k(7, 1, false), &[t(&[2, 6])]).expect_err("k > size");
        assert!(e.message.contains("k = 7") && e.message.contains("6 values"), "{e}");
        let n = TensorType::f32(vec![Dim::known(2), Dim::symbol("N")]);
        assert!(run(&k(1, 1, false), &[n]).is_err(), "a symbolic axis cannot be checked");
        // The values keep the input's type.
        assert_eq!(run(&k(2, 0, false), &[i64s(&[5])]).expect("valid"), i64s(&[2]));
    }

    #[test]
    fn gather_has_the_index_shape_and_take_along_dim_broadcasts() {
        let g = Gather { axis: 2, broadcast: false };
        assert_eq!(run(&g, &[t(&[1, 8, 64]), i64s(&[1, 8, 6])]).expect("valid"), t(&[1, 8, 6]));
        // Axes but `dim` may be smaller than the input's (torch.gather), not larger.
        assert_eq!(run(&g, &[t(&[2, 8, 64]), i64s(&[1, 3, 100])]).expect("valid"), t(&[1, 3, 100]));
        let e = run(&g, &[t(&[1, 8, 64]), i64s(&[1, 9, 6])]).expect_err("axis 1 too large");
        assert!(e.to_string().contains("axis 1 of the index is 9"), "{e}");
        assert!(run(&g, &[t(&[1, 8, 64]), i64s(&[8, 6])]).is_err(), "ranks differ");
        let a = Gather { axis: 2, broadcast: true };
        assert_eq!(run(&a, &[t(&[1, 8, 64]), i64s(&[1, 1, 6])]).expect("valid"), t(&[1, 8, 6]));
        assert_eq!(run(&a, &[t(&[1, 1, 64]), i64s(&[3, 2, 6])]).expect("valid"), t(&[3, 2, 6]));
        assert!(run(&a, &[t(&[1, 8, 64]), i64s(&[1, 3, 6])]).is_err(), "8 and 3 do not broadcast");
    }

    #[test]
    fn index_select_at_a_computed_index() {
        let s = IndexSelectAt { axis: 1 };
        assert_eq!(run(&s, &[t(&[2, 5, 4]), i64s(&[3])]).expect("valid"), t(&[2, 3, 4]));
        assert!(run(&s, &[t(&[2, 5, 4]), i64s(&[3, 1])]).is_err(), "a 2-D index");
        assert!(run(&IndexSelectAt { axis: 3 }, &[t(&[2, 5, 4]), i64s(&[3])]).is_err());
    }

    #[test]
    fn one_hot_adds_an_axis_of_classes() {
        assert_eq!(run(&OneHot { num_classes: 3 }, &[i64s(&[1, 6])]).expect("valid"), i64s(&[1, 6, 3]));
        assert!(run(&OneHot { num_classes: 0 }, &[i64s(&[2])]).is_err());
    }

    #[test]
    fn where_with_a_number_broadcasts_its_tensors() {
        let c = TensorType::new(DType::Bool, vec![Dim::known(4), Dim::known(1)]);
        let w = WhereScalar { input: None, other: Some(0.0), dtype: DType::F32 };
        assert_eq!(w.arity(), Some(2));
        assert_eq!(run(&w, &[c.clone(), t(&[1, 5])]).expect("valid"), t(&[4, 5]));
        let both = WhereScalar { input: Some(1.0), other: Some(0.0), dtype: DType::I64 };
        assert_eq!(run(&both, std::slice::from_ref(&c)).expect("valid"), i64s(&[4, 1]));
        assert!(run(&w, &[c.clone(), t(&[3, 5])]).is_err(), "4 and 3");
        let nan = WhereScalar { input: Some(f64::NAN), other: None, dtype: DType::F32 };
        assert!(run(&nan, &[c.clone(), t(&[1])]).is_err());
        let none = WhereScalar { input: None, other: None, dtype: DType::F32 };
        assert!(run(&none, &[c, t(&[1]), t(&[1])]).is_err());
    }
}

#[cfg(test)]
mod movement_tests {
    use super::super::testutil::run;
    use super::super::{Expand, Permute, Reshape};
    use super::*;

    #[test]
    fn indices_move_like_floats() {
        let i = TensorType::new(DType::I64, vec![Dim::known(1), Dim::known(6)]);
        let r = Reshape { shape: vec![Dim::known(1), Dim::known(1), Dim::known(6)] };
        let y = run(&r, std::slice::from_ref(&i)).expect("an i64 reshape");
        assert_eq!(y.dtype, DType::I64);
        let e = Expand { shape: vec![Dim::known(1), Dim::known(4), Dim::known(6)] };
        assert_eq!(run(&e, &[y]).expect("an i64 expand").dtype, DType::I64);
        assert_eq!(run(&Permute { perm: vec![1, 0] }, &[i]).expect("an i64 permute").dtype, DType::I64);
    }
}
