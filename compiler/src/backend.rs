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

/// What the spec's `prune` rules did to a plan: the shared weights they select, with how
/// many values each lost, and how far the pruned plan's outputs move.
#[derive(Clone, Debug, PartialEq)]
pub struct PruneSummary {
    pub layers: Vec<passes::prune::PrunedLayer>,
    /// Per output, the largest absolute difference between the pruned plan and the same
    /// plan compiled without pruning, over the base and every variant, on seeded inputs
    /// (batch 1, uniform in [-1, 1), [`PRUNE_INPUT_SEED`]).
    pub output_difference: Vec<(String, f32)>,
}

impl PruneSummary {
    /// Values zeroed and elements of the selected shared weights.
    pub fn totals(&self) -> (u64, u64) {
        (self.layers.iter().map(|l| l.zeroed).sum(), self.layers.iter().map(|l| l.total).sum())
    }
}

/// What `--variant-f16` did to a plan: the weights whose variant values it stores at
/// half precision, the bytes that saved, and how far the outputs move.
#[derive(Clone, Debug, PartialEq)]
pub struct HalfSummary {
    /// The parameters stored f16 (`fc.weight`), the largest first.
    pub params: Vec<String>,
    /// Bytes of the f16 tensors in the plan, and what they would take at f32.
    pub stored: (u64, u64),
    /// Per output, the largest absolute difference between the plan and the same model
    /// compiled without `--variant-f16`, over the base and every variant, on seeded
    /// inputs ([`PRUNE_INPUT_SEED`]).
    pub output_difference: Vec<(String, f32)>,
}

impl HalfSummary {
    /// One line for `readi compile`.
    pub fn line(&self) -> String {
        let worst = self.output_difference.iter().map(|(_, d)| *d).fold(0.0f32, f32::max);
        const SHOWN: usize = 4;
        let mut names = self.params.iter().take(SHOWN).cloned().collect::<Vec<_>>().join(", ");
        if self.params.len() > SHOWN {
            names += &format!(" and {} more", self.params.len() - SHOWN);
        }
        format!(
            "stored the variants' {names} at f16: {} instead of {}; outputs differ by at most {worst:.2e} from f32 on \
             seeded inputs",
            crate::print::bytes(self.stored.0),
            crate::print::bytes(self.stored.1)
        )
    }
}

/// The effect of `--variant-f16` on `plan`, which [`compile_explained`] built from these
/// arguments with `strategy`: `None` when the strategy stores no weight f16; else the
/// output difference against the module compiled again without it.
#[allow(clippy::too_many_arguments)]
pub fn half_summary(
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
    plan: std::sync::Arc<Plan>,
    strategy: Option<&passes::choose_strategy::Strategy>,
) -> Result<Option<HalfSummary>, Diagnostics> {
    let Some(s) = strategy.filter(|s| !s.half.is_empty()) else { return Ok(None) };
    // `choose_strategy` lists them largest first.
    let params = s.half.iter().map(|h| h.param.clone()).collect();
    let half = plan.manifest.tensors.iter().filter(|t| t.dtype == readi_plan::DType::F16);
    let stored = half.map(|t| t.bytes() as u64).sum::<u64>();
    let exact = CompileOptions { variant_f16: false, ..opts.clone() };
    let output_difference = difference_from(plan, module, base, base_name, sources, &exact)?;
    Ok(Some(HalfSummary { params, stored: (stored, stored * 2), output_difference }))
}

/// One line per melded variant: how many of its layers were taken whole from one part
/// and how many interpolated (the `meld` pass's record). Empty without melds.
pub fn meld_summary(
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
) -> Result<Vec<String>, Diagnostics> {
    if opts.melds.is_empty() {
        return Ok(Vec::new());
    }
    let mut m = module.clone();
    let inputs = BackendInputs { base, base_name, variants: sources, opts };
    passes::run_backend(&mut m, &inputs, Some(passes::Pass::Meld))?;
    let table = m.tensors.as_ref().ok_or_else(|| ice(module, "no tensor table after `meld`".into()))?;
    Ok(table
        .variants
        .iter()
        .filter(|v| v.key.is_meld())
        .map(|v| format!("variant `{}`: {}", v.key, v.origin))
        .collect())
}

/// The seed of the inputs [`prune_summary`] and [`half_summary`] run both plans on.
pub const PRUNE_INPUT_SEED: u64 = 7;

