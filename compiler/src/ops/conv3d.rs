//! `conv3d(x, out, kernel, stride=1, padding=0, dilation=1, groups=1, bias=true)` on
//! `[N, C, D, H, W]`: PyTorch's `nn.Conv3d`, its arguments in its order (those of
//! `conv2d`), each size an int or a `[d, h, w]` triple; weight `[out, in/groups, kd, kh,
//! kw]` as its `state_dict` has it.

use readi_plan::ops::{Conv3d, Window3};

use super::{Args, BiasedConv, Builtin, ConvWeights, Epilogue, P, R, boolean, int, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

/// A conv3d layer in the IR (see [`BiasedConv`]).
pub type Conv3dOp = BiasedConv<Conv3d>;

impl ConvWeights for Conv3d {
    fn weight_dims(&self) -> Vec<i64> {
        self.weight_shape().to_vec()
    }
    fn out_channels(&self) -> i64 {
        self.out_channels
    }
}

const PARAMS: &[P] = &[
    req("x"),
    req("out"),
    req("kernel"),
    int("stride", 1),
    int("padding", 0),
    int("dilation", 1),
    int("groups", 1),
    boolean("bias", true),
];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("conv3d", PARAMS, conv3d)]
}

/// An int or a list of three ints (depth, height, width), each at least `min`: `3` or
/// `[3, 1, 1]`.
pub(super) fn triple(args: &Args<'_>, name: &str, min: i64) -> R<[i64; 3]> {
    let expected = "an int or a list of three ints [d, h, w]";
    let t = match args.value(name) {
        Some(Value::Int(i)) => [*i; 3],
        Some(v @ Value::List(l)) => match l[..] {
            [Value::Int(a), Value::Int(b), Value::Int(c)] => [a, b, c],
            _ => return Err(args.mismatch(name, expected, v)),
        },
        Some(v) => return Err(args.mismatch(name, expected, v)),
        None => return Err(args.bad_value(name, "missing".into())),
    };
    if t.iter().any(|&v| v < min) {
        let shown = if t[0] == t[1] && t[1] == t[2] { t[0].to_string() } else { format!("{t:?}") };
        return Err(args.bad_value(name, format!("must be at least {min}, got {shown}")));
    }
    Ok(t)
}

fn conv3d(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let in_channels = t.known_dim(1).filter(|_| t.rank() == 5).ok_or_else(|| {
        args.bad_value("x", format!("conv3d needs an NCDHW tensor with a known channel count, got {t}"))
    })?;
    let window = Window3 {
        kernel: triple(args, "kernel", 1)?,
        stride: triple(args, "stride", 1)?,
        padding: triple(args, "padding", 0)?,
        dilation: triple(args, "dilation", 1)?,
    };
    let conv = Conv3d {
        in_channels,
        out_channels: args.int_at_least("out", 1)?,
        window,
        groups: args.int_at_least("groups", 1)?,
    };
    super::conv::check_groups(args, in_channels, conv.out_channels, conv.groups)?;
    let op = Conv3dOp { conv, bias: args.boolean("bias")?, epilogue: Epilogue::default() };
    Ok((Op::Conv3d(op), vec![args.tensor("x")?]))
}
