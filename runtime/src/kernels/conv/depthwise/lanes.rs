//! Depthwise layers of small planes with the channels in the vector lanes (AVX-512).
//!
//! The row-vectorised path ([`super::Registers`]) puts a plane's pixels in the lanes: a
//! 7-pixel output row fills 7 of 16, each plane is copied (split by column phase at stride
//! 2) and set up on its own, and at stride 2 on 14x14 and 28x28 inputs that left
//! MobileNetV2's and EfficientNet-B0's layers at 3.8-4.8x ONNX Runtime's time, which keeps
//! its activations channel-blocked (NCHW16c). Here sixteen channels go through together:
//! their planes are transposed, sixteen pixels at a time (a 16x16 transpose in registers),
//! into one zero-bordered copy holding each pixel's sixteen channels as one vector; every
//! tap of every output pixel is then one load and one multiply-add with the taps of the
//! sixteen channels, whatever the stride and the row's width, and the sums, scaled,
//! shifted and activated in registers, are transposed back into the output planes.
//!
//! The transposes cost about what the row path's copy did (pulp's partial loads and stores
//! are calls, so the partial ones are masked intrinsics here); the multiply-adds fill
//! every lane. See [`MAX_OUT_PLANE`] for what was measured.

use core::arch::x86_64::__m512;

use pulp::x86::V4;
use pulp::{Simd, cast};
use rayon::prelude::*;

use crate::kernels::Epilogue;
use crate::kernels::conv::{Conv2dShape, clamp_vector};
use crate::kernels::elementwise;
use crate::kernels::layout::transpose16 as transpose;

use super::PADDED;

/// Channels a vector holds (AVX-512's f32 lanes).
const L: usize = 16;

/// Output pixels whose sums one block keeps in registers (`B` vectors). Eight took
/// 1.1-1.55x four's time on the layers measured below (one thread, 2026-12-06).
const B: usize = 4;

/// Taps of the largest kernel (7x7).
const MAX_TAPS: usize = 49;

/// The most output pixels per plane this path takes (28x28). On the AMD EPYC (Zen 4,
/// 2026-12-06; this path's time over the row path's, the two alternating call by call in
/// one process, 550 pairs, 1 / 2 threads, ReLU6 or SiLU after): at stride 2, 576
/// channels 14 to 7 0.30 / 0.30, 672 channels 5x5 14 to 7 0.32 / 0.34, 192 and 240
/// channels 28 to 14 0.45-0.56 / 0.49-0.63, 144 channels 56 to 28 0.69 / 0.68 (5x5 0.74
/// / 0.86-0.98); at stride 1, 7x7 planes 0.56-0.66 / 0.64-0.76 (960 channels; 1152 with
/// SiLU 0.76 / 0.88), 14x14 ones 0.73-0.81 / 0.77-0.85, 28x28 ones 0.76-0.78 with 5x5
/// kernels, 0.97-1.0 with 3x3. On 56x56 outputs the rows won (144 channels: 1.04 / 1.33),
/// and MobileNetV2's 112 to 56 layer's copy (208 Ki floats) is past [`MAX_COPY`].
const MAX_OUT_PLANE: usize = 28 * 28;

/// The largest zero-bordered copy of sixteen planes (floats) this path keeps per thread:
/// a 58x58 input (56x56 and its border, a stride-2 layer to 28x28).
const MAX_COPY: usize = 64 * 1024;

/// Whether a depthwise layer takes this path: AVX-512 at run time, one output channel per
/// input channel, a square kernel of 3, 5 or 7 at stride 1 or 2 without dilation, and an
/// output plane of at most [`MAX_OUT_PLANE`] pixels whose bordered input copy fits
/// [`MAX_COPY`].
/// (Of these, the 3x3 ones and the 5x5 ones at stride 2 with rows of 16 outputs or more,
/// padded by half the kernel, are read in place instead: `super::reads_in_place`.)
pub(super) fn applies(s: &Conv2dShape) -> bool {
    let side = |len: usize, pad: usize| len.saturating_add(pad.saturating_mul(2));
    let copy = side(s.h, s.pad_h).saturating_mul(side(s.w, s.pad_w)).saturating_mul(L);
    s.cin == s.groups
        && s.cout == s.cin
        && s.stride_h == s.stride_w
        && matches!(s.stride_w, 1 | 2)
        && (s.dil_h, s.dil_w) == (1, 1)
        && s.kh == s.kw
        && matches!(s.kh, 3 | 5 | 7)
        && s.oh.saturating_mul(s.ow) <= MAX_OUT_PLANE
        && copy <= MAX_COPY
        && V4::try_new().is_some()
}

