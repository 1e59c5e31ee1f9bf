//! `merge_lora`: merges each LoRA branch into its layer's weight, per variant (rule
//! `merge_lora`): `W + scale * B A`, PEFT's merge (for a conv, `A` is
//! `[rank, in * kh * kw]` and `B` is `[out, rank]`). The branch's nodes leave the graph, so
//! an adapted plan runs the base model's schedule; each variant stores the merged weight
//! of every layer its LoRA changes.
//!
//! Merges only the layers `choose_strategy` marked merge (every layer with `--lora merge`,
//! none with `--lora branch`). Does nothing without LoRA. Assumes `commute_adapters` ran
//! (it moves only branches that stay).

use readi_grammar::diag::Diagnostics;

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch, internal};
use crate::adapt::Injection;
use crate::ir::{self, ValueRef};
use crate::module::Module;
use crate::passes::LoraMode;
use crate::passes::choose_strategy::lora_mode;

pub fn run(module: &Module, inputs: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let Some(plan) = &module.adapt else { return Ok(Output::Patches(Vec::new())) };
    let mut patches = Vec::new();
    for inj in &plan.injections {
        let Injection::Lora { base, a, b, add, factor, .. } = *inj else { continue };
        if lora_mode(module, inputs, &g.node(base).path) != LoraMode::Merge {
            continue;
        }
        let name = |n| ir::join_path(&g.node(n).path, "weight");
        let (w, wa, wb) = (name(base), name(a), name(b));
        let rank = g.node(a).params.first().and_then(|s| s.shape.first()).copied().unwrap_or(1).max(1) as usize;
        let shape = table.get(&w).map(|t| t.shape.clone()).unwrap_or_default();
        let merged =
            table.derive_one(&[&w, &wa, &wb], "merged into", shape, |v| merge(v, rank, factor)).map_err(internal)?;
        let mut p = Patch::new("merge_lora");
        p.tensors.push((w, merged));
        p.replace_uses.push((ValueRef { node: add, port: 0 }, ValueRef { node: base, port: 0 }));
        p.remove.extend(inj.nodes());
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// `W + factor * B A` from `[W, A, B]`, accumulated in f64: the runtime's merge
/// (`readi_runtime::kernels::merge::merge_lora`), which a session merging a layer on
/// switch runs too.
fn merge(v: &[&[f32]], rank: usize, factor: f64) -> Vec<f32> {
    let mut out = vec![0.0f32; v[0].len()];
    readi_runtime::kernels::merge::merge_lora(v[0], v[1], v[2], rank, factor, &mut out);
    out
}

/// `B A` in f64, row-major `[rows, cols]`, from `A` `[rank, cols]` and `B` `[rows, rank]`
/// flattened: a LoRA update before its scale (the meld weighs each part's).
pub(super) fn lora_delta(a: &[f32], b: &[f32], rank: usize) -> Vec<f64> {
    let cols = a.len() / rank;
    let rows = b.len() / rank;
    let mut out = vec![0.0f64; rows * cols];
    for o in 0..rows {
        for c in 0..cols {
            out[o * cols + c] = (0..rank).map(|r| b[o * rank + r] as f64 * a[r * cols + c] as f64).sum();
        }
    }
    out
}
