//! The per-layer strategy (`choose_strategy`): the chooser with fixed kernel costs
//! (hand-derived choices), plans whose layers mix merge and branch computing what the
//! all-merge and all-branch plans compute, and the bytes it reports against the plan's
//! own variant tables.
//!
//! The spec is torchvision's ResNet-18 with PEFT LoRA r=4 alpha=8 on every 3x3 conv of
//! layer3 and layer4, every BatchNorm and the classifier tuned.

mod common;

use std::collections::HashSet;
use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, LoraMode};
use readi_compiler::passes::choose_strategy::{self, Conv2dShape, ConvAlgo, Strategy, Timing};
use readi_plan::format::Manifest;
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::Plan;

const ADAPT: &str = "adapt {
  tune batchnorm
  tune fc
  lora rank=4 alpha=8 on layer3.{0,1}.{conv1,conv2}, layer4.{0,1}.{conv1,conv2}
}";

/// ResNet-18 with [`ADAPT`] for its `adapt` section, at `img` pixels and 10 classes.
fn module(img: &str) -> Module {
    module_of(img, "10")
}

/// The same with `classes` classes.
fn module_of(img: &str, classes: &str) -> Module {
    let text = std::fs::read_to_string(common::root().join("models/resnet18.readi")).expect("spec");
    let start = text.find("adapt {").expect("adapt section");
    let end = start + text[start..].find("\n}").expect("end of adapt") + 2;
    let text = format!("{}{ADAPT}{}", &text[..start], &text[end..]);
    let (sources, out) =
        common::compile_text("resnet18_lora.readi", &text, &[("num_classes", classes), ("img", img)], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

/// The image size of the budget tests: at 448 pixels ResNet-18's layer3 runs at 28x28 (its
/// stride-1 convs by Winograd F(4x4)) and layer4 at 14x14 (F(2x2)), so the budgets choose
/// among every algorithm (at 224, layer3 takes F(2x2) and layer4 im2col).
const IMG: &str = "448";

const KEYS: [&str; 2] = ["gamma=0.25", "blur=5"];

/// Milliseconds proportional to multiply-adds: Winograd F(4x4) does 4x fewer, F(2x2)
/// 2.25x fewer; 1e-6 ms each.
fn macs(s: &Conv2dShape, algo: ConvAlgo) -> f64 {
    let m = (s.cout * s.k() * s.oh * s.ow) as f64;
    let speed = match algo {
        ConvAlgo::Winograd4 => 4.0,
        ConvAlgo::Winograd2 => 2.25,
        _ => 1.0,
    };
    m / speed * 1e-6
}

fn opts(lora: LoraMode, budget: Option<f64>) -> CompileOptions {
    CompileOptions { lora, memory_budget: budget, timing: Timing::Fixed(macs), ..CompileOptions::default() }
}

fn compile(m: &Module, o: &CompileOptions) -> (Plan, Vec<String>, Option<Strategy>) {
    let weights = backend::seeded_weights(&m.graph, 11);
    let keys: Vec<String> = KEYS.iter().map(|k| k.to_string()).collect();
    let variants = backend::seeded_variants(m, &keys, 12);
    let (plan, warnings, s) = backend::compile_explained(m, &weights, "<seeded>", &variants, o).expect("compiles");
    (plan, warnings.0.iter().map(|d| d.message.clone()).collect(), s)
}

/// Per variant, the bytes of the tensors its table replaces (each once), from the plan.
fn plan_variant_bytes(m: &Manifest) -> Vec<u64> {
    m.variants
        .iter()
        .map(|v| {
            let own: HashSet<usize> = v.replaces.iter().map(|r| r.with).collect();
            own.iter().map(|&t| m.tensors[t].bytes() as u64).sum()
        })
        .collect()
}

fn mode_of(s: &Strategy, path: &str) -> LoraMode {
    s.lora_of(path).unwrap_or_else(|| panic!("no decision for {path}"))
}

const LAYER3: [&str; 4] = ["layer3.0.conv1", "layer3.0.conv2", "layer3.1.conv1", "layer3.1.conv2"];
const LAYER4_WINOGRAD: [&str; 3] = ["layer4.0.conv2", "layer4.1.conv1", "layer4.1.conv2"];

#[test]
fn loose_budget_merges_everything_at_the_default_algorithms() {
    let m = module(IMG);
    let (plan, warnings, s) = compile(&m, &opts(LoraMode::Auto, Some(1000.0)));
    let s = s.expect("a strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(s.layers.len(), 8);
    for l in &s.layers {
        assert_eq!(l.lora, Some(LoraMode::Merge), "{}", l.path);
    }
    // Hand-derived: layer3's stride-1 convs at 28x28 are Winograd F(4x4), 36 * 256 * 256
    // floats; layer4's at 14x14 F(2x2), 16 * 512 * 512; the stride-2 ones im2col, raw.
    let by = choose_strategy::by_path(&s);
    assert_eq!(by["layer3.0.conv2"].algo, Some(ConvAlgo::Winograd4));
    assert_eq!(by["layer3.0.conv2"].bytes, vec![36 * 256 * 256 * 4; 2]);
    assert_eq!(by["layer4.1.conv1"].algo, Some(ConvAlgo::Winograd2));
    assert_eq!(by["layer4.1.conv1"].bytes, vec![16 * 512 * 512 * 4; 2]);
    assert_eq!(by["layer4.0.conv1"].algo, Some(ConvAlgo::Im2col));
    assert_eq!(by["layer4.0.conv1"].bytes, vec![512 * 256 * 9 * 4; 2]);
    // The same as the default compile (merge, no budget), byte for byte.
    let (default, _, _) = compile(&m, &opts(LoraMode::Merge, None));
    assert_eq!(plan_variant_bytes(&plan.manifest), plan_variant_bytes(&default.manifest));
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));
}

#[test]
fn tight_budget_branches_the_largest_layers_first() {
    let m = module(IMG);
    let (_, _, merged) = compile(&m, &opts(LoraMode::Auto, Some(1000.0)));
    let merged = merged.expect("a strategy");
    // Branching layer4.0.conv2 saves its F(2x2) weight, 16 * 512 * 512 floats, for A (stored
    // raw, 9 floats per 3x3; the runtime packs it for F(2x2)) and B, 4 * 512 * 9 + 512 * 4
    // floats: 16.7 MB for 4.01 ms added (A and B's multiply-adds at 1e-6 ms each, 14x14
    // outputs), 4.2 MB/ms, the same for layer4.1's two. Next: layer4.0.conv1, 4.67 MB for
    // 2.21 ms (2.1 MB/ms); layer3's F(4x4) convs, 9.40 MB for 8.03 ms (1.2 MB/ms);
    // layer3.0.conv1, 1.16 MB for 4.42 ms (0.26 MB/ms); im2col instead of Winograd saves
    // less for far more. A budget that the three layer4 F(2x2) convs branched just meet:
    let saved = 3 * (16 * 512 * 512 - (4 * 512 * 9 + 512 * 4)) * 4;
    let need = merged.variant_bytes().into_iter().max().expect("variants") - saved;
    let pct = need as f64 * 100.0 / merged.base_bytes as f64 + 1e-9;
    let (plan, warnings, s) = compile(&m, &opts(LoraMode::Auto, Some(pct)));
    let s = s.expect("a strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    for p in LAYER4_WINOGRAD {
        assert_eq!(mode_of(&s, p), LoraMode::Branch, "{p}");
    }
    assert_eq!(mode_of(&s, "layer4.0.conv1"), LoraMode::Merge);
    for p in LAYER3 {
        assert_eq!(mode_of(&s, p), LoraMode::Merge, "{p}");
    }
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));
    // A little less: layer4.0.conv1 goes next.
    let (_, _, s) = compile(&m, &opts(LoraMode::Auto, Some(pct - 0.01)));
    let s = s.expect("a strategy");
    assert_eq!(mode_of(&s, "layer4.0.conv1"), LoraMode::Branch);
    assert_eq!(mode_of(&s, "layer3.0.conv2"), LoraMode::Merge);
    // The explained predicted latency: every branched layer adds its A and B.
    let a_b = |cin: usize, cout: usize, hw: usize, stride: usize| {
        let o = hw / stride;
        (4 * cin * 9 * o * o + cout * 4 * o * o) as f64 * 1e-6
    };
    let added: f64 = s.layers.iter().filter_map(|l| l.added_ms).sum();
    let want = 3.0 * a_b(512, 512, 14, 1) + a_b(256, 512, 28, 2);
    assert!((added - want).abs() < 1e-9, "{added} vs {want}");
}

