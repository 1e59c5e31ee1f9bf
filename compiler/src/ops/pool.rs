//! `maxpool(x, kernel, stride=kernel, padding=0, ceil_mode=false)`,
//! `avgpool(..., count_include_pad=true)`, `global_avgpool(x)`, and
//! `adaptive_avgpool(x, output_size)` / `adaptive_maxpool(x, output_size)` (an int or
//! `[h, w]`, PyTorch's `adaptive_{avg,max}_pool2d`).
//!
//! An adaptive pooling whose bins are all alike is written as the plain pooling it equals:
//! to 1x1 an average is `global_avgpool`; where the output size divides the input's, a
//! `maxpool` or `avgpool` with kernel and stride `H / oh` (PyTorch's bins are then exactly
//! those windows). Other sizes keep the adaptive op.

use readi_plan::ops::{AdaptivePool2d, GlobalAvgPool, Pool2d, PoolKind, Pure, Window2};

use super::{Args, Builtin, P, R, absent, boolean, int, req};
use crate::ir::{Op, ValueRef};

const MAXPOOL: &[P] = &[req("x"), req("kernel"), absent("stride"), int("padding", 0), boolean("ceil_mode", false)];
const AVGPOOL: &[P] = &[
    req("x"),
    req("kernel"),
    absent("stride"),
    int("padding", 0),
    boolean("ceil_mode", false),
    boolean("count_include_pad", true),
];
const GLOBAL: &[P] = &[req("x")];
const ADAPTIVE: &[P] = &[req("x"), req("output_size")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("maxpool", MAXPOOL, pool),
        Builtin::new("avgpool", AVGPOOL, pool),
        Builtin::new("global_avgpool", GLOBAL, global_avgpool),
        Builtin::new("adaptive_avgpool", ADAPTIVE, adaptive),
        Builtin::new("adaptive_maxpool", ADAPTIVE, adaptive),
    ]
}

fn pool(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let avg = args.sig.name == "avgpool";
    let kernel = args.pair("kernel", 1)?;
    let stride = if args.present("stride") { args.pair("stride", 1)? } else { kernel };
    let window = Window2 { kernel, stride, padding: args.pair("padding", 0)?, dilation: [1, 1] };
    let pool = Pool2d {
        kind: if avg { PoolKind::Avg } else { PoolKind::Max },
        window,
        ceil_mode: args.boolean("ceil_mode")?,
        count_include_pad: if avg { args.boolean("count_include_pad")? } else { true },
    };
    Ok((Op::Pure(Pure::Pool(pool)), vec![args.tensor("x")?]))
}

fn global_avgpool(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    Ok((Op::Pure(Pure::GlobalAvgPool(GlobalAvgPool)), vec![args.tensor("x")?]))
}

fn adaptive(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let kind = if args.sig.name == "adaptive_avgpool" { PoolKind::Avg } else { PoolKind::Max };
    let output_size = args.pair("output_size", 1)?;
    let t = args.ttype("x")?;
    let known = |a: usize| t.known_dim(a).filter(|&d| t.rank() == 4 && d >= 1);
    let op = match (known(2), known(3)) {
        _ if kind == PoolKind::Avg && output_size == [1, 1] && t.rank() == 4 => Pure::GlobalAvgPool(GlobalAvgPool),
        (Some(h), Some(w)) if h % output_size[0] == 0 && w % output_size[1] == 0 => {
            let kernel = [h / output_size[0], w / output_size[1]];
            let window = Window2 { kernel, stride: kernel, padding: [0, 0], dilation: [1, 1] };
            Pure::Pool(Pool2d { kind, window, ceil_mode: false, count_include_pad: true })
        }
        _ => Pure::AdaptivePool(AdaptivePool2d { kind, output_size }),
    };
    Ok((Op::Pure(op), vec![args.tensor("x")?]))
}
