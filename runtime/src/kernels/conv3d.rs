//! 3-D convolution (PyTorch's `Conv3d`), NCDHW, weight as PyTorch stores it,
//! `[cout, cin/groups, kd, kh, kw]`, with a fused per-channel epilogue.
//!
//! Three paths, chosen from the shape ([`path`]); the weight is read as it is by each:
//!
//! * vol2col + GEMM (any shape): per image and group, per tile of output voxels, the input
//!   under each tap is unfolded into a `(cin/groups·kd·kh·kw) × tile` matrix ([`vol2col`])
//!   and one GEMM multiplies the group's weight by it, straight into the output planes
//!   (rows `od·oh·ow` apart); the epilogue runs on the tile while it is in cache.
//! * 1x1x1, stride 1, no padding: the input already is that matrix; the GEMM reads it.
//! * depthwise (one input channel per group, more than one group): a direct loop per
//!   output row, no GEMM: the unfolded matrix would have only `kd·kh·kw` rows.
//!
//! Threads: a GEMM work unit is one image and group, whose output planes are contiguous.
//! With at least as many units as threads, each thread owns a run of units, their planes
//! and a tile of the unfolded matrix in the scratch, and never synchronises. With fewer
//! (one image, one group: a lidar encoder at batch 1), the units run one after another
//! and every tile is shared: the threads unfold it by ranges of its rows, then each
//! multiplies it by its range of the output channels and finishes those rows, so no
//! thread unfolds what another one does. Depthwise layers split by output planes.
//! Allocates nothing itself, but each GEMM call (the `gemm` crate, as conv2d's) makes a
//! few small allocations: a batch-1 layer of one tile on 2 threads measured 4 per run
//! (the sparse kernels, through `panel.rs`, make none).

use super::Epilogue;
use super::elementwise::relu;
use super::gemm::{MatMut, MatRef, sgemm};

pub use readi_plan::ops::Conv3dShape;

/// Most elements of the input, output or weight [`check`] accepts (as conv's).
const MAX_ELEMENTS: usize = 1 << 48;

/// How a layer is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Path {
    /// Unfold a tile of output voxels, one GEMM, the epilogue.
    Vol2col,
    /// 1x1x1, stride 1, no padding: GEMM on the input as it is.
    Gemm1x1,
    /// One input channel per group, more than one group: the direct loop.
    Depthwise,
}

/// The path that computes `s`.
pub fn path(s: &Conv3dShape) -> Path {
    if s.groups > 1 && s.cin_g() == 1 {
        Path::Depthwise
    } else if s.kernel == [1; 3] && s.stride == [1; 3] && s.pad == [0; 3] {
        Path::Gemm1x1
    } else {
        Path::Vol2col
    }
}

/// Output voxels per GEMM tile: the unfolded tile and the output tile fill up to 1.5 MiB,
/// in multiples of 16 (the GEMM's vector width), as conv2d's.
fn tile(s: &Conv3dShape) -> usize {
    let per_voxel = s.cout_g().saturating_add(if path(s) == Path::Vol2col { s.k() } else { 0 }).max(1);
    let t = (384 * 1024 / per_voxel).clamp(16, 4096) / 16 * 16;
    t.min(s.out_plane().div_ceil(16) * 16)
}

/// GEMM work units (image, group) and how many threads take runs of them: all of them
/// when there are enough units, else 1 (the units run in turn, each tile shared).
fn unit_parts(s: &Conv3dShape, threads: usize) -> (usize, usize) {
    let units = s.n.saturating_mul(s.groups);
    let threads = threads.max(1);
    (units, if units >= threads { threads } else { 1 })
}

/// Scratch floats [`conv3d`] needs at this thread count, `None` on overflow.
pub fn scratch_len(s: &Conv3dShape, threads: usize) -> Option<usize> {
    match path(s) {
        Path::Depthwise | Path::Gemm1x1 => Some(0),
        Path::Vol2col => {
            let (_, parts) = unit_parts(s, threads);
            let k = s.cin_g().checked_mul(s.kernel[0])?.checked_mul(s.kernel[1])?.checked_mul(s.kernel[2])?;
            parts.checked_mul(k)?.checked_mul(tile(s))
        }
    }
}

