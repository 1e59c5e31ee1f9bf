//! 2-D max and average pooling over `[nc, h, w]` planes, adaptive pooling, and global
//! average pooling, with PyTorch's window, bin and divisor rules. Max pooling 3x3 at
//! stride 2 with rows of at least 16 outputs reads its rows in place with AVX-512
//! (`in_place.rs`); every other pooling goes through a row buffer ([`pool_rows`]).

use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
mod in_place;

use readi_plan::ops::{Pool2d, adaptive_bin, window_out};

use super::layout::split_phases;
use super::reduce::{add_rows, max_nan, max_rows, max_simd, sum_simd};

/// Below this much work (window reads) a kernel runs on the calling thread.
const PAR_MIN: usize = 1 << 15;
/// Window reads per parallel task, roughly.
const TASK_WORK: usize = 1 << 14;

pub use readi_plan::ops::PoolKind;

/// Sizes of a 2-D pooling over `nc` planes of `h × w`, producing `oh × ow` per plane.
///
/// `oh` and `ow` are PyTorch's output sizes for these parameters (so with `ceil_mode` the
/// last window may run past the input, but always starts inside it or its left padding);
/// `ceil_mode` itself only matters to that computation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pool2dShape {
    pub nc: usize,
    pub h: usize,
    pub w: usize,
    pub kh: usize,
    pub kw: usize,
    pub stride_h: usize,
    pub stride_w: usize,
    pub pad_h: usize,
    pub pad_w: usize,
    pub oh: usize,
    pub ow: usize,
    pub ceil_mode: bool,
    pub count_include_pad: bool,
}

/// One window along one axis: the input range it covers, clamped to the input, and its
/// length over the padded input (PyTorch's `pool_size` factor).
#[derive(Clone, Copy)]
struct Window {
    start: usize,
    end: usize,
    padded_len: usize,
}

/// The window of output index `o`: it starts at `o * stride - pad`, ends `k` later but not
/// past the right padding, and is then clamped to `[0, len)`. As PyTorch's avg_pool2d.
fn window(o: usize, len: usize, k: usize, stride: usize, pad: usize) -> Window {
    let start = (o * stride) as isize - pad as isize;
    let end = (start + k as isize).min((len + pad) as isize);
    let padded_len = (end - start) as usize;
    let clamp = |i: isize| i.clamp(0, len as isize) as usize;
    Window { start: clamp(start), end: clamp(end), padded_len }
}

/// PyTorch's pooled output length (dilation 1): the shared window rule,
/// [`window_out`], on kernel sizes; 0 when the window does not fit.
fn pooled_len(len: usize, k: usize, stride: usize, pad: usize, ceil_mode: bool) -> usize {
    let i = |v: usize| i64::try_from(v).unwrap_or(i64::MAX);
    window_out(i(len), i(k), i(stride), i(pad), 1, ceil_mode).map_or(0, |o| o as usize)
}

impl Pool2dShape {
    /// The kernel's view of a pooling layer over `nc` planes of `h x w`: the one place a
    /// [`Pool2dShape`] is built from the operator's attributes.
    pub fn of(pool: &Pool2d, nc: usize, h: usize, w: usize) -> Pool2dShape {
        let win = &pool.window;
        let u = |v: i64| usize::try_from(v).unwrap_or(0);
        let (kh, kw, stride_h, stride_w, pad_h, pad_w) = (
            u(win.kernel[0]),
            u(win.kernel[1]),
            u(win.stride[0]),
            u(win.stride[1]),
            u(win.padding[0]),
            u(win.padding[1]),
        );
        Pool2dShape {
            nc,
            h,
            w,
            kh,
            kw,
            stride_h,
            stride_w,
            pad_h,
            pad_w,
            oh: pooled_len(h, kh, stride_h, pad_h, pool.ceil_mode),
            ow: pooled_len(w, kw, stride_w, pad_w, pool.ceil_mode),
            ceil_mode: pool.ceil_mode,
            count_include_pad: pool.count_include_pad,
        }
    }
}

/// Input columns one tile of a pooling row may span (a stack buffer).
const BUF: usize = 1024;

/// The start value of a window reduction.
#[inline(always)]
fn identity(kind: PoolKind) -> f32 {
    match kind {
        PoolKind::Max => f32::NEG_INFINITY,
        PoolKind::Avg => 0.0,
    }
}

/// The output value of a reduced window: the max as is, the sum over PyTorch's divisor
/// (0 for a window entirely outside the input).
#[inline(always)]
fn finish(kind: PoolKind, acc: f32, wy: &Window, wx: &Window, count_include_pad: bool) -> f32 {
    match kind {
        PoolKind::Max => acc,
        PoolKind::Avg => {
            let area = (wy.end - wy.start) * (wx.end - wx.start);
            if area == 0 {
                0.0
            } else {
                let divisor = if count_include_pad { wy.padded_len * wx.padded_len } else { area };
                acc / divisor as f32
            }
        }
    }
}

