//! Activations and unary functions, and data movement (pad, roll, slicing; movement.readi
//! and make_movement_fixtures.py), against PyTorch. Activations: tests/fixtures/ops/activations.readi
//! run on the inputs and weights tests/fixtures/ops/make_activation_fixtures.py wrote,
//! against the outputs torch computed, to 1e-5 (absolute, or relative to values above 1);
//! NaN and infinities where torch has them. Its conv + batchnorm + act and linear + act
//! chains must compile to one fused kernel each.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::{Kernel, Plan};

const SPEC: &str = "tests/fixtures/ops/activations.readi";

fn fixture(name: &str) -> WeightSet {
    let path = common::root().join("tests/fixtures/ops").join(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

fn plan() -> Plan {
    let (sources, out) = common::compile(SPEC, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let weights = fixture("activations.weights.safetensors");
    let (plan, _) = backend::compile(&module, &weights, "activations.weights.safetensors", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    plan
}

#[test]
fn activations_match_pytorch() {
    let plan = Arc::new(plan());
    let io = fixture("activations.io.safetensors");
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let outputs = Session::new(plan, 2).expect("session").run(&inputs).expect("runs");
    assert_eq!(outputs.len(), io.tensors.keys().filter(|k| k.starts_with("output.")).count());
    for (name, t) in &outputs {
        let (shape, want) = &io.tensors[&format!("output.{name}")];
        assert_eq!(&t.shape, shape, "shape of {name}");
        let mut worst = 0.0f32;
        for (i, (&g, &w)) in t.data.iter().zip(want).enumerate() {
            if w.is_nan() || w.is_infinite() {
                assert!(g.is_nan() == w.is_nan() && (w.is_nan() || g == w), "{name}[{i}]: {g}, torch {w}");
                continue;
            }
            let err = (g - w).abs() / w.abs().max(1.0);
            assert!(err <= 1e-5, "{name}[{i}]: {g}, torch {w} (error {err:e})");
            worst = worst.max(err);
        }
        eprintln!("{name}: max error vs torch {worst:e}");
    }
}

#[test]
fn conv_and_linear_activations_run_in_the_epilogue() {
    let plan = plan();
    let steps = &plan.manifest.steps;
    for chain in ["b1", "b2", "b3", "b4", "c5", "fc1", "fc2", "fc3", "fc4"] {
        let step = steps.iter().find(|s| s.path.contains(chain)).unwrap_or_else(|| panic!("no step for {chain}"));
        let ep = step.kernel.epilogue().unwrap_or_else(|| panic!("{chain}: {:?} has no epilogue", step.kernel));
        assert!(ep.act.is_some(), "{chain}: the activation is not fused into {}", step.path);
    }
    // No activation step is left reading a conv's, linear's or affine's output.
    let fusable = |v: usize| {
        steps.iter().any(|s| {
            s.output == v
                && matches!(s.kernel, Kernel::Conv2d { .. } | Kernel::Linear { .. } | Kernel::ChannelAffine { .. })
        })
    };
    for s in steps {
        if matches!(s.kernel, Kernel::Pure(readi_plan::ops::Pure::Activation(_))) {
            assert!(!fusable(s.inputs[0]), "{} was not fused", s.path);
        }
    }
}

/// pad (three modes, cropping), roll and every way of slicing against PyTorch:
/// tests/fixtures/ops/movement.readi on the inputs make_movement_fixtures.py wrote. Data
/// movement copies values, so they must be exactly torch's.
#[test]
fn movement_matches_pytorch() {
    let spec = "tests/fixtures/ops/movement.readi";
    let (sources, out) = common::compile(spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let none = WeightSet { tensors: Default::default() };
    let (plan, _) = backend::compile(&module, &none, "none", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let io = fixture("movement.io.safetensors");
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let outputs = Session::new(Arc::new(plan), 2).expect("session").run(&inputs).expect("runs");
    assert_eq!(outputs.len(), io.tensors.keys().filter(|k| k.starts_with("output.")).count());
    for (name, t) in &outputs {
        let (shape, want) = &io.tensors[&format!("output.{name}")];
        assert_eq!(&t.shape, shape, "shape of {name}");
        assert_eq!(&t.data, want, "{name}");
    }
}