/// The preconditions of [`conv3d`]: groups divide the channels, no kernel, stride or
/// dilation is 0, the output size is PyTorch's, and the lengths of the weight, input,
/// output and epilogue vectors fit the shape. The executor checks this at bind time.
pub fn check(
    s: &Conv3dShape,
    weight_len: usize,
    x_len: usize,
    out_len: usize,
    epilogue: [Option<usize>; 2],
) -> Result<(), String> {
    if s.groups == 0 || !s.cin.is_multiple_of(s.groups) || !s.cout.is_multiple_of(s.groups) {
        return Err(format!("groups={} must divide {} input and {} output channels", s.groups, s.cin, s.cout));
    }
    if s.cin == 0 || s.cout == 0 {
        return Err(format!("{} input and {} output channels: a conv3d needs at least one", s.cin, s.cout));
    }
    if s.kernel.iter().chain(&s.stride).chain(&s.dil).any(|&v| v == 0) {
        return Err(format!("kernel {:?}, stride {:?}, dilation {:?}: none may be 0", s.kernel, s.stride, s.dil));
    }
    let product =
        |dims: &[usize]| dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).filter(|&n| n <= MAX_ELEMENTS);
    let [d, h, w] = s.input;
    let [od, oh, ow] = s.out;
    let [kd, kh, kw] = s.kernel;
    let (Some(wl), Some(xl), Some(ol)) = (
        product(&[s.cout, s.cin_g(), kd, kh, kw]),
        product(&[s.n, s.cin, d, h, w]),
        product(&[s.n, s.cout, od, oh, ow]),
    ) else {
        return Err(format!("the layer is too large ({s:?})"));
    };
    let sizes = s.input.iter().chain(&s.out).chain(&s.pad).chain(&s.stride).chain(&s.dil);
    if sizes.chain(&s.kernel).any(|&v| v > MAX_ELEMENTS) {
        return Err(format!("input {:?}, output {:?}: out of range", s.input, s.out));
    }
    for (i, axis) in ["depth", "height", "width"].into_iter().enumerate() {
        // Every value is at most 2^48 (checked above), so each fits an i64.
        let v = |x: usize| x as i64;
        let want =
            readi_plan::ops::window_out(v(s.input[i]), v(s.kernel[i]), v(s.stride[i]), v(s.pad[i]), v(s.dil[i]), false);
        if want != Some(v(s.out[i])) {
            return Err(format!(
                "output {axis} {} is not PyTorch's for input {}, kernel {}, stride {}, padding {}, dilation {}",
                s.out[i], s.input[i], s.kernel[i], s.stride[i], s.pad[i], s.dil[i]
            ));
        }
    }
    if weight_len != wl {
        return Err(format!(
            "weight has {weight_len} values, [{}, {}, {kd}, {kh}, {kw}] needs {wl}",
            s.cout,
            s.cin_g()
        ));
    }
    if x_len != xl || out_len != ol {
        return Err(format!("input has {x_len} values (needs {xl}), output {out_len} (needs {ol})"));
    }
    if let Some(n) = epilogue.into_iter().flatten().find(|&n| n != s.cout) {
        return Err(format!("an epilogue vector has {n} values for {} output channels", s.cout));
    }
    Ok(())
}

/// Computes one layer: `out = epilogue(conv3d(x, weight))`; `scratch` holds at least
/// [`scratch_len`] floats.
///
/// # Panics
/// If the layer fails [`check`] or the scratch is short.
pub fn conv3d(
    s: &Conv3dShape,
    weight: &[f32],
    ep: &Epilogue,
    x: &[f32],
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    let lens = [ep.scale.map(<[f32]>::len), ep.shift.map(<[f32]>::len)];
    if let Err(e) = check(s, weight.len(), x.len(), out.len(), lens) {
        panic!("conv3d: {e}");
    }
    let need = scratch_len(s, threads).unwrap_or(usize::MAX);
    assert!(scratch.len() >= need, "conv3d: scratch has {} floats, needs {need}", scratch.len());
    if out.is_empty() {
        return;
    }
    let threads = threads.max(1);
    let job = Job { s, weight, ep, x, path: path(s), tile: tile(s), plane: s.out_plane() };
    if job.path == Path::Depthwise {
        let planes = s.n * s.cout;
        job.depthwise_planes(out, 0, planes, threads.min(planes));
        return;
    }
    let (units, parts) = unit_parts(s, threads);
    if parts > 1 || threads == 1 {
        job.units(out, scratch, 0, units, parts);
    } else {
        let per_unit = s.cout_g() * job.plane;
        for (u, planes) in out.chunks_mut(per_unit).enumerate() {
            job.shared_unit(u, planes, scratch, threads);
        }
    }
}

