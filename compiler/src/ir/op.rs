//! Operations of the graph IR and their parameter slots.
//!
//! Each [`Op`] is self-describing: its attributes hold every size its parameters depend
//! on (a conv knows its input channels), so [`Op::param_slots`] derives the parameter
//! slots from the op alone and the verifier can check them against the input shapes.
//! The attributes and shape rules are `readi_plan::ops`'s, shared with the runtime;
//! [`Op::def`] gives the rule of any op.

use readi_plan::ops::{self, BatchNorm, GroupNorm, LayerNorm, Operator, Pure, ShapeError, ShapeResult};

use super::{DType, TensorType};
use crate::ops::{
    AffineOp, BufferOp, ConstantOp, Conv3dOp, ConvOp, ConvTransposeOp, IndexSelectOp, LinearOp, ParameterOp,
    batchnorm_slots, groupnorm_slots, layernorm_slots,
};

/// An operation of the graph. The tensor inputs are the node's incoming edges; everything
/// else is an attribute here.
#[derive(Clone, Debug, PartialEq)]
pub enum Op {
    /// A graph input. It has no incoming edges and one output.
    Input(InputAttrs),
    /// A learned tensor used directly (a position embedding, a query table).
    Parameter(ParameterOp),
    /// A `state_dict` buffer used directly (an int64 index table).
    Buffer(BufferOp),
    /// A tensor computed at compile time from stored tensors (`fold_constants`).
    Constant(ConstantOp),
    /// `index_select` / `embedding` with its index as an input, until the back end folds
    /// the index's values into the op (a `Pure::IndexSelect`).
    IndexSelect(IndexSelectOp),
    /// 2-D convolution over NCHW, weight `[out, in/groups, kh, kw]`, optional bias `[out]`.
    Conv2d(ConvOp),
    /// Transposed 2-D convolution over NCHW, weight `[in, out/groups, kh, kw]`, optional
    /// bias `[out]`.
    ConvTranspose2d(ConvTransposeOp),
    /// 3-D convolution over NCDHW, weight `[out, in/groups, kd, kh, kw]`, optional bias
    /// `[out]`.
    Conv3d(Conv3dOp),
    /// Batch normalisation over axis 1 with affine parameters and running statistics.
    BatchNorm(BatchNorm),
    /// Layer normalisation over the last axis.
    LayerNorm(LayerNorm),
    /// Group normalisation over groups of axis 1's channels.
    GroupNorm(GroupNorm),
    /// `y = x W^T + b` over the last axis.
    Linear(LinearOp),
    /// A per-channel affine: a BatchNorm folded by the back end that no conv absorbed.
    ChannelAffine(AffineOp),
    /// An operator without parameters: element-wise ops, layout, pooling, reductions.
    Pure(Pure),
}

/// Attributes of a graph input.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct InputAttrs {
    pub name: String,
    pub modality: Option<String>,
    pub optional: bool,
}

impl Operator for InputAttrs {
    fn kind_name(&self) -> &'static str {
        "input"
    }
    fn arity(&self) -> Option<usize> {
        Some(0)
    }
    fn infer(&self, _: &[&TensorType]) -> ShapeResult<TensorType> {
        Err(ShapeError::new("an input's type is declared, not inferred"))
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = vec![("name", self.name.clone())];
        if let Some(m) = &self.modality {
            v.push(("modality", m.clone()));
        }
        if self.optional {
            v.push(("optional", "true".into()));
        }
        v
    }
}

/// Whether a slot holds a trainable parameter or a buffer (running statistics, counters).
/// PyTorch's `parameters()` counts only the former; its `state_dict` holds both.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SlotKind {
    Param,
    Buffer,
    /// A parameter an adaptation rule adds (a LoRA matrix, an adapter weight): not part of
    /// the base model, zero there, and owned by every variant.
    Added,
}

