//! `conv2d(x, out, kernel, stride=1, padding=0, dilation=1, groups=1, bias=true)` and
//! `conv1d` with the same arguments on `[N, C, L]`: PyTorch's `Conv1d`, computed as the
//! conv2d over `[N, C, 1, L]` with a `1 x kernel` window (lowering reshapes around it),
//! its weight `[out, in/groups, kernel]` as PyTorch's `state_dict` has it.

use readi_plan::ops::{Conv2d, ConvAlgo, Operator, ShapeError, ShapeResult, TensorType, Window2};

use super::{Args, Builtin, Epilogue, P, R, boolean, int, req};
use crate::ir::{Op, ParamSlot, ValueRef};

/// A conv layer in the IR: the operator, whether it has a bias, and what the back end
/// decided for it.
#[derive(Clone, Debug, PartialEq)]
pub struct ConvOp {
    pub conv: Conv2d,
    pub bias: bool,
    /// Back end: what runs after the accumulation (`fold_batchnorm`, `fuse_epilogues`).
    pub epilogue: Epilogue,
    /// Back end: the algorithm that computes the layer (`choose_conv_algo`).
    pub algo: Option<ConvAlgo>,
    /// Back end: the weight slot holds the weight packed for `algo` (`pack_weights`).
    pub packed: bool,
    /// Back end: a LoRA branch of this rank computed in the layer's kernel (`fuse_lora`),
    /// slots `lora_A` (packed with the weight) and `lora_B` (pre-scaled).
    pub lora: Option<i64>,
    /// Back end: merged on switch (`pack_weights`, as `choose_strategy` decided): the
    /// weight and `lora_A` slots stay raw although `packed`; the runtime packs the weight,
    /// `B A` merged in, into a per-session working copy when the variant changes.
    pub switch: bool,
    /// Back end: a residual adapter on the output (`fuse_adapters`), between the
    /// epilogue's shift and its ReLU.
    pub adapter: Option<AdapterOp>,
    /// Back end: a second input of the output's shape added after the epilogue's shift,
    /// before its activation (`fuse_epilogues`: a residual connection's add).
    pub residual: bool,
    /// Back end: a last input `[N, in, 1, 1]` scales the input's channels per image
    /// before the conv (`fuse_epilogues`: a squeeze-and-excitation's multiply).
    pub channel_scale: bool,
    /// A `conv1d`: the input is `[N, C, L]` and the output `[N, out, L']`, computed as
    /// `conv` (kernel height 1) on `[N, C, 1, L]`; unpacked weights drop the kernel
    /// height (`[out, in/groups, kw]`).
    pub one_d: bool,
}

/// A bottleneck adapter fused into a conv: `y + up(act(down y))` on its output, `down`
/// a 1x1 conv to `mid` channels and `up` one back, both with a bias: slots
/// `adapter.down.weight [mid, out, 1, 1]`, `adapter.down.bias [mid]`,
/// `adapter.up.weight [out, mid, 1, 1]`, `adapter.up.bias [out]`, bound to the adapter's
/// own tensors.
#[derive(Clone, Debug, PartialEq)]
pub struct AdapterOp {
    pub mid: i64,
    pub act: readi_plan::ops::Activation,
}

impl AdapterOp {
    /// The slot names, in the order [`ConvOp::param_slots`] lists them.
    pub const SLOTS: [&'static str; 4] =
        ["adapter.down.weight", "adapter.down.bias", "adapter.up.weight", "adapter.up.bias"];
}

impl ConvOp {
    /// A conv as the language writes it.
    pub fn new(conv: Conv2d, bias: bool) -> ConvOp {
        ConvOp {
            conv,
            bias,
            epilogue: Epilogue::default(),
            algo: None,
            packed: false,
            lora: None,
            switch: false,
            adapter: None,
            residual: false,
            channel_scale: false,
            one_d: false,
        }
    }

    /// The unpacked weight shape of a conv to `out` channels: PyTorch's, without the
    /// kernel height of a `conv1d`.
    fn raw_weight_shape(&self, out: i64) -> Vec<i64> {
        let mut w = Conv2d { out_channels: out, ..self.conv.clone() }.weight_shape().to_vec();
        if self.one_d {
            w.remove(2);
        }
        w
    }

    /// `weight [out, in/groups, kh, kw]` (packed: `[len]` of the algorithm's layout),
    /// with a bias `bias [out]`, a fused LoRA branch's `lora_A [rank, in, kh, kw]`
    /// (packed: `[len]` of the algorithm's layout at `rank` outputs) and
    /// `lora_B [out, rank]`, then the epilogue's slots.
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        let weight = match self.algo.filter(|_| self.packed && !self.switch) {
            Some(algo) => vec![algo.packed_len(&self.conv.shape(1, 0, 0)) as i64],
            None => self.raw_weight_shape(self.conv.out_channels),
        };
        let mut v = vec![ParamSlot::param("weight", weight)];
        if self.bias {
            v.push(ParamSlot::param("bias", vec![self.conv.out_channels]));
        }
        if let Some(rank) = self.lora {
            let a = Conv2d { out_channels: rank, ..self.conv.clone() };
            // `pack_weights` packs `A` only where that keeps its layout (a Winograd `A`
            // stays raw; the runtime packs it).
            let a_shape = match self.algo.filter(|a| self.packed && a.packs_as_is() && !self.switch) {
                Some(algo) => vec![algo.packed_len(&a.shape(1, 0, 0)) as i64],
                None => self.raw_weight_shape(rank),
            };
            v.push(ParamSlot::param("lora_A", a_shape));
            v.push(ParamSlot::param("lora_B", vec![self.conv.out_channels, rank]));
        }
        v.extend(self.epilogue.slots(self.conv.out_channels));
        if let Some(a) = &self.adapter {
            let c = self.conv.out_channels;
            let [dw, db, uw, ub] = AdapterOp::SLOTS;
            v.push(ParamSlot::param(dw, vec![a.mid, c, 1, 1]));
            v.push(ParamSlot::param(db, vec![a.mid]));
            v.push(ParamSlot::param(uw, vec![c, a.mid, 1, 1]));
            v.push(ParamSlot::param(ub, vec![c]));
        }
        v
    }
}

