//! `resolve_adapt`: binds the rules of the `adapt` section to the layers they select.
//!
//! Changes: nothing in the graph; produces an [`AdaptPlan`] side table: for each rule,
//! the layers it applies to, which parameters it makes per-variant (`tune`), how many
//! parameters it adds (`lora`, `adapter`), and which variants own them: every variant for
//! an unscoped section, those its scope names for `adapt camera { ... }` ([`Scope`]). Injecting the LoRA branches and adapters into
//! the graph is a later pass; this one fixes *what* each variant owns.
//!
//! Checks, each an error naming the rule:
//! * a selector that selects nothing, or only layers a rule cannot apply to
//!   (`lora` needs linear or conv2d layers; an adapter needs a 4-D input with known
//!   channels and spatial sizes);
//! * unknown op kinds, unknown or bad options (`rank=0`, `act=tanhh`);
//! * a section scope that is no modality of an input, no axis, `missing` nor
//!   `missing=<modality>` (a warning when it covers no declared variant);
//! * two rules that claim one parameter in conflicting ways (LoRA on a weight another
//!   rule tunes; two LoRA branches or two adapters at one layer), showing both rules.
//!   Scopes do not make conflicting rules compatible (there is one graph for all the
//!   variants); two `tune` rules in different scopes on one parameter are fine.
//!
//! Parameter accounting (what a variant stores beyond the base):
//! * `tune`: every selected slot (weights, biases, BatchNorm running statistics);
//! * `lora` on `linear(in, out)`: `rank * (in + out)`; on `conv2d(in, out, k)`:
//!   `rank * in * kh * kw + out * rank` (PEFT's `lora_A` conv and 1x1 `lora_B` conv);
//! * `adapter` with squeeze `r` on `C` channels: a 1x1 conv `C -> C/r` and a 1x1 conv
//!   `C/r -> C`, both with bias: `2 * C * C/r + C/r + C` (two linears on `[N, C]` rows).

use std::collections::{HashMap, HashSet};

use readi_grammar::ast::{
    AdaptKind, AdaptSection, OptionValue, Pattern, RuleOption, SelItem, Selector, SourceFile, VariantDecl,
};
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, Span, suggest};

pub use crate::adapt::{AdaptPlan, Injection, ResolvedRule, RuleKind, Scope, Target};
use crate::ir::{Activation, Graph, NodeId, Op, ScopeKind};
use crate::select::Matcher;
use readi_plan::key::MISSING_AXIS;

/// Whether `word` names an op kind a selector may use (a builtin op, not an alias).
fn is_op_kind(word: &str) -> bool {
    crate::ops::op_kinds().any(|k| k == word)
}

/// Default LoRA rank (the paper's `k`).
pub const DEFAULT_RANK: i64 = 4;
/// Default LoRA alpha (PEFT's `lora_alpha` default).
pub const DEFAULT_ALPHA: f64 = 8.0;
/// Default adapter squeeze ratio (the paper's `r`).
pub const DEFAULT_SQUEEZE: i64 = 2;

/// Resolves the rules of every `adapt` section of the file, in source order.
pub fn run(graph: &Graph, sections: &[&AdaptSection], ast: &SourceFile, diags: &mut Diagnostics) -> AdaptPlan {
    let blocks: Vec<&str> = ast.blocks().map(|b| b.name.name.as_str()).collect();
    let cx = Cx { graph, blocks };
    let names = ScopeNames::of(graph, ast);
    let mut rules = Vec::new();
    for section in sections {
        let scope = names.resolve(section, diags);
        for rule in &section.rules {
            let text = readi_grammar::ast_print::adapt_rule(rule);
            let resolved = match &rule.kind {
                AdaptKind::Tune { selector } => cx.tune(selector, diags),
                AdaptKind::Lora { options, selector } => cx.lora(options, selector, diags),
                AdaptKind::Adapter { options, scopes, before } => cx.adapter(options, scopes, before, diags),
                AdaptKind::Prune { options, selector } => cx.prune(options, selector.as_ref(), diags),
            };
            if matches!(rule.kind, AdaptKind::Prune { .. })
                && let Some(scope) = scope.as_ref().filter(|s| !s.is_all())
            {
                // Pruning changes the shared weights, which every variant reads.
                diags.push(
                    Diagnostic::error(Code::BadSelector, "`prune` cannot be scoped to conditions")
                        .with_primary(rule.span, format!("in a section scoped to {}", scope.names.join(", ")))
                        .with_note("pruning changes the shared weights every variant reads; put it in `adapt { ... }`"),
                );
                continue;
            }
            if let (Some((kind, targets)), Some(scope)) = (resolved, scope.as_ref()) {
                rules.push(ResolvedRule { text, span: rule.span, kind, targets, scope: scope.clone() });
            }
        }
    }
    check_conflicts(graph, &rules, diags);
    AdaptPlan { rules, injections: Vec::new() }
}

