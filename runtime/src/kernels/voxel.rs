//! The lidar front end (see `readi_plan::ops::Voxelize` and `LidarDepthMap` for their
//! meaning): voxelization of one frame's points, and the sparse depth image.
//!
//! [`voxelize`] makes one pass over the points in input order, as mmcv's CPU
//! `hard_voxelize`: a point's cell is computed in f32 as mmcv does, looked up in an
//! open-addressing hash table of the cells seen so far ([`Table`], sized from
//! `max_voxels` when the session binds, cleared per run: O(V + P) per run, nothing
//! allocated), and a new cell gets the next voxel id while there is room. Sequential, so
//! the voxel ids are the order of first appearance at any thread count.
//!
//! [`lidar_depth_map`] projects the points into each camera in f64 (BEVFusion computes in
//! f32; a point within about 1e-6, relative, of a pixel edge may land in the neighbouring
//! pixel compared with PyTorch), one camera per task, each camera's points in input
//! order so the last point on a pixel wins, as CPU torch's `index_put_` does.

use rayon::prelude::*;
use readi_plan::ops::{LidarDepthMap, VoxelOutput, Voxelize};

/// An empty slot of the table.
const EMPTY: u32 = u32::MAX;

/// The per-step state of a voxelization: the hash table from a cell's number to its
/// voxel id, and each voxel's point count.
pub struct Table {
    keys: Vec<u32>,
    ids: Vec<u32>,
    counts: Vec<u32>,
    /// `log2` of the table's slots.
    bits: u32,
}

/// The slots of the table for `max_voxels` voxels: a power of two at least twice as many,
/// so a probe sequence stays short.
fn slots(max_voxels: usize) -> Option<usize> {
    max_voxels.checked_mul(2)?.max(8).checked_next_power_of_two()
}

impl Table {
    pub fn new(max_voxels: usize) -> Table {
        let n = slots(max_voxels).unwrap_or(8);
        Table { keys: vec![EMPTY; n], ids: vec![0; n], counts: vec![0; max_voxels], bits: n.trailing_zeros() }
    }

    /// The bytes a table for `max_voxels` voxels takes.
    pub fn bytes(max_voxels: usize) -> Option<usize> {
        slots(max_voxels)?.checked_mul(8)?.checked_add(max_voxels.checked_mul(4)?)
    }

    fn clear(&mut self) {
        self.keys.fill(EMPTY);
        self.counts.fill(0);
    }

    /// The slot holding `key`, or the empty slot where it goes.
    fn find(&self, key: u32) -> usize {
        let mask = self.keys.len() - 1;
        let mut s = ((u64::from(key).wrapping_mul(0x9E37_79B9_7F4A_7C15)) >> (64 - self.bits)) as usize;
        while self.keys[s] != key && self.keys[s] != EMPTY {
            s = (s + 1) & mask;
        }
        s
    }
}

/// The sizes of one voxelization step: points, features per point, the grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dims {
    pub p: usize,
    pub c: usize,
    pub grid: [usize; 3],
}

/// Checks a step of `op` on a points input and an output of these shapes.
pub fn check(op: &Voxelize, points: &[usize], out: &[usize]) -> Result<Dims, String> {
    let name = if op.max_points.is_some() { "voxelize" } else { "dynamic_voxelize" };
    let grid = op.check().map_err(|e| format!("{name} {e}"))?;
    let &[p, c] = points else { return Err(format!("{name}: points of shape {points:?}, not [P, C]")) };
    if c < 3 {
        return Err(format!("{name}: points of shape {points:?} have fewer than 3 features"));
    }
    let v = op.max_voxels;
    // On the stack: a session's run checks the step again and allocates nothing.
    let (want, rank) = match (op.output, op.max_points) {
        (VoxelOutput::Voxels, Some(t)) => ([v, t, c], 3),
        (VoxelOutput::Mean, None) => ([v, c, 0], 2),
        (VoxelOutput::Coords, _) => ([v, 3, 0], 2),
        (VoxelOutput::NumPoints, Some(_)) => ([v, 0, 0], 1),
        (o, _) => return Err(format!("{name} has no `{}` result", o.name())),
    };
    let want = &want[..rank];
    if out != want || want.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).is_none() {
        return Err(format!("{name}: output {out:?}, expected {want:?}"));
    }
    if p >= u32::MAX as usize {
        return Err(format!("{name}: {p} points, more than it counts"));
    }
    Ok(Dims { p, c, grid })
}

