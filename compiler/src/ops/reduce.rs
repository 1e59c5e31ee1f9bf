//! The reductions `sum`, `mean`, `max`, `min`, `var` and `std` (`x, dim, keepdim=false`,
//! and `correction=1` for `var` and `std`: PyTorch's `torch.sum`, `torch.mean`,
//! `torch.amax`, `torch.amin`, `torch.var`, `torch.std`), and `softmax(x, axis=-1)`.
//!
//! `dim` is an axis or a list of axes, negative counting from the end; left out, every
//! axis. `mean` also takes its earlier spelling `axes`.

use readi_plan::ops::{Pure, Reduce, ReduceKind, Softmax};

use super::{Args, Builtin, P, R, absent, boolean, int, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

const SOFTMAX: &[P] = &[req("x"), int("axis", -1)];
const REDUCE: &[P] = &[req("x"), absent("dim"), boolean("keepdim", false)];
const MEAN: &[P] = &[req("x"), absent("dim"), boolean("keepdim", false), absent("axes")];
const VAR: &[P] = &[req("x"), absent("dim"), boolean("keepdim", false), int("correction", 1)];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("softmax", SOFTMAX, softmax),
        Builtin::new("sum", REDUCE, reduce),
        Builtin::new("mean", MEAN, reduce),
        Builtin::new("max", REDUCE, reduce),
        Builtin::new("min", REDUCE, reduce),
        Builtin::new("var", VAR, reduce),
        Builtin::new("std", VAR, reduce),
    ]
}

fn softmax(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("x")?.rank();
    Ok((Op::Pure(Pure::Softmax(Softmax { axis: args.axis("axis", rank)? })), vec![args.tensor("x")?]))
}

fn reduce(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let name = args.sig.name;
    let rank = args.ttype("x")?.rank();
    let correction = || {
        let c = args.int("correction")?;
        if c < 0 {
            return Err(args.bad_value("correction", format!("must be at least 0, got {c}")));
        }
        Ok(c)
    };
    let kind = match name {
        "sum" => ReduceKind::Sum,
        "mean" => ReduceKind::Mean,
        "max" => ReduceKind::Max,
        "min" => ReduceKind::Min,
        "var" => ReduceKind::Var { correction: correction()? },
        _ => ReduceKind::Std { correction: correction()? },
    };
    if let (true, Some(Value::Tensor { .. })) = (matches!(kind, ReduceKind::Max | ReduceKind::Min), args.value("dim")) {
        let what = if kind == ReduceKind::Max { "maximum" } else { "minimum" };
        return Err(args.bad_value(
            "dim",
            format!(
                "`{name}` reduces over axes; the element-wise {what} of two tensors (torch.{what}) is `{what}(input, other)`"
            ),
        ));
    }
    let given = if args.present("axes") { "axes" } else { "dim" };
    if args.present("axes") && args.present("dim") {
        return Err(args.bad_value("axes", "is the earlier spelling of `dim`: give one of them".into()));
    }
    let mut axes = if args.present(given) {
        let axes = args.axes(given, rank)?;
        if axes.is_empty() {
            return Err(args.bad_value(given, "lists no axis (leave it out to reduce over every axis)".into()));
        }
        axes
    } else {
        (0..rank).collect()
    };
    axes.sort_unstable();
    if axes.windows(2).any(|w| w[0] == w[1]) {
        return Err(args.bad_value(given, "lists an axis twice".into()));
    }
    let op = Op::Pure(Pure::Reduce(Reduce { kind, axes, keepdim: args.boolean("keepdim")? }));
    Ok((op, vec![args.tensor("x")?]))
}
