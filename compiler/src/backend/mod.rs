//! The back end: from a checked module and its weights to a runtime plan.
//!
//! | pass            | changes                                                    |
//! |-----------------|------------------------------------------------------------|
//! | `bind_weights`  | binds safetensors tensors to parameter slots by name       |
//! | `bind_variants` | checks each variant's tensors against the adaptation rules |
//! | `lower`         | schedule of kernel steps; folds BatchNorm, fuses ReLU/bias  |
//! | `plan_buffers`  | assigns activation buffers by liveness                     |
//!
//! [`compile`] runs them and returns a [`Plan`] held in memory; `Plan::write` stores it.
//! With variants, the base and every variant are lowered to the same schedule and each
//! variant keeps the stored tensors that differ from the base (see [`variants`]).

pub mod buffers;
pub mod lower;
pub mod peft;
pub mod variants;
pub mod weights;

use std::collections::HashSet;

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_runtime::plan::Plan;

use crate::ir::{self, Graph};
use crate::passes::Module;
use crate::passes::resolve_adapt::Injection;
pub use variants::{LoraMode, VariantSource};
pub use weights::WeightSet;

/// Options of the back end.
#[derive(Clone, Debug, Default)]
pub struct CompileOptions {
    /// Tensors in the weights file that the model does not use are warnings, not errors.
    pub allow_unused: bool,
    /// How LoRA branches run.
    pub lora: LoraMode,
    /// An owned parameter a variant does not give is an error, not a warning.
    pub strict: bool,
    /// Melded variants to build from the given ones, `fog=0.06+gamma=0.5`.
    pub melds: Vec<String>,
}

fn ice(message: String) -> Diagnostics {
    Diagnostics(vec![Diagnostic::error(Code::Internal, format!("internal compiler error: {message}"))])
}

/// Compiles a checked module with its base weights and no variants.
pub fn compile(
    module: &Module,
    weights: &WeightSet,
    weights_name: &str,
    opts: &CompileOptions,
) -> Result<(Plan, Diagnostics), Diagnostics> {
    compile_variants(module, weights, weights_name, &[], opts)
}

/// Compiles a checked module with its base weights and the parameters of each variant.
/// Returns the plan and any warnings.
pub fn compile_variants(
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
) -> Result<(Plan, Diagnostics), Diagnostics> {
    // Melded variants: from their parts' parameters, then like any other variant.
    let melded = variants::melded_sources(module, sources, &opts.melds, base)?;
    let all: Vec<VariantSource>;
    let sources = if melded.is_empty() {
        sources
    } else {
        all = sources.iter().cloned().chain(melded).collect();
        &all[..]
    };
    let keys = variants::check_keys(module, sources)?;
    let (mut bound, mut warnings) = weights::bind(&module.graph, base, base_name, opts.allow_unused)?;
    let owned = variants::owned_params(module);
    let zeros = variants::zero_added(&owned);
    for (name, z) in &zeros {
        bound.insert(name.clone(), z);
    }
    // Bind every variant first: whether an adapter can move behind its BatchNorm depends on
    // the values of all of them.
    let mut bound_variants = Vec::new();
    let mut errors = Diagnostics::default();
    for (source, key) in sources.iter().zip(keys) {
        match variants::bind_variant(&module.graph, &owned, source, &key, opts.strict) {
            Ok(bv) => bound_variants.push((key, bv)),
            Err(d) => errors.extend(d),
        }
    }
    if errors.has_errors() {
        return Err(errors);
    }
    let vbounds: Vec<weights::Bound<'_>> = bound_variants
        .iter_mut()
        .map(|(_, bv)| {
            warnings.extend(std::mem::take(&mut bv.warnings));
            let mut vb = bound.clone();
            vb.extend(bv.values.iter().map(|(n, v)| (n.clone(), *v)));
            vb
        })
        .collect();
    // Adapters and LoRA branches no variant uses leave the schedule (without variants, all).
    let all_bounds = std::iter::once(&bound).chain(&vbounds);
    let dropped = variants::inactive(module, all_bounds.clone());
    let commuted: Vec<Injection> =
        variants::commutable(module, opts.lora, all_bounds).into_iter().filter(|inj| !dropped.contains(inj)).collect();
    let graph = variants::lowering_graph(module, opts.lora, &dropped, &commuted);
    let base_commuted = variants::commute_weights(module, &commuted, &bound);
    let mut base_bound = bound.clone();
    for (name, w) in &base_commuted {
        base_bound.insert(name.clone(), w);
    }
    let lower::Lowered { mut manifest, tensors: base_tensors, .. } = lower::lower(&graph, &base_bound)?;
    let mut store = variants::TensorStore::new(std::mem::take(&mut manifest.tensors), base_tensors);
    // Tensors derived from these parameters count as added in the budget.
    let mut added: HashSet<String> = owned.iter().filter(|(_, o)| o.added).map(|(n, _)| n.clone()).collect();
    if opts.lora == LoraMode::Merge {
        for inj in module.adapt.iter().flat_map(|a| &a.injections) {
            if let Injection::Lora { base, .. } = inj {
                added.insert(ir::join_path(&module.graph.node(*base).path, "weight"));
            }
        }
    }
    let mut tables = Vec::new();
    for ((key, bv), mut vbound) in bound_variants.into_iter().zip(vbounds) {
        let merged = if opts.lora == LoraMode::Merge { variants::merge_lora(module, &vbound) } else { Vec::new() };
        let moved = variants::commute_weights(module, &commuted, &vbound);
        for (name, w) in merged.iter().chain(&moved) {
            vbound.insert(name.clone(), w);
        }
        // Only tensors derived from what the variant changes need computing.
        let changed: HashSet<String> =
            bv.values.iter().map(|(n, _)| n).chain(merged.iter().chain(&moved).map(|(n, _)| n)).cloned().collect();
        let lowered = lower::lower_only(&graph, &vbound, &changed)?;
        let replaces = store.diff(&key, lowered, &added).map_err(ice)?;
        tables.push(variants::table(key, replaces, &owned, bv.fallback));
    }
    if errors.has_errors() {
        return Err(errors);
    }
    manifest.tensors = store.specs;
    manifest.variants = tables;
    manifest.conditions = module.variants.clone();
    let plan = Plan::new(manifest, store.data).map_err(|e| ice(format!("the plan is invalid: {e}")))?;
    Ok((plan, warnings))
}

