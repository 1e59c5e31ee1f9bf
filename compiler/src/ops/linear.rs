//! `linear(x, out, bias=true)` and `matmul(a, b)`.

use readi_plan::ops::{Linear, MatMul, Operator, Pure, ShapeResult, TensorType};

use super::{Args, Builtin, Epilogue, P, R, boolean, req};
use crate::ir::{Op, ParamSlot, ValueRef};

/// A linear layer in the IR: the operator, whether it has a bias, and what the back end
/// decided for it.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearOp {
    pub linear: Linear,
    pub bias: bool,
    /// Back end: what runs after the accumulation (`fuse_epilogues`).
    pub epilogue: Epilogue,
    /// Back end: the weight slot holds the weight transposed, `[in, out]`, the layout the
    /// GEMM reads fastest, or in panels when `panels` (`pack_weights`).
    pub packed: bool,
    /// Back end: the packed weight is in panels of [`PANEL`](readi_plan::ops::PANEL)
    /// outputs ([`Linear::panel_len`] values), for the runtime's register-blocked product.
    pub panels: bool,
    /// Back end: a LoRA branch of this rank computed in the layer's kernel (`fuse_lora`),
    /// slots `lora_A [rank, in]` and `lora_B [out, rank]` (pre-scaled).
    pub lora: Option<i64>,
}

impl LinearOp {
    /// A linear layer as the language writes it.
    pub fn new(linear: Linear, bias: bool) -> LinearOp {
        LinearOp { linear, bias, epilogue: Epilogue::default(), packed: false, panels: false, lora: None }
    }

    /// `weight [out, in]` (packed: `[in, out]`, or in panels `[panel_len]`), with a bias
    /// `bias [out]`, a fused LoRA branch's `lora_A [rank, in]` and `lora_B [out, rank]`,
    /// then the epilogue's slots.
    pub fn param_slots(&self) -> Vec<ParamSlot> {
        let l = &self.linear;
        let weight = match (self.packed, self.panels) {
            (true, true) => vec![l.panel_len().map_or(i64::MAX, |n| n as i64)],
            (true, false) => vec![l.in_features, l.out_features],
            (false, _) => vec![l.out_features, l.in_features],
        };
        let mut v = vec![ParamSlot::param("weight", weight)];
        if self.bias {
            v.push(ParamSlot::param("bias", vec![l.out_features]));
        }
        if let Some(rank) = self.lora {
            v.push(ParamSlot::param("lora_A", vec![rank, l.in_features]));
            v.push(ParamSlot::param("lora_B", vec![l.out_features, rank]));
        }
        v.extend(self.epilogue.slots(l.out_features));
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
        if self.panels {
            v.push(("weight", "panels".to_string()));
        }
        if let Some(rank) = self.lora {
            v.push(("lora", format!("rank {rank}")));
        }
        if let Some(e) = self.epilogue.attr() {
            v.push(("epilogue", e));
        }
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
    Ok((Op::Linear(LinearOp::new(linear, args.boolean("bias")?)), vec![args.tensor("x")?]))
}

fn matmul(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    Ok((Op::Pure(Pure::MatMul(MatMul)), vec![args.tensor("a")?, args.tensor("b")?]))
}