/// The effect of the module's `prune` rules on `pruned`, the plan
/// [`compile_variants`] built from these arguments: the counts `prune` found, and the
/// output difference against the module compiled again with the rules' thresholds at 0.
/// `None` when the spec has no `prune` rule.
pub fn prune_summary(
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
    pruned: std::sync::Arc<Plan>,
) -> Result<Option<PruneSummary>, Diagnostics> {
    let is_prune = |r: &crate::adapt::ResolvedRule| matches!(r.kind, crate::adapt::RuleKind::Prune { .. });
    if !module.adapt.as_ref().is_some_and(|a| a.rules.iter().any(is_prune)) {
        return Ok(None);
    }
    let mut melded = module.clone();
    let inputs = BackendInputs { base, base_name, variants: sources, opts };
    passes::run_backend(&mut melded, &inputs, Some(passes::Pass::Meld))?;
    let table = melded.tensors.as_ref().ok_or_else(|| ice(module, "no tensor table after `meld`".into()))?;
    let layers = passes::prune::report(&melded, table);
    // The same module with every threshold at 0 (|x| < 0 never holds): rule indices, which
    // the injections refer to, stay as they are.
    let mut plain = module.clone();
    for r in plain.adapt.iter_mut().flat_map(|a| a.rules.iter_mut()).filter(|r| is_prune(r)) {
        r.kind = crate::adapt::RuleKind::Prune { below: 0.0 };
    }
    let output_difference = difference_from(pruned, &plain, base, base_name, sources, opts)?;
    Ok(Some(PruneSummary { layers, output_difference }))
}

/// Per output, how far `plan` is from `module` compiled with `opts` ([`output_difference`]
/// on [`PRUNE_INPUT_SEED`]'s inputs): what a lossy step (pruning, f16 storage) moved.
fn difference_from(
    plan: std::sync::Arc<Plan>,
    module: &Module,
    base: &WeightSet,
    base_name: &str,
    sources: &[VariantSource],
    opts: &CompileOptions,
) -> Result<Vec<(String, f32)>, Diagnostics> {
    let (other, _) = compile_variants(module, base, base_name, sources, opts)?;
    output_difference(plan, std::sync::Arc::new(other), PRUNE_INPUT_SEED)
        .map_err(|e| ice(module, format!("running the plans to compare them: {e}")))
}

/// Per output, the largest absolute difference between two plans of one model over the
/// base and every variant of `a`, on seeded inputs at batch 1.
pub fn output_difference(
    a: std::sync::Arc<Plan>,
    b: std::sync::Arc<Plan>,
    seed: u64,
) -> Result<Vec<(String, f32)>, String> {
    use readi_runtime::exec::{Input, Session};
    let mut rng = SplitMix(seed);
    let inputs: Vec<(String, Vec<usize>, Vec<f32>)> = a
        .manifest
        .input_shapes(1)
        .into_iter()
        .map(|(name, shape)| {
            let data = (0..shape.iter().product()).map(|_| rng.uniform()).collect();
            (name.to_string(), shape, data)
        })
        .collect();
    let feed: Vec<Input<'_>> = inputs.iter().map(|(name, shape, data)| Input { name, data, shape }).collect();
    let keys: Vec<String> =
        std::iter::once("base".to_string()).chain(a.manifest.variants.iter().map(|v| v.key.to_string())).collect();
    let mut sa = Session::new(a, 2).map_err(|e| e.to_string())?;
    let mut sb = Session::new(b, 2).map_err(|e| e.to_string())?;
    let mut out: Vec<(String, f32)> = Vec::new();
    for key in &keys {
        sa.set_variant(key).map_err(|e| e.to_string())?;
        sb.set_variant(key).map_err(|e| e.to_string())?;
        let ya = sa.run(&feed).map_err(|e| e.to_string())?;
        let yb = sb.run(&feed).map_err(|e| e.to_string())?;
        for ((name, x), (_, y)) in ya.iter().zip(&yb) {
            let d = x.data.iter().zip(&y.data).map(|(p, q)| (p - q).abs()).fold(0.0f32, f32::max);
            match out.iter_mut().find(|(n, _)| n == name) {
                Some((_, m)) => *m = m.max(d),
                None => out.push((name.clone(), d)),
            }
        }
    }
    Ok(out)
}

/// Deterministic weights for every parameter of the base model: see [`seeded_tensor`].
pub fn seeded_weights(graph: &Graph, seed: u64) -> WeightSet {
    let mut set = WeightSet::default();
    for (name, id, slot) in graph.param_table() {
        if slot.dtype == readi_grammar::ast::DType::I64 && matches!(graph.node(id).op, crate::ir::Op::Buffer(_)) {
            // An index buffer: zeros, an index valid for any table.
            let shape: Vec<usize> = slot.shape.iter().map(|&d| d as usize).collect();
            let zeros = vec![0.0; shape.iter().product()];
            set.integer.insert(name.clone());
            set.tensors.insert(name, (shape, zeros));
            continue;
        }
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
/// that key owns (within its scope) gets [`seeded_tensor`] with seed `seed + i` (LoRA `B` and adapter `up`
/// included, so no variant equals the base). For demos, tests and benchmarks.
pub fn seeded_variants(module: &Module, keys: &[String], seed: u64) -> Vec<VariantSource> {
    let owned = variants::owned_params(module);
    keys.iter()
        .enumerate()
        .map(|(i, key)| {
            let mut weights = WeightSet::default();
            // What the key owns (a key that does not parse gets everything; binding reports it).
            let k = readi_plan::VariantKey::parse(key).ok();
            for (name, o) in owned.iter().filter(|(_, o)| k.as_ref().is_none_or(|k| o.is_owned_by(k))) {
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
