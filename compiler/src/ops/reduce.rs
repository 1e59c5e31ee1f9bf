//! `mean(x, axes, keepdim=false)` and `softmax(x, axis=-1)`.

use readi_plan::ops::{Mean, Pure, Softmax};

use super::{Args, Builtin, P, R, boolean, int, req};
use crate::ir::{Op, ValueRef};

const SOFTMAX: &[P] = &[req("x"), int("axis", -1)];
const MEAN: &[P] = &[req("x"), req("axes"), boolean("keepdim", false)];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("softmax", SOFTMAX, softmax), Builtin::new("mean", MEAN, mean)]
}

fn softmax(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("x")?.rank();
    Ok((Op::Pure(Pure::Softmax(Softmax { axis: args.axis("axis", rank)? })), vec![args.tensor("x")?]))
}

fn mean(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let rank = args.ttype("x")?.rank();
    let mut axes = args.axes("axes", rank)?;
    axes.sort_unstable();
    if axes.windows(2).any(|w| w[0] == w[1]) {
        return Err(args.bad_value("axes", "lists an axis twice".into()));
    }
    let op = Op::Pure(Pure::Mean(Mean { axes, keepdim: args.boolean("keepdim")? }));
    Ok((op, vec![args.tensor("x")?]))
}
