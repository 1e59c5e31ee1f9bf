//! Element-wise operators: binary ops with NumPy broadcasting, ops with a constant, and
//! activations.
//!
//! Adding an activation: a variant of [`Activation`] with its name and its formula in
//! [`Activation::reference`], then its kernel in `runtime/src/kernels/elementwise.rs`.
//! The language gets it as a builtin `name(x)` from [`Activation::ALL`]; nothing else
//! needs to know (see `docs/contributing.md`).

use serde::{Deserialize, Serialize};

use super::{DType, Operator, ShapeError, ShapeResult, TensorType, float};
use crate::dim::Dim;

/// Element-wise binary operations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum BinaryOp {
    Add,
    Sub,
    Mul,
    Div,
    /// `a ** b`, C's `powf` (PyTorch's `pow`; with a constant exponent 2, 3, 0.5, -0.5, -1
    /// or -2 it is the product, root or reciprocal, as in PyTorch's kernel).
    Pow,
    /// Comparisons (`==`, `!=`, `<`, `<=`, `>`, `>=`): a bool tensor, 1 where true and 0
    /// where false as values.
    Eq,
    Ne,
    Lt,
    Le,
    Gt,
    Ge,
}

impl BinaryOp {
    /// Whether the operation is a comparison (its result is bool; it takes any types).
    pub fn is_comparison(self) -> bool {
        matches!(self, BinaryOp::Eq | BinaryOp::Ne | BinaryOp::Lt | BinaryOp::Le | BinaryOp::Gt | BinaryOp::Ge)
    }

    /// The operations with a builtin `name(a, b)` (`pow` has its own, `pow(x, exponent)`).
    pub const ALL: [BinaryOp; 4] = [BinaryOp::Add, BinaryOp::Sub, BinaryOp::Mul, BinaryOp::Div];

    pub fn name(self) -> &'static str {
        match self {
            BinaryOp::Add => "add",
            BinaryOp::Sub => "sub",
            BinaryOp::Mul => "mul",
            BinaryOp::Div => "div",
            BinaryOp::Pow => "pow",
            BinaryOp::Eq => "eq",
            BinaryOp::Ne => "ne",
            BinaryOp::Lt => "lt",
            BinaryOp::Le => "le",
            BinaryOp::Gt => "gt",
            BinaryOp::Ge => "ge",
        }
    }

    /// The operation on one pair of values.
    #[inline(always)]
    pub fn apply(self, a: f32, b: f32) -> f32 {
        match self {
            BinaryOp::Add => a + b,
            BinaryOp::Sub => a - b,
            BinaryOp::Mul => a * b,
            BinaryOp::Div => a / b,
            BinaryOp::Pow => a.powf(b),
            BinaryOp::Eq => (a == b) as u8 as f32,
            BinaryOp::Ne => (a != b) as u8 as f32,
            BinaryOp::Lt => (a < b) as u8 as f32,
            BinaryOp::Le => (a <= b) as u8 as f32,
            BinaryOp::Gt => (a > b) as u8 as f32,
            BinaryOp::Ge => (a >= b) as u8 as f32,
        }
    }
}

impl Operator for BinaryOp {
    fn kind_name(&self) -> &'static str {
        self.name()
    }

    fn arity(&self) -> Option<usize> {
        Some(2)
    }

    fn any_dtype(&self) -> bool {
        self.is_comparison()
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (a, b) = (inputs[0], inputs[1]);
        if self.is_comparison() {
            let shape = broadcast(&a.shape, &b.shape)
                .map_err(|e| ShapeError::new(format!("cannot broadcast {a} with {b}")).note(e))?;
            return Ok(TensorType::new(DType::Bool, shape));
        }
        if a.dtype != b.dtype {
            return Err(ShapeError::new(format!("{} of different element types: {a} and {b}", self.name())));
        }
        let shape = broadcast(&a.shape, &b.shape)
            .map_err(|e| ShapeError::new(format!("cannot broadcast {a} with {b}")).note(e))?;
        Ok(TensorType::new(a.dtype, shape))
    }
}