/// What a section's scope may name: the modalities of the inputs, the axes of the
/// variants section (with their modality), and the modalities with a missing-modality
/// variant (`missing m: variant`).
struct ScopeNames {
    modalities: Vec<String>,
    axes: Vec<(String, String)>,
    missing_variants: Vec<String>,
    has_variants: bool,
}

impl ScopeNames {
    fn of(graph: &Graph, ast: &SourceFile) -> ScopeNames {
        let mut modalities: Vec<String> = Vec::new();
        for n in graph.input_nodes() {
            if let Op::Input(a) = &graph.node(n).op
                && let Some(m) = &a.modality
                && !modalities.contains(m)
            {
                modalities.push(m.clone());
            }
        }
        let (mut axes, mut missing_variants) = (Vec::new(), Vec::new());
        let mut has_variants = false;
        for v in ast.variant_sections() {
            has_variants = true;
            for d in &v.decls {
                match d {
                    VariantDecl::Axis { name, modality, .. } => axes.push((name.name.clone(), modality.name.clone())),
                    VariantDecl::Missing { modality, policy, .. } if policy.name == "variant" => {
                        missing_variants.push(modality.name.clone())
                    }
                    _ => {}
                }
            }
        }
        ScopeNames { modalities, axes, missing_variants, has_variants }
    }

    /// Every name a scope may be, for messages.
    fn known(&self) -> Vec<String> {
        let mut out: Vec<String> = self.modalities.clone();
        out.extend(self.axes.iter().map(|a| a.0.clone()).filter(|a| !self.modalities.contains(a)));
        out.push(MISSING_AXIS.to_string());
        out.extend(self.modalities.iter().map(|m| format!("{MISSING_AXIS}={m}")));
        out
    }

    /// The section's scope, or `None` (reported) when it names something the spec does not
    /// have. A scope that covers no declared variant is a warning.
    fn resolve(&self, section: &AdaptSection, diags: &mut Diagnostics) -> Option<Scope> {
        let mut scope = Scope::all();
        let mut ok = true;
        for sc in &section.scopes {
            let text = sc.text();
            let (axes, missing): (Vec<String>, Vec<String>) = match &sc.value {
                None if sc.name.name == MISSING_AXIS => (vec![], self.modalities.clone()),
                None => {
                    let name = sc.name.name.as_str();
                    let axes: Vec<String> =
                        self.axes.iter().filter(|(a, m)| a == name || m == name).map(|a| a.0.clone()).collect();
                    if axes.is_empty() && !self.modalities.iter().any(|m| m == name) {
                        diags.push(self.unknown(&sc.name.name, sc.span, "no modality or axis of this name"));
                        ok = false;
                        continue;
                    }
                    (axes, vec![])
                }
                Some(v) if sc.name.name == MISSING_AXIS => {
                    if !self.modalities.contains(&v.name) {
                        diags.push(self.unknown(&text, v.span, "no input has this modality"));
                        ok = false;
                        continue;
                    }
                    (vec![], vec![v.name.clone()])
                }
                Some(_) => {
                    diags.push(self.unknown(&text, sc.span, "only `missing=<modality>` takes a value"));
                    ok = false;
                    continue;
                }
            };
            let covers_some = !axes.is_empty() || missing.iter().any(|m| self.missing_variants.contains(m));
            if !covers_some && self.has_variants {
                diags.push(
                    Diagnostic::warning(Code::BadVariant, format!("scope `{text}` covers no declared variant"))
                        .with_primary(sc.span, "no variant has this scope")
                        .with_note("the rules of this section are injected, but no variant owns their parameters"),
                );
            }
            scope.names.push(text);
            for a in axes {
                if !scope.axes.contains(&a) {
                    scope.axes.push(a);
                }
            }
            for m in missing {
                if !scope.missing.contains(&m) {
                    scope.missing.push(m);
                }
            }
        }
        ok.then_some(scope)
    }

