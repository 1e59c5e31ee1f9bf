//! The builtin ops and functions of the language: their signatures, argument checking,
//! and the construction of IR ops from checked arguments.
//!
//! Argument names follow PyTorch where it has one (`stride`, `padding`, `groups`,
//! `ceil_mode`, `align_corners`); `out` is the output channel/feature count.

use readi_grammar::diag::{Code, Diagnostic, Span};

use super::value::Value;
use crate::ir::*;

/// A default value of an op parameter.
#[derive(Clone, Copy, Debug)]
pub(super) enum Def {
    Required,
    Int(i64),
    Float(f64),
    Bool(bool),
    Str(&'static str),
    /// Optional without a value (`stride` of pools defaults to the kernel).
    Absent,
}

/// A parameter of a builtin.
#[derive(Clone, Copy, Debug)]
pub(super) struct P {
    pub name: &'static str,
    pub default: Def,
}

const fn req(name: &'static str) -> P {
    P { name, default: Def::Required }
}
const fn int(name: &'static str, v: i64) -> P {
    P { name, default: Def::Int(v) }
}
const fn flt(name: &'static str, v: f64) -> P {
    P { name, default: Def::Float(v) }
}
const fn boolean(name: &'static str, v: bool) -> P {
    P { name, default: Def::Bool(v) }
}
const fn absent(name: &'static str) -> P {
    P { name, default: Def::Absent }
}

/// Signature of a builtin op or function.
#[derive(Debug)]
pub(super) struct Sig {
    pub name: &'static str,
    pub params: &'static [P],
    pub kind: BuiltinKind,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum BuiltinKind {
    /// Creates a graph node.
    Op,
    /// Computes a value at elaboration time (`dim`, `len`).
    Function,
}

macro_rules! sig {
    ($name:literal, $kind:ident, [$($p:expr),* $(,)?]) => {
        Sig { name: $name, params: &[$($p),*], kind: BuiltinKind::$kind }
    };
}

/// Every builtin, ops first. Adding an op means adding it here, to [`build_op`], to
/// [`crate::infer`], and to `Op`.
pub(super) static BUILTINS: &[Sig] = &[
    sig!(
        "conv2d",
        Op,
        [
            req("x"),
            req("out"),
            req("kernel"),
            int("stride", 1),
            int("padding", 0),
            int("dilation", 1),
            int("groups", 1),
            boolean("bias", true),
        ]
    ),
    sig!("batchnorm", Op, [req("x"), flt("eps", 1e-5), flt("momentum", 0.1)]),
    sig!("layernorm", Op, [req("x"), flt("eps", 1e-5), boolean("affine", true)]),
    sig!("linear", Op, [req("x"), req("out"), boolean("bias", true)]),
    sig!("matmul", Op, [req("a"), req("b")]),
    sig!("add", Op, [req("a"), req("b")]),
    sig!("sub", Op, [req("a"), req("b")]),
    sig!("mul", Op, [req("a"), req("b")]),
    sig!("div", Op, [req("a"), req("b")]),
    sig!("relu", Op, [req("x")]),
    sig!("gelu", Op, [req("x"), P { name: "approximate", default: Def::Str("none") }]),
    sig!("sigmoid", Op, [req("x")]),
    sig!("softmax", Op, [req("x"), int("axis", -1)]),
    sig!("concat", Op, [req("xs"), req("axis")]),
    sig!("reshape", Op, [req("x"), req("shape")]),
    sig!("transpose", Op, [req("x"), req("dim0"), req("dim1")]),
    sig!("permute", Op, [req("x"), req("dims")]),
    sig!("flatten", Op, [req("x"), int("start", 1), int("end", -1)]),
    sig!("maxpool", Op, [req("x"), req("kernel"), absent("stride"), int("padding", 0), boolean("ceil_mode", false),]),
    sig!(
        "avgpool",
        Op,
        [
            req("x"),
            req("kernel"),
            absent("stride"),
            int("padding", 0),
            boolean("ceil_mode", false),
            boolean("count_include_pad", true),
        ]
    ),
    sig!("global_avgpool", Op, [req("x")]),
    sig!(
        "upsample",
        Op,
        [
            req("x"),
            absent("scale"),
            absent("size"),
            P { name: "mode", default: Def::Str("nearest") },
            boolean("align_corners", false),
        ]
    ),
    sig!("mean", Op, [req("x"), req("axes"), boolean("keepdim", false)]),
    sig!("parameter", Op, [req("shape")]),
    sig!("dim", Function, [req("x"), req("axis")]),
    sig!("rank", Function, [req("x")]),
    sig!("len", Function, [req("list")]),
    sig!("min", Function, [req("a"), req("b")]),
    sig!("max", Function, [req("a"), req("b")]),
];

pub(super) fn builtin(name: &str) -> Option<&'static Sig> {
    BUILTINS.iter().find(|s| s.name == name)
}

/// Arguments bound to a builtin's parameters, defaults filled in.
pub(super) struct Args<'g> {
    pub sig: &'static Sig,
    /// One entry per parameter: the value and where it came from (`None`: absent).
    pub values: Vec<Option<(Value, Span)>>,
    pub call_span: Span,
    pub graph: &'g Graph,
}

