//! `commute_adapters`: moves an adapter (and, with LoRA as a branch, a LoRA branch) from
//! before its BatchNorm to behind it, so that the BatchNorm folds into the conv before it
//! again and the activation is not read one more time.
//!
//! With the BatchNorm `y = s x + t` (per channel, from [`batchnorm_affine`]):
//!
//! * rule `adapter_behind_batchnorm`: `bn(x + up(act(down(x))))` becomes
//!   `bn(x) + up'(act(down'(bn(x))))`, exact with `down' = W / s` per input channel and
//!   bias `b - (W / s) t`, and `up' = s W`, `s b` per output channel. Applies when no
//!   variant's scale is near zero (`|s| >= 1e-3`), where dividing by it would lose the
//!   adapter's precision;
//! * rule `lora_behind_batchnorm`: `bn(y + scale B(A(x)))` becomes
//!   `bn(y) + scale (s B)(A(x))` when the sum feeds only the BatchNorm: `lora_B` takes
//!   `s B`. Only for a layer whose LoRA stays a branch (`--lora branch`, or
//!   `choose_strategy`'s choice; merged LoRA leaves no branch), and only for a branch
//!   `fuse_lora` does not compute inside its layer (a rewired input, say).
//!
//! The moved weights keep their names; each variant's are computed from its own
//! BatchNorm and adapter values. Does nothing when no injection sits before a BatchNorm
//! (or a scale is near zero). Assumes `drop_inactive` ran.

use readi_grammar::diag::Diagnostics;
use readi_plan::ops::batchnorm_affine;

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch, internal};
use crate::adapt::Injection;
use crate::ir::{self, Graph, NodeId, Op, ValueRef};
use crate::module::Module;
use crate::passes::LoraMode;
use crate::passes::choose_strategy::lora_mode;
use crate::weights::tensors::TensorTable;

