//! Constants, comparisons' companions, casts and indexing, with PyTorch's names:
//! `arange(start, end, step=1)`, `zeros(size)`, `ones(size)`, `full(size, fill_value)`
//! (each with `dtype`), `where(condition, input, other)`, `float(x)`, `to(x, dtype)`,
//! `index_select(input, dim, index)` and `embedding(input, weight)`.
//!
//! Integer and bool tensors exist at compile time only: `arange` of ints is i64, a
//! comparison is bool, an int64 `buffer` is i64. `fold_constants` computes every node of
//! them (with the runtime's kernels) into a stored f32 tensor. An index must be such a
//! constant: `index_select` and `embedding` make an [`IndexSelectOp`] whose index input
//! the back end folds into the plan's [`IndexSelect`] (the indices in the step, checked
//! when the plan loads) when it is a constant; an index computed from a model input
//! (a `topk`'s, an `argmax`'s) becomes an `index_select` step reading it
//! ([`IndexSelectAt`](readi_plan::ops::IndexSelectAt)), each position checked as it
//! runs. `where` takes a number for either branch (`where(c, x, 0.0)`).

use readi_plan::DType;
use readi_plan::ops::{
    Cast, Fill, IndexSelect, Operator, Pure, ShapeError, ShapeResult, TensorType, Where, WhereScalar,
};

use super::{Args, Builtin, P, R, absent, int, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

/// `index_select(input, dim, index)` (`embedding`: axis 0) before the back end knows the
/// index's values: the data and the index as inputs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IndexSelectOp {
    pub axis: usize,
}

impl Operator for IndexSelectOp {
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
        if index.dtype != DType::I64 {
            return Err(ShapeError::new(format!("index_select needs an i64 index, got {index}")));
        }
        if self.axis >= x.rank() {
            return Err(ShapeError::new(format!("axis {} is out of range for {x}", self.axis)));
        }
        Ok(TensorType::new(x.dtype, IndexSelect::out_shape(&x.shape, self.axis, &index.shape)))
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("axis", self.axis.to_string())]
    }
}

const ARANGE: &[P] = &[req("start"), absent("end"), int("step", 1), absent("dtype")];
const FILLED: &[P] = &[req("size"), absent("dtype")];
const FULL: &[P] = &[req("size"), req("fill_value"), absent("dtype")];
const WHERE: &[P] = &[req("condition"), req("input"), req("other")];
const FLOAT: &[P] = &[req("x")];
const TO: &[P] = &[req("x"), req("dtype")];
const INDEX_SELECT: &[P] = &[req("input"), req("dim"), req("index")];
const EMBEDDING: &[P] = &[req("input"), req("weight")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("arange", ARANGE, arange).alias(),
        Builtin::new("zeros", FILLED, zeros).alias(),
        Builtin::new("ones", FILLED, ones).alias(),
        Builtin::new("full", FULL, full),
        Builtin::new("where", WHERE, where_),
        Builtin::new("float", FLOAT, float).alias(),
        Builtin::new("to", TO, to),
        Builtin::new("index_select", INDEX_SELECT, index_select),
        Builtin::new("embedding", EMBEDDING, embedding).alias(),
    ]
}

/// Most elements a constant the spec computes may have.
const MAX_CONSTANT: i64 = 1 << 24;

/// The `dtype` argument: `f32`, `i64` or `bool` (written bare or as a string).
fn dtype_arg(args: &Args<'_>, default: DType) -> R<DType> {
    if !args.present("dtype") {
        return Ok(default);
    }
    let name = args.string("dtype")?;
    match name.as_str() {
        "f32" | "float32" | "float" => Ok(DType::F32),
        "i64" | "int64" | "long" => Ok(DType::I64),
        "bool" => Ok(DType::Bool),
        other => Err(args.bad_value("dtype", format!("must be f32, i64 or bool, got `{other}`"))),
    }
}

/// A number argument, and whether it was an int.
fn number(args: &Args<'_>, name: &str) -> R<(f64, bool)> {
    match args.value(name) {
        Some(Value::Int(i)) => Ok((*i as f64, true)),
        Some(Value::Float(f)) if f.is_finite() => Ok((*f, false)),
        Some(v) => Err(args.mismatch(name, "a finite number", v)),
        None => Err(args.bad_value(name, "missing".into())),
    }
}

/// The constant's shape from `size` (an int or a list of ints), bounded.
fn size(args: &Args<'_>) -> R<Vec<i64>> {
    let shape = args.int_list("size")?;
    if shape.iter().any(|&d| d < 0) {
        return Err(args.bad_value("size", format!("must be sizes of at least 0, got {shape:?}")));
    }
    let n = shape.iter().try_fold(1i64, |a, &d| a.checked_mul(d));
    if n.is_none_or(|n| n > MAX_CONSTANT) {
        return Err(args.bad_value("size", format!("a constant may have at most {MAX_CONSTANT} elements")));
    }
    Ok(shape)
}