    fn unknown(&self, text: &str, span: Span, label: &str) -> Diagnostic {
        let known = self.known();
        let mut d = Diagnostic::error(Code::UnknownName, format!("unknown adaptation scope `{text}`"))
            .with_primary(span, label.to_string());
        if let Some(s) = suggest(text, known.iter().map(String::as_str)) {
            d = d.with_note(format!("did you mean `{s}`?"));
        }
        d.with_note(format!(
            "a scope is a modality, an axis or a missing modality; this spec has: {}",
            known.join(", ")
        ))
    }
}

struct Cx<'g> {
    graph: &'g Graph,
    blocks: Vec<&'g str>,
}

/// A selected layer: the whole node, or only some of its slots.
#[derive(Clone, Debug, PartialEq)]
struct Selected {
    node: NodeId,
    /// `None`: every slot.
    slots: Option<Vec<&'static str>>,
}

impl Cx<'_> {
    /// Resolves a selector to layers, reporting items that select nothing.
    fn select(&self, selector: &Selector, diags: &mut Diagnostics) -> Option<Vec<Selected>> {
        let mut out: Vec<Selected> = Vec::new();
        // Where each node is in `out`: items may select a node again.
        let mut at: HashMap<NodeId, usize> = HashMap::new();
        let mut ok = true;
        for item in &selector.items {
            match self.select_item(item) {
                Ok(found) if found.is_empty() => {
                    ok = false;
                    diags.push(self.nothing_selected(item));
                }
                Ok(found) => {
                    for s in found {
                        match at.get(&s.node) {
                            Some(&i) => match (&mut out[i].slots, s.slots) {
                                (Some(a), Some(b)) => {
                                    for x in b {
                                        if !a.contains(&x) {
                                            a.push(x);
                                        }
                                    }
                                }
                                (slots, _) => *slots = None,
                            },
                            None => {
                                at.insert(s.node, out.len());
                                out.push(s);
                            }
                        }
                    }
                }
                Err(d) => {
                    ok = false;
                    diags.push(d);
                }
            }
        }
        ok.then_some(out)
    }

    fn nothing_selected(&self, item: &SelItem) -> Diagnostic {
        let mut d = Diagnostic::error(Code::BadSelector, "this selector matches no layer")
            .with_primary(item.span(), "selects nothing");
        if let SelItem::Pattern(p) = item
            && let Some(first) = p.segments.first()
            && let readi_grammar::ast::PatternSeg::Word(w) = first
        {
            let tops: Vec<&str> =
                self.graph.node_ids().filter_map(|n| self.graph.node(n).path.split('.').next()).collect();
            if let Some(s) = suggest(w, tops.iter().copied()) {
                d = d.with_note(format!("did you mean `{s}`?"));
            }
        }
        d
    }

    fn check_kinds(&self, kinds: &[readi_grammar::ast::Ident]) -> Result<(), Diagnostic> {
        for k in kinds {
            if !is_op_kind(&k.name) {
                let mut d = Diagnostic::error(Code::BadSelector, format!("`{}` is not an op kind", k.name))
                    .with_primary(k.span, "unknown op kind");
                if let Some(s) = suggest(&k.name, crate::ops::op_kinds()) {
                    d = d.with_note(format!("did you mean `{s}`?"));
                }
                return Err(d);
            }
        }
        Ok(())
    }

    fn select_item(&self, item: &SelItem) -> Result<Vec<Selected>, Diagnostic> {
        let g = self.graph;
        match item {
            SelItem::Pattern(p) => {
                if let Some(word) = p.as_single_word()
                    && is_op_kind(word)
                {
                    return Ok(g
                        .node_ids()
                        .filter(|&n| g.node(n).op.kind_name() == word)
                        .map(|node| Selected { node, slots: None })
                        .collect());
                }
                let m = Matcher::new(p)?;
                let mut out = Vec::new();
                for n in g.node_ids() {
                    let node = g.node(n);
                    if matches!(node.op, Op::Input(_)) {
                        continue;
                    }
                    if m.selects(&node.path) {
                        out.push(Selected { node: n, slots: None });
                        continue;
                    }
                    let slots: Vec<&'static str> =
                        node.params.iter().filter(|s| m.matches_exactly(&node.param_name(s))).map(|s| s.name).collect();
                    if !slots.is_empty() {
                        out.push(Selected { node: n, slots: Some(slots) });
                    }
                }
                Ok(out)
            }
            SelItem::KindsIn { kinds, scopes, .. } => {
                self.check_kinds(kinds)?;
                let scopes =
                    scopes.iter().map(|s| Ok((s, Matcher::new(s)?))).collect::<Result<Vec<_>, Diagnostic>>()?;
                let mut out = Vec::new();
                for n in g.node_ids() {
                    let node = g.node(n);
                    if !kinds.iter().any(|k| k.name == node.op.kind_name()) {
                        continue;
                    }
                    if scopes.iter().any(|(s, m)| self.in_scope(n, s, m)) {
                        out.push(Selected { node: n, slots: None });
                    }
                }
                Ok(out)
            }
        }
    }

    /// Whether a node lies in an instance of the named block, or under a path pattern.
    fn in_scope(&self, n: NodeId, scope: &Pattern, m: &Matcher) -> bool {
        let node = self.graph.node(n);
        match scope.as_single_word().filter(|w| self.blocks.contains(w)) {
            Some(block) => {
                self.graph.scope_chain(node.scope).any(|s| matches!(&s.kind, ScopeKind::Block(b) if b == block))
            }
            None => {
                let parent = node.path.rsplit_once('.').map(|(p, _)| p).unwrap_or("");
                m.selects(parent)
            }
        }
    }

    fn tune(&self, selector: &Selector, diags: &mut Diagnostics) -> Option<(RuleKind, Vec<Target>)> {
        let selected = self.select(selector, diags)?;
        let mut targets = Vec::new();
        for s in selected {
            let node = self.graph.node(s.node);
            let slots: Vec<&'static str> = match s.slots {
                Some(v) => v,
                None => node.params.iter().map(|p| p.name).collect(),
            };
            if slots.is_empty() {
                continue;
            }
            let tuned = node.params.iter().filter(|p| slots.contains(&p.name)).map(|p| p.numel()).sum();
            targets.push(Target { node: s.node, slots, tuned, added: 0 });
        }
        if targets.is_empty() {
            diags.push(
                Diagnostic::error(Code::BadSelector, "`tune` selects no layer with parameters")
                    .with_primary(selector.span, "nothing to tune here"),
            );
            return None;
        }
        Some((RuleKind::Tune, targets))
    }

    fn lora(
        &self,
        options: &[RuleOption],
        selector: &Selector,
        diags: &mut Diagnostics,
    ) -> Option<(RuleKind, Vec<Target>)> {
        let opts = Options::parse(options, &["rank", "alpha", "rslora"], diags)?;
        let rank = opts.int("rank", DEFAULT_RANK, 1, diags)?;
        let alpha = opts.float("alpha", DEFAULT_ALPHA, diags)?;
        let rslora = opts.flag("rslora", diags)?;
        let selected = self.select(selector, diags)?;
        let mut targets = Vec::new();
        let mut skipped: Vec<&str> = Vec::new();
        let mut ok = true;
        for s in selected {
            let node = self.graph.node(s.node);
            let (fan_in, fan_out, added) = match &node.op {
                Op::Linear(l) => {
                    let (fin, fout) = (l.linear.in_features, l.linear.out_features);
                    (fin, fout, rank * (fin + fout))
                }
                Op::Conv2d(c) if c.conv.groups == 1 => {
                    let c = &c.conv;
                    let k = c.window.kernel[0] * c.window.kernel[1];
                    (c.in_channels * k, c.out_channels, rank * c.in_channels * k + c.out_channels * rank)
                }
                Op::Conv2d(_) => {
                    diags.push(
                        Diagnostic::error(
                            Code::BadSelector,
                            format!("LoRA on grouped conv `{}` is not supported", node.path),
                        )
                        .with_primary(selector.span, "selects a grouped conv")
                        .with_secondary(node.span, "the layer"),
                    );
                    ok = false;
                    continue;
                }
                op => {
                    if op.has_params() {
                        skipped.push(op.kind_name());
                    }
                    continue;
                }
            };
            if rank > fan_in.min(fan_out) {
                diags.push(
                    Diagnostic::error(
                        Code::BadOption,
                        format!("LoRA rank {rank} exceeds the size of `{}` ({fan_in} in, {fan_out} out)", node.path),
                    )
                    .with_primary(opts.span_of("rank").unwrap_or(selector.span), "rank too large")
                    .with_secondary(node.span, "the layer"),
                );
                ok = false;
                continue;
            }
            targets.push(Target { node: s.node, slots: vec![], tuned: 0, added: added as u64 });
        }
        if ok && targets.is_empty() {
            let mut d = Diagnostic::error(Code::BadSelector, "`lora` selects no linear or conv2d layer")
                .with_primary(selector.span, "LoRA applies to linear and conv2d layers");
            if !skipped.is_empty() {
                skipped.sort_unstable();
                skipped.dedup();
                d = d.with_note(format!("it selects only {} layers", skipped.join(", ")));
            }
            diags.push(d);
            return None;
        }
        ok.then_some((RuleKind::Lora { rank, alpha, rslora }, targets))
    }

    fn adapter(
        &self,
        options: &[RuleOption],
        scopes: &[Pattern],
        before: &Pattern,
        diags: &mut Diagnostics,
    ) -> Option<(RuleKind, Vec<Target>)> {
        let opts = Options::parse(options, &["squeeze", "act"], diags)?;
        let squeeze = opts.int("squeeze", DEFAULT_SQUEEZE, 1, diags)?;
        let act = opts.activation("act", diags)?;
        let g = self.graph;
        // The scope instances: every instance of a named block, or scopes on a path.
        let mut instances = Vec::new();
        let mut ok = true;
        for sp in scopes {
            let found: Vec<usize> = match sp.as_single_word().filter(|w| self.blocks.contains(w)) {
                Some(block) => (0..g.scopes.len())
                    .filter(|&i| matches!(&g.scopes[i].kind, ScopeKind::Block(b) if b == block))
                    .collect(),
                None => {
                    let m = match Matcher::new(sp) {
                        Ok(m) => m,
                        Err(d) => {
                            diags.push(d);
                            ok = false;
                            continue;
                        }
                    };
                    (1..g.scopes.len()).filter(|&i| m.matches_exactly(&g.scopes[i].path)).collect()
                }
            };
            if found.is_empty() {
                let mut d = Diagnostic::error(Code::BadSelector, format!("`{}` matches no block instance", sp.text))
                    .with_primary(sp.span, "no instance");
                if let Some(s) = suggest(&sp.text, self.blocks.iter().copied()) {
                    d = d.with_note(format!("did you mean block `{s}`?"));
                }
                diags.push(d);
                ok = false;
            }
            instances.extend(found);
        }
        if !ok {
            return None;
        }
        let kind_target = before.as_single_word().filter(|w| is_op_kind(w));
        let before_m = match kind_target {
            Some(_) => None,
            None => match Matcher::new(before) {
                Ok(m) => Some(m),
                Err(d) => {
                    diags.push(d);
                    return None;
                }
            },
        };
        // The nodes under each path prefix, in node order: an instance's nodes are those
        // under its path, found without a scan of the graph per instance.
        let mut under: HashMap<&str, Vec<NodeId>> = HashMap::new();
        for n in g.node_ids() {
            let path = g.node(n).path.as_str();
            for (i, _) in path.match_indices('.') {
                under.entry(&path[..i]).or_default().push(n);
            }
        }
        let mut targets: Vec<Target> = Vec::new();
        let mut taken: HashSet<NodeId> = HashSet::new();
        for &inst in &instances {
            let prefix = g.scopes[inst].path.as_str();
            for &n in under.get(prefix).map(Vec::as_slice).unwrap_or_default() {
                let node = g.node(n);
                let rel = &node.path[prefix.len() + 1..];
                let hit = match (&before_m, kind_target) {
                    (Some(m), _) => m.matches_exactly(rel),
                    (None, Some(kind)) => node.op.kind_name() == kind,
                    (None, None) => false,
                };
                if !hit || taken.contains(&n) {
                    continue;
                }
                let input = g.inputs(n).first().and_then(|v| g.value_type(*v)).cloned();
                // The adapter's 1x1 convs need known channels and spatial sizes; on rows of
                // features ([N, C]: a sparse tensor's, a linear's) it is two linears.
                let fits = |t: &&crate::ir::TensorType| {
                    (t.rank() == 4 && t.known_dim(2).is_some() && t.known_dim(3).is_some()) || t.rank() == 2
                };
                let channels = input.as_ref().filter(fits).and_then(|t| t.known_dim(1));
                let Some(c) = channels else {
                    diags.push(
                        Diagnostic::error(
                            Code::BadSelector,
                            format!(
                                "an adapter needs an NCHW input with known channels and spatial sizes, or [N, C] rows, but `{}` takes {}",
                                node.path,
                                show(input.as_ref())
                            ),
                        )
                        .with_primary(before.span, "adapter target")
                        .with_secondary(node.span, "the layer"),
                    );
                    ok = false;
                    continue;
                };
                if c % squeeze != 0 {
                    diags.push(
                        Diagnostic::error(
                            Code::BadOption,
                            format!("squeeze={squeeze} does not divide the {c} channels before `{}`", node.path),
                        )
                        .with_primary(opts.span_of("squeeze").unwrap_or(before.span), "bad squeeze ratio")
                        .with_secondary(node.span, "the layer"),
                    );
                    ok = false;
                    continue;
                }
                let mid = c / squeeze;
                let added = (2 * c * mid + mid + c) as u64;
                taken.insert(n);
                targets.push(Target { node: n, slots: vec![], tuned: 0, added });
            }
        }
        if ok && targets.is_empty() {
            diags.push(
                Diagnostic::error(Code::BadSelector, format!("no layer `{}` in the selected instances", before.text))
                    .with_primary(before.span, "matches nothing inside"),
            );
            return None;
        }
        ok.then_some((RuleKind::Adapter { squeeze, act }, targets))
    }
}

