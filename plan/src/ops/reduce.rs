//! Reductions: `mean` over axes, and `softmax` along one axis.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, axis_in_range, list};
use crate::dim::Dim;

/// Mean over the given axes (sorted, distinct).
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Mean {
    pub axes: Vec<usize>,
    pub keepdim: bool,
}

impl Operator for Mean {
    fn kind_name(&self) -> &'static str {
        "mean"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (x, axes) = (inputs[0], &self.axes);
        let mut seen = vec![false; x.rank()];
        for &a in axes {
            if a >= x.rank() || seen[a] {
                return Err(ShapeError::new(format!("mean axes {axes:?} are out of range or repeated for {x}")));
            }
            seen[a] = true;
        }
        if axes.windows(2).any(|w| w[0] >= w[1]) {
            return Err(ShapeError::new(format!("mean axes {axes:?} are not sorted")));
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
        vec![("axes", list(&self.axes)), ("keepdim", self.keepdim.to_string())]
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

    #[test]
    fn mean_drops_or_keeps_axes() {
        assert_eq!(run(&Mean { axes: vec![1, 2], keepdim: false }, &[t(&[2, 3, 4, 5])]), Ok(t(&[2, 5])));
        assert_eq!(run(&Mean { axes: vec![1], keepdim: true }, &[t(&[2, 3, 4])]), Ok(t(&[2, 1, 4])));
        assert!(run(&Mean { axes: vec![3], keepdim: true }, &[t(&[2, 3, 4])]).is_err());
        assert!(run(&Mean { axes: vec![2, 1], keepdim: true }, &[t(&[2, 3, 4])]).is_err());
        assert!(run(&Softmax { axis: 3 }, &[t(&[2, 3, 4])]).is_err());
    }
}
