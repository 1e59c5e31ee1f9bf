//! [`ConvAlgo::Depthwise`](super::ConvAlgo::Depthwise), one input channel per group: a
//! direct loop per output plane with the epilogue, parallel over groups of planes; no
//! GEMM, no scratch but a zero-padded copy of the plane each thread keeps. Square 3x3,
//! 5x5 and 7x7 kernels at stride 1 and 2 (MobileNet's, EfficientNet's, ConvNeXt's) run
//! in SIMD registers: with AVX-512, on output planes of at most 28x28, sixteen channels
//! at a time in the lanes (`lanes.rs`), and with rows of at least 16 outputs by rows read
//! in place (`in_place.rs`: 3x3, 5x5 and 7x7 at stride 1 and 3x3 and 5x5 at stride 2,
//! padding half the kernel; at stride 1 the 5x5 and 7x7 ones only on planes the lanes do
//! not take); else by rows of a padded copy (`Registers`), or at stride 1 on planes with
//! rows of at most 8 pixels (7x7) by the plane read flat (`flat.rs`); the rest through
//! the loops of `depthwise_acc`.

use rayon::prelude::*;

mod flat;
#[cfg(target_arch = "x86_64")]
mod in_place;
#[cfg(target_arch = "x86_64")]
mod lanes;

use super::{Conv2dShape, pad_interior, pad_phases, store_vector, vector_starts};
use crate::kernels::Epilogue;
use crate::kernels::elementwise::relu;

/// Direct conv for one input channel per group, parallel over groups of output planes.
pub(super) fn depthwise(s: &Conv2dShape, w: &[f32], ep: &Epilogue, x: &[f32], out: &mut [f32], threads: usize) {
    let plane = s.oh * s.ow;
    if plane == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    let in_place = reads_in_place(s);
    #[cfg(target_arch = "x86_64")]
    if !in_place && lanes::applies(s) {
        return lanes::depthwise(s, w, ep, x, out, threads);
    }
    // Planes per task: several, so that a task's setup (a SIMD dispatch, zeroing the
    // padded copy) is shared by them (MobileNetV2's 7x7 planes took about as long to set
    // up as to compute), and at least four tasks per thread.
    let per = (s.n * s.cout / (4 * threads.max(1))).clamp(1, 64);
    let flat = flat::applies(s);
    let registers = Registers::applies(s);
    let group = |(i, dst): (usize, &mut [f32])| {
        #[cfg(target_arch = "x86_64")]
        if in_place {
            return in_place::planes(s, w, ep, x, i * per, dst);
        }
        if flat {
            pulp::Arch::new().dispatch(flat::Flat { s, w, x, ep, first: i * per, dst });
        } else if registers {
            pulp::Arch::new().dispatch(Registers { s, w, x, ep, first: i * per, dst });
        } else {
            for (j, dst) in dst.chunks_mut(plane).enumerate() {
                let (xc, k, c) = plane_operands(s, w, x, i * per + j);
                depthwise_loops(s, xc, k, c, ep, dst);
            }
        }
    };
    if threads <= 1 {
        out.chunks_mut(per * plane).enumerate().for_each(group);
    } else {
        out.par_chunks_mut(per * plane).enumerate().for_each(group);
    }
}

/// Whether a layer takes the flat path (`flat.rs`), for the tests.
#[cfg(test)]
pub(super) fn flat_applies(s: &Conv2dShape) -> bool {
    flat::applies(s)
}

/// Whether a layer is read in place (`in_place.rs`): every layer that path takes but the
/// 5x5 and 7x7 ones at stride 1 on planes the lanes path takes too. In the models (per
/// step, one / two threads, the two paths alternating run by run, 2026-12-06), reading in
/// place took of the lanes path's time: MobileNetV2's 3x3 layers with 28x28 outputs 0.58
/// (144 channels, 56 to 28) and 0.85-0.90 (192 channels, stride 1); the 5x5 56 to 28
/// layers 0.68 / 0.52 (MobileNetV3, 72 channels) and 0.82 / 0.70 (EfficientNet-B0, 144);
/// MobileNetV3's 5x5 stride-1 layers at 28x28 1.07 (there the lanes path reads each of 25
/// taps as one vector of sixteen channels, where this one shuffles none).
#[cfg(target_arch = "x86_64")]
fn reads_in_place(s: &Conv2dShape) -> bool {
    in_place::applies(s) && (s.kh == 3 || s.stride_w == 2 || !lanes::applies(s))
}

