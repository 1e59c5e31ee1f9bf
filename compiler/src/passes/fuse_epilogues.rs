//! `fuse_epilogues`: gives conv, transposed conv, linear and channel-affine nodes the
//! work they can do while writing their output.
//!
//! * rule `bias_to_shift`: a conv's, transposed conv's, conv3d's or linear's bias becomes
//!   its epilogue's shift (the same tensor; a folded BatchNorm already has a shift and no
//!   bias);
//! * rule `fuse_activation`: an activation (any [`Activation`]: relu, relu6, clamp,
//!   hardswish, silu, gelu, ..., and the unary functions such as `exp`) whose input is a
//!   conv, transposed conv, conv3d, linear or channel affine without one, that nothing
//!   else reads, runs in that node's epilogue; the activation leaves the graph. One per
//!   node: a second activation stays a node. (A BatchNorm after a transposed conv or a
//!   conv3d is not folded into it: it stays a channel affine, which takes the activation.)
//!
//! * rule `fuse_residual`: an `add` of a conv2d's output and another value of the same
//!   shape (a residual connection: `bn3(conv3(x)) + identity`), where nothing else reads
//!   the conv and it has no activation, becomes the conv's second input, added after its
//!   scale and shift (and its adapter); the add leaves the graph, and the ReLU after it can
//!   then join the conv by `fuse_activation`. The first operand is taken when both are
//!   such convs. The other operand does not depend on the conv (the add is the conv's only
//!   reader), so the graph stays acyclic.
//!
//! * rule `fuse_channel_scale`: a `mul` of a value `[N, C, H, W]` by a per-channel scale
//!   `[N, C, 1, 1]` (a squeeze-and-excitation's), read only by a 1x1 conv (as its input),
//!   becomes the conv's last input, the conv computed with its weight's input channels
//!   scaled per image; the mul and its product leave the graph. Only where the weight
//!   (`out · in/groups`) is at most half the product (`C · H · W`, per image): the conv
//!   then reads the unscaled input from farther away than the product it replaces, and
//!   scales its weight; EfficientNet-B0's 14x14 projections (weight 0.57 of the product)
//!   ran as long fused as the multiply and conv apart, its 56x56 and 112x112 ones
//!   (0.01-0.05) gained most of the multiply's time (per-step profile, 6 alternating
//!   rounds, 2026-12-06). Not on a conv with a LoRA branch (which reads the input too). A
//!   residual fused after it goes before it.
//!
//! Does nothing when no bias is left and no activation, residual add or channel scale
//! follows such a node. Assumes `fold_batchnorm` ran (so a ReLU after a folded BatchNorm
//! follows its conv).

use readi_grammar::diag::Diagnostics;

use super::{BackendInputs, Output, Patch, rebind};
use crate::ir::{Activation, BinaryOp, Graph, NodeId, Op, Pure, ValueRef};
use crate::module::Module;
use crate::ops::Epilogue;

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let g = &module.graph;
    let mut patches = Vec::new();
    for id in g.node_ids() {
        let node = g.node(id);
        let bias = || node.params.iter().find(|s| s.name == "bias").map(|s| node.param_name(s));
        let shifted = match &node.op {
            Op::Conv2d(c) if c.bias && !c.epilogue.shift => {
                let mut c = c.clone();
                c.bias = false;
                c.epilogue.shift = true;
                Some(Op::Conv2d(c))
            }
            Op::ConvTranspose2d(c) if c.bias && !c.epilogue.shift => {
                let mut c = c.clone();
                c.bias = false;
                c.epilogue.shift = true;
                Some(Op::ConvTranspose2d(c))
            }
            Op::Conv3d(c) if c.bias && !c.epilogue.shift => {
                let mut c = c.clone();
                c.bias = false;
                c.epilogue.shift = true;
                Some(Op::Conv3d(c))
            }
            Op::Linear(l) if l.bias && !l.epilogue.shift => {
                let mut l = l.clone();
                l.bias = false;
                l.epilogue.shift = true;
                Some(Op::Linear(l))
            }
            _ => None,
        };
        if let (Some(new), Some(b)) = (shifted, bias()) {
            let slots = rebind(&new, &node.params, &[("shift", b)]);
            let mut p = Patch::new("bias_to_shift");
            p.rewrite.push((id, new, slots));
            patches.push(p);
            continue;
        }
        if let Op::Pure(Pure::Activation(act)) = node.op
            && let Some(x) = g.inputs(id).first()
            && let Some(new) = with_activation(g, x.node, act)
        {
            let producer = g.node(x.node);
            let slots = rebind(&new, &producer.params, &[]);
            let mut p = Patch::new("fuse_activation");
            p.rewrite.push((x.node, new, slots));
            p.replace_uses.push((ValueRef { node: id, port: 0 }, *x));
            p.fuse.push((x.node, node.path.clone()));
            p.remove.push(id);
            patches.push(p);
            continue;
        }
        if let Op::Pure(Pure::Binary(BinaryOp::Mul)) = node.op
            && let Some((conv, x, scale, new)) = scaled_conv(g, id)
        {
            let slots = rebind(&new, &g.node(conv).params, &[]);
            let port = if matches!(&new, Op::Conv2d(c) if c.residual) { 2 } else { 1 };
            let mut p = Patch::new("fuse_channel_scale");
            p.rewrite.push((conv, new, slots));
            p.set_inputs.push((conv, 0, x));
            p.set_inputs.push((conv, port, scale));
            p.fuse.push((conv, node.path.clone()));
            p.remove.push(id);
            patches.push(p);
            continue;
        }
        if let Op::Pure(Pure::Binary(BinaryOp::Add)) = node.op
            && let Some((conv, other, new)) = residual_conv(g, id)
        {
            let producer = g.node(conv.node);
            let slots = rebind(&new, &producer.params, &[]);
            let mut p = Patch::new("fuse_residual");
            p.rewrite.push((conv.node, new, slots));
            p.set_inputs.push((conv.node, 1, other));
            // A channel scale fused before stays the last input.
            if let Some(&scale) = g.inputs(conv.node).get(1).filter(|_| producer_scaled(producer)) {
                p.set_inputs.push((conv.node, 2, scale));
            }
            p.replace_uses.push((ValueRef { node: id, port: 0 }, conv));
            p.fuse.push((conv.node, node.path.clone()));
            p.remove.push(id);
            patches.push(p);
        }
    }
    Ok(Output::Patches(patches))
}