impl Cx<'_> {
    /// `prune below=T [in SEL]`: the conv2d and linear layers it selects (every one
    /// without a selector). Which of their weights are shared is known once the variants
    /// are bound; the `prune` pass skips the others.
    fn prune(
        &self,
        options: &[RuleOption],
        selector: Option<&Selector>,
        diags: &mut Diagnostics,
    ) -> Option<(RuleKind, Vec<Target>)> {
        let opts = Options::parse(options, &["below"], diags)?;
        let below = opts.float("below", DEFAULT_PRUNE_BELOW, diags)?;
        let g = self.graph;
        let prunable = |n: NodeId| matches!(g.node(n).op, Op::Conv2d(_) | Op::Linear(_));
        let nodes: Vec<NodeId> = match selector {
            None => g.node_ids().filter(|&n| prunable(n)).collect(),
            Some(sel) => {
                let selected = self.select(sel, diags)?;
                let nodes: Vec<NodeId> = selected
                    .into_iter()
                    .filter(|s| prunable(s.node) && s.slots.as_ref().is_none_or(|v| v.contains(&"weight")))
                    .map(|s| s.node)
                    .collect();
                if nodes.is_empty() {
                    diags.push(
                        Diagnostic::error(Code::BadSelector, "`prune` selects no conv2d or linear weight")
                            .with_primary(sel.span, "pruning applies to conv2d and linear weights"),
                    );
                    return None;
                }
                nodes
            }
        };
        let targets = nodes.into_iter().map(|node| Target { node, slots: vec![], tuned: 0, added: 0 }).collect();
        Some((RuleKind::Prune { below }, targets))
    }
}

