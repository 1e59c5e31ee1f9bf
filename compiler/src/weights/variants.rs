//! Variant sources: each variant's parameters as its files give them, and what the
//! variants own.
//!
//! A variant owns exactly what the rules make per-variant: the slots `tune` rules select
//! (BatchNorm affine and running statistics, head weights, ...) and every slot
//! `inject_adapt` added (LoRA matrices, adapter convs). `bind_variants` checks each
//! source against this and binds it into the tensor table.

use std::collections::BTreeMap;

use readi_grammar::ast::DType;
use readi_plan::VariantKey;

use super::WeightSet;
use crate::adapt::RuleKind;
use crate::ir::{NodeId, ParamSlot, SlotKind};
use crate::module::Module;

/// One variant's parameters, by PyTorch name, and where they came from (for messages).
#[derive(Clone, Debug, Default)]
pub struct VariantSource {
    pub key: String,
    pub weights: WeightSet,
    pub origin: String,
}

/// A parameter the variants own.
#[derive(Clone, Debug, PartialEq)]
pub struct Owned {
    pub shape: Vec<usize>,
    /// Added by a rule (zero in the base) rather than an existing, tuned parameter.
    pub added: bool,
    pub node: NodeId,
}

/// Every parameter a variant owns, by full name.
pub fn owned_params(module: &Module) -> BTreeMap<String, Owned> {
    let g = &module.graph;
    let mut owned = BTreeMap::new();
    let Some(plan) = &module.adapt else { return owned };
    let mut add = |node: NodeId, slot: &ParamSlot| {
        if slot.dtype == DType::F32 {
            let shape = slot.shape.iter().map(|&d| d as usize).collect();
            let added = slot.kind == SlotKind::Added;
            owned.insert(g.node(node).param_name(slot), Owned { shape, added, node });
        }
    };
    for r in plan.rules.iter().filter(|r| r.kind == RuleKind::Tune) {
        for t in &r.targets {
            for slot in g.node(t.node).params.iter().filter(|s| t.slots.contains(&s.name)) {
                add(t.node, slot);
            }
        }
    }
    for inj in &plan.injections {
        for n in inj.nodes() {
            for slot in &g.node(n).params {
                add(n, slot);
            }
        }
    }
    owned
}

/// The declared key a written key names: `fog=0.030` names `fog=0.03`; a melded key names
/// the meld of its parts in any order, each of them declared (`gamma=0.5+fog=0.06` names
/// `fog=0.06+gamma=0.5`).
pub fn canonical_key(key: &str, declared: &[VariantKey]) -> Option<VariantKey> {
    let k = VariantKey::parse(key).ok()?;
    let ok = !k.is_base() && k.part_keys().all(|p| declared.contains(&p));
    ok.then_some(k)
}
