//! Stride-1 depthwise layers of small planes, vectorised over the plane read flat.
//!
//! A 7x7 output row fills 7 of an AVX-512 vector's 16 lanes. Read row-major as one run
//! of pixels, a 7x7 plane is four vectors (49 of 64 lanes), and the tap `(ky, kx)` of a
//! conv whose output is as large as its input reads every output pixel's input at the
//! same offset, `(ky - pad_h) w + (kx - pad_w)`, from a copy of the plane with zeros
//! around it; only the pixels whose column `ox + kx - pad_w` falls outside the row (the
//! offset crossed a row end) must not take the tap, and which those are depends on `kx`
//! and the vector alone. So each tap is, per output vector, one unaligned load and one
//! multiply-add under that mask, the sums of up to [`TILE`] vectors in registers over
//! all the taps. The epilogue's scale, shift and clamp apply as the sums are stored;
//! another activation runs once over all of a task's planes.

use crate::kernels::Epilogue;
use crate::kernels::conv::{Conv2dShape, store_vector};

use super::{PADDED, plane_operands};

/// Output vectors whose sums a tile keeps in registers.
const TILE: usize = 8;

/// The widest plane this path takes: rows of at most half an AVX-512 vector (7x7
/// planes). A 14-pixel row fills 14 of the row-vectorised path's 16 lanes, and there the
/// masked taps cost more than the idle lanes: on EfficientNet-B0's and MobileNetV2's
/// 14x14 layers this path took 1.03-1.13x the row path's time, on their 7x7 ones
/// 0.57-0.71x (alternating calls in one process, 1 and 2 threads, 2026-12-06).
const MAX_W: usize = 8;

/// The most pixels of a plane this path takes (its column masks are per pixel).
const MAX_PLANE: usize = 256;

/// The largest kernel side this path takes.
const MAX_K: usize = 7;

/// Whether a depthwise layer takes this path: stride 1, no dilation, an output of the
/// input's size ("same" padding, odd kernels), rows of at most 8 pixels, planes of at
/// most 256, at most 7x7 taps.
pub(super) fn applies(s: &Conv2dShape) -> bool {
    (s.stride_h, s.stride_w, s.dil_h, s.dil_w) == (1, 1, 1, 1)
        && (s.oh, s.ow) == (s.h, s.w)
        && s.w <= MAX_W
        && s.h * s.w <= MAX_PLANE
        && s.kh <= MAX_K
        && s.kw <= MAX_K
}

/// Planes `first..` of the output (index `n * cout + c`), as many as `dst` holds.
pub(super) struct Flat<'a> {
    pub(super) s: &'a Conv2dShape,
    pub(super) w: &'a [f32],
    pub(super) x: &'a [f32],
    pub(super) ep: &'a Epilogue<'a>,
    pub(super) first: usize,
    pub(super) dst: &'a mut [f32],
}

impl pulp::WithSimd for Flat<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Flat { s, w, x, ep, first, dst } = self;
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let (wd, plane) = (s.w, s.h * s.w);
        let vectors = plane.div_ceil(lanes);
        // The copy: `pad_h` rows and `pad_w` pixels of zeros before the plane and after
        // its last vector, so that every tap of every output vector reads inside it.
        let border = s.pad_h * wd + s.pad_w;
        let len = 2 * border + vectors * lanes;
        // The thread's zero-bordered copy of the plane it is on, and the column masks.
        let mut buf = PADDED.take();
        buf.clear();
        buf.resize(len + s.kw * vectors * lanes, 0.0);
        let (copy, valid) = buf.split_at_mut(len);
        // `valid[kx][p]`: 1 where output pixel `p`'s column moved by `kx - pad_w` stays
        // in its row.
        for (kx, v) in valid.chunks_exact_mut(vectors * lanes).enumerate() {
            for (p, m) in v.iter_mut().enumerate() {
                let col = (p % wd + kx) as isize - s.pad_w as isize;
                *m = if (0..wd as isize).contains(&col) { 1.0 } else { 0.0 };
            }
        }
        let clamp = ep.clamp();
        for (j, out) in dst.chunks_exact_mut(plane).enumerate() {
            let (xc, k, c) = plane_operands(s, w, x, first + j);
            copy[border..border + plane].copy_from_slice(xc);
            let g = Plane {
                copy,
                valid,
                k,
                s,
                scale: simd.splat_f32s(ep.scale.map_or(1.0, |v| v[c])),
                shift: simd.splat_f32s(ep.shift.map_or(0.0, |v| v[c])),
                clamp,
            };
            let mut v = 0;
            while v + TILE <= vectors {
                g.tile::<S, TILE>(simd, v, out);
                v += TILE;
            }
            while v + 4 <= vectors {
                g.tile::<S, 4>(simd, v, out);
                v += 4;
            }
            while v < vectors {
                g.tile::<S, 1>(simd, v, out);
                v += 1;
            }
        }
        PADDED.set(buf);
        ep.finish_unclamped(dst);
    }
}

/// What every tile of one plane reads.
struct Plane<'a, V> {
    /// The plane with its zero border.
    copy: &'a [f32],
    /// Per kernel column, which output pixels take its taps (1) or not (0).
    valid: &'a [f32],
    /// The plane's taps, `kh x kw`.
    k: &'a [f32],
    s: &'a Conv2dShape,
    scale: V,
    shift: V,
    clamp: Option<(f32, f32)>,
}

impl<V: Copy> Plane<'_, V> {
    /// Output vectors `v0..v0 + R`: the sums over every tap in registers, then stored by
    /// the register paths' `store_vector` (the last vector only as far as the plane).
    #[inline(always)]
    fn tile<S: pulp::Simd<f32s = V>, const R: usize>(&self, simd: S, v0: usize, out: &mut [f32]) {
        let (s, lanes) = (self.s, size_of::<V>() / size_of::<f32>());
        let (wd, row) = (s.w, self.valid.len() / s.kw);
        let mut acc = [simd.splat_f32s(0.0); R];
        let half = simd.splat_f32s(0.5);
        let vec = |a: &[f32]| S::as_simd_f32s(&a[..lanes]).0[0];
        for kx in 0..s.kw {
            let valid = &self.valid[kx * row + v0 * lanes..];
            let masks: [S::m32s; R] = std::array::from_fn(|r| simd.greater_than_f32s(vec(&valid[r * lanes..]), half));
            for ky in 0..s.kh {
                let tap = simd.splat_f32s(self.k[ky * s.kw + kx]);
                // Output pixel `p` reads position `p + ky w + kx` of the copy (its border
                // is `pad_h` rows and `pad_w` pixels).
                let from = &self.copy[v0 * lanes + ky * wd + kx..];
                for (r, a) in acc.iter_mut().enumerate() {
                    let xv = vec(&from[r * lanes..]);
                    *a = simd.select_f32s(masks[r], simd.mul_add_f32s(xv, tap, *a), *a);
                }
            }
        }
        for (r, a) in acc.into_iter().enumerate() {
            let at = (v0 + r) * lanes;
            if at < out.len() {
                let end = out.len().min(at + lanes);
                store_vector(simd, a, self.scale, self.shift, self.clamp, &mut out[at..end]);
            }
        }
    }
}
