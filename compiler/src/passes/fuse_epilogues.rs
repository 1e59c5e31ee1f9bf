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
//! Does nothing when no bias is left and no activation or residual add follows such a
//! node. Assumes `fold_batchnorm` ran (so a ReLU after a folded BatchNorm follows its conv).

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
        if let Op::Pure(Pure::Binary(BinaryOp::Add)) = node.op
            && let Some((conv, other, new)) = residual_conv(g, id)
        {
            let producer = g.node(conv.node);
            let slots = rebind(&new, &producer.params, &[]);
            let mut p = Patch::new("fuse_residual");
            p.rewrite.push((conv.node, new, slots));
            p.set_inputs.push((conv.node, 1, other));
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