/// The paper's pruning threshold (t-READi: "we reset all parameters whose absolute value
/// is less than 1e-3").
pub const DEFAULT_PRUNE_BELOW: f64 = 1e-3;

fn show(t: Option<&crate::ir::TensorType>) -> String {
    t.map(|t| t.to_string()).unwrap_or_else(|| "nothing".into())
}

/// Checked rule options.
struct Options<'a> {
    opts: &'a [RuleOption],
}

impl<'a> Options<'a> {
    fn parse(opts: &'a [RuleOption], known: &[&str], diags: &mut Diagnostics) -> Option<Options<'a>> {
        let mut ok = true;
        for (i, o) in opts.iter().enumerate() {
            if !known.contains(&o.name.name.as_str()) {
                let mut d = Diagnostic::error(Code::BadOption, format!("unknown option `{}`", o.name.name))
                    .with_primary(o.name.span, "not an option of this rule");
                d = match suggest(&o.name.name, known.iter().copied()) {
                    Some(s) => d.with_note(format!("did you mean `{s}`?")),
                    None => d.with_note(format!("options: {}", known.join(", "))),
                };
                diags.push(d);
                ok = false;
            }
            if let Some(prev) = opts[..i].iter().find(|p| p.name.name == o.name.name) {
                diags.push(
                    Diagnostic::error(Code::BadOption, format!("option `{}` is given twice", o.name.name))
                        .with_primary(o.span, "again here")
                        .with_secondary(prev.span, "first here"),
                );
                ok = false;
            }
        }
        ok.then_some(Options { opts })
    }

    fn get(&self, name: &str) -> Option<&'a RuleOption> {
        self.opts.iter().find(|o| o.name.name == name)
    }

