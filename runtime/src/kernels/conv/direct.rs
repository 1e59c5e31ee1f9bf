//! A direct conv for layers with few input channels per group, run for
//! [`ConvAlgo::Im2col`](super::ConvAlgo::Im2col) layers it applies to, on the same
//! PyTorch-layout weight: the stems (MobileNet's, EfficientNet's and RegNet's 3x3 stride 2
//! from three channels, ResNet's 7x7 stride 2) and grouped convs of narrow groups
//! (RegNet's 3x3 convs, eight channels a group).
//!
//! im2col unfolds such a layer into GEMMs whose depth is only `cin/groups · k · k` (27 for
//! a 3x3 stem, 72 for a RegNet group), one per group and tile: the unfolded tile is as
//! large as the output, and each GEMM's packing costs about what its multiply-adds do
//! (MobileNetV2's stem ran at 30 GFLOP/s on one core, a quarter of the machine's peak;
//! RegNetY-400MF's grouped convs took 39% of its time). Here the input of each image is
//! copied once into zero-padded planes (at stride 2 split into their even and odd columns,
//! so every load is contiguous), and each output row is computed in SIMD vectors for
//! [`CH`] output channels of a group at once: every input vector loaded is multiplied into
//! all of them (fused multiply-adds), the sums stay in registers, and the epilogue's
//! scale, shift and ReLU are applied as they are stored. (`readi bench --profile` still
//! counts these layers as `conv2d/im2col`, their algorithm in the plan.)

use rayon::prelude::*;

use super::{Conv2dShape, pad_phases, store_vector, vector_starts};
use crate::kernels::Epilogue;

/// Output channels computed together: each input vector feeds this many accumulators.
const CH: usize = 8;

/// Most input channels per group the direct conv takes.
const MAX_CIN: usize = 8;

/// Whether the direct conv computes this layer: at most four input channels in one
/// group, or at most [`MAX_CIN`] per group in several (one is the depthwise algorithm's);
/// a square 3x3, 5x5 or 7x7 kernel at stride 1 or 2, no dilation.
pub(super) fn applies(s: &Conv2dShape) -> bool {
    let few = if s.groups == 1 { s.cin <= 4 } else { s.cin_g() <= MAX_CIN };
    few && s.kh == s.kw
        && matches!(s.kh, 3 | 5 | 7)
        && s.stride_h == s.stride_w
        && matches!(s.stride_w, 1 | 2)
        && (s.dil_h, s.dil_w) == (1, 1)
}

/// The `rows x cols` of each of an image's `stride · cin` padded phase planes.
fn geometry(s: &Conv2dShape) -> (usize, usize) {
    (s.h + 2 * s.pad_h, (s.w + 2 * s.pad_w).div_ceil(s.stride_w))
}

/// Scratch floats the direct conv needs: one image's padded input planes and a vector's
/// worth of slack (a row narrower than a vector is read a whole vector wide).
pub(super) fn scratch_len(s: &Conv2dShape) -> usize {
    let (rows, cols) = geometry(s);
    s.stride_w * s.cin * rows * cols + 16
}

/// `out = epilogue(conv(x, w))` for a layer [`applies`] accepts, `w` in PyTorch's layout,
/// `scratch` of at least [`scratch_len`] floats; parallel over groups of output channels.
pub(super) fn conv(
    s: &Conv2dShape,
    w: &[f32],
    ep: &Epilogue,
    x: &[f32],
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    let (rows, cols) = geometry(s);
    let plane = s.oh * s.ow;
    let phases = &mut scratch[..scratch_len(s)];
    for (n, image) in out.chunks_mut(s.cout * plane).enumerate() {
        let xn = &x[n * s.cin * s.h * s.w..][..s.cin * s.h * s.w];
        pad(s, xn, rows, cols, phases, threads);
        let phases: &[f32] = phases;
        // Per group, its output channels [`CH`] at a time.
        let cout_g = s.cout_g();
        let chunk = |g: usize, (j, dst): (usize, &mut [f32])| {
            pulp::Arch::new().dispatch(Rows { s, w, ep, phases, rows, cols, g, c0: g * cout_g + j * CH, dst });
        };
        if threads <= 1 {
            for (g, planes) in image.chunks_mut(cout_g * plane).enumerate() {
                planes.chunks_mut(CH * plane).enumerate().for_each(|c| chunk(g, c));
            }
        } else {
            image.par_chunks_mut(cout_g * plane).enumerate().for_each(|(g, planes)| {
                planes.par_chunks_mut(CH * plane).enumerate().for_each(|c| chunk(g, c));
            });
        }
    }
}

