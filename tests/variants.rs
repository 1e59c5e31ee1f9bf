//! Variant plans: parity with PyTorch + PEFT, switching, budgets and bad variant files.
//!
//! The PyTorch side (tests/fixtures/make_fixtures.py, `--only variants`) seeds the base
//! model with readi's generator, sets each variant's tuned and adapter parameters from the
//! generator with the variant's seed, adds a real PEFT LoRA (`init_lora_weights=False`) and
//! saves it with `save_pretrained`, and records the outputs. Here the same tuned and
//! adapter values are generated again, the committed PEFT directories are read, and every
//! variant must match PyTorch to 1e-4, with LoRA merged and as a branch.

mod common;

use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::variants::owned_params;
use readi_compiler::backend::{self, CompileOptions, LoraMode, VariantSource, WeightSet, peft, seeded_tensor};
use readi_compiler::ir::SlotKind;
use readi_grammar::diag::{Diagnostics, SourceMap};
use readi_runtime::exec::{Input, Session, Tensor};
use readi_runtime::plan::Plan;

const SEED: u64 = 2024;

struct Fixture {
    tensors: WeightSet,
    overrides: Vec<(String, String)>,
    /// Variant keys with their seeds.
    variants: Vec<(String, u64)>,
}

fn fixture(model: &str) -> Fixture {
    let path = common::root().join(format!("tests/fixtures/variants/{model}.safetensors"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).expect("header");
    let md = meta.metadata().clone().expect("metadata");
    let pairs = |key: &str, sep: char| -> Vec<(String, String)> {
        md[key]
            .split(',')
            .map(|kv| kv.rsplit_once(sep).map(|(k, v)| (k.to_string(), v.to_string())).expect("pair"))
            .collect()
    };
    let variants = pairs("variants", ':').into_iter().map(|(k, s)| (k, s.parse().expect("seed"))).collect();
    let overrides = pairs("overrides", '=');
    assert_eq!(md["seed"], SEED.to_string());
    Fixture { tensors: WeightSet::from_safetensors(model, &bytes).expect("fixture"), overrides, variants }
}

fn module(model: &str, overrides: &[(String, String)]) -> (SourceMap, Module) {
    let ov: Vec<(&str, &str)> = overrides.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    let (sources, out) = common::compile(&format!("models/{model}.readi"), &ov, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    (sources, out.module.expect("module"))
}

/// The seeded base weights, through a safetensors file.
fn base_weights(m: &Module) -> WeightSet {
    let bytes = backend::seeded_weights(&m.graph, SEED).to_safetensors().expect("serialise");
    WeightSet::from_safetensors("base.safetensors", &bytes).expect("valid")
}

/// A variant's tuned and adapter values from the generator, as the fixture script made
/// them, plus the committed PEFT adapter.
fn variant_source(model: &str, m: &Module, key: &str, seed: u64) -> VariantSource {
    let mut set = WeightSet::default();
    for (name, o) in owned_params(m) {
        if !name.contains(".lora_") {
            set.tensors.insert(name.clone(), (o.shape.clone(), seeded_tensor(seed, &name, &o.shape)));
        }
    }
    let bytes = set.to_safetensors().expect("serialise");
    let mut weights = WeightSet::from_safetensors("params.safetensors", &bytes).expect("valid");
    let dir = common::root().join(format!("tests/fixtures/variants/{model}/{key}"));
    let config = std::fs::read_to_string(dir.join(peft::CONFIG_FILE)).expect("config");
    let adapter = std::fs::read(dir.join(peft::WEIGHTS_FILE)).expect("adapter");
    let lora = peft::read_adapter(&dir.display().to_string(), &config, &adapter, m).expect("adapter reads");
    assert!(!lora.tensors.is_empty());
    weights.tensors.extend(lora.tensors);
    VariantSource { key: key.to_string(), weights, origin: format!("{key} files") }
}

fn compile(sources: &SourceMap, m: &Module, variants: &[VariantSource], lora: LoraMode) -> Plan {
    let opts = CompileOptions { lora, strict: true, ..Default::default() };
    let (plan, warnings) = backend::compile_variants(m, &base_weights(m), "base.safetensors", variants, &opts)
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    assert!(warnings.is_empty(), "{}", sources.render_all(&warnings, false));
    plan
}

fn inputs(fx: &WeightSet) -> Vec<Input<'_>> {
    fx.tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect()
}

fn max_abs_error(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

fn run_as(session: &mut Session, key: &str, fx: &WeightSet) -> Vec<(String, Tensor)> {
    session.set_variant(key).expect("known key");
    session.run(&inputs(fx)).expect("run")
}

fn check_parity(model: &str) {
    let fx = fixture(model);
    let (sources, m) = module(model, &fx.overrides);
    let variants: Vec<VariantSource> =
        fx.variants.iter().map(|(k, seed)| variant_source(model, &m, k, *seed)).collect();
    for lora in [LoraMode::Merge, LoraMode::Branch] {
        let plan = Arc::new(compile(&sources, &m, &variants, lora));
        assert_eq!(plan.manifest.variants.len(), variants.len());
        // Adapters and LoRA branches before a BatchNorm move behind it, so every BatchNorm
        // folds into its conv (the parity below checks that the moves are exact).
        let affine = plan.manifest.steps.iter().filter(|s| s.kernel.name() == "channel_affine").count();
        assert_eq!(affine, 0, "{model} (LoRA {}): unfused BatchNorms", lora.name());
        let mut session = Session::new(plan, 2).expect("session");
        for key in std::iter::once("base").chain(fx.variants.iter().map(|(k, _)| k.as_str())) {
            for (name, t) in run_as(&mut session, key, &fx.tensors) {
                let (shape, want) = &fx.tensors.tensors[&format!("{key}.{name}")];
                assert_eq!(&t.shape, shape);
                let err = max_abs_error(&t.data, want);
                eprintln!("{model} {key} (LoRA {}): `{name}` max abs error vs PyTorch + PEFT {err:e}", lora.name());
                assert!(err <= 1e-4, "{model} {key}: `{name}` differs from PyTorch by {err:e}");
            }
        }
    }
}

#[test]
fn resnet18_variants_match_pytorch_and_peft() {
    check_parity("resnet18");
}

#[test]
fn vit_variants_match_pytorch_and_peft() {
    check_parity("vit_encoder");
}

#[test]
fn switching_back_and_forth_is_bit_identical_to_a_fresh_run() {
    let fx = fixture("resnet18");
    let (sources, m) = module("resnet18", &fx.overrides);
    let variants: Vec<VariantSource> =
        fx.variants.iter().map(|(k, seed)| variant_source("resnet18", &m, k, *seed)).collect();
    let plan = Arc::new(compile(&sources, &m, &variants, LoraMode::Branch));
    let (a, b) = (&fx.variants[0].0, &fx.variants[1].0);
    let fresh = run_as(&mut Session::new(plan.clone(), 2).expect("session"), a, &fx.tensors);
    let mut s = Session::new(plan, 2).expect("session");
    let first = run_as(&mut s, a, &fx.tensors);
    let other = run_as(&mut s, b, &fx.tensors);
    let again = run_as(&mut s, a, &fx.tensors);
    let bits =
        |r: &[(String, Tensor)]| r.iter().flat_map(|(_, t)| t.data.iter().map(|v| v.to_bits())).collect::<Vec<_>>();
    assert_eq!(bits(&first), bits(&fresh));
    assert_eq!(bits(&again), bits(&fresh), "A -> B -> A drifted from a fresh run of A");
    assert_ne!(bits(&other), bits(&fresh), "the variants should differ");
}

/// Every bundled model compiles with several variants, and a variant stores only the
/// tensors its owned parameters reach.
#[test]
fn bundled_models_compile_with_variants() {
    for model in ["resnet18", "vit_encoder", "pointpillars_bev", "bevfusion_tiny"] {
        let (sources, m) = module(model, &[]);
        let keys = m.variants.as_ref().expect("variants").keys();
        let keys: Vec<String> = keys.into_iter().take(3).map(|k| k.to_string()).collect();
        let variants = backend::seeded_variants(&m, &keys, 100);
        let plan = compile(&sources, &m, &variants, LoraMode::Branch);
        let mf = &plan.manifest;
        assert_eq!(mf.variants.len(), 3, "{model}");
        // Budgets: tuned elements are the rule-selected slots, added the injected ones,
        // and the latter follow resolve_adapt's closed-form accounting.
        let adapt = m.adapt.as_ref().expect("adapt");
        let added_slots: u64 =
            m.graph.param_table().iter().filter(|(_, _, s)| s.kind == SlotKind::Added).map(|(_, _, s)| s.numel()).sum();
        assert_eq!(added_slots, adapt.added_elements(), "{model}: injected slots vs the rules' accounting");
        for v in &mf.variants {
            // Each variant's budget is its own scope's (all of it when nothing is scoped).
            let (tuned, added) = adapt.budget(&m.graph, &v.key);
            if !adapt.is_scoped() {
                assert_eq!((tuned, added), (adapt.tuned_elements(&m.graph), added_slots), "{model}");
            }
            assert_eq!(v.added_elements, added, "{model}");
            assert_eq!(v.tuned_elements, tuned, "{model}: the table agrees with `readi params`");
            assert!(v.tuned_elements > 0 && !v.replaces.is_empty(), "{model}");
            // A replacement has its base's shape and is not a base tensor.
            for r in &v.replaces {
                assert_eq!(mf.tensors[r.base].shape, mf.tensors[r.with].shape);
                assert!(r.with >= mf.steps.iter().flat_map(|s| s.kernel.tensors()).max().unwrap_or(0));
            }
        }
    }
}

#[test]
fn identical_variants_share_their_tensors_and_zero_variants_store_nothing() {
    let (sources, m) = module("resnet18", &[("num_classes".into(), "10".into())]);
    let owned = owned_params(&m);
    let base = backend::seeded_weights(&m.graph, SEED);
    let mut same = WeightSet::default();
    let mut transparent = WeightSet::default();
    for (name, o) in &owned {
        same.tensors.insert(name.clone(), (o.shape.clone(), seeded_tensor(7, name, &o.shape)));
        // Base values for tuned parameters, zeros for added ones: the base model again.
        let v = if o.added { vec![0.0; o.shape.iter().product()] } else { base.tensors[name].1.clone() };
        transparent.tensors.insert(name.clone(), (o.shape.clone(), v));
    }
    let sources_v = vec![
        VariantSource { key: "gamma=0.25".into(), weights: same.clone(), origin: "a".into() },
        VariantSource { key: "gamma=0.5".into(), weights: same, origin: "b".into() },
        VariantSource { key: "blur=5".into(), weights: transparent, origin: "c".into() },
    ];
    let plan = compile(&sources, &m, &sources_v, LoraMode::Merge);
    let v = &plan.manifest.variants;
    assert_eq!(v[0].replaces, v[1].replaces, "identical variants point at the same stored tensors");
    assert!(v[2].replaces.is_empty(), "a variant equal to the base stores nothing: {:?}", v[2].replaces.len());
    let stored: std::collections::HashSet<usize> = v.iter().flat_map(|t| t.replaces.iter().map(|r| r.with)).collect();
    assert_eq!(stored.len(), v[0].replaces.len());
}

/// Compiles resnet18 (10 classes) with one variant and returns the errors.
fn variant_errors(variant: VariantSource, strict: bool) -> (SourceMap, Diagnostics) {
    let (sources, m) = module("resnet18", &[("num_classes".into(), "10".into())]);
    let opts = CompileOptions { strict, ..Default::default() };
    match backend::compile_variants(&m, &base_weights(&m), "base.safetensors", &[variant], &opts) {
        Ok((_, warnings)) => (sources, warnings),
        Err(d) => (sources, d),
    }
}

fn one(key: &str, name: &str, shape: Vec<usize>) -> VariantSource {
    let mut set = WeightSet::default();
    let n = shape.iter().product();
    set.tensors.insert(name.into(), (shape, vec![0.5; n]));
    VariantSource { key: key.into(), weights: set, origin: "v.safetensors".into() }
}

#[test]
fn bad_variant_files_are_clear_errors() {
    let text = |(s, d): (SourceMap, Diagnostics)| (d.has_errors(), s.render_all(&d, false));

    let (err, msg) = text(variant_errors(one("fog=0.03", "fc.bias", vec![10]), false));
    assert!(err && msg.contains("variant key `fog=0.03` is not declared"), "{msg}");

    let (err, msg) = text(variant_errors(one("gamma=0.25", "conv1.weight", vec![64, 3, 7, 7]), false));
    assert!(err && msg.contains("`conv1.weight` is not per-variant") && msg.contains("a `tune` rule"), "{msg}");

    let (err, msg) = text(variant_errors(one("gamma=0.25", "fc.bias", vec![11]), false));
    assert!(err && msg.contains("`fc.bias` has shape [11], but the model needs [10]"), "{msg}");

    // One owned tensor given: the rest keep the base value, reported; an error when strict.
    let (err, msg) = text(variant_errors(one("gamma=0.25", "fc.bias", vec![10]), false));
    assert!(!err && msg.contains("warning") && msg.contains("keeps the base value"), "{msg}");
    let (err, msg) = text(variant_errors(one("gamma=0.25", "fc.bias", vec![10]), true));
    assert!(err && msg.contains("keep the base value"), "{msg}");

    // Keys are matched by value: `gamma=0.250` is `gamma=0.25`.
    let (err, _) = text(variant_errors(one("gamma=0.250", "fc.bias", vec![10]), false));
    assert!(!err);
}

#[test]
fn a_peft_adapter_that_disagrees_with_the_rule_is_an_error() {
    let fx = fixture("resnet18");
    let (sources, m) = module("resnet18", &fx.overrides);
    let dir = common::root().join("tests/fixtures/variants/resnet18/blur=5");
    let config = std::fs::read_to_string(dir.join(peft::CONFIG_FILE)).expect("config");
    let adapter = std::fs::read(dir.join(peft::WEIGHTS_FILE)).expect("adapter");
    let bad = config.replace("\"r\": 4", "\"r\": 8");
    assert_ne!(bad, config, "the fixture config has `\"r\": 4`");
    let d = peft::read_adapter("blur=5", &bad, &adapter, &m).expect_err("r disagrees with the rule");
    let msg = sources.render_all(&d, false);
    assert!(msg.contains("r = 8 (the rule's rank = 4)") && msg.contains("lora rank=4"), "{msg}");

    let dora = config.replace("\"use_dora\": false", "\"use_dora\": true");
    let d = peft::read_adapter("blur=5", &dora, &adapter, &m).expect_err("DoRA");
    assert!(sources.render_all(&d, false).contains("DoRA"));

    let d = peft::read_adapter("blur=5", "{\"r\": 4,", &adapter, &m).expect_err("bad JSON");
    assert!(sources.render_all(&d, false).contains("adapter_config.json:1:"), "names line and column");
}

#[test]
fn base_weights_must_not_hold_variant_parameters() {
    let (sources, m) = module("resnet18", &[("num_classes".into(), "10".into())]);
    let mut base = base_weights(&m);
    base.tensors.insert("layer1.0.bn2.adapter.up.bias".into(), (vec![64], vec![0.0; 64]));
    let d = backend::compile(&m, &base, "base.safetensors", &CompileOptions::default()).expect_err("error");
    let msg = sources.render_all(&d, false);
    assert!(msg.contains("belongs to the variants"), "{msg}");
}

/// LoRA merged or as a branch: the same outputs, different costs. Both plans have the
/// base's schedule (the branch runs inside its layer's kernel: `fuse_lora`); the branch
/// plan's variants are smaller.
#[test]
fn merged_and_branch_lora_agree() {
    let fx = fixture("vit_encoder");
    let (sources, m) = module("vit_encoder", &fx.overrides);
    let variants: Vec<VariantSource> =
        fx.variants.iter().map(|(k, seed)| variant_source("vit_encoder", &m, k, *seed)).collect();
    let merged = Arc::new(compile(&sources, &m, &variants, LoraMode::Merge));
    let branch = Arc::new(compile(&sources, &m, &variants, LoraMode::Branch));
    let base = Arc::new(compile(&sources, &m, &[], LoraMode::Merge));
    assert_eq!(merged.manifest.steps.len(), base.manifest.steps.len());
    assert_eq!(branch.manifest.steps.len(), base.manifest.steps.len());
    // Every LoRA layer (q, k, v and proj of each block) carries its branch.
    let fused = branch.manifest.steps.iter().filter(|s| s.kernel.lora().is_some()).count();
    let layers = owned_params(&m).into_iter().filter(|(n, _)| n.ends_with(".lora_A.weight")).count();
    assert!(layers > 0);
    assert_eq!(fused, layers);
    assert!(merged.manifest.steps.iter().all(|s| s.kernel.lora().is_none()));
    let lora_bytes = |p: &Plan| -> usize {
        p.manifest.variants[0].replaces.iter().filter(|r| r.added).map(|r| p.manifest.tensors[r.with].numel()).sum()
    };
    assert!(lora_bytes(&branch) < lora_bytes(&merged), "branch stores only A and B");
    let key = &fx.variants[0].0;
    let a = run_as(&mut Session::new(merged, 1).expect("s"), key, &fx.tensors);
    let b = run_as(&mut Session::new(branch, 1).expect("s"), key, &fx.tensors);
    for ((_, x), (_, y)) in a.iter().zip(&b) {
        assert!(max_abs_error(&x.data, &y.data) <= 1e-4);
    }
}

/// Adapters no variant gives values for compute zeros: they leave the schedule, so a set
/// of LoRA-only variants runs the base model's schedule.
#[test]
fn unused_adapters_leave_the_schedule() {
    let fx = fixture("resnet18");
    let (sources, m) = module("resnet18", &fx.overrides);
    let dir = common::root().join("tests/fixtures/variants/resnet18/blur=5");
    let config = std::fs::read_to_string(dir.join(peft::CONFIG_FILE)).expect("config");
    let adapter = std::fs::read(dir.join(peft::WEIGHTS_FILE)).expect("adapter");
    let lora = peft::read_adapter("blur=5", &config, &adapter, &m).expect("adapter reads");
    let only_lora = VariantSource { key: "blur=5".into(), weights: lora, origin: "peft".into() };
    let opts = CompileOptions::default();
    let base_w = base_weights(&m);
    let (with_lora, warnings) =
        backend::compile_variants(&m, &base_w, "base", &[only_lora], &opts).unwrap_or_else(|d| panic!("{d:?}"));
    assert!(sources.render_all(&warnings, false).contains("keeps the base value"));
    let base = compile(&sources, &m, &[], LoraMode::Merge);
    assert_eq!(with_lora.manifest.steps.len(), base.manifest.steps.len());
    let with_adapters = compile(&sources, &m, &[variant_source("resnet18", &m, "blur=5", 7)], LoraMode::Merge);
    // Each adapter runs in the kernel of the conv before it (`fuse_adapters`).
    assert_eq!(with_adapters.manifest.steps.len(), base.manifest.steps.len());
    assert!(with_adapters.manifest.steps.iter().any(|s| s.kernel.adapter().is_some()));
    assert!(base.manifest.steps.iter().all(|s| s.kernel.adapter().is_none()));
}

/// Convs of every algorithm with a LoRA branch each, and a linear: Winograd F(4x4) and
/// F(2x2) at 3x3, the 1x1 GEMM, im2col at stride 2 and dilation 2.
const FUSED: &str = "model m {
  input x: f32[N, 32, 24, 24] @camera
  w4 = conv2d(x, 32, kernel=3, padding=1, bias=false)
  n4 = batchnorm(w4)
  small = maxpool(relu(n4), kernel=2)
  w2 = conv2d(small, 40, kernel=3, padding=1, bias=false)
  n2 = batchnorm(w2)
  pw = conv2d(relu(n2), 24, kernel=1)
  s2 = conv2d(pw, 16, kernel=3, stride=2, padding=2, dilation=2)
  fc = linear(flatten(relu(s2), start=1), 10)
  output y = fc
}
adapt {
  tune batchnorm
  lora rank=4 alpha=8 on w4
  lora rank=4 alpha=8 on w2
  lora rank=4 alpha=8 on pw
  lora rank=4 alpha=8 on s2
  lora rank=4 alpha=8 on fc
}
variants {
  axis fog on camera: 0.03, 0.06 clear 0
}
";

/// A LoRA branch fused into a conv of every algorithm (Winograd F(4x4) and F(2x2), the
/// 1x1 GEMM, im2col at stride 2 and dilation 2) and a linear layer, each followed by a
/// tuned BatchNorm (or a ReLU): the branch plan's outputs are the merged plan's, whose
/// weights `W + scale B A` the compiler computed in f64; at batch 1 and 3, on 1 and 2
/// threads.
#[test]
fn fused_branches_match_merged_lora_on_every_algorithm() {
    let spec = FUSED;
    let (sources, out) = common::compile_text("fused.readi", spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = vec!["fog=0.03".to_string(), "fog=0.06".to_string()];
    let variants = backend::seeded_variants(&m, &keys, SEED + 1);
    let merged = Arc::new(compile(&sources, &m, &variants, LoraMode::Merge));
    let branch = Arc::new(compile(&sources, &m, &variants, LoraMode::Branch));
    assert_eq!(branch.manifest.steps.len(), merged.manifest.steps.len());
    let algos: Vec<String> = branch
        .manifest
        .steps
        .iter()
        .filter(|s| s.kernel.lora().is_some())
        .map(|s| match &s.kernel {
            readi_runtime::plan::Kernel::Conv2d { algo, .. } => algo.name().to_string(),
            k => k.name().to_string(),
        })
        .collect();
    assert_eq!(algos, ["winograd4", "winograd2", "gemm1x1", "im2col", "linear"]);
    branch_matches_merged(&merged, &branch, [32, 24, 24], 5);
}

/// The branch plan's outputs are the merged plan's (to 1e-5 of the output's scale) under
/// the base and both variants, at batch 1 and 3 of a seeded input `x` of `chw`, on 1 and 2
/// threads.
fn branch_matches_merged(merged: &Arc<Plan>, branch: &Arc<Plan>, chw: [usize; 3], seed: u64) {
    for batch in [1usize, 3] {
        let shape = [&[batch][..], &chw[..]].concat();
        let x = seeded_tensor(seed, "x", &shape);
        let input = [Input { name: "x", data: &x, shape: &shape }];
        for threads in [1, 2] {
            let mut a = Session::new(merged.clone(), threads).expect("session");
            let mut b = Session::new(branch.clone(), threads).expect("session");
            for key in ["base", "fog=0.03", "fog=0.06"] {
                a.set_variant(key).expect("key");
                b.set_variant(key).expect("key");
                let (ya, yb) = (a.run(&input).expect("run"), b.run(&input).expect("run"));
                let scale = ya[0].1.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                let err = max_abs_error(&ya[0].1.data, &yb[0].1.data);
                assert!(
                    err <= 1e-5 * scale.max(1.0),
                    "{key}, batch {batch}, {threads} threads: {err:e} (scale {scale})"
                );
            }
        }
    }
}

/// A conv of weight panels (a 6x6 plane; 128 -> 320 channels, a weight too large for
/// im2col's register tiles) with a LoRA branch: its kernel reads `A` raw, so the plan
/// stores it raw; the branch plan's outputs are the merged plan's, at batch 1 and 3, on 1
/// and 2 threads.
#[test]
fn a_lora_branch_on_weight_panels_matches_the_merged_weight() {
    let spec = "model m {
  input x: f32[N, 128, 12, 12] @camera
  p = conv2d(x, 320, kernel=3, stride=2, padding=1, bias=false)
  n = batchnorm(p)
  fc = linear(flatten(relu(n), start=1), 10)
  output y = fc
}
adapt {
  tune batchnorm
  lora rank=4 alpha=8 on p
}
variants {
  axis fog on camera: 0.03, 0.06 clear 0
}
";
    let (sources, out) = common::compile_text("panels.readi", spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = vec!["fog=0.03".to_string(), "fog=0.06".to_string()];
    let variants = backend::seeded_variants(&m, &keys, SEED + 2);
    let merged = Arc::new(compile(&sources, &m, &variants, LoraMode::Merge));
    let branch = Arc::new(compile(&sources, &m, &variants, LoraMode::Branch));
    let conv = |p: &Plan| {
        p.manifest.steps.iter().find_map(|s| match &s.kernel {
            readi_runtime::plan::Kernel::Conv2d { algo, lora, .. } => {
                Some((algo.name(), lora.map(|l| (l.a_raw, p.manifest.tensors[l.a].numel()))))
            }
            _ => None,
        })
    };
    assert_eq!(conv(&merged), Some(("panels", None)));
    assert_eq!(conv(&branch), Some(("panels", Some((true, 4 * 128 * 9)))));
    branch_matches_merged(&merged, &branch, [128, 12, 12], 7);
}

/// A branch plan's outputs under `key` from a fresh session on 2 threads.
fn fresh_run(plan: &Arc<Plan>, key: &str, input: &[Input<'_>]) -> Vec<f32> {
    let mut s = Session::new(Arc::clone(plan), 2).expect("session");
    s.set_variant(key).expect("key");
    s.run(input).expect("run").remove(0).1.data
}

/// A Winograd layer's LoRA `A` is stored raw (9 floats per 3x3 per rank per input channel)
/// and packed by the session when a run's variant differs from the one it packed last:
/// switching back and forth gives a fresh session's outputs bit for bit, a run while
/// another thread switches sees exactly one variant, and a crafted raw `A` is refused.
#[test]
fn a_raw_winograd_lora_a_is_packed_for_each_runs_variant() {
    use readi_runtime::plan::Kernel;
    let (sources, out) = common::compile_text("fused.readi", FUSED, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = vec!["fog=0.03".to_string(), "fog=0.06".to_string()];
    let variants = backend::seeded_variants(&m, &keys, SEED + 1);
    let plan = Arc::new(compile(&sources, &m, &variants, LoraMode::Branch));
    let stored: Vec<(&str, bool, usize)> = plan
        .manifest
        .steps
        .iter()
        .filter_map(|s| match &s.kernel {
            Kernel::Conv2d { algo, lora: Some(l), .. } => {
                Some((algo.name(), l.a_raw, plan.manifest.tensors[l.a].numel()))
            }
            _ => None,
        })
        .collect();
    // w4 and w2 read 32 channels, pw 40 (1x1), s2 24: the GEMM paths' packing is the raw
    // layout, so only the Winograd layers need the flag.
    assert_eq!(
        stored,
        [
            ("winograd4", true, 4 * 32 * 9),
            ("winograd2", true, 4 * 32 * 9),
            ("gemm1x1", false, 4 * 40),
            ("im2col", false, 4 * 24 * 9)
        ]
    );

    // A -> B -> A (and the base) in one session: a fresh session's outputs, bit for bit.
    let shape = vec![2, 32, 24, 24];
    let x = seeded_tensor(6, "x", &shape);
    let input = [Input { name: "x", data: &x, shape: &shape }];
    let want: Vec<Vec<f32>> = ["base", "fog=0.03", "fog=0.06"].iter().map(|k| fresh_run(&plan, k, &input)).collect();
    assert!(want[1] != want[2] && want[0] != want[1], "the variants must differ");
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    for k in [1, 2, 1, 0, 2, 2, 1] {
        s.set_variant(["base", "fog=0.03", "fog=0.06"][k]).expect("key");
        assert_eq!(s.run(&input).expect("run")[0].1.data, want[k], "variant {k}");
    }

    // Another thread switches between A and B meanwhile: each run is one of them, the one
    // the session reports.
    let handle = s.switch_handle();
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let switcher = {
        let (handle, stop) = (handle.clone(), Arc::clone(&stop));
        std::thread::spawn(move || {
            let mut n = 0u64;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                handle.set("fog=0.03").expect("key");
                handle.set("fog=0.06").expect("key");
                n += 2;
            }
            n
        })
    };
    let (mut seen, mut i) = ([0usize; 3], 0);
    while i < 200 || ((seen[1] == 0 || seen[2] == 0) && i < 10_000) {
        i += 1;
        let y = s.run(&input).expect("run").remove(0).1.data;
        let used = s.last_variant().expect("ran");
        assert!(used == 1 || used == 2, "run {i}: variant {used}");
        assert_eq!(y, want[used], "run {i}: not variant {used}'s outputs");
        seen[used] += 1;
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    assert!(switcher.join().expect("switcher") > 2);
    assert!(seen[1] > 0 && seen[2] > 0, "{seen:?}");

    // Crafted plans: a raw A read as packed, a rank its raw length does not fit, a raw A
    // on a linear. Refused when the plan is made, with the tensor's name.
    let tensors: Vec<Vec<f32>> = (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect();
    type Edit = fn(&mut readi_runtime::plan::LoraSpec);
    let cases: [(usize, Edit, &str); 3] = [
        (0, |l| l.a_raw = false, "`winograd4` at rank 4 needs 4608"),
        (1, |l| l.rank = 3, "`raw` at rank 3 needs 864"),
        (4, |l| l.a_raw = true, "cannot be stored raw"),
    ];
    for (which, edit, want) in cases {
        let mut manifest = plan.manifest.clone();
        let step = manifest.steps.iter_mut().filter(|s| s.kernel.lora().is_some()).nth(which).expect("step");
        match &mut step.kernel {
            Kernel::Conv2d { lora: Some(l), .. } | Kernel::Linear { lora: Some(l), .. } => edit(l),
            _ => unreachable!("a LoRA step"),
        }
        let err = Plan::new(manifest, tensors.clone()).expect_err("refused").to_string();
        assert!(err.contains(want) && err.contains("lora_A"), "case {which}: {err}");
    }
}

/// [`FUSED`] with a tuned Winograd conv `t4` (no LoRA): each of its variants owns the
/// conv's weight and bias.
const SWITCHED: &str = "model m {
  input x: f32[N, 32, 24, 24] @camera
  w4 = conv2d(x, 32, kernel=3, padding=1, bias=false)
  n4 = batchnorm(w4)
  t4 = conv2d(relu(n4), 32, kernel=3, padding=1)
  small = maxpool(relu(t4), kernel=2)
  w2 = conv2d(small, 40, kernel=3, padding=1, bias=false)
  n2 = batchnorm(w2)
  pw = conv2d(relu(n2), 24, kernel=1)
  s2 = conv2d(pw, 16, kernel=3, stride=2, padding=2, dilation=2)
  fc = linear(flatten(relu(s2), start=1), 10)
  output y = fc
}
adapt {
  tune batchnorm
  tune t4
  lora rank=4 alpha=8 on w4
  lora rank=4 alpha=8 on w2
  lora rank=4 alpha=8 on pw
  lora rank=4 alpha=8 on s2
  lora rank=4 alpha=8 on fc
}
variants {
  axis fog on camera: 0.03, 0.06 clear 0
}
";

/// [`SWITCHED`] compiled with every conv it can merge on switch merged on switch (an
/// unreachable memory budget keeps the free savings; a switch budget nothing exceeds),
/// and with `--lora merge`.
fn switched_plans() -> (Arc<Plan>, Arc<Plan>) {
    use readi_compiler::passes::choose_strategy::{Conv2dShape, ConvAlgo, Timing};
    let (sources, out) = common::compile_text("switched.readi", SWITCHED, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = vec!["fog=0.03".to_string(), "fog=0.06".to_string()];
    let variants = backend::seeded_variants(&m, &keys, SEED + 1);
    let weights = base_weights(&m);
    // Multiply-adds, 1e-6 ms each; Winograd does 4x (F(4x4)) or 2.25x (F(2x2)) fewer.
    fn kernel(s: &Conv2dShape, algo: ConvAlgo) -> f64 {
        let speed = match algo {
            ConvAlgo::Winograd4 => 4.0,
            ConvAlgo::Winograd2 => 2.25,
            _ => 1.0,
        };
        (s.cout * s.k() * s.oh * s.ow) as f64 * 1e-6 / speed
    }
    fn switch(_: &Conv2dShape, _: ConvAlgo, _: usize) -> f64 {
        0.01
    }
    let opts = CompileOptions {
        lora: LoraMode::Auto,
        memory_budget: Some(0.0),
        switch_budget: Some(1.0),
        timing: Timing::FixedSwitch(kernel, switch),
        ..Default::default()
    };
    let (plan, warnings) = backend::compile_variants(&m, &weights, "base.safetensors", &variants, &opts)
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    assert_eq!(warnings.0.len(), 1, "{}", sources.render_all(&warnings, false));
    assert!(warnings.0[0].message.contains("kept the fastest assignment"), "{}", warnings.0[0].message);
    let merged = compile(&sources, &m, &variants, LoraMode::Merge);
    (Arc::new(plan), Arc::new(merged))
}

/// Merge on switch: the plan stores each switched conv's weight raw and its variants only
/// raw tensors (raw `A` and `B`, a tuned conv's raw weight); a session computes what the
/// merged-per-variant plan computes (to rounding: it merges the pre-scaled `B`), A -> B ->
/// A gives a fresh session's outputs bit for bit, the stored tensors are never written,
/// and a run while another thread switches sees exactly one variant.
#[test]
fn merge_on_switch_is_consistent_exact_and_thread_safe() {
    use readi_runtime::plan::Kernel;
    let (plan, merged) = switched_plans();
    let m = &plan.manifest;
    let switched: Vec<(&str, &str, usize, bool)> = m
        .steps
        .iter()
        .filter_map(|s| match &s.kernel {
            Kernel::Conv2d { algo, weight, lora, switch: true, .. } => {
                Some((s.path.as_str(), algo.name(), m.tensors[*weight].numel(), lora.is_some()))
            }
            _ => None,
        })
        .collect();
    // Every conv: raw weights (9 floats per 3x3 per channel pair) at each algorithm.
    let paths: Vec<&str> = switched.iter().map(|s| s.0.split(' ').next().expect("path")).collect();
    assert_eq!(paths, ["w4", "t4", "w2", "pw", "s2"], "{switched:?}");
    let want_algos = ["winograd4", "winograd4", "winograd2", "gemm1x1", "im2col"];
    let want_len = [32 * 32 * 9, 32 * 32 * 9, 40 * 32 * 9, 24 * 40, 16 * 24 * 9];
    for (i, s) in switched.iter().enumerate() {
        assert_eq!((s.1, s.2, s.3), (want_algos[i], want_len[i], i != 1), "{s:?}");
    }
    // A variant stores no packed weight: only raw ones (t4's), raw A and B, BatchNorm
    // affines, the fc's merged weight.
    for v in &m.variants {
        for r in &v.replaces {
            let name = &m.tensors[r.with].name;
            assert!(!name.contains("@winograd"), "{} stores {name}", v.key);
        }
    }

    let shape = vec![2, 32, 24, 24];
    let x = seeded_tensor(6, "x", &shape);
    let input = [Input { name: "x", data: &x, shape: &shape }];
    let keys = ["base", "fog=0.03", "fog=0.06"];
    let stored: Vec<Vec<u32>> =
        (0..m.tensors.len()).map(|i| plan.tensor(i).iter().map(|v| v.to_bits()).collect()).collect();
    let want: Vec<Vec<f32>> = keys.iter().map(|k| fresh_run(&plan, k, &input)).collect();
    assert!(want[1] != want[2] && want[0] != want[1], "the variants must differ");
    // The merged-per-variant plan, to within 1e-6 of the output's scale.
    for (k, key) in keys.iter().enumerate() {
        let y = fresh_run(&merged, key, &input);
        let scale = y.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1.0);
        let err = max_abs_error(&y, &want[k]);
        assert!(err <= 1e-6 * scale, "{key}: {err:e} (scale {scale})");
    }
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    for k in [1, 2, 1, 0, 2, 2, 1, 0] {
        s.set_variant(keys[k]).expect("key");
        assert_eq!(s.run(&input).expect("run")[0].1.data, want[k], "variant {k}");
    }
    // Batch 1 rebinds (new buffers): still the right variant.
    let shape1 = vec![1, 32, 24, 24];
    let input1 = [Input { name: "x", data: &x[..32 * 24 * 24], shape: &shape1 }];
    let want1 = fresh_run(&plan, "fog=0.06", &input1);
    s.set_variant("fog=0.06").expect("key");
    assert_eq!(s.run(&input1).expect("run")[0].1.data, want1);
    s.set_variant("fog=0.03").expect("key");
    assert_eq!(s.run(&input).expect("run")[0].1.data, want[1]);

    // Another thread switches meanwhile: each run is one variant, the one reported.
    let handle = s.switch_handle();
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let switcher = {
        let (handle, stop) = (handle.clone(), Arc::clone(&stop));
        std::thread::spawn(move || {
            let mut n = 0u64;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                handle.set("fog=0.03").expect("key");
                handle.set("fog=0.06").expect("key");
                handle.set("base").expect("key");
                n += 3;
            }
            n
        })
    };
    let (mut seen, mut i) = ([0usize; 3], 0);
    while i < 200 || (seen.contains(&0) && i < 10_000) {
        i += 1;
        let y = s.run(&input).expect("run").remove(0).1.data;
        let used = s.last_variant().expect("ran");
        assert_eq!(y, want[used], "run {i}: not variant {used}'s outputs");
        seen[used] += 1;
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    assert!(switcher.join().expect("switcher") > 3);
    assert!(!seen.contains(&0), "{seen:?}");
    // The stored tensors (the base's and the variants') are as they were.
    for (i, bits) in stored.iter().enumerate() {
        assert!(plan.tensor(i).iter().map(|v| v.to_bits()).eq(bits.iter().copied()), "tensor {i} was written");
    }
    // The working copies are the session's, counted once (not per variant).
    let f = readi_runtime::exec::footprint(&plan, 1, 1).expect("footprint");
    let packed: usize = [32 * 32 * 36, 32 * 32 * 36, 40 * 32 * 16, 24 * 40, 16 * 24 * 9].iter().sum();
    // With the raw buffer of the largest Winograd layer with LoRA (w2: 40 * 32 * 9).
    assert_eq!(f.working, (packed + 40 * 32 * 9) * 4);
}

/// Crafted merge-on-switch plans are refused when the plan is made, naming the tensor.
#[test]
fn crafted_merge_on_switch_plans_are_refused() {
    use readi_runtime::plan::Kernel;
    let (plan, merged_plan) = switched_plans();
    let tensors: Vec<Vec<f32>> = (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect();
    type Edit = fn(&mut Kernel);
    let cases: [(&str, Edit, &str); 3] = [
        // A raw weight read as packed.
        (
            "w4",
            |k| {
                if let Kernel::Conv2d { switch, .. } = k {
                    *switch = false
                }
            },
            "`winograd4` needs 36864",
        ),
        // The LoRA A packed (it must be raw to be merged).
        (
            "w4",
            |k| {
                if let Kernel::Conv2d { lora: Some(l), .. } = k {
                    l.a_raw = false
                }
            },
            "must be stored raw",
        ),
        // A rank the raw A and B do not fit.
        (
            "w2",
            |k| {
                if let Kernel::Conv2d { lora: Some(l), .. } = k {
                    l.rank = 3
                }
            },
            "at rank 3 needs",
        ),
    ];
    for (path, edit, want) in cases {
        let mut manifest = plan.manifest.clone();
        let step = manifest.steps.iter_mut().find(|s| s.path.split(' ').next() == Some(path)).expect("step");
        edit(&mut step.kernel);
        let err = Plan::new(manifest, tensors.clone()).expect_err("refused").to_string();
        assert!(err.contains(want) && err.contains(path), "{path}: {err}");
    }
    // A packed (Winograd) weight marked raw: its length is the packed one.
    let mut manifest = merged_plan.manifest.clone();
    let tensors: Vec<Vec<f32>> = (0..manifest.tensors.len()).map(|i| merged_plan.tensor(i).to_vec()).collect();
    let step = manifest.steps.iter_mut().find(|s| s.path.starts_with("t4")).expect("t4");
    if let Kernel::Conv2d { switch, .. } = &mut step.kernel {
        *switch = true;
    }
    let err = Plan::new(manifest, tensors).expect_err("refused").to_string();
    assert!(err.contains("`raw` needs 9216") && err.contains("t4"), "{err}");
}
