//! `fuse_lora`: computes each LoRA branch left in the graph inside its layer's kernel
//! (rule `fuse_lora`): `y + scale * lora_B(lora_A(x))` on a conv or linear layer
//! `y = layer(x)` becomes that layer with a LoRA part of the branch's rank, so its
//! kernel reads `x` once and adds `B (A x)` to its accumulator before the epilogue. The
//! branch's four nodes leave the graph.
//!
//! The layer's slots `lora_A` and `lora_B` read `<layer>.lora_A.weight` (`pack_weights`
//! packs it with the conv's weight, for the same algorithm) and
//! `<layer>.lora_B.weight@scaled`, `scale * B` (the scale is PEFT's `alpha / rank`),
//! derived per variant: a variant still stores only its `A` and `B`; the layer's weight
//! stays the base's. A BatchNorm after the layer folds into it afterwards
//! (`fold_batchnorm`), its scale applied to the sum, which is `bn(y + scale B A x)` as the
//! spec says, for each variant's own BatchNorm (and AdaBN re-estimates it on the sum).
//!
//! Applies when the branch is as `inject_adapt` built it: `lora_A` reads the layer's
//! input, each of the branch's nodes and the layer feed only the next one, and the layer
//! is a conv of one group or a linear layer with nothing fused into it yet. Otherwise the
//! branch stays as separate steps: grouped and depthwise convs (`lora_A` is a dense conv
//! there, which their kernels do not compute), a layer whose input an adapter rewired, a
//! layer read by something besides the sum. [`fusable`] is the test; `commute_adapters`
//! leaves such branches where they are.
//!
//! Does nothing with `--lora merge` (`merge_lora` took every branch) or without LoRA.
//! Assumes `merge_lora` ran and `fold_batchnorm` did not.

use readi_grammar::diag::Diagnostics;

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch, internal, rebind};
use crate::adapt::Injection;
use crate::ir::{self, BinaryOp, Graph, Op, Pure, Scalar, SlotKind, ValueRef};
use crate::module::Module;
use crate::ops::{ConvOp, LinearOp};

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let Some(plan) = &module.adapt else { return Ok(Output::Patches(Vec::new())) };
    let mut patches = Vec::new();
    for inj in &plan.injections {
        let Injection::Lora { base, a, b, scale, add, .. } = *inj else { continue };
        let Some(rank) = fusable(g, inj) else { continue };
        let Op::Pure(Pure::Scalar(Scalar { value: factor, .. })) = g.node(scale).op else { continue };
        let node = g.node(base);
        let name = |n| ir::join_path(&g.node(n).path, "weight");
        let (wa, wb) = (name(a), name(b));
        let scaled_name = format!("{wb}@scaled");
        let out = match &node.op {
            Op::Conv2d(c) => c.conv.out_channels,
            Op::Linear(l) => l.linear.out_features,
            _ => continue,
        };
        let shape = vec![out.max(0) as usize, rank as usize];
        let scaled = table
            .derive_one(&[&wb], "scaled as", shape, |v| v[0].iter().map(|&w| (w as f64 * factor) as f32).collect())
            .map_err(internal)?;
        let new = match &node.op {
            Op::Conv2d(c) => Op::Conv2d(ConvOp { lora: Some(rank), ..c.clone() }),
            Op::Linear(l) => Op::Linear(LinearOp { lora: Some(rank), ..l.clone() }),
            _ => continue,
        };
        let mut slots = rebind(&new, &node.params, &[("lora_A", wa), ("lora_B", scaled_name.clone())]);
        for s in slots.iter_mut().filter(|s| s.name.starts_with("lora_")) {
            s.kind = SlotKind::Added;
        }
        let mut p = Patch::new("fuse_lora");
        p.tensors.push((scaled_name, scaled));
        p.rewrite.push((base, new, slots));
        p.replace_uses.push((ValueRef { node: add, port: 0 }, ValueRef { node: base, port: 0 }));
        p.fuse.push((base, "lora".into()));
        p.remove.extend(inj.nodes());
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// The rank of a LoRA injection that [`run`] fuses into its layer, or `None` when its
/// branch stays as separate steps (see the module documentation).
pub(crate) fn fusable(g: &Graph, inj: &Injection) -> Option<i64> {
    let Injection::Lora { base, a, b, scale, add, .. } = *inj else { return None };
    if ![base, a, b, scale, add].iter().all(|&n| g.contains(n)) {
        return None;
    }
    let out = |node| ValueRef { node, port: 0 };
    // Each node read once, by the next; the layer's and lora_A's input the same.
    let feeds = |from, to| g.uses(from) == 1 && g.users(from) == [to];
    let chain = feeds(base, add) && feeds(a, b) && feeds(b, scale) && feeds(scale, add);
    let wired = !g.inputs(a).is_empty()
        && g.inputs(a).first() == g.inputs(base).first()
        && g.inputs(b) == [out(a)]
        && g.inputs(scale) == [out(b)]
        && g.inputs(add) == [out(base), out(scale)];
    let scaling =
        matches!(g.node(scale).op, Op::Pure(Pure::Scalar(Scalar { op: BinaryOp::Mul, scalar_first: false, .. })))
            && matches!(g.node(add).op, Op::Pure(Pure::Binary(BinaryOp::Add)));
    if !(chain && wired && scaling) {
        return None;
    }
    let rank = match (&g.node(base).op, &g.node(a).op) {
        (Op::Conv2d(c), Op::Conv2d(ca)) => {
            let bare = c.epilogue.is_empty() && c.algo.is_none() && !c.packed && c.lora.is_none();
            let same_window = ca.conv.window == c.conv.window && ca.conv.in_channels == c.conv.in_channels;
            (bare && c.conv.groups == 1 && ca.conv.groups == 1 && same_window && !ca.bias)
                .then_some(ca.conv.out_channels)
        }
        (Op::Linear(l), Op::Linear(la)) => {
            let bare = l.epilogue.is_empty() && !l.packed && l.lora.is_none();
            (bare && la.linear.in_features == l.linear.in_features && !la.bias).then_some(la.linear.out_features)
        }
        _ => None,
    }?;
    // lora_B maps the rank back to the layer's outputs, without a bias.
    let b_ok = match &g.node(b).op {
        Op::Conv2d(cb) => cb.conv.in_channels == rank && !cb.bias && cb.conv.window == ir::Window2::ONE,
        Op::Linear(lb) => lb.linear.in_features == rank && !lb.bias,
        _ => false,
    };
    (b_ok && rank >= 1).then_some(rank)
}
