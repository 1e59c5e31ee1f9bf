//! Layout operators: `concat`, `reshape` (also `flatten`), `permute` (also `transpose`).

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, axis_in_range, list};
use crate::dim::Dim;

/// Concatenation of the inputs along one axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Concat {
    pub axis: usize,
}

impl Operator for Concat {
    fn kind_name(&self) -> &'static str {
        "concat"
    }

    /// A copy: integer and bool tensors move like floats (indices from `topk`).
    fn any_dtype(&self) -> bool {
        true
    }

    fn arity(&self) -> Option<usize> {
        None
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let axis = self.axis;
        let first = inputs[0];
        axis_in_range(axis, first)?;
        let mut total = Dim::known(0);
        for t in inputs {
            if t.rank() != first.rank() || t.dtype != first.dtype {
                return Err(ShapeError::new(format!("concat of {first} and {t}: ranks or element types differ")));
            }
            for (i, (d0, d)) in first.shape.iter().zip(&t.shape).enumerate() {
                if i != axis && d0 != d {
                    return Err(ShapeError::new(format!(
                        "concat along axis {axis} needs equal sizes elsewhere, but axis {i} of {first} and {t} differ"
                    )));
                }
            }
            let d = &t.shape[axis];
            total = match (total.as_known(), d.as_known()) {
                (Some(a), Some(b)) => {
                    Dim::known(a.checked_add(b).ok_or_else(|| ShapeError::new("concat size overflows"))?)
                }
                _ => {
                    return Err(ShapeError::new(format!("concat along axis {axis} needs known sizes there, got {t}")));
                }
            };
        }
        let mut shape = first.shape.clone();
        shape[axis] = total;
        Ok(TensorType::new(first.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("axis", self.axis.to_string())]
    }
}

/// Reshape to a fixed target shape (element count unchanged). In a plan the target is
/// also the output value's shape.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Reshape {
    pub shape: Vec<Dim>,
}

impl Operator for Reshape {
    fn kind_name(&self) -> &'static str {
        "reshape"
    }

    /// A copy: integer and bool tensors move like floats (indices from `topk`).
    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        let have = Dim::product(&x.shape).ok_or_else(|| ShapeError::new("element count overflows"))?;
        let want = Dim::product(&self.shape).ok_or_else(|| ShapeError::new("element count overflows"))?;
        if have != want {
            let shown: Vec<String> = self.shape.iter().map(|d| d.to_string()).collect();
            return Err(ShapeError::new(format!(
                "cannot reshape {x} ({have} elements) to [{}] ({want} elements)",
                shown.join(", ")
            )));
        }
        Ok(TensorType::new(x.dtype, self.shape.clone()))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("shape", list(&self.shape))]
    }
}

/// Axis permutation: output axis `i` is input axis `perm[i]`.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Permute {
    pub perm: Vec<usize>,
}

impl Operator for Permute {
    fn kind_name(&self) -> &'static str {
        "permute"
    }

    /// A copy: integer and bool tensors move like floats (indices from `topk`).
    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (x, perm) = (inputs[0], &self.perm);
        let mut seen = vec![false; x.rank()];
        if perm.len() != x.rank() {
            return Err(ShapeError::new(format!(
                "permutation {perm:?} has {} axes but {x} has {}",
                perm.len(),
                x.rank()
            )));
        }
        for &p in perm {
            if p >= x.rank() || seen[p] {
                return Err(ShapeError::new(format!("{perm:?} is not a permutation of the axes of {x}")));
            }
            seen[p] = true;
        }
        Ok(TensorType::new(x.dtype, perm.iter().map(|&p| x.shape[p].clone()).collect()))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("perm", list(&self.perm))]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;
    use crate::ops::DType;

    #[test]
    fn reshape_keeps_symbolic_element_count() {
        let n = Dim::symbol("N");
        let x = TensorType::new(DType::F32, vec![n.clone(), Dim::known(6), Dim::known(3)]);
        let six_n = n.checked_mul(&Dim::known(6)).expect("no overflow");
        let out = run(&Reshape { shape: vec![six_n, Dim::known(3)] }, std::slice::from_ref(&x)).expect("ok");
        assert_eq!(out.to_string(), "f32[6*N, 3]");
        let e = run(&Reshape { shape: vec![n, Dim::known(17)] }, &[x]).expect_err("an error");
        assert!(e.message.contains("18*N"), "{e:?}");
    }

    #[test]
    fn concat_sums_the_axis() {
        assert_eq!(run(&Concat { axis: 1 }, &[t(&[1, 2, 4]), t(&[1, 3, 4])]), Ok(t(&[1, 5, 4])));
        assert!(run(&Concat { axis: 1 }, &[t(&[1, 2, 4]), t(&[1, 3, 5])]).is_err());
        assert!(run(&Concat { axis: 3 }, &[t(&[1, 2, 4])]).is_err());
    }

    #[test]
    fn permute_checks_the_permutation() {
        assert_eq!(run(&Permute { perm: vec![2, 0, 1] }, &[t(&[2, 3, 4])]), Ok(t(&[4, 2, 3])));
        assert!(run(&Permute { perm: vec![0, 0, 1] }, &[t(&[2, 3, 4])]).is_err());
        assert!(run(&Permute { perm: vec![1, 0] }, &[t(&[2, 3, 4])]).is_err());
    }
}
