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
    /// `torch.maximum` / `torch.minimum`: the larger (smaller) of the two, NaN if either
    /// is NaN.
    Maximum,
    Minimum,
    /// `torch.floor_divide` (`a // b`): the quotient rounded towards negative infinity,
    /// computed as PyTorch's CPU kernel does for floats (from `fmod`, so exact on
    /// integers below 2^24); a zero divisor gives IEEE's `a / b`.
    FloorDiv,
    /// `torch.remainder` (`a % b`): `a - b * floor(a / b)`, with the divisor's sign, from
    /// `fmod` as PyTorch computes it; NaN for a zero divisor.
    Remainder,
    /// `torch.atan2(input, other)`: the angle of the point `(other, input)`.
    Atan2,
}

impl BinaryOp {
    /// Whether the operation is a comparison (its result is bool; it takes any types).
    pub fn is_comparison(self) -> bool {
        matches!(self, BinaryOp::Eq | BinaryOp::Ne | BinaryOp::Lt | BinaryOp::Le | BinaryOp::Gt | BinaryOp::Ge)
    }

    /// The operations with a builtin `name(a, b)` (`pow` has its own, `pow(x, exponent)`;
    /// the ones after `div` theirs, with PyTorch's `input` and `other`).
    pub const ALL: [BinaryOp; 4] = [BinaryOp::Add, BinaryOp::Sub, BinaryOp::Mul, BinaryOp::Div];

    /// The operations with a builtin `name(input, other)` (a number for either).
    pub const INPUT_OTHER: [BinaryOp; 5] =
        [BinaryOp::Maximum, BinaryOp::Minimum, BinaryOp::FloorDiv, BinaryOp::Remainder, BinaryOp::Atan2];

    /// Whether the operation takes integer tensors too (`maximum`, `minimum`,
    /// `floor_divide`, `remainder`), an integer result from integers.
    pub fn takes_integers(self) -> bool {
        matches!(self, BinaryOp::Maximum | BinaryOp::Minimum | BinaryOp::FloorDiv | BinaryOp::Remainder)
    }

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
            BinaryOp::Maximum => "maximum",
            BinaryOp::Minimum => "minimum",
            BinaryOp::FloorDiv => "floor_divide",
            BinaryOp::Remainder => "remainder",
            BinaryOp::Atan2 => "atan2",
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
            BinaryOp::Maximum => maximum(a, b),
            BinaryOp::Minimum => minimum(a, b),
            BinaryOp::FloorDiv => floor_divide(a, b),
            BinaryOp::Remainder => remainder(a, b),
            BinaryOp::Atan2 => a.atan2(b),
        }
    }
}

/// `torch.maximum` of two values: NaN if either is.
#[inline(always)]
pub fn maximum(a: f32, b: f32) -> f32 {
    if a.is_nan() || a > b { a } else { b }
}

/// `torch.minimum` of two values: NaN if either is.
#[inline(always)]
pub fn minimum(a: f32, b: f32) -> f32 {
    if a.is_nan() || a < b { a } else { b }
}

/// `torch.floor_divide` of two floats, PyTorch's `div_floor_floating`: the exact
/// quotient of `a - fmod(a, b)` by `b`, one less when the remainder's sign differs from
/// the divisor's, rounded to the nearest integer (the division may leave it a hair off).
#[inline(always)]
pub fn floor_divide(a: f32, b: f32) -> f32 {
    if b == 0.0 {
        return a / b;
    }
    let m = a % b;
    let mut div = (a - m) / b;
    if m != 0.0 && (b < 0.0) != (m < 0.0) {
        div -= 1.0;
    }
    if div != 0.0 {
        let f = div.floor();
        if div - f > 0.5 { f + 1.0 } else { f }
    } else {
        0.0f32.copysign(a / b)
    }
}