#[test]
fn impossible_budget_warns_with_the_smallest_achievable() {
    let m = module(IMG);
    let (plan, warnings, s) = compile(&m, &opts(LoraMode::Auto, Some(0.1)));
    let s = s.expect("a strategy");
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].contains("cannot be met"), "{}", warnings[0]);
    let least = s.unmet.expect("unmet");
    assert!(warnings[0].contains(&format!("{least:.2}%")), "{}", warnings[0]);
    // Paying latency would not meet the budget: the fastest assignment is kept (no
    // layer's switch, as long as a run of its kernel here, fits the 1 ms switch budget).
    for l in &s.layers {
        assert_eq!((l.lora, l.switch), (Some(LoraMode::Merge), false), "{}", l.path);
    }
    assert!(warnings[0].contains("kept the fastest assignment"), "{}", warnings[0]);
    assert!(s.unmet_added_ms.expect("what the least costs") > 0.0);
    let bytes = plan_variant_bytes(&plan.manifest);
    assert_eq!(s.variant_bytes(), bytes);
    // The smallest by hand: ResNet-18's BatchNorms have 4800 channels (scale and shift
    // each), the classifier 512 * 10 + 10, the eight A and B, A raw (9 floats per 3x3 per
    // rank per input channel, whatever the layer's algorithm; the runtime packs a
    // Winograd one): layer3.0.conv1 4*128*9 + 256*4, three more in layer3 4*256*9 +
    // 256*4, layer4.0.conv1 4*256*9 + 512*4, three more in layer4 4*512*9 + 512*4.
    let ab =
        (4 * 128 * 9 + 256 * 4) + 3 * (4 * 256 * 9 + 256 * 4) + (4 * 256 * 9 + 512 * 4) + 3 * (4 * 512 * 9 + 512 * 4);
    let max = ((2 * 4800 + 512 * 10 + 10) + ab) as u64 * 4;
    assert!((least - max as f64 * 100.0 / s.base_bytes as f64).abs() < 1e-9);
    // And that is what `--lora branch` stores.
    let (branched, _, _) = compile(&m, &opts(LoraMode::Branch, None));
    assert_eq!(plan_variant_bytes(&branched.manifest).into_iter().max(), Some(max));
}

