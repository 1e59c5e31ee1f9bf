//! The back end's entry points: from a checked module, its weights and its variants to
//! a runtime plan.
//!
//! The back-end passes (`bind_weights` to `plan_buffers`) are in [`crate::passes`], run
//! by the same driver as the front end; what they work on is in [`crate::weights`] (and
//! re-exported here). [`compile`] and [`compile_variants`] run them and return a [`Plan`]
//! held in memory; `Plan::write` stores it.

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_runtime::plan::Plan;

use crate::ir::Graph;
use crate::module::Module;
use crate::passes::{self, BackendInputs};
pub use crate::passes::{CompileOptions, LoraMode};
pub use crate::weights::{VariantSource, WeightSet, peft, tensors, variants};

/// An internal error about `module` as a whole, at the model's declaration.
fn ice(module: &Module, message: String) -> Diagnostics {
    let d = Diagnostic::error(Code::Internal, format!("internal compiler error: {message}"))
        .with_primary(module.graph.scopes[0].span, "while compiling this model")
        .with_note("please report this with the input file");
    Diagnostics(vec![d])
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

/// Compiles a checked module with its base weights and the parameters of each variant:
/// runs the back-end passes and builds the plan. Returns the plan and any warnings.
pub fn compile_variants(
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
) -> Result<(Plan, Diagnostics), Diagnostics> {
    compile_explained(module, base, base_name, sources, opts).map(|(p, w, _)| (p, w))
}

/// [`compile_variants`], also returning the per-layer strategy `choose_strategy` decided
/// (`None` when no layer had a choice), for `readi compile --explain`.
pub fn compile_explained(
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
) -> Result<(Plan, Diagnostics, Option<passes::choose_strategy::Strategy>), Diagnostics> {
    let mut m = module.clone();
    let inputs = BackendInputs { base, base_name, variants: sources, opts };
    let warnings = passes::run_backend(&mut m, &inputs, None)?.warnings;
    let lowered = m.lowered.take().ok_or_else(|| ice(module, "the back end produced no plan".into()))?;
    let plan =
        Plan::new(lowered.manifest, lowered.data).map_err(|e| ice(module, format!("the plan is invalid: {e}")))?;
    Ok((plan, warnings, m.strategy.take()))
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