/// What every unit of one call reads.
struct Job<'a> {
    s: &'a Conv3dShape,
    weight: &'a [f32],
    ep: &'a Epilogue<'a>,
    x: &'a [f32],
    path: Path,
    /// Output voxels per GEMM tile.
    tile: usize,
    /// Voxels of one output plane.
    plane: usize,
}

impl Job<'_> {
    /// Floats of the unfolded tile (0 when nothing is unfolded).
    fn col_len(&self) -> usize {
        if self.path == Path::Vol2col { self.s.k() * self.tile } else { 0 }
    }

    /// Units `u0..u1` on `parts` threads: `out` holds their planes, `scratch` an unfolded
    /// tile per part. Halves the range until one part is left.
    fn units(&self, out: &mut [f32], scratch: &mut [f32], u0: usize, u1: usize, parts: usize) {
        let per_unit = self.s.cout_g() * self.plane;
        let per_part = self.col_len();
        if parts <= 1 || u1 - u0 <= 1 {
            for (u, planes) in (u0..u1).zip(out.chunks_mut(per_unit)) {
                self.unit(u, planes, &mut scratch[..per_part]);
            }
            return;
        }
        let half = parts / 2;
        let um = u0 + (u1 - u0) * half / parts;
        let (lo, hi) = out.split_at_mut((um - u0) * per_unit);
        let (slo, shi) = scratch.split_at_mut(half * per_part);
        rayon::join(|| self.units(lo, slo, u0, um, half), || self.units(hi, shi, um, u1, parts - half));
    }

    /// The input of unit `u`'s group and the first channel of the group.
    fn group_of(&self, u: usize) -> (&[f32], usize) {
        let s = self.s;
        let (n, g) = (u / s.groups, u % s.groups);
        let plane_in = s.in_plane();
        (&self.x[(n * s.cin + g * s.cin_g()) * plane_in..][..s.cin_g() * plane_in], g * s.cout_g())
    }

    /// The GEMM's right-hand matrix for voxels `p0..p0 + tp`: the unfolded tile in
    /// `col` (which `unfold` filled) or the input itself.
    fn rhs<'b>(&self, xg: &'b [f32], col: &'b [f32], p0: usize, tp: usize) -> MatRef<'b> {
        let s = self.s;
        if self.path == Path::Gemm1x1 {
            MatRef { data: &xg[p0..], rows: s.cin_g(), cols: tp, row_stride: s.in_plane(), col_stride: 1 }
        } else {
            MatRef::row_major(&col[..s.k() * tp], s.k(), tp)
        }
    }

    /// Unit `u` (one image and group) on the calling thread, into `planes` (its output
    /// channels'), `col` holding one unfolded tile.
    fn unit(&self, u: usize, planes: &mut [f32], col: &mut [f32]) {
        let s = self.s;
        let (xg, c0) = self.group_of(u);
        let wg = &self.weight[c0 * s.k()..][..s.cout_g() * s.k()];
        let mut p0 = 0;
        while p0 < self.plane {
            let tp = self.tile.min(self.plane - p0);
            if self.path == Path::Vol2col {
                vol2col(s, xg, p0, tp, 0, s.k(), &mut col[..s.k() * tp]);
            }
            self.gemm_rows(wg, self.rhs(xg, col, p0, tp), planes, c0, p0, tp);
            p0 += tp;
        }
    }

    /// Unit `u` on all `threads`: per tile, the rows of the unfolded tile split between
    /// them, then the output channels.
    fn shared_unit(&self, u: usize, planes: &mut [f32], col: &mut [f32], threads: usize) {
        let s = self.s;
        let (xg, c0) = self.group_of(u);
        let wg = &self.weight[c0 * s.k()..][..s.cout_g() * s.k()];
        let mut p0 = 0;
        while p0 < self.plane {
            let tp = self.tile.min(self.plane - p0);
            if self.path == Path::Vol2col {
                self.unfold(xg, p0, tp, 0, s.k(), &mut col[..s.k() * tp], threads.min(s.k()));
            }
            let rhs = self.rhs(xg, col, p0, tp);
            self.gemm_split(wg, rhs, planes, c0, p0, tp, threads.min(s.cout_g()));
            p0 += tp;
        }
    }

    /// Rows `r0..r1` of the unfolded tile of voxels `p0..p0 + tp` into `col` on `parts`
    /// threads.
    #[allow(clippy::too_many_arguments)]
    fn unfold(&self, xg: &[f32], p0: usize, tp: usize, r0: usize, r1: usize, col: &mut [f32], parts: usize) {
        if parts <= 1 || r1 - r0 <= 1 {
            vol2col(self.s, xg, p0, tp, r0, r1, col);
            return;
        }
        let half = parts / 2;
        let rm = r0 + (r1 - r0) * half / parts;
        let (lo, hi) = col.split_at_mut((rm - r0) * tp);
        rayon::join(|| self.unfold(xg, p0, tp, r0, rm, lo, half), || self.unfold(xg, p0, tp, rm, r1, hi, parts - half));
    }

    /// [`Job::gemm_rows`] on `parts` threads, each taking a range of the channels (rows
    /// of `w` and planes of `planes`, the first being channel `c0`).
    #[allow(clippy::too_many_arguments)]
    fn gemm_split(&self, w: &[f32], rhs: MatRef, planes: &mut [f32], c0: usize, p0: usize, tp: usize, parts: usize) {
        let rows = planes.len() / self.plane;
        if parts <= 1 || rows <= 1 {
            self.gemm_rows(w, rhs, planes, c0, p0, tp);
            return;
        }
        let half = parts / 2;
        let mid = rows * half / parts;
        let (plo, phi) = planes.split_at_mut(mid * self.plane);
        let (wlo, whi) = w.split_at(mid * rhs.rows);
        rayon::join(
            || self.gemm_split(wlo, rhs, plo, c0, p0, tp, half),
            || self.gemm_split(whi, rhs, phi, c0 + mid, p0, tp, parts - half),
        );
    }

    /// `planes[c][p0..p0 + tp] = epilogue(w[c] · rhs)` for each channel `c` of `planes`
    /// (the first is channel `c0`), `w` row-major with `rhs.rows` columns.
    fn gemm_rows(&self, w: &[f32], rhs: MatRef, planes: &mut [f32], c0: usize, p0: usize, tp: usize) {
        let rows = planes.len() / self.plane;
        let lhs = MatRef::row_major(&w[..rows * rhs.rows], rows, rhs.rows);
        let dst = MatMut { data: &mut planes[p0..], rows, cols: tp, row_stride: self.plane, col_stride: 1 };
        sgemm(lhs, rhs, dst, false, 1);
        finish_tile(planes, self.plane, p0, tp, c0, self.ep);
    }

    /// Depthwise planes `u0..u1` (global index `image · cout + channel`) on `parts`
    /// threads, into `out` (their planes).
    fn depthwise_planes(&self, out: &mut [f32], u0: usize, u1: usize, parts: usize) {
        if parts <= 1 || u1 - u0 <= 1 {
            let s = self.s;
            let plane_in = s.in_plane();
            let taps = s.taps();
            for (u, plane) in (u0..u1).zip(out.chunks_mut(self.plane)) {
                let (n, c) = (u / s.cout, u % s.cout);
                // One input channel per group: the group's index is the input channel's.
                let ci = c / s.cout_g();
                let xc = &self.x[(n * s.cin + ci) * plane_in..][..plane_in];
                depthwise_plane(s, xc, &self.weight[c * taps..][..taps], plane, c, self.ep);
            }
            return;
        }
        let half = parts / 2;
        let um = u0 + (u1 - u0) * half / parts;
        let (lo, hi) = out.split_at_mut((um - u0) * self.plane);
        rayon::join(|| self.depthwise_planes(lo, u0, um, half), || self.depthwise_planes(hi, um, u1, parts - half));
    }
}