/// 2-D pooling of `x` (`[nc, h, w]`) into `out` (`[nc, oh, ow]`), exactly as PyTorch's
/// `max_pool2d` / `avg_pool2d` (dilation 1, no `divisor_override`).
///
/// Max: the maximum over the window clamped to the input (padding is `-inf`).
/// Avg: the window sum divided by, if `count_include_pad`, the window's area over the
/// padded input (`min(start + k, len + pad) - start` per axis, so a `ceil_mode` window
/// running past the right padding counts only up to it), else its area clamped to the
/// input. Preconditions: `k >= 1`, `stride >= 1`, `pad <= k / 2` (PyTorch's own checks),
/// and `oh`, `ow` as PyTorch computes them.
pub fn pool2d(kind: PoolKind, s: &Pool2dShape, x: &[f32], out: &mut [f32]) {
    assert_eq!(x.len(), s.nc * s.h * s.w, "pool2d: x is not [nc, h, w]");
    assert_eq!(out.len(), s.nc * s.oh * s.ow, "pool2d: out is not [nc, oh, ow]");
    assert!(s.kh >= 1 && s.kw >= 1 && s.stride_h >= 1 && s.stride_w >= 1, "pool2d: zero kernel or stride");
    assert!(s.pad_h <= s.kh / 2 && s.pad_w <= s.kw / 2, "pool2d: padding exceeds half the kernel");
    debug_assert_eq!(s.oh, pooled_len(s.h, s.kh, s.stride_h, s.pad_h, s.ceil_mode), "pool2d: oh for {s:?}");
    debug_assert_eq!(s.ow, pooled_len(s.w, s.kw, s.stride_w, s.pad_w, s.ceil_mode), "pool2d: ow for {s:?}");
    if out.is_empty() {
        return;
    }
    let s = *s;
    let rows_per_task = (TASK_WORK / (s.ow * s.kh * s.kw)).max(1);
    #[cfg(target_arch = "x86_64")]
    let in_place = in_place::applies(kind, &s);
    #[cfg(not(target_arch = "x86_64"))]
    let in_place = false;
    let run = |first: usize, out: &mut [f32]| {
        #[cfg(target_arch = "x86_64")]
        if in_place {
            return in_place::rows(&s, x, first, out);
        }
        pulp::Arch::new().dispatch(PoolRows { kind, s: &s, x, first, out })
    };
    if out.len() * s.kh * s.kw >= PAR_MIN && s.nc * s.oh > rows_per_task {
        out.par_chunks_mut(rows_per_task * s.ow).enumerate().for_each(|(t, o)| run(t * rows_per_task, o));
    } else {
        run(0, out);
    }
}

/// Output rows `first..` (counted over all planes) of a pooling, into `out`; compiled for
/// the widest SIMD the CPU has.
struct PoolRows<'a> {
    kind: PoolKind,
    s: &'a Pool2dShape,
    x: &'a [f32],
    first: usize,
    out: &'a mut [f32],
}

impl pulp::WithSimd for PoolRows<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let PoolRows { kind, s, x, first, out } = self;
        match kind {
            PoolKind::Avg => pool_rows::<Sum>(s, x, first, out),
            PoolKind::Max => pool_rows::<Max>(s, x, first, out),
        }
    }
}

/// A window reduction, as a type so that each gets its own vectorised loops.
trait Reduction {
    const KIND: PoolKind;
    /// Adds `v` to the reduction `acc`.
    fn combine(acc: f32, v: f32) -> f32;
}

/// The maximum, with NaN winning (as PyTorch's `val > max || isnan(val)`).
struct Max;
/// The sum, for `Avg`.
struct Sum;

impl Reduction for Max {
    const KIND: PoolKind = PoolKind::Max;
    #[inline(always)]
    fn combine(acc: f32, v: f32) -> f32 {
        if v > acc || v.is_nan() { v } else { acc }
    }
}

impl Reduction for Sum {
    const KIND: PoolKind = PoolKind::Avg;
    #[inline(always)]
    fn combine(acc: f32, v: f32) -> f32 {
        acc + v
    }
}

