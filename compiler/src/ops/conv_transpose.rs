//! `conv_transpose2d(x, out, kernel, stride=1, padding=0, output_padding=0, groups=1,
//! bias=true, dilation=1)`: PyTorch's `nn.ConvTranspose2d`, its arguments in its order.

use readi_plan::ops::{ConvTranspose2d, Operator, ShapeResult, TensorType};

use super::{Args, Builtin, Epilogue, P, R, boolean, int, req};
use crate::ir::{Op, ParamSlot, ValueRef};

/// A transposed conv layer in the IR: the operator, whether it has a bias, and what the
/// back end fused into it (`fuse_epilogues`: the bias as the shift, an activation).
#[derive(Clone, Debug, PartialEq)]
pub struct ConvTransposeOp {
    pub conv: ConvTranspose2d,
    pub bias: bool,
    pub epilogue: Epilogue,
}

impl ConvTransposeOp {
    /// `weight [in, out/groups, kh, kw]` (PyTorch's layout, which the kernel reads as it
    /// is), with a bias `bias [out]`, then the epilogue's slots.
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        let mut v = vec![ParamSlot::param("weight", self.conv.weight_shape().to_vec())];
        if self.bias {
            v.push(ParamSlot::param("bias", vec![self.conv.out_channels]));
        }
        v.extend(self.epilogue.slots(self.conv.out_channels));
        v
    }
}

impl Operator for ConvTransposeOp {
    fn kind_name(&self) -> &'static str {
        self.conv.kind_name()
    }
    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        self.conv.infer(inputs)
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = self.conv.attrs();
        v.push(("bias", self.bias.to_string()));
        if let Some(e) = self.epilogue.attr() {
            v.push(("epilogue", e));
        }
        v
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
