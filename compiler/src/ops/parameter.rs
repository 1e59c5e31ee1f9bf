//! `parameter(shape)`: a learned tensor used directly (a position embedding, a query
//! table). Its single slot has an empty name, so its `state_dict` key is the node path.
//! `buffer(shape, dtype=i64)`: a `state_dict` buffer used directly, the same way (an
//! index table). And the op of a tensor `fold_constants` computed at compile time.

use readi_plan::DType;
use readi_plan::ops::{Operator, ShapeError, ShapeResult, TensorType};

use super::{Args, Builtin, P, R, absent, req};
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
    vec![Builtin::new("parameter", PARAMS, parameter), Builtin::new("buffer", BUFFER_PARAMS, buffer)]
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

/// The IR op of a `buffer(shape, dtype=...)`: a `state_dict` buffer used directly (Swin's
/// int64 `relative_position_index`). Not trainable, so `readi params` lists it only with
/// `--buffers`. An integer buffer is a compile-time value: `fold_constants` folds every
/// node computed from it (an index it selects with), and one that reaches a kernel is an
/// error (the runtime computes only f32).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BufferOp {
    pub shape: Vec<i64>,
    pub dtype: DType,
}

impl BufferOp {
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        vec![ParamSlot::buffer("", self.shape.clone(), self.dtype)]
    }
}

impl Operator for BufferOp {
    fn kind_name(&self) -> &'static str {
        "buffer"
    }
    fn arity(&self) -> Option<usize> {
        Some(0)
    }
    fn infer(&self, _: &[&TensorType]) -> ShapeResult<TensorType> {
        if self.shape.iter().any(|&d| d < 0) {
            return Err(ShapeError::new(format!("buffer shape {:?} has a negative axis", self.shape)));
        }
        Ok(TensorType::new(self.dtype, self.shape.iter().map(|&d| Dim::known(d)).collect()))
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let shown: Vec<String> = self.shape.iter().map(|d| d.to_string()).collect();
        vec![("shape", format!("[{}]", shown.join(", "))), ("dtype", self.dtype.as_str().into())]
    }
}

/// The IR op of a tensor `fold_constants` computed at compile time from stored tensors:
/// a node that was `from` (`permute`, `index_select`) and now reads its derived tensor,
/// which its one slot names. Not a parameter of the model: the slot is a buffer, bound
/// to the derived tensor, so the state_dict table is unchanged.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConstantOp {
    pub shape: Vec<i64>,
    /// The type the value had (an integer or bool constant is stored as exact f32 values).
    pub dtype: DType,
    pub from: &'static str,
}

impl ConstantOp {
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        vec![ParamSlot::buffer("", self.shape.clone(), self.dtype)]
    }
}

impl Operator for ConstantOp {
    fn kind_name(&self) -> &'static str {
        "constant"
    }
    fn arity(&self) -> Option<usize> {
        Some(0)
    }
    fn infer(&self, _: &[&TensorType]) -> ShapeResult<TensorType> {
        Ok(TensorType::new(self.dtype, self.shape.iter().map(|&d| Dim::known(d)).collect()))
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let shown: Vec<String> = self.shape.iter().map(|d| d.to_string()).collect();
        vec![
            ("shape", format!("[{}]", shown.join(", "))),
            ("dtype", self.dtype.as_str().into()),
            ("from", self.from.into()),
        ]
    }
}

const BUFFER_PARAMS: &[P] = &[req("shape"), absent("dtype")];

/// The element types a `buffer` may have: f32, or the integer types of index buffers.
fn buffer_dtype(args: &Args<'_>) -> R<DType> {
    if !args.present("dtype") {
        return Ok(DType::F32);
    }
    let name = args.string("dtype")?;
    match name.as_str() {
        "f32" => Ok(DType::F32),
        "i64" => Ok(DType::I64),
        other => Err(args.bad_value("dtype", format!("must be `f32` or `i64`, got `{other}`"))),
    }
}

fn buffer(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let shape = args.int_list("shape")?;
    if shape.iter().any(|&d| d < 0) {
        return Err(args.bad_value("shape", format!("must be a list of sizes of at least 0, got {shape:?}")));
    }
    let numel = shape.iter().try_fold(1i64, |a, &d| a.checked_mul(d));
    if numel.is_none_or(|n| n > 1 << 40) {
        return Err(args.bad_value("shape", "is too large".into()));
    }
    let dtype = buffer_dtype(args)?;
    Ok((Op::Buffer(BufferOp { shape, dtype }), vec![]))
}