/// [`PoolRows`] with the reduction `R`.
///
/// Per output row, per tile of output columns: the window rows are reduced into `buf`
/// (vertical), which spans the tile's windows' columns including padding (padding holds
/// the identity, `-inf` or 0, which changes no result); then each output combines its `kw`
/// columns of `buf` (horizontal). Both are vectorised loops over columns: the horizontal
/// pass reads window column `dx` of all the tile's outputs as one contiguous run, of
/// `buf` itself for stride 1, and of its even or odd columns, split off first, for
/// stride 2. (Other strides gather.)
#[inline(always)]
fn pool_rows<R: Reduction>(s: &Pool2dShape, x: &[f32], first: usize, out: &mut [f32]) {
    let kind = R::KIND;
    let id = identity(kind);
    let (sw, kw) = (s.stride_w, s.kw);
    // Output columns per tile: their windows' padded columns must fit in the stack buffer.
    let tile = if kw <= BUF { ((BUF - kw) / sw + 1).min(s.ow) } else { 1 };
    let mut buf = [0f32; BUF];
    let mut phases = [0f32; BUF];
    // Average pooling: each output column's share of the divisor (see `finish`), for the
    // tile starting at `div_for`.
    let mut div_x = [0f32; BUF];
    let mut div_for = usize::MAX;
    for (i, orow) in out.chunks_mut(s.ow).enumerate() {
        let (plane, oy) = ((first + i) / s.oh, (first + i) % s.oh);
        let xp = &x[plane * s.h * s.w..(plane + 1) * s.h * s.w];
        let wy = window(oy, s.h, s.kh, s.stride_h, s.pad_h);
        for ox0 in (0..s.ow).step_by(tile) {
            let ox1 = (ox0 + tile).min(s.ow);
            if kw > BUF {
                // A window wider than the buffer (tile is 1): reduce it in place.
                let wx = window(ox0, s.w, kw, sw, s.pad_w);
                let mut acc = id;
                for y in wy.start..wy.end {
                    acc = xp[y * s.w + wx.start..y * s.w + wx.end].iter().fold(acc, |a, &v| R::combine(a, v));
                }
                orow[ox0] = finish(kind, acc, &wy, &wx, s.count_include_pad);
                continue;
            }
            // Padded input columns p0..p1 of the tile's windows (p0 may be negative), and
            // the part inside the input, c0..c1.
            let p0 = (ox0 * sw) as isize - s.pad_w as isize;
            let p1 = ((ox1 - 1) * sw + kw) as isize - s.pad_w as isize;
            let clamp = |p: isize| p.clamp(0, s.w as isize) as usize;
            let (c0, c1) = (clamp(p0), clamp(p1).max(clamp(p0)));
            let b = &mut buf[..(p1 - p0) as usize];
            let (left, rest) = b.split_at_mut((c0 as isize - p0) as usize);
            let (inside, right) = rest.split_at_mut(c1 - c0);
            left.fill(id);
            right.fill(id);
            combine_into::<R>(inside, wy.end - wy.start, |i| &xp[(wy.start + i) * s.w + c0..]);
            let o = &mut orow[ox0..ox1];
            match sw {
                1 => combine_into::<R>(o, kw, |dx| &b[dx..]),
                2 => {
                    // The even columns in the first half of `phases`, the odd ones after.
                    let half = BUF / 2;
                    split_phases(b, &mut phases, 0, half);
                    combine_into::<R>(o, kw, |dx| &phases[dx % 2 * half + dx / 2..]);
                }
                _ => {
                    o.fill(id);
                    for dx in 0..kw {
                        for (a, &v) in o.iter_mut().zip(b[dx..].iter().step_by(sw)) {
                            *a = R::combine(*a, v);
                        }
                    }
                }
            }
            let n = o.len();
            if kind == PoolKind::Avg {
                if div_for != ox0 {
                    for (ox, d) in (ox0..ox1).zip(div_x.iter_mut()) {
                        let wx = window(ox, s.w, kw, sw, s.pad_w);
                        let len = if s.count_include_pad { wx.padded_len } else { wx.end - wx.start };
                        // 0 marks a window entirely outside the input.
                        *d = if wx.end > wx.start { len as f32 } else { 0.0 };
                    }
                    div_for = ox0;
                }
                let div_y = if s.count_include_pad { wy.padded_len } else { wy.end - wy.start } as f32;
                let empty_y = wy.end == wy.start;
                for (a, &d) in o.iter_mut().zip(&div_x[..n]) {
                    *a = if d == 0.0 || empty_y { 0.0 } else { *a / (div_y * d) };
                }
            }
        }
    }
}

/// `dst[j] = R-reduction of src(0)[j], .., src(k - 1)[j]` (the identity for `k = 0`).
///
/// The first three sources are combined in one loop that only writes `dst`; further ones
/// are added in read-modify-write loops. (With AVX-512, LLVM compiles a read-modify-write
/// `*a = if v > *a { v } else { *a }` into a masked store, and the next loop's read of
/// `*a` then stalls on store forwarding: it made max pooling 3x slower.)
#[inline(always)]
fn combine_into<'a, R: Reduction>(dst: &mut [f32], k: usize, src: impl Fn(usize) -> &'a [f32]) {
    let n = dst.len();
    let c = R::combine;
    match k {
        0 => dst.fill(identity(R::KIND)),
        1 => dst.copy_from_slice(&src(0)[..n]),
        2 => {
            for ((d, &a), &b) in dst.iter_mut().zip(&src(0)[..n]).zip(&src(1)[..n]) {
                *d = c(a, b);
            }
        }
        _ => {
            let (s0, s1, s2) = (&src(0)[..n], &src(1)[..n], &src(2)[..n]);
            for (((d, &a), &b), &e) in dst.iter_mut().zip(s0).zip(s1).zip(s2) {
                *d = c(c(a, b), e);
            }
            for i in 3..k {
                for (d, &v) in dst.iter_mut().zip(&src(i)[..n]) {
                    *d = c(*d, v);
                }
            }
        }
    }
}

