//! `meld`: builds the melded variants `--meld` asks for (`fog=0.06+gamma=0.5`) from the
//! bound variants that are their parts.
//!
//! Every parameter the variants own becomes `sum(lambda_i * P_i)` over the parts (the
//! paper's `lambda_c P_c + lambda_l P_l`), with the spec's meld rule giving the lambdas; a
//! part that does not change a parameter contributes the base value (zero for an added
//! one). Interpolating the parameters before folding and merging means every later pass
//! sees the melded values. Errors: a key that is not a combination of declared keys, a
//! part that was not given, a meld the rule does not cover, a meld given twice.
//!
//! Produces: the table with one more variant per meld. Does nothing without `--meld`.
//! Changes nothing in the graph. Assumes `bind_variants` ran.

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_plan::VariantKey;

use super::bind_variants::{not_bound, same_bits};
use super::{BackendInputs, Output};
use crate::module::Module;
use crate::weights::tensors::{Data, TensorTable, VariantInfo, first_non_finite};
use crate::weights::variants::canonical_key;

pub fn run(module: &Module, inputs: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let mut table = module.tensors.clone().ok_or_else(not_bound)?;
    let err = |m: String| Diagnostics(vec![Diagnostic::error(Code::VariantWeights, m)]);
    let declared = module.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    for key in &inputs.opts.melds {
        let melded = canonical_key(key, &declared).filter(VariantKey::is_meld).ok_or_else(|| {
            err(format!("`{key}` is not a combination of declared keys (write `fog=0.06+gamma=0.5`)"))
        })?;
        if table.variants.iter().any(|v| v.key == melded) {
            return Err(err(format!("variant `{melded}` is given twice")));
        }
        let spec = module.variants.as_ref().ok_or_else(|| err("the spec has no variants section".into()))?;
        let lambdas = spec.meld_weights(&melded).map_err(|m| err(format!("cannot meld `{melded}`: {m}")))?;
        let mut parts = Vec::new();
        for part in melded.part_keys() {
            let at = table.variants.iter().position(|v| v.key == part);
            parts.push(1 + at.ok_or_else(|| err(format!("cannot meld `{melded}`: no variant `{part}` is given")))?);
        }
        let values = meld(&table, &parts, &lambdas);
        let shown: Vec<String> = melded.part_keys().map(|k| k.to_string()).collect();
        for (name, data) in &values {
            if let Some((i, x)) = first_non_finite(data) {
                let terms: Vec<String> = shown.iter().zip(&lambdas).map(|(k, l)| format!("{l} * `{k}`")).collect();
                return Err(err(format!(
                    "melded tensor `{name}` of `{melded}` is {x} at flat index {i}: the sum {} overflows f32",
                    terms.join(" + ")
                )));
            }
        }
        let origin = format!("meld of {}", shown.join(" and "));
        let provided = parts.iter().flat_map(|&v| table.variants[v - 1].provided.iter().cloned()).collect();
        table.variants.push(VariantInfo { key: melded, fallback: Vec::new(), provided, origin });
        let v = table.variant_count();
        for (name, t) in table.iter_mut() {
            t.variants.resize(v, None);
            if let Some(data) = values.iter().find(|(n, _)| n == name).map(|(_, d)| d)
                && !same_bits(data, &t.base)
            {
                t.variants[v - 1] = Some(Data::from(data.as_slice()));
            }
        }
    }
    Ok(Output::Tensors(Box::new(table)))
}

/// Every owned parameter interpolated over the variants `parts` (table indices, 1 is the
/// first variant) with weights `lambdas`, accumulated in f64.
pub fn meld(table: &TensorTable, parts: &[usize], lambdas: &[f64]) -> Vec<(String, Vec<f32>)> {
    let mut out = Vec::new();
    for name in table.owned.keys() {
        let Some(t) = table.get(name) else { continue };
        let mut acc = vec![0.0f64; t.numel()];
        for (&v, l) in parts.iter().zip(lambdas) {
            for (a, x) in acc.iter_mut().zip(t.value(v)) {
                *a += l * *x as f64;
            }
        }
        out.push((name.clone(), acc.into_iter().map(|v| v as f32).collect()));
    }
    out
}
