//! [`ConvAlgo::Panels`](super::ConvAlgo::Panels): convs whose output planes are a few
//! vectors of pixels (ResNet's 7x7 stage). The GEMM paths put pixels in the vector lanes, so
//! a 49-pixel plane fills four 16-lane vectors with 15 lanes to spare, and the `gemm`
//! crate packs the whole weight again on every call (9.4 MB for a 512-channel 3x3 layer).
//! Here the weight is packed once, at compile time, in the panels of a linear layer
//! ([`panel::pack`]: `[ceil(cout / PANEL)][k][PANEL]`), and each image is unfolded pixel by
//! pixel (`col[p][k]`, `k = cin · kh · kw` in PyTorch's order), so the product is a linear
//! layer's, `prod[p][c] = Σ_k col[p][k] · W[c][k]`, with the output channels in the lanes
//! ([`panel::gemm`]). Each channel's column of `prod`, copied out, takes the conv's one
//! epilogue (`finish`) into its plane.
//!
//! A fused LoRA branch reads `A` raw (`[rank][k]`): `t[p][r] = col[p] · A[r]` by dot
//! products, then `prod += t · Bᵀ` through `B`'s rows packed as panels once a call (`rank ·
//! cout` floats). The threads share the panels (each its channels, their epilogue too).
//!
//! ResNet-18's and ResNet-50's 512-channel 3x3 layers at 7x7 took 0.83-0.86x the time of
//! the im2col path (one thread, a throwaway prototype with a plain unfold, 2026-12-06,
//! EPYC Zen 4); at 14x14 and 28x28 1.03-1.24x, hence [`MAX_PLANE`]; 1x1 layers at 7x7 gained
//! nothing (0.98-1.09x) and keep the 1x1 GEMM.

use rayon::prelude::*;

use super::{Conv2dShape, finish};
use crate::kernels::{Epilogue, Lora, panel};
use readi_plan::ops::PANEL;

/// Most output pixels per image of a layer [`super::choose`] gives this algorithm: a 7x7
/// plane, which fills four 16-lane vectors of pixels with 15 lanes to spare (measured); an
/// 8x8 one fills them exactly and stays on the GEMM paths (not measured).
pub const MAX_PLANE: usize = 49;

/// Scratch floats of a layer with a LoRA branch of `rank` (0: none): one image unfolded,
/// its branch's `t`, the product, `B`'s panels and a plane's row per panel (at most one
/// worker a panel). Saturates (a crafted plan's plane and depth may be large together; no
/// session allocates that).
pub(super) fn scratch_len(s: &Conv2dShape, rank: usize) -> usize {
    let (plane, panels) = (s.oh * s.ow, s.cout.div_ceil(PANEL));
    let unfolded = plane.saturating_mul(s.k().saturating_add(rank));
    let per_panel = plane.saturating_mul(PANEL + 1).saturating_add(rank * PANEL);
    unfolded.saturating_add(panels.saturating_mul(per_panel))
}

/// The conv of every image of `x` into `out` (`[n, cout, oh, ow]`), `w` packed by
/// [`panel::pack`], plus `B (A x)` of `lora`, then the epilogue with the residual `res`.
/// One group (checked by `ConvAlgo::supports`).
#[allow(clippy::too_many_arguments)]
pub(super) fn conv(
    s: &Conv2dShape,
    w: &[f32],
    lora: Option<&Lora>,
    ep: &Epilogue,
    x: &[f32],
    res: Option<&[f32]>,
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    let (k, plane, cout) = (s.k(), s.oh * s.ow, s.cout);
    let rank = lora.map_or(0, |l| l.rank);
    let panels = cout.div_ceil(PANEL);
    // Whole panels a worker, as evenly as they go.
    let per = panels.div_ceil(threads.max(1).min(panels));
    let (col, rest) = scratch.split_at_mut(plane * k);
    let (t, rest) = rest.split_at_mut(plane * rank);
    let (prod, rest) = rest.split_at_mut(panels * PANEL * plane);
    let (bp, rows) = rest.split_at_mut(panel::packed_len(rank, cout));
    let rows = &mut rows[..panels * plane];
    if let Some(l) = lora {
        panel::pack(l.b, rank, cout, bp);
    }
    let bp: &[f32] = bp;
    let (image_in, image_out) = (s.cin * s.h * s.w, cout * plane);
    for n in 0..s.n {
        let xn = &x[n * image_in..][..image_in];
        if threads > 1 && plane > 1 {
            let rows = plane.div_ceil(threads);
            col.par_chunks_mut(rows * k).enumerate().for_each(|(i, c)| unfold(s, xn, i * rows, c));
        } else {
            unfold(s, xn, 0, col);
        }
        let col: &[f32] = col;
        if let Some(l) = lora {
            pulp::Arch::new().dispatch(Dots { col, k, a: l.a, rank, t: &mut *t });
        }
        let t: &[f32] = t;
        let on = &mut out[n * image_out..][..image_out];
        let rn = res.map(|r| &r[n * image_out..][..image_out]);
        let chunk = per * PANEL;
        // Worker `i`: the planes of its channels, its part of the product, a row.
        let job = |i: usize, planes: &mut [f32], prod: &mut [f32], row: &mut [f32]| {
            let c0 = i * chunk;
            let cols = planes.len() / plane;
            let prod = &mut prod[..plane * cols];
            panel::gemm(col, plane, k, &w[c0 * k..][..panel::packed_len(k, cols)], cols, prod);
            if lora.is_some() {
                panel::gemm_add(t, plane, rank, &bp[c0 * rank..][..panel::packed_len(rank, cols)], cols, prod);
            }
            let row = &mut row[..plane];
            for (j, dst) in planes.chunks_exact_mut(plane).enumerate() {
                let c = c0 + j;
                row.iter_mut().zip(prod[j..].iter().step_by(cols)).for_each(|(r, &v)| *r = v);
                finish(dst, row, c, ep, rn.map(|r| &r[c * plane..][..plane]));
            }
        };
        if per >= panels {
            job(0, on, prod, rows);
        } else {
            let pc = chunk * plane;
            let jobs = on.par_chunks_mut(pc).zip(prod.par_chunks_mut(pc)).zip(rows.par_chunks_mut(per * plane));
            jobs.enumerate().for_each(|(i, ((planes, prod), row))| job(i, planes, prod, row));
        }
    }
}