    fn span_of(&self, name: &str) -> Option<Span> {
        self.get(name).map(|o| o.span)
    }

    fn int(&self, name: &str, default: i64, min: i64, diags: &mut Diagnostics) -> Option<i64> {
        let Some(o) = self.get(name) else { return Some(default) };
        match &o.value {
            Some(OptionValue::Number(n)) if n.value.fract() == 0.0 && n.value >= min as f64 && n.value <= 1e9 => {
                Some(n.value as i64)
            }
            _ => {
                diags.push(
                    Diagnostic::error(Code::BadOption, format!("`{name}` must be an integer of at least {min}"))
                        .with_primary(o.span, "bad value"),
                );
                None
            }
        }
    }

    fn float(&self, name: &str, default: f64, diags: &mut Diagnostics) -> Option<f64> {
        let Some(o) = self.get(name) else { return Some(default) };
        match &o.value {
            Some(OptionValue::Number(n)) if n.value > 0.0 => Some(n.value),
            _ => {
                diags.push(
                    Diagnostic::error(Code::BadOption, format!("`{name}` must be a positive number"))
                        .with_primary(o.span, "bad value"),
                );
                None
            }
        }
    }

    fn flag(&self, name: &str, diags: &mut Diagnostics) -> Option<bool> {
        let Some(o) = self.get(name) else { return Some(false) };
        match &o.value {
            None => Some(true),
            Some(OptionValue::Word(w)) if w.name == "true" || w.name == "false" => Some(w.name == "true"),
            _ => {
                diags.push(
                    Diagnostic::error(Code::BadOption, format!("`{name}` is a flag: write `{name}` or `{name}=false`"))
                        .with_primary(o.span, "bad value"),
                );
                None
            }
        }
    }