/// Adaptive pooling of `x` (`[nc, h, w]`) into `out` (`[nc, oh, ow]`), as PyTorch's
/// `adaptive_max_pool2d` / `adaptive_avg_pool2d`: output `(i, j)` reduces the input rows
/// and columns of [`adaptive_bin`]`(i, h, oh)` and `(j, w, ow)`, the maximum with NaN
/// propagating or the mean. A bin's input rows are folded column-wise first (rows up to
/// [`BUF`] wide; wider ones per bin, a bin spanning whole rows as one contiguous run).
#[allow(clippy::too_many_arguments)]
pub fn adaptive_pool2d(
    kind: PoolKind,
    x: &[f32],
    nc: usize,
    h: usize,
    w: usize,
    oh: usize,
    ow: usize,
    out: &mut [f32],
) {
    assert_eq!(x.len(), nc * h * w, "adaptive_pool2d: x is not [nc, h, w]");
    assert_eq!(out.len(), nc * oh * ow, "adaptive_pool2d: out is not [nc, oh, ow]");
    assert!(h >= 1 && w >= 1 && oh >= 1 && ow >= 1, "adaptive_pool2d: an empty axis");
    if out.is_empty() {
        return;
    }
    // Reads per output row: every bin's rows over the whole width, bins overlapping by one.
    let row_work = (h.div_ceil(oh) + 1) * (w + ow);
    let rows_per_task = (TASK_WORK / row_work).max(1);
    let run = |first: usize, out: &mut [f32]| {
        pulp::Arch::new().dispatch(AdaptiveRows { kind, x, h, w, oh, ow, first, out });
    };
    if nc * oh * row_work >= PAR_MIN && nc * oh > rows_per_task {
        out.par_chunks_mut(rows_per_task * ow).enumerate().for_each(|(t, o)| run(t * rows_per_task, o));
    } else {
        run(0, out);
    }
}

/// Output rows `first..` (over all planes) of an adaptive pooling; compiled for the
/// widest SIMD the CPU has.
struct AdaptiveRows<'a> {
    kind: PoolKind,
    x: &'a [f32],
    h: usize,
    w: usize,
    oh: usize,
    ow: usize,
    first: usize,
    out: &'a mut [f32],
}

impl pulp::WithSimd for AdaptiveRows<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let AdaptiveRows { kind, x, h, w, oh, ow, first, out } = self;
        if w <= BUF {
            // Each output row: its bin's input rows folded column-wise into `acc` (whole
            // rows in SIMD vectors), then each bin's columns of `acc`.
            let mut acc = [0f32; BUF];
            let acc = &mut acc[..w];
            for (k, row) in out.chunks_mut(ow).enumerate() {
                let (plane, i) = ((first + k) / oh, (first + k) % oh);
                let (hs, he) = adaptive_bin(i, h, oh);
                let rows = &x[(plane * h + hs) * w..(plane * h + he) * w];
                let init = if kind == PoolKind::Max { f32::NEG_INFINITY } else { 0.0 };
                acc.fill(init);
                for r in rows.chunks(w) {
                    match kind {
                        PoolKind::Avg => add_rows(simd, acc, r),
                        PoolKind::Max => max_rows(simd, acc, r),
                    }
                }
                for (j, o) in row.iter_mut().enumerate() {
                    let (ws, we) = adaptive_bin(j, w, ow);
                    let cols = &acc[ws..we];
                    *o = match kind {
                        PoolKind::Avg => cols.iter().sum::<f32>() / ((he - hs) * (we - ws)) as f32,
                        PoolKind::Max => cols.iter().fold(init, |m, &v| max_nan(m, v)),
                    };
                }
            }
            return;
        }
        for (k, row) in out.chunks_mut(ow).enumerate() {
            let (plane, i) = ((first + k) / oh, (first + k) % oh);
            let (hs, he) = adaptive_bin(i, h, oh);
            let base = plane * h * w;
            for (j, o) in row.iter_mut().enumerate() {
                let (ws, we) = adaptive_bin(j, w, ow);
                // Rows `hs..he` of columns `ws..we`: one run when the bin spans the width.
                let runs = if ws == 0 && we == w { 1 } else { he - hs };
                let len = if runs == 1 { (he - hs) * w - ws - (w - we) } else { we - ws };
                let at = |r: usize| {
                    let b = base + (hs + r) * w + ws;
                    &x[b..b + len]
                };
                *o = match kind {
                    PoolKind::Avg => {
                        let sum: f32 = (0..runs).map(|r| sum_simd(simd, at(r))).sum();
                        sum / ((he - hs) * (we - ws)) as f32
                    }
                    PoolKind::Max => (0..runs).fold(f32::NEG_INFINITY, |m, r| max_nan(m, max_simd(simd, at(r)))),
                };
            }
        }
    }
}

