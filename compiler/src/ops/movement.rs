//! `pad(x, pad, mode="constant", value=0.0)`, `roll(x, shifts, dims)`,
//! `slice(x, dim=0, start, end, step=1)`, `narrow(x, dim, start, length)`, `select(x, dim, index)`, `chunk(x, chunks, dim=0)`,
//! `split(x, split_size_or_sections, dim=0)`, `squeeze(x, dim)`, `unsqueeze(x, dim)` and
//! `expand(x, sizes)`,
//! with PyTorch's names and semantics.
//!
//! `narrow` and `select` make a `slice` (as does `x[...]`, in the elaborator), `chunk` and
//! `split` a list of them, one per piece; `squeeze` and `unsqueeze` make a `reshape`.

use readi_plan::ops::{Expand, Pad, PadMode, Pure, Reshape, Roll, Slice, SliceAxis};

use super::{Args, Builtin, P, R, absent, flt, int, req};
use crate::ir::{Dim, Op, TensorType, ValueRef};
use crate::value::Value;

const PAD: &[P] = &[req("x"), req("pad"), P { name: "mode", default: super::Def::Str("constant") }, flt("value", 0.0)];
const ROLL: &[P] = &[req("x"), req("shifts"), absent("dims")];
const SLICE: &[P] = &[req("x"), int("dim", 0), absent("start"), absent("end"), int("step", 1)];
const NARROW: &[P] = &[req("x"), req("dim"), req("start"), req("length")];
const SELECT: &[P] = &[req("x"), req("dim"), req("index")];
const CHUNK: &[P] = &[req("x"), req("chunks"), int("dim", 0)];
const SPLIT: &[P] = &[req("x"), req("split_size_or_sections"), int("dim", 0)];
const SQUEEZE: &[P] = &[req("x"), absent("dim")];
const UNSQUEEZE: &[P] = &[req("x"), req("dim")];
const EXPAND: &[P] = &[req("x"), req("sizes")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("pad", PAD, pad),
        Builtin::new("roll", ROLL, roll),
        Builtin::new("slice", SLICE, slice),
        Builtin::new("narrow", NARROW, narrow).alias(),
        Builtin::new("select", SELECT, select).alias(),
        Builtin::many("chunk", CHUNK, chunk),
        Builtin::many("split", SPLIT, split),
        Builtin::new("squeeze", SQUEEZE, squeeze).alias(),
        Builtin::new("unsqueeze", UNSQUEEZE, unsqueeze).alias(),
        Builtin::new("expand", EXPAND, expand),
    ]
}

fn pad(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let pads = args.int_list("pad")?;
    let mode = args.string("mode")?;
    let mode = PadMode::parse(&mode).ok_or_else(|| {
        args.bad_value("mode", format!("unknown mode \"{mode}\" (expected \"constant\", \"reflect\" or \"replicate\")"))
    })?;
    let value = args.float("value")?;
    if mode != PadMode::Constant && args.value("value").is_some_and(|v| !matches!(v, Value::Float(0.0) | Value::Int(0)))
    {
        return Err(
            args.bad_value("value", format!("only mode \"constant\" has a fill value, not \"{}\"", mode.name()))
        );
    }
    if !value.is_finite() {
        return Err(args.bad_value("value", format!("must be finite, got {value}")));
    }
    let rank = args.ttype("x")?.rank();
    if !pads.len().is_multiple_of(2) || pads.len() > 2 * rank {
        return Err(args.bad_value(
            "pad",
            format!("needs (before, after) pairs for at most the {rank} axes of `x`, got {} amounts", pads.len()),
        ));
    }
    Ok((Op::Pure(Pure::Pad(Pad { pads, mode, value })), vec![args.tensor("x")?]))
}

fn roll(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("x")?.rank();
    let shifts = args.int_list("shifts")?;
    let axes = if args.present("dims") { args.axes("dims", rank)? } else { Vec::new() };
    if axes.is_empty() && shifts.len() != 1 {
        return Err(args.bad_value("shifts", format!("without `dims` takes one shift, got {}", shifts.len())));
    }
    if !axes.is_empty() && axes.len() != shifts.len() {
        return Err(args.bad_value("dims", format!("{} dims for {} shifts", axes.len(), shifts.len())));
    }
    Ok((Op::Pure(Pure::Roll(Roll { shifts, axes })), vec![args.tensor("x")?]))
}

/// `aten::slice`: `x[start:end:step]` along one axis, Python's bounds.
fn slice(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let axis = args.axis("dim", t.rank())?;
    let bound = |name: &str| if args.present(name) { args.int(name).map(Some) } else { Ok(None) };
    let (start, stop) = (bound("start")?, bound("end")?);
    let step = args.int_at_least("step", 1)?;
    let a = SliceAxis::Range { start, stop, step };
    Ok((Op::Pure(Pure::Slice(one_axis(t.rank(), axis, a))), vec![args.tensor("x")?]))
}

/// The size of axis `axis` of `x`, which the builtin needs known.
fn known(args: &Args<'_>, t: &TensorType, axis: usize, what: &str) -> R<i64> {
    t.known_dim(axis)
        .ok_or_else(|| args.bad_value(what, format!("axis {axis} of {t} is symbolic; its size must be known")))
}

fn one_axis(rank: usize, axis: usize, a: SliceAxis) -> Slice {
    let mut axes = vec![SliceAxis::FULL; rank];
    axes[axis] = a;
    Slice { axes }
}

