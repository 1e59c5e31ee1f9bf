//! [`ConvAlgo::Gemm1x1`](super::ConvAlgo) of one group without a GEMM call: register
//! tiles of `MR` output channels by `NV` vectors of pixels, the weight's rows broadcast,
//! the input planes read in place (a 1x1 conv's input channel plane is a row of the GEMM's
//! right-hand side already), and the epilogue (scale, shift, residual, a clamp) applied
//! in registers as each vector is stored.
//!
//! The `gemm` crate packs the weight on every call and computes a plane in whole vectors
//! (a 7x7 plane's 49 pixels as 64). Here nothing is packed: the weight is read as `MR`
//! row streams, each element broadcast once per tile of pixels. The whole tiles run by
//! chunks of pixels whose input fits L2 ([`CHUNK_FLOATS`]), and within a chunk `MR`
//! channels at a time over all its tiles: the outputs are written `MR` planes at a time
//! (see [`CHUNK_FLOATS`] for why). Pixels left over after the whole tiles run as narrower
//! tiles, then a few last ones as dot products over the input channels, or the last
//! fraction of a vector through scratch, zero-padded.
//!
//! The same tiles run over an Im2col layer's unfolded rows ([`unfolded`]) on planes of
//! one tile and a remainder (7x7: ResNet's strided convs of the last stage).

#[cfg(test)]
use super::ConvAlgo;
use super::split::Part;
use super::{Conv2dShape, affine, clamp_vector, finish, pad_row};
use crate::kernels::gemm::{prefetch, prefetch_l2, strided_rows_product};
use crate::kernels::{Activation, Epilogue, elementwise};

/// Whether a Gemm1x1 layer with activation `act` runs here rather than through the `gemm`
/// crate: one group, and planes of at most [`MAX_PLANE`] pixels with at most
/// [`MAX_STREAMED`] weight floats streamed per image or no more output channels than input
/// ones, or of at most [`ONE_TILE_PLANE`] whatever the weight; or, when the tiles compute
/// the activation in registers (SiLU, sigmoid, GELU, tanh, the hard ones:
/// [`Epilogue::vector_act`]), planes of any size under a weight of at most
/// [`MAX_ACT_WEIGHT`] floats; or an expansion of at most [`MAX_EXPANSION_CIN`] input
/// channels, whatever its plane.
pub(super) fn applies(s: &Conv2dShape, act: Option<Activation>) -> bool {
    let plane = s.oh * s.ow;
    let light = streamed(s, s.cin) <= MAX_STREAMED || s.cout <= s.cin;
    let small = plane <= ONE_TILE_PLANE || (plane <= MAX_PLANE && light);
    let in_registers = act.is_some_and(elementwise::on_vectors) && s.cin * s.cout <= MAX_ACT_WEIGHT;
    let expansion = s.cout >= 2 * s.cin && s.cin <= MAX_EXPANSION_CIN;
    s.groups == 1 && (small || in_registers || expansion)
}

/// The most input channels of an expansion (at least twice as many output channels as
/// input ones) that [`applies`] takes the tiles for on planes of any size. Few multiply-
/// adds per output value leave such a layer waiting on its output's writes, and the tiles
/// write a large plane's outputs `MR` planes at a time ([`BLOCKED_PLANE`]), where the
/// crate's path writes its GEMM's tile to scratch, then every channel's row from it. In
/// the models (the AMD EPYC, Zen 4, 1 MiB L2, 2026-12-06; per step, the crate's path and
/// the tiles chosen run by run in one session, 150 rounds, one / two threads), the tiles
/// took of the crate's time (two runs): MobileNetV2's 16 to 96 on 112x112 0.79-0.87 /
/// 0.67-0.77, its 24 to 144 on 56x56 0.91-0.96 / 0.87-0.94, 32 to 192 on 28x28 1.0 /
/// 0.94, 64 to 384 and 96 to 576 on 14x14 1.0; MobileNetV3-Large's 16 to 64 on 112x112
/// 0.77-0.81 / 0.69-0.89, its hardswish 40 to 240 on 28x28 0.94 / 0.91 and 112 to 672 on
/// 14x14 0.86-0.96 / 0.86-0.90;
/// EfficientNet-B0's SiLU 80 to 480 and 112 to 672 on 14x14 0.88-0.92 / 0.82-0.93;
/// ResNet-50's 64 to 256 on 56x56 (40 rounds) 0.98-1.0 / 0.95-1.03. Deeper ones run near
/// the core's limit in the crate, where the tiles lost (two sessions, 60 rounds):
/// ResNet-50's 128 to 512 on 28x28 1.06-1.10, 256 to 1024 on 14x14 1.04.
const MAX_EXPANSION_CIN: usize = 112;