type R<T> = Result<T, Diagnostic>;

impl Args<'_> {
    fn idx(&self, name: &str) -> usize {
        self.sig.params.iter().position(|p| p.name == name).unwrap_or(usize::MAX)
    }

    fn get(&self, name: &str) -> Option<&(Value, Span)> {
        self.values.get(self.idx(name)).and_then(|v| v.as_ref())
    }

    fn span(&self, name: &str) -> Span {
        self.get(name).map(|(_, s)| *s).unwrap_or(self.call_span)
    }

    fn mismatch(&self, name: &str, expected: &str, found: &Value) -> Diagnostic {
        let ty = match found {
            Value::Tensor { value, .. } => {
                self.graph.value_type(*value).map(|t| format!("a tensor {t}")).unwrap_or_default()
            }
            v => v.kind().to_string(),
        };
        Diagnostic::error(
            Code::TypeMismatch,
            format!("argument `{name}` of `{}` must be {expected}, found {ty}", self.sig.name),
        )
        .with_primary(self.span(name), format!("expected {expected}"))
    }

    fn bad_value(&self, name: &str, message: String) -> Diagnostic {
        Diagnostic::error(Code::BadValue, format!("argument `{name}` of `{}`: {message}", self.sig.name))
            .with_primary(self.span(name), message)
    }

    pub fn present(&self, name: &str) -> bool {
        self.get(name).is_some()
    }

    pub fn value(&self, name: &str) -> Option<&Value> {
        self.get(name).map(|(v, _)| v)
    }

    pub fn tensor(&self, name: &str) -> R<ValueRef> {
        match self.value(name) {
            Some(Value::Tensor { value, .. }) => Ok(*value),
            Some(v) => Err(self.mismatch(name, "a tensor", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    pub fn ttype(&self, name: &str) -> R<&TensorType> {
        let v = self.tensor(name)?;
        self.graph.value_type(v).ok_or_else(|| self.bad_value(name, "has no type".into()))
    }

    pub fn int(&self, name: &str) -> R<i64> {
        match self.value(name) {
            Some(Value::Int(i)) => Ok(*i),
            Some(v) => Err(self.mismatch(name, "an int", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    /// An int at least `min`.
    pub fn int_at_least(&self, name: &str, min: i64) -> R<i64> {
        let v = self.int(name)?;
        if v < min {
            return Err(self.bad_value(name, format!("must be at least {min}, got {v}")));
        }
        Ok(v)
    }

    pub fn float(&self, name: &str) -> R<f64> {
        match self.value(name) {
            Some(Value::Float(f)) => Ok(*f),
            Some(Value::Int(i)) => Ok(*i as f64),
            Some(v) => Err(self.mismatch(name, "a number", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    pub fn boolean(&self, name: &str) -> R<bool> {
        match self.value(name) {
            Some(Value::Bool(b)) => Ok(*b),
            Some(v) => Err(self.mismatch(name, "`true` or `false`", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    pub fn string(&self, name: &str) -> R<String> {
        match self.value(name) {
            Some(Value::Str(s)) => Ok(s.to_string()),
            Some(v) => Err(self.mismatch(name, "a string", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    /// An int or a two-element list of ints, each at least `min`: `3` or `[3, 1]`.
    pub fn pair(&self, name: &str, min: i64) -> R<[i64; 2]> {
        let p = match self.value(name) {
            Some(Value::Int(i)) => [*i, *i],
            Some(Value::List(l)) if l.len() == 2 => match (&l[0], &l[1]) {
                (Value::Int(a), Value::Int(b)) => [*a, *b],
                _ => return Err(self.mismatch(name, "an int or a pair of ints", &Value::List(l.clone()))),
            },
            Some(v) => return Err(self.mismatch(name, "an int or a pair of ints", v)),
            None => return Err(self.bad_value(name, "missing".into())),
        };
        if p[0] < min || p[1] < min {
            return Err(self.bad_value(name, format!("must be at least {min}, got {}", show_pair(p))));
        }
        Ok(p)
    }

    /// An int or a list of ints.
    pub fn int_list(&self, name: &str) -> R<Vec<i64>> {
        match self.value(name) {
            Some(Value::Int(i)) => Ok(vec![*i]),
            Some(Value::List(l)) => l
                .iter()
                .map(|v| match v {
                    Value::Int(i) => Ok(*i),
                    other => Err(self.mismatch(name, "a list of ints", other)),
                })
                .collect(),
            Some(v) => Err(self.mismatch(name, "a list of ints", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    /// An axis index for a tensor of the given rank; negative counts from the end.
    pub fn axis(&self, name: &str, rank: usize) -> R<usize> {
        let a = self.int(name)?;
        self.normalize_axis(name, a, rank)
    }

    fn normalize_axis(&self, name: &str, a: i64, rank: usize) -> R<usize> {
        let r = rank as i64;
        let n = if a < 0 { a + r } else { a };
        if n < 0 || n >= r {
            return Err(self.bad_value(name, format!("axis {a} is out of range for a tensor of rank {rank}")));
        }
        Ok(n as usize)
    }

    pub fn axes(&self, name: &str, rank: usize) -> R<Vec<usize>> {
        let list = self.int_list(name)?;
        list.iter().map(|&a| self.normalize_axis(name, a, rank)).collect()
    }
}

fn show_pair(p: [i64; 2]) -> String {
    if p[0] == p[1] { p[0].to_string() } else { format!("[{}, {}]", p[0], p[1]) }
}

/// Builds the IR op for a builtin op call with bound arguments; returns the op and its
/// tensor inputs in port order.
pub(super) fn build_op(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let name = args.sig.name;
    let x = || args.tensor("x");
    Ok(match name {
        "conv2d" => {
            let t = args.ttype("x")?;
            let in_channels = t.known_dim(1).filter(|_| t.rank() == 4).ok_or_else(|| {
                args.bad_value("x", format!("conv2d needs an NCHW tensor with a known channel count, got {t}"))
            })?;
            let attrs = Conv2dAttrs {
                in_channels,
                out_channels: args.int_at_least("out", 1)?,
                kernel: args.pair("kernel", 1)?,
                stride: args.pair("stride", 1)?,
                padding: args.pair("padding", 0)?,
                dilation: args.pair("dilation", 1)?,
                groups: args.int_at_least("groups", 1)?,
                bias: args.boolean("bias")?,
            };
            if in_channels % attrs.groups != 0 || attrs.out_channels % attrs.groups != 0 {
                return Err(args.bad_value(
                    "groups",
                    format!(
                        "groups={} must divide both the {in_channels} input and {} output channels",
                        attrs.groups, attrs.out_channels
                    ),
                ));
            }
            (Op::Conv2d(attrs), vec![x()?])
        }
        "batchnorm" => {
            let t = args.ttype("x")?;
            let channels = t.known_dim(1).filter(|_| t.rank() >= 2).ok_or_else(|| {
                args.bad_value("x", format!("batchnorm needs a tensor with a known axis 1 (channels), got {t}"))
            })?;
            let eps = positive_float(args, "eps")?;
            let momentum = args.float("momentum")?;
            if !(0.0..=1.0).contains(&momentum) {
                return Err(args.bad_value("momentum", format!("must be in [0, 1], got {momentum}")));
            }
            (Op::BatchNorm { channels, eps, momentum }, vec![x()?])
        }
        "layernorm" => {
            let t = args.ttype("x")?;
            let features = t
                .rank()
                .checked_sub(1)
                .and_then(|l| t.known_dim(l))
                .ok_or_else(|| args.bad_value("x", format!("layernorm needs a known last axis, got {t}")))?;
            let eps = positive_float(args, "eps")?;
            (Op::LayerNorm { features, eps, affine: args.boolean("affine")? }, vec![x()?])
        }
        "linear" => {
            let t = args.ttype("x")?;
            let in_features = t
                .rank()
                .checked_sub(1)
                .and_then(|l| t.known_dim(l))
                .ok_or_else(|| args.bad_value("x", format!("linear needs a known last axis, got {t}")))?;
            let out_features = args.int_at_least("out", 1)?;
            (Op::Linear { in_features, out_features, bias: args.boolean("bias")? }, vec![x()?])
        }
        "matmul" => (Op::MatMul, vec![args.tensor("a")?, args.tensor("b")?]),
        "add" | "sub" | "mul" | "div" => {
            // Function forms of the operators; scalars go through the operator path.
            let kind = match name {
                "add" => BinaryKind::Add,
                "sub" => BinaryKind::Sub,
                "mul" => BinaryKind::Mul,
                _ => BinaryKind::Div,
            };
            (Op::Binary(kind), vec![args.tensor("a")?, args.tensor("b")?])
        }
        "relu" => (Op::Activation(Activation::Relu), vec![x()?]),
        "sigmoid" => (Op::Activation(Activation::Sigmoid), vec![x()?]),
        "gelu" => {
            let act = match args.string("approximate")?.as_str() {
                "none" => Activation::Gelu,
                "tanh" => Activation::GeluTanh,
                other => {
                    return Err(args.bad_value("approximate", format!("must be \"none\" or \"tanh\", got \"{other}\"")));
                }
            };
            (Op::Activation(act), vec![x()?])
        }
        "softmax" => {
            let rank = args.ttype("x")?.rank();
            (Op::Softmax { axis: args.axis("axis", rank)? }, vec![x()?])
        }
        "concat" => {
            let list = match args.value("xs") {
                Some(Value::List(l)) if !l.is_empty() => l.clone(),
                Some(v) => return Err(args.mismatch("xs", "a non-empty list of tensors", v)),
                None => return Err(args.bad_value("xs", "missing".into())),
            };
            let mut inputs = Vec::new();
            for v in list.iter() {
                match v {
                    Value::Tensor { value, .. } => inputs.push(*value),
                    other => return Err(args.mismatch("xs", "a list of tensors", other)),
                }
            }
            let rank = args.graph.value_type(inputs[0]).map(|t| t.rank()).unwrap_or(0);
            (Op::Concat { axis: args.axis("axis", rank)? }, inputs)
        }
        "reshape" => {
            let t = args.ttype("x")?;
            (Op::Reshape { shape: reshape_target(args, t)? }, vec![x()?])
        }
        "transpose" => {
            let rank = args.ttype("x")?.rank();
            let (a, b) = (args.axis("dim0", rank)?, args.axis("dim1", rank)?);
            let mut perm: Vec<usize> = (0..rank).collect();
            perm.swap(a, b);
            (Op::Permute { perm }, vec![x()?])
        }
        "permute" => {
            let rank = args.ttype("x")?.rank();
            let perm = args.axes("dims", rank)?;
            let mut seen = vec![false; rank];
            for &p in &perm {
                seen[p] = true;
            }
            if perm.len() != rank || seen.iter().any(|s| !s) {
                return Err(args.bad_value("dims", format!("must list each of the {rank} axes once")));
            }
            (Op::Permute { perm }, vec![x()?])
        }
        "flatten" => {
            let t = args.ttype("x")?;
            let rank = t.rank();
            let (s, e) = (args.axis("start", rank)?, args.axis("end", rank)?);
            if s > e {
                return Err(args.bad_value("end", format!("flatten end axis {e} is before start axis {s}")));
            }
            let merged = Dim::product(&t.shape[s..=e]).ok_or_else(|| args.bad_value("x", "size overflows".into()))?;
            let mut shape: Vec<Dim> = t.shape[..s].to_vec();
            shape.push(merged);
            shape.extend_from_slice(&t.shape[e + 1..]);
            (Op::Reshape { shape }, vec![x()?])
        }
        "maxpool" | "avgpool" => {
            let kernel = args.pair("kernel", 1)?;
            let stride = if args.present("stride") { args.pair("stride", 1)? } else { kernel };
            let attrs = PoolAttrs {
                kind: if name == "maxpool" { PoolKind::Max } else { PoolKind::Avg },
                kernel,
                stride,
                padding: args.pair("padding", 0)?,
                ceil_mode: args.boolean("ceil_mode")?,
                count_include_pad: if name == "avgpool" { args.boolean("count_include_pad")? } else { true },
            };
            (Op::Pool(attrs), vec![x()?])
        }
        "global_avgpool" => (Op::GlobalAvgPool, vec![x()?]),
        "upsample" => {
            let t = args.ttype("x")?;
            let mut factor = None;
            let size = match (args.present("scale"), args.present("size")) {
                (true, false) => {
                    let scale = positive_float(args, "scale")?;
                    let mut out = [0i64; 2];
                    for (i, o) in out.iter_mut().enumerate() {
                        let len = t.known_dim(2 + i).filter(|_| t.rank() == 4).ok_or_else(|| {
                            args.bad_value(
                                "x",
                                format!("upsample needs an NCHW tensor with known spatial sizes, got {t}"),
                            )
                        })?;
                        // PyTorch: floor(len * scale).
                        let v = (len as f64 * scale).floor();
                        if !(1.0..=1e9).contains(&v) {
                            return Err(args.bad_value("scale", format!("gives an output size of {v}")));
                        }
                        *o = v as i64;
                    }
                    factor = Some([scale, scale]);
                    out
                }
                (false, true) => args.pair("size", 1)?,
                _ => {
                    return Err(Diagnostic::error(
                        Code::BadArgument,
                        "upsample takes exactly one of `scale` and `size`",
                    )
                    .with_primary(args.call_span, "give `scale=2` or `size=[h, w]`"));
                }
            };
            let mode = match args.string("mode")?.as_str() {
                "nearest" => UpsampleMode::Nearest,
                "bilinear" => UpsampleMode::Bilinear,
                other => {
                    return Err(args.bad_value("mode", format!("must be \"nearest\" or \"bilinear\", got \"{other}\"")));
                }
            };
            let align_corners = args.boolean("align_corners")?;
            if align_corners && mode == UpsampleMode::Nearest {
                return Err(args.bad_value("align_corners", "applies to bilinear mode only".into()));
            }
            (Op::Upsample { size, scale: factor, mode, align_corners }, vec![x()?])
        }
        "mean" => {
            let rank = args.ttype("x")?.rank();
            let mut axes = args.axes("axes", rank)?;
            axes.sort_unstable();
            if axes.windows(2).any(|w| w[0] == w[1]) {
                return Err(args.bad_value("axes", "lists an axis twice".into()));
            }
            (Op::Mean { axes, keepdim: args.boolean("keepdim")? }, vec![x()?])
        }
        "parameter" => {
            let shape = args.int_list("shape")?;
            if shape.is_empty() || shape.iter().any(|&d| d < 1) {
                return Err(
                    args.bad_value("shape", format!("must be a non-empty list of sizes of at least 1, got {shape:?}"))
                );
            }
            let numel = shape.iter().try_fold(1i64, |a, &d| a.checked_mul(d));
            if numel.is_none_or(|n| n > 1 << 40) {
                return Err(args.bad_value("shape", "is too large".into()));
            }
            (Op::Parameter { shape }, vec![])
        }
        other => {
            return Err(Diagnostic::error(Code::UnknownName, format!("`{other}` is not an op"))
                .with_primary(args.call_span, "not an op"));
        }
    })
}

fn positive_float(args: &Args<'_>, name: &str) -> R<f64> {
    let v = args.float(name)?;
    if v <= 0.0 || !v.is_finite() {
        return Err(args.bad_value(name, format!("must be a positive number, got {v}")));
    }
    Ok(v)
}

/// The target shape of `reshape`: ints, symbolic dimensions, and at most one `-1`.
fn reshape_target(args: &Args<'_>, t: &TensorType) -> R<Vec<Dim>> {
    let list = match args.value("shape") {
        Some(Value::List(l)) => l.clone(),
        Some(v) => return Err(args.mismatch("shape", "a list of sizes", v)),
        None => return Err(args.bad_value("shape", "missing".into())),
    };
    let mut dims: Vec<Option<Dim>> = Vec::new();
    for v in list.iter() {
        match v {
            Value::Int(-1) => dims.push(None),
            Value::Int(i) if *i >= 1 => dims.push(Some(Dim::known(*i))),
            Value::Int(i) => {
                return Err(args.bad_value("shape", format!("size {i} is not allowed (use -1 to infer one size)")));
            }
            Value::Dim(d) => dims.push(Some(d.clone())),
            other => return Err(args.mismatch("shape", "a list of sizes", other)),
        }
    }
    let unknown = dims.iter().filter(|d| d.is_none()).count();
    if unknown > 1 {
        return Err(args.bad_value("shape", "at most one size can be -1".into()));
    }
    if unknown == 0 {
        return Ok(dims.into_iter().flatten().collect());
    }
    let total = Dim::product(&t.shape).ok_or_else(|| args.bad_value("x", "size overflows".into()))?;
    let known: Vec<Dim> = dims.iter().flatten().cloned().collect();
    let rest = Dim::product(&known).ok_or_else(|| args.bad_value("shape", "size overflows".into()))?;
    let inferred = total.checked_div(&rest).ok_or_else(|| {
        args.bad_value("shape", format!("cannot infer -1: {total} elements are not divisible by {rest}"))
    })?;
    Ok(dims.into_iter().map(|d| d.unwrap_or_else(|| inferred.clone())).collect())
}
