//! `fuse_adapters`: computes a bottleneck adapter in the kernel of the conv that produces
//! its input (rule `fuse_adapter`): `z = y + up(act(down(y)))` on a conv's output
//! `y = conv(x)` (its epilogue's scale and shift applied: a folded BatchNorm) becomes
//! that conv with an adapter epilogue, so the kernel adds the adapter to each chunk of
//! output pixels while it is in cache instead of four more steps streaming the
//! activation. The kernel keeps the unfused order: conv, scale and shift, the adapter,
//! then a ReLU (`fuse_epilogues` fuses the one after the sum into the conv afterwards).
//! The adapter's four nodes leave the graph.
//!
//! The conv's new slots `adapter.down.weight`, `adapter.down.bias`, `adapter.up.weight`
//! and `adapter.up.bias` read the adapter's own tensors (`<down>.weight` and so on, as
//! `commute_adapters` left them), slots of the kind the adapter had: each variant's
//! values come through its table, as for a fused LoRA branch's.
//!
//! Applies when the adapter is as `inject_adapt` built it and `commute_adapters` moved it
//! behind its BatchNorm (which `fold_batchnorm` folded), recognised by its shape (the
//! folded BatchNorm, the injection's anchor, has left the adaptation plan): `down` is a 1x1 conv of one
//! group with a bias from the conv's channels, `act` an activation, `up` a 1x1 conv with
//! a bias back, the sum adds the conv's output and `up`'s; the conv's output is read only
//! by `down` and the sum, each of the adapter's nodes only by the next, and the conv has
//! no ReLU yet and no adapter. Otherwise the adapter stays as separate steps: an adapter
//! whose input is not a conv's output (before a conv, after a pooling, behind a
//! BatchNorm whose scale is near zero, which `commute_adapters` leaves in front), a conv
//! read by something else too, or `CompileOptions::unfused_adapters`.
//!
//! Does nothing without adapters. Assumes `fold_batchnorm` ran and `fuse_epilogues` did
//! not (so the adapter's convs still have their biases and the conv no ReLU).

use readi_grammar::diag::Diagnostics;

use super::{BackendInputs, Output, Patch, rebind};
use crate::ir::{self, BinaryOp, Graph, NodeId, Op, Pure, ValueRef};
use crate::module::Module;
use crate::ops::{AdapterOp, ConvOp};

pub fn run(module: &Module, inputs: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let g = &module.graph;
    if inputs.opts.unfused_adapters {
        return Ok(Output::Patches(Vec::new()));
    }
    let mut patches = Vec::new();
    for add in g.node_ids() {
        let Some(m) = fusable(g, add) else { continue };
        let node = g.node(m.conv);
        let Op::Conv2d(c) = &node.op else { continue };
        let new = Op::Conv2d(ConvOp { adapter: Some(m.adapter), ..c.clone() });
        let slot = |n: NodeId, name: &str| g.node(n).params.iter().find(|s| s.name == name).cloned();
        let [dw, db, uw, ub] = AdapterOp::SLOTS;
        let from = [(dw, m.down, "weight"), (db, m.down, "bias"), (uw, m.up, "weight"), (ub, m.up, "bias")];
        let Some(sources) = from.iter().map(|&(to, n, name)| Some((to, slot(n, name)?, n))).collect::<Option<Vec<_>>>()
        else {
            continue;
        };
        let bind: Vec<(&str, String)> = sources.iter().map(|(to, s, n)| (*to, g.node(*n).param_name(s))).collect();
        let mut slots = rebind(&new, &node.params, &bind);
        for s in slots.iter_mut() {
            if let Some((_, src, _)) = sources.iter().find(|(to, _, _)| *to == s.name) {
                s.kind = src.kind;
            }
        }
        let mut p = Patch::new("fuse_adapter");
        p.rewrite.push((m.conv, new, slots));
        p.replace_uses.push((ValueRef { node: add, port: 0 }, ValueRef { node: m.conv, port: 0 }));
        p.fuse.push((m.conv, "adapter".into()));
        p.remove.extend([m.down, m.act, m.up, add]);
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// An adapter [`run`] fuses: the conv, the adapter's nodes and what the conv gets.
pub(crate) struct Fusable {
    pub conv: NodeId,
    pub down: NodeId,
    pub act: NodeId,
    pub up: NodeId,
    pub adapter: AdapterOp,
}

/// The adapter whose sum is `add`, if [`run`] fuses it into the conv producing its
/// input, or `None` when it stays as separate steps (see the module documentation). An
/// adapter is recognised by its shape, so a bottleneck written in the spec the same way
/// fuses too (exactly: the same arithmetic).
pub(crate) fn fusable(g: &Graph, add: NodeId) -> Option<Fusable> {
    if !matches!(g.node(add).op, Op::Pure(Pure::Binary(BinaryOp::Add))) {
        return None;
    }
    let sum = g.inputs(add);
    let [a, b] = sum[..] else { return None };
    [(a, b), (b, a)].into_iter().find_map(|(y, u)| matched(g, add, y, u))
}

/// [`fusable`] with the sum `add = y + u`, `u` the adapter's `up`.
fn matched(g: &Graph, add: NodeId, y: ValueRef, u: ValueRef) -> Option<Fusable> {
    let out = |node| ValueRef { node, port: 0 };
    let up = u.node;
    let act = g.inputs(up).first()?.node;
    let down = g.inputs(act).first()?.node;
    let conv = y.node;
    if u.port != 0 || y.port != 0 || g.inputs(down).first() != Some(&y) {
        return None;
    }
    let Op::Conv2d(c) = &g.node(conv).op else { return None };
    // The conv: its output read by the adapter's down and sum only (`uses` counts model
    // outputs too), nothing fused after the shift yet.
    if g.uses(conv) != 2 || g.users(conv) != sorted(down, add) {
        return None;
    }
    if c.adapter.is_some() || c.epilogue.act.is_some() || c.packed || c.algo.is_some() {
        return None;
    }
    // Each of the adapter's nodes read once, by the next.
    let feeds = |from: NodeId, to: NodeId| g.uses(from) == 1 && g.users(from) == [to];
    if !(feeds(down, act) && feeds(act, up) && feeds(up, add)) {
        return None;
    }
    if g.inputs(act) != [out(down)] || g.inputs(up) != [out(act)] {
        return None;
    }
    let Op::Pure(Pure::Activation(f)) = g.node(act).op else { return None };
    // Two 1x1 convs of one group with biases, nothing fused: C -> mid -> C.
    let plain = |n: NodeId| match &g.node(n).op {
        Op::Conv2d(k) => (k.conv.window == ir::Window2::ONE
            && k.conv.groups == 1
            && k.bias
            && k.epilogue.is_empty()
            && k.lora.is_none()
            && k.adapter.is_none()
            && k.algo.is_none()
            && !k.packed)
            .then_some((k.conv.in_channels, k.conv.out_channels)),
        _ => None,
    };
    let ((d_in, mid), (u_in, u_out)) = (plain(down)?, plain(up)?);
    let channels = c.conv.out_channels;
    (d_in == channels && u_in == mid && u_out == channels && mid >= 1).then_some(Fusable {
        conv,
        down,
        act,
        up,
        adapter: AdapterOp { mid, act: f },
    })
}

fn sorted(a: NodeId, b: NodeId) -> Vec<NodeId> {
    let mut v = vec![a, b];
    v.sort();
    v
}
