//! `parameter(shape)`: a learned tensor used directly (a position embedding, a query
//! table). Its single slot has an empty name, so its `state_dict` key is the node path.

use readi_plan::DType;
use readi_plan::ops::{Operator, ShapeError, ShapeResult, TensorType};

use super::{Args, Builtin, P, R, req};
use crate::ir::{Dim, Op, ParamSlot, ValueRef};

/// The IR op of a `parameter`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParameterOp {
    pub shape: Vec<i64>,
}

impl ParameterOp {
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        vec![ParamSlot::param("", self.shape.clone())]
    }
}

impl Operator for ParameterOp {
    fn kind_name(&self) -> &'static str {
        "parameter"
    }
    fn arity(&self) -> Option<usize> {
        Some(0)
    }
    fn infer(&self, _: &[&TensorType]) -> ShapeResult<TensorType> {
        if self.shape.iter().any(|&d| d < 1) {
            return Err(ShapeError::new(format!("parameter shape {:?} has an empty axis", self.shape)));
        }
        Ok(TensorType::new(DType::F32, self.shape.iter().map(|&d| Dim::known(d)).collect()))
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let shown: Vec<String> = self.shape.iter().map(|d| d.to_string()).collect();
        vec![("shape", format!("[{}]", shown.join(", ")))]
    }
}

const PARAMS: &[P] = &[req("shape")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("parameter", PARAMS, parameter)]
}

fn parameter(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let shape = args.int_list("shape")?;
    if shape.is_empty() || shape.iter().any(|&d| d < 1) {
        return Err(args.bad_value("shape", format!("must be a non-empty list of sizes of at least 1, got {shape:?}")));
    }
    let numel = shape.iter().try_fold(1i64, |a, &d| a.checked_mul(d));
    if numel.is_none_or(|n| n > 1 << 40) {
        return Err(args.bad_value("shape", "is too large".into()));
    }
    Ok((Op::Parameter(ParameterOp { shape }), vec![]))
}