/// Unfolds pixels `first..` of one image `x` into `col`, a row of `k` values per pixel
/// (input channel, kernel row, kernel column: PyTorch's weight order), zero outside the
/// input; as many pixels as `col` has rows.
fn unfold(s: &Conv2dShape, x: &[f32], first: usize, col: &mut [f32]) {
    let k = s.k();
    let (h, w) = (s.h as isize, s.w as isize);
    let plane_in = s.h * s.w;
    for (p, row) in (first..).zip(col.chunks_exact_mut(k)) {
        let (oy, ox) = ((p / s.ow * s.stride_h) as isize, (p % s.ow * s.stride_w) as isize);
        let (oy, ox) = (oy - s.pad_h as isize, ox - s.pad_w as isize);
        for (ci, dst) in row.chunks_exact_mut(s.kh * s.kw).enumerate() {
            let xc = &x[ci * plane_in..][..plane_in];
            for (ky, dst) in dst.chunks_exact_mut(s.kw).enumerate() {
                let iy = oy + (ky * s.dil_h) as isize;
                if !(0..h).contains(&iy) {
                    dst.fill(0.0);
                    continue;
                }
                let xr = &xc[iy as usize * s.w..][..s.w];
                for (kx, d) in dst.iter_mut().enumerate() {
                    let ix = ox + (kx * s.dil_w) as isize;
                    *d = if (0..w).contains(&ix) { xr[ix as usize] } else { 0.0 };
                }
            }
        }
    }
}

/// `t[p][r] = col[p] · a[r]` for every pixel row of `col` (`k` long) and each of `rank`
/// rows of `a`: four running sums a row (the product's latency), then the tail.
struct Dots<'a> {
    col: &'a [f32],
    k: usize,
    a: &'a [f32],
    rank: usize,
    t: &'a mut [f32],
}

impl pulp::WithSimd for Dots<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Dots { col, k, a, rank, t } = self;
        for (row, tr) in col.chunks_exact(k).zip(t.chunks_exact_mut(rank)) {
            let (xv, xt) = S::as_simd_f32s(row);
            for (r, out) in tr.iter_mut().enumerate() {
                let (av, at) = S::as_simd_f32s(&a[r * k..][..k]);
                let mut acc = [simd.splat_f32s(0.0); 4];
                let (x4, a4) = (xv.chunks_exact(4), av.chunks_exact(4));
                let (xr, ar) = (x4.remainder(), a4.remainder());
                for (x, y) in x4.zip(a4) {
                    for i in 0..4 {
                        acc[i] = simd.mul_add_f32s(x[i], y[i], acc[i]);
                    }
                }
                for (x, y) in xr.iter().zip(ar) {
                    acc[0] = simd.mul_add_f32s(*x, *y, acc[0]);
                }
                let sum = simd.add_f32s(simd.add_f32s(acc[0], acc[1]), simd.add_f32s(acc[2], acc[3]));
                *out = simd.reduce_sum_f32s(sum) + xt.iter().zip(at).map(|(x, y)| x * y).sum::<f32>();
            }
        }
    }
}
