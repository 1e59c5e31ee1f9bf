//! The GEMM paths, [`ConvAlgo::Gemm1x1`] and [`ConvAlgo::Im2col`]: per tile of output
//! pixels (of one image and group), the input as it is or unfolded by [`im2col`], one GEMM
//! into scratch, and the epilogue into the part's output planes. A LoRA branch reads the
//! same tile: `t = A col` (rank rows) and `acc += B t`, before the epilogue. An adapter
//! (one group, a row split: the tile holds every channel) runs on the scaled and shifted
//! tile before it is copied out ([`super::adapter`]). Small planes skip the GEMM call:
//! Gemm1x1 layers in `conv2d_fused`, Im2col tiles here after the unfold
//! ([`super::pointwise`]). Under a split by channels the threads unfold each tile
//! together ([`im2col_shared`]).

use super::adapter::{Adapter, apply_tile};
use super::split::{Part, channel_shares, shared_scratch, sum_shares};
use super::{Conv2dShape, ConvAlgo, Lora, finish, pointwise};
use crate::kernels::Epilogue;
use crate::kernels::elementwise::relu;
use crate::kernels::gemm::{MatMut, MatRef, few_rows_product, sgemm};

/// Pixels per GEMM tile: the unfolded tile plus the result tile fill up to 1.5 MiB, in
/// multiples of 16 pixels (the GEMM's vector width). Larger than L2, but each GEMM call
/// packs the weight again, so fewer, larger tiles measured faster.
pub(super) fn gemm_tile(s: &Conv2dShape, algo: ConvAlgo) -> usize {
    let per_pixel = s.cout_g() + if algo == ConvAlgo::Im2col { s.k() } else { 0 };
    let tile = (384 * 1024 / per_pixel.max(1)).clamp(16, 4096) / 16 * 16;
    tile.min((s.oh * s.ow).div_ceil(16) * 16)
}

/// The pixels of the next GEMM call when `left` remain: at most `tile`; and when `split`
/// ([`split_remainder`]), a multiple of 16 unless fewer than 16 remain. The `gemm` crate
/// packs every pixel of a call (16 to a vector) when their count is not a multiple of 16,
/// and computes them in place otherwise; a remainder of a few pixels in a call of its own
/// packs only those.
fn gemm_cols(left: usize, tile: usize, split: bool) -> usize {
    if left > tile {
        tile
    } else if split && left > 16 {
        left / 16 * 16
    } else {
        left
    }
}

/// Whether a layer's GEMM tiles split off their last pixels past a multiple of 16
/// ([`gemm_cols`]): when the input is deep and the output narrow, packing the tile's input
/// costs more than a second call. A 28x28 plane split by rows between two threads
/// leaves each 392 pixels (2-core AMD EPYC, 2026-12-06, old and new rule alternating
/// call by call in one process, 780 pairs, two threads): MobileNetV2's and
/// EfficientNet-B0's projections 96, 120, 144, 192 and 240 to 32 or 40 channels took
/// 0.92-0.96x the time; expansions 32 or 40 to 96-240 took 1.03-1.05x, ResNet-50's 512 to
/// 128 and 128 to 512 1.01x (kept whole).
pub(super) fn split_remainder(s: &Conv2dShape) -> bool {
    s.cout_g() <= 64 && s.k() >= 2 * s.cout_g()
}

