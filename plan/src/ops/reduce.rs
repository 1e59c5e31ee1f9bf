//! Reductions over axes (`sum`, `mean`, `max`, `min`, `var`, `std`: one operator with a
//! [`ReduceKind`]), and `softmax` along one axis.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, axis_in_range, list};
use crate::dim::Dim;

/// What a [`Reduce`] computes over its axes, as PyTorch's function of the same name.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ReduceKind {
    /// `torch.sum`.
    Sum,
    /// `torch.mean`; NaN over zero elements.
    #[default]
    Mean,
    /// `torch.amax`: the values of `torch.max(x, dim)`; NaN propagates.
    Max,
    /// `torch.amin`; NaN propagates.
    Min,
    /// `torch.var`: squared deviations from the mean over `max(0, count - correction)`
    /// (Bessel's correction 1 by default; 0 is the biased variance).
    Var { correction: i64 },
    /// `torch.std`: the square root of [`ReduceKind::Var`].
    Std { correction: i64 },
}

impl ReduceKind {
    pub fn name(self) -> &'static str {
        match self {
            ReduceKind::Sum => "sum",
            ReduceKind::Mean => "mean",
            ReduceKind::Max => "max",
            ReduceKind::Min => "min",
            ReduceKind::Var { .. } => "var",
            ReduceKind::Std { .. } => "std",
        }
    }

    /// The correction of a variance or standard deviation.
    pub fn correction(self) -> Option<i64> {
        match self {
            ReduceKind::Var { correction } | ReduceKind::Std { correction } => Some(correction),
            _ => None,
        }
    }
}

/// A reduction over the given axes (sorted, distinct): `sum`, `mean`, `max`, `min`,
/// `var`, `std`. Plans written before the other kinds existed stored it as `Mean` without
/// a `kind`, which reads as a mean.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Reduce {
    #[serde(default)]
    pub kind: ReduceKind,
    pub axes: Vec<usize>,
    pub keepdim: bool,
}

impl Operator for Reduce {
    fn kind_name(&self) -> &'static str {
        self.kind.name()
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (x, axes, name) = (inputs[0], &self.axes, self.kind.name());
        let mut seen = vec![false; x.rank()];
        for &a in axes {
            if a >= x.rank() || seen[a] {
                return Err(ShapeError::new(format!("{name} axes {axes:?} are out of range or repeated for {x}")));
            }
            seen[a] = true;
        }
        if axes.windows(2).any(|w| w[0] >= w[1]) {
            return Err(ShapeError::new(format!("{name} axes {axes:?} are not sorted")));
        }
        let extremum = matches!(self.kind, ReduceKind::Max | ReduceKind::Min);
        if let Some(&a) = axes.iter().find(|&&a| extremum && x.known_dim(a) == Some(0)) {
            return Err(ShapeError::new(format!("{name} over the empty axis {a} of {x} has no value")));
        }
        if let Some(c) = self.kind.correction().filter(|&c| c < 0) {
            return Err(ShapeError::new(format!("{name} correction {c} is negative")));
        }
        let shape = x
            .shape
            .iter()
            .enumerate()
            .filter_map(|(i, d)| match (seen[i], self.keepdim) {
                (false, _) => Some(d.clone()),
                (true, true) => Some(Dim::known(1)),
                (true, false) => None,
            })
            .collect();
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = vec![("axes", list(&self.axes)), ("keepdim", self.keepdim.to_string())];
        if let Some(c) = self.kind.correction() {
            v.push(("correction", c.to_string()));
        }
        v
    }
}

/// Softmax along one axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Softmax {
    pub axis: usize,
}

impl Operator for Softmax {
    fn kind_name(&self) -> &'static str {
        "softmax"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        axis_in_range(self.axis, inputs[0])?;
        Ok(inputs[0].clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("axis", self.axis.to_string())]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    fn r(kind: ReduceKind, axes: &[usize], keepdim: bool) -> Reduce {
        Reduce { kind, axes: axes.to_vec(), keepdim }
    }

    #[test]
    fn reductions_drop_or_keep_axes() {
        let var1 = ReduceKind::Var { correction: 1 };
        assert_eq!(run(&r(ReduceKind::Mean, &[1, 2], false), &[t(&[2, 3, 4, 5])]), Ok(t(&[2, 5])));
        assert_eq!(run(&r(ReduceKind::Sum, &[1], true), &[t(&[2, 3, 4])]), Ok(t(&[2, 1, 4])));
        assert_eq!(run(&r(ReduceKind::Max, &[0, 1, 2], false), &[t(&[2, 3, 4])]), Ok(t(&[])));
        assert_eq!(run(&r(ReduceKind::Min, &[0, 2], true), &[t(&[2, 3, 4])]), Ok(t(&[1, 3, 1])));
        assert_eq!(run(&r(var1, &[2], false), &[t(&[2, 3, 7])]), Ok(t(&[2, 3])));
        assert_eq!(run(&r(ReduceKind::Sum, &[], false), &[t(&[2, 3])]), Ok(t(&[2, 3])));
    }

    #[test]
    fn reduction_errors_name_the_op_and_shape() {
        let e = run(&r(ReduceKind::Sum, &[3], true), &[t(&[2, 3, 4])]).expect_err("axis 3 of a 3-D tensor");
        assert_eq!(e.message, "sum axes [3] are out of range or repeated for f32[2, 3, 4]");
        let e = run(&r(ReduceKind::Max, &[2, 1], true), &[t(&[2, 3, 4])]).expect_err("unsorted");
        assert_eq!(e.message, "max axes [2, 1] are not sorted");
        let e = run(&r(ReduceKind::Min, &[1, 1], true), &[t(&[2, 3, 4])]).expect_err("repeated");
        assert!(e.message.starts_with("min axes [1, 1] are out of range or repeated"), "{e}");
        let e = run(&r(ReduceKind::Var { correction: -1 }, &[1], true), &[t(&[2, 3])]).expect_err("negative");
        assert_eq!(e.message, "var correction -1 is negative");
        let e = run(&r(ReduceKind::Max, &[1], false), &[t(&[2, 0, 3])]).expect_err("empty");
        assert_eq!(e.message, "max over the empty axis 1 of f32[2, 0, 3] has no value");
        assert_eq!(run(&r(ReduceKind::Sum, &[1], false), &[t(&[2, 0, 3])]), Ok(t(&[2, 3])));
        assert!(run(&Softmax { axis: 3 }, &[t(&[2, 3, 4])]).is_err());
    }

    #[test]
    fn plans_of_the_mean_operator_read_as_a_mean() {
        let old: super::super::Pure = serde_json::from_str(r#"{"Mean":{"axes":[1],"keepdim":false}}"#).expect("old");
        assert_eq!(old, super::super::Pure::Reduce(r(ReduceKind::Mean, &[1], false)));
        let var = r(ReduceKind::Var { correction: 0 }, &[0, 2], true);
        assert_eq!(var.attrs()[2], ("correction", "0".to_string()));
        assert_eq!(var.kind_name(), "var");
    }
}
