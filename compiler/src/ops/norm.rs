//! `batchnorm(x, eps=1e-5, momentum=0.1)`, `layernorm(x, eps=1e-5, affine=true)` and
//! `groupnorm(x, num_groups, num_channels=C, eps=1e-5, affine=true)` (`nn.GroupNorm`;
//! `num_channels` defaults to axis 1 of `x`).

use readi_plan::DType;
use readi_plan::ops::{BatchNorm, ChannelAffine, GroupNorm, LayerNorm, Operator, ShapeResult, TensorType};

use super::{Args, Builtin, Epilogue, P, R, absent, boolean, flt, positive_float, req};
use crate::ir::{Op, ParamSlot, ValueRef};

/// A BatchNorm's `state_dict`: `weight`, `bias`, `running_mean`, `running_var` (all
/// `[C]`) and `num_batches_tracked` (an i64 scalar).
pub fn batchnorm_slots(bn: &BatchNorm) -> Vec<ParamSlot> {
    let c = bn.channels;
    vec![
        ParamSlot::param("weight", vec![c]),
        ParamSlot::param("bias", vec![c]),
        ParamSlot::buffer("running_mean", vec![c], DType::F32),
        ParamSlot::buffer("running_var", vec![c], DType::F32),
        ParamSlot::buffer("num_batches_tracked", vec![], DType::I64),
    ]
}

/// A LayerNorm's `weight` and `bias` (`[features]`), when it is affine.
pub fn layernorm_slots(ln: &LayerNorm) -> Vec<ParamSlot> {
    if !ln.affine {
        return Vec::new();
    }
    vec![ParamSlot::param("weight", vec![ln.features]), ParamSlot::param("bias", vec![ln.features])]
}

/// A GroupNorm's `weight` and `bias` (`[num_channels]`), when it is affine.
pub fn groupnorm_slots(gn: &GroupNorm) -> Vec<ParamSlot> {
    if !gn.affine {
        return Vec::new();
    }
    vec![ParamSlot::param("weight", vec![gn.num_channels]), ParamSlot::param("bias", vec![gn.num_channels])]
}

/// A BatchNorm the back end could not fold into a conv, as a per-channel affine with its
/// epilogue (scale, shift, maybe a ReLU, and the BatchNorm's record).
#[derive(Clone, Debug, PartialEq)]
pub struct AffineOp {
    pub affine: ChannelAffine,
    pub epilogue: Epilogue,
}

impl AffineOp {
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        self.epilogue.slots(self.affine.channels)
    }
}

impl Operator for AffineOp {
    fn kind_name(&self) -> &'static str {
        self.affine.kind_name()
    }
    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        self.affine.infer(inputs)
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = self.affine.attrs();
        if let Some(e) = self.epilogue.attr() {
            v.push(("epilogue", e));
        }
        v
    }
}

const BATCHNORM: &[P] = &[req("x"), flt("eps", 1e-5), flt("momentum", 0.1)];
const LAYERNORM: &[P] = &[req("x"), flt("eps", 1e-5), boolean("affine", true)];
const GROUPNORM: &[P] =
    &[req("x"), req("num_groups"), absent("num_channels"), flt("eps", 1e-5), boolean("affine", true)];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("batchnorm", BATCHNORM, batchnorm),
        Builtin::new("layernorm", LAYERNORM, layernorm),
        Builtin::new("groupnorm", GROUPNORM, groupnorm),
    ]
}

fn batchnorm(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let channels = t.known_dim(1).filter(|_| t.rank() >= 2).ok_or_else(|| {
        args.bad_value("x", format!("batchnorm needs a tensor with a known axis 1 (channels), got {t}"))
    })?;
    let eps = positive_float(args, "eps")?;
    let momentum = args.float("momentum")?;
    if !(0.0..=1.0).contains(&momentum) {
        return Err(args.bad_value("momentum", format!("must be in [0, 1], got {momentum}")));
    }
    Ok((Op::BatchNorm(BatchNorm { channels, eps, momentum }), vec![args.tensor("x")?]))
}

fn layernorm(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let features = t
        .rank()
        .checked_sub(1)
        .and_then(|l| t.known_dim(l))
        .ok_or_else(|| args.bad_value("x", format!("layernorm needs a known last axis, got {t}")))?;
    let eps = positive_float(args, "eps")?;
    let op = Op::LayerNorm(LayerNorm { features, eps, affine: args.boolean("affine")? });
    Ok((op, vec![args.tensor("x")?]))
}

fn groupnorm(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let num_channels = if args.present("num_channels") {
        args.int_at_least("num_channels", 1)?
    } else {
        t.known_dim(1).filter(|_| t.rank() >= 2).ok_or_else(|| {
            args.bad_value("x", format!("groupnorm needs a tensor with a known axis 1 (channels), got {t}"))
        })?
    };
    let num_groups = args.int_at_least("num_groups", 1)?;
    if num_channels % num_groups != 0 {
        return Err(args.bad_value(
            "num_groups",
            format!("{num_channels} channels do not divide into {num_groups} groups (PyTorch refuses it too)"),
        ));
    }
    let eps = positive_float(args, "eps")?;
    let op = Op::GroupNorm(GroupNorm { num_groups, num_channels, eps, affine: args.boolean("affine")? });
    Ok((op, vec![args.tensor("x")?]))
}