/// Gemm1x1 / Im2col over one part: per image, per tile of pixels, per group: (unfold,)
/// GEMM into scratch (and a LoRA branch's two small ones), epilogue into the output.
#[allow(clippy::too_many_arguments)]
pub(super) fn gemm_part(
    s: &Conv2dShape,
    algo: ConvAlgo,
    w: &[f32],
    lora: Option<&Lora>,
    adapter: Option<&Adapter>,
    ep: &Epilogue,
    x: &[f32],
    part: &mut Part,
    scratch: &mut [f32],
) {
    let (cin_g, cout_g, k) = (s.cin_g(), s.cout_g(), s.k());
    let plane_in = s.h * s.w;
    let tile = gemm_tile(s, algo);
    let rank = lora.map_or(0, |l| l.rank);
    let (acc, rest) = scratch.split_at_mut(tile * cout_g);
    let (t, rest) = rest.split_at_mut(tile * rank);
    let (h, col) = rest.split_at_mut(tile * adapter.map_or(0, |a| a.mid));
    // Small planes of one group skip the GEMM call: register tiles over the unfolded rows.
    let registers = algo == ConvAlgo::Im2col && lora.is_none() && adapter.is_none() && pointwise::applies_unfolded(s);
    let split = !registers && split_remainder(s);
    let last = (part.r1 - 1) / s.oh;
    for n in part.n0..=last {
        let (lo, hi) = part.rows_of(n, s.oh);
        let (p_lo, p_hi) = (lo * s.ow, hi * s.ow);
        let mut p0 = p_lo;
        while p0 < p_hi {
            let tp = gemm_cols(p_hi - p0, tile, split);
            for g in 0..s.groups {
                let chans = part.channels_of(g, cout_g);
                let mrows = chans.len();
                if mrows == 0 {
                    continue;
                }
                let xg = &x[(n * s.cin + g * cin_g) * plane_in..][..cin_g * plane_in];
                let rhs = if algo == ConvAlgo::Gemm1x1 {
                    MatRef { data: &xg[p0..], rows: cin_g, cols: tp, row_stride: plane_in, col_stride: 1 }
                } else {
                    let (col, tail) = col.split_at_mut(k * tp);
                    im2col_simd(s, xg, 0..cin_g, p0, tp, col);
                    if registers {
                        pointwise::unfolded(s, w, ep, col, tp, part, n, chans, (p0, p_lo), tail);
                        continue;
                    }
                    MatRef::row_major(col, k, tp)
                };
                // One group (checked) for a LoRA branch: the tile is the whole input's.
                let branch = lora.map(|l| {
                    let t = &mut t[..l.rank * tp];
                    few_rows_product(MatRef::row_major(l.a, l.rank, k), rhs, MatMut::row_major(t, l.rank, tp));
                    (l.b, l.rank, &*t)
                });
                let scratch = (&mut *acc, &mut *h);
                multiply_tile(s, w, branch, adapter, ep, rhs, part, (n, chans, p0 - p_lo), scratch);
            }
            p0 += tp;
        }
    }
}

/// What the GEMM paths do with a tile once its right-hand side `rhs` is ready (the input
/// in place, or its unfolded rows): channels `chans` of image `n` at the `rhs.cols`
/// pixels `off` from the part's first, one GEMM into `acc`, a LoRA branch's `B t` (`B`
/// of every channel, `rank`, and `t = A rhs`, rank rows of the tile), then the epilogue
/// into the part's planes, through the adapter (and `h`) if there is one.
#[allow(clippy::too_many_arguments)]
fn multiply_tile(
    s: &Conv2dShape,
    w: &[f32],
    branch: Option<(&[f32], usize, &[f32])>,
    adapter: Option<&Adapter>,
    ep: &Epilogue,
    rhs: MatRef,
    part: &mut Part,
    (n, chans, off): (usize, std::ops::Range<usize>, usize),
    (acc, h): (&mut [f32], &mut [f32]),
) {
    let (k, tp, mrows) = (s.k(), rhs.cols, chans.len());
    let lhs = MatRef::row_major(&w[chans.start * k..][..mrows * k], mrows, k);
    let acc = &mut acc[..mrows * tp];
    sgemm(lhs, rhs, MatMut::row_major(acc, mrows, tp), false, 1);
    if let Some((b, rank, t)) = branch {
        let b = MatRef::row_major(&b[chans.start * rank..][..mrows * rank], mrows, rank);
        sgemm(b, MatRef::row_major(&t[..rank * tp], rank, tp), MatMut::row_major(acc, mrows, tp), true, 1);
    }
    if let Some(ad) = adapter {
        // Every channel of the tile (one group, a row split): scale and shift in place,
        // the adapter and the ReLU, then a plain copy out.
        finish_in_place(acc, tp, &Epilogue { act: None, ..*ep });
        apply_tile(ad, acc, mrows, tp, h, ep.act);
        finish_tile(part, n, chans, off, acc, tp, &Epilogue::default());
    } else {
        finish_tile(part, n, chans, off, acc, tp, ep);
    }
}