pub fn run(module: &Module, inputs: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let Some(plan) = &module.adapt else { return Ok(Output::Patches(Vec::new())) };
    let out = |node| ValueRef { node, port: 0 };
    let mut patches = Vec::new();
    for inj in &plan.injections {
        match *inj {
            Injection::Adapter { target, down, up, add, .. } => {
                // Still before the BatchNorm, and no scale near zero in any variant.
                if g.inputs(target).first() != Some(&out(add)) || !scales_fit(g, table, target) {
                    continue;
                }
                let Some(&x) = g.inputs(add).first() else { continue };
                let bn = bn_params(g, target);
                let names =
                    |n: NodeId| [ir::join_path(&g.node(n).path, "weight"), ir::join_path(&g.node(n).path, "bias")];
                let ([wd, bd], [wu, bu]) = (names(down), names(up));
                let mut ins: Vec<&str> = vec![&wd, &bd, &wu, &bu];
                ins.extend(bn.iter().map(String::as_str));
                let shapes: Vec<(&'static str, Vec<usize>)> = [&wd, &bd, &wu, &bu]
                    .iter()
                    .map(|n| ("moved behind its BatchNorm", table.get(n).map(|t| t.shape.clone()).unwrap_or_default()))
                    .collect();
                let eps = bn_eps(g, target);
                let moved = table.derive(&ins, &shapes, |v| move_adapter(v, eps)).map_err(internal)?;
                let mut p = Patch::new("adapter_behind_batchnorm");
                p.tensors.extend([wd, bd, wu, bu].into_iter().zip(moved));
                let bn_out = out(target);
                p.replace_uses.push((bn_out, out(add)));
                p.set_inputs.extend([(target, 0, x), (down, 0, bn_out), (add, 0, bn_out)]);
                patches.push(p);
            }
            // A branch `fuse_lora` computes in its layer's kernel stays before the BatchNorm,
            // which then folds into the layer, over the sum.
            Injection::Lora { base, b, add, .. }
                if lora_mode(module, inputs, &g.node(base).path) == LoraMode::Branch
                    && super::fuse_lora::fusable(g, inj).is_none() =>
            {
                let Some(bn) = sole_batchnorm_user(g, add) else { continue };
                let wb = ir::join_path(&g.node(b).path, "weight");
                let params = bn_params(g, bn);
                let mut ins: Vec<&str> = vec![&wb];
                ins.extend(params.iter().map(String::as_str));
                let shape = table.get(&wb).map(|t| t.shape.clone()).unwrap_or_default();
                super::fold_batchnorm::check_variance(table, &params[3], g.node(bn))?;
                let eps = bn_eps(g, bn);
                let scaled = table
                    .derive_one(&ins, "moved behind its BatchNorm", shape, |v| scale_lora_b(v, eps))
                    .map_err(internal)?;
                let mut p = Patch::new("lora_behind_batchnorm");
                p.tensors.push((wb, scaled));
                let bn_out = out(bn);
                p.replace_uses.push((bn_out, out(add)));
                p.set_inputs.extend([(bn, 0, out(base)), (add, 0, bn_out)]);
                patches.push(p);
            }
            Injection::Lora { .. } => {}
        }
    }
    Ok(Output::Patches(patches))
}

/// The names of a BatchNorm's `weight`, `bias`, `running_mean`, `running_var` tensors.
fn bn_params(g: &Graph, bn: NodeId) -> [String; 4] {
    ["weight", "bias", "running_mean", "running_var"].map(|s| ir::join_path(&g.node(bn).path, s))
}

fn bn_eps(g: &Graph, bn: NodeId) -> f64 {
    match &g.node(bn).op {
        Op::BatchNorm(b) => b.eps,
        _ => 0.0,
    }
}

/// Whether `target` is a BatchNorm whose scale is at least 1e-3 in magnitude (and finite)
/// for every channel, in the base and in every variant.
fn scales_fit(g: &Graph, table: &TensorTable, target: NodeId) -> bool {
    if !matches!(g.node(target).op, Op::BatchNorm(_)) {
        return false;
    }
    let [w, b, m, v] = bn_params(g, target);
    let eps = bn_eps(g, target);
    (0..=table.variant_count()).all(|k| {
        let get = |n: &str| table.value(n, k);
        let (Some(w), Some(b), Some(m), Some(v)) = (get(&w), get(&b), get(&m), get(&v)) else { return false };
        batchnorm_affine(w, b, m, v, eps, None).0.iter().all(|s| s.abs() >= 1e-3 && s.is_finite())
    })
}

/// The BatchNorm that is the only use of a LoRA sum and reads it, if any.
fn sole_batchnorm_user(g: &Graph, add: NodeId) -> Option<NodeId> {
    let users = g.users(add);
    let only = users.len() == 1 && !g.outputs.iter().any(|o| o.value.node == add);
    let bn = only.then(|| users[0]).filter(|&u| matches!(g.node(u).op, Op::BatchNorm(_)))?;
    (g.inputs(bn).first() == Some(&ValueRef { node: add, port: 0 })).then_some(bn)
}

/// The adapter's weights behind the BatchNorm: inputs `[down.w, down.b, up.w, up.b,
/// gamma, beta, mean, var]` under one variant; outputs `[down.w, down.b, up.w, up.b]`.
fn move_adapter(v: &[&[f32]], eps: f64) -> Vec<Vec<f32>> {
    let (wd, bd, wu, bu) = (v[0], v[1], v[2], v[3]);
    let (s, t) = batchnorm_affine(v[4], v[5], v[6], v[7], eps, None);
    let c = s.len();
    let mid = bd.len();
    let mut wd2 = vec![0.0f32; wd.len()];
    let mut bd2 = vec![0.0f32; mid];
    for o in 0..mid {
        let mut shift = bd[o] as f64;
        for ci in 0..c {
            let w = wd[o * c + ci] as f64 / s[ci];
            wd2[o * c + ci] = w as f32;
            shift -= w * t[ci];
        }
        bd2[o] = shift as f32;
    }
    let wu2: Vec<f32> = wu.iter().enumerate().map(|(i, &w)| (w as f64 * s[i / mid]) as f32).collect();
    let bu2: Vec<f32> = bu.iter().zip(&s).map(|(&b, s)| (b as f64 * s) as f32).collect();
    vec![wd2, bd2, wu2, bu2]
}

/// `s B` per output channel: inputs `[B, gamma, beta, mean, var]`.
fn scale_lora_b(v: &[&[f32]], eps: f64) -> Vec<f32> {
    let (s, _) = batchnorm_affine(v[1], v[2], v[3], v[4], eps, None);
    let rank = v[0].len() / s.len().max(1);
    v[0].iter().enumerate().map(|(i, &w)| (w as f64 * s[i / rank]) as f32).collect()
}
