//! Operations of the graph IR and their attributes.
//!
//! Each [`Op`] is self-describing: its attributes hold every size its parameters depend
//! on (a conv knows its input channels), so [`Op::param_slots`] derives the parameter
//! slots from the op alone and the verifier can check them against the input shapes.

use std::fmt::{self, Write};

use readi_grammar::ast::DType;

use super::Dim;

/// An operation of the graph. The tensor inputs are the node's incoming edges; everything
/// else is an attribute here.
#[derive(Clone, Debug, PartialEq)]
pub enum Op {
    /// A graph input. It has no incoming edges and one output.
    Input(InputAttrs),
    /// 2-D convolution over NCHW, weight `[out, in/groups, kh, kw]`, optional bias `[out]`.
    Conv2d(Conv2dAttrs),
    /// Batch normalisation over axis 1 with affine parameters and running statistics.
    BatchNorm { channels: i64, eps: f64, momentum: f64 },
    /// Layer normalisation over the last axis.
    LayerNorm { features: i64, eps: f64, affine: bool },
    /// `y = x W^T + b` over the last axis.
    Linear { in_features: i64, out_features: i64, bias: bool },
    /// Batched matrix product with broadcasting over leading axes.
    MatMul,
    /// Element-wise binary op with NumPy broadcasting.
    Binary(BinaryKind),
    /// Element-wise op with a constant: `x * 0.125`, or `1 - x` when `scalar_first`.
    Scalar { kind: BinaryKind, value: f64, scalar_first: bool },
    /// Element-wise activation.
    Activation(Activation),
    /// Softmax along one axis.
    Softmax { axis: usize },
    /// Concatenation of the inputs along one axis.
    Concat { axis: usize },
    /// Reshape to a fixed target shape (element count unchanged).
    Reshape { shape: Vec<Dim> },
    /// Axis permutation: output axis `i` is input axis `perm[i]`.
    Permute { perm: Vec<usize> },
    /// Max or average pooling over the last two axes.
    Pool(PoolAttrs),
    /// Mean over the spatial axes of NCHW, keeping them as 1x1.
    GlobalAvgPool,
    /// Resize of the last two axes to a fixed size. `scale` is the factor the source gave,
    /// which PyTorch uses (rather than the size ratio) to map output to input positions.
    Upsample { size: [i64; 2], scale: Option<[f64; 2]>, mode: UpsampleMode, align_corners: bool },
    /// Mean over the given axes.
    Mean { axes: Vec<usize>, keepdim: bool },
    /// A learned tensor used directly (a position embedding, a query table). Its single
    /// slot has an empty name, so its `state_dict` key is the node path itself.
    Parameter { shape: Vec<i64> },
}

/// Attributes of a graph input.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct InputAttrs {
    pub name: String,
    pub modality: Option<String>,
    pub optional: bool,
}

/// Attributes of a 2-D convolution.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Conv2dAttrs {
    pub in_channels: i64,
    pub out_channels: i64,
    pub kernel: [i64; 2],
    pub stride: [i64; 2],
    pub padding: [i64; 2],
    pub dilation: [i64; 2],
    pub groups: i64,
    pub bias: bool,
}

