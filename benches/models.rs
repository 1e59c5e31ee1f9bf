//! Whole-model inference: ResNet-18 at 1x3x224x224 and bevfusion_tiny at batch 1, with
//! seeded weights, on 1 and 2 threads.
//!
//!     cargo bench --bench models
//!
//! For the side-by-side with ONNX Runtime on the same weights, run
//! `python3 benches/ort_models.py` (it prints readi / ORT latency ratios).

#[path = "common.rs"]
mod common;

use common::{inputs, plan};
use criterion::{Criterion, criterion_group, criterion_main};
use readi_runtime::exec::{Input, Session};

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
