//! The whole BEVFusion detector (models/bevfusion.readi: Swin-T, GeneralizedLSSFPN and
//! DepthLSSTransform with the lidar depth image, voxelization and the sparse encoder,
//! ConvFuser, SECOND, SECONDFPN, the TransFusion head and its box coder) from a point
//! cloud, two camera views and their calibration to boxes, against a plain-PyTorch port
//! with the reference's state_dict names (tests/fixtures/bevfusion/make_full_fixtures.py),
//! at a reduced size with seeded weights: both branches' BEV features, the dense heatmap
//! and the decoded boxes and scores to 1e-4, labels and the keep mask exactly, at 1 and 2
//! threads (the same bits at both).

mod common;

use readi_runtime::exec::Tensor;

#[test]
fn bevfusion_from_points_and_images_to_boxes_matches_pytorch() {
    let plan = common::bevfusion_plan("models/bevfusion.readi", common::BEVFUSION_SMALL, "full.weights.safetensors");
    let io = common::bevfusion_fixture("full.io.safetensors");
    let one = common::run_at_1_and_2_threads(plan, &io);
    let output = |name: &str| -> &Tensor { common::output(&one, name) };
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
