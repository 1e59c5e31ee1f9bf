//! Depthwise layers with rows of at least 16 outputs (AVX-512), read in place: 3x3, 5x5
//! and 7x7 kernels at stride 1, 3x3 and 5x5 at stride 2, padding half the kernel. The 5x5
//! and 7x7 ones at stride 1 on planes of up to 28x28 outputs stay with the
//! channels-in-lanes path (`super::reads_in_place`).
//!
//! The row path ([`super::Registers`]) copies each input plane into a zero-bordered
//! buffer (at stride 2 split into its even and odd columns) and reads the copy back. On
//! MobileNetV2's 112 to 56 layer the copy and the reading each took about half the
//! layer's time: the copy is bound by the core's stores, and a 50 KiB plane costs as much
//! to copy from L2 as from L3. Here each input row is read where it lies, the columns that
//! fall off the row (the padding) masked to zero in the loads. At stride 1 a kernel row's
//! taps for sixteen outputs are `K` loads from consecutive columns. At stride 2 they come
//! from three loads (columns `2 ox - pad` on), split by two permutes into the even and
//! odd columns, and each further tap by one more permute, one lane on from the tap two
//! before (the third load supplying its last lane). Each
//! input row feeds the sums of every output row of the block that reads it; the sums stay
//! in registers, [`R`] output rows at a time, and the epilogue's scale, shift and clamp
//! are applied as they are stored.
//!
//! Measured on the 2-core AMD EPYC (Zen 4, 2026-12-06), this path's time over the row
//! path's. Alone, the two alternating call by call in one process (380 pairs, inputs warm,
//! 1 / 2 threads): at stride 2, 96 channels 112 to 56 with ReLU6 0.52 / 0.50, 64 with ReLU
//! 0.62 / 0.62, with SiLU (its pass after the conv unchanged) 0.73 / 0.72, 32 channels 224
//! to 112 (a plane past the row path's copy, so its loops) 0.43 / 0.42; at stride 1 3x3 on
//! 112x112 and 56x56 planes 0.77-1.05, 7x7 on 56x56 0.96-1.01, 5x5 0.69-0.72. In the
//! models, one thread, per step (the two paths alternating run by run in one process,
//! 150-200 rounds): MobileNetV2's 112 to 56 layer 0.60 to 0.39 ms, its 32-channel 112x112
//! one 0.30 to 0.27, its 144-channel 56x56 one 0.39 to 0.33; MobileNetV3-Large's 112 to 56
//! layer 0.39-0.40 to 0.25-0.28 ms, its 16-channel 112x112 one 0.17-0.18 to 0.15-0.16 (its
//! 72-channel 56x56 one 0.12 to 0.13, the only step that lost); EfficientNet-B0's 112 to
//! 56 layer 0.74 to 0.57, its 32-channel 112x112 one 0.48 to 0.44; ConvNeXt-T's 7x7 on
//! 56x56 0.59-0.60 to 0.57-0.59. Whole models (medians of the rounds' ratios, 1 / 2
//! threads): MobileNetV2 0.94 / 0.97, MobileNetV3-Large 0.97 and 1.01 in two runs / 1.00,
//! EfficientNet-B0 0.98 / 0.97.

use core::arch::x86_64::__m512;

use pulp::x86::V4;
use pulp::{Simd, cast};

use super::plane_operands;
use crate::kernels::Epilogue;
use crate::kernels::conv::{Conv2dShape, store_vector, vector_starts};
use crate::kernels::rows512::{L, even_odd, load_or, next_column, row_mask};

/// Output rows whose sums one block keeps in registers.
const R: usize = 4;

/// Whether a depthwise layer takes this path: AVX-512 at run time, one output channel per
/// input channel, a square kernel of 3, 5 or 7 at stride 1 or of 3 at stride 2, padding
/// half the kernel, no dilation, and output rows of at least a vector.
pub(super) fn applies(s: &Conv2dShape) -> bool {
    let k = s.kh;
    let kernel = match s.stride_w {
        1 => matches!(k, 3 | 5 | 7),
        2 => matches!(k, 3 | 5),
        _ => false,
    };
    s.cin == s.groups
        && s.cout == s.cin
        && s.stride_h == s.stride_w
        && s.kw == k
        && kernel
        && (s.pad_h, s.pad_w) == (k / 2, k / 2)
        && (s.dil_h, s.dil_w) == (1, 1)
        && s.ow >= L
        && V4::try_new().is_some()
}

/// The planes of `dst` (output planes `first..`) with the epilogue, for a layer
/// [`applies`] takes: one task of `depthwise`'s split of the planes.
pub(super) fn planes(s: &Conv2dShape, w: &[f32], ep: &Epilogue, x: &[f32], first: usize, dst: &mut [f32]) {
    let simd = V4::try_new().expect("in_place::applies checks AVX-512");
    let task = Task { s, w, ep, x, first, dst };
    // Compiled with AVX-512 enabled: everything `dispatch` calls is inlined into it.
    simd.vectorize(
        #[inline(always)]
        move || task.dispatch(simd),
    )
}

/// The planes of `dst`, the first of them output plane `first`: what a task hands to the
/// AVX-512 code as one value. (A closure capturing the seven one by one and calling a
/// function that matches on the stride and kernel, or matching itself, was left out of
/// line by `vectorize`, compiled without AVX-512: every intrinsic a call, ten times
/// slower.)
struct Task<'a> {
    s: &'a Conv2dShape,
    w: &'a [f32],
    ep: &'a Epilogue<'a>,
    x: &'a [f32],
    first: usize,
    dst: &'a mut [f32],
}

