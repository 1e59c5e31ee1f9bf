//! BEVFusion's camera backbone, mmdet 2.x's SwinTransformer (models/bevfusion/swin.readi),
//! against a plain-PyTorch port of mmdet's modules with the same state_dict names
//! (tests/fixtures/bevfusion/swin_ref.py, fixtures by make_swin_fixtures.py), at a reduced
//! size with seeded weights: the three output levels to 1e-4 (absolute, or relative above
//! 1), the same bits at 1 and 2 threads.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_runtime::exec::{Input, Session};

fn fixture(name: &str) -> WeightSet {
    let path = common::root().join("tests/fixtures/bevfusion").join(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

/// Embed 4, depths [2, 2, 2, 2], heads [1, 2, 2, 4], window 4 on two 58 x 90 images: the
/// patch embedding pads to 60 x 92 (15 x 23 patches), stage 0's windows and the first
/// merge pad 15 x 23 to 16 x 24, stage 2's windows pad 4 x 6 to 4 x 8, and stage 3's
/// 2 x 3 map pads to a single window that mmdet still shifts and masks.
const SIZES: &[(&str, &str)] = &[
    ("img_h", "58"),
    ("img_w", "90"),
    ("embed", "4"),
    ("window", "4"),
    ("d0", "2"),
    ("d1", "2"),
    ("d2", "2"),
    ("d3", "2"),
    ("h0", "1"),
    ("h1", "2"),
    ("h2", "2"),
    ("h3", "4"),
];

#[test]
fn swin_backbone_matches_mmdet_port() {
    let rel = "models/bevfusion/swin.readi";
    let (sources, out) = common::compile(rel, SIZES, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let name = "swin.weights.safetensors";
    let (plan, _) = backend::compile(&module, &fixture(name), name, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));

    let io = fixture("swin.io.safetensors");
    let (shape, data) = &io.tensors["input.images"];
    let inputs = [Input { name: "images", data, shape }];
    let plan = Arc::new(plan);
    let one = Session::new(Arc::clone(&plan), 1).expect("session").run(&inputs).expect("runs");
    let two = Session::new(plan, 2).expect("session").run(&inputs).expect("runs");
    for ((name, a), (_, b)) in one.iter().zip(&two) {
        assert!(a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits()), "{name}: 1 and 2 threads differ");
    }
    for level in ["feats0", "feats1", "feats2"] {
        let got = &one.iter().find(|(n, _)| n == level).unwrap_or_else(|| panic!("no output {level}")).1;
        common::close(level, got, &io.tensors[level], 1e-4);
    }
}
