//! `lss_bev_pool`: BEVFusion's camera-to-BEV view transform (see `readi_plan::ops::LssBevPool`
//! for its meaning).
//!
//! Two halves. [`Geometry::update`] computes, from the calibration inputs, where every
//! frustum point lands (`BaseTransform.get_geometry`, then `bev_pool`'s binning) and keeps
//! the points of each BEV cell as a run of a cell-sorted list (bev_pool's "ranks"); it
//! does nothing when the calibration is bit for bit the one it last computed, so a session
//! pays for the geometry once per calibration. [`lss_bev_pool`] then sums, per output
//! element, `depth · context` over its cell's run: parallel over output rows, each element
//! summed by one task in ascending point order (deterministic at any thread count),
//! nothing allocated.
//!
//! Geometry is computed in f64 from the f32 inputs (BEVFusion computes it in f32, with
//! `torch.inverse`), the frustum and the grid's origin and cell size as torch rounds them
//! to f32. A point within about 1e-6 of a cell boundary (relative) may therefore fall in
//! the neighbouring cell compared with PyTorch; away from boundaries the cells are the
//! same. The cell is `((g - (bx - dx / 2)) / dx)` truncated towards zero, as torch's
//! `.long()`: a point less than one cell below the grid's start lands in cell 0, as it
//! does in BEVFusion.

use rayon::prelude::*;
use readi_plan::ops::LssBevPool;

/// The sizes of one `lss_bev_pool` step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dims {
    pub b: usize,
    /// Cameras.
    pub n: usize,
    /// Depth bins.
    pub d: usize,
    pub fh: usize,
    pub fw: usize,
    /// Context channels.
    pub c: usize,
    pub nx: usize,
    pub ny: usize,
    pub nz: usize,
}

impl Dims {
    /// Frustum points over the batch: `B·N·D·fH·fW`.
    pub fn points(&self) -> usize {
        self.b * self.n * self.d * self.fh * self.fw
    }
    /// BEV cells over the batch: `B·nz·nx·ny`.
    pub fn cells(&self) -> usize {
        self.b * self.nz * self.nx * self.ny
    }
    /// Floats of the calibration inputs: three `[B, N, 4, 4]` and one `[B, 4, 4]`.
    fn key_len(&self) -> usize {
        16 * self.b * (3 * self.n + 1)
    }
}

fn numel(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d))
}

/// Checks a step of `op` on inputs and an output of these shapes against the kernel's
/// preconditions (the plan's shape rule says the same, this is what the kernel trusts),
/// and that every index the kernel keeps fits in `u32`; returns the sizes.
pub fn check(op: &LssBevPool, inputs: &[&[usize]], out: &[usize]) -> Result<Dims, String> {
    let err = |what: String| format!("lss_bev_pool: {what}");
    let [depth, context, intr, c2l, img_aug, lidar_aug] = inputs else {
        return Err(err(format!("{} inputs, it takes 6", inputs.len())));
    };
    op.check_image_size().map_err(|e| e.message)?;
    let [nx, ny, nz] = op.grid().map_err(|e| e.message)?;
    let bins = op.depth_bins().map_err(|e| e.message)?;
    let &[b, n, d, fh, fw] = *depth else { return Err(err(format!("depth of shape {depth:?}, not 5-D"))) };
    let &[_, _, c, _, _] = *context else { return Err(err(format!("context of shape {context:?}, not 5-D"))) };
    if *context != [b, n, c, fh, fw] {
        return Err(err(format!("context {context:?} does not match depth {depth:?}")));
    }
    if usize::try_from(bins).ok() != Some(d) {
        return Err(err(format!("{bins} depth bins, depth is {depth:?}")));
    }
    for (name, s) in [("camera_intrinsics", intr), ("camera2lidar", c2l), ("img_aug_matrix", img_aug)] {
        if **s != [b, n, 4, 4] {
            return Err(err(format!("{name} of shape {s:?}, expected {:?}", [b, n, 4, 4])));
        }
    }
    if **lidar_aug != [b, 4, 4] {
        return Err(err(format!("lidar_aug_matrix of shape {lidar_aug:?}, expected {:?}", [b, 4, 4])));
    }
    let [nx, ny, nz] = [nx, ny, nz].map(|v| v as usize);
    if numel(out) != numel(&[b, c, nz, nx, ny]) || out != [b, c * nz, nx, ny] {
        return Err(err(format!("output {out:?}, expected [{b}, {c}·{nz}, {nx}, {ny}]")));
    }
    let dims = Dims { b, n, d, fh, fw, c, nx, ny, nz };
    // Indices the cache keeps as u32: points, context offsets, cells.
    let fits = |s: &[usize]| numel(s).is_some_and(|v| v < u32::MAX as usize);
    if !fits(depth) || !fits(context) || !fits(&[b, nz, nx, ny]) {
        return Err(err(format!("more than 2^32 frustum points, context values or cells ({depth:?}, {context:?})")));
    }
    Ok(dims)
}

