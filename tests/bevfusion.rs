//! BEVFusion's camera neck and view transform, fuser, decoder and TransFusion head
//! (models/bevfusion/*.readi) against a plain-PyTorch port of mit-han-lab/bevfusion's
//! modules with the same state_dict names (tests/fixtures/bevfusion/
//! make_bevfusion_fixtures.py), at a reduced size with seeded weights: BEV features, the
//! head's query selection and predictions and the decoded boxes to 1e-4 (absolute, or
//! relative above 1), the integer outputs exactly, at 1 and 2 threads.

mod common;

use common::{bevfusion_fixture as fixture, bevfusion_plan as compile, output, run_at_1_and_2_threads as run};
use readi_runtime::exec::Tensor;

const DECODER: &[(&str, &str)] = &[
    ("bev", "16"),
    ("camera_ch", "8"),
    ("lidar_ch", "16"),
    ("fused", "16"),
    ("second_out0", "16"),
    ("second_out1", "24"),
    ("layer_num", "2"),
    ("fpn_out", "16"),
    ("num_classes", "10"),
    ("num_proposals", "24"),
    ("hidden", "32"),
    ("num_heads", "8"),
    ("ffn", "48"),
    ("head_conv", "16"),
    ("range_x_min", "-49.0"),
    ("range_z_min", "-3.3"),
];

/// Fuser, SECOND, SECONDFPN and the TransFusion head with its decode, on two samples: the
/// fused and decoded BEV features, the dense heatmap, the selected queries (class and
/// heatmap peak), every prediction, and boxes/scores/labels/keep, where the rows kept
/// equal TransFusionBBoxCoder's own filtered output.
#[test]
fn decoder_and_transfusion_head_match_pytorch() {
    let plan = compile("models/bevfusion/decoder.readi", DECODER, "decoder.weights.safetensors");
    let io = fixture("decoder.io.safetensors");
    let outputs = run(plan, &io);
    for name in [
        "fused",
        "bev",
        "dense_heatmap",
        "query_heatmap_score",
        "center",
        "height",
        "dim",
        "rot",
        "vel",
        "heatmap",
        "boxes",
        "scores",
    ] {
        common::close(name, output(&outputs, name), &io.tensors[name], 1e-4);
    }
    // The integer outputs exactly: the query classes, the labels, the keep mask.
    for name in ["query_labels", "labels", "keep"] {
        common::close(name, output(&outputs, name), &io.tensors[name], 0.0);
    }
    let keep = output(&outputs, "keep");
    let kept = keep.data.iter().filter(|v| **v == 1.0).count();
    assert!(kept > 0 && kept < keep.data.len(), "{kept} of {} kept: the filter is not exercised", keep.data.len());
    // Rows kept, per sample, against the coder's variable-length boxes, scores, labels.
    let (boxes, scores, labels) = (output(&outputs, "boxes"), output(&outputs, "scores"), output(&outputs, "labels"));
    let k = keep.shape[1];
    for b in 0..keep.shape[0] {
        let rows: Vec<usize> = (0..k).filter(|&j| keep.data[b * k + j] == 1.0).collect();
        let gather = |t: &Tensor, width: usize| -> Tensor {
            let data =
                rows.iter().flat_map(|&j| t.data[(b * k + j) * width..(b * k + j + 1) * width].to_vec()).collect();
            let shape = if width == 1 { vec![rows.len()] } else { vec![rows.len(), width] };
            Tensor { shape, data }
        };
        common::close(&format!("kept{b}.boxes"), &gather(boxes, 9), &io.tensors[&format!("kept{b}.boxes")], 1e-4);
        common::close(&format!("kept{b}.scores"), &gather(scores, 1), &io.tensors[&format!("kept{b}.scores")], 1e-4);
        common::close(&format!("kept{b}.labels"), &gather(labels, 1), &io.tensors[&format!("kept{b}.labels")], 0.0);
    }
}

const CAMERA: &[(&str, &str)] = &[
    ("cams", "2"),
    ("img_h", "64"),
    ("img_w", "96"),
    ("c0", "8"),
    ("c1", "12"),
    ("c2", "16"),
    ("neck_out", "16"),
    ("bev_ch", "8"),
    ("x_min", "-8.0"),
    ("x_max", "8.0"),
    ("cell", "1.0"),
    ("z_min", "-2.0"),
    ("z_max", "2.0"),
    ("z_cell", "4.0"),
    ("d_min", "1.0"),
    ("d_max", "9.0"),
    ("d_step", "1.0"),
];

/// GeneralizedLSSFPN on three feature levels of two cameras, then DepthLSSTransform with
/// a sparse depth image and an augmented calibration: the neck's output and the
/// downsampled camera BEV features.
#[test]
fn camera_neck_and_depth_lss_transform_match_pytorch() {
    let plan = compile("models/bevfusion/camera.readi", CAMERA, "camera.weights.safetensors");
    let io = fixture("camera.io.safetensors");
    let outputs = run(plan, &io);
    common::close("neck", output(&outputs, "neck"), &io.tensors["neck"], 1e-4);
    let bev = output(&outputs, "camera_bev");
    common::close("camera_bev", bev, &io.tensors["camera_bev"], 1e-4);
    assert!(bev.data.iter().filter(|v| **v != 0.0).count() > bev.data.len() / 4, "a mostly empty BEV");
}
