//! What the back end fuses into a conv, linear or channel-affine node after its
//! accumulation: `act(acc * scale[c] + shift[c])`, and the BatchNorm it folded.
//!
//! Empty in the front end. `fold_batchnorm` adds a scale and a shift (and the record
//! AdaBN needs to undo the fold), `fuse_epilogues` turns a bias into a shift and absorbs an
//! activation. Each part brings its parameter slots, bound to the tensors the pass derived.

use readi_plan::ops::{Operator, ShapeResult, TensorType};

use crate::ir::{Activation, ParamSlot};

/// See the module documentation.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Epilogue {
    /// A per-channel scale: slot `scale`.
    pub scale: bool,
    /// A per-channel shift (a bias, a folded BatchNorm's shift): slot `shift`.
    pub shift: bool,
    /// Applied last (a ReLU, a clamp, a SiLU, ...).
    pub act: Option<Activation>,
    /// The BatchNorm folded into `scale` and `shift`.
    pub bn: Option<BnFold>,
}

/// A BatchNorm folded into an epilogue, as AdaBN needs it to re-estimate the statistics
/// from a plan: its name and eps, and slots `bn.weight`, `bn.bias` (gamma and beta as
/// themselves) and, when a conv bias went into the shift, `bn.conv_bias`.
#[derive(Clone, Debug, PartialEq)]
pub struct BnFold {
    /// The BatchNorm's path, its PyTorch module name.
    pub name: String,
    pub eps: f64,
    pub conv_bias: bool,
}

impl Epilogue {
    pub fn is_empty(&self) -> bool {
        *self == Epilogue::default()
    }

    /// The slots of an epilogue over `channels` output channels, in order.
    pub fn slots(&self, channels: i64) -> Vec<ParamSlot> {
        let mut v = Vec::new();
        let c = || ParamSlot::param("", vec![channels]);
        let named = |name: &'static str| ParamSlot { name, ..c() };
        if self.scale {
            v.push(named("scale"));
        }
        if self.shift {
            v.push(named("shift"));
        }
        if let Some(bn) = &self.bn {
            v.push(named("bn.weight"));
            v.push(named("bn.bias"));
            if bn.conv_bias {
                v.push(named("bn.conv_bias"));
            }
        }
        v
    }

    /// The epilogue for printouts: `scale+shift+relu (bn1 folded)`, or `None` when empty.
    pub fn attr(&self) -> Option<String> {
        if self.is_empty() {
            return None;
        }
        let mut parts: Vec<String> =
            [(self.scale, "scale"), (self.shift, "shift")].iter().filter(|p| p.0).map(|p| p.1.to_string()).collect();
        parts.extend(self.act.map(Activation::label));
        let mut s = parts.join("+");
        if let Some(bn) = &self.bn {
            s.push_str(&format!(" ({} folded)", bn.name));
        }
        Some(s)
    }
}

/// What a conv operator without LoRA or adapters (`conv_transpose2d`, `conv3d`) tells its
/// IR form: its weight's shape in PyTorch's layout (which its kernel reads as it is) and
/// its output channels.
pub trait ConvWeights: Operator {
    fn weight_dims(&self) -> Vec<i64>;
    fn out_channels(&self) -> i64;
}

/// A conv layer in the IR: the operator, whether it has a bias, and what the back end
/// fused into it (`fuse_epilogues`: the bias as the shift, an activation). Its slots are
/// `weight`, `bias [out]` when it has one, then the epilogue's.
#[derive(Clone, Debug, PartialEq)]
pub struct BiasedConv<C> {
    pub conv: C,
    pub bias: bool,
    pub epilogue: Epilogue,
}

impl<C: ConvWeights> BiasedConv<C> {
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        let mut v = vec![ParamSlot::param("weight", self.conv.weight_dims())];
        if self.bias {
            v.push(ParamSlot::param("bias", vec![self.conv.out_channels()]));
        }
        v.extend(self.epilogue.slots(self.conv.out_channels()));
        v
    }
}

impl<C: ConvWeights> Operator for BiasedConv<C> {
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
