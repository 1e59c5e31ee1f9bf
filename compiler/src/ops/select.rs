//! Operators on indices computed at run time, with PyTorch's names and arguments:
//! `argmax(input, dim=None, keepdim=False)`, `argmin(...)`,
//! `topk(input, k, dim=-1, largest=True, sorted=True)` (a list: values, indices),
//! `gather(input, dim, index)`, `take_along_dim(input, indices, dim)`,
//! `one_hot(tensor, num_classes)`, and the element-wise `maximum(input, other)`,
//! `minimum`, `floor_divide` (`a // b`), `remainder` (`a % b`) and `atan2`, each with a
//! number for either operand.
//!
//! An i64 tensor at run time is f32 holding integers; the kernels check every index they
//! read (an integer in range, else the step fails naming it). `index_select` at a
//! computed index and `where` with a number are built in `index.rs`.

use readi_plan::DType;
use readi_plan::ops::{ArgKind, ArgReduce, BinaryOp, Gather, OneHot, Pure, Scalar, TopK};

use super::{Args, Builtin, P, R, absent, boolean, int, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

const INPUT_OTHER: &[P] = &[req("input"), req("other")];
const ARG: &[P] = &[req("input"), absent("dim"), boolean("keepdim", false)];
const TOPK: &[P] = &[req("input"), req("k"), int("dim", -1), boolean("largest", true), boolean("sorted", true)];
const GATHER: &[P] = &[req("input"), req("dim"), req("index")];
const TAKE_ALONG_DIM: &[P] = &[req("input"), req("indices"), absent("dim")];
const ONE_HOT: &[P] = &[req("tensor"), int("num_classes", -1)];

pub(super) fn builtins() -> Vec<Builtin> {
    let binary = BinaryOp::INPUT_OTHER.iter().map(|op| Builtin::new(op.name(), INPUT_OTHER, input_other));
    let rest = [
        Builtin::new("argmax", ARG, argmax),
        Builtin::new("argmin", ARG, argmin),
        Builtin::many("topk", TOPK, topk),
        Builtin::new("gather", GATHER, gather),
        Builtin::new("take_along_dim", TAKE_ALONG_DIM, take_along_dim),
        Builtin::new("one_hot", ONE_HOT, one_hot),
    ];
    binary.chain(rest).collect()
}

/// `maximum(input, other)` and its kin: two tensors broadcast (one element type), or a
/// tensor and a number on either side.
fn input_other(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let op = BinaryOp::INPUT_OTHER.into_iter().find(|o| o.name() == args.sig.name).ok_or_else(|| {
        readi_grammar::diag::Diagnostic::error(
            readi_grammar::diag::Code::Internal,
            format!("internal compiler error: builtin `{}` names no operator", args.sig.name),
        )
    })?;
    let number = |name: &str| match args.value(name) {
        Some(Value::Int(i)) => Ok(*i as f64),
        Some(Value::Float(f)) if f.is_finite() => Ok(*f),
        Some(v) => Err(args.mismatch(name, "a tensor or a finite number", v)),
        None => Err(args.bad_value(name, "missing".into())),
    };
    match (args.value("input"), args.value("other")) {
        (Some(Value::Tensor { value: a, .. }), Some(Value::Tensor { value: b, .. })) => {
            let (ta, tb) = (args.ttype("input")?, args.ttype("other")?);
            if ta.dtype != tb.dtype {
                return Err(args.bad_value(
                    "other",
                    format!("is {tb} and `input` {ta}: give both one element type (`to(x, dtype)`)"),
                ));
            }
            Ok((Op::Pure(Pure::Binary(op)), vec![*a, *b]))
        }
        (Some(Value::Tensor { value: a, .. }), _) => {
            let value = number("other")?;
            Ok((Op::Pure(Pure::Scalar(Scalar { op, value, scalar_first: false })), vec![*a]))
        }
        (_, Some(Value::Tensor { value: b, .. })) => {
            let value = number("input")?;
            Ok((Op::Pure(Pure::Scalar(Scalar { op, value, scalar_first: true })), vec![*b]))
        }
        _ => Err(args.tensor("input").err().unwrap_or_else(|| args.bad_value("input", "must be a tensor".into()))),
    }
}

fn arg_reduce(args: &Args<'_>, kind: ArgKind) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("input")?;
    let axis = if args.present("dim") { Some(args.axis("dim", t.rank().max(1))?) } else { None };
    // torch: a rank-0 tensor's dim may be 0 or -1, and its argmax is 0.
    let axis = axis.filter(|_| t.rank() > 0);
    let keepdim = args.boolean("keepdim")?;
    Ok((Op::Pure(Pure::ArgReduce(ArgReduce { kind, axis, keepdim })), vec![args.tensor("input")?]))
}

fn argmax(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    arg_reduce(args, ArgKind::Max)
}

fn argmin(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    arg_reduce(args, ArgKind::Min)
}

/// `torch.topk`: a list of two tensors, the values and their indices (i64), one op each.
fn topk(args: &Args<'_>) -> R<Vec<(Op, Vec<ValueRef>)>> {
    let t = args.ttype("input")?;
    let axis = args.axis("dim", t.rank())?;
    let k = args.int_at_least("k", 0)?;
    if let Some(d) = t.known_dim(axis)
        && k > d
    {
        return Err(args.bad_value("k", format!("{k} is more than the {d} values along axis {axis} of {t}")));
    }
    let (largest, sorted) = (args.boolean("largest")?, args.boolean("sorted")?);
    let x = args.tensor("input")?;
    let op = |indices| Op::Pure(Pure::TopK(TopK { k: k as usize, axis, largest, sorted, indices }));
    Ok(vec![(op(false), vec![x]), (op(true), vec![x])])
}

/// The i64 index argument `name` of a gather.
fn index_arg(args: &Args<'_>, name: &str, rank: usize) -> R<ValueRef> {
    let index = args.ttype(name)?;
    if index.dtype != DType::I64 {
        return Err(args.bad_value(name, format!("must be an i64 tensor (from topk, argmax, ...), got {index}")));
    }
    if index.rank() != rank {
        return Err(
            args.bad_value(name, format!("has {} axes and `input` {rank}: they must have as many", index.rank()))
        );
    }
    args.tensor(name)
}

fn gather(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("input")?.rank();
    let axis = args.axis("dim", rank)?;
    let index = index_arg(args, "index", rank)?;
    Ok((Op::Pure(Pure::Gather(Gather { axis, broadcast: false })), vec![args.tensor("input")?, index]))
}

fn take_along_dim(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    if !args.present("dim") {
        return Err(args.bad_value(
            "dim",
            "is needed: readi has take_along_dim along one axis only (flatten both for the other form)".into(),
        ));
    }
    let rank = args.ttype("input")?.rank();
    let axis = args.axis("dim", rank)?;
    let index = index_arg(args, "indices", rank)?;
    Ok((Op::Pure(Pure::Gather(Gather { axis, broadcast: true })), vec![args.tensor("input")?, index]))
}

/// `F.one_hot(tensor, num_classes)`: `num_classes` must be given (PyTorch's default, -1,
/// reads it from the data, which would make the shape depend on it).
fn one_hot(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("tensor")?;
    if t.dtype != DType::I64 {
        return Err(args.bad_value("tensor", format!("must be an i64 tensor of class indices, got {t}")));
    }
    let n = args.int("num_classes")?;
    if n < 1 {
        return Err(args.bad_value(
            "num_classes",
            format!("must be given and at least 1, got {n} (readi needs the number of classes to know the shape)"),
        ));
    }
    Ok((Op::Pure(Pure::OneHot(OneHot { num_classes: n as usize })), vec![args.tensor("tensor")?]))
}
