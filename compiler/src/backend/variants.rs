//! `bind_variants`: each variant's parameters, checked against the adaptation rules, and
//! the plan's variant tables.
//!
//! A variant owns exactly what the rules make per-variant: the slots `tune` rules select
//! (BatchNorm affine and running statistics, head weights, ...) and every slot
//! `inject_adapt` added (LoRA matrices, adapter convs). Its files give owned tensors by
//! PyTorch name. Checks, each an error naming the file and tensor: a key the `variants`
//! section does not declare (or given twice), a tensor the rules do not make per-variant, a
//! wrong shape, a NaN or infinity. An owned tensor a variant does not give keeps the base
//! value (zero for added ones) and is reported: a warning, or an error when strict.
//!
//! Each variant is lowered with the base schedule and its own values; every stored tensor
//! whose bytes differ from the base's becomes one of the variant's replacements, and
//! identical replacements are stored once. With [`LoraMode::Merge`] LoRA is folded into
//! the base layer's weight (`W + scale * B A`, PEFT's merge) and the LoRA branches leave the
//! schedule, so an adapted plan runs as fast as the base; with [`LoraMode::Branch`] the
//! branches run and a variant stores only the small `A` and `B` matrices.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::hash::{Hash, Hasher};

use readi_grammar::ast::DType;
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, suggest};
use readi_plan::VariantKey;
use readi_plan::ops::batchnorm_affine;
use readi_runtime::plan::{Replacement, TensorSpec, VariantTable};

use super::lower::Lowered;
#[cfg(doc)]
use super::lower::lower_only;
use super::weights::{Bound, WeightSet};
use crate::ir::{self, Graph, NodeId, SlotKind, ValueRef};
use crate::passes::Module;
use crate::passes::resolve_adapt::{Injection, RuleKind};

/// How LoRA runs in the plan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LoraMode {
    /// Folded into the adapted layer's weight per variant: no extra work at run time, but
    /// each variant stores the whole weight of every LoRA layer.
    #[default]
    Merge,
    /// Kept as a side branch `scale * B(A(x))`: each variant stores only `A` and `B`.
    Branch,
}

impl LoraMode {
    pub fn name(self) -> &'static str {
        match self {
            LoraMode::Merge => "merge",
            LoraMode::Branch => "branch",
        }
    }
}

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
    let mut add = |node: NodeId, slot: &ir::ParamSlot| {
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

/// The graph the back end lowers: without the injections in `dropped` (those that are
/// zero in the base and every variant, see [`inactive`]: they would compute zeros), and
/// without LoRA branches when LoRA is merged. Injections in `commuted` move behind their
/// BatchNorm (see [`commute_weights`]).
pub fn lowering_graph(module: &Module, lora: LoraMode, dropped: &[Injection], commuted: &[Injection]) -> Graph {
    let mut g = module.graph.clone();
    let Some(plan) = &module.adapt else { return g };
    for inj in &plan.injections {
        match *inj {
            Injection::Lora { base, add, .. } if dropped.contains(inj) || lora == LoraMode::Merge => {
                g.replace_uses(ValueRef { node: add, port: 0 }, ValueRef { node: base, port: 0 });
            }
            Injection::Adapter { target, add, .. } if dropped.contains(inj) => {
                let x = g.inputs(add)[0];
                g.set_input(target, 0, x);
            }
            Injection::Lora { base, add, .. } if commuted.contains(inj) => {
                // bn(y + branch)  ->  bn(y) + s * branch, with lora_B scaled.
                let bn_node = g.users(add)[0];
                let (bn, sum) = (ValueRef { node: bn_node, port: 0 }, ValueRef { node: add, port: 0 });
                g.replace_uses(bn, sum);
                g.set_input(bn_node, 0, ValueRef { node: base, port: 0 });
                g.set_input(add, 0, bn);
                continue;
            }
            Injection::Adapter { target, down, add, .. } if commuted.contains(inj) => {
                // bn(x + up(down(x)))  ->  bn(x) + up'(down'(bn(x))), weights transformed.
                let x = g.inputs(add)[0];
                let (bn, sum) = (ValueRef { node: target, port: 0 }, ValueRef { node: add, port: 0 });
                g.replace_uses(bn, sum);
                g.set_input(target, 0, x);
                g.set_input(down, 0, bn);
                g.set_input(add, 0, bn);
                continue;
            }
            _ => continue,
        }
        for n in inj.nodes() {
            g.remove_node(n);
        }
    }
    g
}

/// The injections whose added parameters are zero in every one of `bounds` (the base's
/// and each variant's values; all of them when there are no variants): no variant uses them.
pub fn inactive<'a, 'w: 'a>(
    module: &Module,
    bounds: impl IntoIterator<Item = &'a Bound<'w>> + Clone,
) -> Vec<Injection> {
    let g = &module.graph;
    let Some(plan) = &module.adapt else { return Vec::new() };
    let zero = |inj: &Injection| {
        inj.nodes().iter().all(|&n| {
            let node = g.node(n);
            node.params.iter().all(|slot| {
                let name = node.param_name(slot);
                bounds.clone().into_iter().all(|b| b.get(&name).is_none_or(|v| v.iter().all(|x| *x == 0.0)))
            })
        })
    };
    plan.injections.iter().filter(|inj| zero(inj)).cloned().collect()
}