/// Voxelizes `points` (`[P, C]`, shapes checked by [`check`]) into `out`, the result
/// `op.output`. Refuses a point with a value that is not finite, naming it.
pub fn voxelize(op: &Voxelize, d: Dims, points: &[f32], table: &mut Table, out: &mut [f32]) -> Result<(), String> {
    let c = d.c;
    let v = op.max_voxels;
    debug_assert_eq!(table.counts.len(), v);
    table.clear();
    match op.output {
        VoxelOutput::Coords => out.fill(-1.0),
        _ => out.fill(0.0),
    }
    let lo = [0, 1, 2].map(|j| op.point_cloud_range[j] as f32);
    let size = op.voxel_size.map(|s| s as f32);
    let [nx, ny, nz] = d.grid;
    let mut used = 0usize;
    for (i, row) in points.chunks_exact(c).enumerate().take(d.p) {
        if let Some((j, x)) = row.iter().enumerate().find(|(_, x)| !x.is_finite()) {
            return Err(format!("points row {i} has {x} in feature {j}; every value must be finite"));
        }
        // mmcv's `floor((p - min) / size)` in f32, the point dropped outside the grid.
        let mut cell = [0usize; 3];
        let mut inside = true;
        for j in 0..3 {
            let q = ((row[j] - lo[j]) / size[j]).floor();
            if !(q >= 0.0 && q < d.grid[j] as f32) {
                inside = false;
                break;
            }
            cell[j] = q as usize;
        }
        if !inside {
            continue;
        }
        let [x, y, z] = cell;
        // `grid` has fewer than `u32::MAX` cells (checked by `Voxelize::grid`); `min`
        // keeps an f32 rounding at the edge in range.
        let key = ((z.min(nz - 1) * ny + y.min(ny - 1)) * nx + x.min(nx - 1)) as u32;
        let s = table.find(key);
        let id = if table.keys[s] == key {
            table.ids[s] as usize
        } else {
            if used >= v {
                continue;
            }
            table.keys[s] = key;
            table.ids[s] = used as u32;
            if op.output == VoxelOutput::Coords {
                out[used * 3..used * 3 + 3].copy_from_slice(&[z as f32, y as f32, x as f32]);
            }
            used += 1;
            used - 1
        };
        let n = table.counts[id] as usize;
        match (op.output, op.max_points) {
            (VoxelOutput::Voxels, Some(t)) if n < t => {
                out[(id * t + n) * c..(id * t + n + 1) * c].copy_from_slice(row);
            }
            (VoxelOutput::Mean, _) => {
                for (o, &x) in out[id * c..(id + 1) * c].iter_mut().zip(row) {
                    *o += x;
                }
            }
            _ => {}
        }
        if op.max_points.is_none_or(|t| n < t) {
            table.counts[id] += 1;
        }
    }
    match op.output {
        VoxelOutput::NumPoints => {
            for (o, &n) in out.iter_mut().zip(&table.counts) {
                *o = n as f32;
            }
        }
        VoxelOutput::Mean => {
            for (row, &n) in out.chunks_exact_mut(c).zip(&table.counts).take(used) {
                let n = n as f32;
                row.iter_mut().for_each(|x| *x /= n);
            }
        }
        _ => {}
    }
    Ok(())
}

/// Checks a `lidar_depth_map` step: points `[P, C]`, three `[1, N, 4, 4]`, one `[1, 4, 4]`
/// and the output `[1, N, 1, H, W]`. Returns `(P, C, N)`.
pub fn check_depth_map(
    op: &LidarDepthMap,
    inputs: &[&[usize]],
    out: &[usize],
) -> Result<(usize, usize, usize), String> {
    let err = |what: String| format!("lidar_depth_map: {what}");
    let [points, k, c2l, ia, la] = inputs else { return Err(err(format!("{} inputs, it takes 5", inputs.len()))) };
    let &[p, c] = *points else { return Err(err(format!("points of shape {points:?}, not [P, C]"))) };
    if c < 3 {
        return Err(err(format!("points of shape {points:?} have fewer than 3 features")));
    }
    let &[b, n, _, _] = *k else { return Err(err(format!("camera_intrinsics of shape {k:?}, not 4-D"))) };
    if b != 1 {
        return Err(err(format!("a batch of {b}: the points are one frame's, so the matrices must have a batch of 1")));
    }
    for (name, s) in [("camera_intrinsics", k), ("camera2lidar", c2l), ("img_aug_matrix", ia)] {
        if **s != [1, n, 4, 4] {
            return Err(err(format!("{name} of shape {s:?}, expected [1, {n}, 4, 4]")));
        }
    }
    if **la != [1, 4, 4] {
        return Err(err(format!("lidar_aug_matrix of shape {la:?}, expected [1, 4, 4]")));
    }
    let [h, w] = op.image_size;
    let (h, w) = (usize::try_from(h).map_err(|_| err("image_size".into()))?, usize::try_from(w).unwrap_or(0));
    if out != [1, n, 1, h, w] || h == 0 || w == 0 {
        return Err(err(format!("output {out:?}, expected [1, {n}, 1, {h}, {w}]")));
    }
    Ok((p, c, n))
}

