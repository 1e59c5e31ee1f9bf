//! The lidar front end of BEVFusion: `voxelize` (mmcv's hard voxelization),
//! `dynamic_voxelize` (dynamic voxelization with a scatter mean, as `DynamicSimpleVFE`)
//! and `lidar_depth_map` (the sparse depth image of `BaseDepthTransform.forward`).
//!
//! A frame's points are `f32[P, C]` (`x, y, z, ...`, `C >= 3`; `P` symbolic, one frame
//! per run). A set of voxels is a fixed capacity `V` (`max_voxels`) of rows: the active
//! voxels are a prefix, numbered in the order of the first point that falls in each (as
//! mmcv's CPU `hard_voxelize`); every inactive row has coordinates `(-1, -1, -1)`, zero
//! features and 0 points. Coordinates are `(z, y, x)` grid cells, as mmdetection3d's
//! voxelization returns them. Each result is its own op ([`VoxelOutput`]), as `topk`'s.

use serde::{Deserialize, Serialize};

use super::{DType, Operator, ShapeError, ShapeResult, TensorType, float, list};
use crate::dim::Dim;

/// Most cells the voxel grid may have (its cells are numbered in a `u32`).
pub const MAX_GRID_CELLS: u64 = u32::MAX as u64 - 1;
/// Most voxels a set may hold, and most points per voxel.
pub const MAX_VOXELS: usize = 1 << 24;

/// Which result of a voxelization an op computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum VoxelOutput {
    /// `f32[V, T, C]`: each voxel's points in input order (hard voxelization).
    Voxels,
    /// `i64[V, 3]`: each voxel's `(z, y, x)` cell.
    Coords,
    /// `i64[V]`: each voxel's kept points (hard voxelization).
    NumPoints,
    /// `f32[V, C]`: the mean of each voxel's points (dynamic voxelization).
    Mean,
}

impl VoxelOutput {
    pub fn name(self) -> &'static str {
        match self {
            VoxelOutput::Voxels => "voxels",
            VoxelOutput::Coords => "coords",
            VoxelOutput::NumPoints => "num_points",
            VoxelOutput::Mean => "features",
        }
    }
}

/// `voxelize(points, voxel_size, point_cloud_range, max_num_points, max_voxels)`
/// (`max_points` `Some`) and `dynamic_voxelize(points, voxel_size, point_cloud_range,
/// max_voxels)` (`None`), as mmcv's CPU voxelization computes in f32: the grid has
/// `round((max - min) / size)` cells per axis; a point's cell is `floor((p - min) /
/// size)`, the point dropped when a cell is outside the grid; a voxel past
/// `max_voxels` is dropped with its points, and a point past `max_points` in its voxel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Voxelize {
    /// `[x, y, z]`.
    pub voxel_size: [f64; 3],
    /// `[x0, y0, z0, x1, y1, z1]`.
    pub point_cloud_range: [f64; 6],
    pub max_points: Option<usize>,
    pub max_voxels: usize,
    pub output: VoxelOutput,
}

impl Voxelize {
    /// The grid's cells per axis, `[nx, ny, nz]`, as mmcv rounds them (in f32).
    pub fn grid(&self) -> Result<[usize; 3], String> {
        let mut g = [0usize; 3];
        for (j, axis) in ["x", "y", "z"].into_iter().enumerate() {
            let (lo, hi, size) = (self.point_cloud_range[j], self.point_cloud_range[j + 3], self.voxel_size[j]);
            if !(lo.is_finite() && hi.is_finite() && size.is_finite()) {
                return Err(format!("the {axis} range and voxel size must be finite"));
            }
            if size <= 0.0 {
                return Err(format!("voxel_size {axis} must be positive, got {}", float(size)));
            }
            let n = ((hi as f32 - lo as f32) / size as f32).round();
            if !(n >= 1.0 && n <= MAX_GRID_CELLS as f32) {
                return Err(format!(
                    "point_cloud_range {axis} [{}, {}] over voxel_size {} gives {n} cells, not at least 1",
                    float(lo),
                    float(hi),
                    float(size)
                ));
            }
            g[j] = n as usize;
        }
        let cells = g.iter().try_fold(1u64, |a, &n| a.checked_mul(n as u64));
        if cells.is_none_or(|c| c > MAX_GRID_CELLS) {
            return Err(format!("a grid of {} x {} x {} cells is more than {MAX_GRID_CELLS}", g[0], g[1], g[2]));
        }
        Ok(g)
    }

    /// Refuses attributes out of range: the grid, and `max_voxels` / `max_points` between
    /// 1 and [`MAX_VOXELS`].
    pub fn check(&self) -> Result<[usize; 3], String> {
        if !(1..=MAX_VOXELS).contains(&self.max_voxels) {
            return Err(format!("max_voxels must be between 1 and {MAX_VOXELS}, got {}", self.max_voxels));
        }
        if let Some(t) = self.max_points
            && !(1..=MAX_VOXELS).contains(&t)
        {
            return Err(format!("max_num_points must be between 1 and {MAX_VOXELS}, got {t}"));
        }
        self.grid()
    }
}

