//! `choose_conv_algo`: picks each conv's algorithm (rule `choose_conv_algo`) with the
//! runtime's cost model, `readi_runtime::kernels::conv::choose`, on the layer's shape at
//! batch size 1 (the choice does not depend on the batch): Winograd F(4x4) or F(2x2) for
//! 3x3 stride-1 layers with enough channels, a plain GEMM for 1x1 stride-1 layers, the
//! direct loop for depthwise layers, weight panels for large weights on 7x7 planes, im2col
//! otherwise.
//!
//! A variant-owned conv takes the algorithm `choose_strategy` chose for it (a compact one
//! under a memory budget). Does nothing when every conv has an algorithm. Assumes the epilogues are fused (the
//! choice does not depend on them, but packing follows).

use readi_grammar::diag::Diagnostics;
use readi_runtime::kernels::conv;

use super::{BackendInputs, Output, Patch, rebind};
use crate::ir::{Graph, NodeId, Op};
use crate::module::Module;
use crate::ops::ConvOp;

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let g = &module.graph;
    let mut patches = Vec::new();
    for id in g.node_ids() {
        let node = g.node(id);
        let Op::Conv2d(c) = &node.op else { continue };
        if c.algo.is_some() {
            continue;
        }
        let (h, w) = spatial(g, id);
        let shape = c.conv.shape(1, h, w);
        let chosen = module.strategy.as_ref().and_then(|s| s.algo_of(&node.path)).filter(|a| a.supports(&shape));
        let algo = chosen.unwrap_or_else(|| conv::choose(&shape));
        let new = Op::Conv2d(ConvOp { algo: Some(algo), ..c.clone() });
        let slots = rebind(&new, &node.params, &[]);
        let mut p = Patch::new("choose_conv_algo");
        p.rewrite.push((id, new, slots));
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// The spatial size of a node's first input (known for a conv: its shape rule checks).
pub(super) fn spatial(g: &Graph, id: NodeId) -> (usize, usize) {
    let t = g.inputs(id).first().and_then(|v| g.value_type(*v).cloned());
    let dim = |axis: usize| t.as_ref().and_then(|t| t.known_dim(axis)).map_or(0, |d| d.max(0) as usize);
    // A conv1d's `[N, C, L]` is `[N, C, 1, L]`.
    if t.as_ref().is_some_and(|t| t.rank() == 3) { (1, dim(2)) } else { (dim(2), dim(3)) }
}