/// The BatchNorm affine `y = s * x + t` of a node, from bound values.
fn bn_affine(module: &Module, bn: NodeId, bound: &Bound<'_>) -> Option<(Vec<f64>, Vec<f64>)> {
    let node = module.graph.node(bn);
    let ir::Op::BatchNorm(bn) = &node.op else { return None };
    let get = |slot: &str| bound.get(&ir::join_path(&node.path, slot)).copied();
    let (w, b, mean, var) = (get("weight")?, get("bias")?, get("running_mean")?, get("running_var")?);
    Some(batchnorm_affine(w, b, mean, var, bn.eps, None))
}

/// The BatchNorm right after a LoRA branch's sum, if that is the sum's only use.
fn bn_after(module: &Module, add: NodeId) -> Option<NodeId> {
    let g = &module.graph;
    let users = g.users(add);
    let only = users.len() == 1 && !g.outputs.iter().any(|o| o.value.node == add);
    only.then(|| users[0]).filter(|&u| matches!(g.node(u).op, ir::Op::BatchNorm { .. }))
}

/// Injections that can move behind the BatchNorm after them for every one of `bounds`
/// (the base's and each variant's values), so that the BatchNorm folds into the conv
/// before it again, saving a pass over the activation: an adapter before a BatchNorm whose
/// scale is nowhere near zero, and (with LoRA as a branch) a LoRA branch whose sum only
/// feeds a BatchNorm.
pub fn commutable<'a, 'w: 'a>(
    module: &Module,
    lora: LoraMode,
    bounds: impl IntoIterator<Item = &'a Bound<'w>> + Clone,
) -> Vec<Injection> {
    let Some(plan) = &module.adapt else { return Vec::new() };
    plan.injections
        .iter()
        .filter(|inj| match inj {
            Injection::Adapter { target, .. } => bounds.clone().into_iter().all(|b| {
                bn_affine(module, *target, b).is_some_and(|(s, _)| s.iter().all(|v| v.abs() >= 1e-3 && v.is_finite()))
            }),
            Injection::Lora { add, .. } => lora == LoraMode::Branch && bn_after(module, *add).is_some(),
        })
        .cloned()
        .collect()
}

