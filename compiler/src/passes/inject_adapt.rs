//! `inject_adapt`: adds the layers of the `lora` and `adapter` rules to the graph.
//!
//! Changes: for every LoRA target `y = layer(x)` (PEFT's structure and names):
//!
//! ```text
//! y' = y + scale * lora_B(lora_A(x))        scale = alpha / rank  (alpha / sqrt(rank): rsLoRA)
//! ```
//!
//! * linear `in -> out`: `lora_A` is `linear(in -> rank)`, `lora_B` is `linear(rank -> out)`,
//!   both without bias;
//! * conv2d: `lora_A` is a conv to `rank` channels with the layer's kernel, stride, padding
//!   and dilation, `lora_B` a 1x1 conv from `rank` to the layer's output channels.
//!
//! Nodes `<layer>.lora_A`, `<layer>.lora_B` (parameters `<layer>.lora_A.weight`, ...),
//! `<layer>.lora_scale` and `<layer>.lora_add`; every former use of `y` reads `y'`.
//!
//! For every adapter target `t(x)` (before a BatchNorm, say), a residual bottleneck on its
//! input, `t(x + up(act(down(x))))`: `down` a 1x1 conv `C -> C/squeeze` with bias, `up` a 1x1
//! conv `C/squeeze -> C` with bias (on rows of features `[N, C]`, a sparse tensor's, two
//! linears). Nodes `<t>.adapter.down`, `.act`, `.up`, `.add`.
//!
//! The new parameter slots are [`SlotKind::Added`]: they are not in the base model, whose
//! value for them is zero (so `lora_B = 0` and `up = 0` make every branch vanish), and each
//! variant owns them. The pass records what it built in [`AdaptPlan::injections`], which
//! the back end uses to merge LoRA into the base weights.
//!
//! Assumes: `resolve_adapt` ran without errors (targets are linear/conv2d layers with
//! known sizes, adapter inputs are NCHW or `[N, C]` with channels divisible by the squeeze ratio).

use readi_grammar::diag::Span;

use super::resolve_adapt::{AdaptPlan, Injection, RuleKind};
use crate::ir::{
    Activation, BinaryOp, Conv2d, Graph, Linear, Node, NodeId, Op, Pure, Scalar, SlotKind, ValueRef, Window2,
};
use crate::ops::{ConvOp, LinearOp};

/// Runs the pass. Returns `Err` with a message only on a broken invariant (a compiler bug).
pub fn run(graph: &mut Graph, plan: &mut AdaptPlan) -> Result<(), String> {
    let mut injections = Vec::new();
    for (rule, r) in plan.rules.iter().enumerate() {
        for t in &r.targets {
            match r.kind {
                RuleKind::Tune | RuleKind::Prune { .. } => {}
                RuleKind::Lora { rank, .. } => {
                    let scale = r.kind.lora_scale().unwrap_or(1.0);
                    injections.push(lora(graph, t.node, rank, scale, rule, r.span)?);
                }
                RuleKind::Adapter { squeeze, act } => {
                    injections.push(adapter(graph, t.node, squeeze, act, rule, r.span)?);
                }
            }
        }
    }
    plan.injections = injections;
    Ok(())
}

/// Adds a node computing `op` on `inputs` at `path`, in `like`'s scope, its parameter
/// slots marked as added.
fn add(
    graph: &mut Graph,
    like: NodeId,
    path: String,
    op: Op,
    inputs: &[ValueRef],
    span: Span,
) -> Result<NodeId, String> {
    let types: Vec<_> = inputs
        .iter()
        .map(|v| graph.value_type(*v).cloned())
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| format!("`{path}` reads a missing value"))?;
    let refs: Vec<_> = types.iter().collect();
    let outputs = op.infer(&refs).map_err(|e| format!("`{path}`: {}", e.message))?;
    let mut params = op.param_slots();
    for p in &mut params {
        p.kind = SlotKind::Added;
    }
    let scope = graph.node(like).scope;
    Ok(graph.add_node(Node::new(op, path, scope, params, outputs, span), inputs))
}