/// Whether a layer takes the channels-in-lanes path (`lanes.rs`) on this machine, for
/// the tests.
#[cfg(test)]
pub(super) fn lanes_applies(s: &Conv2dShape) -> bool {
    #[cfg(target_arch = "x86_64")]
    return !reads_in_place(s) && lanes::applies(s);
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

/// Whether a layer takes the read-in-place path (`in_place.rs`) on this machine, for the
/// tests.
#[cfg(test)]
pub(super) fn in_place_applies(s: &Conv2dShape) -> bool {
    #[cfg(target_arch = "x86_64")]
    return reads_in_place(s);
    #[cfg(not(target_arch = "x86_64"))]
    return false;
}

/// Output plane `idx` (image `idx / cout`, channel `idx % cout`): its input plane, its
/// kernel and its channel.
#[inline(always)]
fn plane_operands<'a>(s: &Conv2dShape, w: &'a [f32], x: &'a [f32], idx: usize) -> (&'a [f32], &'a [f32], usize) {
    let (n, c) = (idx / s.cout, idx % s.cout);
    let g = c / s.cout_g();
    (&x[(n * s.cin + g) * s.h * s.w..][..s.h * s.w], &w[c * s.kh * s.kw..][..s.kh * s.kw], c)
}

/// The depthwise conv of a group of planes at stride 1 or 2, no dilation, square kernels
/// of 3, 5 or 7, on a zero-padded copy of each input plane (at stride 2 split into its
/// even and odd columns, so that a row's taps are contiguous loads): [`ROWS`] output rows
/// at a time in SIMD vectors (the last vector of a row overlapping the one before it),
/// each output row's taps as straight fused multiply-adds (the kernel size and stride
/// known at compile time), the sums kept in registers, the epilogue's scale, shift and
/// clamp (ReLU, ReLU6) applied as they are stored.
///
/// A row narrower than a vector (7x7 and 14x14 planes) is stored a whole vector wide
/// while the plane has room past it (the rows stored after it overwrite the extra
/// lanes), through the stack only for its last rows. With that and ReLU6 applied in the
/// store instead of a pass over each plane, MobileNetV2's 14x14 and 7x7 layers took
/// 0.66-0.76x as long on one thread; at stride 2, its 28 to 14 and 14 to 7 layers 0.8x,
/// EfficientNet-B0's 5x5 ones 0.4-0.5x (they were in the loops).
///
/// What it replaced (still the path for other strides, dilation and other kernels:
/// [`depthwise_loops`]) kept one output row per tap in a lane array and reloaded the input
/// row for every output row it reaches, and set each plane up on its own: on one thread
/// MobileNetV2's 144-channel 56x56 layer went from 822 to 271 us, ConvNeXt-T's 96-channel
/// 7x7 from 1676 to 488 us, 960 channels at 7x7 from 328 to 116 us.
struct Registers<'a> {
    s: &'a Conv2dShape,
    w: &'a [f32],
    x: &'a [f32],
    ep: &'a Epilogue<'a>,
    /// The index of the first of `dst`'s planes.
    first: usize,
    dst: &'a mut [f32],
}

impl Registers<'_> {
    /// Square 3x3, 5x5 or 7x7 kernels at stride 1 or 2, no dilation, a padded plane that
    /// fits [`MAX_PADDED`]. (Strided 3x3 layers with rows wider than 16 outputs went to the
    /// loops, which read the input in place, until the block's taps were unrolled: since
    /// then the copy split by column phase takes MobileNetV2's 56 to 28 layer in 0.60-0.66x
    /// the loops' time, its 112 to 56 one in 0.83-0.90x, at 1 and 2 threads.)
    fn applies(s: &Conv2dShape) -> bool {
        let padded = (s.h + 2 * s.pad_h) * (s.w + 2 * s.pad_w + 1);
        s.stride_h == s.stride_w
            && matches!(s.stride_w, 1 | 2)
            && (s.dil_h, s.dil_w) == (1, 1)
            && s.kh == s.kw
            && matches!(s.kh, 3 | 5 | 7)
            && padded <= MAX_PADDED
    }
}

impl pulp::WithSimd for Registers<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        match (self.s.stride_w, self.s.kh) {
            (1, 3) => self.planes::<S, 1, 3>(simd),
            (1, 5) => self.planes::<S, 1, 5>(simd),
            (1, 7) => self.planes::<S, 1, 7>(simd),
            (2, 3) => self.planes::<S, 2, 3>(simd),
            (2, 5) => self.planes::<S, 2, 5>(simd),
            (2, 7) => self.planes::<S, 2, 7>(simd),
            _ => unreachable!("Registers::applies"),
        }
    }
}