/// The largest weight (floats) a Gemm1x1 layer of any plane size takes the tiles with when
/// they compute its activation in registers. The crate's path writes the GEMM's tile to
/// scratch, then the epilogue reads it back and the activation's pass reads the output
/// again; the tiles compute SiLU on the sums and store once. EfficientNet-B0's SiLU
/// expansions (2-core Xeon, AVX-512, 2026-12-06, tiles' time over the crate path's,
/// alternating calls in one process, 2-3 runs, 1 / 2 threads): 16 to 96 channels on
/// 112x112 0.89-0.92 / 0.92-0.95, 24 to 144 on 56x56 0.93 / 0.98, 40 to 240 on 28x28
/// 0.98-1.02 / 0.85-0.91; 112 to 672 on 14x14 (75 Ki floats, past this bound) 0.98-1.07 /
/// 1.00-1.06. With a ReLU the crate's path stayed ahead on large planes (16 to 96 on
/// 112x112: 1.10 / 1.15) while the tiles went tile by tile over every channel; by chunks
/// they now take such expansions whatever the activation ([`MAX_EXPANSION_CIN`]). GELU
/// and tanh, costlier, take the same rule unmeasured.
const MAX_ACT_WEIGHT: usize = 16 * 1024;

/// Whether an Im2col layer's tiles run here ([`unfolded`]) rather than through the `gemm`
/// crate: one group and planes of at most [`MAX_UNFOLDED_PLANE`] pixels, whatever the
/// weight (they are all within [`ONE_TILE_PLANE`]).
pub(super) fn applies_unfolded(s: &Conv2dShape) -> bool {
    s.groups == 1 && s.oh * s.ow <= MAX_UNFOLDED_PLANE
}

/// Whether the tiles over an Im2col layer's unfolded rows stream at most
/// [`MAX_STREAMED`] weight floats per image: below that bound they beat the weight
/// panels on 7x7 planes, above it the panels win (`conv::choose`).
pub(super) fn light_unfolded(s: &Conv2dShape) -> bool {
    streamed(s, s.k()) <= MAX_STREAMED
}

/// Weight floats the tiles read per image of a layer of `depth` input rows: the whole
/// weight once per group of 48 pixels (an AVX-512 tile's three vectors).
fn streamed(s: &Conv2dShape, depth: usize) -> usize {
    s.cout * depth * (s.oh * s.ow).div_ceil(48)
}

/// The most weight floats [`applies`] lets the tiles stream per image of more than
/// [`ONE_TILE_PLANE`] pixels (1.25 MiB), and the bound of [`light_unfolded`]. The tiles
/// broadcast the weight from six rows at a time, once per group of pixels; the crate
/// packs it once per call. Measured on a 2-core Xeon with a
/// 2 MiB L2 (2026-12-05, `readi bench --profile`, alternating rounds, one thread, the
/// crate's time over the tiles'): MobileNetV2's 1x1 layers streaming 123-307 Ki floats
/// 1.02-1.23 (the tiles win), its 7x7 320 -> 1280 one (400 Ki) 0.93; ResNet-50's 14x14
/// and 7x7 ones (1-1.25 Mi) 0.75-0.89, ResNet-18's 7x7 3x3 im2col layers (2.3-4.7 Mi)
/// 0.91-0.92 (its 7x7 1x1 downsampling, 0.26 Mi, 0.91 too, a 0.17 ms step the bound
/// leaves in the tiles). With the bound, one thread: ResNet-50 0.944 of the time before,
/// EfficientNet-B0 0.980, MobileNetV2 1.008 (two threads: 0.991, 1.024).
///
/// On the AMD EPYC (1 MiB L2, 2026-12-07; per step, the two paths chosen run by run in one
/// session, 60 rounds, one / two threads) the bound held for the 14x14 expansions
/// (ResNet-50's 256 to 1024 with its residual 1.07-1.08 in the tiles) but not for the
/// reductions, which now take the tiles whatever their weight: the 672 to 112 projections
/// with a residual of MobileNetV3-Large 0.86 / 0.85 and EfficientNet-B0 0.85-0.86 /
/// 0.81-0.94, ResNet-50's 1024 to 256 0.96-0.98 / 0.94-0.97 and 1024 to 512 0.97-1.03.
/// The models: MobileNetV3-Large 0.983 / 0.992, EfficientNet-B0 0.994 / 1.005, ResNet-50
/// 0.994 / 0.996 (a noisy host: steps the rule does not touch moved by up to 3%).
const MAX_STREAMED: usize = 320 * 1024;

