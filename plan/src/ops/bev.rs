//! `lss_bev_pool`: BEVFusion's camera-to-BEV view transform (Lift-Splat-Shoot), one
//! operator from a depth distribution and a context to the bird's-eye-view grid.
//!
//! As `mmdet3d/models/vtransforms/base.py` of mit-han-lab/bevfusion (`BaseTransform`):
//! a frustum of `D x fH x fW` points per camera (depths `arange(*dbound)`, image columns
//! `linspace(0, iW - 1, fW)`, rows `linspace(0, iH - 1, fH)`), moved into the lidar frame
//! by `get_geometry` (the image augmentation undone, `x, y` scaled by depth,
//! `camera2lidar_rots @ inverse(intrins)` and the translation, then the lidar
//! augmentation), binned by `bev_pool` (`((geom - (bx - dx / 2)) / dx).long()`, points
//! outside the grid dropped) and summed per cell, the `z` cells laid out along channels:
//! `out[b, z·C + c, x, y]`. The features are `depth[b, n, d, h, w] · context[b, n, c, h,
//! w]`, formed on the fly (BEVFusion materialises them as `[B, N, D, fH, fW, C]`).

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, float};
use crate::dim::Dim;

/// Most cells an axis of the grid may have.
pub const MAX_GRID_AXIS: i64 = 1 << 16;

/// The attributes of `lss_bev_pool`: the network's input image size and the grid's and
/// the depth bins' `[start, stop, step]`, as BEVFusion's config gives them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LssBevPool {
    /// `[iH, iW]`, the (augmented) image the features were computed from.
    pub image_size: [i64; 2],
    pub xbound: [f64; 3],
    pub ybound: [f64; 3],
    pub zbound: [f64; 3],
    pub dbound: [f64; 3],
}

/// Why a `[start, stop, step]` bound is refused, if it is.
pub fn check_bound(b: [f64; 3]) -> Result<(), String> {
    let [start, stop, step] = b;
    if !(start.is_finite() && stop.is_finite() && step.is_finite()) {
        return Err(format!("must be finite, got {}", show_bound(b)));
    }
    if step <= 0.0 {
        return Err(format!("needs a positive step, got {}", show_bound(b)));
    }
    if stop <= start {
        return Err(format!("needs start < stop, got {}", show_bound(b)));
    }
    Ok(())
}

/// `[start, stop, step]` as printouts show it.
pub fn show_bound(b: [f64; 3]) -> String {
    format!("[{}, {}, {}]", float(b[0]), float(b[1]), float(b[2]))
}

impl LssBevPool {
    /// The cells of the grid axis `name` bounded by `b`: `gen_dx_bx`'s `nx`, `(stop -
    /// start) / step` truncated.
    pub fn cells(name: &str, b: [f64; 3]) -> ShapeResult<i64> {
        check_bound(b).map_err(|e| ShapeError::new(format!("lss_bev_pool {name} {e}")))?;
        let n = ((b[1] - b[0]) / b[2]).trunc();
        if !(1.0..=MAX_GRID_AXIS as f64).contains(&n) {
            return Err(ShapeError::new(format!(
                "lss_bev_pool {name} {} gives {n} cells, not between 1 and {MAX_GRID_AXIS}",
                show_bound(b)
            )));
        }
        Ok(n as i64)
    }

    /// `[nx, ny, nz]`, the grid's cells per axis.
    pub fn grid(&self) -> ShapeResult<[i64; 3]> {
        Ok([
            LssBevPool::cells("xbound", self.xbound)?,
            LssBevPool::cells("ybound", self.ybound)?,
            LssBevPool::cells("zbound", self.zbound)?,
        ])
    }

    /// `D`, the depth bins: the length of `torch.arange(*dbound)`, `ceil((stop - start) /
    /// step)`.
    pub fn depth_bins(&self) -> ShapeResult<i64> {
        let b = self.dbound;
        check_bound(b).map_err(|e| ShapeError::new(format!("lss_bev_pool dbound {e}")))?;
        let n = ((b[1] - b[0]) / b[2]).ceil();
        if !(1.0..=MAX_GRID_AXIS as f64).contains(&n) {
            return Err(ShapeError::new(format!(
                "lss_bev_pool dbound {} gives {n} depth bins, not between 1 and {MAX_GRID_AXIS}",
                show_bound(b)
            )));
        }
        Ok(n as i64)
    }