impl Registers<'_> {
    /// Every plane of `dst`, through one padded copy (at stride 2 split into its even and
    /// odd columns, [`pad_phases`]): zeroed once, its interior rewritten for each plane
    /// (the border stays zero).
    #[inline(always)]
    fn planes<S: pulp::Simd, const ST: usize, const K: usize>(self, simd: S) {
        let Registers { s, w, x, ep, first, dst } = self;
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let mut buf = PADDED.take();
        let (rows, cols) = (s.h + 2 * s.pad_h, (s.w + 2 * s.pad_w).div_ceil(ST));
        buf.clear();
        // One vector of slack: a row narrower than a vector is read a whole vector wide
        // (the lanes past the row, the next row's or the slack's, are never stored).
        buf.resize(ST * rows * cols + lanes, 0.0);
        let clamp = ep.clamp();
        for (j, dst) in dst.chunks_mut(s.oh * s.ow).enumerate() {
            let (xc, k, c) = plane_operands(s, w, x, first + j);
            pad_phases(s, xc, rows, cols, &mut buf);
            let taps: [[f32; K]; K] = std::array::from_fn(|ky| std::array::from_fn(|kx| k[ky * K + kx]));
            let scale = ep.scale.map_or(1.0, |v| v[c]);
            let shift = ep.shift.map_or(0.0, |v| v[c]);
            let g = Geometry { rows, cols, ow: s.ow, scale, shift, clamp };
            // 5x5 and 7x7 kernels at stride 1 on planes of at least 16 rows: blocks of
            // eight rows first, more sums in flight for taps that stay in registers
            // anyway: 0.89-0.99x the time on EfficientNet-B0's and MobileNetV3's 5x5
            // layers at 28x28 and 56x56, 0.98-0.99x on ConvNeXt's 7x7 (alternating
            // calls in one process, 1 and 2 threads, 2026-12-06); on 14x14 planes
            // 0.97-1.10x, and 3x3 kernels or stride 2 ran slower (2026-12-05).
            let mut start = 0;
            if ST == 1 && K >= 5 && s.oh >= 16 {
                while start + 8 <= s.oh {
                    g.rows::<S, 8, K, ST>(simd, &buf, &taps, start, dst);
                    start += 8;
                }
            }
            let full = start + (s.oh - start) / ROWS * ROWS;
            for oy in (start..full).step_by(ROWS) {
                g.rows::<S, ROWS, K, ST>(simd, &buf, &taps, oy, dst);
            }
            // The rows left after the whole blocks: one at a time, or when there are
            // `ROWS - 1` of them, as one more block over the last `ROWS` rows (its first
            // row again, the same values): a 7-row output (14 to 7 at stride 2) took
            // 0.89-0.95x the time (in-process A/B, 1 and 2 threads); fewer rows left
            // run better one by one (two of 14: 1.03x as a block).
            if (s.oh - start) % ROWS == ROWS - 1 && s.oh >= ROWS {
                g.rows::<S, ROWS, K, ST>(simd, &buf, &taps, s.oh - ROWS, dst);
            } else {
                for oy in full..s.oh {
                    g.rows::<S, 1, K, ST>(simd, &buf, &taps, oy, dst);
                }
            }
            ep.finish_unclamped(dst);
        }
        PADDED.set(buf);
    }
}

/// What [`Registers`] works with: the padded plane's rows and columns (a phase's at
/// stride 2), the output row's, and the epilogue's affine and clamp.
#[derive(Clone, Copy)]
struct Geometry {
    rows: usize,
    cols: usize,
    ow: usize,
    scale: f32,
    shift: f32,
    clamp: Option<(f32, f32)>,
}

impl Geometry {
    /// [`Geometry::block`], compiled apart for blocks whose last store fits the plane
    /// (rows of at least a vector, or narrower rows stored a vector wide into the rows
    /// after them): there every [`store_vector`] is a whole vector, and the partial store's
    /// `memcpy` call, around which LLVM had spilled the block's loaded rows on every
    /// vector, drops out. 0.82-0.93x the time on MobileNetV2's depthwise layers on 56x56,
    /// 28x28 and 14x14 planes with ReLU, 0.84-0.89x on EfficientNet-B0's 14x14 ones,
    /// 0.91-0.98x with SiLU (its pass after the conv unchanged); 7-pixel rows unchanged
    /// (in-process A/B, 1 and 2 threads, 2026-12-06; those figures with the clamp's bounds
    /// splatted once in a copy of `store_vector`, which `store_vector` itself, its clamp a
    /// branch per vector, runs within 1.00-1.03x of).
    #[inline(always)]
    fn rows<S: pulp::Simd, const R: usize, const K: usize, const ST: usize>(
        self,
        simd: S,
        padded: &[f32],
        taps: &[[f32; K]; K],
        oy0: usize,
        dst: &mut [f32],
    ) {
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let last = (oy0 + R - 1) * self.ow + self.ow.saturating_sub(lanes) + lanes;
        if last <= dst.len() {
            self.block::<S, R, K, ST, true>(simd, padded, taps, oy0, dst)
        } else {
            self.block::<S, R, K, ST, false>(simd, padded, taps, oy0, dst)
        }
    }

