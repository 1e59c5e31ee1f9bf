//! One suite, several paths: every language case and the demo model run as compiled and
//! after a plan write -> load round trip (bit-identical outputs), on 1 and 2 threads
//! (equal to rounding), with finite outputs. The lowering's fusion decisions are a
//! snapshot per model.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions};
use readi_runtime::exec::{Input, Session, Tensor};
use readi_runtime::plan::Plan;

fn compile(rel: &str) -> Plan {
    let (sources, out) = common::compile(rel, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let w = backend::seeded_weights(&module.graph, 9);
    backend::compile(&module, &w, "seeded", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{rel}: {}", sources.render_all(&d, false)))
        .0
}

fn inputs(plan: &Plan, batch: usize) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let b = plan.manifest.symbols.iter().map(|s| (s.clone(), batch)).collect();
    plan.manifest
        .inputs
        .iter()
        .map(|i| {
            let shape: Vec<usize> = i.shape.iter().map(|d| d.eval(&b).expect("bound")).collect();
            let n: usize = shape.iter().product();
            let data = (0..n).map(|k| ((k * 2654435761usize) % 2001) as f32 / 1000.0 - 1.0).collect();
            (i.name.clone(), shape, data)
        })
        .collect()
}

fn run(plan: Arc<Plan>, data: &[(String, Vec<usize>, Vec<f32>)], threads: usize) -> Vec<(String, Tensor)> {
    let given: Vec<Input<'_>> = data.iter().map(|(n, s, d)| Input { name: n, data: d, shape: s }).collect();
    Session::new(plan, threads).expect("session").run(&given).expect("runs")
}

/// The schedule as `readi inspect --verbose` lists it: kernel, algorithm and epilogue,
/// shapes, buffers and fused paths, then the buffer plan.
fn schedule(plan: &Plan) -> String {
    readi::inspect::schedule(&plan.manifest, true) + &readi::inspect::buffers(&plan.manifest)
}

fn check_paths(rel: &str, batch: usize) -> Plan {
    let plan = Arc::new(compile(rel));
    let data = inputs(&plan, batch);
    let a = run(plan.clone(), &data, 2);
    for (name, t) in &a {
        assert!(t.data.iter().all(|v| v.is_finite()), "{rel}: `{name}` is not finite");
    }
    let bytes = plan.to_bytes().expect("serialise");
    let path = std::env::temp_dir().join(format!("readi-paths-{}-{}.plan", std::process::id(), rel.replace('/', "_")));
    std::fs::write(&path, bytes).expect("write");
    let loaded = Arc::new(Plan::load(&path).expect("load"));
    let b = run(loaded, &data, 2);
    let _ = std::fs::remove_file(&path);
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        assert!(
            x.shape == y.shape && x.data.iter().zip(&y.data).all(|(p, q)| p.to_bits() == q.to_bits()),
            "{rel}: `{name}` changed after reload"
        );
    }
    let c = run(plan.clone(), &data, 1);
    for ((name, x), (_, y)) in a.iter().zip(&c) {
        let err = x.data.iter().zip(&y.data).map(|(p, q)| (p - q).abs() / (1.0 + q.abs())).fold(0.0f32, f32::max);
        assert!(err < 1e-5, "{rel}: `{name}` differs between 2 and 1 threads by {err:e}");
    }
    Arc::try_unwrap(plan).unwrap_or_else(|p| compile(&p.manifest.model))
}

#[test]
fn language_cases_run_on_every_path() {
    insta::glob!("cases/ok/*.readi", |path| {
        check_paths(&common::rel_path(path), 2);
    });
}

#[test]
fn bevfusion_tiny_runs_on_every_path() {
    let plan = check_paths("models/bevfusion_tiny.readi", 1);
    insta::assert_snapshot!("schedule_bevfusion_tiny", schedule(&plan));
}

#[test]
fn resnet18_schedule_fuses_batchnorm_and_relu() {
    let plan = compile("models/resnet18.readi");
    let text = schedule(&plan);
    // 20 convs (17 + 3 downsample projections), every BatchNorm folded into one.
    assert_eq!(plan.manifest.steps.iter().filter(|s| s.kernel.name() == "conv2d").count(), 20);
    assert!(!text.contains("channel_affine"), "{text}");
    insta::assert_snapshot!("schedule_resnet18", text);
}