/// The weights that make the moves exact. With the BatchNorm `y = s x + t`:
/// `bn(x + up(down(x))) = bn(x) + s * up(down((bn(x) - t) / s))`, so an adapter's `down`
/// takes `W / s` (per input channel) and bias `b - (W / s) t`, and its `up` takes `s * W`,
/// `s * b` (per output channel); `bn(y + scale * B(A(x))) = bn(y) + scale * (s B)(A(x))`,
/// so a LoRA branch's `lora_B` takes `s * B`.
pub fn commute_weights(module: &Module, commuted: &[Injection], bound: &Bound<'_>) -> Vec<(String, Vec<f32>)> {
    let g = &module.graph;
    let mut out = Vec::new();
    let name = |n: NodeId, slot: &str| ir::join_path(&g.node(n).path, slot);
    for inj in commuted {
        if let Injection::Lora { b, add, .. } = *inj {
            let scaled = bn_after(module, add).and_then(|bn| bn_affine(module, bn, bound)).and_then(|(s, _)| {
                let w = bound.get(&name(b, "weight"))?;
                let rank = w.len() / s.len();
                Some(w.iter().enumerate().map(|(i, &v)| (v as f64 * s[i / rank]) as f32).collect::<Vec<f32>>())
            });
            if let Some(w) = scaled {
                out.push((name(b, "weight"), w));
            }
            continue;
        }
        let Injection::Adapter { target, down, up, .. } = *inj else { continue };
        let Some((s, t)) = bn_affine(module, target, bound) else { continue };
        let get = |n: NodeId, slot: &str| bound.get(&name(n, slot)).copied();
        let (Some(wd), Some(bd), Some(wu), Some(bu)) =
            (get(down, "weight"), get(down, "bias"), get(up, "weight"), get(up, "bias"))
        else {
            continue;
        };
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
        out.extend([
            (name(down, "weight"), wd2),
            (name(down, "bias"), bd2),
            (name(up, "weight"), wu2),
            (name(up, "bias"), bu2),
        ]);
    }
    out
}

/// Zero values for every added slot: the base model's value of LoRA and adapter weights.
pub fn zero_added(owned: &BTreeMap<String, Owned>) -> Vec<(String, Vec<f32>)> {
    owned.iter().filter(|(_, o)| o.added).map(|(n, o)| (n.clone(), vec![0.0; o.shape.iter().product()])).collect()
}

/// A melded variant (`fog=0.06+gamma=0.5`) from its parts' parameters (each part one of
/// the key's conditions, in any order): every owned parameter is `sum(lambda_i * P_i)`
/// (the paper's `lambda_c P_c + lambda_l P_l`), a part that does not give a parameter
/// contributing the base value (zero for added ones).
pub fn meld(
    module: &Module,
    key: &VariantKey,
    parts: &[&VariantSource],
    base: &WeightSet,
) -> Result<VariantSource, Diagnostics> {
    let err = |m: String| Diagnostics(vec![Diagnostic::error(Code::VariantWeights, m)]);
    let spec = module.variants.as_ref().ok_or_else(|| err("the spec has no variants section".into()))?;
    let weights_of_key = spec.meld_weights(key).map_err(|m| err(format!("cannot meld `{key}`: {m}")))?;
    let conditions: Vec<VariantKey> = key.part_keys().collect();
    let mut lambdas = Vec::with_capacity(parts.len());
    for part in parts {
        let k = VariantKey::parse(&part.key).map_err(|e| err(e.to_string()))?;
        let at = conditions.iter().position(|c| *c == k);
        lambdas.push(weights_of_key[at.ok_or_else(|| err(format!("`{k}` is not a part of `{key}`")))?]);
    }
    let mut weights = WeightSet::default();
    for (name, o) in owned_params(module) {
        let n: usize = o.shape.iter().product();
        let mut acc = vec![0.0f64; n];
        for (part, l) in parts.iter().zip(&lambdas) {
            let v = part.weights.tensors.get(&name).or_else(|| base.tensors.get(&name)).map(|(_, d)| d.as_slice());
            if let Some(v) = v.filter(|v| v.len() == n) {
                for (a, x) in acc.iter_mut().zip(v) {
                    *a += l * *x as f64;
                }
            }
        }
        weights.tensors.insert(name, (o.shape.clone(), acc.into_iter().map(|v| v as f32).collect()));
    }
    let shown: Vec<String> = key.part_keys().map(|k| k.to_string()).collect();
    let origin = format!("meld of {}", shown.join(" and "));
    Ok(VariantSource { key: key.to_string(), weights, origin })
}