/// A named tensor a node needs besides its inputs: a weight, a bias, a running statistic.
/// Its full name is `<node path>.<name>`, the PyTorch `state_dict` key, unless a back-end
/// pass bound the slot to a tensor it derived (`tensor`: a folded scale, a packed
/// weight). Values are bound from safetensors by `bind_weights`; here the slot fixes
/// name, shape and type.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamSlot {
    pub name: &'static str,
    pub shape: Vec<i64>,
    pub dtype: DType,
    pub kind: SlotKind,
    /// The tensor the slot reads when it is not `<path>.<name>`.
    pub tensor: Option<String>,
}

impl ParamSlot {
    /// A trainable f32 parameter.
    pub fn param(name: &'static str, shape: Vec<i64>) -> ParamSlot {
        ParamSlot { name, shape, dtype: DType::F32, kind: SlotKind::Param, tensor: None }
    }
    /// A buffer (running statistics, counters).
    pub fn buffer(name: &'static str, shape: Vec<i64>, dtype: DType) -> ParamSlot {
        ParamSlot { name, shape, dtype, kind: SlotKind::Buffer, tensor: None }
    }
    /// The same slot reading `tensor`.
    pub fn bound(self, tensor: String) -> ParamSlot {
        ParamSlot { tensor: Some(tensor), ..self }
    }
    /// Number of elements.
    pub fn numel(&self) -> u64 {
        // Saturating: elaboration refuses parameters over `MAX_PARAM_ELEMENTS`, so this
        // only guards sums over a graph that was not elaborated.
        self.shape.iter().fold(1u64, |acc, &d| acc.saturating_mul(d.max(0) as u64))
    }
}

impl Op {
    /// The operator's definition: its name, attributes and shape rule.
    pub fn def(&self) -> &dyn Operator {
        match self {
            Op::Input(o) => o,
            Op::Parameter(o) => o,
            Op::Buffer(o) => o,
            Op::Constant(o) => o,
            Op::IndexSelect(o) => o,
            Op::Conv2d(o) => o,
            Op::ConvTranspose2d(o) => o,
            Op::Conv3d(o) => o,
            Op::BatchNorm(o) => o,
            Op::LayerNorm(o) => o,
            Op::GroupNorm(o) => o,
            Op::Linear(o) => o,
            Op::ChannelAffine(o) => o,
            Op::Pure(p) => p.op(),
        }
    }

    /// The op's name as written in the language; selectors match op kinds by this name.
    pub fn kind_name(&self) -> &'static str {
        self.def().kind_name()
    }

    /// Number of tensor inputs, or `None` for variadic ops (concat: one or more).
    pub fn arity(&self) -> Option<usize> {
        self.def().arity()
    }

    /// The output types of the op applied to inputs of the given types.
    pub fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<Vec<TensorType>> {
        ops::infer(self.def(), inputs).map(|t| vec![t])
    }

    /// The attributes as `key=value` pairs for printers, in a fixed order. Defaults are
    /// printed too: the printout is the op's full meaning.
    pub fn attrs(&self) -> Vec<(&'static str, String)> {
        self.def().attrs()
    }

    /// The parameter slots of this op, in `state_dict` order.
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        match self {
            Op::Parameter(p) => p.param_slots(),
            Op::Buffer(b) => b.param_slots(),
            Op::Constant(c) => c.param_slots(),
            Op::Conv2d(c) => c.param_slots(),
            Op::ConvTranspose2d(c) => c.param_slots(),
            Op::Conv3d(c) => c.param_slots(),
            Op::BatchNorm(bn) => batchnorm_slots(bn),
            Op::LayerNorm(ln) => layernorm_slots(ln),
            Op::GroupNorm(gn) => groupnorm_slots(gn),
            Op::Linear(l) => l.param_slots(),
            Op::ChannelAffine(a) => a.param_slots(),
            Op::Input(_) | Op::Pure(_) | Op::IndexSelect(_) => Vec::new(),
        }
    }

    /// Whether the op has trainable parameters (and so needs a name).
    pub fn has_params(&self) -> bool {
        !self.param_slots().is_empty()
    }
}