/// The depthwise conv `x -> out` (`[n, c, h, w] -> [n, c, oh, ow]`, `w` PyTorch's `[c,
/// 1, k, k]`) with the epilogue, parallel over groups of sixteen channels of each image.
/// Only for layers [`applies`] takes.
pub(super) fn depthwise(s: &Conv2dShape, w: &[f32], ep: &Epilogue, x: &[f32], out: &mut [f32], threads: usize) {
    let simd = V4::try_new().expect("lanes::applies checks AVX-512");
    let plane = s.oh * s.ow;
    let groups = s.cout.div_ceil(L);
    // Tasks of one image's groups of channels: several groups a task (one dispatch and
    // one buffer a task), at least four tasks a thread.
    let per = (s.n * groups / (4 * threads.max(1))).clamp(1, 8);
    let (image, chunk) = (s.cout * plane, per * L * plane);
    // Task `t` of image `n`: channels from `t per L`.
    let run = |n: usize, t: usize, dst: &mut [f32]| {
        let c0 = t * per * L;
        let x = &x[(n * s.cin + c0) * s.h * s.w..];
        let task = Task { s, w: &w[c0 * s.kh * s.kw..], ep, x, c0, dst };
        // Compiled with AVX-512 enabled: everything `dispatch` calls is inlined into it.
        simd.vectorize(
            #[inline(always)]
            move || task.dispatch(simd),
        );
    };
    if threads <= 1 {
        for (n, im) in out.chunks_mut(image).enumerate() {
            im.chunks_mut(chunk).enumerate().for_each(|(t, dst)| run(n, t, dst));
        }
    } else {
        out.par_chunks_mut(image).enumerate().for_each(|(n, im)| {
            im.par_chunks_mut(chunk).enumerate().for_each(|(t, dst)| run(n, t, dst));
        });
    }
}

/// Channels `c0..` of one image, as many as `dst` holds planes: `x` and `w` start at
/// channel `c0`.
struct Task<'a> {
    s: &'a Conv2dShape,
    w: &'a [f32],
    ep: &'a Epilogue<'a>,
    x: &'a [f32],
    c0: usize,
    dst: &'a mut [f32],
}

