//! `concat(xs, axis)`, `reshape(x, shape)`, `flatten(x, start=1, end=-1)`,
//! `transpose(x, dim0, dim1)` and `permute(x, dims)`. `flatten` is a reshape and
//! `transpose` a permute.

use readi_plan::ops::{Concat, Permute, Pure, Reshape};

use super::{Args, Builtin, P, R, int, req};
use crate::ir::{Dim, Op, TensorType, ValueRef};
use crate::value::Value;

const CONCAT: &[P] = &[req("xs"), req("axis")];
const RESHAPE: &[P] = &[req("x"), req("shape")];
const TRANSPOSE: &[P] = &[req("x"), req("dim0"), req("dim1")];
const PERMUTE: &[P] = &[req("x"), req("dims")];
const FLATTEN: &[P] = &[req("x"), int("start", 1), int("end", -1)];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("concat", CONCAT, concat),
        Builtin::new("reshape", RESHAPE, reshape),
        Builtin::new("transpose", TRANSPOSE, transpose).alias(),
        Builtin::new("permute", PERMUTE, permute),
        Builtin::new("flatten", FLATTEN, flatten).alias(),
    ]
}

fn concat(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let list = match args.value("xs") {
        Some(Value::List(l)) if !l.is_empty() => l.clone(),
        Some(v) => return Err(args.mismatch("xs", "a non-empty list of tensors", v)),
        None => return Err(args.bad_value("xs", "missing".into())),
    };
    let mut inputs = Vec::new();
    for v in list.iter() {
        match v {
            Value::Tensor { value, .. } => inputs.push(*value),
            other => return Err(args.mismatch("xs", "a list of tensors", other)),
        }
    }
    let rank = args.graph.value_type(inputs[0]).map(|t| t.rank()).unwrap_or(0);
    Ok((Op::Pure(Pure::Concat(Concat { axis: args.axis("axis", rank)? })), inputs))
}

fn reshape(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let shape = reshape_target(args, t)?;
    Ok((Op::Pure(Pure::Reshape(Reshape { shape })), vec![args.tensor("x")?]))
}

fn transpose(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("x")?.rank();
    let (a, b) = (args.axis("dim0", rank)?, args.axis("dim1", rank)?);
    let mut perm: Vec<usize> = (0..rank).collect();
    perm.swap(a, b);
    Ok((Op::Pure(Pure::Permute(Permute { perm })), vec![args.tensor("x")?]))
}

fn permute(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("x")?.rank();
    let perm = args.axes("dims", rank)?;
    let mut seen = vec![false; rank];
    for &p in &perm {
        seen[p] = true;
    }
    if perm.len() != rank || seen.iter().any(|s| !s) {
        return Err(args.bad_value("dims", format!("must list each of the {rank} axes once")));
    }
    Ok((Op::Pure(Pure::Permute(Permute { perm })), vec![args.tensor("x")?]))
}

fn flatten(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let rank = t.rank();
    let (s, e) = (args.axis("start", rank)?, args.axis("end", rank)?);
    if s > e {
        return Err(args.bad_value("end", format!("flatten end axis {e} is before start axis {s}")));
    }
    let merged = Dim::product(&t.shape[s..=e]).ok_or_else(|| args.bad_value("x", "size overflows".into()))?;
    let mut shape: Vec<Dim> = t.shape[..s].to_vec();
    shape.push(merged);
    shape.extend_from_slice(&t.shape[e + 1..]);
    Ok((Op::Pure(Pure::Reshape(Reshape { shape })), vec![args.tensor("x")?]))
}

/// The target shape of `reshape`: ints, symbolic dimensions, and at most one `-1`.
fn reshape_target(args: &Args<'_>, t: &TensorType) -> R<Vec<Dim>> {
    let list = match args.value("shape") {
        Some(Value::List(l)) => l.clone(),
        Some(v) => return Err(args.mismatch("shape", "a list of sizes", v)),
        None => return Err(args.bad_value("shape", "missing".into())),
    };
    let mut dims: Vec<Option<Dim>> = Vec::new();
    for v in list.iter() {
        match v {
            Value::Int(-1) => dims.push(None),
            Value::Int(i) if *i >= 1 => dims.push(Some(Dim::known(*i))),
            Value::Int(i) => {
                return Err(args.bad_value("shape", format!("size {i} is not allowed (use -1 to infer one size)")));
            }
            Value::Dim(d) => dims.push(Some(d.clone())),
            other => return Err(args.mismatch("shape", "a list of sizes", other)),
        }
    }
    let unknown = dims.iter().filter(|d| d.is_none()).count();
    if unknown > 1 {
        return Err(args.bad_value("shape", "at most one size can be -1".into()));
    }
    if unknown == 0 {
        return Ok(dims.into_iter().flatten().collect());
    }
    let total = Dim::product(&t.shape).ok_or_else(|| args.bad_value("x", "size overflows".into()))?;
    let known: Vec<Dim> = dims.iter().flatten().cloned().collect();
    let rest = Dim::product(&known).ok_or_else(|| args.bad_value("shape", "size overflows".into()))?;
    let inferred = total.checked_div(&rest).ok_or_else(|| {
        args.bad_value("shape", format!("cannot infer -1: {total} elements are not divisible by {rest}"))
    })?;
    Ok(dims.into_iter().map(|d| d.unwrap_or_else(|| inferred.clone())).collect())
}
