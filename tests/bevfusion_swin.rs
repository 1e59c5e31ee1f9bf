//! BEVFusion's camera backbone, mmdet 2.x's SwinTransformer (models/bevfusion/swin.readi),
//! against a plain-PyTorch port of mmdet's modules with the same state_dict names
//! (tests/fixtures/bevfusion/swin_ref.py, fixtures by make_swin_fixtures.py), at a reduced
//! size with seeded weights: the three output levels to 1e-4 (absolute, or relative above
//! 1), the same bits at 1 and 2 threads.

mod common;

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
    let plan = common::bevfusion_plan("models/bevfusion/swin.readi", SIZES, "swin.weights.safetensors");
    let io = common::bevfusion_fixture("swin.io.safetensors");
    let one = common::run_at_1_and_2_threads(plan, &io);
    for level in ["feats0", "feats1", "feats2"] {
        common::close(level, common::output(&one, level), &io.tensors[level], 1e-4);
    }
}
