//! `bind_variants`: binds each variant's tensors into the tensor table, checked against
//! the adaptation rules.
//!
//! A variant's files give the tensors it owns by PyTorch name (safetensors files, PEFT
//! adapter directories; see [`crate::weights::variants`]). Checks, each an error naming
//! the file and tensor: a key the `variants` section does not declare (or given twice), a
//! tensor the rules do not make per-variant, a tensor outside the variant's scope (owned
//! only by the variants of another `adapt` section's scope: the error names both scopes),
//! a wrong shape, a NaN or infinity. An owned tensor a variant does not give keeps the
//! base value (zero for added ones): one warning for all such variants together, or an
//! error per variant with `--strict`.
//!
//! Produces: the table with one value row per variant, in the order given; a variant's
//! value is kept only where it differs from the base's bits. Does nothing without
//! variants. Changes nothing in the graph. Assumes `bind_weights` ran.

use std::collections::{BTreeMap, HashMap, HashSet};

use readi_grammar::diag::{Code, Diagnostic, Diagnostics, suggest};
use readi_plan::VariantKey;

use super::{BackendInputs, Output};
use crate::module::Module;
use crate::weights::VariantSource;
use crate::weights::tensors::{Data, VariantInfo};
use crate::weights::variants::{Owned, canonical_key, owned_by};

pub fn run(module: &Module, inputs: &BackendInputs<'_>, warnings: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let mut table = module.tensors.clone().ok_or_else(not_bound)?;
    let sources = inputs.variants;
    if sources.is_empty() {
        return Ok(Output::Tensors(Box::new(table)));
    }
    let keys = check_keys(module, sources)?;
    let mut errors = Diagnostics::default();
    let mut bound = Vec::new();
    for (source, key) in sources.iter().zip(keys) {
        match bind_variant(module, &table.owned, source, &key, inputs.opts.strict) {
            Ok(bv) => bound.push((key, source, bv)),
            Err(d) => errors.extend(d),
        }
    }
    if errors.has_errors() {
        return Err(errors);
    }
    if let Some(w) = partial_warning(&bound) {
        warnings.push(w);
    }
    let first = table.variant_count();
    for (key, source, bv) in bound {
        let provided = bv.values.iter().map(|(n, _)| n.clone()).collect();
        table.variants.push(VariantInfo { key, fallback: bv.fallback, provided, origin: source.origin.clone() });
        let v = table.variant_count();
        let given: HashMap<&str, &[f32]> = bv.values.iter().map(|(n, d)| (n.as_str(), *d)).collect();
        for (name, t) in table.iter_mut() {
            t.variants.resize(v, None);
            if let Some(&data) = given.get(name.as_str())
                && !same_bits(data, &t.base)
            {
                t.variants[v - 1] = Some(Data::from(data));
            }
        }
    }
    debug_assert!(table.variant_count() == first + sources.len());
    Ok(Output::Tensors(Box::new(table)))
}

pub(super) fn not_bound() -> Diagnostics {
    super::internal("the weights are not bound")
}