/// The melded variants `keys` asks for (`fog=0.06+gamma=0.5`), each from the given
/// variants that are its parts.
pub fn melded_sources(
    module: &Module,
    sources: &[VariantSource],
    keys: &[String],
    base: &WeightSet,
) -> Result<Vec<VariantSource>, Diagnostics> {
    let err = |m: String| Diagnostics(vec![Diagnostic::error(Code::VariantWeights, m)]);
    let declared = module.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    let mut melded = Vec::new();
    for key in keys {
        let canonical = canonical_key(key, &declared).filter(VariantKey::is_meld).ok_or_else(|| {
            err(format!("`{key}` is not a combination of declared keys (write `fog=0.06+gamma=0.5`)"))
        })?;
        let mut parts = Vec::new();
        for part in canonical.part_keys() {
            let found = sources.iter().find(|s| canonical_key(&s.key, &declared).as_ref() == Some(&part));
            parts.push(found.ok_or_else(|| err(format!("cannot meld `{canonical}`: no variant `{part}` is given")))?);
        }
        melded.push(meld(module, &canonical, &parts, base)?);
    }
    Ok(melded)
}

/// The declared key a written key names: `fog=0.030` names `fog=0.03`; a melded key names
/// the meld of its parts in any order, each of them declared (`gamma=0.5+fog=0.06` names
/// `fog=0.06+gamma=0.5`).
pub fn canonical_key(key: &str, declared: &[VariantKey]) -> Option<VariantKey> {
    let k = VariantKey::parse(key).ok()?;
    let ok = !k.is_base() && k.part_keys().all(|p| declared.contains(&p));
    ok.then_some(k)
}

/// Checks the keys of all variants: declared by the spec, each given once.
pub fn check_keys(module: &Module, variants: &[VariantSource]) -> Result<Vec<VariantKey>, Diagnostics> {
    let declared = module.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    let shown: Vec<String> = declared.iter().map(|k| k.to_string()).collect();
    let mut diags = Diagnostics::default();
    let mut keys: Vec<VariantKey> = Vec::new();
    for v in variants {
        let Some(k) = canonical_key(&v.key, &declared) else {
            let mut d = Diagnostic::error(
                Code::VariantWeights,
                format!("{}: variant key `{}` is not declared by the spec", v.origin, v.key),
            );
            d = match suggest(&v.key, shown.iter().map(String::as_str)) {
                Some(s) => d.with_note(format!("did you mean `{s}`?")),
                None if declared.is_empty() => d.with_note("the spec has no `variants` section"),
                None => d.with_note(format!("declared keys: {}", shown.join(", "))),
            };
            diags.push(d);
            continue;
        };
        if keys.contains(&k) {
            diags.push(Diagnostic::error(Code::VariantWeights, format!("{}: variant `{k}` is given twice", v.origin)));
        }
        keys.push(k);
    }
    if module.adapt.is_none() && !variants.is_empty() {
        diags.push(
            Diagnostic::error(Code::VariantWeights, "the spec has no `adapt` section, so variants own no parameters")
                .with_note("add rules such as `tune batchnorm` to make parameters per-variant"),
        );
    }
    if diags.has_errors() { Err(diags) } else { Ok(keys) }
}

/// One variant's checked tensors.
pub struct BoundVariant<'w> {
    /// The tensors it gives, to bind over the base values.
    pub values: Vec<(String, &'w [f32])>,
    /// Owned parameters it does not give (they keep the base value).
    pub fallback: Vec<String>,
    pub warnings: Diagnostics,
}