fn out(node: NodeId) -> ValueRef {
    ValueRef { node, port: 0 }
}

fn lora(graph: &mut Graph, base: NodeId, rank: i64, scale: f64, rule: usize, span: Span) -> Result<Injection, String> {
    let node = graph.node(base).clone();
    let x = graph.inputs(base).first().copied().ok_or_else(|| format!("`{}` has no input", node.path))?;
    let (op_a, op_b) = match &node.op {
        Op::Linear(l) => {
            let linear =
                |in_features, out_features| Op::Linear(LinearOp::new(Linear { in_features, out_features }, false));
            (linear(l.linear.in_features, rank), linear(rank, l.linear.out_features))
        }
        Op::Conv2d(c) => {
            let a = Conv2d { out_channels: rank, groups: 1, ..c.conv.clone() };
            let b = Conv2d { in_channels: rank, out_channels: c.conv.out_channels, window: Window2::ONE, groups: 1 };
            // A conv1d's branch is two conv1ds (PEFT's `Conv1d` LoRA: `A [rank, in, k]`).
            let op = |conv| Op::Conv2d(ConvOp { one_d: c.one_d, ..ConvOp::new(conv, false) });
            (op(a), op(b))
        }
        op => return Err(format!("LoRA on a `{}` layer `{}`", op.kind_name(), node.path)),
    };
    let p = &node.path;
    let a = add(graph, base, format!("{p}.lora_A"), op_a, &[x], span)?;
    let b = add(graph, base, format!("{p}.lora_B"), op_b, &[out(a)], span)?;
    let scaled = Op::Pure(Pure::Scalar(Scalar { op: BinaryOp::Mul, value: scale, scalar_first: false }));
    let s = add(graph, base, format!("{p}.lora_scale"), scaled, &[out(b)], span)?;
    let sum =
        add(graph, base, format!("{p}.lora_add"), Op::Pure(Pure::Binary(BinaryOp::Add)), &[out(base), out(s)], span)?;
    graph.replace_uses_except(out(base), out(sum), sum);
    Ok(Injection::Lora { rule, base, a, b, scale: s, add: sum, factor: scale })
}

fn adapter(
    graph: &mut Graph,
    target: NodeId,
    squeeze: i64,
    act: Activation,
    rule: usize,
    span: Span,
) -> Result<Injection, String> {
    let path = graph.node(target).path.clone();
    let x = graph.inputs(target).first().copied().ok_or_else(|| format!("`{path}` has no input"))?;
    let c = graph
        .value_type(x)
        .and_then(|t| t.known_dim(1))
        .ok_or_else(|| format!("the input of `{path}` has no known channel count"))?;
    // 1x1 convs on NCHW, linears on rows of features ([N, C]: a sparse tensor's).
    let rows = graph.value_type(x).is_some_and(|t| t.rank() == 2);
    let conv = |cin: i64, cout: i64| {
        if rows {
            return Op::Linear(LinearOp::new(Linear { in_features: cin, out_features: cout }, true));
        }
        let conv = Conv2d { in_channels: cin, out_channels: cout, window: Window2::ONE, groups: 1 };
        Op::Conv2d(ConvOp::new(conv, true))
    };
    let mid = c / squeeze;
    let down = add(graph, target, format!("{path}.adapter.down"), conv(c, mid), &[x], span)?;
    let a = add(graph, target, format!("{path}.adapter.act"), Op::Pure(Pure::Activation(act)), &[out(down)], span)?;
    let up = add(graph, target, format!("{path}.adapter.up"), conv(mid, c), &[out(a)], span)?;
    let sum =
        add(graph, target, format!("{path}.adapter.add"), Op::Pure(Pure::Binary(BinaryOp::Add)), &[x, out(up)], span)?;
    graph.set_input(target, 0, out(sum));
    Ok(Injection::Adapter { rule, target, down, act: a, up, add: sum })
}