/// The range of output indices `o` in `0..out` whose input index `o·stride + off` lies in
/// `0..len`.
#[inline(always)]
fn inside(out: usize, len: usize, stride: usize, off: isize) -> (usize, usize) {
    let lo = ((-off).max(0) as usize).div_ceil(stride).min(out);
    let hi = if len as isize - off <= 0 { 0 } else { ((len as isize - off) as usize).div_ceil(stride).min(out) };
    (lo, hi.max(lo))
}

/// The input offset of tap `t` along an axis: `t·dilation − padding`.
#[inline(always)]
fn offset(t: usize, dil: usize, pad: usize) -> isize {
    (t * dil) as isize - pad as isize
}

simd_fn! {
    /// Rows `r0..r1` of the unfolded matrix of output voxels `p0..p0 + tp` of one image
    /// and group into `col` (row-major, rows of `tp`): row `(ci, kz, ky, kx)`, column `p`
    /// holds the input voxel tap `(kz, ky, kx)` of output voxel `p` reads from channel
    /// `ci`, 0 in the padding.
    fn vol2col(s: &Conv3dShape, xg: &[f32], p0: usize, tp: usize, r0: usize, r1: usize, col: &mut [f32]) {
        let [d, h, w] = s.input;
        let [_, oh, ow] = s.out;
        let [_, kh, kw] = s.kernel;
        let taps = s.taps();
        let plane_in = s.in_plane();
        for (r, dst) in (r0..r1).zip(col.chunks_mut(tp)) {
            let (ci, t) = (r / taps, r % taps);
            let (tz, ty, tx) = (t / (kh * kw), t / kw % kh, t % kw);
            let xc = &xg[ci * plane_in..][..plane_in];
            let dz = offset(tz, s.dil[0], s.pad[0]);
            let dy = offset(ty, s.dil[1], s.pad[1]);
            let dx = offset(tx, s.dil[2], s.pad[2]);
            let (ox_lo, ox_hi) = inside(ow, w, s.stride[2], dx);
            // The tile in runs along the output rows.
            let mut p = p0;
            let mut off = 0;
            while off < tp {
                let (row, ox0) = (p / ow, p % ow);
                let (oz, oy) = (row / oh, row % oh);
                let run = (ow - ox0).min(tp - off);
                let seg = &mut dst[off..off + run];
                let iz = (oz * s.stride[0]) as isize + dz;
                let iy = (oy * s.stride[1]) as isize + dy;
                if iz < 0 || iz >= d as isize || iy < 0 || iy >= h as isize {
                    seg.fill(0.0);
                } else {
                    let src = &xc[(iz as usize * h + iy as usize) * w..][..w];
                    let (a, b) = (ox_lo.clamp(ox0, ox0 + run), ox_hi.clamp(ox0, ox0 + run));
                    seg[..a - ox0].fill(0.0);
                    seg[b - ox0..].fill(0.0);
                    if a < b {
                        let ix0 = ((a * s.stride[2]) as isize + dx) as usize;
                        strided_copy(&mut seg[a - ox0..b - ox0], &src[ix0..], s.stride[2]);
                    }
                }
                p += run;
                off += run;
            }
        }
    }
}