/// Copies image `xn` into `phases`: per input channel and column phase, the zero-padded
/// plane (`rows x cols`); at stride 2 padded column `p` is column `p / 2` of phase `p % 2`.
/// The channels in parallel.
fn pad(s: &Conv2dShape, xn: &[f32], rows: usize, cols: usize, phases: &mut [f32], threads: usize) {
    let per = s.stride_w * rows * cols;
    let (planes, slack) = phases.split_at_mut(s.cin * per);
    slack.fill(0.0);
    let one = |(xc, out): (&[f32], &mut [f32])| pad_channel(s, xc, rows, cols, out);
    if threads <= 1 {
        xn.chunks_exact(s.h * s.w).zip(planes.chunks_exact_mut(per)).for_each(one);
    } else {
        xn.par_chunks_exact(s.h * s.w).zip(planes.par_chunks_exact_mut(per)).for_each(one);
    }
}

simd_fn! {
    /// One input channel `xc` into its phase planes `out` ([`pad`]).
    fn pad_channel(s: &Conv2dShape, xc: &[f32], rows: usize, cols: usize, out: &mut [f32]) {
        out.fill(0.0);
        pad_phases(s, xc, rows, cols, out);
    }
}

/// Output channels `c0..` of group `g` (as many as `dst` holds planes of, at most [`CH`])
/// of one image.
struct Rows<'a> {
    s: &'a Conv2dShape,
    w: &'a [f32],
    ep: &'a Epilogue<'a>,
    phases: &'a [f32],
    rows: usize,
    cols: usize,
    g: usize,
    c0: usize,
    dst: &'a mut [f32],
}

impl pulp::WithSimd for Rows<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        match (self.s.stride_w, self.s.kh) {
            (1, 3) => self.run::<S, 1, 3>(simd),
            (1, 5) => self.run::<S, 1, 5>(simd),
            (1, 7) => self.run::<S, 1, 7>(simd),
            (2, 3) => self.run::<S, 2, 3>(simd),
            (2, 5) => self.run::<S, 2, 5>(simd),
            (2, 7) => self.run::<S, 2, 7>(simd),
            _ => unreachable!("direct::applies"),
        }
    }
}

impl Rows<'_> {
    #[inline(always)]
    fn run<S: pulp::Simd, const ST: usize, const K: usize>(self, simd: S) {
        let Rows { s, w, ep, phases, rows, cols, g, c0, dst } = self;
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let (plane, ow, cin_g) = (s.oh * s.ow, s.ow, s.cin_g());
        let chans = dst.len() / plane;
        let k = cin_g * K * K;
        // The group's weights, zero for channels past its end, and its affine.
        let mut taps = [[0.0f32; MAX_CIN * 49]; CH];
        for (c, t) in taps.iter_mut().enumerate().take(chans) {
            t[..k].copy_from_slice(&w[(c0 + c) * k..][..k]);
        }
        let at = |c: usize, v: Option<&[f32]>, default: f32| v.map_or(default, |v| v[c0 + c.min(chans - 1)]);
        let scale: [S::f32s; CH] = std::array::from_fn(|c| simd.splat_f32s(at(c, ep.scale, 1.0)));
        let shift: [S::f32s; CH] = std::array::from_fn(|c| simd.splat_f32s(at(c, ep.shift, 0.0)));
        let width = lanes.min(ow);
        let clamp = ep.clamp();
        for oy in 0..s.oh {
            for ox in vector_starts(ow, width) {
                let mut acc = [simd.splat_f32s(0.0); CH];
                for ci in 0..cin_g {
                    for ky in 0..K {
                        for kx in 0..K {
                            // Padded column ST ox + kx: column ox + kx / ST of phase kx % ST,
                            // of the group's input channel ci.
                            let row = (((g * cin_g + ci) * ST + kx % ST) * rows + ST * oy + ky) * cols;
                            let i = row + ox + kx / ST;
                            let v = S::as_simd_f32s(&phases[i..i + lanes]).0[0];
                            let t = (ci * K + ky) * K + kx;
                            for (a, tc) in acc.iter_mut().zip(&taps) {
                                *a = simd.mul_add_f32s(v, simd.splat_f32s(tc[t]), *a);
                            }
                        }
                    }
                }
                for (c, a) in acc.into_iter().enumerate().take(chans) {
                    store_vector(simd, a, scale[c], shift[c], clamp, &mut dst[c * plane + oy * ow + ox..][..width]);
                }
            }
        }
        for plane_out in dst.chunks_mut(plane) {
            ep.finish_unclamped(plane_out);
        }
    }
}