impl Task<'_> {
    #[inline(always)]
    fn dispatch(self, simd: V4) {
        match (self.s.stride_w, self.s.kh) {
            (1, 3) => self.run::<1, 3>(simd),
            (1, 5) => self.run::<1, 5>(simd),
            (1, 7) => self.run::<1, 7>(simd),
            (2, 3) => self.run::<2, 3>(simd),
            (2, 5) => self.run::<2, 5>(simd),
            (2, 7) => self.run::<2, 7>(simd),
            _ => unreachable!("lanes::applies"),
        }
    }

    /// Every group of sixteen channels of the task: transposed in, each output row by
    /// blocks of [`B`] pixels, transposed out.
    #[inline(always)]
    fn run<const ST: usize, const K: usize>(self, simd: V4) {
        let Task { s, w, ep, x, c0, dst } = self;
        let (ph, pw) = (s.h + 2 * s.pad_h, s.w + 2 * s.pad_w);
        let plane = s.oh * s.ow;
        // The thread's buffer of the depthwise paths: the copy, then the block of outputs
        // (`plane` vectors), then sixteen vectors of slack the transpose back reads past
        // the block's last pixel. Not cleared: the copy is written whole (border too) for
        // each group, the block too but for the slack, whose lanes are never stored.
        let mut buf = PADDED.take();
        let need = ph * pw * L + (plane + L) * L;
        if buf.len() < need {
            buf.resize(need, 0.0);
        }
        let (copy, sums) = buf.split_at_mut(ph * pw * L);
        let clamp = ep.clamp();
        let in_registers = ep.vector_act::<V4>();
        for (g, dst) in dst.chunks_mut(L * plane).enumerate() {
            let nc = dst.len() / plane;
            let (ch, x) = (c0 + g * L, &x[g * L * s.h * s.w..]);
            transpose_in(simd, s, x, nc, copy);
            // Each tap's sixteen channels, then the epilogue's scale and shift.
            let mut taps = [simd.splat_f32s(0.0); MAX_TAPS];
            for (t, tap) in taps.iter_mut().enumerate().take(K * K) {
                let mut lane = [0.0f32; L];
                for (c, v) in lane.iter_mut().enumerate().take(nc) {
                    *v = w[(g * L + c) * K * K + t];
                }
                *tap = vector(&lane);
            }
            let (mut scale, mut shift) = ([1.0f32; L], [0.0f32; L]);
            for c in 0..nc {
                scale[c] = ep.scale.map_or(1.0, |v| v[ch + c]);
                shift[c] = ep.shift.map_or(0.0, |v| v[ch + c]);
            }
            let (scale, shift) = (vector(&scale), vector(&shift));
            let geo = Geometry { pw, ow: s.ow, scale, shift, clamp, in_registers };
            for oy in 0..s.oh {
                // Blocks of `B` pixels, the last one overlapping the one before it.
                let mut ox = 0;
                while ox < s.ow {
                    if s.ow >= B {
                        let at = ox.min(s.ow - B);
                        geo.block::<ST, K, B>(simd, copy, &taps, oy, at, sums);
                        ox = at + B;
                    } else {
                        geo.block::<ST, K, 1>(simd, copy, &taps, oy, ox, sums);
                        ox += 1;
                    }
                }
            }
            transpose_out(simd, sums, plane, nc, dst);
            // Another activation than a clamp or one computed on the sums (hardswish).
            if in_registers.is_none() {
                ep.finish_unclamped(dst);
            }
        }
        PADDED.set(buf);
    }
}

/// What every block of one group of channels shares.
struct Geometry {
    /// Columns of the bordered copy.
    pw: usize,
    ow: usize,
    scale: pulp::f32x16,
    shift: pulp::f32x16,
    clamp: Option<(f32, f32)>,
    in_registers: Option<crate::kernels::Activation>,
}

impl Geometry {
    /// Output pixels `ox0..ox0 + R` of row `oy`: every tap a load of the copy and a
    /// multiply-add, then `act(sum · scale + shift)` into the block of outputs.
    #[inline(always)]
    fn block<const ST: usize, const K: usize, const R: usize>(
        &self,
        simd: V4,
        copy: &[f32],
        taps: &[pulp::f32x16; MAX_TAPS],
        oy: usize,
        ox0: usize,
        sums: &mut [f32],
    ) {
        let pw = self.pw;
        // The farthest vector the block reads: row ST oy + K - 1, column ST (ox0 + R - 1)
        // + K - 1.
        let last = ((ST * oy + K - 1) * pw + ST * (ox0 + R - 1) + K - 1) * L;
        assert!(last + L <= copy.len(), "depthwise lanes: a block reads past the copy");
        let base = copy.as_ptr();
        let mut acc = [simd.splat_f32s(0.0); R];
        for ky in 0..K {
            for kx in 0..K {
                let tap = taps[ky * K + kx];
                for (r, a) in acc.iter_mut().enumerate() {
                    let at = ((ST * oy + ky) * pw + ST * (ox0 + r) + kx) * L;
                    // SAFETY: `at + L <= last + L <= copy.len()` (asserted above: `ky, kx
                    // < K`, `r < R`).
                    #[allow(unsafe_code)]
                    let v = unsafe { base.add(at).cast::<pulp::f32x16>().read_unaligned() };
                    *a = simd.mul_add_f32s(v, tap, *a);
                }
            }
        }
        let mut z = acc;
        for v in z.iter_mut() {
            // Multiplied, then added, as the row path's store does.
            *v = simd.add_f32s(simd.mul_f32s(*v, self.scale), self.shift);
            if let Some(cl) = self.clamp {
                *v = clamp_vector(simd, *v, cl);
            }
        }
        if let Some(act) = self.in_registers {
            z = elementwise::act_simd(simd, act, z);
        }
        for (r, v) in z.into_iter().enumerate() {
            let at = (oy * self.ow + ox0 + r) * L;
            V4::as_mut_simd_f32s(&mut sums[at..at + L]).0[0] = v;
        }
    }
}