/// The largest plane (pixels of one image) [`applies`] takes. On an AMD EPYC (1 MiB L2,
/// 2026-12-05), on 7x7 planes this path ran MobileNetV2's and ResNet-50's 1x1 convs in
/// 0.76-0.81x the `gemm` crate's time (94-110 GFLOP/s against 75-86, one thread, warm),
/// on 14x14 ones in 0.91-1.03x; on 28x28 and larger, 0.96-1.10x, and in the model a
/// 112x112 expansion (16 to 96 channels, bound by writing its output) took 1.17x: the
/// crate's path writes each output row from one long tile, this one then wrote every
/// plane a tile apart (by chunks since: [`BLOCKED_PLANE`], [`MAX_EXPANSION_CIN`]).
const MAX_PLANE: usize = 256;

/// Planes of at most this many pixels (one AVX-512 tile of three vectors and a fourth:
/// 7x7) take the tiles whatever their weight ([`applies`], [`applies_unfolded`]). On the
/// AMD EPYC (Zen 4, AVX-512 on 256-bit units, 1 MiB L2; 2026-12-06, the tiles' time over
/// the crate's, old and new rule alternating call by call in one process, 350 pairs, 1 /
/// 2 threads) the 7x7 layers [`MAX_STREAMED`] had sent to the crate: MobileNetV2's 320 to
/// 1280 with ReLU6 0.80 / 0.79, 960 to 320 0.79 / 0.77; EfficientNet-B0's SiLU 192 to 1152
/// 0.78 / 0.77, 320 to 1280 0.78 / 0.78, 1152 to 320 0.79 / 0.77; ResNet-50's 512 to 2048
/// 0.82 / 0.84, 2048 to 512 0.80 / 0.79 and its 1024 to 2048 stride-2 downsampling (over
/// its unfolded rows) 0.83 / 0.84. Its 14x14 layers measured 0.97-1.02 (the bound stays
/// there), the 28x28 and 56x56 ones 1.01-1.11. On the Xeon whose measurements set
/// [`MAX_STREAMED`] (2026-12-05), the 320 to 1280 layer had run 1.07x as long by the
/// tiles as by the crate: re-measure there.
const ONE_TILE_PLANE: usize = 64;

/// The largest plane [`applies_unfolded`] takes: one AVX-512 tile and a remainder. On the
/// EPYC, on ResNet-50's 7x7 strided 3x3 (4608 unfolded rows) and 1x1 downsampling, the
/// steps took 0.89-0.90x the crate path's time in the model (ResNet-18's 7x7 strided 3x3
/// 0.85x); its 14x14 strided 3x3 (2304 rows, 196 pixels) took 1.17x: the tiles re-read an
/// unfolded matrix larger than L2 once per 6 channels, where the crate blocks it for the
/// cache. One tile's plane, which takes the tiles whatever its weight.
const MAX_UNFOLDED_PLANE: usize = ONE_TILE_PLANE;