type M4 = [[f64; 4]; 4];

fn m4(m: &[f32]) -> M4 {
    let mut r = [[0.0; 4]; 4];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = f64::from(m[i * 4 + j]);
        }
    }
    r
}

fn mul(a: &M4, b: &M4) -> M4 {
    let mut r = [[0.0; 4]; 4];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = (0..4).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    r
}

/// The inverse of the leading `n x n` block of `a` (Gauss-Jordan with partial
/// pivoting), `None` if it is singular.
fn inverse(a: &M4, n: usize) -> Option<M4> {
    let mut m = *a;
    let mut inv = [[0.0; 4]; 4];
    for (i, row) in inv.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for col in 0..n {
        let piv = (col..n).max_by(|&x, &y| m[x][col].abs().total_cmp(&m[y][col].abs()))?;
        if m[piv][col].abs() < 1e-12 || !m[piv][col].is_finite() {
            return None;
        }
        m.swap(col, piv);
        inv.swap(col, piv);
        let p = m[col][col];
        for j in 0..n {
            m[col][j] /= p;
            inv[col][j] /= p;
        }
        for r in (0..n).filter(|&r| r != col) {
            let f = m[r][col];
            for j in 0..n {
                m[r][j] -= f * m[col][j];
                inv[r][j] -= f * inv[col][j];
            }
        }
    }
    Some(inv)
}