/// For an `add` node: the operand that is a conv2d able to take the other as its residual
/// (same type as the add's output, read only by the add, no activation, no residual yet,
/// not a conv1d), the other operand, and the conv's new op.
fn residual_conv(g: &Graph, add: NodeId) -> Option<(ValueRef, ValueRef, Op)> {
    let [a, b] = g.inputs(add)[..] else { return None };
    let out = &g.node(add).outputs[0];
    let ty = |v: ValueRef| &g.node(v.node).outputs[v.port as usize];
    [(a, b), (b, a)].into_iter().find_map(|(x, other)| {
        let Op::Conv2d(c) = &g.node(x.node).op else { return None };
        let fits = !c.residual && !c.one_d && c.epilogue.act.is_none();
        (fits && g.uses(x.node) == 1 && ty(x) == out && ty(other) == out)
            .then(|| (x, other, Op::Conv2d(crate::ops::ConvOp { residual: true, ..c.clone() })))
    })
}

/// Whether a node is a conv with a fused channel scale.
fn producer_scaled(node: &crate::ir::Node) -> bool {
    matches!(&node.op, Op::Conv2d(c) if c.channel_scale)
}

/// For a `mul` node: the 1x1 conv that alone reads its product (at its input), the
/// operand of the product's shape `[N, C, H, W]`, the one of shape `[N, C, 1, 1]` (the
/// scale), and the conv's new op with the scale fused. Only where the weight, `out ·
/// in/groups`, is at most half of `C · H · W` (see the module doc). The conv has no LoRA
/// branch (which would read the unscaled input) and is not a conv1d.
fn scaled_conv(g: &Graph, mul: NodeId) -> Option<(NodeId, ValueRef, ValueRef, Op)> {
    let [a, b] = g.inputs(mul)[..] else { return None };
    let out = &g.node(mul).outputs[0];
    let [conv] = g.users(mul)[..] else { return None };
    if g.uses(mul) != 1 || !g.incoming(conv).iter().any(|&(port, v)| port == 0 && v.node == mul) {
        return None;
    }
    let Op::Conv2d(c) = &g.node(conv).op else { return None };
    let win = &c.conv.window;
    let fits = !c.channel_scale && !c.one_d && c.lora.is_none() && win.kernel == [1, 1];
    // The product's channels and plane (its batch may be symbolic).
    let (ch, h, w) = (out.known_dim(1)?, out.known_dim(2)?, out.known_dim(3)?);
    let weight = c.conv.out_channels.checked_mul(c.conv.in_channels / c.conv.groups.max(1))?;
    if !fits || out.rank() != 4 || 2 * weight > ch * h * w {
        return None;
    }
    let one = crate::ir::Dim::known(1);
    let is_scale = |t: &crate::ir::TensorType| {
        t.dtype == out.dtype
            && t.rank() == 4
            && t.shape[..2] == out.shape[..2]
            && t.shape[2..].iter().all(|d| *d == one)
    };
    [(a, b), (b, a)].into_iter().find_map(|(x, scale)| {
        (g.value_type(x)? == out && is_scale(g.value_type(scale)?))
            .then(|| (conv, x, scale, Op::Conv2d(crate::ops::ConvOp { channel_scale: true, ..c.clone() })))
    })
}

/// The op of `producer` with `act` in its epilogue, if it is a conv, linear or channel
/// affine without an activation whose output only `act` reads.
fn with_activation(g: &Graph, producer: NodeId, act: Activation) -> Option<Op> {
    if g.uses(producer) != 1 {
        return None;
    }
    let relu = |e: &Epilogue| e.act.is_none().then(|| Epilogue { act: Some(act), ..e.clone() });
    Some(match &g.node(producer).op {
        Op::Conv2d(c) => Op::Conv2d(crate::ops::ConvOp { epilogue: relu(&c.epilogue)?, ..c.clone() }),
        Op::ConvTranspose2d(c) => {
            Op::ConvTranspose2d(crate::ops::ConvTransposeOp { epilogue: relu(&c.epilogue)?, ..c.clone() })
        }
        Op::Conv3d(c) => Op::Conv3d(crate::ops::Conv3dOp { epilogue: relu(&c.epilogue)?, ..c.clone() }),
        Op::Linear(l) => Op::Linear(crate::ops::LinearOp { epilogue: relu(&l.epilogue)?, ..l.clone() }),
        Op::ChannelAffine(a) => Op::ChannelAffine(crate::ops::AffineOp { epilogue: relu(&a.epilogue)?, ..a.clone() }),
        _ => return None,
    })
}
