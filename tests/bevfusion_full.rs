//! The whole BEVFusion detector (models/bevfusion.readi: Swin-T, GeneralizedLSSFPN and
//! DepthLSSTransform with the lidar depth image, voxelization and the sparse encoder,
//! ConvFuser, SECOND, SECONDFPN, the TransFusion head and its box coder) from a point
//! cloud, two camera views and their calibration to boxes, against a plain-PyTorch port
//! with the reference's state_dict names (tests/fixtures/bevfusion/make_full_fixtures.py),
//! at a reduced size with seeded weights: both branches' BEV features, the dense heatmap
//! and the decoded boxes and scores to 1e-4, labels and the keep mask exactly, at 1 and 2
//! threads (the same bits at both).

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_runtime::exec::{Input, Session, Tensor};

fn fixture(name: &str) -> WeightSet {
    let path = common::root().join("tests/fixtures/bevfusion").join(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

#[test]
fn bevfusion_from_points_and_images_to_boxes_matches_pytorch() {
    let (sources, out) = common::compile("models/bevfusion.readi", common::BEVFUSION_SMALL, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let weights = fixture("full.weights.safetensors");
    let (plan, _) = backend::compile(&module, &weights, "full.weights.safetensors", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let io = fixture("full.io.safetensors");
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let plan = Arc::new(plan);
    let one = Session::new(Arc::clone(&plan), 1).expect("session").run(&inputs).expect("runs");
    let two = Session::new(plan, 2).expect("session").run(&inputs).expect("runs");
    for ((name, a), (_, b)) in one.iter().zip(&two) {
        assert!(a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits()), "{name}: 1 and 2 threads differ");
    }
    let output = |name: &str| -> &Tensor { &one.iter().find(|(n, _)| n == name).expect(name).1 };
    for name in ["camera_bev", "lidar_bev", "dense_heatmap", "boxes", "scores"] {
        common::close(name, output(name), &io.tensors[name], 1e-4);
    }
    for name in ["labels", "keep"] {
        common::close(name, output(name), &io.tensors[name], 0.0);
    }
    // The fixture exercises the coder's filter and both branches.
    let kept = output("keep").data.iter().filter(|v| **v == 1.0).count();
    assert!(kept > 0 && kept < 12, "{kept} of 12 boxes kept");
    for name in ["camera_bev", "lidar_bev"] {
        let t = output(name);
        assert!(t.data.iter().filter(|v| **v != 0.0).count() > t.data.len() / 10, "{name} is mostly empty");
    }
}
