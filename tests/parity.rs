//! Parity with PyTorch: torchvision's ResNet-18 and a small ViT encoder, run by PyTorch
//! with readi's seeded weights (tests/fixtures/make_fixtures.py), must agree with readi to
//! 1e-4 (max abs error). Each model also runs after a plan write -> load round trip, which
//! must give bit-identical outputs to the plan as compiled.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_runtime::exec::{Input, Session, Tensor};
use readi_runtime::plan::Plan;

const SEED: u64 = 2024;

/// Compiles a bundled model with seeded weights that go through a safetensors file, as a
/// user's PyTorch export would.
fn compile_seeded(rel: &str, overrides: &[(&str, &str)]) -> Plan {
    let (sources, out) = common::compile(rel, overrides, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let bytes = backend::seeded_weights(&module.graph, SEED).to_safetensors().expect("serialises");
    let weights = WeightSet::from_safetensors("seeded.safetensors", &bytes).expect("valid safetensors");
    let (plan, warnings) = backend::compile(&module, &weights, "seeded.safetensors", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    assert!(warnings.is_empty(), "{}", sources.render_all(&warnings, false));
    plan
}

fn fixture(name: &str) -> WeightSet {
    let path = common::root().join("tests/fixtures/parity").join(format!("{name}.safetensors"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

fn run(plan: Arc<Plan>, fx: &WeightSet, threads: usize) -> Vec<(String, Tensor)> {
    let inputs: Vec<Input<'_>> = fx
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let mut session = Session::new(plan, threads).expect("session");
    session.run(&inputs).expect("run")
}

fn max_abs_error(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Checks a fixture against the plan as compiled and after a save/load round trip.
fn check(rel: &str, overrides: &[(&str, &str)], fixture_name: &str) {
    let plan = Arc::new(compile_seeded(rel, overrides));
    let fx = fixture(fixture_name);
    let compiled = run(plan.clone(), &fx, 2);
    for (name, t) in &compiled {
        let (shape, want) = &fx.tensors[&format!("output.{name}")];
        assert_eq!(&t.shape, shape, "{fixture_name}: shape of {name}");
        let err = max_abs_error(&t.data, want);
        eprintln!("{fixture_name}: `{name}` max abs error vs PyTorch {err:e}");
        assert!(err <= 1e-4, "{fixture_name}: output `{name}` differs from PyTorch by {err:e}");
    }

    let dir = common::Scratch::new(&format!("parity-{fixture_name}"));
    let path = dir.join("model.plan");
    plan.write(&path).expect("write plan");
    let loaded = Arc::new(Plan::load(&path).expect("load plan"));
    assert!(loaded.is_mapped());
    assert_eq!(loaded.manifest, plan.manifest);
    let reloaded = run(loaded, &fx, 2);
    for ((name, a), (_, b)) in compiled.iter().zip(&reloaded) {
        let same = a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same && a.shape == b.shape, "{fixture_name}: `{name}` changed after the save/load round trip");
    }
}

#[test]
fn resnet18_matches_pytorch_at_batch_2() {
    check("models/resnet18.readi", &[("num_classes", "10"), ("img", "64")], "resnet18_b2_64");
}

#[test]
fn resnet18_matches_pytorch_at_224() {
    check("models/resnet18.readi", &[("num_classes", "10")], "resnet18_b1_224");
}

#[test]
fn vit_encoder_matches_pytorch() {
    let small = [("img", "32"), ("patch", "8"), ("width", "64"), ("depth", "2"), ("heads", "4"), ("num_classes", "10")];
    check("models/vit_encoder.readi", &small, "vit_encoder_small");
}

#[test]
fn one_thread_and_two_threads_agree() {
    let plan = Arc::new(compile_seeded("models/resnet18.readi", &[("num_classes", "10"), ("img", "64")]));
    let fx = fixture("resnet18_b2_64");
    let a = run(plan.clone(), &fx, 1);
    let b = run(plan, &fx, 2);
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        let err = max_abs_error(&x.data, &y.data);
        assert!(err <= 1e-5, "`{name}` differs between 1 and 2 threads by {err:e}");
    }
}
