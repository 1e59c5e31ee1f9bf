//! `conv_transpose2d(x, out, kernel, stride=1, padding=0, output_padding=0, groups=1,
//! bias=true, dilation=1)`: PyTorch's `nn.ConvTranspose2d`, its arguments in its order.

use readi_plan::ops::ConvTranspose2d;

use super::{Args, BiasedConv, Builtin, ConvWeights, Epilogue, P, R, boolean, int, req};
use crate::ir::{Op, ValueRef};

/// A transposed conv layer in the IR (see [`BiasedConv`]).
pub type ConvTransposeOp = BiasedConv<ConvTranspose2d>;

impl ConvWeights for ConvTranspose2d {
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
    int("output_padding", 0),
    int("groups", 1),
    boolean("bias", true),
    int("dilation", 1),
];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("conv_transpose2d", PARAMS, conv_transpose2d)]
}

fn conv_transpose2d(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let in_channels = t.known_dim(1).filter(|_| t.rank() == 4).ok_or_else(|| {
        args.bad_value("x", format!("conv_transpose2d needs an NCHW tensor with a known channel count, got {t}"))
    })?;
    let window = super::conv::window2(args)?;
    let output_padding = args.pair("output_padding", 0)?;
    for ((&op, &stride), &dilation) in output_padding.iter().zip(&window.stride).zip(&window.dilation) {
        if op >= stride && op >= dilation {
            return Err(args.bad_value(
                "output_padding",
                format!(
                    "output_padding {op} must be smaller than either the stride {stride} or the dilation {dilation}"
                ),
            ));
        }
    }
    let conv = ConvTranspose2d {
        in_channels,
        out_channels: args.int_at_least("out", 1)?,
        window,
        output_padding,
        groups: args.int_at_least("groups", 1)?,
    };
    super::conv::check_groups(args, in_channels, conv.out_channels, conv.groups)?;
    let op = ConvTransposeOp { conv, bias: args.boolean("bias")?, epilogue: Epilogue::default() };
    Ok((Op::ConvTranspose2d(op), vec![args.tensor("x")?]))
}