/// Binds one variant's tensors over the base values.
pub fn bind_variant<'w>(
    graph: &Graph,
    owned: &BTreeMap<String, Owned>,
    source: &'w VariantSource,
    key: &VariantKey,
    strict: bool,
) -> Result<BoundVariant<'w>, Diagnostics> {
    let mut diags = Diagnostics::default();
    let mut values = Vec::new();
    let base_params: HashSet<String> = graph.param_table().into_iter().map(|(n, _, _)| n).collect();
    let file = &source.origin;
    for (name, (shape, data)) in &source.weights.tensors {
        if name.ends_with("num_batches_tracked") {
            continue;
        }
        let Some(o) = owned.get(name) else {
            let mut d = Diagnostic::error(
                Code::VariantWeights,
                format!("{file}: tensor `{name}` is not per-variant: no adaptation rule makes it so"),
            );
            d = if base_params.contains(name) {
                d.with_note("it is a parameter of the base model; a `tune` rule selecting it would make it per-variant")
            } else {
                match suggest(name, owned.keys().map(String::as_str)) {
                    Some(s) => d.with_note(format!("did you mean `{s}`?")),
                    None => d.with_note("it is not a parameter of the model"),
                }
            };
            diags.push(d);
            continue;
        };
        if *shape != o.shape {
            diags.push(
                Diagnostic::error(
                    Code::VariantWeights,
                    format!("{file}: tensor `{name}` has shape {shape:?}, but the model needs {:?}", o.shape),
                )
                .with_primary(graph.node(o.node).span, format!("expects {:?}", o.shape)),
            );
            continue;
        }
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            diags.push(Diagnostic::error(
                Code::VariantWeights,
                format!("{file}: tensor `{name}` holds {} at flat index {i}; weights must be finite", data[i]),
            ));
            continue;
        }
        values.push((name.clone(), data.as_slice()));
    }
    let fallback: Vec<String> = owned.keys().filter(|n| !source.weights.tensors.contains_key(*n)).cloned().collect();
    if !fallback.is_empty() && !diags.has_errors() {
        let shown: Vec<&str> = fallback.iter().take(4).map(String::as_str).collect();
        let more = if fallback.len() > 4 { format!(" and {} more", fallback.len() - 4) } else { String::new() };
        let message = format!(
            "variant `{key}` does not give {} of its {} parameters; they keep the base value: {}{more}",
            fallback.len(),
            owned.len(),
            shown.join(", ")
        );
        diags.push(if strict {
            Diagnostic::error(Code::VariantWeights, message).with_note("without --strict this is a warning")
        } else {
            Diagnostic::warning(Code::VariantWeights, message).with_note("--strict makes this an error")
        });
    }
    if diags.has_errors() { Err(diags) } else { Ok(BoundVariant { values, fallback, warnings: diags }) }
}

/// PEFT's merge of every LoRA branch into its layer's weight: `W + scale * B A` (for a
/// conv, `A` is `[rank, in * kh * kw]` and `B` is `[out, rank]`). Returns the merged weights
/// of the layers whose branch is non-zero.
pub fn merge_lora(module: &Module, bound: &Bound<'_>) -> Vec<(String, Vec<f32>)> {
    let g = &module.graph;
    let mut merged = Vec::new();
    let Some(plan) = &module.adapt else { return merged };
    for inj in &plan.injections {
        let Injection::Lora { base, a, b, factor, .. } = *inj else { continue };
        let name = |n: NodeId| ir::join_path(&g.node(n).path, "weight");
        let (Some(w), Some(wa), Some(wb)) = (bound.get(&name(base)), bound.get(&name(a)), bound.get(&name(b))) else {
            continue;
        };
        if wa.iter().all(|v| *v == 0.0) || wb.iter().all(|v| *v == 0.0) {
            continue;
        }
        let rank = g.node(a).params[0].shape[0] as usize;
        let cols = wa.len() / rank;
        let rows = wb.len() / rank;
        let mut out = w.to_vec();
        for o in 0..rows {
            for c in 0..cols {
                let delta: f64 = (0..rank).map(|r| wb[o * rank + r] as f64 * wa[r * cols + c] as f64).sum();
                out[o * cols + c] = (w[o * cols + c] as f64 + factor * delta) as f32;
            }
        }
        merged.push((name(base), out));
    }
    merged
}

