//! `prune`: zeroes the small values of the shared weights (rule `prune`), as the paper
//! does to the frozen layers (t-READi: "we reset all parameters whose absolute value is
//! less than 1e-3").
//!
//! A `prune below=T [in SEL]` rule selects conv2d and linear layers (all of them without
//! `in`); of each, only the `weight` is pruned, and only if it is *shared*: no variant
//! owns it (not in [`TensorTable::owned`]: not tuned, not added by LoRA or an adapter) and
//! no variant replaces it (a melded LoRA layer's weight). Biases, BatchNorm parameters and
//! statistics are never pruned. Every value with `|w| < T` becomes 0 in the base value;
//! a weight two rules select takes the larger threshold. Each pruned weight is one patch
//! replacing the tensor, so every later pass (folding, packing) sees the zeros.
//!
//! A rule whose layers are all variant-owned prunes nothing: a warning at the rule. The
//! counts ([`report`]) are what `readi compile` prints. Does nothing without a `prune`
//! rule, or when no shared weight has a non-zero value below its threshold (so a second
//! round finds nothing). Changes nothing in the graph. Assumes `meld` ran.

use std::collections::BTreeMap;

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch};
use crate::adapt::RuleKind;
use crate::ir::NodeId;
use crate::module::Module;
use crate::weights::tensors::{Data, Tensor, TensorTable};

pub fn run(module: &Module, _: &BackendInputs<'_>, warnings: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let (layers, idle) = select(module, table);
    for span in idle {
        let d = Diagnostic::warning(Code::BadSelector, "this `prune` rule selects only weights the variants own")
            .with_primary(span, "prunes nothing")
            .with_note("`prune` changes only shared weights: not tuned, not added, not replaced by a variant");
        // The driver asks again until nothing changes: say it once.
        if !warnings.0.contains(&d) {
            warnings.push(d);
        }
    }
    let mut patches = Vec::new();
    for l in layers.into_iter().filter(|l| l.zeroed > 0) {
        let Some(t) = table.get(&l.tensor) else { continue };
        let base: Vec<f32> = t.base.iter().map(|&x| if below(x, l.below) { 0.0 } else { x }).collect();
        let mut p = Patch::new("prune");
        p.tensors.push((l.tensor, Tensor { base: Data::from(base), ..t.clone() }));
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// One shared weight a `prune` rule selects.
#[derive(Clone, Debug, PartialEq)]
pub struct PrunedLayer {
    /// The layer's path.
    pub layer: String,
    pub tensor: String,
    /// The threshold: the largest of the rules that select it.
    pub below: f64,
    /// Non-zero values of magnitude below the threshold: the values pruning zeroes.
    pub zeroed: u64,
    /// Elements of the weight.
    pub total: u64,
}

/// What the module's `prune` rules select and zero, from the table's current values
/// (before `prune` ran: what it will zero; after: nothing is left to zero), in layer
/// order. Empty without `prune` rules.
pub fn report(module: &Module, table: &TensorTable) -> Vec<PrunedLayer> {
    select(module, table).0
}

/// The shared weights the `prune` rules select: how many, their elements, and how many
/// of those are zero (after the `prune` pass, at least the values it zeroed). `None`
/// without `prune` rules.
pub fn zeros(module: &Module, table: &TensorTable) -> Option<(usize, u64, u64)> {
    module.adapt.as_ref()?.rules.iter().find(|r| matches!(r.kind, RuleKind::Prune { .. }))?;
    let layers = report(module, table);
    let total = layers.iter().map(|l| l.total).sum();
    let zero = layers
        .iter()
        .filter_map(|l| table.get(&l.tensor))
        .map(|t| t.base.iter().filter(|x| **x == 0.0).count() as u64)
        .sum();
    Some((layers.len(), total, zero))
}

/// The selected shared weights, and the spans of the rules that select none.
fn select(module: &Module, table: &TensorTable) -> (Vec<PrunedLayer>, Vec<readi_grammar::diag::Span>) {
    let g = &module.graph;
    let mut by_tensor: BTreeMap<String, (NodeId, PrunedLayer)> = BTreeMap::new();
    let mut idle = Vec::new();
    for r in module.adapt.iter().flat_map(|p| &p.rules) {
        let RuleKind::Prune { below } = r.kind else { continue };
        let mut any = false;
        for t in &r.targets {
            let node = g.node(t.node);
            let Some(slot) = node.params.iter().find(|s| s.name == "weight") else { continue };
            let name = node.param_name(slot);
            let Some(tensor) = table.get(&name) else { continue };
            if table.owned.contains_key(&name) || tensor.varies() {
                continue;
            }
            any = true;
            let (_, e) = by_tensor.entry(name.clone()).or_insert_with(|| {
                let total = tensor.numel() as u64;
                (t.node, PrunedLayer { layer: node.path.clone(), tensor: name, below, zeroed: 0, total })
            });
            e.below = e.below.max(below);
        }
        if !any {
            idle.push(r.span);
        }
    }
    let mut layers: Vec<(NodeId, PrunedLayer)> = by_tensor.into_values().collect();
    for (_, l) in &mut layers {
        let t = table.get(&l.tensor);
        l.zeroed = t.map_or(0, |t| t.base.iter().filter(|&&x| x != 0.0 && below(x, l.below)).count()) as u64;
    }
    layers.sort_by_key(|(n, _)| *n);
    (layers.into_iter().map(|(_, l)| l).collect(), idle)
}

/// Whether pruning at `threshold` zeroes `x`: `|x| < threshold`, compared in f64.
fn below(x: f32, threshold: f64) -> bool {
    (x.abs() as f64) < threshold
}
