//! The adaptation plan: the rules of the `adapt` section bound to the layers they
//! select (`resolve_adapt`), and the nodes `inject_adapt` added for them. A side table of
//! the module ([`crate::module::Module::adapt`]); the back end's passes read the
//! injections to drop, move or merge them.

use std::collections::HashMap;

use readi_grammar::ast::DType;
use readi_grammar::diag::Span;
use readi_plan::VariantKey;
use readi_plan::key::KeyPart;

use crate::ir::{Activation, Graph, NodeId};

/// Every rule of the `adapt` section, bound to layers.
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptPlan {
    pub rules: Vec<ResolvedRule>,
    /// The layers `inject_adapt` added, one entry per LoRA or adapter target; empty before
    /// that pass.
    pub injections: Vec<Injection>,
}

/// The nodes `inject_adapt` added for one target. `rule` indexes [`AdaptPlan::rules`].
#[derive(Clone, Debug, PartialEq)]
pub enum Injection {
    /// `base` now feeds `add = base + scale(lora_B(lora_A(x)))`; `factor` is the scale.
    Lora { rule: usize, base: NodeId, a: NodeId, b: NodeId, scale: NodeId, add: NodeId, factor: f64 },
    /// `target` now reads `add = x + up(act(down(x)))`.
    Adapter { rule: usize, target: NodeId, down: NodeId, act: NodeId, up: NodeId, add: NodeId },
}

impl Injection {
    /// The layer the injection adapts: the LoRA's base layer, the adapter's target.
    pub fn anchor(&self) -> NodeId {
        match *self {
            Injection::Lora { base, .. } => base,
            Injection::Adapter { target, .. } => target,
        }
    }

    /// The index of the rule it was injected for, in [`AdaptPlan::rules`].
    pub fn rule(&self) -> usize {
        match *self {
            Injection::Lora { rule, .. } | Injection::Adapter { rule, .. } => rule,
        }
    }

    /// Every node the injection added.
    pub fn nodes(&self) -> [NodeId; 4] {
        match *self {
            Injection::Lora { a, b, scale, add, .. } => [a, b, scale, add],
            Injection::Adapter { down, act, up, add, .. } => [down, act, up, add],
        }
    }
}

/// One rule and what it selected.
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedRule {
    /// The rule as written (canonical form).
    pub text: String,
    pub span: Span,
    pub kind: RuleKind,
    pub targets: Vec<Target>,
    /// The variants that own what the rule makes per-variant (its section's scope).
    pub scope: Scope,
}

/// The variants a rule's parameters belong to: every variant (an unscoped `adapt { }`
/// section), or those a scoped section names (`adapt camera, missing=lidar { }`).
///
/// Resolved against the spec when the rules are: a modality stands for every axis on it,
/// `missing` for every modality, so whether a key is covered needs nothing but the key.
/// A melded key is covered when one of its parts is (a meld owns the union of what its
/// parts own); the base key is never covered.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Scope {
    /// The scopes as written (`camera`, `missing=lidar`); empty for every variant.
    pub names: Vec<String>,
    /// The axes whose variants it covers.
    pub axes: Vec<String>,
    /// The modalities whose missing-modality variant it covers.
    pub missing: Vec<String>,
}

impl Scope {
    /// Every variant (an unscoped section).
    pub fn all() -> Scope {
        Scope::default()
    }

    /// Whether this is an unscoped section's scope.
    pub fn is_all(&self) -> bool {
        self.names.is_empty()
    }

    /// Whether the variant `key` owns what this scope's rules make per-variant.
    pub fn covers(&self, key: &VariantKey) -> bool {
        if self.is_all() {
            return !key.is_base();
        }
        key.parts().iter().any(|p| match p {
            KeyPart::Level { axis, .. } => self.axes.contains(axis),
            KeyPart::Missing { modality } => self.missing.contains(modality),
        })
    }