/// Whether two values have the same bits.
pub(crate) fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Checks the keys of all variants: declared by the spec, each given once.
fn check_keys(module: &Module, variants: &[VariantSource]) -> Result<Vec<VariantKey>, Diagnostics> {
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

/// Variants that give part of what they own, all in one warning (a LoRA-only PEFT
/// directory is a normal variant; one line per compile, not per variant).
fn partial_warning(bound: &[(VariantKey, &VariantSource, BoundVariant<'_>)]) -> Option<Diagnostic> {
    let partial: Vec<String> = bound
        .iter()
        .filter(|(_, _, bv)| !bv.fallback.is_empty())
        .map(|(key, _, bv)| format!("{key} gives {} of {}", bv.owned - bv.fallback.len(), bv.owned))
        .collect();
    if partial.is_empty() {
        return None;
    }
    const SHOWN: usize = 6;
    let more = if partial.len() > SHOWN { format!(", and {} more", partial.len() - SHOWN) } else { String::new() };
    let n = partial.len();
    let (verb, pronoun) = if n == 1 { ("gives", "it owns") } else { ("give", "they own") };
    Some(Diagnostic::warning(
        Code::VariantWeights,
        format!(
            "{n} variant{} {verb} part of what {pronoun} (the rest keeps the base value): {}{more}; --strict makes \
             this an error",
            if n == 1 { "" } else { "s" },
            partial[..n.min(SHOWN)].join(", ")
        ),
    ))
}

/// One variant's checked tensors.
struct BoundVariant<'w> {
    /// The tensors it gives, to bind over the base values.
    pub values: Vec<(String, &'w [f32])>,
    /// Owned parameters it does not give (they keep the base value).
    pub fallback: Vec<String>,
    /// How many parameters it owns (within its scope).
    pub owned: usize,
}

/// The scopes whose rules the variant `key` owns, for messages: `camera` or `camera and
/// the unscoped rules`.
fn scopes_of(module: &Module, key: &VariantKey) -> String {
    let mut named: Vec<String> = Vec::new();
    let mut unscoped = false;
    for r in module.adapt.iter().flat_map(|p| &p.rules).filter(|r| r.scope.covers(key)) {
        if r.scope.is_all() {
            unscoped = true;
        } else if !named.contains(&r.scope.label()) {
            named.push(r.scope.label());
        }
    }
    let named: Vec<String> = named.iter().map(|n| format!("scope `{n}`")).collect();
    match (named.is_empty(), unscoped) {
        (true, true) => "the unscoped rules".into(),
        (true, false) => "no rule".into(),
        (false, true) => format!("the unscoped rules and {}", named.join(", ")),
        (false, false) => named.join(", "),
    }
}

/// Binds one variant's tensors over the base values.
fn bind_variant<'w>(
    module: &Module,
    owned: &BTreeMap<String, Owned>,
    source: &'w VariantSource,
    key: &VariantKey,
    strict: bool,
) -> Result<BoundVariant<'w>, Diagnostics> {
    let graph = &module.graph;
    let mut diags = Diagnostics::default();
    let mut values = Vec::new();
    let base_params: HashSet<String> = graph.param_table().into_iter().map(|(n, _, _)| n).collect();
    let file = &source.origin;
    for (name, (shape, data)) in &source.weights.tensors {
        if name.ends_with("num_batches_tracked") {
            continue;
        }
        if let Some(o) = owned.get(name)
            && !o.is_owned_by(key)
        {
            diags.push(
                Diagnostic::error(
                    Code::VariantWeights,
                    format!(
                        "{file}: tensor `{name}` is outside the scope of variant `{key}`: it is owned by scope `{}`, \
                         and `{key}` owns {}",
                        o.scope_label(),
                        scopes_of(module, key)
                    ),
                )
                .with_primary(graph.node(o.node).span, format!("per-variant for scope `{}`", o.scope_label()))
                .with_note("give it in the files of a variant of that scope, or widen the `adapt` section's scope"),
            );
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
    // Within the variant's scope: what it owns and did not give.
    let mine: Vec<&String> = owned_by(owned, key).map(|(n, _)| n).collect();
    let fallback: Vec<String> =
        mine.iter().filter(|n| !source.weights.tensors.contains_key(n.as_str())).map(|n| (*n).clone()).collect();
    if strict && !fallback.is_empty() && !diags.has_errors() {
        let shown: Vec<&str> = fallback.iter().take(4).map(String::as_str).collect();
        let more = if fallback.len() > 4 { format!(" and {} more", fallback.len() - 4) } else { String::new() };
        diags.push(
            Diagnostic::error(
                Code::VariantWeights,
                format!(
                    "variant `{key}` does not give {} of its {} parameters; they would keep the base value: {}{more}",
                    fallback.len(),
                    mine.len(),
                    shown.join(", ")
                ),
            )
            .with_note("without --strict this is a warning"),
        );
    }
    if diags.has_errors() { Err(diags) } else { Ok(BoundVariant { values, fallback, owned: mine.len() }) }
}