/// NumPy broadcasting of two shapes.
pub fn broadcast(a: &[Dim], b: &[Dim]) -> Result<Vec<Dim>, String> {
    let n = a.len().max(b.len());
    let one = Dim::known(1);
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let da = if i + a.len() >= n { &a[i + a.len() - n] } else { &one };
        let db = if i + b.len() >= n { &b[i + b.len() - n] } else { &one };
        let d = if da == db || *db == one {
            da.clone()
        } else if *da == one {
            db.clone()
        } else {
            return Err(format!("axis {i} (from the right: {}) has sizes {da} and {db}", n - i));
        };
        out.push(d);
    }
    Ok(out)
}

/// An element-wise op with a constant: `x * 0.125`, or `1 - x` when `scalar_first`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scalar {
    pub op: BinaryOp,
    pub value: f64,
    pub scalar_first: bool,
}

impl Operator for Scalar {
    fn kind_name(&self) -> &'static str {
        self.op.name()
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        if !self.value.is_finite() {
            return Err(ShapeError::new(format!(
                "{} with the constant {}: constants must be finite",
                self.op.name(),
                self.value
            )));
        }
        if self.op.is_comparison() {
            return Ok(TensorType::new(DType::Bool, inputs[0].shape.clone()));
        }
        Ok(inputs[0].clone())
    }

    fn any_dtype(&self) -> bool {
        self.op.is_comparison()
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = vec![("scalar", float(self.value))];
        if self.scalar_first {
            v.push(("scalar_first", "true".into()));
        }
        v
    }
}

/// Element-wise activations and unary functions, each with PyTorch's semantics (NaN in,
/// NaN out; `log` of a negative number is NaN, of 0 is `-inf`).
///
/// The ones with options (`Clamp`, `LeakyRelu`, `Elu`) hold them as f32, the precision
/// PyTorch applies them in to an f32 tensor.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Activation {
    /// `max(x, 0)`.
    Relu,
    /// GELU with the exact erf formulation, PyTorch's default.
    Gelu,
    /// GELU with the tanh approximation (`approximate="tanh"`).
    GeluTanh,
    /// `1 / (1 + exp(-x))`.
    Sigmoid,
    /// The hyperbolic tangent.
    Tanh,
    /// `x * sigmoid(x)` (PyTorch's `SiLU`, also called swish).
    Silu,
    /// `min(max(x, 0), 6)`.
    Relu6,
    /// `min(max(x, min), max)`, either bound optional (PyTorch's `clamp`; `hardtanh` is
    /// both bounds, -1 and 1 by default). With `min > max` every value is `max`, as in
    /// PyTorch.
    Clamp { min: Option<f32>, max: Option<f32> },
    /// `x * relu6(x + 3) / 6`.
    Hardswish,
    /// `relu6(x + 3) / 6`.
    Hardsigmoid,
    /// `x` for `x > 0`, else `negative_slope * x`.
    LeakyRelu { negative_slope: f32 },
    /// `x` for `x > 0`, else `alpha * (exp(x) - 1)`.
    Elu { alpha: f32 },
    /// `e^x`.
    Exp,
    /// The natural logarithm.
    Log,
    /// `√x`.
    Sqrt,
    /// `1 / √x`.
    Rsqrt,
    /// `|x|`.
    Abs,
    /// `-x`.
    Neg,
    /// The error function.
    Erf,
}

impl Activation {
    /// Every activation, those with options at PyTorch's defaults (`Clamp` as
    /// `hardtanh`'s -1 and 1).
    pub const ALL: [Activation; 19] = [
        Activation::Relu,
        Activation::Gelu,
        Activation::GeluTanh,
        Activation::Sigmoid,
        Activation::Tanh,
        Activation::Silu,
        Activation::Relu6,
        Activation::Clamp { min: Some(-1.0), max: Some(1.0) },
        Activation::Hardswish,
        Activation::Hardsigmoid,
        Activation::LeakyRelu { negative_slope: 0.01 },
        Activation::Elu { alpha: 1.0 },
        Activation::Exp,
        Activation::Log,
        Activation::Sqrt,
        Activation::Rsqrt,
        Activation::Abs,
        Activation::Neg,
        Activation::Erf,
    ];

