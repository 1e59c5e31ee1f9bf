//! `bind_variants`: binds each variant's tensors into the tensor table, checked against
//! the adaptation rules.
//!
//! A variant's files give the tensors it owns by PyTorch name (safetensors files, PEFT
//! adapter directories; see [`crate::weights::variants`]). Checks, each an error naming
//! the file and tensor: a key the `variants` section does not declare (or given twice), a
//! tensor the rules do not make per-variant, a wrong shape, a NaN or infinity. An owned
//! tensor a variant does not give keeps the base value (zero for added ones) and is
//! reported: a warning, or an error with `--strict`.
//!
//! Produces: the table with one value row per variant, in the order given; a variant's
//! value is kept only where it differs from the base's bits. Does nothing without
//! variants. Changes nothing in the graph. Assumes `bind_weights` ran.

use std::collections::{BTreeMap, HashMap, HashSet};

use readi_grammar::diag::{Code, Diagnostic, Diagnostics, suggest};
use readi_plan::VariantKey;

use super::{BackendInputs, Output};
use crate::ir::Graph;
use crate::module::Module;
use crate::weights::VariantSource;
use crate::weights::tensors::{Data, VariantInfo};
use crate::weights::variants::{Owned, canonical_key};

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
        match bind_variant(&module.graph, &table.owned, source, &key, inputs.opts.strict) {
            Ok(bv) => bound.push((key, source, bv)),
            Err(d) => errors.extend(d),
        }
    }
    if errors.has_errors() {
        return Err(errors);
    }
    let first = table.variant_count();
    for (key, source, bv) in bound {
        warnings.extend(bv.warnings);
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

/// One variant's checked tensors.
struct BoundVariant<'w> {
    /// The tensors it gives, to bind over the base values.
    pub values: Vec<(String, &'w [f32])>,
    /// Owned parameters it does not give (they keep the base value).
    pub fallback: Vec<String>,
    pub warnings: Diagnostics,
}

/// Binds one variant's tensors over the base values.
fn bind_variant<'w>(
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
