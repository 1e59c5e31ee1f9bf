//! Element-wise operators: binary ops with NumPy broadcasting, ops with a constant, and
//! activations.
//!
//! Adding an activation: a variant of [`Activation`] with its name and its formula in
//! [`Activation::reference`], then its kernel in `runtime/src/kernels/elementwise.rs`.
//! The language gets it as a builtin `name(x)` from [`Activation::ALL`]; nothing else
//! needs to know (see `docs/contributing.md`).

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, float};
use crate::dim::Dim;

/// Element-wise binary operations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum BinaryOp {
    Add,
    Sub,
    Mul,
    Div,
}

impl BinaryOp {
    pub const ALL: [BinaryOp; 4] = [BinaryOp::Add, BinaryOp::Sub, BinaryOp::Mul, BinaryOp::Div];

    pub fn name(self) -> &'static str {
        match self {
            BinaryOp::Add => "add",
            BinaryOp::Sub => "sub",
            BinaryOp::Mul => "mul",
            BinaryOp::Div => "div",
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

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (a, b) = (inputs[0], inputs[1]);
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
        Ok(inputs[0].clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = vec![("scalar", float(self.value))];
        if self.scalar_first {
            v.push(("scalar_first", "true".into()));
        }
        v
    }
}

/// Element-wise activations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
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
}

impl Activation {
    /// Every activation.
    pub const ALL: [Activation; 6] = [
        Activation::Relu,
        Activation::Gelu,
        Activation::GeluTanh,
        Activation::Sigmoid,
        Activation::Tanh,
        Activation::Silu,
    ];

    /// The name in the language (both GELUs are `gelu`; `approximate` tells them apart).
    pub fn name(self) -> &'static str {
        match self {
            Activation::Relu => "relu",
            Activation::Gelu | Activation::GeluTanh => "gelu",
            Activation::Sigmoid => "sigmoid",
            Activation::Tanh => "tanh",
            Activation::Silu => "silu",
        }
    }

    /// The activation's formula, evaluated in f64 with libm: what the runtime's vectorised
    /// kernels are tested against.
    pub fn reference(self, x: f64) -> f64 {
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
        }
    }
}

impl Operator for Activation {
    fn kind_name(&self) -> &'static str {
        self.name()
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        Ok(inputs[0].clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        match self {
            Activation::GeluTanh => vec![("approximate", "tanh".into())],
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
    }

    #[test]
    fn a_constant_must_be_finite() {
        let s = Scalar { op: BinaryOp::Mul, value: f64::INFINITY, scalar_first: false };
        assert!(run(&s, &[t(&[2])]).is_err());
    }
}