/// The sparse depth image (shapes checked by [`check_depth_map`]): `mats` are the
/// `camera_intrinsics`, `camera2lidar`, `img_aug_matrix` and `lidar_aug_matrix` data.
pub fn lidar_depth_map(
    op: &LidarDepthMap,
    (p, c, n): (usize, usize, usize),
    points: &[f32],
    mats: [&[f32]; 4],
    out: &mut [f32],
    threads: usize,
) -> Result<(), String> {
    for (name, m) in ["camera_intrinsics", "camera2lidar", "img_aug_matrix", "lidar_aug_matrix"].iter().zip(mats) {
        if let Some(i) = m.iter().position(|x| !x.is_finite()) {
            return Err(format!("{name} holds {} at {i}; every value must be finite", m[i]));
        }
    }
    if let Some(i) = points[..p * c].iter().position(|x| !x.is_finite()) {
        return Err(format!("points row {} has {} in feature {}; every value must be finite", i / c, points[i], i % c));
    }
    let la = m4(mats[3]);
    let la_inv = inverse(&la, 3).ok_or("lidar_aug_matrix's rotation is singular")?;
    let (h, w) = (op.image_size[0] as usize, op.image_size[1] as usize);
    let cam = |j: usize| -> Result<(M4, M4), String> {
        let k = m4(&mats[0][j * 16..(j + 1) * 16]);
        let c2l = inverse(&m4(&mats[1][j * 16..(j + 1) * 16]), 4)
            .ok_or_else(|| format!("camera2lidar of camera {j} is singular"))?;
        Ok((mul(&k, &c2l), m4(&mats[2][j * 16..(j + 1) * 16])))
    };
    for j in 0..n {
        cam(j)?;
    }
    let work = |(j, img): (usize, &mut [f32])| {
        img.fill(0.0);
        let Ok((l2i, ia)) = cam(j) else { return };
        for row in points.chunks_exact(c).take(p) {
            let q = [0, 1, 2].map(|i| f64::from(row[i]) - la[i][3]);
            let q = [0, 1, 2].map(|i| (0..3).map(|k| la_inv[i][k] * q[k]).sum::<f64>());
            let q = [0, 1, 2].map(|i| (0..3).map(|k| l2i[i][k] * q[k]).sum::<f64>() + l2i[i][3]);
            let d = q[2].clamp(1e-5, 1e5);
            let q = [q[0] / d, q[1] / d, d];
            let r = [0, 1].map(|i| (0..3).map(|k| ia[i][k] * q[k]).sum::<f64>() + ia[i][3]);
            // BEVFusion swaps to (row, col) = (y, x).
            let (y, x) = (r[1], r[0]);
            if y < h as f64 && y >= 0.0 && x < w as f64 && x >= 0.0 {
                img[y as usize * w + x as usize] = d as f32;
            }
        }
    };
    if threads > 1 && n > 1 {
        out.par_chunks_mut(h * w).enumerate().for_each(work);
    } else {
        out.chunks_mut(h * w).enumerate().for_each(work);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn op(output: VoxelOutput, max_points: Option<usize>, max_voxels: usize) -> Voxelize {
        Voxelize {
            voxel_size: [1.0, 1.0, 1.0],
            point_cloud_range: [0.0, 0.0, 0.0, 4.0, 4.0, 2.0],
            max_points,
            max_voxels,
            output,
        }
    }

    fn run(o: &Voxelize, points: &[f32]) -> Vec<f32> {
        let shape = [points.len() / 4, 4];
        let out_shape: Vec<usize> = match o.output {
            VoxelOutput::Voxels => vec![o.max_voxels, o.max_points.unwrap_or(0), 4],
            VoxelOutput::Coords => vec![o.max_voxels, 3],
            VoxelOutput::NumPoints => vec![o.max_voxels],
            VoxelOutput::Mean => vec![o.max_voxels, 4],
        };
        let d = check(o, &shape, &out_shape).expect("shapes");
        let mut out = vec![0.0; out_shape.iter().product()];
        voxelize(o, d, points, &mut Table::new(o.max_voxels), &mut out).expect("runs");
        out
    }

    #[test]
    fn first_appearance_order_and_caps() {
        // Cells (x, y, z): a (1, 0, 0), b (3, 3, 1), a, out of range, c (0, 0, 0), a.
        let pts = [
            1.5, 0.5, 0.5, 1.0, //
            3.5, 3.5, 1.5, 2.0, //
            1.2, 0.1, 0.2, 3.0, //
            4.0, 0.0, 0.0, 4.0, //
            0.0, 0.0, 0.0, 5.0, //
            1.9, 0.9, 0.9, 6.0,
        ];
        let coords = run(&op(VoxelOutput::Coords, Some(2), 2), &pts);
        assert_eq!(coords, [0.0, 0.0, 1.0, 1.0, 3.0, 3.0], "(z, y, x); c dropped past 2 voxels");
        let n = run(&op(VoxelOutput::NumPoints, Some(2), 3), &pts);
        assert_eq!(n, [2.0, 1.0, 1.0], "a's third point dropped");
        let v = run(&op(VoxelOutput::Voxels, Some(2), 3), &pts);
        assert_eq!(&v[..8], &pts[..4].iter().chain(&pts[8..12]).copied().collect::<Vec<_>>()[..]);
        let mean = run(&op(VoxelOutput::Mean, None, 4), &pts);
        assert_eq!(mean[3], (1.0 + 3.0 + 6.0) / 3.0);
        assert_eq!(&mean[12..], [0.0; 4], "inactive row");
        let coords = run(&op(VoxelOutput::Coords, None, 4), &pts);
        assert_eq!(&coords[9..], [-1.0; 3]);
    }

    #[test]
    fn non_finite_points_are_refused() {
        let o = op(VoxelOutput::Coords, Some(2), 2);
        let d = check(&o, &[2, 4], &[2, 3]).expect("shapes");
        let pts = [0.0, 0.0, 0.0, 0.0, 1.0, f32::NAN, 0.0, 0.0];
        let e = voxelize(&o, d, &pts, &mut Table::new(2), &mut [0.0; 6]).expect_err("NaN");
        assert_eq!(e, "points row 1 has NaN in feature 1; every value must be finite");
    }

    #[test]
    fn inverse_inverts() {
        let a = [[2.0, 1.0, 0.0, 1.0], [0.0, 1.0, 0.5, 0.0], [1.0, 0.0, 3.0, 2.0], [0.0, 0.0, 0.0, 1.0]];
        let i = inverse(&a, 4).expect("regular");
        let p = mul(&a, &i);
        for (r, row) in p.iter().enumerate() {
            for (c, x) in row.iter().enumerate() {
                assert!((x - if r == c { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        assert!(inverse(&[[0.0; 4]; 4], 3).is_none());
    }
}