simd_fn! {
    /// The epilogue of one GEMM tile: row `c - chans.start` of `acc` (rows of `tp`) into
    /// the part's plane of image `n`, channel `c`, from offset `off`.
    fn finish_tile(
        part: &mut Part<'_>,
        n: usize,
        chans: std::ops::Range<usize>,
        off: usize,
        acc: &[f32],
        tp: usize,
        ep: &Epilogue<'_>,
    ) {
        for (c, acc_row) in chans.zip(acc.chunks(tp)) {
            let res = part.residual(n, c).map(|r| &r[off..]);
            finish(&mut part.plane(n, c)[off..], acc_row, c, ep, res);
        }
    }
}

simd_fn! {
    /// The epilogue on a tile of every channel (rows of `tp`), in place.
    fn finish_in_place(acc: &mut [f32], tp: usize, ep: &Epilogue<'_>) {
        for (c, row) in acc.chunks_mut(tp).enumerate() {
            let scale = ep.scale.map_or(1.0, |v| v[c]);
            let shift = ep.shift.map_or(0.0, |v| v[c]);
            match (ep.scale.is_some(), ep.relu()) {
                (true, true) => row.iter_mut().for_each(|a| *a = relu(*a * scale + shift)),
                (true, false) => row.iter_mut().for_each(|a| *a = *a * scale + shift),
                (false, true) => row.iter_mut().for_each(|a| *a = relu(*a + shift)),
                (false, false) => row.iter_mut().for_each(|a| *a += shift),
            }
        }
    }
}

/// Im2col over parts that split a layer of one group by output channels (each part owns
/// every pixel), no adapter in the tiles: per image and tile of pixels, the parts first
/// unfold the tile together, each its share of the input channels into one matrix (in the
/// first part's scratch), then each multiplies its channels (a GEMM, or the register
/// tiles of small planes) and writes them with the epilogue. Through [`gemm_part`] each
/// part would unfold the whole tile itself: ResNet-50's 28 -> 14 strided 3x3 (2304
/// unfolded rows of 196 pixels) scaled 1.39x from one thread to two; shared, that step
/// took 0.83x as long at two threads, its 14 -> 7 one 0.87x, the 1x1 downsampling ones
/// 0.91-0.95x (6 alternating rounds). A LoRA branch's `t = A col` sums every input
/// channel: each part sums its share's rows while they are hot (into its scratch), and
/// every part adds the shares up (rank rows of the tile per part).
/// `jobs` are the parts with their scratch, each at least `part_scratch` floats.
pub(super) fn im2col_shared(
    s: &Conv2dShape,
    w: &[f32],
    lora: Option<&Lora>,
    ep: &Epilogue,
    x: &[f32],
    jobs: &mut [(Part, &mut [f32])],
) {
    use rayon::prelude::*;
    let (cin_g, cout_g, k, kk) = (s.cin_g(), s.cout_g(), s.k(), s.kh * s.kw);
    assert_eq!(s.groups, 1, "im2col_shared: one group");
    let tile = gemm_tile(s, ConvAlgo::Im2col);
    let registers = lora.is_none() && pointwise::applies_unfolded(s);
    let rank = lora.map_or(0, |l| l.rank);
    let threads = jobs.len();
    // Each job's accumulator and tail scratch (`t`, or the register tiles' scratch), and
    // its share of `t`; the first job's unfolding area is shared.
    let (shared, mut shares_t, mut own) = shared_scratch(jobs, tile * cout_g, k * tile, rank * tile);
    let (plane_in, plane) = (s.h * s.w, s.oh * s.ow);
    for n in 0..s.n {
        let xg = &x[n * s.cin * plane_in..][..cin_g * plane_in];
        for p0 in (0..plane).step_by(tile) {
            let tp = tile.min(plane - p0);
            // Each job unfolds a share of the input channels into its rows of the tile
            // (and multiplies them by their columns of `A`).
            let shares = channel_shares(&mut shared[..k * tp], cin_g, threads, kk * tp);
            shares.into_par_iter().zip(shares_t.par_iter_mut()).for_each(|((cis, col), share_t)| {
                im2col_simd(s, xg, cis.clone(), p0, tp, col);
                if let Some(l) = lora {
                    let (c0, depth) = (cis.start * kk, cis.len() * kk);
                    let a = MatRef { data: &l.a[c0..], rows: rank, cols: depth, row_stride: k, col_stride: 1 };
                    let dst = MatMut::row_major(&mut share_t[..rank * tp], rank, tp);
                    few_rows_product(a, MatRef::row_major(col, depth, tp), dst);
                }
            });
            let (col, shares_t): (&[f32], &[&mut [f32]]) = (&shared[..k * tp], &shares_t);
            own.par_iter_mut().for_each(|(part, acc, tail)| {
                let chans = part.channels_of(0, cout_g);
                if chans.is_empty() {
                    return;
                }
                if registers {
                    pointwise::unfolded(s, w, ep, col, tp, part, n, chans, (p0, 0), tail);
                    return;
                }
                let branch = lora.map(|l| {
                    let t = &mut tail[..rank * tp];
                    sum_shares(t, shares_t);
                    (l.b, rank, &*t)
                });
                let rhs = MatRef::row_major(col, k, tp);
                multiply_tile(s, w, branch, None, ep, rhs, part, (n, chans, p0), (acc, &mut []));
            });
        }
    }
}