    /// The name in the language (both GELUs are `gelu`; `approximate` tells them apart).
    pub fn name(self) -> &'static str {
        match self {
            Activation::Relu => "relu",
            Activation::Gelu | Activation::GeluTanh => "gelu",
            Activation::Sigmoid => "sigmoid",
            Activation::Tanh => "tanh",
            Activation::Silu => "silu",
            Activation::Relu6 => "relu6",
            Activation::Clamp { .. } => "clamp",
            Activation::Hardswish => "hardswish",
            Activation::Hardsigmoid => "hardsigmoid",
            Activation::LeakyRelu { .. } => "leaky_relu",
            Activation::Elu { .. } => "elu",
            Activation::Exp => "exp",
            Activation::Log => "log",
            Activation::Sqrt => "sqrt",
            Activation::Rsqrt => "rsqrt",
            Activation::Abs => "abs",
            Activation::Neg => "neg",
            Activation::Erf => "erf",
        }
    }

    /// The activation for printouts: its name, and its options in parentheses
    /// (`leaky_relu(negative_slope=0.1)`).
    pub fn label(self) -> String {
        let attrs = self.attrs();
        if attrs.is_empty() {
            return self.name().to_string();
        }
        let a: Vec<String> = attrs.iter().map(|(k, v)| format!("{k}={v}")).collect();
        format!("{}({})", self.name(), a.join(", "))
    }

    /// Whether the language writes it with options (`gelu(x, approximate=)`,
    /// `clamp(x, min=, max=)`, ...) rather than as `name(x)` alone.
    pub fn has_options(self) -> bool {
        matches!(
            self,
            Activation::Gelu
                | Activation::GeluTanh
                | Activation::Clamp { .. }
                | Activation::LeakyRelu { .. }
                | Activation::Elu { .. }
        )
    }

    /// Its options are usable: a clamp has a bound, none is NaN, a slope or alpha is finite.
    pub fn check_options(self) -> Result<(), String> {
        let bad = |what: &str, v: f32| Err(format!("{} with {what} {v}: must be a number", self.name()));
        match self {
            Activation::Clamp { min: None, max: None } => {
                Err("clamp without `min` or `max`: give at least one".to_string())
            }
            Activation::Clamp { min: Some(v), .. } if v.is_nan() => bad("min", v),
            Activation::Clamp { max: Some(v), .. } if v.is_nan() => bad("max", v),
            Activation::LeakyRelu { negative_slope: v } if !v.is_finite() => bad("negative_slope", v),
            Activation::Elu { alpha: v } if !v.is_finite() => bad("alpha", v),
            _ => Ok(()),
        }
    }

    /// The activation's formula, evaluated in f64 with libm: what the runtime's vectorised
    /// kernels are tested against.
    pub fn reference(self, x: f64) -> f64 {
        // `f64::clamp` keeps NaN.
        let relu6 = |v: f64| v.clamp(0.0, 6.0);
        match self {
            Activation::Relu => x.max(0.0),
            Activation::Gelu => 0.5 * x * (1.0 + libm::erf(x / std::f64::consts::SQRT_2)),
            Activation::GeluTanh => {
                let c = (2.0 / std::f64::consts::PI).sqrt();
                0.5 * x * (1.0 + (c * (x + 0.044715 * x * x * x)).tanh())
            }
            Activation::Sigmoid => 1.0 / (1.0 + (-x).exp()),
            Activation::Tanh => x.tanh(),
            Activation::Silu => x / (1.0 + (-x).exp()),
            Activation::Relu6 => relu6(x),
            Activation::Clamp { min, max } => {
                let lo = min.map_or(f64::NEG_INFINITY, f64::from);
                let hi = max.map_or(f64::INFINITY, f64::from);
                let y = if x < lo { lo } else { x };
                if y > hi { hi } else { y }
            }
            Activation::Hardswish => x * relu6(x + 3.0) / 6.0,
            Activation::Hardsigmoid => relu6(x + 3.0) / 6.0,
            Activation::LeakyRelu { negative_slope } => {
                if x > 0.0 {
                    x
                } else {
                    x * f64::from(negative_slope)
                }
            }
            Activation::Elu { alpha } => {
                if x > 0.0 {
                    x
                } else {
                    f64::from(alpha) * x.exp_m1()
                }
            }
            Activation::Exp => x.exp(),
            Activation::Log => x.ln(),
            Activation::Sqrt => x.sqrt(),
            Activation::Rsqrt => 1.0 / x.sqrt(),
            Activation::Abs => x.abs(),
            Activation::Neg => -x,
            Activation::Erf => libm::erf(x),
        }
    }
}