/// A switch merges and packs the layer's weight: 1e-6 ms per weight element here.
fn merge_ms(s: &Conv2dShape, _: ConvAlgo, _: usize) -> f64 {
    (s.cout * s.k()) as f64 * 1e-6
}

fn switch_opts(budget: Option<f64>, switch_ms: f64) -> CompileOptions {
    CompileOptions {
        timing: Timing::FixedSwitch(macs, merge_ms),
        switch_budget: Some(switch_ms),
        ..opts(LoraMode::Auto, budget)
    }
}

fn switched(s: &Strategy) -> Vec<&str> {
    s.layers.iter().filter(|l| l.switch).map(|l| l.path.as_str()).collect()
}

#[test]
fn a_layer_goes_merge_on_switch_when_its_merge_fits_the_switch_budget() {
    let m = module(IMG);
    let (_, _, merged) = compile(&m, &opts(LoraMode::Auto, Some(1000.0)));
    let merged = merged.expect("a strategy");
    // Merging layer3.0.conv2 on switch saves its F(4x4) weight, 36 * 256 * 256 floats, for
    // raw A and B (4 * 256 * 9 + 256 * 4), adds no latency and costs its merge, 256 * 2304
    // elements = 0.590 ms: the first move, if it fits the switch budget.
    let saved = (36 * 256 * 256 - (4 * 256 * 9 + 256 * 4)) * 4;
    let need = merged.variant_bytes().into_iter().max().expect("variants") - saved;
    let pct = need as f64 * 100.0 / merged.base_bytes as f64 + 1e-9;
    let (plan, warnings, s) = compile(&m, &switch_opts(Some(pct), 1.0));
    let s = s.expect("a strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(switched(&s), ["layer3.0.conv2"]);
    let l = choose_strategy::by_path(&s)["layer3.0.conv2"];
    // Stored per variant: raw A and B, the plan's tables byte for byte; the working copy
    // (F(4x4)) once per session; no latency added.
    assert_eq!(l.bytes, vec![(4 * 256 * 9 + 256 * 4) * 4; 2]);
    assert_eq!(l.working, 36 * 256 * 256 * 4);
    assert_eq!(l.added_ms, Some(0.0));
    assert!((s.switch_ms() - 256.0 * 2304.0 * 1e-6).abs() < 1e-12);
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));
    for o in s.layers.iter().filter(|l| !l.switch) {
        assert_eq!(o.lora, Some(LoraMode::Merge), "{}", o.path);
    }
    let step = plan.manifest.steps.iter().find(|st| st.path.starts_with("layer3.0.conv2")).expect("step");
    assert!(matches!(step.kernel, readi_runtime::plan::Kernel::Conv2d { switch: true, .. }), "{:?}", step.kernel);

    // A switch budget below its merge: it does not; the budget is met by branching.
    let (plan, warnings, s) = compile(&m, &switch_opts(Some(pct), 0.5));
    let s = s.expect("a strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    assert!(!switched(&s).contains(&"layer3.0.conv2"), "{:?}", switched(&s));
    assert!(s.switch_ms() <= 0.5);
    assert!(s.layers.iter().any(|l| l.lora == Some(LoraMode::Branch) && !l.switch));
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));

    // An unreachable budget keeps the free savings: the most bytes per switch ms that fit
    // 1 ms, layer3.0.conv2 (0.590 ms) then layer3.0.conv1 (256 * 1152 elements, 0.295 ms);
    // layer4's (1.18 and 2.36 ms) never fit.
    let (plan, warnings, s) = compile(&m, &switch_opts(Some(0.1), 1.0));
    let s = s.expect("a strategy");
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert_eq!(switched(&s), ["layer3.0.conv1", "layer3.0.conv2"]);
    assert!((s.switch_ms() - (2304.0 + 1152.0) * 256.0 * 1e-6).abs() < 1e-12);
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));
    assert!(choose_strategy::explain(&s).contains("merge-on-switch"));
}