    /// Output rows `oy0..oy0 + R` of the plane `dst`, vector by vector along the row, at
    /// stride `ST`. A row narrower than a vector is stored a whole vector wide where the
    /// plane has room past it: the rows stored after it overwrite the extra lanes. With
    /// `WHOLE` (the block's last store fits the plane, [`Geometry::rows`]) every store is
    /// a whole vector.
    #[inline(always)]
    fn block<S: pulp::Simd, const R: usize, const K: usize, const ST: usize, const WHOLE: bool>(
        self,
        simd: S,
        padded: &[f32],
        taps: &[[f32; K]; K],
        oy0: usize,
        dst: &mut [f32],
    ) {
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let ow = self.ow;
        let (scale, shift) = (simd.splat_f32s(self.scale), simd.splat_f32s(self.shift));
        let width = lanes.min(ow);
        // The farthest vector the block reads: the last phase's last row of the block
        // (ST (R - 1) + K rows from row ST oy0), from the last vector start plus the
        // widest tap's column.
        let last_row = (ST - 1) * self.rows + ST * oy0 + ST * (R - 1) + K - 1;
        let end = last_row * self.cols + (ow - width) + (K - 1) / ST + lanes;
        assert!(end <= padded.len(), "depthwise: block reads past the padded plane");
        let base = padded.as_ptr();
        for ox in vector_starts(ow, width) {
            let mut acc = [simd.splat_f32s(0.0); R];
            // Output row r reads block rows ST r + ky. Every bound is a constant, so the
            // loops unroll into straight multiply-adds, each with its load folded in and
            // the taps held in registers where they fit. Before, a loop over the block's
            // rows (each loaded once, tested for the output rows it reaches) stayed a
            // loop: LLVM kept the tests and a bounds check around every tap, about six
            // instructions per multiply-add (`perf annotate`, 5x5 at stride 2). Unrolled
            // and read unchecked: 0.62-0.91x the time on MobileNetV2's and
            // EfficientNet-B0's depthwise shapes at 1 and 2 threads (old and new block in
            // alternating calls in one process, 2026-12-05).
            for (ky, row_taps) in taps.iter().enumerate() {
                for (r, a) in acc.iter_mut().enumerate() {
                    let j = ST * r + ky;
                    for (kx, &tap) in row_taps.iter().enumerate() {
                        // Padded column ST ox + kx: column ox + kx / ST of phase kx % ST.
                        let at = ((kx % ST) * self.rows + ST * oy0 + j) * self.cols + ox + kx / ST;
                        // SAFETY: `at + lanes <= end <= padded.len()` (asserted above:
                        // `j <= ST (R - 1) + K - 1`, `ox <= ow - width`).
                        #[allow(unsafe_code)]
                        let v = unsafe { base.add(at).cast::<S::f32s>().read_unaligned() };
                        *a = simd.mul_add_f32s(v, simd.splat_f32s(tap), *a);
                    }
                }
            }
            for (r, a) in acc.into_iter().enumerate() {
                let at = (oy0 + r) * ow + ox;
                // A whole vector where the block fits (the slice's length is then known,
                // and the partial store's copy drops out), else up to the plane's end.
                let room = if WHOLE {
                    lanes
                } else if width < lanes {
                    (dst.len() - at).min(lanes)
                } else {
                    width
                };
                store_vector(simd, a, scale, shift, self.clamp, &mut dst[at..][..room]);
            }
        }
    }
}

simd_fn! {
    /// One output plane (channel `c`) of a depthwise conv with the epilogue, by the loops
    /// of [`depthwise_acc`], for what [`Registers`] does not take (dilation, other
    /// strides, non-square kernels, planes too large to copy).
    fn depthwise_loops(s: &Conv2dShape, xc: &[f32], k: &[f32], c: usize, ep: &Epilogue<'_>, dst: &mut [f32]) {
        depthwise_acc(s, xc, k, dst);
        let acc_scale = ep.scale.map_or(1.0, |v| v[c]);
        let shift = ep.shift.map_or(0.0, |v| v[c]);
        if ep.relu() {
            dst.iter_mut().for_each(|d| *d = relu(*d * acc_scale + shift));
        } else {
            dst.iter_mut().for_each(|d| *d = *d * acc_scale + shift);
        }
        ep.finish_act(dst);
    }
}