/// Deterministic weights for every parameter of the base model: see [`seeded_tensor`].
pub fn seeded_weights(graph: &Graph, seed: u64) -> WeightSet {
    let mut set = WeightSet::default();
    for (name, _, slot) in graph.param_table() {
        if slot.dtype != readi_grammar::ast::DType::F32 || slot.kind == crate::ir::SlotKind::Added {
            continue;
        }
        let shape: Vec<usize> = slot.shape.iter().map(|&d| d as usize).collect();
        let data = seeded_tensor(seed, &name, &shape);
        set.tensors.insert(name, (shape, data));
    }
    set
}

/// Deterministic parameters for variants of a module: for the `i`-th key, every parameter
/// the variants own gets [`seeded_tensor`] with seed `seed + i` (LoRA `B` and adapter `up`
/// included, so no variant equals the base). For demos, tests and benchmarks.
pub fn seeded_variants(module: &Module, keys: &[String], seed: u64) -> Vec<VariantSource> {
    let owned = variants::owned_params(module);
    keys.iter()
        .enumerate()
        .map(|(i, key)| {
            let mut weights = WeightSet::default();
            for (name, o) in &owned {
                let data = seeded_tensor(seed + i as u64, name, &o.shape);
                weights.tensors.insert(name.clone(), (o.shape.clone(), data));
            }
            VariantSource { key: key.clone(), weights, origin: format!("<seeded variant {key}>") }
        })
        .collect()
}

/// The seeded value of one tensor, a function of the seed, the tensor's name and its
/// shape only, so that any implementation can reproduce it (the PyTorch fixture script
/// `tests/fixtures/make_fixtures.py` does, to run the same weights):
///
/// * a SplitMix64 stream seeded with `seed ^ fnv1a64(name)` gives `u` uniform in [-1, 1):
///   `((x >> 40) / 2^24) * 2 - 1`, in f32;
/// * `*.weight` with two or more axes (conv, linear): `u * (1 / sqrt(fan_in))` with
///   `fan_in = product(shape[1..])` (PyTorch's default init range);
/// * `*.running_var`: `1 + 0.25 * |u|`; other one-axis `*.weight` (norm layers):
///   `1 + 0.1 * u`; everything else (biases, running means, free parameters): `0.1 * u`.
pub fn seeded_tensor(seed: u64, name: &str, shape: &[usize]) -> Vec<f32> {
    let mut rng = SplitMix(seed ^ fnv1a64(name));
    let n: usize = shape.iter().product();
    let is_weight = name.ends_with(".weight") || name == "weight";
    if is_weight && shape.len() >= 2 {
        let fan_in: usize = shape[1..].iter().product();
        let bound = 1.0f32 / (fan_in as f32).sqrt();
        (0..n).map(|_| rng.uniform() * bound).collect()
    } else if name.ends_with("running_var") {
        (0..n).map(|_| 1.0 + 0.25 * rng.uniform().abs()).collect()
    } else if is_weight {
        (0..n).map(|_| 1.0 + 0.1 * rng.uniform()).collect()
    } else {
        (0..n).map(|_| 0.1 * rng.uniform()).collect()
    }
}

/// FNV-1a, 64 bit, of a string's UTF-8 bytes.
fn fnv1a64(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// SplitMix64: a small, well-mixed deterministic generator.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [-1, 1), exactly representable in f32.
    fn uniform(&mut self) -> f32 {
        ((self.next() >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeded_tensors_follow_the_documented_recipe() {
        // The published FNV-1a 64-bit test vectors.
        assert_eq!(fnv1a64(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64("a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(fnv1a64("foobar"), 0x8594_4171_f739_67e8);
        let a = seeded_tensor(1, "fc.weight", &[3, 4]);
        assert_eq!(a.len(), 12);
        assert!(a.iter().all(|v| v.abs() <= 0.5), "|u| / sqrt(4) <= 0.5: {a:?}");
        let v = seeded_tensor(1, "bn.running_var", &[8]);
        assert!(v.iter().all(|x| (1.0..=1.25).contains(x)), "{v:?}");
        assert_ne!(seeded_tensor(1, "a.bias", &[4]), seeded_tensor(1, "b.bias", &[4]));
        assert_eq!(seeded_tensor(7, "a.bias", &[4]), seeded_tensor(7, "a.bias", &[4]));
    }
}