/// [`macs`] a thousand times faster: ResNet-18's convs take about 1.8 ms, so a
/// layer3 merge at [`merge_ms`] (0.3 to 0.6 ms) is a quarter of a run.
fn fast_macs(s: &Conv2dShape, algo: ConvAlgo) -> f64 {
    macs(s, algo) * 1e-3
}

#[test]
fn the_default_switch_budget_keeps_the_first_run_after_a_switch_within_two_percent() {
    let m = module(IMG);
    let timing = Timing::FixedSwitch(fast_macs, merge_ms);
    let (_, _, merged) = compile(&m, &CompileOptions { timing, ..opts(LoraMode::Auto, Some(1000.0)) });
    let merged = merged.expect("a strategy");
    // The budget layer3.0.conv2 merged on switch would meet (as above).
    let saved = (36 * 256 * 256 - (4 * 256 * 9 + 256 * 4)) * 4;
    let need = merged.variant_bytes().into_iter().max().expect("variants") - saved;
    let pct = need as f64 * 100.0 / merged.base_bytes as f64 + 1e-9;
    // Given 1 ms, the switch takes it: 0.590 ms of re-merge, a third of this run.
    let given = CompileOptions { timing, switch_budget: Some(1.0), ..opts(LoraMode::Auto, Some(pct)) };
    let (_, _, s) = compile(&m, &given);
    assert_eq!(switched(&s.expect("a strategy")), ["layer3.0.conv2"]);
    // By default the re-merge may take 2% of the base's conv time (its sum over every conv
    // at its algorithm, by hand from `fast_macs`): no layer fits, so the budget is met by
    // a branch instead.
    let (plan, warnings, s) = compile(&m, &CompileOptions { timing, ..opts(LoraMode::Auto, Some(pct)) });
    let s = s.expect("a strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    let conv_ms: f64 = s.base_ms.expect("timed");
    assert!((s.switch_budget_ms - 0.02 * conv_ms).abs() < 1e-12, "{} vs {conv_ms}", s.switch_budget_ms);
    assert!(s.switch_budget_ms < 0.2, "{}", s.switch_budget_ms);
    assert_eq!(switched(&s), Vec::<&str>::new());
    assert!(s.layers.iter().any(|l| l.lora == Some(LoraMode::Branch)));
    assert!(s.max_pct() <= pct);
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));
}