impl Task<'_> {
    /// [`plane_rows`] for the layer's stride and kernel.
    #[inline(always)]
    fn dispatch(self, simd: V4) {
        let Task { s, w, ep, x, first, dst } = self;
        match (s.stride_w, s.kh) {
            (1, 3) => plane_rows::<1, 3>(simd, s, w, ep, x, first, dst),
            (1, 5) => plane_rows::<1, 5>(simd, s, w, ep, x, first, dst),
            (1, 7) => plane_rows::<1, 7>(simd, s, w, ep, x, first, dst),
            (2, 3) => plane_rows::<2, 3>(simd, s, w, ep, x, first, dst),
            (2, 5) => plane_rows::<2, 5>(simd, s, w, ep, x, first, dst),
            _ => unreachable!("in_place::applies"),
        }
    }
}

/// The planes of `dst`, the first of them output plane `first`, block of rows by block.
#[inline(always)]
fn plane_rows<const ST: usize, const K: usize>(
    simd: V4,
    s: &Conv2dShape,
    w: &[f32],
    ep: &Epilogue,
    x: &[f32],
    first: usize,
    dst: &mut [f32],
) {
    let clamp = ep.clamp();
    for (j, dst) in dst.chunks_mut(s.oh * s.ow).enumerate() {
        let (xc, k, c) = plane_operands(s, w, x, first + j);
        // Each tap splatted (loops: closures are compiled without AVX-512).
        let mut taps: [[__m512; K]; K] = [[cast(simd.splat_f32s(0.0)); K]; K];
        for (ky, row) in taps.iter_mut().enumerate() {
            for (kx, t) in row.iter_mut().enumerate() {
                *t = cast(simd.splat_f32s(k[ky * K + kx]));
            }
        }
        let g = Plane {
            x: xc,
            h: s.h,
            w: s.w,
            ow: s.ow,
            scale: simd.splat_f32s(ep.scale.map_or(1.0, |v| v[c])),
            shift: simd.splat_f32s(ep.shift.map_or(0.0, |v| v[c])),
            clamp,
        };
        let full = s.oh / R * R;
        for oy in (0..full).step_by(R) {
            g.rows::<ST, K, R>(simd, &taps, oy, dst);
        }
        for oy in full..s.oh {
            g.rows::<ST, K, 1>(simd, &taps, oy, dst);
        }
        ep.finish_unclamped(dst);
    }
}

/// One input plane (`h x w`, row-major) and what its output plane's stores share.
struct Plane<'a> {
    x: &'a [f32],
    h: usize,
    w: usize,
    ow: usize,
    scale: pulp::f32x16,
    shift: pulp::f32x16,
    clamp: Option<(f32, f32)>,
}

impl Plane<'_> {
    /// Output rows `oy0..oy0 + RR` of the plane `dst`, vector by vector along the rows.
    #[inline(always)]
    fn rows<const ST: usize, const K: usize, const RR: usize>(
        &self,
        simd: V4,
        taps: &[[__m512; K]; K],
        oy0: usize,
        dst: &mut [f32],
    ) {
        let f = simd.avx512f;
        let pad = K / 2;
        let loads = if ST == 1 { K } else { 3 };
        let w = self.w as isize;
        for ox in vector_starts(self.ow, L) {
            // Stride 1: the loads of tap kx from column `ox - pad + kx`. Stride 2: three
            // loads from column `2 ox - pad`, 16 and 32 further, of the third only its first
            // K - 2 lanes. Each masked to the columns inside the row.
            let col = (ST * ox) as isize - pad as isize;
            let mut from = [0isize; K];
            let mut mask = [0u16; K];
            for (kx, (fr, m)) in from.iter_mut().zip(mask.iter_mut()).enumerate().take(loads) {
                *fr = if ST == 1 { col + kx as isize } else { col + (kx * L) as isize };
                *m = row_mask(*fr, w);
            }
            if ST == 2 {
                mask[2] &= (1 << (K - 2)) - 1;
            }
            let mut acc = [f._mm512_setzero_ps(); RR];
            for j in 0..ST * (RR - 1) + K {
                // Input row `ST oy0 - pad + j`, read by output rows `r` with `j - ST r`
                // in 0..K (the kernel row).
                let iy = (ST * oy0 + j) as isize - pad as isize;
                if iy < 0 || iy >= self.h as isize {
                    continue;
                }
                let row = &self.x[iy as usize * self.w..][..self.w];
                let zero = f._mm512_setzero_ps();
                let mut t = [zero; K];
                for kx in 0..loads {
                    t[kx] = load_or(simd, zero, row, from[kx], mask[kx]);
                }
                if ST == 2 {
                    // Columns 2 (ox + i) - pad + kx: the even and odd columns of the first
                    // two loads, then each one lane on from the one two taps before, its
                    // last lane lane kx - 2 of the third load.
                    let c = t[2];
                    (t[0], t[1]) = even_odd(simd, t[0], t[1]);
                    for kx in 2..K {
                        t[kx] = next_column(simd, t[kx - 2], c, (kx - 2) as u32);
                    }
                }
                for (r, acc) in acc.iter_mut().enumerate() {
                    let ky = j as isize - (ST * r) as isize;
                    if (0..K as isize).contains(&ky) {
                        for (&tap, &v) in taps[ky as usize].iter().zip(&t) {
                            *acc = f._mm512_fmadd_ps(v, tap, *acc);
                        }
                    }
                }
            }
            for (r, a) in acc.into_iter().enumerate() {
                let out = &mut dst[(oy0 + r) * self.ow + ox..][..L];
                store_vector(simd, cast(a), self.scale, self.shift, self.clamp, out);
            }
        }
    }
}
