//! Shared by the benches: seeded plans of the bundled models and deterministic inputs.
#![allow(dead_code)]

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions};
use readi_compiler::passes::{self, Options};
use readi_grammar::diag::FileId;
use readi_runtime::plan::Plan;

/// A spec compiled with seeded weights and no variants.
pub fn plan(src: &str) -> Arc<Plan> {
    let out = passes::run(FileId(0), src, &Options::default());
    let module = out.module.expect("the model checks");
    let weights = backend::seeded_weights(&module.graph, 1);
    Arc::new(backend::compile(&module, &weights, "seeded", &CompileOptions::default()).expect("compiles").0)
}

/// Deterministic inputs in [-1, 1) for every input of a plan at batch 1.
pub fn inputs(plan: &Plan) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    plan.manifest
        .input_shapes(1)
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let data = (0..n).map(|k| ((k * 7919 % 1000) as f32 / 500.0) - 1.0).collect();
            (name.to_string(), shape, data)
        })
        .collect()
}