/// The kernel rows the register-blocked path holds at once (ConvNeXt's 7x7 needs 7).
const MAX_TAP_ROWS: usize = 16;

/// The accumulation of a depthwise conv plane into `dst`.
///
/// At column stride 1, a plane whose zero-padded copy fits [`MAX_PADDED`] is copied so
/// (into a buffer each thread keeps) and accumulated by [`padded_rows`]: no border columns,
/// four output rows at a time. On ConvNeXt-T (7x7: three border columns of 49 scalar taps
/// each side of a 56-column row) the whole model ran 0.83x as long, on MobileNetV2 0.94x
/// (alternating runs against the border path, 2 threads); both now take [`Registers`],
/// which leaves this path the stride-1 kernels it does not (dilated, not square).
///
/// Otherwise (larger planes, other strides): the columns whose taps all fall
/// inside the input row (the interior) go in blocks of 16, 8 or 4 (the widest that fits the
/// interior: 56x56 planes take 16, 14x14 take 8, 7x7 take 4) with the sum kept in registers
/// and each output written once, the last block overlapping the one before it instead of a
/// scalar remainder; the border columns go one by one. Strides 1 and 2 get their own copy
/// of the loops, so the interior's loads are contiguous (stride 1) or a fixed de-interleave
/// (stride 2). Narrower interiors and kernels taller than [`MAX_TAP_ROWS`] add one tap at a
/// time over the whole row.
#[inline(always)]
fn depthwise_acc(s: &Conv2dShape, xc: &[f32], k: &[f32], dst: &mut [f32]) {
    let padded = (s.h + 2 * s.pad_h) * (s.w + 2 * s.pad_w);
    // Stride 1 only: for stride 2 (the de-interleaved loads) the copy measured no faster
    // than the border path below.
    if padded <= MAX_PADDED && s.stride_w == 1 {
        // Taken out of the thread-local and put back, not borrowed in a closure: a
        // closure would not inherit the SIMD target features `depthwise_plane` runs with.
        let mut buf = PADDED.take();
        pad_plane(s, xc, &mut buf);
        match s.ow {
            16.. => padded_rows::<16>(s, &buf, k, dst),
            8.. => padded_rows::<8>(s, &buf, k, dst),
            4.. => padded_rows::<4>(s, &buf, k, dst),
            _ => padded_rows::<1>(s, &buf, k, dst),
        }
        PADDED.set(buf);
        return;
    }
    match s.stride_w {
        1 => depthwise_blocks(s, xc, k, dst, 1),
        2 => depthwise_blocks(s, xc, k, dst, 2),
        stride => depthwise_blocks(s, xc, k, dst, stride),
    }
}

#[inline(always)]
fn depthwise_blocks(s: &Conv2dShape, xc: &[f32], k: &[f32], dst: &mut [f32], stride: usize) {
    let (pad, dil) = (s.pad_w, s.dil_w);
    // Interior columns: ox * stride >= pad and ox * stride + (kw - 1) * dil - pad < w.
    let reach = (s.kw - 1) * dil;
    let hi = if s.w + pad > reach { ((s.w + pad - reach - 1) / stride + 1).min(s.ow) } else { 0 };
    let lo = pad.div_ceil(stride).min(hi);
    match hi - lo {
        _ if s.kh > MAX_TAP_ROWS => depthwise_taps(s, xc, k, dst, stride),
        16.. => depthwise_rows::<16>(s, xc, k, dst, stride, lo, hi),
        8.. => depthwise_rows::<8>(s, xc, k, dst, stride, lo, hi),
        4.. => depthwise_rows::<4>(s, xc, k, dst, stride, lo, hi),
        _ => depthwise_taps(s, xc, k, dst, stride),
    }
}

/// Floats of the largest zero-padded input plane [`depthwise_acc`] copies a plane into
/// (64 KiB, in L2: MobileNet's 112x112 planes fit, a BEV grid's do not).
const MAX_PADDED: usize = 16 * 1024;