/// Checks a points input: `[P, C]` with a known `C >= 3`. Returns `C`.
pub fn point_features(op: &str, x: &TensorType) -> ShapeResult<i64> {
    let c = match (x.rank(), x.known_dim(1)) {
        (2, Some(c)) if c >= 3 => c,
        _ => {
            return Err(ShapeError::new(format!(
                "{op} points must be [P, C] with a known C of at least 3 (x, y, z, ...), got {x}"
            )));
        }
    };
    if !x.dtype.is_float() {
        return Err(ShapeError::new(format!("{op} points must be floating-point, got {x}")));
    }
    Ok(c)
}

impl Operator for Voxelize {
    fn kind_name(&self) -> &'static str {
        if self.max_points.is_some() { "voxelize" } else { "dynamic_voxelize" }
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = self.kind_name();
        self.check().map_err(|e| ShapeError::new(format!("{name} {e}")))?;
        let x = inputs[0];
        let c = point_features(name, x)?;
        let v = Dim::known(self.max_voxels as i64);
        let (dtype, shape) = match (self.output, self.max_points) {
            (VoxelOutput::Voxels, Some(t)) => (x.dtype, vec![v, Dim::known(t as i64), Dim::known(c)]),
            (VoxelOutput::Mean, None) => (x.dtype, vec![v, Dim::known(c)]),
            (VoxelOutput::Coords, _) => (DType::I64, vec![v, Dim::known(3)]),
            (VoxelOutput::NumPoints, Some(_)) => (DType::I64, vec![v]),
            (out, _) => return Err(ShapeError::new(format!("{name} has no `{}` result", out.name()))),
        };
        Ok(TensorType::new(dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let f = |v: &[f64]| list(&v.iter().map(|&x| float(x)).collect::<Vec<_>>());
        let mut a = vec![("voxel_size", f(&self.voxel_size)), ("point_cloud_range", f(&self.point_cloud_range))];
        if let Some(t) = self.max_points {
            a.push(("max_num_points", t.to_string()));
        }
        a.push(("max_voxels", self.max_voxels.to_string()));
        a.push(("output", self.output.name().into()));
        a
    }
}

/// The input names of `lidar_depth_map`, in port order (mmdetection3d's).
pub const DEPTH_MAP_INPUTS: [&str; 5] =
    ["points", "camera_intrinsics", "camera2lidar", "img_aug_matrix", "lidar_aug_matrix"];

/// `lidar_depth_map(points, camera_intrinsics, camera2lidar, img_aug_matrix,
/// lidar_aug_matrix, image_size)`: BEVFusion's sparse depth image
/// (`BaseDepthTransform.forward`), `f32[B, N, 1, H, W]` with `B = 1` at run time (one
/// frame's points). Per camera, each point's `x, y, z` has the lidar augmentation undone,
/// goes through `lidar2image = intrinsics · inverse(camera2lidar)`, its depth `d` clamped
/// to `[1e-5, 1e5]`, `x, y` divided by it, then the image augmentation; a point whose
/// pixel `(row, col)` is inside the image writes `d` (clamped, as BEVFusion's in-place
/// clamp makes it) at `(trunc(row), trunc(col))`; the last such point in input order wins.
/// As BEVFusion, the depth is not otherwise masked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LidarDepthMap {
    /// `[H, W]`.
    pub image_size: [i64; 2],
}