fn narrow(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let axis = args.axis("dim", t.rank())?;
    let d = known(args, t, axis, "dim")?;
    let start = args.int("start")?;
    let s = if start < 0 { start + d } else { start };
    if s < 0 || s > d {
        return Err(args.bad_value("start", format!("{start} is out of range for axis {axis} of {t}")));
    }
    let length = args.int_at_least("length", 0)?;
    if s + length > d {
        return Err(
            args.bad_value("length", format!("start {s} + length {length} exceeds size {d} of axis {axis} of {t}"))
        );
    }
    let a = SliceAxis::Range { start: Some(s), stop: Some(s + length), step: 1 };
    Ok((Op::Pure(Pure::Slice(one_axis(t.rank(), axis, a))), vec![args.tensor("x")?]))
}

fn select(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let axis = args.axis("dim", t.rank())?;
    let i = args.int("index")?;
    if let Some(d) = t.known_dim(axis)
        && (i >= d || i < -d)
    {
        return Err(args.bad_value("index", format!("{i} is out of range for axis {axis} of {t}")));
    }
    Ok((Op::Pure(Pure::Slice(one_axis(t.rank(), axis, SliceAxis::Index(i)))), vec![args.tensor("x")?]))
}

/// One slice per `(start, length)` along `axis`.
fn pieces(args: &Args<'_>, axis: usize, bounds: Vec<(i64, i64)>) -> R<Vec<(Op, Vec<ValueRef>)>> {
    let t = args.ttype("x")?;
    let x = args.tensor("x")?;
    Ok(bounds
        .into_iter()
        .map(|(s, n)| {
            let a = SliceAxis::Range { start: Some(s), stop: Some(s + n), step: 1 };
            (Op::Pure(Pure::Slice(one_axis(t.rank(), axis, a))), vec![x])
        })
        .collect())
}

/// `torch.chunk`: pieces of `ceil(d / chunks)`, the last smaller; fewer than `chunks` when
/// that size leaves nothing for the rest.
fn chunk(args: &Args<'_>) -> R<Vec<(Op, Vec<ValueRef>)>> {
    let t = args.ttype("x")?;
    let axis = args.axis("dim", t.rank())?;
    let d = known(args, t, axis, "dim")?;
    let chunks = args.int_at_least("chunks", 1)?;
    let size = ((d + chunks - 1) / chunks).max(1);
    let bounds = (0..d).step_by(size as usize).map(|s| (s, size.min(d - s))).collect();
    pieces(args, axis, bounds)
}

/// `torch.split`: pieces of `split_size` (the last smaller), or of the listed sizes, which
/// must add up to the axis.
fn split(args: &Args<'_>) -> R<Vec<(Op, Vec<ValueRef>)>> {
    let t = args.ttype("x")?;
    let axis = args.axis("dim", t.rank())?;
    let d = known(args, t, axis, "dim")?;
    let name = "split_size_or_sections";
    let bounds = match args.value(name) {
        Some(Value::Int(_)) => {
            let size = args.int_at_least(name, 1)?;
            (0..d).step_by(size as usize).map(|s| (s, size.min(d - s))).collect()
        }
        _ => {
            let sizes = args.int_list(name)?;
            if let Some(bad) = sizes.iter().find(|&&n| n < 0) {
                return Err(args.bad_value(name, format!("a section size must not be negative, got {bad}")));
            }
            let total: i64 = sizes.iter().sum();
            if total != d {
                return Err(args.bad_value(name, format!("sections add up to {total}, but axis {axis} of {t} is {d}")));
            }
            let mut s = 0;
            sizes
                .into_iter()
                .map(|n| {
                    s += n;
                    (s - n, n)
                })
                .collect()
        }
    };
    pieces(args, axis, bounds)
}

fn squeeze(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let axes = if args.present("dim") { args.axes("dim", t.rank())? } else { (0..t.rank()).collect() };
    // PyTorch leaves an axis that is not 1 in place.
    let shape: Vec<Dim> = t
        .shape
        .iter()
        .enumerate()
        .filter(|(i, d)| !(axes.contains(i) && d.as_known() == Some(1)))
        .map(|(_, d)| d.clone())
        .collect();
    Ok((Op::Pure(Pure::Reshape(Reshape { shape })), vec![args.tensor("x")?]))
}

fn unsqueeze(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let axis = args.axis("dim", t.rank() + 1)?;
    let mut shape = t.shape.clone();
    shape.insert(axis, Dim::known(1));
    Ok((Op::Pure(Pure::Reshape(Reshape { shape })), vec![args.tensor("x")?]))
}

/// `Tensor.expand`: `-1` keeps an axis; new axes go in front; an axis of size 1 may take
/// any size (a symbolic one too).
fn expand(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let list = match args.value("sizes") {
        Some(Value::List(l)) => l.clone(),
        Some(v) => return Err(args.mismatch("sizes", "a list of sizes", v)),
        None => return Err(args.bad_value("sizes", "missing".into())),
    };
    if list.len() < t.rank() {
        return Err(args.bad_value("sizes", format!("{} sizes for {t}: at least {} needed", list.len(), t.rank())));
    }
    let lead = list.len() - t.rank();
    let mut shape = Vec::with_capacity(list.len());
    for (i, v) in list.iter().enumerate() {
        let d = match v {
            Value::Int(-1) if i >= lead => t.shape[i - lead].clone(),
            Value::Int(n) if *n >= 0 => Dim::known(*n),
            Value::Dim(d) => d.clone(),
            Value::Int(n) => {
                return Err(args.bad_value(
                    "sizes",
                    format!("size {n} at position {i} is not allowed (-1 keeps an existing axis)"),
                ));
            }
            other => return Err(args.mismatch("sizes", "a list of sizes", other)),
        };
        shape.push(d);
    }
    Ok((Op::Pure(Pure::Expand(Expand { shape })), vec![args.tensor("x")?]))
}