/// Runs every variant of a plan on one seeded image.
fn outputs(plan: Plan, img: usize) -> Vec<Vec<f32>> {
    let plan = Arc::new(plan);
    let keys: Vec<String> = plan.variant_keys().map(|k| k.to_string()).collect();
    let mut session = Session::new(plan, 1).expect("session");
    let shape = [1, 3, img, img];
    let data = backend::seeded_tensor(5, "image", &shape);
    keys.iter()
        .map(|k| {
            session.set_variant(k).expect("key");
            let out = session.run(&[Input { name: "image", data: &data, shape: &shape }]).expect("runs");
            out[0].1.data.clone()
        })
        .collect()
}

#[test]
fn mixed_strategies_compute_what_all_merge_and_all_branch_compute() {
    // At 96 pixels layer3's stride-1 convs are F(2x2) (6x6), layer4's im2col.
    let m = module("96");
    let (merged, _, sm) = compile(&m, &opts(LoraMode::Merge, None));
    let (branched, _, sb) = compile(&m, &opts(LoraMode::Branch, None));
    let (sm, sb) = (sm.expect("strategy"), sb.expect("strategy"));
    let base = {
        let weights = backend::seeded_weights(&m.graph, 11);
        backend::compile(&m, &weights, "<seeded>", &CompileOptions::default()).expect("base").0
    };
    // The base plan's bytes, as the strategy counts them.
    assert_eq!(sm.base_bytes, base.tensor_bytes() as u64);
    let (lo, hi) = (sb.max_pct(), sm.max_pct());
    let (mixed, warnings, s) = compile(&m, &opts(LoraMode::Auto, Some((lo + hi) / 2.0)));
    let s = s.expect("strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    let modes: HashSet<&str> = s.layers.iter().filter_map(|l| l.lora.map(LoraMode::name)).collect();
    assert_eq!(modes.len(), 2, "a mix of merge and branch: {:?}", s.layers);
    assert!(s.max_pct() <= (lo + hi) / 2.0);
    for (st, plan) in [(&sm, &merged), (&sb, &branched), (&s, &mixed)] {
        assert_eq!(st.variant_bytes(), plan_variant_bytes(&plan.manifest));
    }
    let want = outputs(merged, 96);
    for plan in [branched, mixed] {
        for (a, b) in want.iter().zip(outputs(plan, 96)) {
            let err = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
            let scale = a.iter().map(|x| x.abs()).fold(0.0, f32::max).max(1.0);
            assert!(err <= 1e-4 * scale, "max error {err}");
        }
    }
}

#[test]
fn explain_table() {
    let m = module(IMG);
    // Merges at 1e-6 ms per weight element: layer3.0.conv2 (0.590 ms) and layer3.0.conv1
    // (0.295 ms) fit the 1 ms switch budget.
    let mut o = switch_opts(Some(20.0), 1.0);
    o.explain = true;
    let (_, _, s) = compile(&m, &o);
    insta::assert_snapshot!(choose_strategy::explain(&s.expect("strategy")));
}

#[test]
fn fusion_model_bytes_are_the_plans() {
    // BEVFusion-tiny: LoRA on attention projections (linear), adapters, tuned LayerNorms and
    // Winograd-packed head convs.
    let (sources, out) = common::compile("models/bevfusion_tiny.readi", &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let weights = backend::seeded_weights(&m.graph, 3);
    let keys: Vec<String> = ["fog=0.03", "gamma=0.25"].iter().map(|k| k.to_string()).collect();
    let variants = backend::seeded_variants(&m, &keys, 4);
    let base = backend::compile(&m, &weights, "<seeded>", &CompileOptions::default()).expect("base").0;
    for o in [opts(LoraMode::Merge, None), opts(LoraMode::Branch, None), opts(LoraMode::Auto, Some(3.0))] {
        let (plan, _, s) = backend::compile_explained(&m, &weights, "<seeded>", &variants, &o).expect("compiles");
        let s = s.expect("strategy");
        assert_eq!(s.base_bytes, base.tensor_bytes() as u64);
        assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest), "{:?}", o.lora);
    }
}