impl Operator for LidarDepthMap {
    fn kind_name(&self) -> &'static str {
        "lidar_depth_map"
    }

    fn arity(&self) -> Option<usize> {
        Some(5)
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let [h, w] = self.image_size;
        if !(1..=1 << 16).contains(&h) || !(1..=1 << 16).contains(&w) {
            return Err(ShapeError::new(format!(
                "lidar_depth_map image_size must be positive (at most 65536), got [{h}, {w}]"
            )));
        }
        point_features("lidar_depth_map", inputs[0])?;
        let k = inputs[1];
        if k.rank() != 4 || k.known_dim(1).is_none() {
            return Err(ShapeError::new(format!(
                "lidar_depth_map camera_intrinsics must be [B, N, 4, 4] with a known N, got {k}"
            )));
        }
        let (b, n, four) = (k.shape[0].clone(), k.shape[1].clone(), Dim::known(4));
        for (j, name) in DEPTH_MAP_INPUTS.iter().enumerate().skip(1) {
            let want: Vec<Dim> = if j == 4 {
                vec![b.clone(), four.clone(), four.clone()]
            } else {
                vec![b.clone(), n.clone(), four.clone(), four.clone()]
            };
            if inputs[j].shape != want {
                let s = if j == 4 { "[B, 4, 4]" } else { "[B, N, 4, 4]" };
                return Err(ShapeError::new(format!(
                    "lidar_depth_map {name} must be {s} with camera_intrinsics' B and N, got {} and {k}",
                    inputs[j]
                )));
            }
        }
        let shape = vec![b, n, Dim::known(1), Dim::known(h), Dim::known(w)];
        Ok(TensorType::new(inputs[0].dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("image_size", format!("{}x{}", self.image_size[0], self.image_size[1]))]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    fn hard(output: VoxelOutput) -> Voxelize {
        Voxelize {
            voxel_size: [0.5, 0.5, 1.0],
            point_cloud_range: [-4.0, -4.0, -2.0, 4.0, 4.0, 2.0],
            max_points: Some(5),
            max_voxels: 100,
            output,
        }
    }

    #[test]
    fn results_have_the_capacity_as_rows() {
        let p = || TensorType::f32(vec![Dim::symbol("P"), Dim::known(4)]);
        assert_eq!(run(&hard(VoxelOutput::Voxels), &[p()]), Ok(t(&[100, 5, 4])));
        let coords = run(&hard(VoxelOutput::Coords), &[p()]).expect("coords");
        assert_eq!((coords.dtype, coords.shape), (DType::I64, vec![Dim::known(100), Dim::known(3)]));
        let n = run(&hard(VoxelOutput::NumPoints), &[p()]).expect("num_points");
        assert_eq!((n.dtype, n.shape), (DType::I64, vec![Dim::known(100)]));
        let dynamic = Voxelize { max_points: None, output: VoxelOutput::Mean, ..hard(VoxelOutput::Voxels) };
        assert_eq!(run(&dynamic, &[t(&[7, 5])]), Ok(t(&[100, 5])));
        assert!(run(&Voxelize { output: VoxelOutput::Voxels, ..dynamic }, &[t(&[7, 5])]).is_err());
    }

    #[test]
    fn grid_is_rounded_as_mmcv() {
        // nuScenes: 0.075 m over [-54, 54) and 0.2 m over [-5, 3).
        let op = Voxelize {
            voxel_size: [0.075, 0.075, 0.2],
            point_cloud_range: [-54.0, -54.0, -5.0, 54.0, 54.0, 3.0],
            ..hard(VoxelOutput::Coords)
        };
        assert_eq!(op.grid(), Ok([1440, 1440, 40]));
        let odd = Voxelize { voxel_size: [0.3, 0.5, 1.0], ..hard(VoxelOutput::Coords) };
        assert_eq!(odd.grid().map(|g| g[0]), Ok(27), "8 / 0.3 = 26.67 rounds up");
    }

    #[test]
    fn bad_attributes_and_inputs_are_refused() {
        let e = run(&Voxelize { voxel_size: [0.0, 0.5, 1.0], ..hard(VoxelOutput::Coords) }, &[t(&[9, 4])]);
        assert_eq!(e.expect_err("size 0").message, "voxelize voxel_size x must be positive, got 0.0");
        let e = run(&Voxelize { max_voxels: 0, ..hard(VoxelOutput::Coords) }, &[t(&[9, 4])]);
        assert!(e.expect_err("0 voxels").message.contains("max_voxels"));
        let flat = [-4.0, -4.0, 2.0, 4.0, 4.0, 2.0];
        assert!(run(&Voxelize { point_cloud_range: flat, ..hard(VoxelOutput::Coords) }, &[t(&[9, 4])]).is_err());
        let tiny = Voxelize { voxel_size: [1e-6, 1e-6, 1e-6], ..hard(VoxelOutput::Coords) };
        assert!(tiny.grid().expect_err("too many cells").contains("more than"));
        assert!(run(&hard(VoxelOutput::Coords), &[t(&[9, 2])]).is_err(), "C = 2");
        assert!(run(&hard(VoxelOutput::Coords), &[t(&[9, 4, 1])]).is_err(), "rank 3");
    }

    #[test]
    fn depth_map_shapes() {
        let op = LidarDepthMap { image_size: [32, 48] };
        let ins = |n: i64| vec![t(&[50, 5]), t(&[1, n, 4, 4]), t(&[1, n, 4, 4]), t(&[1, n, 4, 4]), t(&[1, 4, 4])];
        assert_eq!(run(&op, &ins(6)), Ok(t(&[1, 6, 1, 32, 48])));
        let mut bad = ins(6);
        bad[2] = t(&[1, 5, 4, 4]);
        assert!(run(&op, &bad).expect_err("N differs").message.contains("camera2lidar must be"));
        assert!(run(&LidarDepthMap { image_size: [0, 48] }, &ins(6)).is_err());
    }
}