    /// Refuses an image size that is not positive.
    pub fn check_image_size(&self) -> ShapeResult<()> {
        let [h, w] = self.image_size;
        if h < 1 || w < 1 || h > 1 << 24 || w > 1 << 24 {
            return Err(ShapeError::new(format!("lss_bev_pool image_size must be positive, got [{h}, {w}]")));
        }
        Ok(())
    }
}

/// The input names, in port order, as mmdetection3d names them.
pub const LSS_INPUTS: [&str; 6] =
    ["depth", "context", "camera_intrinsics", "camera2lidar", "img_aug_matrix", "lidar_aug_matrix"];

impl Operator for LssBevPool {
    fn kind_name(&self) -> &'static str {
        "lss_bev_pool"
    }

    fn arity(&self) -> Option<usize> {
        Some(6)
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        self.check_image_size()?;
        let [nx, ny, nz] = self.grid()?;
        let bins = self.depth_bins()?;
        let ranks = [5, 5, 4, 4, 4, 3];
        for ((t, rank), name) in inputs.iter().zip(ranks).zip(LSS_INPUTS) {
            if t.rank() != rank {
                return Err(ShapeError::new(format!("lss_bev_pool {name} must have {rank} axes, got {t}")));
            }
        }
        let (depth, context) = (inputs[0], inputs[1]);
        let known = |t: &TensorType, axis: usize, name: &str| {
            t.known_dim(axis).ok_or_else(|| {
                ShapeError::new(format!("lss_bev_pool needs a known size on axis {axis} of {name}, got {t}"))
            })
        };
        let batch = &depth.shape[0];
        let cams = known(depth, 1, "depth")?;
        let [d, fh, fw] = [known(depth, 2, "depth")?, known(depth, 3, "depth")?, known(depth, 4, "depth")?];
        let c = known(context, 2, "context")?;
        if d != bins {
            return Err(ShapeError::new(format!(
                "lss_bev_pool dbound {} gives {bins} depth bins, but depth is {depth}",
                show_bound(self.dbound)
            )));
        }
        let want = |t: &TensorType, shape: &[Dim]| t.shape == shape;
        let (b, n) = (batch.clone(), Dim::known(cams));
        let ctx = [b.clone(), n.clone(), Dim::known(c), Dim::known(fh), Dim::known(fw)];
        if !want(context, &ctx) {
            return Err(ShapeError::new(format!(
                "lss_bev_pool context must be [B, N, C, fH, fW] with depth's B, N, fH, fW, got {context} and {depth}"
            )));
        }
        let four = Dim::known(4);
        for (j, name) in LSS_INPUTS.iter().enumerate().skip(2) {
            let t = inputs[j];
            let shape: Vec<Dim> = if j == 5 {
                vec![b.clone(), four.clone(), four.clone()]
            } else {
                vec![b.clone(), n.clone(), four.clone(), four.clone()]
            };
            if !want(t, &shape) {
                let s = if j == 5 { "[B, 4, 4]" } else { "[B, N, 4, 4]" };
                return Err(ShapeError::new(format!(
                    "lss_bev_pool {name} must be {s} with depth's B and N, got {t} and depth {depth}"
                )));
            }
        }
        let channels = c
            .checked_mul(nz)
            .filter(|&v| v <= i64::from(u32::MAX))
            .ok_or_else(|| ShapeError::new(format!("lss_bev_pool: {c} channels times {nz} z cells overflow")))?;
        let shape = vec![b, Dim::known(channels), Dim::known(nx), Dim::known(ny)];
        Ok(TensorType::new(depth.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![
            ("image_size", format!("{}x{}", self.image_size[0], self.image_size[1])),
            ("xbound", show_bound(self.xbound)),
            ("ybound", show_bound(self.ybound)),
            ("zbound", show_bound(self.zbound)),
            ("dbound", show_bound(self.dbound)),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    fn op() -> LssBevPool {
        LssBevPool {
            image_size: [64, 96],
            xbound: [-8.0, 8.0, 2.0],
            ybound: [-8.0, 8.0, 2.0],
            zbound: [-2.0, 2.0, 2.0],
            dbound: [2.0, 10.0, 2.0],
        }
    }

    fn inputs(b: i64, n: i64, d: i64, c: i64) -> Vec<TensorType> {
        vec![
            t(&[b, n, d, 4, 6]),
            t(&[b, n, c, 4, 6]),
            t(&[b, n, 4, 4]),
            t(&[b, n, 4, 4]),
            t(&[b, n, 4, 4]),
            t(&[b, 4, 4]),
        ]
    }

    #[test]
    fn output_is_channels_times_z_by_the_grid() {
        assert_eq!(run(&op(), &inputs(1, 2, 4, 3)), Ok(t(&[1, 6, 8, 8])));
        // BEVFusion's nuScenes grid: 0.3 m cells over [-54, 54), one z cell, 118 depths.
        let big = LssBevPool {
            image_size: [256, 704],
            xbound: [-54.0, 54.0, 0.3],
            ybound: [-54.0, 54.0, 0.3],
            zbound: [-10.0, 10.0, 20.0],
            dbound: [1.0, 60.0, 0.5],
        };
        assert_eq!(big.depth_bins(), Ok(118));
        assert_eq!(big.grid().map(|g| g[2]), Ok(1));
        assert_eq!(big.grid().map(|g| [g[0], g[1]]), Ok([360, 360]));
        // (0.7 - 0) / 0.1 is 6.999999999999999 in f64: truncated, as `torch.LongTensor`.
        let odd = LssBevPool { xbound: [0.0, 0.7, 0.1], ..op() };
        assert_eq!(odd.grid().map(|g| g[0]), Ok(6));
    }

    #[test]
    fn shapes_must_agree() {
        let e = run(&op(), &inputs(1, 2, 5, 3)).expect_err("5 depths for 4 bins");
        assert!(e.message.contains("gives 4 depth bins"), "{}", e.message);
        let mut bad = inputs(1, 2, 4, 3);
        bad[1] = t(&[1, 2, 3, 4, 7]);
        assert!(run(&op(), &bad).expect_err("fW differs").message.contains("context must be"));
        let mut bad = inputs(1, 2, 4, 3);
        bad[5] = t(&[1, 2, 4, 4]);
        let e = run(&op(), &bad).expect_err("lidar_aug_matrix rank");
        assert_eq!(e.message, "lss_bev_pool lidar_aug_matrix must have 3 axes, got f32[1, 2, 4, 4]");
        let mut bad = inputs(1, 2, 4, 3);
        bad[3] = t(&[1, 3, 4, 4]);
        assert!(run(&op(), &bad).expect_err("cameras differ").message.contains("camera2lidar must be"));
        assert!(run(&op(), &inputs(1, 2, 4, 3)[..5]).is_err());
    }

    #[test]
    fn bounds_and_image_size_are_checked() {
        let i = inputs(1, 2, 4, 3);
        let e = run(&LssBevPool { xbound: [-8.0, 8.0, 0.0], ..op() }, &i).expect_err("step 0");
        assert_eq!(e.message, "lss_bev_pool xbound needs a positive step, got [-8.0, 8.0, 0.0]");
        assert!(run(&LssBevPool { ybound: [8.0, -8.0, 2.0], ..op() }, &i).is_err());
        assert!(run(&LssBevPool { zbound: [0.0, 1.0, 2.0], ..op() }, &i).is_err(), "0 cells");
        assert!(run(&LssBevPool { dbound: [2.0, f64::NAN, 2.0], ..op() }, &i).is_err());
        assert!(run(&LssBevPool { xbound: [0.0, 1.0, 1e-9], ..op() }, &i).is_err(), "too many cells");
        let e = run(&LssBevPool { image_size: [0, 96], ..op() }, &i).expect_err("empty image");
        assert_eq!(e.message, "lss_bev_pool image_size must be positive, got [0, 96]");
    }
}