/// The input floats (64 Ki, 256 KiB: a quarter of the AMD EPYC's L2) of one chunk of
/// pixels whose whole tiles run channel block by channel block ([`Image::range`], planes
/// of at least [`BLOCKED_PLANE`]): the chunk's input is read from memory once and from L2
/// by every further block of `MR` channels, and the outputs are written `MR` planes at a
/// time. Tile by tile over all channels, a layer writes every one of its output planes a
/// tile apart: writing 96 planes of 112x112 that way (vector stores alone, nothing
/// computed, the caches flushed before each run) took 2.6-2.8x as long as writing them 6
/// planes at a time over the whole plane, 1.8x as long as 6 at a time over chunks of
/// 1536 pixels (a C loop on the AMD EPYC, 2026-12-06): the hardware prefetchers follow a
/// few streams, not 96.
const CHUNK_FLOATS: usize = 64 * 1024;

/// The smallest plane (pixels) whose whole tiles run by chunks ([`CHUNK_FLOATS`]): 56x56.
/// Against tile by tile over every channel (per step in the models, the two chosen run by
/// run in one session, 150 rounds, one / two threads, AMD EPYC, 2026-12-06): 16 to 96 on
/// 112x112 0.74 / 0.72 (MobileNetV2), 16 to 64 0.72 / 0.78 (MobileNetV3-Large), 24 to 144
/// on 56x56 0.96 / 0.96; on 28x28 planes 1.05-1.19 at two threads (MobileNetV2's 32 to
/// 192, MobileNetV3's 40 to 120), on 14x14 and 7x7 ones 1.02-1.12.
const BLOCKED_PLANE: usize = 56 * 56;

/// The smallest plane that runs by chunks when the tiles compute an activation on the
/// sums (SiLU, hardswish: [`Epilogue::vector_act`]), less bound by writing: 112x112.
/// EfficientNet-B0's SiLU expansions by chunks: 16 to 96 on 112x112 0.95 / 0.98 of the
/// time tile by tile, 24 to 144 on 56x56 1.03-1.05.
const BLOCKED_ACT_PLANE: usize = 112 * 112;

/// Scratch floats of one part over `depth` input rows: a padded tail's input columns and
/// its sums, for vectors of up to 16 lanes and micro-tiles of up to 8 rows; or the columns
/// of the dot products' pixels.
pub(super) fn scratch_len(depth: usize) -> usize {
    (depth + 8) * 16
}

/// A plane whose whole vectors leave at most a `DOTS`-th of one computes those last
/// pixels as dot products over the input channels ([`Image::dots`]) instead of a
/// zero-padded vector: a 7x7 plane is three AVX-512 vectors and one pixel, which padded
/// costs a third more than the rest.
const DOTS: usize = 4;

/// Channels whose weight rows [`Image::dots`] multiplies at a time: eight sums in flight,
/// enough to cover the multiply-add's latency on two units.
const DOT_ROWS: usize = 8;

/// Channels [`Image::dots`] finishes together.
const DOT_BLOCK: usize = 64;

/// The conv of one part (its output channels of its rows) into the part's planes, image
/// by image.
pub(super) fn part(s: &Conv2dShape, w: &[f32], ep: &Epilogue, x: &[f32], part: &mut Part, scratch: &mut [f32]) {
    let (cin, plane) = (s.cin, s.oh * s.ow);
    let chans = part.channels_of(0, s.cout);
    for n in part.n0..=(part.r1 - 1) / s.oh {
        let (lo, hi) = part.rows_of(n, s.oh);
        let x = &x[n * cin * plane..][..cin * plane];
        let im = Image::new(w, ep, x, (cin, plane), n, 0, lo * s.ow, plane);
        let q = lo * s.ow..hi * s.ow;
        pulp::Arch::new().dispatch(Pass { im, part: &mut *part, chans: chans.clone(), q, scratch: &mut *scratch });
    }
}

/// Pixels `q` of one image's rows, channels `chans`, compiled for the widest SIMD the CPU
/// has: micro-tiles of `MR` channels by `NV` vectors, the sums in 18 of the 32 AVX-512
/// registers (8x3, 24 sums, ran at half the speed: they did not stay in registers), 12
/// of the 16 AVX2 ones.
struct Pass<'a, 'p> {
    im: Image<'a>,
    part: &'a mut Part<'p>,
    chans: std::ops::Range<usize>,
    q: std::ops::Range<usize>,
    scratch: &'a mut [f32],
}