/// The preconditions of [`adaptive_pool2d`]: a 4-D input `[n, c, h, w]` with `h, w >= 1`,
/// an output `[n, c, oh, ow]` with `oh, ow >= 1`.
pub fn check_adaptive(x: &[usize], out: &[usize]) -> Result<(), String> {
    match (x, out) {
        (&[n, c, h, w], &[n2, c2, oh, ow]) if n == n2 && c == c2 && h * w * oh * ow >= 1 => Ok(()),
        _ => Err(format!("adaptive pooling of {x:?} cannot give {out:?}")),
    }
}

/// Mean of each of the `nc` rows of `x` (`[nc, hw]`), into `out` (`[nc]`).
pub fn global_avgpool(x: &[f32], nc: usize, hw: usize, out: &mut [f32]) {
    debug_assert_eq!(
        check_global_avgpool(&[1, nc, hw, 1], &[1, out.len(), 1, 1]),
        Ok(()),
        "global_avgpool preconditions"
    );
    assert_eq!(x.len(), nc * hw, "global_avgpool: x is not [nc, hw]");
    assert_eq!(out.len(), nc, "global_avgpool: out is not [nc]");
    if hw == 0 {
        out.fill(f32::NAN);
        return;
    }
    if x.len() >= PAR_MIN && nc > 1 {
        let rows = (TASK_WORK / hw).max(1);
        out.par_chunks_mut(rows).zip(x.par_chunks(rows * hw)).for_each(|(o, x)| row_means(x, o));
    } else {
        row_means(x, out);
    }
}

/// `out[i] = mean(x[i·hw..(i + 1)·hw])`, `hw = x.len() / out.len()`, compiled for the
/// widest SIMD the CPU has.
fn row_means(x: &[f32], out: &mut [f32]) {
    struct Op<'a>(&'a [f32], &'a mut [f32]);
    impl pulp::WithSimd for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, simd: S) {
            let Op(x, out) = self;
            let hw = x.len() / out.len();
            let inv = 1.0 / hw as f32;
            for (o, r) in out.iter_mut().zip(x.chunks(hw)) {
                *o = sum_simd(simd, r) * inv;
            }
        }
    }
    pulp::Arch::new().dispatch(Op(x, out));
}

/// The preconditions of [`pool2d`] on a 4-D value `x` (`[n, c, h, w]`) giving `out`:
/// kernel and stride at least 1, padding at most half the kernel, the window fits and the
/// output is `[n, c, oh, ow]` as the pooling formula gives.
pub fn check(pool: &Pool2d, x: &[usize], out: &[usize]) -> Result<(), String> {
    let &[n, c, h, w] = x else { return Err(format!("pool2d of a value of shape {x:?}, not 4-D")) };
    let nc = n.checked_mul(c).ok_or("pool2d: too many planes")?;
    let s = Pool2dShape::of(pool, nc, h, w);
    if s.kh == 0 || s.kw == 0 || s.stride_h == 0 || s.stride_w == 0 {
        return Err(format!("pool2d kernel {}x{} or stride {}x{} is 0", s.kh, s.kw, s.stride_h, s.stride_w));
    }
    if s.pad_h > s.kh / 2 || s.pad_w > s.kw / 2 {
        return Err(format!("pool2d padding {}x{} exceeds half the kernel {}x{}", s.pad_h, s.pad_w, s.kh, s.kw));
    }
    let want = [
        n,
        c,
        pooled_len(h, s.kh, s.stride_h, s.pad_h, s.ceil_mode),
        pooled_len(w, s.kw, s.stride_w, s.pad_w, s.ceil_mode),
    ];
    if out != want || s.oh != want[2] || s.ow != want[3] {
        return Err(format!("pool2d kernel {}x{} does not fit input {x:?} with output {out:?}", s.kh, s.kw));
    }
    Ok(())
}