/// `dst[i] = src[i · stride]`.
#[inline(always)]
fn strided_copy(dst: &mut [f32], src: &[f32], stride: usize) {
    if stride == 1 {
        dst.copy_from_slice(&src[..dst.len()]);
    } else {
        dst.iter_mut().zip(src.iter().step_by(stride)).for_each(|(d, &v)| *d = v);
    }
}

/// `dst[i] += w · src[i · stride]`.
#[inline(always)]
fn strided_axpy(dst: &mut [f32], src: &[f32], stride: usize, w: f32) {
    if stride == 1 {
        dst.iter_mut().zip(src).for_each(|(d, &v)| *d += w * v);
    } else {
        dst.iter_mut().zip(src.iter().step_by(stride)).for_each(|(d, &v)| *d += w * v);
    }
}

/// The epilogue of channel `c` in place on `row`.
#[inline(always)]
fn finish_row(row: &mut [f32], c: usize, ep: &Epilogue) {
    let scale = ep.scale.map_or(1.0, |v| v[c]);
    let shift = ep.shift.map_or(0.0, |v| v[c]);
    match (ep.scale.is_some(), ep.relu()) {
        (true, true) => row.iter_mut().for_each(|a| *a = relu(*a * scale + shift)),
        (true, false) => row.iter_mut().for_each(|a| *a = *a * scale + shift),
        (false, true) => row.iter_mut().for_each(|a| *a = relu(*a + shift)),
        (false, false) if ep.shift.is_some() => row.iter_mut().for_each(|a| *a += shift),
        (false, false) => {}
    }
    ep.finish_act(row);
}

