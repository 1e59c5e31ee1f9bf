//! The lidar front end of BEVFusion, with mmdetection3d's names:
//! `voxelize(points, voxel_size, point_cloud_range, max_num_points, max_voxels)` (a list:
//! voxels, coords, num_points; mmcv's hard voxelization),
//! `dynamic_voxelize(points, voxel_size, point_cloud_range, max_voxels)` (a list:
//! features, the scatter mean of each voxel's points, and coords) and
//! `lidar_depth_map(points, camera_intrinsics, camera2lidar, img_aug_matrix,
//! lidar_aug_matrix, image_size)` (BEVFusion's sparse depth image).

use readi_plan::ops::{DEPTH_MAP_INPUTS, LidarDepthMap, Pure, VoxelOutput, Voxelize, point_features};

use super::{Args, Builtin, P, R, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

const VOXELIZE: &[P] =
    &[req("points"), req("voxel_size"), req("point_cloud_range"), req("max_num_points"), req("max_voxels")];
const DYNAMIC_VOXELIZE: &[P] = &[req("points"), req("voxel_size"), req("point_cloud_range"), req("max_voxels")];
const LIDAR_DEPTH_MAP: &[P] = &[
    req("points"),
    req("camera_intrinsics"),
    req("camera2lidar"),
    req("img_aug_matrix"),
    req("lidar_aug_matrix"),
    req("image_size"),
];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::many("voxelize", VOXELIZE, voxelize),
        Builtin::many("dynamic_voxelize", DYNAMIC_VOXELIZE, dynamic_voxelize),
        Builtin::new("lidar_depth_map", LIDAR_DEPTH_MAP, lidar_depth_map),
    ]
}

/// A list of `N` finite numbers.
fn numbers<const N: usize>(args: &Args<'_>, name: &str, what: &str) -> R<[f64; N]> {
    let mut out = [0.0; N];
    match args.value(name) {
        Some(Value::List(l)) if l.len() == N => {
            for (o, v) in out.iter_mut().zip(l.iter()) {
                *o = match v {
                    Value::Int(i) => *i as f64,
                    Value::Float(f) if f.is_finite() => *f,
                    other => return Err(args.mismatch(name, what, other)),
                };
            }
        }
        Some(v) => return Err(args.mismatch(name, what, v)),
        None => return Err(args.bad_value(name, "missing".into())),
    }
    Ok(out)
}

/// The voxelization attributes and the points, checked; `max_points` from
/// `max_num_points` when the builtin has it.
fn parts(args: &Args<'_>, hard: bool) -> R<(Voxelize, ValueRef)> {
    let voxel_size = numbers::<3>(args, "voxel_size", "a list [x, y, z] of three numbers")?;
    if let Some(s) = voxel_size.iter().find(|s| **s <= 0.0) {
        return Err(args.bad_value("voxel_size", format!("must be positive, got {s}")));
    }
    let point_cloud_range = numbers::<6>(args, "point_cloud_range", "a list [x0, y0, z0, x1, y1, z1] of six numbers")?;
    let max_points = if hard { Some(args.int_at_least("max_num_points", 1)? as usize) } else { None };
    let max_voxels = args.int_at_least("max_voxels", 1)? as usize;
    let op = Voxelize { voxel_size, point_cloud_range, max_points, max_voxels, output: VoxelOutput::Coords };
    if let Err(e) = op.check() {
        let at = if e.contains("max_voxels") {
            "max_voxels"
        } else if e.contains("max_num_points") {
            "max_num_points"
        } else {
            "point_cloud_range"
        };
        return Err(args.bad_value(at, e));
    }
    let t = args.ttype("points")?;
    point_features(args.sig.name, t).map_err(|e| args.bad_value("points", e.message))?;
    Ok((op, args.tensor("points")?))
}

/// mmcv's hard voxelization: `[voxels, coords, num_points]`, one op each.
fn voxelize(args: &Args<'_>) -> R<Vec<(Op, Vec<ValueRef>)>> {
    let (op, x) = parts(args, true)?;
    let one = |output| (Op::Pure(Pure::Voxelize(Voxelize { output, ..op.clone() })), vec![x]);
    Ok(vec![one(VoxelOutput::Voxels), one(VoxelOutput::Coords), one(VoxelOutput::NumPoints)])
}

/// Dynamic voxelization with a scatter mean: `[features, coords]`, one op each.
fn dynamic_voxelize(args: &Args<'_>) -> R<Vec<(Op, Vec<ValueRef>)>> {
    let (op, x) = parts(args, false)?;
    let one = |output| (Op::Pure(Pure::Voxelize(Voxelize { output, ..op.clone() })), vec![x]);
    Ok(vec![one(VoxelOutput::Mean), one(VoxelOutput::Coords)])
}

fn lidar_depth_map(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let size = args.int_list("image_size")?;
    let image_size = match size[..] {
        [h, w] if (1..=1 << 16).contains(&h) && (1..=1 << 16).contains(&w) => [h, w],
        _ => return Err(args.bad_value("image_size", format!("must be [height, width], both positive, got {size:?}"))),
    };
    let t = args.ttype("points")?;
    point_features("lidar_depth_map", t).map_err(|e| args.bad_value("points", e.message))?;
    let shapes = ["[P, C]", "[B, N, 4, 4]", "[B, N, 4, 4]", "[B, N, 4, 4]", "[B, 4, 4]"];
    let mut inputs = Vec::with_capacity(DEPTH_MAP_INPUTS.len());
    for (name, shape) in DEPTH_MAP_INPUTS.iter().zip(shapes) {
        let t = args.ttype(name)?;
        let rank = shape.split(',').count();
        if t.rank() != rank {
            return Err(args.bad_value(name, format!("must be {shape} ({rank} axes), got {t}")));
        }
        inputs.push(args.tensor(name)?);
    }
    Ok((Op::Pure(Pure::LidarDepthMap(LidarDepthMap { image_size })), inputs))
}