/// Bytes a [`Geometry`] of these sizes keeps.
pub fn geometry_bytes(d: &Dims) -> Option<usize> {
    let u32s = d.points().checked_mul(3)?.checked_add(d.cells())?.checked_add(1)?;
    u32s.checked_mul(4)?.checked_add(d.key_len().checked_mul(4)?)
}

/// Where one `lss_bev_pool` step's frustum points land, for one calibration: the cache a
/// session keeps per step. All buffers are sized at creation.
#[derive(Debug)]
pub struct Geometry {
    dims: Dims,
    /// The calibration inputs the geometry was computed from, concatenated (valid only
    /// when `valid`).
    key: Vec<f32>,
    valid: bool,
    /// `start[cell]..start[cell + 1]`: the run of `cell` in `depth_at` / `ctx_at`, cells
    /// numbered `((b·nz + z)·nx + x)·ny + y`.
    start: Vec<u32>,
    /// Per kept point, in cell order and, within a cell, in point order: its index in
    /// `depth` (the point's own index, `(((b·N + n)·D + d)·fH + h)·fW + w`).
    depth_at: Vec<u32>,
    /// ... and the offset of its channel 0 in `context`.
    ctx_at: Vec<u32>,
    /// Per point, its cell (`u32::MAX`: outside the grid); scratch of [`Geometry::update`].
    cell_of: Vec<u32>,
    /// Times the geometry was computed.
    builds: usize,
}

/// `torch.linspace(start, end, steps)` in f32, as PyTorch's CPU kernel computes it: from
/// the start for the first half, from the end for the second.
fn linspace(start: f32, end: f32, steps: usize, i: usize) -> f32 {
    if steps == 1 {
        return start;
    }
    let step = (end - start) / (steps - 1) as f32;
    if i < steps / 2 { start + step * i as f32 } else { end - step * (steps - i - 1) as f32 }
}

/// The grid origin (`bx - dx / 2`) and cell size of an axis, as BEVFusion's f32
/// parameters hold them.
fn axis(b: [f64; 3]) -> (f64, f64) {
    let dx = b[2] as f32;
    let bx = (b[0] + b[2] / 2.0) as f32;
    (f64::from(bx - dx / 2.0), f64::from(dx))
}

type M3 = [[f64; 3]; 3];

/// The upper-left 3x3 block and the translation column of a row-major 4x4 matrix.
fn split(m: &[f32]) -> (M3, [f64; 3]) {
    let r = |i: usize| [0, 1, 2].map(|j| f64::from(m[i * 4 + j]));
    ([r(0), r(1), r(2)], [0, 1, 2].map(|i| f64::from(m[i * 4 + 3])))
}