simd_fn! {
    /// The epilogue on voxels `p0..p0 + tp` of each plane (of `plane` voxels) of `planes`,
    /// the first being channel `c0`.
    fn finish_tile(planes: &mut [f32], plane: usize, p0: usize, tp: usize, c0: usize, ep: &Epilogue<'_>) {
        for (i, p) in planes.chunks_mut(plane).enumerate() {
            finish_row(&mut p[p0..p0 + tp], c0 + i, ep);
        }
    }
}

simd_fn! {
    /// One depthwise output plane (channel `c`, input channel `xc`, weight `wc` of
    /// `kd·kh·kw` taps): per output row, each tap inside the input adds its weight times
    /// the input row it reads; then the epilogue on the row.
    fn depthwise_plane(s: &Conv3dShape, xc: &[f32], wc: &[f32], out: &mut [f32], c: usize, ep: &Epilogue<'_>) {
        let [d, h, w] = s.input;
        let [od, oh, ow] = s.out;
        let [kd, kh, kw] = s.kernel;
        for oz in 0..od {
            for oy in 0..oh {
                let row = &mut out[(oz * oh + oy) * ow..][..ow];
                row.fill(0.0);
                for tz in 0..kd {
                    let iz = (oz * s.stride[0]) as isize + offset(tz, s.dil[0], s.pad[0]);
                    if iz < 0 || iz >= d as isize {
                        continue;
                    }
                    for ty in 0..kh {
                        let iy = (oy * s.stride[1]) as isize + offset(ty, s.dil[1], s.pad[1]);
                        if iy < 0 || iy >= h as isize {
                            continue;
                        }
                        let src = &xc[(iz as usize * h + iy as usize) * w..][..w];
                        for tx in 0..kw {
                            let dx = offset(tx, s.dil[2], s.pad[2]);
                            let (a, b) = inside(ow, w, s.stride[2], dx);
                            if a < b {
                                let ix0 = ((a * s.stride[2]) as isize + dx) as usize;
                                let wv = wc[(tz * kh + ty) * kw + tx];
                                strided_axpy(&mut row[a..b], &src[ix0..], s.stride[2], wv);
                            }
                        }
                    }
                }
                finish_row(row, c, ep);
            }
        }
    }
}