#[test]
fn a_budget_that_is_not_a_percentage_is_refused_by_name() {
    let o = common::readi(&[
        "compile",
        "models/resnet18.readi",
        "--weights",
        "none.safetensors",
        "-o",
        "none.plan",
        "--memory-budget=-3",
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--memory-budget") && err.contains("not a percentage"), "{err}");
}

/// `--variant-f16` stores the tuned classifier's variant values at half precision only when
/// the budget needs it: at ImageNet's 1000 classes the fc alone is over a budget that
/// every layer's smallest option meets otherwise. The strategy's bytes are the plan's.
#[test]
fn variant_f16_halves_the_head_only_where_the_budget_needs_it() {
    let m = module_of("96", "1000");
    let (_, _, least) = compile(&m, &opts(LoraMode::Branch, None));
    let least = least.expect("strategy");
    let fc = (512 * 1000 * 4) as f64 * 100.0 / least.base_bytes as f64;
    // Between the smallest exact assignment and that with the fc at half size.
    let budget = least.max_pct() - fc / 4.0;
    let f16 = |budget: Option<f64>| CompileOptions { variant_f16: true, ..opts(LoraMode::Auto, budget) };

    let (_, warnings, _) = compile(&m, &opts(LoraMode::Auto, Some(budget)));
    assert!(warnings.iter().any(|w| w.contains("cannot be met")), "{warnings:?}");
    let (plan, warnings, s) = compile(&m, &f16(Some(budget)));
    let s = s.expect("strategy");
    assert!(warnings.is_empty(), "{warnings:?}");
    let halves: Vec<&str> = s.half.iter().map(|h| h.param.as_str()).collect();
    assert_eq!(halves, ["fc.weight"]);
    assert!(s.max_pct() <= budget, "{} > {budget}", s.max_pct());
    assert_eq!(s.variant_bytes(), plan_variant_bytes(&plan.manifest));
    let half: Vec<&str> = plan
        .manifest
        .tensors
        .iter()
        .filter(|t| t.dtype == readi_plan::DType::F16)
        .map(|t| t.name.split('#').next().unwrap_or_default())
        .collect();
    assert_eq!(half, ["fc.weight@panels", "fc.weight@panels"], "one per variant");

    // A budget the fastest assignment meets at f32: no f16. (Between that and the
    // smallest, precision goes before latency: the user asked for f16 to be used.)
    let (_, _, fastest) = compile(&m, &opts(LoraMode::Merge, None));
    let (plan, _, s) = compile(&m, &f16(Some(fastest.expect("strategy").max_pct() + 0.5)));
    assert!(s.expect("strategy").half.is_empty());
    assert!(plan.manifest.tensors.iter().all(|t| t.dtype == readi_plan::DType::F32));
}

/// A plan that stores the head's variant values f16 computes exactly what the same model
/// computes with those values rounded to f16 first and stored f32, for every variant, in
/// any order of switches (the session's decoded copy follows the variant), and within
/// f16's rounding of the exact plan.
#[test]
fn a_head_stored_f16_computes_what_its_rounded_values_compute() {
    let m = module_of("64", "1000");
    let weights = backend::seeded_weights(&m.graph, 11);
    let keys: Vec<String> = KEYS.iter().map(|k| k.to_string()).collect();
    let variants = backend::seeded_variants(&m, &keys, 12);
    let merge = opts(LoraMode::Merge, None);
    let f16 = CompileOptions { variant_f16: true, ..merge.clone() };
    let (half, _, s) = backend::compile_explained(&m, &weights, "<seeded>", &variants, &f16).expect("compiles");
    assert_eq!(s.expect("strategy").half.len(), 1, "the fc, the only weight no choice changes");
    assert!(half.manifest.tensors.iter().any(|t| t.dtype == readi_plan::DType::F16));
    // Round the variants' fc to f16 by hand: the nearest f16, ties to even: 11
    // significant bits, an ulp of 2^(e - 10) for an exponent e of at least -14 (below,
    // the subnormals' fixed 2^-24); the seeded values are far inside f16's range.
    let round = |x: f32| -> f32 {
        let e = (x.abs().log2().floor() as i32).max(-14);
        let ulp = 2f32.powi(e - 10);
        let q = x / ulp;
        let r = q.round();
        let r = if (q - q.trunc()).abs() == 0.5 && r % 2.0 != 0.0 { r - q.signum() } else { r };
        r * ulp
    };
    let mut rounded = variants.clone();
    for v in &mut rounded {
        let (_, data) = v.weights.tensors.get_mut("fc.weight").expect("the variant tunes fc");
        for x in data.iter_mut() {
            assert!(x.abs() < 60000.0, "inside f16's range: {x}");
            *x = round(*x);
        }
    }
    let (want, _, _) = backend::compile_explained(&m, &weights, "<seeded>", &rounded, &merge).expect("compiles");
    let (exact, _, _) = backend::compile_explained(&m, &weights, "<seeded>", &variants, &merge).expect("compiles");
    let (half, want, exact) = (Arc::new(half), Arc::new(want), Arc::new(exact));
    let shape = [1, 3, 64, 64];
    let data = backend::seeded_tensor(5, "image", &shape);
    let mut sh = Session::new(half.clone(), 2).expect("session");
    let mut sw = Session::new(want, 2).expect("session");
    let mut se = Session::new(exact, 1).expect("session");
    // Back and forth, the base between, so the copy is decoded again and again.
    for key in ["gamma=0.25", "blur=5", "base", "blur=5", "gamma=0.25", "gamma=0.25", "base"] {
        let run = |s: &mut Session| {
            s.set_variant(key).expect("key");
            s.run(&[Input { name: "image", data: &data, shape: &shape }]).expect("runs")[0].1.data.clone()
        };
        let (h, w, e) = (run(&mut sh), run(&mut sw), run(&mut se));
        assert_eq!(h, w, "{key}: the f16 plan against the rounded one");
        let err = h.iter().zip(&e).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        let scale = e.iter().map(|x| x.abs()).fold(0.0, f32::max);
        assert!(err <= 1e-2 * scale, "{key}: {err} against the exact plan's scale {scale}");
        if key == "base" {
            assert_eq!(err, 0.0, "the base reads no f16 tensor");
        }
    }
    // The plan file keeps the f16 tensors, and a loaded plan runs the same.
    let dir = common::Scratch::new("f16");
    let path = dir.join("half.plan");
    half.write(&path).expect("write");
    let loaded = Arc::new(Plan::load(&path).expect("loads"));
    assert!(loaded.is_mapped());
    assert_eq!(loaded.tensor_bytes(), half.tensor_bytes());
    let mut sl = Session::new(loaded, 2).expect("session");
    for key in ["blur=5", "gamma=0.25"] {
        sh.set_variant(key).expect("key");
        sl.set_variant(key).expect("key");
        let input = [Input { name: "image", data: &data, shape: &shape }];
        assert_eq!(sl.run(&input).expect("runs"), sh.run(&input).expect("runs"), "{key}");
    }
}
