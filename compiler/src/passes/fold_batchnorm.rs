//! `fold_batchnorm`: folds every BatchNorm into a per-channel affine
//! `y = scale * x + shift` (from [`batchnorm_affine`]: `scale = gamma / sqrt(var + eps)`,
//! `shift = beta - mean * scale`), computed in f64 and stored as f32.
//!
//! * rule `fold_into_conv`: a BatchNorm whose input is a conv that nothing else reads
//!   becomes that conv's epilogue scale and shift (a conv bias folds into the shift:
//!   `shift = beta + (bias - mean) * scale`). The conv weight is untouched, so a variant
//!   can own the affine alone.
//! * rule `channel_affine`: any other BatchNorm becomes a channel-affine node.
//!
//! Either way the node records the BatchNorm (its name and eps, gamma, beta and the
//! folded conv bias as themselves) so that `readi adapt-bn` can re-estimate its
//! statistics from the plan. Each variant's scale and shift are computed from its own
//! parameters. Does nothing when no BatchNorm is left. Assumes the adaptations are placed
//! (`drop_inactive`, `commute_adapters`, `merge_lora`).

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_plan::ops::{ChannelAffine, batchnorm_affine, batchnorm_channel};

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch, internal, rebind};
use crate::ir::{Graph, NodeId, Op, ValueRef};
use crate::module::Module;
use crate::ops::{AffineOp, BnFold, ConvOp, Epilogue};
use crate::weights::tensors::{Tensor, TensorTable};

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let mut patches = Vec::new();
    for id in g.node_ids() {
        let node = g.node(id);
        let Op::BatchNorm(bn) = &node.op else { continue };
        let name = |slot: &str| node.params.iter().find(|s| s.name == slot).map(|s| node.param_name(s));
        let (Some(w), Some(b), Some(mean), Some(var)) =
            (name("weight"), name("bias"), name("running_mean"), name("running_var"))
        else {
            return Err(internal(format!("BatchNorm `{}` lacks its parameter slots", node.path)));
        };
        let c = bn.channels.max(0) as usize;
        let eps = bn.eps;
        let conv = foldable_conv(g, id);
        let conv_bias = conv.and_then(|cv| match &g.node(cv).op {
            Op::Conv2d(op) if op.bias => {
                g.node(cv).params.iter().find(|s| s.name == "bias").map(|s| g.node(cv).param_name(s))
            }
            _ => None,
        });
        check_variance(table, &var, node)?;
        let scale_name = format!("{}@scale", node.path);
        let shift_name = format!("{}@shift", node.path);
        let scale = table
            .derive_one(&[&w, &var], "folded into", vec![c], |v| {
                v[0].iter()
                    .zip(v[1])
                    .map(|(&g, &var)| batchnorm_channel(g as f64, 0.0, 0.0, var as f64, eps).0 as f32)
                    .collect()
            })
            .map_err(internal)?;
        let shift = shift_tensor(table, [&w, &b, &mean, &var], conv_bias.as_deref(), c, eps).map_err(internal)?;
        let fold = BnFold { name: node.path.clone(), eps, conv_bias: conv_bias.is_some() };
        let epilogue = Epilogue { scale: true, shift: true, act: None, bn: Some(fold) };
        let mut bind =
            vec![("scale", scale_name.clone()), ("shift", shift_name.clone()), ("bn.weight", w), ("bn.bias", b)];
        let mut p = match conv {
            Some(cv) => {
                let conv_node = g.node(cv);
                let Op::Conv2d(op) = &conv_node.op else { continue };
                if let Some(cb) = conv_bias {
                    bind.push(("bn.conv_bias", cb));
                }
                let new = Op::Conv2d(ConvOp { bias: false, epilogue, ..op.clone() });
                let slots = rebind(&new, &conv_node.params, &bind);
                let mut p = Patch::new("fold_into_conv");
                p.rewrite.push((cv, new, slots));
                p.replace_uses.push((ValueRef { node: id, port: 0 }, ValueRef { node: cv, port: 0 }));
                p.fuse.push((cv, node.path.clone()));
                p.remove.push(id);
                p
            }
            None => {
                let new = Op::ChannelAffine(AffineOp { affine: ChannelAffine { channels: bn.channels }, epilogue });
                let slots = rebind(&new, &[], &bind);
                let mut p = Patch::new("channel_affine");
                p.rewrite.push((id, new, slots));
                p
            }
        };
        p.tensors.extend([(scale_name, scale), (shift_name, shift)]);
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// The conv before a BatchNorm that the BatchNorm can fold into: nothing else reads it,
/// and no epilogue or algorithm has been given to it yet.
fn foldable_conv(g: &Graph, bn: NodeId) -> Option<NodeId> {
    let x = *g.inputs(bn).first()?;
    let Op::Conv2d(c) = &g.node(x.node).op else { return None };
    let sole = g.users(x.node) == [bn] && g.uses(x.node) == 1;
    (sole && c.epilogue.is_empty() && c.algo.is_none() && !c.packed).then_some(x.node)
}

/// The folded shift from `[gamma, beta, mean, var]` and a conv bias folded in.
fn shift_tensor(table: &TensorTable, bn: [&str; 4], prior: Option<&str>, c: usize, eps: f64) -> Result<Tensor, String> {
    let mut ins: Vec<&str> = vec![bn[1], bn[2], bn[0], bn[3]];
    ins.extend(prior);
    table.derive_one(&ins, "folded into", vec![c], |v| {
        let (_, t) = batchnorm_affine(v[2], v[0], v[1], v[3], eps, v.get(4).copied());
        t.into_iter().map(|x| x as f32).collect()
    })
}

/// An error at the BatchNorm `node` if its variance `var` is negative anywhere.
pub(super) fn check_variance(table: &TensorTable, var: &str, node: &crate::ir::Node) -> Result<(), Diagnostics> {
    let Some(m) = negative_variance(table, var) else { return Ok(()) };
    Err(Diagnostics(vec![
        Diagnostic::error(Code::Weights, format!("{m}: BatchNorm `{}` cannot be folded", node.path))
            .with_primary(node.span, "its scale would be gamma / sqrt(running_var + eps)")
            .with_note(
                "a variance is never negative; the weights file is corrupt or was not exported from a BatchNorm",
            ),
    ]))
}

/// `bn1.running_var[3] = -1 is negative` (and the variant, if it is one's value): the
/// first negative (or NaN) variance in the base or a variant. `sqrt` would make it NaN.
pub fn negative_variance(table: &TensorTable, var: &str) -> Option<String> {
    let t = table.get(var)?;
    (0..=t.variants.len()).filter(|&v| v == 0 || t.variants[v - 1].is_some()).find_map(|v| {
        let i = t.value(v).iter().position(|x| x.is_nan() || *x < 0.0)?;
        let variant = match v.checked_sub(1).and_then(|i| table.variants.get(i)) {
            Some(info) => format!(" in variant `{}`", info.key),
            None => String::new(),
        };
        Some(format!("{var}[{i}] = {} is negative{variant}", t.value(v)[i]))
    })
}