/// The preconditions of [`global_avgpool`]: a 4-D input `[n, c, h, w]`, output `[n, c, 1, 1]`.
pub fn check_global_avgpool(x: &[usize], out: &[usize]) -> Result<(), String> {
    match *x {
        [n, c, _, _] if out == [n, c, 1, 1] => Ok(()),
        _ => Err(format!("global_avgpool of {x:?} cannot give {out:?}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, data};

    #[allow(clippy::too_many_arguments)]
    fn shape(
        nc: usize,
        h: usize,
        w: usize,
        k: (usize, usize),
        stride: (usize, usize),
        pad: (usize, usize),
        ceil_mode: bool,
        cip: bool,
    ) -> Pool2dShape {
        Pool2dShape {
            nc,
            h,
            w,
            kh: k.0,
            kw: k.1,
            stride_h: stride.0,
            stride_w: stride.1,
            pad_h: pad.0,
            pad_w: pad.1,
            oh: pooled_len(h, k.0, stride.0, pad.0, ceil_mode),
            ow: pooled_len(w, k.1, stride.1, pad.1, ceil_mode),
            ceil_mode,
            count_include_pad: cip,
        }
    }

    /// Visits every kernel tap of every window and classifies it: inside the input, in the
    /// padding (counts towards the divisor only with count_include_pad), or past the right
    /// padding (never counts).
    fn naive(kind: PoolKind, s: &Pool2dShape, x: &[f32]) -> Vec<f32> {
        let mut out = Vec::new();
        for p in 0..s.nc {
            for oy in 0..s.oh {
                for ox in 0..s.ow {
                    let (mut max, mut total, mut inside, mut padded) = (f32::NEG_INFINITY, 0.0f32, 0, 0);
                    for dy in 0..s.kh {
                        for dx in 0..s.kw {
                            let iy = (oy * s.stride_h + dy) as isize - s.pad_h as isize;
                            let ix = (ox * s.stride_w + dx) as isize - s.pad_w as isize;
                            if iy >= (s.h + s.pad_h) as isize || ix >= (s.w + s.pad_w) as isize {
                                continue;
                            }
                            padded += 1;
                            if iy < 0 || ix < 0 || iy >= s.h as isize || ix >= s.w as isize {
                                continue;
                            }
                            let v = x[(p * s.h + iy as usize) * s.w + ix as usize];
                            max = if max.is_nan() || v.is_nan() { f32::NAN } else { max.max(v) };
                            total += v;
                            inside += 1;
                        }
                    }
                    out.push(match kind {
                        PoolKind::Max => max,
                        PoolKind::Avg => total / if s.count_include_pad { padded } else { inside } as f32,
                    });
                }
            }
        }
        out
    }

    fn check(s: Pool2dShape) {
        let x = data(s.nc * s.h * s.w, (s.h * 31 + s.w) as u64);
        for kind in [PoolKind::Max, PoolKind::Avg] {
            let mut got = vec![f32::NAN; s.nc * s.oh * s.ow];
            pool2d(kind, &s, &x, &mut got);
            assert_close(&got, &naive(kind, &s, &x), 1e-6);
        }
    }

    #[test]
    fn pool_plain_strided_and_padded() {
        for cip in [false, true] {
            check(shape(2, 4, 4, (2, 2), (2, 2), (0, 0), false, cip));
            check(shape(3, 7, 5, (3, 3), (1, 1), (1, 1), false, cip));
            check(shape(1, 9, 6, (3, 2), (2, 1), (1, 0), false, cip));
            check(shape(2, 1, 8, (1, 3), (1, 2), (0, 1), false, cip));
            check(shape(1, 5, 5, (5, 5), (1, 1), (2, 2), false, cip));
            check(shape(4, 1, 1, (1, 1), (1, 1), (0, 0), false, cip));
        }
    }

    #[test]
    fn pool_ceil_mode_windows_past_the_input() {
        for cip in [false, true] {
            check(shape(2, 5, 6, (3, 3), (2, 2), (1, 1), true, cip));
            check(shape(1, 5, 6, (2, 3), (2, 2), (0, 0), true, cip));
            check(shape(3, 8, 7, (3, 3), (3, 3), (1, 1), true, cip));
            check(shape(1, 6, 9, (4, 2), (3, 2), (2, 1), true, cip));
            check(shape(1, 2, 2, (3, 3), (2, 2), (1, 1), true, cip));
        }
    }

    #[test]
    fn pool_rows_wider_than_one_tile_and_windows_wider_than_the_buffer() {
        for cip in [false, true] {
            check(shape(1, 4, 2500, (3, 3), (1, 1), (1, 1), false, cip));
            check(shape(2, 5, 2501, (3, 3), (2, 2), (1, 1), true, cip));
            check(shape(2, 3, 1500, (2, 1100), (1, 300), (1, 0), true, cip));
        }
    }

    #[test]
    fn pool_large_runs_in_parallel_and_matches() {
        check(shape(64, 56, 57, (3, 3), (2, 2), (1, 1), true, false));
        check(shape(3, 112, 112, (3, 3), (2, 2), (1, 1), false, true));
    }

    #[test]
    fn pool_output_length_matches_pytorch_shapes() {
        // Shapes of F.avg_pool2d(torch.zeros(1, 1, h, w), k, s, p, ceil_mode=...) for each case.
        assert_eq!(pooled_len(5, 3, 2, 1, true), 3);
        assert_eq!(pooled_len(6, 3, 2, 1, true), 4);
        assert_eq!(pooled_len(6, 3, 2, 1, false), 3);
        assert_eq!(pooled_len(6, 2, 2, 1, true), 4);
        // (n - 1) * stride >= len + pad: the would-be last window starts in the right padding.
        assert_eq!(pooled_len(5, 2, 2, 1, true), 3);
        assert_eq!(pooled_len(112, 3, 2, 1, false), 56);
    }

    /// x = torch.arange(30.).reshape(1, 1, 5, 6) for the PyTorch literals below.
    fn arange_5x6() -> Vec<f32> {
        (0..30).map(|v| v as f32).collect()
    }

    fn run(kind: PoolKind, s: &Pool2dShape, x: &[f32]) -> Vec<f32> {
        let mut out = vec![f32::NAN; s.nc * s.oh * s.ow];
        pool2d(kind, s, x, &mut out);
        out
    }

    #[test]
    fn avg_pool_matches_pytorch_divisors() {
        let x = arange_5x6();
        // F.avg_pool2d(x, 3, 2, 1, ceil_mode=True, count_include_pad=True): the last column's
        // windows reach past w + pad, so they divide by 6, not 9 (e.g. (5 + 11) / 6).
        let s = shape(1, 5, 6, (3, 3), (2, 2), (1, 1), true, true);
        #[rustfmt::skip]
        let want = [
            1.5555556, 3.3333333, 4.6666665, 2.6666667,
            8.333333, 14.0, 16.0, 8.5,
            9.555555, 15.333333, 16.666666, 8.666667,
        ];
        assert_close(&run(PoolKind::Avg, &s, &x), &want, 1e-6);
        // Same with count_include_pad=False: divide by the taps inside the input.
        let s = Pool2dShape { count_include_pad: false, ..s };
        let want = [3.5, 5.0, 7.0, 8.0, 12.5, 14.0, 16.0, 17.0, 21.5, 23.0, 25.0, 26.0];
        assert_close(&run(PoolKind::Avg, &s, &x), &want, 1e-6);
        // F.avg_pool2d(x, (2, 3), (2, 2), 0, ceil_mode=True, count_include_pad=True): without
        // padding a window past the input divides by its clamped area either way.
        let s = shape(1, 5, 6, (2, 3), (2, 2), (0, 0), true, true);
        let want = [4.0, 6.0, 7.5, 16.0, 18.0, 19.5, 25.0, 27.0, 28.5];
        assert_close(&run(PoolKind::Avg, &s, &x), &want, 1e-6);
        // F.avg_pool2d(x, (3, 2), (3, 1), (1, 1), count_include_pad=True)
        let s = shape(1, 5, 6, (3, 2), (3, 1), (1, 1), false, true);
        #[rustfmt::skip]
        let want = [
            1.0, 2.3333333, 3.0, 3.6666667, 4.3333335, 5.0, 2.6666667,
            9.0, 18.5, 19.5, 20.5, 21.5, 22.5, 11.5,
        ];
        assert_close(&run(PoolKind::Avg, &s, &x), &want, 1e-6);
    }

    #[test]
    fn max_pool_matches_pytorch() {
        let x = arange_5x6();
        let neg: Vec<f32> = x.iter().map(|v| -v).collect();
        // F.max_pool2d(-x, 3, 2, 1, ceil_mode=True): padding never wins, even over negatives.
        let s = shape(1, 5, 6, (3, 3), (2, 2), (1, 1), true, false);
        let want = [-0.0, -1.0, -3.0, -5.0, -6.0, -7.0, -9.0, -11.0, -18.0, -19.0, -21.0, -23.0];
        assert_close(&run(PoolKind::Max, &s, &neg), &want, 0.0);
        // F.max_pool2d(x, (2, 3), (2, 2), 0, ceil_mode=True)
        let s = shape(1, 5, 6, (2, 3), (2, 2), (0, 0), true, false);
        let want = [8.0, 10.0, 11.0, 20.0, 22.0, 23.0, 26.0, 28.0, 29.0];
        assert_close(&run(PoolKind::Max, &s, &x), &want, 0.0);
    }

    /// Max pooling 3x3 at stride 2 with rows of 16 outputs and more (the AVX-512 path,
    /// `in_place.rs`, where the CPU has it): every padding of at most one on each axis, with
    /// and without `ceil_mode`, rows of exactly a vector and of a vector and a bit, planes
    /// split between tasks. The inputs are all negative, so a padding read as 0 would win;
    /// NaN and `-inf` at corners, edges and inside must come out as PyTorch's (NaN
    /// propagates). Compared bit for bit with the naive loops.
    #[test]
    fn max_pool_3x3_stride_2_rows_in_place() {
        let mut cases = 0;
        for (nc, h, w) in [(2, 33, 33), (1, 32, 34), (2, 7, 47), (3, 112, 112), (1, 9, 64)] {
            for pad in [(0, 0), (1, 1), (0, 1), (1, 0)] {
                for ceil in [false, true] {
                    let s = shape(nc, h, w, (3, 3), (2, 2), pad, ceil, false);
                    if s.ow < 16 {
                        continue;
                    }
                    #[cfg(target_arch = "x86_64")]
                    assert_eq!(in_place::applies(PoolKind::Max, &s), pulp::x86::V4::try_new().is_some(), "{s:?}");
                    let mut x: Vec<f32> = data(nc * h * w, (h * 7 + w) as u64).iter().map(|v| v - 3.0).collect();
                    let last = x.len() - 1;
                    for (i, v) in [
                        (0, f32::NAN),
                        (w - 1, f32::NAN),
                        (h * w / 2 + 5, f32::NAN),
                        (w + 2, f32::NEG_INFINITY),
                        (last, f32::NAN),
                        (last - w, f32::NEG_INFINITY),
                    ] {
                        x[i] = v;
                    }
                    let (got, want) = (run(PoolKind::Max, &s, &x), naive(PoolKind::Max, &s, &x));
                    for (i, (g, e)) in got.iter().zip(&want).enumerate() {
                        assert!(
                            g.to_bits() == e.to_bits() || g.is_nan() && e.is_nan(),
                            "{s:?} output {i}: {g} against {e}"
                        );
                    }
                    assert!(want.iter().any(|v| v.is_nan()), "{s:?}: no NaN reached an output");
                    cases += 1;
                }
            }
        }
        assert_eq!(cases, 40);
    }

    #[test]
    fn max_pool_propagates_nan() {
        // torch.nn.functional.max_pool2d(torch.tensor([[[1., nan], [3., 2.]]]), 2) is nan.
        let s = shape(1, 2, 2, (2, 2), (2, 2), (0, 0), false, false);
        assert!(run(PoolKind::Max, &s, &[1.0, f32::NAN, 3.0, 2.0])[0].is_nan());
    }

    #[test]
    fn global_avgpool_means_rows() {
        for (nc, hw) in [(1, 1), (3, 7), (5, 49), (300, 150)] {
            let x = data(nc * hw, 3);
            let mut got = vec![f32::NAN; nc];
            global_avgpool(&x, nc, hw, &mut got);
            let want: Vec<f32> =
                x.chunks(hw).map(|r| (r.iter().map(|&v| v as f64).sum::<f64>() / hw as f64) as f32).collect();
            assert_close(&got, &want, 1e-6);
        }
    }

    /// Plain reference: each bin's values by PyTorch's formula, in f64.
    fn naive_adaptive(kind: PoolKind, x: &[f32], nc: usize, h: usize, w: usize, oh: usize, ow: usize) -> Vec<f32> {
        let mut out = Vec::new();
        for p in 0..nc {
            for i in 0..oh {
                let bin = |i: usize, len: usize, out: usize| {
                    let (a, b) = ((i * len) as f64 / out as f64, ((i + 1) * len) as f64 / out as f64);
                    (a.floor() as usize, b.ceil() as usize)
                };
                let (hs, he) = bin(i, h, oh);
                for j in 0..ow {
                    let (ws, we) = bin(j, w, ow);
                    let vals: Vec<f64> =
                        (hs..he).flat_map(|y| (ws..we).map(move |xx| x[(p * h + y) * w + xx] as f64)).collect();
                    out.push(match kind {
                        PoolKind::Avg => vals.iter().sum::<f64>() / vals.len() as f64,
                        PoolKind::Max => {
                            vals.iter().fold(f64::NEG_INFINITY, |a, &v| if v > a || v.is_nan() { v } else { a })
                        }
                    } as f32);
                }
            }
        }
        out
    }

    #[test]
    fn adaptive_pooling_matches_pytorchs_bins() {
        // Divisible, non-divisible, output larger than input, 1x1, whole-width bins,
        // wide rows and many planes (the parallel path).
        let cases = [
            (2, 7, 5, 3, 2),
            (3, 14, 14, 7, 7),
            (1, 10, 9, 4, 5),
            (2, 3, 2, 5, 4),
            (4, 6, 6, 1, 1),
            (1, 5, 11, 3, 1),
            (1, 1, 1, 2, 3),
            (64, 33, 35, 6, 7),
            (2, 300, 301, 2, 2),
        ];
        for (nc, h, w, oh, ow) in cases {
            let x = data(nc * h * w, (h * w) as u64);
            for kind in [PoolKind::Avg, PoolKind::Max] {
                let mut got = vec![f32::NAN; nc * oh * ow];
                adaptive_pool2d(kind, &x, nc, h, w, oh, ow, &mut got);
                assert_close(&got, &naive_adaptive(kind, &x, nc, h, w, oh, ow), 1e-5);
            }
        }
    }

    #[test]
    fn adaptive_maxpool_propagates_nan() {
        let mut x = data(2 * 5 * 5, 4);
        x[5 * 5 + 2 * 5 + 2] = f32::NAN; // plane 1, (2, 2): 5 -> 3 bins [0, 2), [1, 4), [3, 5), so only in bin (1, 1).
        let mut got = vec![0.0; 2 * 3 * 3];
        adaptive_pool2d(PoolKind::Max, &x, 2, 5, 5, 3, 3, &mut got);
        let nan: Vec<usize> = (0..got.len()).filter(|&i| got[i].is_nan()).collect();
        assert_eq!(nan, [9 + 4]);
        assert_eq!(check_adaptive(&[1, 2, 5, 5], &[1, 2, 3, 3]), Ok(()));
        assert!(check_adaptive(&[1, 2, 0, 5], &[1, 2, 3, 3]).is_err());
        assert!(check_adaptive(&[1, 2, 5, 5], &[1, 3, 3, 3]).is_err());
    }
}