thread_local! {
    /// Each thread's zero-padded copy of the plane it is on: the buffer of every
    /// depthwise path (the rows', the flat one's, the lanes'), one at a time a thread.
    static PADDED: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Copies input plane `xc` into `buf` with `pad` zeros around it: `(h + 2 pad_h) x (w +
/// 2 pad_w)`, row-major. Every tap of every output then lies inside the copy.
#[inline(always)]
fn pad_plane(s: &Conv2dShape, xc: &[f32], buf: &mut Vec<f32>) {
    let pw = s.w + 2 * s.pad_w;
    buf.clear();
    buf.resize((s.h + 2 * s.pad_h) * pw, 0.0);
    pad_interior(s, xc, pw, buf);
}

/// The accumulation over a zero-padded plane (`pad_plane`): [`ROWS`] output rows at a
/// time (then one at a time for the rest), in blocks of `L` columns (the last block
/// overlapping the one before it; `ow` is at least `L`) that keep their sums in registers
/// over all `kh x kw` taps and are written once. No border case: the padding supplies the
/// zeros. Column stride 1.
#[inline(always)]
fn padded_rows<const L: usize>(s: &Conv2dShape, p: &[f32], k: &[f32], dst: &mut [f32]) {
    let full = s.oh / ROWS * ROWS;
    let (top, rest) = dst.split_at_mut(full * s.ow);
    for (i, rows) in top.chunks_exact_mut(ROWS * s.ow).enumerate() {
        padded_block::<L, ROWS>(s, p, k, rows, i * ROWS);
    }
    for (i, row) in rest.chunks_exact_mut(s.ow).enumerate() {
        padded_block::<L, 1>(s, p, k, row, full + i);
    }
}

/// Output rows to accumulate at once: independent sums, so that a block's adds do not wait
/// on each other (a single one would be bound by the add latency, four cycles a tap).
const ROWS: usize = 4;

/// Output rows `oy0..oy0 + R` (`dst`, `R` rows of `ow`) of [`padded_rows`].
#[inline(always)]
fn padded_block<const L: usize, const R: usize>(s: &Conv2dShape, p: &[f32], k: &[f32], dst: &mut [f32], oy0: usize) {
    let pw = s.w + 2 * s.pad_w;
    let (kw, dil_w) = (s.kw, s.dil_w);
    let mut ox = 0;
    loop {
        let mut acc = [[0.0f32; L]; R];
        for ky in 0..s.kh {
            for (kx, &wv) in k[ky * kw..][..kw].iter().enumerate() {
                for (r, acc) in acc.iter_mut().enumerate() {
                    let iy = (oy0 + r) * s.stride_h + ky * s.dil_h;
                    let seg = &p[iy * pw + ox + kx * dil_w..][..L];
                    for (a, &v) in acc.iter_mut().zip(seg) {
                        *a += wv * v;
                    }
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            dst[r * s.ow + ox..][..L].copy_from_slice(acc);
        }
        if ox + L >= s.ow {
            break;
        }
        ox = (ox + L).min(s.ow - L);
    }
}

/// [`depthwise_acc`] with interior blocks of `L` columns over `lo..hi` (at least `L` wide).
#[inline(always)]
fn depthwise_rows<const L: usize>(
    s: &Conv2dShape,
    xc: &[f32],
    k: &[f32],
    dst: &mut [f32],
    stride: usize,
    lo: usize,
    hi: usize,
) {
    let (pad, dil, kw) = (s.pad_w, s.dil_w, s.kw);
    let span = (L - 1) * stride + 1;
    let input_row = |iy: isize| (iy >= 0 && iy < s.h as isize).then(|| &xc[iy as usize * s.w..][..s.w]);
    for (oy, row) in dst.chunks_mut(s.ow).enumerate() {
        let iy0 = (oy * s.stride_h) as isize - s.pad_h as isize;
        // The input rows of this output row's taps, with their kernel rows.
        let mut rows: [(&[f32], usize); MAX_TAP_ROWS] = [(&[], 0); MAX_TAP_ROWS];
        let mut taps = 0;
        for ky in 0..s.kh {
            if let Some(src) = input_row(iy0 + (ky * s.dil_h) as isize) {
                rows[taps] = (src, ky * kw);
                taps += 1;
            }
        }
        let rows = &rows[..taps];
        // A border column, its taps checked one by one.
        let one = |ox: usize| {
            let mut acc = 0.0f32;
            for &(src, k0) in rows {
                for kx in 0..kw {
                    let ix = (ox * stride + kx * dil) as isize - pad as isize;
                    if ix >= 0 && (ix as usize) < s.w {
                        acc += k[k0 + kx] * src[ix as usize];
                    }
                }
            }
            acc
        };
        for (ox, d) in row.iter_mut().enumerate().take(lo) {
            *d = one(ox);
        }
        for (ox, d) in row.iter_mut().enumerate().skip(hi) {
            *d = one(ox);
        }
        let mut ox = lo;
        loop {
            let mut acc = [0.0f32; L];
            let x0 = ox * stride - pad;
            for &(src, k0) in rows {
                for (kx, &wv) in k[k0..k0 + kw].iter().enumerate() {
                    let seg = &src[x0 + kx * dil..][..span];
                    for (i, a) in acc.iter_mut().enumerate() {
                        *a += wv * seg[i * stride];
                    }
                }
            }
            row[ox..ox + L].copy_from_slice(&acc);
            if ox + L == hi {
                break;
            }
            ox = (ox + L).min(hi - L);
        }
    }
}

/// The accumulation one tap at a time over each output row: for planes too narrow for
/// [`depthwise_rows`]'s blocks.
#[inline(always)]
fn depthwise_taps(s: &Conv2dShape, xc: &[f32], k: &[f32], dst: &mut [f32], stride: usize) {
    dst.fill(0.0);
    let (h, w) = (s.h as isize, s.w as isize);
    for (oy, row) in dst.chunks_mut(s.ow).enumerate() {
        for ky in 0..s.kh {
            let iy = (oy * s.stride_h + ky * s.dil_h) as isize - s.pad_h as isize;
            if iy < 0 || iy >= h {
                continue;
            }
            let src = &xc[iy as usize * s.w..][..s.w];
            for kx in 0..s.kw {
                let wv = k[ky * s.kw + kx];
                let dx = (kx * s.dil_w) as isize - s.pad_w as isize;
                let ox_lo = ((-dx).max(0) as usize).div_ceil(stride).min(s.ow);
                let ox_hi = if w - dx <= 0 { 0 } else { ((w - dx) as usize).div_ceil(stride).min(s.ow) };
                if ox_lo >= ox_hi {
                    continue;
                }
                let ix0 = ((ox_lo * stride) as isize + dx) as usize;
                let body = &mut row[ox_lo..ox_hi];
                if stride == 1 {
                    for (d, &v) in body.iter_mut().zip(&src[ix0..]) {
                        *d += wv * v;
                    }
                } else {
                    for (d, &v) in body.iter_mut().zip(src[ix0..].iter().step_by(stride)) {
                        *d += wv * v;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};
    use crate::kernels::{Activation, Epilogue};

    /// A NaN in the input stays NaN in the outputs it reaches through the clamped stores
    /// (rows of a vector and more, and narrower rows stored a vector wide) on every SIMD
    /// width, with and without a ReLU; the others stay finite.
    #[test]
    fn a_nan_reaches_the_outputs_it_touches() {
        for (hw, k) in [(20, 3), (14, 5)] {
            let s = Conv2dShape::square(1, 1, hw, 1, k, 1, k / 2, 1);
            assert!(Registers::applies(&s));
            let mut x = data(hw * hw, 1);
            let (cy, cx) = (hw / 2, hw / 2);
            x[cy * hw + cx] = f32::NAN;
            let w = data(k * k, 2);
            for act in [None, Some(Activation::Relu)] {
                let ep = Epilogue { scale: None, shift: None, act };
                for b in backends() {
                    let mut got = vec![0.0; hw * hw];
                    b.run(Registers { s: &s, w: &w, x: &x, ep: &ep, first: 0, dst: &mut got });
                    for (i, v) in got.iter().enumerate() {
                        let (y, x) = (i / hw, i % hw);
                        let reached = y.abs_diff(cy) <= k / 2 && x.abs_diff(cx) <= k / 2;
                        assert_eq!(v.is_nan(), reached, "{b:?} {act:?} {hw}x{hw} k{k}: ({y}, {x}) = {v}");
                    }
                }
            }
        }
    }

    /// Every output plane of `s` by the loops of `depthwise_loops`: what the register
    /// paths are checked against.
    fn by_the_loops(s: &Conv2dShape, x: &[f32], w: &[f32], ep: &Epilogue) -> Vec<f32> {
        let plane = s.oh * s.ow;
        let mut want = vec![f32::NAN; s.n * s.cout * plane];
        for (i, dst) in want.chunks_mut(plane).enumerate() {
            let (xc, kc, c) = plane_operands(s, w, x, i);
            depthwise_loops(s, xc, kc, c, ep, dst);
        }
        want
    }

    /// The flat path on every SIMD width against the loops (with AVX-512 these layers
    /// take the lanes, so the conv tests no longer reach it there).
    #[test]
    fn the_flat_path_matches_the_loops_on_every_simd_width() {
        let acts = [None, Some(Activation::Relu6), Some(Activation::Silu), Some(Activation::Hardswish)];
        for (i, (n, c, (h, w), cout, k)) in [
            (2, 5, (7, 7), 5, 3),
            (1, 3, (7, 7), 6, 5),
            (1, 4, (7, 7), 4, 7),
            (3, 40, (4, 4), 40, 3),
            (1, 30, (6, 8), 30, 3),
        ]
        .into_iter()
        .enumerate()
        {
            let s = Conv2dShape { groups: c, ..Conv2dShape::square(n, c, 7, cout, k, 1, k / 2, c) };
            let s = Conv2dShape { h, w, oh: h, ow: w, ..s };
            assert!(flat::applies(&s), "{s:?}");
            let x = data(n * c * h * w, 5);
            let wt = data(cout * k * k, 6);
            let (scale, shift) = (data(cout, 7), data(cout, 8));
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: acts[i % acts.len()] };
            let want = by_the_loops(&s, &x, &wt, &ep);
            for b in backends() {
                let mut got = vec![f32::NAN; want.len()];
                b.run(flat::Flat { s: &s, w: &wt, x: &x, ep: &ep, first: 0, dst: &mut got });
                assert_close(&got, &want, 1e-5);
            }
        }
    }

    /// [`Registers`] on every SIMD width this CPU has (the kernel picks the widest),
    /// against the loops it replaced ([`depthwise_loops`]): 3x3, 5x5 and 7x7 kernels at
    /// stride 1 and 2 (odd and even padding and widths, so both column phases start the
    /// row), planes narrower than a vector, a row a vector and a bit wide, two images, a
    /// channel multiplier, rows not a multiple of the block's, and each kind of
    /// activation: none, the clamps applied in the store (ReLU, ReLU6, a clamp) and one
    /// applied after (Hardswish).
    #[test]
    fn every_simd_width_matches_the_loops() {
        let acts = [
            None,
            Some(Activation::Relu),
            Some(Activation::Relu6),
            Some(Activation::Clamp { min: Some(-0.25), max: Some(0.5) }),
            Some(Activation::Hardswish),
        ];
        for (i, (n, cin, (h, w), cout, k, stride, pad)) in [
            (2, 3, (9, 21), 3, 3, 1, 1),
            (1, 2, (7, 7), 4, 3, 1, 1),
            (1, 2, (11, 18), 2, 5, 1, 2),
            (1, 3, (6, 5), 3, 7, 1, 3),
            (1, 1, (14, 14), 1, 7, 1, 3),
            (2, 3, (14, 14), 3, 3, 2, 1),
            (1, 2, (13, 27), 4, 3, 2, 1),
            // Strided 3x3 rows wider than a vector (MobileNetV2's 112 to 56), and wider
            // than two.
            (1, 2, (10, 56), 2, 3, 2, 1),
            (1, 3, (9, 70), 3, 3, 2, 1),
            (1, 2, (28, 28), 2, 5, 2, 2),
            (1, 3, (15, 9), 3, 5, 2, 1),
            (1, 2, (14, 14), 2, 7, 2, 3),
            (1, 2, (9, 12), 2, 3, 2, 0),
        ]
        .into_iter()
        .enumerate()
        {
            let (oh, ow) = ((h + 2 * pad - k) / stride + 1, (w + 2 * pad - k) / stride + 1);
            let s = Conv2dShape {
                n,
                cin,
                h,
                w,
                cout,
                kh: k,
                kw: k,
                stride_h: stride,
                stride_w: stride,
                pad_h: pad,
                pad_w: pad,
                dil_h: 1,
                dil_w: 1,
                groups: cin,
                oh,
                ow,
            };
            assert!(Registers::applies(&s), "{s:?}");
            let x = data(n * cin * h * w, 5);
            let wt = data(cout * k * k, 6);
            let (scale, shift) = (data(cout, 7), data(cout, 8));
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: acts[i % acts.len()] };
            let plane = oh * ow;
            let want = by_the_loops(&s, &x, &wt, &ep);
            for b in backends() {
                let mut got = vec![f32::NAN; want.len()];
                b.run(Registers { s: &s, w: &wt, x: &x, ep: &ep, first: 0, dst: &mut got });
                assert_close(&got, &want, 1e-5);
                // From a later plane on, as a second task would.
                let mut tail = vec![f32::NAN; want.len() - plane];
                b.run(Registers { s: &s, w: &wt, x: &x, ep: &ep, first: 1, dst: &mut tail });
                assert_close(&tail, &want[plane..], 1e-5);
            }
        }
    }
}
