//! `maxpool(x, kernel, stride=kernel, padding=0, ceil_mode=false)`,
//! `avgpool(..., count_include_pad=true)` and `global_avgpool(x)`.

use readi_plan::ops::{GlobalAvgPool, Pool2d, PoolKind, Pure, Window2};

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

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("maxpool", MAXPOOL, pool),
        Builtin::new("avgpool", AVGPOOL, pool),
        Builtin::new("global_avgpool", GLOBAL, global_avgpool),
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