/// Copies `nc` (at most sixteen) planes of `x` (`[nc, h, w]`) into `copy`, the bordered
/// `[h + 2 pad_h][w + 2 pad_w][16]`: pixel by pixel the sixteen channels as one vector
/// (lanes past `nc` zero), by 16x16 transposes of sixteen pixels of a row. The border
/// is written zero too.
#[inline(always)]
fn transpose_in(simd: V4, s: &Conv2dShape, x: &[f32], nc: usize, copy: &mut [f32]) {
    let pw = s.w + 2 * s.pad_w;
    let plane = s.h * s.w;
    let zero = simd.splat_f32s(0.0);
    // The border rows, and the border columns of the rows between.
    let (top, bottom) = (s.pad_h * pw * L, (s.pad_h + s.h) * pw * L);
    copy[..top].fill(0.0);
    copy[bottom..].fill(0.0);
    for iy in 0..s.h {
        let row = &mut copy[(iy + s.pad_h) * pw * L..][..pw * L];
        row[..s.pad_w * L].fill(0.0);
        row[(s.pad_w + s.w) * L..].fill(0.0);
        let mut ix = 0;
        while ix < s.w {
            let cols = L.min(s.w - ix);
            let mut rows: [__m512; L] = [cast(zero); L];
            for (c, r) in rows.iter_mut().enumerate().take(nc) {
                *r = load_first(simd, &x[c * plane + iy * s.w + ix..][..cols]);
            }
            let t = transpose(simd, rows);
            for (j, v) in t.into_iter().take(cols).enumerate() {
                let at = (s.pad_w + ix + j) * L;
                V4::as_mut_simd_f32s(&mut row[at..at + L]).0[0] = cast(v);
            }
            ix += cols;
        }
    }
}

/// Writes the block of outputs `sums` (`[plane][16]`) into `nc` output planes of `dst`:
/// sixteen pixels at a time, transposed.
#[inline(always)]
fn transpose_out(simd: V4, sums: &[f32], plane: usize, nc: usize, dst: &mut [f32]) {
    let mut p = 0;
    while p < plane {
        let cols = L.min(plane - p);
        // Pixels past the plane read the slack after the block (never stored).
        let mut rows: [__m512; L] = [cast(simd.splat_f32s(0.0)); L];
        for (j, r) in rows.iter_mut().enumerate() {
            *r = cast(vector(&sums[(p + j) * L..][..L]));
        }
        let t = transpose(simd, rows);
        for (c, v) in t.into_iter().take(nc).enumerate() {
            store_first(simd, &mut dst[c * plane + p..][..cols], v);
        }
        p += cols;
    }
}

/// The sixteen floats of `a` (at least sixteen) as one vector.
#[inline(always)]
fn vector(a: &[f32]) -> pulp::f32x16 {
    V4::as_simd_f32s(&a[..L]).0[0]
}

/// `a` (at most sixteen floats) in the first lanes of a vector, zero after: a masked load
/// (pulp's partial loads are calls).
#[inline(always)]
fn load_first(simd: V4, a: &[f32]) -> __m512 {
    let n = a.len().min(L);
    let mask = ((1u32 << n) - 1) as u16;
    // SAFETY: the masked load reads only the lanes of `mask`, the first `n <= a.len()`
    // floats of `a`; masked-off lanes do not fault.
    #[allow(unsafe_code)]
    unsafe {
        simd.avx512f._mm512_maskz_loadu_ps(mask, a.as_ptr())
    }
}

/// Stores the first `out.len()` (at most sixteen) lanes of `v` into `out`: a masked store.
#[inline(always)]
fn store_first(simd: V4, out: &mut [f32], v: __m512) {
    let n = out.len().min(L);
    let mask = ((1u32 << n) - 1) as u16;
    // SAFETY: the masked store writes only the lanes of `mask`, the first `n <= out.len()`
    // floats of `out`.
    #[allow(unsafe_code)]
    unsafe {
        simd.avx512f._mm512_mask_storeu_ps(out.as_mut_ptr(), mask, v)
    }
}