/// The plan's tensors: the base's, then each distinct replacement once.
pub struct TensorStore {
    pub specs: Vec<TensorSpec>,
    pub data: Vec<Vec<f32>>,
    by_hash: HashMap<u64, Vec<usize>>,
    base_len: usize,
}

fn bits_hash(shape: &[usize], data: &[f32]) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    shape.hash(&mut h);
    for v in data {
        v.to_bits().hash(&mut h);
    }
    h.finish()
}

fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

impl TensorStore {
    /// The store of a plan whose base tensors are `specs` and `data` (taken, not copied).
    pub fn new(specs: Vec<TensorSpec>, data: Vec<Vec<f32>>) -> TensorStore {
        let mut by_hash: HashMap<u64, Vec<usize>> = HashMap::new();
        for (i, (spec, d)) in specs.iter().zip(&data).enumerate() {
            by_hash.entry(bits_hash(&spec.shape, d)).or_default().push(i);
        }
        TensorStore { base_len: data.len(), specs, data, by_hash }
    }

    /// The variant's replacements: every tensor of `lowered` (from [`lower_only`], which
    /// leaves the tensors the variant does not change empty, among them the base-only
    /// records for AdaBN) whose bytes differ from the base's. `added` holds the parameters
    /// whose tensors count as added.
    pub fn diff(
        &mut self,
        key: &VariantKey,
        lowered: Lowered,
        added: &HashSet<String>,
    ) -> Result<Vec<Replacement>, String> {
        if lowered.tensors.len() != self.base_len {
            return Err(format!(
                "variant `{key}` lowers to {} tensors, the base to {}",
                lowered.tensors.len(),
                self.base_len
            ));
        }
        let mut replaces = Vec::new();
        for (i, (data, sources)) in lowered.tensors.into_iter().zip(lowered.sources).enumerate() {
            let spec = &lowered.manifest.tensors[i];
            if spec.name != self.specs[i].name || spec.shape != self.specs[i].shape {
                return Err(format!(
                    "variant `{key}` lowers tensor {i} as `{}`, the base as `{}`",
                    spec.name, self.specs[i].name
                ));
            }
            let computed = !data.is_empty() || spec.numel() == 0;
            if !computed || same_bits(&data, &self.data[i]) {
                continue;
            }
            let h = bits_hash(&spec.shape, &data);
            let found = self.by_hash.get(&h).and_then(|c| {
                c.iter().copied().find(|&j| self.specs[j].shape == spec.shape && same_bits(&self.data[j], &data))
            });
            let with = match found {
                Some(j) => j,
                None => {
                    self.specs.push(TensorSpec { name: format!("{}#{key}", spec.name), shape: spec.shape.clone() });
                    self.data.push(data);
                    let j = self.data.len() - 1;
                    self.by_hash.entry(h).or_default().push(j);
                    j
                }
            };
            let added = sources.iter().any(|s| added.contains(s));
            replaces.push(Replacement { base: i, with, added });
        }
        Ok(replaces)
    }
}

/// A variant's table.
pub fn table(
    key: VariantKey,
    replaces: Vec<Replacement>,
    owned: &BTreeMap<String, Owned>,
    fallback: Vec<String>,
) -> VariantTable {
    let count = |added: bool| -> u64 {
        owned.values().filter(|o| o.added == added).map(|o| o.shape.iter().product::<usize>() as u64).sum()
    };
    VariantTable { key, replaces, tuned_elements: count(false), added_elements: count(true), fallback }
}
