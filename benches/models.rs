//! Whole-model inference: ResNet-18 at 1x3x224x224 and bevfusion_tiny at batch 1, with
//! seeded weights, on 1 and 2 threads.
//!
//!     cargo bench --bench models
//!
//! For the side-by-side with ONNX Runtime on the same weights, run
//! `python3 benches/ort_models.py` (it prints readi / ORT latency ratios).

use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use readi_compiler::backend::{self, CompileOptions};
use readi_compiler::passes::{self, Options};
use readi_grammar::diag::FileId;
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::Plan;

fn plan(src: &str) -> Arc<Plan> {
    let out = passes::run(FileId(0), src, &Options::default());
    let module = out.module.expect("the model checks");
    let weights = backend::seeded_weights(&module.graph, 1);
    Arc::new(backend::compile(&module, &weights, "seeded", &CompileOptions::default()).expect("compiles").0)
}

fn inputs(plan: &Plan) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let ones = plan.manifest.symbols.iter().map(|s| (s.clone(), 1usize)).collect();
    plan.manifest
        .inputs
        .iter()
        .map(|i| {
            let shape: Vec<usize> = i.shape.iter().map(|d| d.eval(&ones).unwrap_or(1)).collect();
            let n: usize = shape.iter().product();
            let data = (0..n).map(|k| ((k * 7919 % 1000) as f32 / 500.0) - 1.0).collect();
            (i.name.clone(), shape, data)
        })
        .collect()
}

fn models(c: &mut Criterion) {
    let mut group = c.benchmark_group("models");
    group.sample_size(10);
    for (name, src) in [
        ("resnet18", include_str!("../models/resnet18.readi")),
        ("bevfusion_tiny", include_str!("../models/bevfusion_tiny.readi")),
    ] {
        let plan = plan(src);
        let data = inputs(&plan);
        for threads in [1, 2] {
            let mut session = Session::new(plan.clone(), threads).expect("session");
            let given: Vec<Input<'_>> = data.iter().map(|(n, s, d)| Input { name: n, data: d, shape: s }).collect();
            group
                .bench_function(format!("{name}/threads={threads}"), |b| b.iter(|| session.run(&given).expect("runs")));
        }
    }
    group.finish();
}

criterion_group!(benches, models);
criterion_main!(benches);