/// Attributes of max and average pooling.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PoolAttrs {
    pub kind: PoolKind,
    pub kernel: [i64; 2],
    pub stride: [i64; 2],
    pub padding: [i64; 2],
    pub ceil_mode: bool,
    /// Average pooling only: whether padded zeros count in the divisor.
    pub count_include_pad: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PoolKind {
    Max,
    Avg,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BinaryKind {
    Add,
    Sub,
    Mul,
    Div,
}

impl BinaryKind {
    pub fn name(self) -> &'static str {
        match self {
            BinaryKind::Add => "add",
            BinaryKind::Sub => "sub",
            BinaryKind::Mul => "mul",
            BinaryKind::Div => "div",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Activation {
    Relu,
    /// GELU with the exact erf formulation.
    Gelu,
    /// GELU with the tanh approximation.
    GeluTanh,
    Sigmoid,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum UpsampleMode {
    Nearest,
    Bilinear,
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
/// Its full name is `<node path>.<name>`, the PyTorch `state_dict` key. Values are bound
/// later (from safetensors); here the slot only fixes name, shape and type.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamSlot {
    pub name: &'static str,
    pub shape: Vec<i64>,
    pub dtype: DType,
    pub kind: SlotKind,
}

impl ParamSlot {
    fn param(name: &'static str, shape: Vec<i64>) -> ParamSlot {
        ParamSlot { name, shape, dtype: DType::F32, kind: SlotKind::Param }
    }
    fn buffer(name: &'static str, shape: Vec<i64>, dtype: DType) -> ParamSlot {
        ParamSlot { name, shape, dtype, kind: SlotKind::Buffer }
    }
    /// Number of elements.
    pub fn numel(&self) -> u64 {
        self.shape.iter().map(|&d| d.max(0) as u64).product()
    }
}

impl Op {
    /// The op's name as written in the language; selectors match op kinds by this name.
    pub fn kind_name(&self) -> &'static str {
        match self {
            Op::Input(_) => "input",
            Op::Conv2d(_) => "conv2d",
            Op::BatchNorm { .. } => "batchnorm",
            Op::LayerNorm { .. } => "layernorm",
            Op::Linear { .. } => "linear",
            Op::MatMul => "matmul",
            Op::Binary(k) => k.name(),
            Op::Scalar { kind, .. } => kind.name(),
            Op::Activation(Activation::Relu) => "relu",
            Op::Activation(Activation::Gelu | Activation::GeluTanh) => "gelu",
            Op::Activation(Activation::Sigmoid) => "sigmoid",
            Op::Softmax { .. } => "softmax",
            Op::Concat { .. } => "concat",
            Op::Reshape { .. } => "reshape",
            Op::Permute { .. } => "permute",
            Op::Pool(p) => match p.kind {
                PoolKind::Max => "maxpool",
                PoolKind::Avg => "avgpool",
            },
            Op::GlobalAvgPool => "global_avgpool",
            Op::Upsample { .. } => "upsample",
            Op::Mean { .. } => "mean",
            Op::Parameter { .. } => "parameter",
        }
    }

    /// Number of tensor inputs, or `None` for variadic ops (concat: one or more).
    pub fn arity(&self) -> Option<usize> {
        match self {
            Op::Input(_) | Op::Parameter { .. } => Some(0),
            Op::MatMul | Op::Binary(_) => Some(2),
            Op::Concat { .. } => None,
            _ => Some(1),
        }
    }

    /// The parameter slots of this op, in `state_dict` order.
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        match self {
            Op::Conv2d(c) => {
                let mut v = vec![ParamSlot::param(
                    "weight",
                    vec![c.out_channels, c.in_channels / c.groups.max(1), c.kernel[0], c.kernel[1]],
                )];
                if c.bias {
                    v.push(ParamSlot::param("bias", vec![c.out_channels]));
                }
                v
            }
            Op::BatchNorm { channels, .. } => vec![
                ParamSlot::param("weight", vec![*channels]),
                ParamSlot::param("bias", vec![*channels]),
                ParamSlot::buffer("running_mean", vec![*channels], DType::F32),
                ParamSlot::buffer("running_var", vec![*channels], DType::F32),
                ParamSlot::buffer("num_batches_tracked", vec![], DType::I64),
            ],
            Op::LayerNorm { features, affine: true, .. } => {
                vec![ParamSlot::param("weight", vec![*features]), ParamSlot::param("bias", vec![*features])]
            }
            Op::Linear { in_features, out_features, bias } => {
                let mut v = vec![ParamSlot::param("weight", vec![*out_features, *in_features])];
                if *bias {
                    v.push(ParamSlot::param("bias", vec![*out_features]));
                }
                v
            }
            Op::Parameter { shape } => vec![ParamSlot::param("", shape.clone())],
            _ => Vec::new(),
        }
    }

    /// Whether the op has trainable parameters (and so needs a name).
    pub fn has_params(&self) -> bool {
        !self.param_slots().is_empty()
    }

    /// The attributes as `key=value` pairs for printers, in a fixed order. Defaults are
    /// printed too: the printout is the op's full meaning.
    pub fn attrs(&self) -> Vec<(&'static str, String)> {
        fn pair(p: [i64; 2]) -> String {
            if p[0] == p[1] { p[0].to_string() } else { format!("{}x{}", p[0], p[1]) }
        }
        fn float(v: f64) -> String {
            let s = format!("{v:?}");
            if s.contains('e') || s.contains('.') { s } else { format!("{s}.0") }
        }
        fn list<T: fmt::Display>(v: &[T]) -> String {
            let mut s = String::from("[");
            for (i, x) in v.iter().enumerate() {
                if i > 0 {
                    s.push_str(", ");
                }
                let _ = write!(s, "{x}");
            }
            s.push(']');
            s
        }
        match self {
            Op::Input(a) => {
                let mut v = vec![("name", a.name.clone())];
                if let Some(m) = &a.modality {
                    v.push(("modality", m.clone()));
                }
                if a.optional {
                    v.push(("optional", "true".into()));
                }
                v
            }
            Op::Conv2d(c) => vec![
                ("in", c.in_channels.to_string()),
                ("out", c.out_channels.to_string()),
                ("kernel", pair(c.kernel)),
                ("stride", pair(c.stride)),
                ("padding", pair(c.padding)),
                ("dilation", pair(c.dilation)),
                ("groups", c.groups.to_string()),
                ("bias", c.bias.to_string()),
            ],
            Op::BatchNorm { channels, eps, momentum } => {
                vec![("channels", channels.to_string()), ("eps", float(*eps)), ("momentum", float(*momentum))]
            }
            Op::LayerNorm { features, eps, affine } => {
                vec![("features", features.to_string()), ("eps", float(*eps)), ("affine", affine.to_string())]
            }
            Op::Linear { in_features, out_features, bias } => {
                vec![("in", in_features.to_string()), ("out", out_features.to_string()), ("bias", bias.to_string())]
            }
            Op::MatMul | Op::Binary(_) | Op::GlobalAvgPool => vec![],
            Op::Scalar { value, scalar_first, .. } => {
                let mut v = vec![("scalar", float(*value))];
                if *scalar_first {
                    v.push(("scalar_first", "true".into()));
                }
                v
            }
            Op::Activation(Activation::GeluTanh) => vec![("approximate", "tanh".into())],
            Op::Activation(_) => vec![],
            Op::Softmax { axis } => vec![("axis", axis.to_string())],
            Op::Concat { axis } => vec![("axis", axis.to_string())],
            Op::Reshape { shape } => vec![("shape", list(shape))],
            Op::Permute { perm } => vec![("perm", list(perm))],
            Op::Pool(p) => {
                let mut v = vec![
                    ("kernel", pair(p.kernel)),
                    ("stride", pair(p.stride)),
                    ("padding", pair(p.padding)),
                    ("ceil_mode", p.ceil_mode.to_string()),
                ];
                if p.kind == PoolKind::Avg {
                    v.push(("count_include_pad", p.count_include_pad.to_string()));
                }
                v
            }
            Op::Upsample { size, scale, mode, align_corners } => vec![
                ("size", format!("{}x{}", size[0], size[1])),
                (
                    "scale",
                    match scale {
                        Some(s) if s[0] == s[1] => float(s[0]),
                        Some(s) => format!("{}x{}", float(s[0]), float(s[1])),
                        None => "none".into(),
                    },
                ),
                (
                    "mode",
                    match mode {
                        UpsampleMode::Nearest => "nearest".into(),
                        UpsampleMode::Bilinear => "bilinear".into(),
                    },
                ),
                ("align_corners", align_corners.to_string()),
            ],
            Op::Mean { axes, keepdim } => vec![("axes", list(axes)), ("keepdim", keepdim.to_string())],
            Op::Parameter { shape } => vec![("shape", list(shape))],
        }
    }
}
