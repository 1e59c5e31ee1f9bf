//! Variant sources: each variant's parameters as its files give them, and what the
//! variants own.
//!
//! A variant owns exactly what the rules make per-variant: the slots `tune` rules select
//! (BatchNorm affine and running statistics, head weights, ...) and every slot
//! `inject_adapt` added (LoRA matrices, adapter convs), each within the scope of its
//! rule's section ([`Owned::is_owned_by`]: `adapt camera { ... }` is owned by the camera
//! variants only). `bind_variants` checks each source against this and binds it into the
//! tensor table.

use std::collections::BTreeMap;

use readi_grammar::ast::DType;
use readi_plan::VariantKey;

use super::WeightSet;
use crate::adapt::{RuleKind, Scope};
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
    /// The scopes of the rules that make it per-variant (one per rule; two `tune` rules
    /// of different sections may claim one parameter). A variant owns it when one of them
    /// covers its key.
    pub scopes: Vec<Scope>,
}

impl Owned {
    /// Whether the variant `key` owns this parameter (a meld: whether one of its parts does).
    pub fn is_owned_by(&self, key: &VariantKey) -> bool {
        self.scopes.iter().any(|s| s.covers(key))
    }

    /// What the plan records of its owners ([`readi_plan::format::ParamSpec::owned_by`]):
    /// empty for every variant (some unscoped rule owns it), otherwise every scope name
    /// of its rules' sections, once each. Equivalent to [`Owned::is_owned_by`]: a scope
    /// covers a key when one of its names does.
    pub fn recorded_scopes(&self) -> Vec<String> {
        if self.scopes.iter().any(Scope::is_all) {
            return Vec::new();
        }
        let mut names: Vec<String> = Vec::new();
        for n in self.scopes.iter().flat_map(|s| &s.names) {
            if !names.contains(n) {
                names.push(n.clone());
            }
        }
        names
    }

    /// The scopes that own it, for messages: `camera`, `every variant`.
    pub fn scope_label(&self) -> String {
        let mut names: Vec<String> = self.scopes.iter().map(Scope::label).collect();
        names.dedup();
        names.join("; ")
    }
}

/// What the variant `key` owns, of `owned` (every parameter some variant owns).
pub fn owned_by<'a>(
    owned: &'a BTreeMap<String, Owned>,
    key: &'a VariantKey,
) -> impl Iterator<Item = (&'a String, &'a Owned)> + 'a {
    owned.iter().filter(move |(_, o)| o.is_owned_by(key))
}

/// Every parameter a variant owns, by full name.
pub fn owned_params(module: &Module) -> BTreeMap<String, Owned> {
    let g = &module.graph;
    let mut owned = BTreeMap::new();
    let Some(plan) = &module.adapt else { return owned };
    let mut add = |node: NodeId, slot: &ParamSlot, scope: &Scope| {
        if slot.dtype == DType::F32 {
            let shape = slot.shape.iter().map(|&d| d as usize).collect();
            let added = slot.kind == SlotKind::Added;
            let o: &mut Owned =
                owned.entry(g.node(node).param_name(slot)).or_insert(Owned { shape, added, node, scopes: Vec::new() });
            if !o.scopes.contains(scope) {
                o.scopes.push(scope.clone());
            }
        }
    };
    for r in plan.rules.iter().filter(|r| r.kind == RuleKind::Tune) {
        for t in &r.targets {
            for slot in g.node(t.node).params.iter().filter(|s| t.slots.contains(&s.name)) {
                add(t.node, slot, &r.scope);
            }
        }
    }
    for inj in &plan.injections {
        let Some(rule) = plan.rules.get(inj.rule()) else { continue };
        for n in inj.nodes() {
            for slot in &g.node(n).params {
                add(n, slot, &rule.scope);
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