/// The naive loop: every output voxel the sum over its group's input channels and the
/// taps inside the input, then the epilogue; the reference of the tests and benchmarks.
pub fn reference(s: &Conv3dShape, weight: &[f32], ep: &Epilogue, x: &[f32], out: &mut [f32]) {
    let (cin_g, cout_g) = (s.cin_g(), s.cout_g());
    let [d, h, w] = s.input;
    let [od, oh, ow] = s.out;
    let [kd, kh, kw] = s.kernel;
    let at = |o: usize, k: usize, axis: usize| (o * s.stride[axis] + k * s.dil[axis]) as isize - s.pad[axis] as isize;
    for n in 0..s.n {
        for co in 0..s.cout {
            let g = co / cout_g;
            for oz in 0..od {
                for oy in 0..oh {
                    for ox in 0..ow {
                        let mut acc = 0.0f64;
                        for cl in 0..cin_g {
                            let ci = g * cin_g + cl;
                            for tz in 0..kd {
                                for ty in 0..kh {
                                    for tx in 0..kw {
                                        let (iz, iy, ix) = (at(oz, tz, 0), at(oy, ty, 1), at(ox, tx, 2));
                                        if iz < 0 || iy < 0 || ix < 0 {
                                            continue;
                                        }
                                        let (iz, iy, ix) = (iz as usize, iy as usize, ix as usize);
                                        if iz >= d || iy >= h || ix >= w {
                                            continue;
                                        }
                                        let xv = x[(((n * s.cin + ci) * d + iz) * h + iy) * w + ix];
                                        let wv = weight[(((co * cin_g + cl) * kd + tz) * kh + ty) * kw + tx];
                                        acc += xv as f64 * wv as f64;
                                    }
                                }
                            }
                        }
                        let mut v = acc as f32 * ep.scale.map_or(1.0, |v| v[co]) + ep.shift.map_or(0.0, |v| v[co]);
                        if let Some(act) = ep.act {
                            v = act.reference(v as f64) as f32;
                        }
                        out[(((n * s.cout + co) * od + oz) * oh + oy) * ow + ox] = v;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdata::data;
    use readi_plan::ops::{Activation, Conv3d, Window3};

    /// `(n, cin, [d, h, w], cout, kernel, stride, padding, dilation, groups)`.
    type Case = (usize, usize, [usize; 3], usize, [i64; 3], [i64; 3], [i64; 3], [i64; 3], usize);

    fn shape(c: &Case) -> Conv3dShape {
        let &(n, cin, [d, h, w], cout, kernel, stride, padding, dilation, groups) = c;
        let window = Window3 { kernel, stride, padding, dilation };
        Conv3d { in_channels: cin as i64, out_channels: cout as i64, window, groups: groups as i64 }.shape(n, d, h, w)
    }

    const CASES: &[Case] = &[
        // SECOND's submanifold-sized block (small): 3x3x3, padding 1.
        (1, 4, [5, 6, 7], 8, [3; 3], [1; 3], [1; 3], [1; 3], 1),
        // Stride 2 with padding, two images (units split between threads).
        (2, 3, [7, 6, 9], 5, [3; 3], [2; 3], [1; 3], [1; 3], 1),
        // Its depth downsampling: kernel (3, 1, 1), stride (2, 1, 1).
        (1, 6, [9, 4, 5], 6, [3, 1, 1], [2, 1, 1], [0; 3], [1; 3], 1),
        // Dilation and mixed padding, a rectangular kernel.
        (1, 2, [8, 7, 9], 3, [2, 3, 2], [1, 2, 1], [2, 0, 1], [3, 2, 2], 1),
        // Groups.
        (2, 6, [4, 5, 6], 4, [3, 2, 3], [1, 1, 2], [1, 1, 1], [1; 3], 2),
        // Depthwise with padding, stride and dilation; a channel multiplier of 2.
        (1, 4, [6, 7, 8], 4, [3; 3], [2, 1, 2], [1, 2, 1], [1, 2, 1], 4),
        (2, 3, [4, 4, 5], 6, [2, 3, 3], [1; 3], [0, 1, 1], [2, 1, 1], 3),
        // 1x1x1 (the plain GEMM), and 1x1x1 with stride 2 (unfolded).
        (2, 5, [3, 4, 5], 7, [1; 3], [1; 3], [0; 3], [1; 3], 1),
        (1, 5, [3, 4, 5], 7, [1; 3], [2; 3], [0; 3], [1; 3], 1),
        // A window larger than the input, filled by the padding; stride above the kernel.
        (1, 2, [2, 2, 2], 3, [3; 3], [3, 4, 3], [2; 3], [1; 3], 1),
        // More voxels than one tile holds, so tiles straddle output rows and slices.
        (1, 3, [6, 18, 23], 4, [3; 3], [1; 3], [1; 3], [1; 3], 1),
    ];

    fn run(s: &Conv3dShape, w: &[f32], ep: &Epilogue, x: &[f32], threads: usize) -> Vec<f32> {
        let mut out = vec![f32::NAN; s.n * s.cout * s.out_plane()];
        let mut scratch = vec![f32::NAN; scratch_len(s, threads).expect("fits")];
        conv3d(s, w, ep, x, &mut out, &mut scratch, threads);
        out
    }

    fn close(got: &[f32], want: &[f32], what: &str) {
        assert_eq!(got.len(), want.len(), "{what}");
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!((g - w).abs() <= 1e-4 * w.abs().max(1.0), "{what}[{i}]: {g} vs {w}");
        }
    }

    #[test]
    fn matches_the_naive_loop() {
        let paths: Vec<Path> = CASES.iter().map(|c| path(&shape(c))).collect();
        for p in [Path::Vol2col, Path::Gemm1x1, Path::Depthwise] {
            assert!(paths.contains(&p), "no case takes {p:?}");
        }
        for (k, c) in CASES.iter().enumerate() {
            let s = shape(c);
            let x = data(s.n * s.cin * s.in_plane(), 2 * k as u64);
            let w = data(s.weight_len(), 2 * k as u64 + 1);
            let bias = data(s.cout, 99);
            let scale = data(s.cout, 98);
            let eps = [
                Epilogue { scale: None, shift: None, act: None },
                Epilogue { scale: None, shift: Some(&bias), act: Some(Activation::Relu) },
                Epilogue { scale: Some(&scale), shift: Some(&bias), act: Some(Activation::Silu) },
            ];
            for ep in &eps {
                let mut want = vec![0.0; s.n * s.cout * s.out_plane()];
                reference(&s, &w, ep, &x, &mut want);
                for threads in [1, 2, 3] {
                    let what = format!("case {k} ({:?}) at {threads} threads {ep:?}", paths[k]);
                    close(&run(&s, &w, ep, &x, threads), &want, &what);
                }
            }
        }
    }

    #[test]
    fn hand_computed_values() {
        // One channel, a 2x2x2 input 1..8, a 2x2x2 kernel of ones: one output, the sum 36.
        let s = shape(&(1, 1, [2, 2, 2], 1, [2; 3], [1; 3], [0; 3], [1; 3], 1));
        let x: Vec<f32> = (1..=8).map(|v| v as f32).collect();
        assert_eq!(run(&s, &[1.0; 8], &Epilogue::default(), &x, 1), [36.0]);
        // A 1x1x1 kernel at stride 2 over 3x1x3 picks the corners: x[0], x[2], x[6], x[8].
        let s = shape(&(1, 1, [3, 1, 3], 1, [1; 3], [2; 3], [0; 3], [1; 3], 1));
        let x: Vec<f32> = (0..9).map(|v| v as f32).collect();
        assert_eq!(run(&s, &[10.0], &Epilogue::default(), &x, 1), [0.0, 20.0, 60.0, 80.0]);
        // Padding 1 around a single voxel 2 with a 3x3x3 kernel: each of the 27 outputs
        // sees the voxel through the tap opposite its offset, w[26 - i] · 2.
        let s = shape(&(1, 1, [3, 3, 3], 1, [3; 3], [1; 3], [1; 3], [1; 3], 1));
        let mut x = vec![0.0; 27];
        x[13] = 2.0;
        let w: Vec<f32> = (0..27).map(|v| v as f32).collect();
        let want: Vec<f32> = (0..27).map(|i| (26 - i) as f32 * 2.0).collect();
        assert_eq!(run(&s, &w, &Epilogue::default(), &x, 2), want);
    }

    #[test]
    fn check_refuses_what_the_kernel_cannot_run() {
        let s = shape(&CASES[1]);
        let (x, o) = (s.n * s.cin * s.in_plane(), s.n * s.cout * s.out_plane());
        assert_eq!(check(&s, s.weight_len(), x, o, [None, Some(s.cout)]), Ok(()));
        let e = check(&s, s.weight_len() - 1, x, o, [None, None]).expect_err("short weight");
        assert!(e.contains("weight has 404 values, [5, 3, 3, 3, 3] needs 405"), "{e}");
        let e = check(&Conv3dShape { stride: [2, 0, 2], ..s }, s.weight_len(), x, o, [None, None]).expect_err("0");
        assert!(e.contains("none may be 0"), "{e}");
        let deep = Conv3dShape { out: [s.out[0] + 1, s.out[1], s.out[2]], ..s };
        let e = check(&deep, s.weight_len(), x, o + s.n * s.cout * s.out[1] * s.out[2], [None, None]).expect_err("d");
        assert!(e.contains("output depth 5 is not PyTorch's for input 7, kernel 3, stride 2, padding 1"), "{e}");
        let e = check(&Conv3dShape { groups: 2, ..s }, s.weight_len(), x, o, [None, None]).expect_err("g");
        assert!(e.contains("groups=2"), "{e}");
        let e = check(&s, s.weight_len(), x - 1, o, [None, None]).expect_err("input");
        assert!(e.contains("input has"), "{e}");
        let e = check(&s, s.weight_len(), x, o, [Some(1), None]).expect_err("epilogue");
        assert!(e.contains("epilogue"), "{e}");
        let huge = Conv3dShape { input: [1 << 20, 1 << 20, 1 << 20], ..s };
        let e = check(&huge, s.weight_len(), x, o, [None, None]).expect_err("huge");
        assert!(e.contains("too large"), "{e}");
    }

    #[test]
    fn scratch_is_one_tile_per_thread_that_unfolds() {
        let s = shape(&CASES[1]);
        let one = scratch_len(&s, 1).expect("fits");
        assert_eq!(one, s.k() * tile(&s));
        // Two images: a tile for each of 2 threads; 3 threads share each unit's tile.
        assert_eq!(scratch_len(&s, 2), Some(2 * one));
        assert_eq!(scratch_len(&s, 3), Some(one));
        assert_eq!(scratch_len(&shape(&CASES[5]), 2), Some(0));
        assert_eq!(scratch_len(&shape(&CASES[7]), 2), Some(0));
    }
}
