//! Front-end speed: parse, and parse + elaborate + all passes + verifier ("check"), for
//! each bundled model. The goal for bevfusion_tiny's check is under 50 ms.
//!
//!     cargo bench --bench frontend

use criterion::{Criterion, criterion_group, criterion_main};
use readi_compiler::passes::{self, Options};
use readi_grammar::diag::FileId;

const MODELS: &[(&str, &str)] = &[
    ("bevfusion_tiny", include_str!("../models/bevfusion_tiny.readi")),
    ("resnet18", include_str!("../models/resnet18.readi")),
    ("vit_encoder", include_str!("../models/vit_encoder.readi")),
    ("pointpillars_bev", include_str!("../models/pointpillars_bev.readi")),
];

fn frontend(c: &mut Criterion) {
    for (name, src) in MODELS {
        c.bench_function(&format!("parse/{name}"), |b| {
            b.iter(|| readi_grammar::parse(FileId(0), std::hint::black_box(src)))
        });
        c.bench_function(&format!("check/{name}"), |b| {
            b.iter(|| {
                let out = passes::run(FileId(0), std::hint::black_box(src), &Options::default());
                assert!(!out.diagnostics.has_errors());
                out
            })
        });
    }
}

criterion_group!(benches, frontend);
criterion_main!(benches);