simd_fn! {
    /// [`im2col`], vectorised.
    fn im2col_simd(s: &Conv2dShape, xg: &[f32], cis: std::ops::Range<usize>, p0: usize, tp: usize, col: &mut [f32]) {
        im2col(s, xg, cis, p0, tp, col)
    }
}

/// Unfolds output pixels `p0..p0 + tp` of one image and group, input channels `cis` of
/// the group, into `col`, a row-major `(cis.len()·kh·kw) × tp` matrix: `col[(ci -
/// cis.start, ky, kx)][p] = x[ci, iy, ix]` (0 in the padding).
#[inline(always)]
fn im2col(s: &Conv2dShape, xg: &[f32], cis: std::ops::Range<usize>, p0: usize, tp: usize, col: &mut [f32]) {
    let (h, w) = (s.h as isize, s.w as isize);
    let mut row = 0;
    for ci in cis {
        let xc = &xg[ci * s.h * s.w..][..s.h * s.w];
        for ky in 0..s.kh {
            for kx in 0..s.kw {
                let dst = &mut col[row * tp..][..tp];
                row += 1;
                let dy = (ky * s.dil_h) as isize - s.pad_h as isize;
                let dx = (kx * s.dil_w) as isize - s.pad_w as isize;
                // Output columns whose input column is inside the image: ox in ox_lo..ox_hi.
                let ox_lo = ((-dx).max(0) as usize).div_ceil(s.stride_w).min(s.ow);
                let ox_hi = if w - dx <= 0 { 0 } else { ((w - dx) as usize).div_ceil(s.stride_w).min(s.ow) };
                let mut p = p0;
                let mut off = 0;
                while off < tp {
                    let (oy, ox0) = (p / s.ow, p % s.ow);
                    let run = (s.ow - ox0).min(tp - off);
                    let seg = &mut dst[off..off + run];
                    let iy = (oy * s.stride_h) as isize + dy;
                    if iy < 0 || iy >= h {
                        seg.fill(0.0);
                    } else {
                        let src = &xc[iy as usize * s.w..][..s.w];
                        let (a, b) = (ox_lo.clamp(ox0, ox0 + run), ox_hi.clamp(ox0, ox0 + run));
                        let (a, b) = (a, b.max(a));
                        seg[..a - ox0].fill(0.0);
                        seg[b - ox0..].fill(0.0);
                        let ix0 = (a * s.stride_w) as isize + dx;
                        let body = &mut seg[a - ox0..b - ox0];
                        if !body.is_empty() {
                            let ix0 = ix0 as usize;
                            strided_copy(body, &src[ix0..], s.stride_w);
                        }
                    }
                    p += run;
                    off += run;
                }
            }
        }
    }
}

/// `dst[i] = src[i · stride]`, vectorised for the common strides.
#[inline(always)]
fn strided_copy(dst: &mut [f32], src: &[f32], stride: usize) {
    let n = dst.len();
    match stride {
        1 => dst.copy_from_slice(&src[..n]),
        2 => {
            // All but the last element as pairs (the last may have no partner in `src`).
            let (head, last) = dst.split_at_mut(n - 1);
            for (d, pair) in head.iter_mut().zip(src.chunks_exact(2)) {
                *d = pair[0];
            }
            last[0] = src[2 * (n - 1)];
        }
        _ => dst.iter_mut().zip(src.iter().step_by(stride)).for_each(|(d, &v)| *d = v),
    }
}