impl Operator for ConvOp {
    fn kind_name(&self) -> &'static str {
        if self.one_d { "conv1d" } else { self.conv.kind_name() }
    }
    fn arity(&self) -> Option<usize> {
        Some(1 + usize::from(self.residual) + usize::from(self.channel_scale))
    }
    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        if self.residual || self.channel_scale {
            return self.conv.infer_fused(inputs, self.residual, self.channel_scale);
        }
        if !self.one_d {
            return self.conv.infer(inputs);
        }
        let x = inputs[0];
        if x.rank() != 3 {
            return Err(ShapeError::new(format!("conv1d expects a 3-D [N, C, L] tensor, got {x}")));
        }
        let mut shape = x.shape.clone();
        shape.insert(2, readi_plan::Dim::known(1));
        let mut out = self.conv.infer(&[&TensorType::new(x.dtype, shape)])?;
        out.shape.remove(2);
        Ok(out)
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = self.conv.attrs();
        if self.one_d {
            // The window's width: its height is 1, stride 1, no padding, no dilation.
            let w = &self.conv.window;
            let width = [w.kernel[1], w.stride[1], w.padding[1], w.dilation[1]];
            for ((_, value), x) in v[2..6].iter_mut().zip(width) {
                *value = x.to_string();
            }
        }
        v.push(("bias", self.bias.to_string()));
        if let Some(algo) = self.algo {
            v.push(("algo", algo.name().to_string()));
        }
        if let Some(rank) = self.lora {
            v.push(("lora", format!("rank {rank}")));
        }
        if self.switch {
            v.push(("switch", "merge on switch".to_string()));
        }
        if let Some(e) = self.epilogue.attr() {
            v.push(("epilogue", e));
        }
        if let Some(a) = &self.adapter {
            v.push(("adapter", format!("mid {} {}", a.mid, a.act.name())));
        }
        if self.residual {
            v.push(("residual", "input 1, before the activation".to_string()));
        }
        if self.channel_scale {
            let at = 1 + usize::from(self.residual);
            v.push(("channel_scale", format!("input {at}, on the input's channels")));
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
    int("dilation", 1),
    int("groups", 1),
    boolean("bias", true),
];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("conv2d", PARAMS, conv2d), Builtin::new("conv1d", PARAMS, conv1d)]
}

/// `conv1d`: the conv2d of a `1 x kernel` window over `[N, C, 1, L]`.
fn conv1d(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let in_channels = t.known_dim(1).filter(|_| t.rank() == 3).ok_or_else(|| {
        args.bad_value("x", format!("conv1d needs an [N, C, L] tensor with a known channel count, got {t}"))
    })?;
    let window = Window2 {
        kernel: [1, args.int_at_least("kernel", 1)?],
        stride: [1, args.int_at_least("stride", 1)?],
        padding: [0, args.int_at_least("padding", 0)?],
        dilation: [1, args.int_at_least("dilation", 1)?],
    };
    let conv = Conv2d {
        in_channels,
        out_channels: args.int_at_least("out", 1)?,
        window,
        groups: args.int_at_least("groups", 1)?,
    };
    check_groups(args, conv.in_channels, conv.out_channels, conv.groups)?;
    let op = ConvOp { one_d: true, ..ConvOp::new(conv, args.boolean("bias")?) };
    Ok((Op::Conv2d(op), vec![args.tensor("x")?]))
}

/// `groups` divides both channel counts (conv2d, conv1d and conv_transpose2d).
pub(super) fn check_groups(args: &Args<'_>, in_channels: i64, out_channels: i64, groups: i64) -> R<()> {
    if in_channels % groups != 0 || out_channels % groups != 0 {
        return Err(args.bad_value(
            "groups",
            format!("groups={groups} must divide both the {in_channels} input and {out_channels} output channels"),
        ));
    }
    Ok(())
}

/// The `kernel`, `stride`, `padding` and `dilation` arguments of a 2-D conv, each an int
/// or a pair.
pub(super) fn window2(args: &Args<'_>) -> R<Window2> {
    Ok(Window2 {
        kernel: args.pair("kernel", 1)?,
        stride: args.pair("stride", 1)?,
        padding: args.pair("padding", 0)?,
        dilation: args.pair("dilation", 1)?,
    })
}

fn conv2d(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let in_channels = t.known_dim(1).filter(|_| t.rank() == 4).ok_or_else(|| {
        args.bad_value("x", format!("conv2d needs an NCHW tensor with a known channel count, got {t}"))
    })?;
    let window = window2(args)?;
    let conv = Conv2d {
        in_channels,
        out_channels: args.int_at_least("out", 1)?,
        window,
        groups: args.int_at_least("groups", 1)?,
    };
    check_groups(args, conv.in_channels, conv.out_channels, conv.groups)?;
    Ok((Op::Conv2d(ConvOp::new(conv, args.boolean("bias")?)), vec![args.tensor("x")?]))
}
