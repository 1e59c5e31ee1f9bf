//! `linear(x, out, bias=true)` and `matmul(a, b)`.

use readi_plan::ops::{Linear, MatMul, Operator, Pure, ShapeResult, TensorType};

use super::{Args, Builtin, P, R, boolean, req};
use crate::ir::{Op, ParamSlot, ValueRef};

/// A linear layer in the IR: the operator and whether it has a bias.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LinearOp {
    pub linear: Linear,
    pub bias: bool,
}

impl LinearOp {
    /// `weight [out, in]` and, with a bias, `bias [out]`.
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        let l = &self.linear;
        let mut v = vec![ParamSlot::param("weight", vec![l.out_features, l.in_features])];
        if self.bias {
            v.push(ParamSlot::param("bias", vec![l.out_features]));
        }
        v
    }
}

impl Operator for LinearOp {
    fn kind_name(&self) -> &'static str {
        self.linear.kind_name()
    }
    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        self.linear.infer(inputs)
    }
    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut v = self.linear.attrs();
        v.push(("bias", self.bias.to_string()));
        v
    }
}

const LINEAR: &[P] = &[req("x"), req("out"), boolean("bias", true)];
const MATMUL: &[P] = &[req("a"), req("b")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("linear", LINEAR, linear), Builtin::new("matmul", MATMUL, matmul)]
}

fn linear(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let in_features = t
        .rank()
        .checked_sub(1)
        .and_then(|l| t.known_dim(l))
        .ok_or_else(|| args.bad_value("x", format!("linear needs a known last axis, got {t}")))?;
    let linear = Linear { in_features, out_features: args.int_at_least("out", 1)? };
    Ok((Op::Linear(LinearOp { linear, bias: args.boolean("bias")? }), vec![args.tensor("x")?]))
}

fn matmul(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    Ok((Op::Pure(Pure::MatMul(MatMul)), vec![args.tensor("a")?, args.tensor("b")?]))
}