impl pulp::WithSimd for Pass<'_, '_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Pass { im, part, chans, q, scratch } = self;
        match size_of::<S::f32s>() / size_of::<f32>() {
            16 => im.range::<S, 6, 3>(simd, part, chans, q, scratch),
            8 => im.range::<S, 3, 4>(simd, part, chans, q, scratch),
            4 => im.range::<S, 2, 8>(simd, part, chans, q, scratch),
            _ => im.range::<S, 2, 16>(simd, part, chans, q, scratch),
        }
    }
}

/// What every micro-tile over one image's input rows shares: the rows (the image's
/// input planes, or an unfolded tile's rows), and where a pixel of them lands in the
/// part's planes.
#[derive(Clone, Copy)]
struct Image<'a> {
    w: &'a [f32],
    ep: &'a Epilogue<'a>,
    /// `depth` input rows, `stride` apart.
    x: &'a [f32],
    depth: usize,
    stride: usize,
    n: usize,
    /// Pixel `q` of the rows is pixel `first + q` of the image's planes; the part's
    /// planes start at its pixel `p_lo`.
    first: usize,
    p_lo: usize,
    /// Pixels of the image's planes.
    plane: usize,
    clamp: Option<(f32, f32)>,
    /// An activation that is not a clamp, applied to each micro-tile once stored.
    post: Option<Activation>,
}

impl<'a> Image<'a> {
    #[allow(clippy::too_many_arguments)]
    fn new(
        w: &'a [f32],
        ep: &'a Epilogue<'a>,
        x: &'a [f32],
        (depth, stride): (usize, usize),
        n: usize,
        first: usize,
        p_lo: usize,
        plane: usize,
    ) -> Self {
        let clamp = ep.clamp();
        let post = ep.act.filter(|_| clamp.is_none());
        Image { w, ep, x, depth, stride, n, first, p_lo, plane, clamp, post }
    }
}

/// An Im2col tile of one group-1 layer of small planes ([`applies_unfolded`]) instead of
/// its GEMM: `col`, the unfolded `k x tp` rows of pixels `p0..p0 + tp` of image `n`,
/// channels `chans`, into the part's planes (which start at pixel `p_lo`); `scratch`
/// holds at least [`scratch_len`]`(k)` floats.
#[allow(clippy::too_many_arguments)]
pub(super) fn unfolded(
    s: &Conv2dShape,
    w: &[f32],
    ep: &Epilogue,
    col: &[f32],
    tp: usize,
    part: &mut Part,
    n: usize,
    chans: std::ops::Range<usize>,
    (p0, p_lo): (usize, usize),
    scratch: &mut [f32],
) {
    let k = s.k();
    let im = Image::new(w, ep, &col[..k * tp], (k, tp), n, p0, p_lo, s.oh * s.ow);
    pulp::Arch::new().dispatch(Pass { im, part, chans, q: 0..tp, scratch });
}