    /// The scope for messages: `camera, missing=lidar`, or `every variant`.
    pub fn label(&self) -> String {
        if self.is_all() { "every variant".to_string() } else { self.names.join(", ") }
    }
}

/// What a rule does to each target.
#[derive(Clone, Debug, PartialEq)]
pub enum RuleKind {
    Tune,
    Lora {
        rank: i64,
        alpha: f64,
        rslora: bool,
    },
    Adapter {
        squeeze: i64,
        act: Activation,
    },
    /// `prune below=T`: the targets' shared weights lose the values of magnitude below
    /// `T` (the `prune` pass); the rule owns nothing.
    Prune {
        below: f64,
    },
}

impl RuleKind {
    /// LoRA's scale: `alpha / rank`, or `alpha / sqrt(rank)` with rsLoRA.
    pub fn lora_scale(&self) -> Option<f64> {
        match self {
            RuleKind::Lora { rank, alpha, rslora } => {
                Some(if *rslora { alpha / (*rank as f64).sqrt() } else { alpha / *rank as f64 })
            }
            _ => None,
        }
    }
}

/// One layer a rule applies to.
#[derive(Clone, Debug, PartialEq)]
pub struct Target {
    pub node: NodeId,
    /// `tune`: the slots made per-variant.
    pub slots: Vec<&'static str>,
    /// Existing elements the variant stores (tuned slots).
    pub tuned: u64,
    /// New elements the variant adds (LoRA matrices, adapter weights).
    pub added: u64,
}

impl AdaptPlan {
    /// Forgets removed nodes: the targets on them and the injections that contain them
    /// (a back-end pass that drops or merges a branch removes its nodes).
    pub fn forget(&mut self, removed: &[NodeId]) {
        for r in &mut self.rules {
            r.targets.retain(|t| !removed.contains(&t.node));
        }
        self.injections
            .retain(|inj| !removed.contains(&inj.anchor()) && inj.nodes().iter().all(|n| !removed.contains(n)));
    }

    /// Existing parameter elements tuned per variant (each f32 slot counted once), over
    /// every scope: what the variants own together.
    pub fn tuned_elements(&self, graph: &Graph) -> u64 {
        self.tuned_elements_where(graph, |_| true)
    }

    /// New parameter elements added, over every scope.
    pub fn added_elements(&self) -> u64 {
        self.added_elements_where(|_| true)
    }

    /// What variant `key` owns: existing elements tuned and elements added by the rules
    /// whose scope covers it (the base owns nothing).
    pub fn budget(&self, graph: &Graph, key: &VariantKey) -> (u64, u64) {
        let covers = |s: &Scope| s.covers(key);
        (self.tuned_elements_where(graph, covers), self.added_elements_where(covers))
    }

    /// Whether some rule is in a scoped section.
    pub fn is_scoped(&self) -> bool {
        self.rules.iter().any(|r| !r.scope.is_all())
    }

    /// Existing elements tuned by the rules whose scope `keep` accepts, each slot once.
    pub fn tuned_elements_where(&self, graph: &Graph, keep: impl Fn(&Scope) -> bool) -> u64 {
        let mut seen: HashMap<(NodeId, &str), u64> = HashMap::new();
        for r in self.rules.iter().filter(|r| keep(&r.scope)) {
            for t in &r.targets {
                let node = graph.node(t.node);
                for s in &t.slots {
                    // num_batches_tracked (an i64 counter) is bookkeeping, not a parameter.
                    if let Some(slot) = node.params.iter().find(|p| p.name == *s && p.dtype == DType::F32) {
                        seen.insert((t.node, s), slot.numel());
                    }
                }
            }
        }
        seen.values().sum()
    }

    /// New elements added by the rules whose scope `keep` accepts.
    pub fn added_elements_where(&self, keep: impl Fn(&Scope) -> bool) -> u64 {
        self.rules.iter().filter(|r| keep(&r.scope)).flat_map(|r| &r.targets).map(|t| t.added).sum()
    }
}
