//! BEVFusion's lidar encoder (models/bevfusion/lidar.readi: hard voxelization,
//! HardSimpleVFE, mmdet3d's SparseEncoder with SparseBasicBlocks, the height-flattened BEV)
//! against a plain-PyTorch port (tests/fixtures/bevfusion/make_lidar_fixtures.py: mit-han-lab's
//! CPU voxelization in numpy, the sparse convs as dense conv3d with an active-site mask) at a
//! reduced size with seeded weights: `lidar_bev` to 1e-4 on two point clouds of different
//! sizes in one session, the same bits at 1 and 2 threads.

mod common;

use std::sync::Arc;

use readi_runtime::exec::{Input, Session};

/// The sizes of make_lidar_fixtures.py's `cfg` and `build(5, 4, 6, 8, 8, 6)`.
const LIDAR: &[(&str, &str)] = &[
    ("vx", "0.25"),
    ("vy", "0.25"),
    ("x_min", "-6.0"),
    ("y_min", "-6.0"),
    ("x_max", "6.0"),
    ("y_max", "6.0"),
    ("max_points", "4"),
    ("max_voxels", "240"),
    ("nx", "48"),
    ("ny", "48"),
    ("max_sites", "1920"),
    ("c0", "4"),
    ("c1", "6"),
    ("c2", "8"),
    ("c3", "8"),
    ("out_ch", "6"),
];

/// A 320-point cloud (the voxel cap of 240 and the 4 points per voxel both hit, points
/// outside the range) and a 150-point one, run one after the other in the same sessions.
#[test]
fn lidar_encoder_matches_pytorch() {
    let plan = common::bevfusion_plan("models/bevfusion/lidar.readi", LIDAR, "lidar.weights.safetensors");
    let io = common::bevfusion_fixture("lidar.io.safetensors");
    let plan = Arc::new(plan);
    let mut one = Session::new(Arc::clone(&plan), 1).expect("session");
    let mut two = Session::new(plan, 2).expect("session");
    for case in ["large", "small", "large"] {
        let (shape, data) = &io.tensors[&format!("{case}.input.points")];
        let inputs = [Input { name: "points", data, shape }];
        let a = one.run(&inputs).expect("runs");
        let b = two.run(&inputs).expect("runs");
        let (got, got2) = (&a.iter().find(|(n, _)| n == "lidar_bev").expect("lidar_bev").1, &b[0].1);
        assert!(
            got.data.iter().zip(&got2.data).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{case}: 1 and 2 threads differ"
        );
        common::close(&format!("{case}.lidar_bev"), got, &io.tensors[&format!("{case}.lidar_bev")], 1e-4);
        let nonzero = got.data.iter().filter(|v| **v != 0.0).count();
        assert!(nonzero > got.data.len() / 5, "{case}: a mostly empty BEV ({nonzero} of {})", got.data.len());
    }
}