    fn activation(&self, name: &str, diags: &mut Diagnostics) -> Option<Activation> {
        let Some(o) = self.get(name) else { return Some(Activation::Relu) };
        // Every activation without options by its name, and `gelu` (the exact one).
        let plain = Activation::ALL.into_iter().filter(|a| !a.has_options() || *a == Activation::Gelu);
        let mut acts: Vec<&str> = plain.map(|a| a.name()).collect();
        acts.dedup();
        match &o.value {
            Some(OptionValue::Word(w)) if acts.contains(&w.name.as_str()) => {
                Activation::ALL.into_iter().find(|a| a.name() == w.name)
            }
            other => {
                let mut d = Diagnostic::error(Code::BadOption, format!("`{name}` must be one of {}", acts.join(", ")))
                    .with_primary(o.span, "unknown activation");
                if let Some(OptionValue::Word(w)) = other
                    && let Some(s) = suggest(&w.name, acts)
                {
                    d = d.with_note(format!("did you mean `{s}`?"));
                }
                diags.push(d);
                None
            }
        }
    }
}

/// Reports pairs of rules that claim one parameter in conflicting ways.
fn check_conflicts(graph: &Graph, rules: &[ResolvedRule], diags: &mut Diagnostics) {
    // node -> (rule index) for each claim kind.
    let mut tuned_weight: HashMap<NodeId, usize> = HashMap::new();
    let mut lora: HashMap<NodeId, usize> = HashMap::new();
    let mut adapter: HashMap<NodeId, usize> = HashMap::new();
    let mut reported: std::collections::HashSet<(usize, usize)> = Default::default();
    let mut conflict = |a: usize, b: usize, what: String, diags: &mut Diagnostics| {
        if reported.insert((a.min(b), a.max(b))) {
            let (first, second) = (a.min(b), a.max(b));
            diags.push(
                Diagnostic::error(Code::RuleConflict, format!("adaptation rules conflict: {what}"))
                    .with_primary(rules[second].span, "this rule")
                    .with_secondary(rules[first].span, "conflicts with this rule")
                    .with_note("narrow one selector so that each parameter is claimed once"),
            );
        }
    };
    for (i, r) in rules.iter().enumerate() {
        for t in &r.targets {
            let path = &graph.node(t.node).path;
            match r.kind {
                RuleKind::Tune => {
                    if t.slots.contains(&"weight") {
                        if let Some(&j) = lora.get(&t.node) {
                            conflict(j, i, format!("`{path}.weight` is tuned and also adapted by LoRA"), diags);
                        }
                        tuned_weight.entry(t.node).or_insert(i);
                    }
                }
                RuleKind::Lora { .. } => {
                    if let Some(&j) = tuned_weight.get(&t.node) {
                        conflict(j, i, format!("`{path}.weight` is tuned and also adapted by LoRA"), diags);
                    }
                    if let Some(&j) = lora.get(&t.node) {
                        conflict(j, i, format!("`{path}` gets two LoRA branches"), diags);
                    }
                    lora.entry(t.node).or_insert(i);
                }
                // Pruning claims nothing: it only changes shared base weights.
                RuleKind::Prune { .. } => {}
                RuleKind::Adapter { .. } => {
                    if let Some(&j) = adapter.get(&t.node) {
                        conflict(j, i, format!("two adapters before `{path}`"), diags);
                    }
                    adapter.entry(t.node).or_insert(i);
                }
            }
        }
    }
}