/// The inverse, or `None` when `m` is singular (its determinant at most 1e-12 of the
/// product of its rows' norms, or the inverse not finite).
fn inverse(m: &M3) -> Option<M3> {
    let c = |i: usize, j: usize| {
        let (i1, i2, j1, j2) = ((i + 1) % 3, (i + 2) % 3, (j + 1) % 3, (j + 2) % 3);
        m[i1][j1] * m[i2][j2] - m[i1][j2] * m[i2][j1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    let scale: f64 = m.iter().map(|r| r.iter().map(|v| v * v).sum::<f64>().sqrt()).product();
    if det.abs() <= 1e-12 * scale || !det.is_finite() {
        return None;
    }
    // The adjugate is the transposed cofactor matrix.
    let inv = [0, 1, 2].map(|i| [0, 1, 2].map(|j| c(j, i) / det));
    inv.iter().flatten().all(|v| v.is_finite()).then_some(inv)
}

fn mul(a: &M3, b: &M3) -> M3 {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn apply(m: &M3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

/// The cell index along an axis of `cells` cells of a coordinate, truncated towards zero
/// as `.long()`, or `None` outside `[0, cells)`.
fn cell(g: f64, (lo, dx): (f64, f64), cells: usize) -> Option<usize> {
    let q = (g - lo) / dx;
    // trunc(q) is in [0, cells) exactly when -1 < q < cells.
    (q > -1.0 && q < cells as f64).then_some(q as usize)
}

impl Geometry {
    /// The sizes the cache was made for.
    pub fn dims(&self) -> Dims {
        self.dims
    }

    /// A cache for a step of these sizes, with nothing computed yet; allocates every
    /// buffer it will use.
    pub fn new(dims: Dims) -> Geometry {
        let p = dims.points();
        Geometry {
            dims,
            key: vec![0.0; dims.key_len()],
            valid: false,
            start: vec![0; dims.cells() + 1],
            depth_at: vec![0; p],
            ctx_at: vec![0; p],
            cell_of: vec![0; p],
            builds: 0,
        }
    }

    /// How many times the geometry was computed (not found unchanged).
    pub fn builds(&self) -> usize {
        self.builds
    }

    /// How many frustum points land inside the grid.
    pub fn kept(&self) -> usize {
        self.start.last().map_or(0, |&v| v as usize)
    }

    fn same_key(&self, calib: [&[f32]; 4]) -> bool {
        let mut at = 0;
        for part in calib {
            let mine = &self.key[at..at + part.len()];
            if !mine.iter().zip(part).all(|(a, b)| a.to_bits() == b.to_bits()) {
                return false;
            }
            at += part.len();
        }
        true
    }

    /// Makes the cache hold the geometry of `calib` (`camera_intrinsics`, `camera2lidar`,
    /// `img_aug_matrix`, `lidar_aug_matrix`, of the shapes [`check`] accepted): nothing to
    /// do when they equal, bit for bit, the ones it was last computed from. Allocates
    /// nothing but an error's message. An `Err` (a singular intrinsics or image
    /// augmentation matrix, a point whose coordinates are not finite) leaves the cache
    /// empty, so the next call computes again.
    pub fn update(&mut self, op: &LssBevPool, calib: [&[f32]; 4]) -> Result<(), String> {
        if self.valid && self.same_key(calib) {
            return Ok(());
        }
        self.valid = false;
        self.compute(op, calib)?;
        let mut at = 0;
        for part in calib {
            self.key[at..at + part.len()].copy_from_slice(part);
            at += part.len();
        }
        self.valid = true;
        self.builds += 1;
        Ok(())
    }

    /// Every point's cell into `cell_of`, then a counting sort into the runs.
    fn compute(&mut self, op: &LssBevPool, [intr, c2l, img_aug, lidar_aug]: [&[f32]; 4]) -> Result<(), String> {
        let Dims { b: nb, n: nn, d: nd, fh, fw, c: nc, nx, ny, nz } = self.dims;
        let (ax, ay, az) = (axis(op.xbound), axis(op.ybound), axis(op.zbound));
        let [ih, iw] = op.image_size;
        let [d0, _, dstep] = op.dbound;
        let hw = fh * fw;
        let mut p = 0usize;
        for b in 0..nb {
            let (rl, tl) = split(&lidar_aug[b * 16..b * 16 + 16]);
            for n in 0..nn {
                let cam = (b * nn + n) * 16;
                let at = |what: &str| format!("{what}[{b}, {n}] is singular");
                let (k, _) = split(&intr[cam..cam + 16]);
                let inv_k = inverse(&k).ok_or_else(|| at("camera_intrinsics"))?;
                let (ra, ta) = split(&img_aug[cam..cam + 16]);
                let inv_a = inverse(&ra).ok_or_else(|| at("the rotation of img_aug_matrix"))?;
                let (rc, tc) = split(&c2l[cam..cam + 16]);
                let combine = mul(&rc, &inv_k);
                for d in 0..nd {
                    let depth = f64::from((d0 + d as f64 * dstep) as f32);
                    for h in 0..fh {
                        let y = f64::from(linspace(0.0, (ih - 1) as f32, fh, h));
                        for w in 0..fw {
                            let x = f64::from(linspace(0.0, (iw - 1) as f32, fw, w));
                            let q = apply(&inv_a, [x - ta[0], y - ta[1], depth - ta[2]]);
                            let q = [q[0] * q[2], q[1] * q[2], q[2]];
                            let g = apply(&combine, q);
                            let g = [g[0] + tc[0], g[1] + tc[1], g[2] + tc[2]];
                            let g = apply(&rl, g);
                            let g = [g[0] + tl[0], g[1] + tl[1], g[2] + tl[2]];
                            if !g.iter().all(|v| v.is_finite()) {
                                return Err(format!(
                                    "the geometry of camera [{b}, {n}] at depth bin {d}, row {h}, column {w} is not finite"
                                ));
                            }
                            let c = match (cell(g[0], ax, nx), cell(g[1], ay, ny), cell(g[2], az, nz)) {
                                (Some(x), Some(y), Some(z)) => (((b * nz + z) * nx + x) * ny + y) as u32,
                                _ => u32::MAX,
                            };
                            self.cell_of[p] = c;
                            p += 1;
                        }
                    }
                }
            }
        }
        // Counting sort, stable: counts, their prefix sums (each cell's start), points
        // placed in order with `start` as the cursor (it ends at each cell's end), then
        // shifted back by one cell.
        let start = &mut self.start;
        start.fill(0);
        for &c in &self.cell_of {
            if c != u32::MAX {
                start[c as usize + 1] += 1;
            }
        }
        for i in 1..start.len() {
            start[i] += start[i - 1];
        }
        let plane = nd * hw;
        for (p, &c) in self.cell_of.iter().enumerate() {
            if c == u32::MAX {
                continue;
            }
            let slot = &mut start[c as usize];
            self.depth_at[*slot as usize] = p as u32;
            // The point's camera and pixel; its context row is [b, n, 0, h, w].
            let (cam, pix) = (p / plane, p % hw);
            self.ctx_at[*slot as usize] = (cam * nc * hw + pix) as u32;
            *slot += 1;
        }
        let cells = start.len() - 1;
        start.copy_within(0..cells, 1);
        start[0] = 0;
        Ok(())
    }
}

/// Output rows (`ny` values) per parallel task, at least.
const ROWS_PER_TASK: usize = 16;

/// The BEV features `[B, C·nz, nx, ny]` into `out` from `depth` `[B, N, D, fH, fW]` and
/// `context` `[B, N, C, fH, fW]`, over the points `g` (updated for this run's
/// calibration) puts in each cell: `out[b, z·C + c, x, y] = Σ depth[p] · context[b, n, c,
/// h, w]` over the points `p = (b, n, d, h, w)` of cell `(b, z, x, y)`. Cells no point
/// reaches are 0.
pub fn lss_bev_pool(g: &Geometry, depth: &[f32], context: &[f32], out: &mut [f32], threads: usize) {
    let Dims { nx, ny, c: nc, fh, fw, .. } = g.dims;
    let hw = fh * fw;
    debug_assert!(g.valid && out.len() == g.dims.cells() * nc);
    if ny == 0 || out.is_empty() {
        return;
    }
    let row = |(r, o): (usize, &mut [f32])| {
        let x = r % nx;
        let c = (r / nx) % nc;
        let bz = r / (nx * nc);
        let cell0 = (bz * nx + x) * ny;
        let ctx = &context[c * hw..];
        for (y, v) in o.iter_mut().enumerate() {
            let (s, e) = (g.start[cell0 + y] as usize, g.start[cell0 + y + 1] as usize);
            let mut acc = 0.0f32;
            for (&p, &q) in g.depth_at[s..e].iter().zip(&g.ctx_at[s..e]) {
                acc += depth[p as usize] * ctx[q as usize];
            }
            *v = acc;
        }
    };
    if threads > 1 {
        out.par_chunks_mut(ny).enumerate().with_min_len(ROWS_PER_TASK).for_each(row);
    } else {
        out.chunks_mut(ny).enumerate().for_each(row);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::data;

    fn op() -> LssBevPool {
        LssBevPool {
            image_size: [64, 96],
            xbound: [-8.0, 8.0, 2.0],
            ybound: [-8.0, 8.0, 2.0],
            zbound: [-2.0, 2.0, 2.0],
            dbound: [2.0, 10.0, 2.0],
        }
    }

    /// A row-major 4x4 from a 3x3 block and a translation.
    fn mat4(r: [[f64; 3]; 3], t: [f64; 3]) -> Vec<f32> {
        let mut m = vec![0.0f32; 16];
        for i in 0..3 {
            for j in 0..3 {
                m[i * 4 + j] = r[i][j] as f32;
            }
            m[i * 4 + 3] = t[i] as f32;
        }
        m[15] = 1.0;
        m
    }

    fn yaw(a: f64) -> [[f64; 3]; 3] {
        [[a.cos(), -a.sin(), 0.0], [a.sin(), a.cos(), 0.0], [0.0, 0.0, 1.0]]
    }

    /// A calibration of `nb` samples of `nn` cameras, looking out horizontally around
    /// the car, with augmentations when `aug`; `seed` varies it.
    fn calib(nb: usize, nn: usize, aug: bool, seed: u64) -> [Vec<f32>; 4] {
        let jitter = data(64, seed);
        let (mut k, mut c2l, mut ia, mut la) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for b in 0..nb {
            for n in 0..nn {
                let j = |i: usize| f64::from(jitter[(b * nn + n) * 6 + i]);
                let f = 60.0 + 5.0 * j(0);
                k.extend(mat4([[f, 0.0, 47.5 + j(1)], [0.0, f, 31.5], [0.0, 0.0, 1.0]], [0.0; 3]));
                // Camera axes (x right, y down, z forward) to lidar (x forward, z up), then
                // a yaw per camera.
                let cam = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]];
                let a = n as f64 * 2.4 + 0.3 * j(2);
                let r = super::mul(&yaw(a), &cam);
                c2l.extend(mat4(r, [0.4 * j(3), 0.3 * j(4), 0.7 + 0.2 * j(5)]));
                if aug {
                    let s = 0.9 + 0.05 * j(0);
                    let rot = [
                        [s * 0.1f64.cos(), -s * 0.1f64.sin(), 0.0],
                        [s * 0.1f64.sin(), s * 0.1f64.cos(), 0.0],
                        [0.0, 0.0, 1.0],
                    ];
                    ia.extend(mat4(rot, [-3.0 + j(1), 2.0 * j(2), 0.0]));
                } else {
                    ia.extend(mat4([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.0; 3]));
                }
            }
            let (r, t) = if aug { (yaw(0.35 + 0.1 * b as f64), [0.5, -0.25, 0.1]) } else { (yaw(0.0), [0.0; 3]) };
            la.extend(mat4(r, t));
        }
        [k, c2l, ia, la]
    }

    /// Inverse by Gauss-Jordan elimination with partial pivoting.
    fn gauss_inverse(m: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
        let mut a = [[0.0; 6]; 3];
        for i in 0..3 {
            a[i][..3].copy_from_slice(&m[i]);
            a[i][3 + i] = 1.0;
        }
        for col in 0..3 {
            let piv = (col..3).max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs())).expect("rows");
            a.swap(col, piv);
            let p = a[col][col];
            a[col].iter_mut().for_each(|v| *v /= p);
            for r in 0..3 {
                if r != col {
                    let f = a[r][col];
                    let src = a[col];
                    a[r].iter_mut().zip(src).for_each(|(v, s)| *v -= f * s);
                }
            }
        }
        [0, 1, 2].map(|i| [a[i][3], a[i][4], a[i][5]])
    }

    /// The naive reference, in f64: BEVFusion's steps one by one with 4x4 matrices, the
    /// features materialised `[B, N, D, fH, fW, C]`, a scatter-add into `[B, C, nz, nx,
    /// ny]`, then the z cells moved to channels.
    fn reference(op: &LssBevPool, d: &Dims, depth: &[f32], ctx: &[f32], cal: &[Vec<f32>; 4]) -> Vec<f32> {
        let (nb, nn, nd, fh, fw, nc) = (d.b, d.n, d.d, d.fh, d.fw, d.c);
        let m = |t: &[f32], i: usize| -> [[f64; 4]; 4] {
            [0, 1, 2, 3].map(|r| [0, 1, 2, 3].map(|c| f64::from(t[i * 16 + r * 4 + c])))
        };
        let three = |m: [[f64; 4]; 4]| [0, 1, 2].map(|r| [0, 1, 2].map(|c| m[r][c]));
        let mv = |m: [[f64; 3]; 3], v: [f64; 3]| [0, 1, 2].map(|r| (0..3).map(|c| m[r][c] * v[c]).sum::<f64>());
        let grid = [op.xbound, op.ybound, op.zbound];
        let size = [d.nx, d.ny, d.nz];
        let mut feats = vec![0.0f64; nb * nn * nd * fh * fw * nc];
        for (i, f) in feats.iter_mut().enumerate() {
            let c = i % nc;
            let pt = i / nc;
            let (hw, cam) = (pt % (fh * fw), pt / (nd * fh * fw));
            *f = f64::from(depth[pt]) * f64::from(ctx[(cam * nc + c) * fh * fw + hw]);
        }
        let mut acc = vec![0.0f64; nb * nc * d.nz * d.nx * d.ny];
        for b in 0..nb {
            for n in 0..nn {
                let cam = b * nn + n;
                let (k, e, a, l) = (m(&cal[0], cam), m(&cal[1], cam), m(&cal[2], cam), m(&cal[3], b));
                for di in 0..nd {
                    for h in 0..fh {
                        for w in 0..fw {
                            let xs = (op.image_size[1] - 1) as f64 * w as f64 / (fw - 1).max(1) as f64;
                            let ys = (op.image_size[0] - 1) as f64 * h as f64 / (fh - 1).max(1) as f64;
                            let ds = op.dbound[0] + di as f64 * op.dbound[2];
                            let p = [xs - a[0][3], ys - a[1][3], ds - a[2][3]];
                            let p = mv(gauss_inverse(three(a)), p);
                            let p = [p[0] * p[2], p[1] * p[2], p[2]];
                            let p = mv(three(e), mv(gauss_inverse(three(k)), p));
                            let p = [p[0] + e[0][3], p[1] + e[1][3], p[2] + e[2][3]];
                            let p = mv(three(l), p);
                            let p = [p[0] + l[0][3], p[1] + l[1][3], p[2] + l[2][3]];
                            let ix: Vec<i64> =
                                (0..3).map(|ax| ((p[ax] - grid[ax][0]) / grid[ax][2]).trunc() as i64).collect();
                            if (0..3).any(|ax| ix[ax] < 0 || ix[ax] >= size[ax] as i64) {
                                continue;
                            }
                            let (x, y, z) = (ix[0] as usize, ix[1] as usize, ix[2] as usize);
                            let pt = (((cam * nd + di) * fh + h) * fw) + w;
                            for c in 0..nc {
                                acc[(((b * nc + c) * d.nz + z) * d.nx + x) * d.ny + y] += feats[pt * nc + c];
                            }
                        }
                    }
                }
            }
        }
        // torch.cat(x.unbind(dim=2), 1): [B, C, nz, nx, ny] to [B, nz·C, nx, ny].
        let plane = d.nx * d.ny;
        let mut out = vec![0.0f32; acc.len()];
        for b in 0..nb {
            for c in 0..nc {
                for z in 0..d.nz {
                    let src = ((b * nc + c) * d.nz + z) * plane;
                    let dst = ((b * d.nz + z) * nc + c) * plane;
                    for i in 0..plane {
                        out[dst + i] = acc[src + i] as f32;
                    }
                }
            }
        }
        out
    }

    fn shapes(d: &Dims) -> [Vec<usize>; 7] {
        let (b, n) = (d.b, d.n);
        [
            vec![b, n, d.d, d.fh, d.fw],
            vec![b, n, d.c, d.fh, d.fw],
            vec![b, n, 4, 4],
            vec![b, n, 4, 4],
            vec![b, n, 4, 4],
            vec![b, 4, 4],
            vec![b, d.c * d.nz, d.nx, d.ny],
        ]
    }

    fn run(
        op: &LssBevPool,
        g: &mut Geometry,
        depth: &[f32],
        ctx: &[f32],
        cal: &[Vec<f32>; 4],
        threads: usize,
    ) -> Vec<f32> {
        g.update(op, [&cal[0], &cal[1], &cal[2], &cal[3]]).expect("geometry");
        let mut out = vec![f32::NAN; g.dims.cells() * g.dims.c];
        lss_bev_pool(g, depth, ctx, &mut out, threads);
        out
    }

    fn assert_close(got: &[f32], want: &[f32]) {
        crate::kernels::testutil::assert_close(got, want, 1e-5);
    }

    #[test]
    fn matches_the_naive_reference() {
        for (nb, nn, fh, fw, c, aug) in [(1, 2, 4, 6, 3, false), (2, 3, 5, 7, 4, true), (1, 1, 1, 1, 2, true)] {
            let op = op();
            let s = |v: &[usize]| v.to_vec();
            let dims = Dims { b: nb, n: nn, d: 4, fh, fw, c, nx: 8, ny: 8, nz: 2 };
            let sh = shapes(&dims);
            let parts: Vec<&[usize]> = sh[..6].iter().map(Vec::as_slice).collect();
            assert_eq!(check(&op, &parts, &s(&sh[6])), Ok(dims));
            let depth: Vec<f32> = data(dims.points(), 3).iter().map(|v| v.abs()).collect();
            let ctx = data(nb * nn * c * fh * fw, 4);
            let cal = calib(nb, nn, aug, 5);
            let want = reference(&op, &dims, &depth, &ctx, &cal);
            let mut g = Geometry::new(dims);
            let one = run(&op, &mut g, &depth, &ctx, &cal, 1);
            assert_close(&one, &want);
            let two = run(&op, &mut g, &depth, &ctx, &cal, 2);
            assert!(one.iter().zip(&two).all(|(a, b)| a.to_bits() == b.to_bits()), "threads change the sums");
            if fh > 1 {
                assert!(g.kept() > dims.points() / 2, "only {} of {} points kept", g.kept(), dims.points());
                assert!(g.kept() < dims.points(), "every point kept: the test does not drop any");
            }
        }
    }

    #[test]
    fn the_cache_follows_the_calibration() {
        let op = op();
        let dims = Dims { b: 1, n: 2, d: 4, fh: 4, fw: 6, c: 3, nx: 8, ny: 8, nz: 2 };
        let depth = data(dims.points(), 7);
        let ctx = data(2 * 3 * 24, 8);
        let (a, b) = (calib(1, 2, false, 1), calib(1, 2, true, 2));
        let mut g = Geometry::new(dims);
        assert_close(&run(&op, &mut g, &depth, &ctx, &a, 1), &reference(&op, &dims, &depth, &ctx, &a));
        run(&op, &mut g, &depth, &ctx, &a, 1);
        assert_eq!(g.builds(), 1, "the same calibration computed again");
        assert_close(&run(&op, &mut g, &depth, &ctx, &b, 1), &reference(&op, &dims, &depth, &ctx, &b));
        assert_eq!(g.builds(), 2);
        // One bit of one matrix is a new calibration.
        let mut c = b.clone();
        c[3][3] = f32::from_bits(c[3][3].to_bits() ^ 1);
        run(&op, &mut g, &depth, &ctx, &c, 1);
        assert_eq!(g.builds(), 3);
    }

    #[test]
    fn truncation_keeps_points_less_than_a_cell_below_the_grid() {
        // One camera looking along lidar x from the origin, one pixel, one depth bin at 4:
        // the point sits at x = 4 + tx. With xbound [5, 13, 2], tx = 0.5 puts it half a
        // cell below the grid (cell 0, as `.long()` truncates -0.25 to 0), tx = -1.5 one
        // and a quarter cells below (dropped), tx = 3.5 in cell 1.
        let op = LssBevPool {
            image_size: [1, 1],
            xbound: [5.0, 13.0, 2.0],
            ybound: [-1.0, 1.0, 2.0],
            zbound: [-1.0, 1.0, 2.0],
            dbound: [4.0, 5.0, 1.0],
        };
        let dims = Dims { b: 1, n: 1, d: 1, fh: 1, fw: 1, c: 1, nx: 4, ny: 1, nz: 1 };
        let cam = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]];
        let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let mut g = Geometry::new(dims);
        for (tx, want) in [(0.5, [2.0f32, 0.0, 0.0, 0.0]), (-1.5, [0.0; 4]), (3.5, [0.0, 2.0, 0.0, 0.0])] {
            let cal = [
                mat4(id, [0.0; 3]),
                mat4(cam, [tx, 0.0, 0.0]),
                mat4(id, [0.0; 3]),
                vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            ];
            assert_eq!(run(&op, &mut g, &[2.0], &[1.0], &cal, 1), want, "tx {tx}");
        }
    }

    #[test]
    fn singular_matrices_are_refused() {
        let op = op();
        let dims = Dims { b: 1, n: 2, d: 4, fh: 4, fw: 6, c: 3, nx: 8, ny: 8, nz: 2 };
        let mut g = Geometry::new(dims);
        let mut cal = calib(1, 2, true, 9);
        cal[0][16] = 0.0; // camera 1's fx
        let e = g.update(&op, [&cal[0], &cal[1], &cal[2], &cal[3]]).expect_err("fx = 0");
        assert_eq!(e, "camera_intrinsics[0, 1] is singular");
        let mut cal = calib(1, 2, true, 9);
        for v in &mut cal[2][..3] {
            *v = 0.0; // camera 0's augmentation loses a row
        }
        let e = g.update(&op, [&cal[0], &cal[1], &cal[2], &cal[3]]).expect_err("row of zeros");
        assert_eq!(e, "the rotation of img_aug_matrix[0, 0] is singular");
        // After an error the next good calibration is computed.
        let good = calib(1, 2, true, 9);
        g.update(&op, [&good[0], &good[1], &good[2], &good[3]]).expect("good");
        assert_eq!(g.builds(), 1);
    }

    #[test]
    fn linspace_as_torch() {
        assert_eq!((0..6).map(|i| linspace(0.0, 95.0, 6, i)).collect::<Vec<_>>(), [0.0, 19.0, 38.0, 57.0, 76.0, 95.0]);
        assert_eq!(linspace(0.0, 63.0, 1, 0), 0.0);
        assert_eq!(linspace(0.0, 1.0, 3, 2), 1.0);
    }

    #[test]
    fn check_refuses_mismatched_shapes() {
        let op = op();
        let dims = Dims { b: 1, n: 2, d: 4, fh: 4, fw: 6, c: 3, nx: 8, ny: 8, nz: 2 };
        let sh = shapes(&dims);
        let mut parts: Vec<&[usize]> = sh[..6].iter().map(Vec::as_slice).collect();
        assert!(check(&op, &parts, &[1, 3, 8, 8]).is_err(), "C·nz channels");
        assert!(check(&op, &parts[..5], &sh[6]).is_err());
        let bad = [1, 2, 4, 4];
        parts[5] = &bad;
        assert!(check(&op, &parts, &sh[6]).expect_err("rank").contains("lidar_aug_matrix"));
    }
}