fn arange(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    // `arange(end)` or `arange(start, end, step)`, as torch.arange.
    let (first, first_int) = number(args, "start")?;
    let (start, end, ints) = if args.present("end") {
        let (end, end_int) = number(args, "end")?;
        (first, end, first_int && end_int)
    } else {
        (0.0, first, first_int)
    };
    let (step, step_int) = number(args, "step")?;
    if step == 0.0 {
        return Err(args.bad_value("step", "must not be zero".into()));
    }
    let len = ((end - start) / step).ceil().max(0.0);
    if len > MAX_CONSTANT as f64 {
        return Err(args.bad_value("end", format!("a constant may have at most {MAX_CONSTANT} elements")));
    }
    let ints = ints && step_int;
    if ints && (start.abs() > MAX_CONSTANT as f64 || end.abs() > MAX_CONSTANT as f64) {
        return Err(args.bad_value("end", format!("integer constants are at most {MAX_CONSTANT} in magnitude")));
    }
    let dtype = dtype_arg(args, if ints { DType::I64 } else { DType::F32 })?;
    Ok((Op::Pure(Pure::Fill(Fill { shape: vec![len as i64], start, step, dtype })), vec![]))
}

fn filled(args: &Args<'_>, value: f64) -> R<(Op, Vec<ValueRef>)> {
    let shape = size(args)?;
    let dtype = dtype_arg(args, DType::F32)?;
    Ok((Op::Pure(Pure::Fill(Fill { shape, start: value, step: 0.0, dtype })), vec![]))
}

fn zeros(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    filled(args, 0.0)
}

fn ones(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    filled(args, 1.0)
}

fn full(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let (value, is_int) = number(args, "fill_value")?;
    let shape = size(args)?;
    // As torch.full: an int fill value makes an i64 tensor.
    let dtype = dtype_arg(args, if is_int { DType::I64 } else { DType::F32 })?;
    Ok((Op::Pure(Pure::Fill(Fill { shape, start: value, step: 0.0, dtype })), vec![]))
}

fn where_(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let c = args.ttype("condition")?;
    if c.dtype != DType::Bool {
        return Err(args.bad_value("condition", format!("must be a bool tensor (a comparison), got {c}")));
    }
    let is_tensor = |name| matches!(args.value(name), Some(Value::Tensor { .. }));
    if is_tensor("input") && is_tensor("other") {
        let inputs = vec![args.tensor("condition")?, args.tensor("input")?, args.tensor("other")?];
        return Ok((Op::Pure(Pure::Where(Where)), inputs));
    }
    // `torch.where(c, x, 0.0)`: a number for a branch, promoted as torch does (an int
    // tensor with a float makes floats; two ints make an i64).
    let mut inputs = vec![args.tensor("condition")?];
    let mut branch = |name: &str| -> R<(Option<f64>, Option<DType>, bool)> {
        match args.value(name) {
            Some(Value::Tensor { value, .. }) => {
                inputs.push(*value);
                Ok((None, Some(args.ttype(name)?.dtype), false))
            }
            _ => {
                let (v, is_int) = number(args, name)?;
                Ok((Some(v), None, !is_int))
            }
        }
    };
    let (input, ti, fi) = branch("input")?;
    let (other, to, fo) = branch("other")?;
    let dtype = match ti.or(to) {
        Some(t) if t.is_float() => t,
        Some(_) if fi || fo => DType::F32,
        Some(DType::Bool) | None if !(fi || fo) => DType::I64,
        Some(t) if !(fi || fo) => t,
        _ => DType::F32,
    };
    Ok((Op::Pure(Pure::WhereScalar(WhereScalar { input, other, dtype })), inputs))
}

fn float(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    Ok((Op::Pure(Pure::Cast(Cast { to: DType::F32 })), vec![args.tensor("x")?]))
}

fn to(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let to = dtype_arg(args, DType::F32)?;
    Ok((Op::Pure(Pure::Cast(Cast { to })), vec![args.tensor("x")?]))
}

fn index_select(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("input")?.rank();
    let axis = args.axis("dim", rank)?;
    let index = args.ttype("index")?;
    if index.dtype != DType::I64 || index.rank() != 1 {
        return Err(
            args.bad_value("index", format!("must be a 1-D i64 tensor (an int64 buffer, an arange), got {index}"))
        );
    }
    Ok((Op::IndexSelect(IndexSelectOp { axis }), vec![args.tensor("input")?, args.tensor("index")?]))
}

/// `F.embedding(input, weight)`: the rows of `weight` at the positions `input` holds, the
/// index's shape in front of the row.
fn embedding(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let index = args.ttype("input")?;
    if index.dtype != DType::I64 {
        return Err(args.bad_value("input", format!("must be an i64 tensor of indices, got {index}")));
    }
    if args.ttype("weight")?.rank() != 2 {
        return Err(args.bad_value("weight", format!("must be a 2-D table, got {}", args.ttype("weight")?)));
    }
    Ok((Op::IndexSelect(IndexSelectOp { axis: 0 }), vec![args.tensor("weight")?, args.tensor("input")?]))
}