impl Image<'_> {
    /// Channels `chans` of pixels `q` of the rows: whole tiles of `NV` vectors (by chunks
    /// of pixels, `MR` channels at a time over a chunk's tiles: [`CHUNK_FLOATS`]), then
    /// pairs and single vectors, then one padded vector, and the plane's last few pixels
    /// (if in `q`) as dot products. Every pixel of a channel sums its input channels in
    /// the same order whichever of these takes it, but for the dot products.
    #[inline(always)]
    fn range<S: pulp::Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        part: &mut Part,
        chans: std::ops::Range<usize>,
        q: std::ops::Range<usize>,
        scratch: &mut [f32],
    ) {
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        // Dot products sum in another order than the tiles, so they take the same pixels
        // whatever the split: the plane's last few, if a vector's whole multiples leave
        // at most a `DOTS`-th of one. Every other pixel sums as in a tile (a padded vector
        // does too), so the bits do not depend on the thread count.
        let left = self.plane % lanes;
        let dots_at = if left > 0 && DOTS * left <= lanes { self.plane - left } else { self.plane };
        let end = q.end.min(dots_at.saturating_sub(self.first)).max(q.start);
        let width = NV * lanes;
        let whole = q.start + (end - q.start) / width * width;
        // The whole tiles by chunks of pixels, a block of channels at a time over a chunk:
        // on large planes `MR` channels over as many pixels as `CHUNK_FLOATS` allows, else
        // every channel over one tile.
        let blocked =
            self.plane >= BLOCKED_PLANE && (self.ep.vector_act::<S>().is_none() || self.plane >= BLOCKED_ACT_PLANE);
        let (chunk, channels) = if blocked {
            ((CHUNK_FLOATS / self.depth.max(1) / width * width).max(width), MR)
        } else {
            (width, chans.len().max(1))
        };
        for p0 in (q.start..whole).step_by(chunk) {
            let p1 = whole.min(p0 + chunk);
            for c in chans.clone().step_by(channels) {
                let block = c..chans.end.min(c + channels);
                for p in (p0..p1).step_by(width) {
                    // The later blocks find the chunk's input in L2.
                    if c == chans.start {
                        self.fetch_next(p, width, end, lanes);
                    }
                    self.tile::<S, MR, NV>(simd, part, block.clone(), p);
                }
            }
        }
        let mut p = whole;
        // What is left, less than a tile: pairs of vectors, then single ones, then a
        // padded one.
        while NV > 2 && p + 2 * lanes <= end {
            self.tile::<S, MR, 2>(simd, part, chans.clone(), p);
            p += 2 * lanes;
        }
        while NV > 1 && p + lanes <= end {
            self.tile::<S, MR, 1>(simd, part, chans.clone(), p);
            p += lanes;
        }
        if p < end {
            self.tail::<S, MR>(simd, part, chans.clone(), p, end, scratch);
        }
        if end < q.end {
            self.dots::<S>(simd, part, chans, end, q.end, scratch);
        }
    }

    /// Asks for the input rows of the tile of `width` pixels after the one at `p`, if it
    /// is whole before `end`: rows a plane apart are more streams than the hardware
    /// prefetcher follows.
    #[inline(always)]
    fn fetch_next(&self, p: usize, width: usize, end: usize, lanes: usize) {
        if p + 2 * width <= end {
            for ci in 0..self.depth {
                (width..2 * width).step_by(lanes).for_each(|v| prefetch(&self.x[ci * self.stride + p + v]));
            }
        }
    }

    /// Channels `chans` of the `NV` vectors of pixels from `p`, by micro-tiles of `MR`
    /// channels (then 4, 2, 1 for the last).
    #[inline(always)]
    fn tile<S: pulp::Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        part: &mut Part,
        chans: std::ops::Range<usize>,
        p: usize,
    ) {
        let mut c = chans.start;
        while c < chans.end {
            let left = chans.end - c;
            c += if left >= MR {
                self.micro::<S, MR, NV>(simd, part, c, p)
            } else if left >= 4 && MR > 4 {
                self.micro::<S, 4, NV>(simd, part, c, p)
            } else if left >= 2 {
                self.micro::<S, 2, NV>(simd, part, c, p)
            } else {
                self.micro::<S, 1, NV>(simd, part, c, p)
            };
        }
    }

    /// Channels `c0..c0 + MR` at the `NV` vectors of pixels from `p`: the sums in
    /// registers, then `act(sum · scale + shift + res)` stored.
    #[inline(always)]
    fn micro<S: pulp::Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        part: &mut Part,
        c0: usize,
        p: usize,
    ) -> usize {
        let (cin, plane) = (self.depth, self.stride);
        let width = NV * size_of::<S::f32s>() / size_of::<f32>();
        let a: [&[f32]; MR] = std::array::from_fn(|r| &self.w[(c0 + r) * cin..][..cin]);
        let acc = strided_rows_product::<S, MR, NV>(simd, a, &self.x[p..], plane);
        let off = self.first + p - self.p_lo;
        // The activation computed on the sums, else (not a clamp) a pass over the stored block.
        let in_registers = self.ep.vector_act::<S>();
        for (r, sums) in acc.iter().enumerate() {
            let c = c0 + r;
            let scale = simd.splat_f32s(self.ep.scale.map_or(1.0, |v| v[c]));
            let shift = simd.splat_f32s(self.ep.shift.map_or(0.0, |v| v[c]));
            let res = part.residual(self.n, c).map(|q| S::as_simd_f32s(&q[off..][..width]).0);
            let out = &mut part.plane(self.n, c)[off..][..width];
            let (dst, _) = S::as_mut_simd_f32s(out);
            let mut z = *sums;
            for v in 0..NV {
                // Multiplied, then added, as `finish` does for the tails and dot products:
                // a fused multiply-add would round differently, and which pixels take
                // which path depends on the split.
                z[v] = simd.add_f32s(simd.mul_f32s(sums[v], scale), shift);
                if let Some(res) = res {
                    z[v] = simd.add_f32s(z[v], res[v]);
                }
                z[v] = self.clamp.map_or(z[v], |cl| clamp_vector(simd, z[v], cl));
            }
            if let Some(act) = in_registers {
                z = elementwise::act_simd(simd, act, z);
            }
            dst.copy_from_slice(&z);
            if let Some(f) = self.post.filter(|_| in_registers.is_none()) {
                elementwise::activation_chunk(f, out);
            }
        }
        MR
    }

    /// Pixels `p..end` (a few) of channels `chans` as dot products: each pixel's input
    /// column copied out contiguous, then for [`DOT_ROWS`] channels at a time (as many sums
    /// in flight) the weight rows times the columns, in vectors of input channels. The sums
    /// of a block of [`DOT_BLOCK`] channels are finished together: the affine per channel,
    /// then an activation other than a ReLU in one pass over the block (a 1x1 plane, a
    /// squeeze-and-excitation conv's, is one pixel a channel: a call per channel cost as
    /// much as its weight row's multiplies).
    #[inline(always)]
    fn dots<S: pulp::Simd>(
        self,
        simd: S,
        part: &mut Part,
        chans: std::ops::Range<usize>,
        p: usize,
        end: usize,
        scratch: &mut [f32],
    ) {
        const G: usize = DOT_ROWS;
        let (cin, plane, r) = (self.depth, self.stride, end - p);
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let cols = &mut scratch[..r * cin];
        for (j, col) in cols.chunks_exact_mut(cin).enumerate() {
            col.iter_mut().enumerate().for_each(|(ci, v)| *v = self.x[ci * plane + p + j]);
        }
        let off = self.first + p - self.p_lo;
        // Channel-major within a block: `sums[(c - b0) * r + j]`.
        let mut sums = [0.0f32; DOT_BLOCK * DOTS];
        let mut vals = [0.0f32; DOT_BLOCK * DOTS];
        for b0 in chans.clone().step_by(DOT_BLOCK) {
            let b1 = chans.end.min(b0 + DOT_BLOCK);
            let mut c = b0;
            while c < b1 {
                let g = (b1 - c).min(G);
                let rows: [&[f32]; G] = std::array::from_fn(|k| &self.w[(c + k.min(g - 1)) * cin..][..cin]);
                // The next group's rows, fetched into L2 while this one's are multiplied
                // (a line per row and step, as the first pixel reads them): a squeeze-
                // and-excitation conv's weight comes from L3 or memory, once per image,
                // faster when asked for ahead.
                let ahead = self.w.get((c + g) * cin..(c + g + G) * cin).unwrap_or(&[]);
                for (j, col) in cols.chunks_exact(cin).enumerate() {
                    let (cv, ct) = S::as_simd_f32s(col);
                    let mut acc = [simd.splat_f32s(0.0); G];
                    let heads: [&[S::f32s]; G] = rows.map(|row| S::as_simd_f32s(row).0);
                    for (i, &x) in cv.iter().enumerate() {
                        if j == 0 && !ahead.is_empty() {
                            (0..G).for_each(|k| prefetch_l2(&ahead[(i * G + k) * lanes]));
                        }
                        for k in 0..G {
                            acc[k] = simd.mul_add_f32s(heads[k][i], x, acc[k]);
                        }
                    }
                    for k in 0..g {
                        let tail = &rows[k][cin - ct.len()..];
                        let t: f32 = tail.iter().zip(ct).map(|(a, b)| a * b).sum();
                        sums[(c - b0 + k) * r + j] = simd.reduce_sum_f32s(acc[k]) + t;
                    }
                }
                c += g;
            }
            let block = &mut vals[..(b1 - b0) * r];
            for (k, (v, s)) in block.chunks_exact_mut(r).zip(sums.chunks_exact(r)).enumerate() {
                let res = part.residual(self.n, b0 + k).map(|q| &q[off..]);
                affine(v, s, b0 + k, self.ep, res);
            }
            self.ep.finish_act(block);
            for (k, v) in block.chunks_exact(r).enumerate() {
                part.plane(self.n, b0 + k)[off..off + r].copy_from_slice(v);
            }
        }
    }

    /// Pixels `p..end` (less than a vector) of channels `chans`: the input columns copied
    /// into a zero-padded vector per channel, one vector of sums per micro-tile, the
    /// epilogue on the real pixels.
    #[inline(always)]
    fn tail<S: pulp::Simd, const MR: usize>(
        self,
        simd: S,
        part: &mut Part,
        chans: std::ops::Range<usize>,
        p: usize,
        end: usize,
        scratch: &mut [f32],
    ) {
        let (cin, plane) = (self.depth, self.stride);
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let (xs, rest) = scratch.split_at_mut(cin * lanes);
        let sums = &mut rest[..MR * lanes];
        for (ci, dst) in xs.chunks_exact_mut(lanes).enumerate() {
            pad_row(dst, &self.x[ci * plane + p..ci * plane + end]);
        }
        let off = self.first + p - self.p_lo;
        let mut c = chans.start;
        while c < chans.end {
            let mr = (chans.end - c).min(MR);
            let a: [&[f32]; MR] = std::array::from_fn(|r| &self.w[(c + r.min(mr - 1)) * cin..][..cin]);
            let acc = strided_rows_product::<S, MR, 1>(simd, a, xs, lanes);
            let (sv, _) = S::as_mut_simd_f32s(sums);
            for (d, a) in sv.iter_mut().zip(&acc) {
                *d = a[0];
            }
            for (r, row) in sums.chunks_exact(lanes).take(mr).enumerate() {
                let res = part.residual(self.n, c + r).map(|q| &q[off..]);
                finish(&mut part.plane(self.n, c + r)[off..off + end - p], &row[..end - p], c + r, self.ep, res);
            }
            c += mr;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::split::split;
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

    /// Each SIMD backend (its own tile widths, so its own tails) against the definition
    /// `relu6(w x · scale + shift + res)` in f64, on planes of 1 to 50 pixels.
    #[test]
    fn every_simd_width_matches_the_definition() {
        let (cin, cout) = (21, 11);
        for plane in [1, 3, 4, 9, 16, 17, 33, 49, 50] {
            let s = Conv2dShape {
                n: 1,
                cin,
                h: 1,
                w: plane,
                cout,
                kh: 1,
                kw: 1,
                stride_h: 1,
                stride_w: 1,
                pad_h: 0,
                pad_w: 0,
                dil_h: 1,
                dil_w: 1,
                groups: 1,
                oh: 1,
                ow: plane,
            };
            let (w, x, res) = (data(cout * cin, 1), data(cin * plane, 2), data(cout * plane, 3));
            let (scale, shift) = (data(cout, 4), data(cout, 5));
            let want: Vec<f32> = (0..cout * plane)
                .map(|i| {
                    let (c, p) = (i / plane, i % plane);
                    let sum: f64 = (0..cin).map(|ci| f64::from(w[c * cin + ci]) * f64::from(x[ci * plane + p])).sum();
                    let z = sum * f64::from(scale[c]) + f64::from(shift[c]) + f64::from(res[i]);
                    z.clamp(0.0, 6.0) as f32
                })
                .collect();
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu6) };
            for b in backends() {
                let mut out = vec![f32::NAN; cout * plane];
                let mut scratch = vec![f32::NAN; scratch_len(cin)];
                let mut parts = split(&mut out, Some(&res), &s, ConvAlgo::Gemm1x1, 1);
                let im = Image::new(&w, &ep, &x, (cin, plane), 0, 0, 0, plane);
                b.run(Pass { im, part: &mut parts[0], chans: 0..cout, q: 0..plane, scratch: &mut scratch });
                drop(parts);
                assert_close(&out, &want, 1e-5);
            }
        }
    }
}