impl Operator for Activation {
    fn kind_name(&self) -> &'static str {
        self.name()
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        self.check_options().map_err(ShapeError::new)?;
        Ok(inputs[0].clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let f = |v: f32| float(f64::from(v));
        match *self {
            Activation::GeluTanh => vec![("approximate", "tanh".into())],
            Activation::Clamp { min, max } => {
                min.map(|v| ("min", f(v))).into_iter().chain(max.map(|v| ("max", f(v)))).collect()
            }
            Activation::LeakyRelu { negative_slope } => vec![("negative_slope", f(negative_slope))],
            Activation::Elu { alpha } => vec![("alpha", f(alpha))],
            _ => Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    #[test]
    fn broadcasting_follows_numpy() {
        assert_eq!(broadcast(&t(&[4, 1, 3]).shape, &t(&[5, 1]).shape), Ok(t(&[4, 5, 3]).shape));
        assert!(broadcast(&t(&[4, 2]).shape, &t(&[3]).shape).is_err());
        let n = Dim::symbol("N");
        let a = vec![n.clone(), Dim::known(3)];
        assert_eq!(broadcast(&a, &[Dim::known(1), Dim::known(3)]), Ok(a.clone()));
        let e = run(&BinaryOp::Add, &[t(&[2, 3]), t(&[3, 2])]).expect_err("an error");
        assert!(e.message.contains("cannot broadcast f32[2, 3] with f32[3, 2]"), "{e:?}");
    }

    #[test]
    fn reference_formulas_at_hand_computed_points() {
        // tanh(1) = 0.761594..., silu(1) = 1 / (1 + e^-1) = 0.731058..., gelu(1) =
        // 0.5 (1 + erf(1 / sqrt 2)) = 0.841344...
        let close = |a: f64, b: f64| (a - b).abs() < 1e-6;
        assert!(close(Activation::Tanh.reference(1.0), 0.761_594_2));
        assert!(close(Activation::Silu.reference(1.0), 0.731_058_6));
        assert!(close(Activation::Silu.reference(-2.0), -2.0 * 0.119_202_9));
        assert!(close(Activation::Gelu.reference(1.0), 0.841_344_7));
        assert!(close(Activation::Sigmoid.reference(0.0), 0.5));
        assert_eq!(Activation::Relu.reference(-3.0), 0.0);
        // hardswish(-3) = 0, hardswish(3) = 3, hardswish(1) = 1 * 4 / 6; hardsigmoid(0) = 1/2;
        // elu(-1) = e^-1 - 1 = -0.632120...; clamp's bounds; log(-1) is NaN.
        assert_eq!(Activation::Hardswish.reference(-3.0), 0.0);
        assert_eq!(Activation::Hardswish.reference(3.0), 3.0);
        assert!(close(Activation::Hardswish.reference(1.0), 4.0 / 6.0));
        assert_eq!(Activation::Hardsigmoid.reference(0.0), 0.5);
        assert!(close(Activation::Elu { alpha: 1.0 }.reference(-1.0), -0.632_120_56));
        assert_eq!(Activation::Relu6.reference(7.0), 6.0);
        let c = Activation::Clamp { min: Some(-0.5), max: None };
        assert_eq!((c.reference(-2.0), c.reference(9.0)), (-0.5, 9.0));
        assert!(Activation::Log.reference(-1.0).is_nan());
        assert!(close(Activation::Erf.reference(1.0), 0.842_700_8));
    }

    #[test]
    fn activation_options_are_checked_and_printed() {
        let clamp = Activation::Clamp { min: None, max: None };
        assert!(run(&clamp, &[t(&[2])]).expect_err("no bounds").message.contains("at least one"));
        assert!(run(&Activation::Clamp { min: Some(f32::NAN), max: None }, &[t(&[2])]).is_err());
        assert!(run(&Activation::Elu { alpha: f32::INFINITY }, &[t(&[2])]).is_err());
        let c = Activation::Clamp { min: Some(0.0), max: Some(6.5) };
        assert_eq!(c.attrs(), vec![("min", "0.0".to_string()), ("max", "6.5".to_string())]);
        assert_eq!(Activation::LeakyRelu { negative_slope: 0.2 }.attrs()[0].0, "negative_slope");
    }

    #[test]
    fn a_constant_must_be_finite() {
        let s = Scalar { op: BinaryOp::Mul, value: f64::INFINITY, scalar_first: false };
        assert!(run(&s, &[t(&[2])]).is_err());
    }
}