/// `torch.remainder` of two floats: `fmod(a, b)`, plus `b` when its sign differs from the
/// divisor's.
#[inline(always)]
pub fn remainder(a: f32, b: f32) -> f32 {
    let m = a % b;
    if m != 0.0 && (b < 0.0) != (m < 0.0) { m + b } else { m }
}

impl Operator for BinaryOp {
    fn kind_name(&self) -> &'static str {
        self.name()
    }

    fn arity(&self) -> Option<usize> {
        Some(2)
    }

    fn any_dtype(&self) -> bool {
        self.is_comparison() || self.takes_integers()
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
        if !inputs[0].dtype.is_float() && self.value.fract() != 0.0 {
            // An integer tensor with a fractional number: a float result, as torch.
            return Ok(TensorType::f32(inputs[0].shape.clone()));
        }
        Ok(inputs[0].clone())
    }

    fn any_dtype(&self) -> bool {
        self.op.is_comparison() || self.op.takes_integers()
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
    fn floor_division_and_remainder_follow_python() {
        // Hand-computed with Python's `//` and `%`: the quotient rounds down, the
        // remainder takes the divisor's sign.
        let cases = [
            (7.0, 2.0, 3.0, 1.0),
            (-7.0, 2.0, -4.0, 1.0),
            (7.0, -2.0, -4.0, -1.0),
            (-7.0, -2.0, 3.0, -1.0),
            (191.0, 64.0, 2.0, 63.0),
            (128.0, 64.0, 2.0, 0.0),
            (5.5, 2.0, 2.0, 1.5),
            (-0.5, 2.0, -1.0, 1.5),
        ];
        for (a, b, q, r) in cases {
            assert_eq!((floor_divide(a, b), remainder(a, b)), (q, r), "{a} // {b}, {a} % {b}");
        }
        assert_eq!(floor_divide(1.0, 0.0), f32::INFINITY);
        assert!(remainder(1.0, 0.0).is_nan());
        // Every integer quotient below 2^24 is exact (a // b times b plus a % b is a).
        for a in [0.0f32, 1.0, 16_777_215.0, 12_345_677.0, 65_535.0] {
            for b in [1.0f32, 3.0, 64.0, 4095.0, -7.0] {
                let (q, r) = (floor_divide(a, b), remainder(a, b));
                assert_eq!(f64::from(q) * f64::from(b) + f64::from(r), f64::from(a), "{a} // {b}");
            }
        }
    }

    #[test]
    fn maximum_and_minimum_propagate_nan() {
        assert_eq!((maximum(1.0, 2.0), minimum(1.0, 2.0)), (2.0, 1.0));
        for (a, b) in [(f32::NAN, 1.0), (1.0, f32::NAN)] {
            assert!(maximum(a, b).is_nan() && minimum(a, b).is_nan(), "{a} {b}");
        }
    }

    #[test]
    fn integer_operations_keep_their_type() {
        let i = |s: &[i64]| TensorType::new(DType::I64, s.iter().map(|&d| Dim::known(d)).collect());
        let y = run(&BinaryOp::FloorDiv, &[i(&[1, 6]), i(&[1])]).expect("valid");
        assert_eq!(y, i(&[1, 6]));
        assert!(run(&BinaryOp::Atan2, &[i(&[2]), i(&[2])]).is_err(), "atan2 of integers");
        assert!(run(&BinaryOp::Maximum, &[i(&[2]), t(&[2])]).is_err(), "an i64 and an f32");
        let s = |value| Scalar { op: BinaryOp::Remainder, value, scalar_first: false };
        assert_eq!(run(&s(64.0), &[i(&[6])]).expect("valid"), i(&[6]));
        assert_eq!(run(&s(2.5), &[i(&[6])]).expect("valid"), t(&[6]), "a fractional divisor makes floats");
    }

    #[test]
    fn a_constant_must_be_finite() {
        let s = Scalar { op: BinaryOp::Mul, value: f64::INFINITY, scalar_first: false };
        assert!(run(&s, &[t(&[2])]).is_err());
    }
}
