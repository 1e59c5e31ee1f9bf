//! A residual bottleneck adapter fused into the conv that produces its input
//! ([`Adapter`]): on the conv's output `y` after the epilogue's scale and shift,
//! `y + up · act(down · y + down_bias) + up_bias`, then the epilogue's ReLU.
//!
//! The adapter needs every channel of a pixel, so it runs on tiles of pixels holding all
//! `cout` channels, two small products per tile (`h = down · y` to `mid` rows, `y += up ·
//! h`) while the tile is in cache:
//!
//! * the GEMM paths (Gemm1x1, Im2col) under a split by output rows compute every channel
//!   of a tile of pixels into one accumulator: [`apply_tile`] runs there, between the
//!   scale/shift and the copy to the output (`im2col.rs`), so the conv's output is
//!   written once, final;
//! * everywhere else the conv finishes with scale and shift only, and [`Fused`] runs over
//!   its output planes where they are, [`TILE`] pixels at a time: `h` by micro-tiles of
//!   bottleneck rows with the sums in registers (the weight's rows broadcast, the tile's
//!   rows copied side by side and read at one stride by [`strided_rows_product`]: read
//!   in place through an iterator of row slices, ResNet-18's adapted steps took
//!   1.05-1.13x as long at two threads), then `y` by micro-tiles of channels with the up
//!   bias, the residual and a clamp (ReLU) applied in registers as each vector is
//!   stored. Under a conv split by rows it runs inside each thread's part, right after
//!   the conv wrote it ([`apply_part`]); under a split by channels (each thread then
//!   holds only some channels of a pixel), and after the depthwise loop, over the whole
//!   output with the threads sharing the pixels ([`apply_fused`]).
//!
//! Before, this path made two `gemm` crate GEMMs per chunk of pixels (packing operands on
//! every call, passes for the biases and the ReLU) with a join between `down` by chunks
//! and `up` by channels. ResNet-18 with its spec's adapters took 1.095x the time of the
//! same plan without them at two threads (1.8x the adapters' 5.4% share of the
//! multiply-adds) and 1.077x at one; with this path 1.055-1.079x (median 1.067, 1.2x their
//! share) and 1.062-1.083x (median 1.077, 1.35x), alternating rounds over a day's runs on
//! a shared host (2026-12-05; the README's variants table).

use rayon::prelude::*;

use super::{Conv2dShape, pad_row};
use crate::kernels::gemm::{MatMut, MatRef, prefetch, sgemm, strided_rows_product};
use crate::kernels::{Activation, clamp_bounds, elementwise};

/// An adapter's tensors: `down` `[mid, cout]` row-major, `down_bias` `[mid]`, `up`
/// `[cout, mid]`, `up_bias` `[cout]`, and the activation between them.
#[derive(Clone, Copy, Debug)]
pub struct Adapter<'a> {
    pub down: &'a [f32],
    pub down_bias: &'a [f32],
    pub up: &'a [f32],
    pub up_bias: &'a [f32],
    pub mid: usize,
    pub act: Activation,
}

impl Adapter<'_> {
    /// Whether the lengths fit a conv of `cout` output channels.
    pub fn check(&self, cout: usize) -> Result<(), String> {
        let mc = self.mid.checked_mul(cout);
        if self.mid == 0 || self.mid > cout {
            return Err(format!("adapter bottleneck of {} channels: it must be 1 to {cout}", self.mid));
        }
        if Some(self.down.len()) != mc
            || Some(self.up.len()) != mc
            || self.down_bias.len() != self.mid
            || self.up_bias.len() != cout
        {
            return Err(format!(
                "adapter down has {} values, up {}, biases {} and {} (needs {} x {cout}, {cout} x {}, {} and {cout})",
                self.down.len(),
                self.up.len(),
                self.down_bias.len(),
                self.up_bias.len(),
                self.mid,
                self.mid,
                self.mid
            ));
        }
        Ok(())
    }
}

/// The adapter on one tile `y` (`cout` rows of `tp` pixels, row-major, already scaled and
/// shifted), in place, then the step's activation `act`; `h` holds at least `mid · tp`
/// floats. Two GEMMs, for the GEMM paths' tiles (`im2col.rs`).
pub(super) fn apply_tile(ad: &Adapter, y: &mut [f32], cout: usize, tp: usize, h: &mut [f32], act: Option<Activation>) {
    let (mid, h) = (ad.mid, &mut h[..ad.mid * tp]);
    // h = act(down · y + down_bias)
    let yt = MatRef::row_major(&y[..cout * tp], cout, tp);
    sgemm(MatRef::row_major(ad.down, mid, cout), yt, MatMut::row_major(h, mid, tp), false, 1);
    bias_rows(h, ad.down_bias, tp, false);
    // A tile is one thread's work: its activations on this thread.
    elementwise::activation_chunk(ad.act, h);
    // y += up · h + up_bias, then act
    let dst = MatMut::row_major(&mut y[..cout * tp], cout, tp);
    sgemm(MatRef::row_major(ad.up, cout, mid), MatRef::row_major(h, mid, tp), dst, true, 1);
    let relu = act == Some(Activation::Relu);
    bias_rows(y, ad.up_bias, tp, relu);
    if let Some(f) = act.filter(|_| !relu) {
        elementwise::activation_chunk(f, &mut y[..cout * tp]);
    }
}

simd_fn! {
    /// Each row of `tp` values of `rows` plus its `bias[c]`, then the ReLU if `relu`.
    fn bias_rows(rows: &mut [f32], bias: &[f32], tp: usize, relu: bool) {
        for (row, &b) in rows.chunks_mut(tp).zip(bias) {
            if relu {
                row.iter_mut().for_each(|v| *v = elementwise::relu(*v + b));
            } else {
                row.iter_mut().for_each(|v| *v += b);
            }
        }
    }
}

/// Pixels per tile: [`apply_by_weights`]'s, and [`Fused`]'s where the tile's copy fits the
/// L1 cache ([`fused_tile`]), else half of this. Every backend's micro-tile divides half a
/// tile (AVX-512: four vectors in a whole tile, two otherwise; AVX2 four, in chunks of
/// 32 pixels; 4 lanes eight; 32 scalars).
const TILE: usize = 64;

/// Floats in a cache line.
const LINE: usize = 16;

/// The tile width of [`Fused`] for `cout` channels: a whole [`TILE`] where the tile's
/// rows copied side by side fit 32 KiB (of a 48 KiB L1 cache, beside `h` and the weights'
/// rows in use), else half of one. On AVX-512 a whole tile takes micro-tiles of 6 rows by
/// 4 vectors (24 sums), half a tile 8 by 2 (16): ResNet-18's layer1 and layer2 adapters
/// (64 and 128 channels) took 0.80-0.91x the time with whole tiles of 6 by 4 against half
/// tiles of 8 by 2; layer3's (256 channels, whole tiles of 64 KiB) 0.96-1.0x, so it keeps
/// the half tiles (in-process A/B, conv and adapter, 1 and 2 threads, 2026-12-06).
fn fused_tile(cout: usize) -> usize {
    if cout * TILE * size_of::<f32>() <= 32 << 10 { TILE } else { TILE / 2 }
}

/// Scratch floats of one worker of [`apply_fused`]: a tile's bottleneck rows, and a tail
/// tile of the output and of the residual.
pub(super) fn fused_scratch_len(cout: usize, mid: usize) -> usize {
    (mid + 2 * cout) * fused_tile(cout)
}

/// The adapter of a conv step on its output `[n, cout, oh, ow]` (scaled and shifted), in
/// place, plus the residual `res` if given, then the activation `act`: tile by tile of
/// [`TILE`] pixels, both projections in registers ([`Fused`]). The threads share the
/// pixels in whole half tiles, each its own run of every channel plane, except where the
/// weights outweigh the output ([`apply_by_weights`]). (Sharing `down` by tiles and `up`
/// by channels instead measured 0.972 of the old two-GEMM path's time in ResNet-18 at two
/// threads, against this path's 0.956; each thread summing `down` over its own channels
/// in its conv part, then `up` after a join, 1.099 of the adapter-free plan's time against
/// 1.055.)
pub(super) fn apply_fused(
    s: &Conv2dShape,
    ad: &Adapter,
    out: &mut [f32],
    act: Option<Activation>,
    res: Option<&[f32]>,
    scratch: &mut [f32],
    threads: usize,
) {
    let (cout, plane) = (s.cout, s.oh * s.ow);
    if plane == 0 || s.n == 0 {
        return;
    }
    if by_weights(s, ad.mid, threads) {
        return apply_by_weights(s, ad, out, act, res, scratch, threads);
    }
    // The threads share whole half tiles (a 28x28 plane: 25 and 24 of them).
    let unit = TILE / 2;
    let tiles = plane.div_ceil(unit);
    let total = s.n * tiles;
    let workers = threads.max(1).min(total);
    let bound = |w: usize| w * total / workers;
    // Each worker's runs of pixels: per image it touches, one segment of every channel plane.
    let mut pieces: Vec<Vec<Piece>> = (0..workers).map(|_| Vec::new()).collect();
    for (i, image) in out.chunks_mut(cout * plane).enumerate() {
        let (t0, t1) = (i * tiles, (i + 1) * tiles);
        let mut widths: Vec<(usize, usize)> = Vec::with_capacity(workers);
        for (w, mine) in pieces.iter_mut().enumerate() {
            let (a, b) = (bound(w).max(t0) - t0, bound(w + 1).min(t1).saturating_sub(t0));
            if a < b {
                let width = (b * unit).min(plane) - a * unit;
                widths.push((w, width));
                let res = res.map(|r| &r[i * cout * plane + a * unit..]);
                mine.push(Piece { rows: Vec::with_capacity(cout), res, tp: width });
            }
        }
        for row in image.chunks_mut(plane) {
            let mut rest = row;
            for &(w, width) in &widths {
                let (seg, tail) = std::mem::take(&mut rest).split_at_mut(width);
                rest = tail;
                pieces[w].last_mut().expect("a piece per image").rows.push(seg);
            }
        }
    }
    let per = fused_scratch_len(cout, ad.mid);
    let run = |(pieces, scratch): (Vec<Piece>, &mut [f32])| {
        for mut p in pieces {
            let res = p.res.map(|data| Strided { data, stride: plane, at: 0 });
            pulp::Arch::new().dispatch(Fused { ad, rows: &mut p.rows, res, tp: p.tp, act, scratch: &mut *scratch });
        }
    };
    if workers == 1 {
        run((pieces.pop().expect("one worker"), scratch));
    } else {
        pieces.into_par_iter().zip(scratch.par_chunks_mut(per)).for_each(run);
    }
}

/// Implements `pulp::WithSimd` for a pass over tiles with a `run::<S, MR, NV, HV>`
/// method: micro-tiles of `MR` rows by `NV` vectors across a tile, or `HV` across half a
/// tile (a narrow tail); sums in 24 or 16 of the 32 AVX-512 registers (24 where the
/// pass's rule says it runs whole tiles), 12 of the 16 AVX2 ones.
macro_rules! tile_pass {
    ($($t:ty => |$p:ident| $wide:expr),*) => {$(
        impl pulp::WithSimd for $t {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: pulp::Simd>(self, simd: S) {
                let $p = &self;
                match size_of::<S::f32s>() / size_of::<f32>() {
                    16 if $wide => self.run::<S, 6, 4, 2>(simd),
                    16 => self.run::<S, 8, 2, 1>(simd),
                    8 => self.run::<S, 3, 4, 2>(simd),
                    4 => self.run::<S, 2, 8, 4>(simd),
                    _ => self.run::<S, 2, { TILE / 2 }, { TILE / 4 }>(simd),
                }
            }
        }
    )*};
}

// Whether a pass runs whole tiles (the AVX-512 micro-tile for them): [`Fused`] by its
// channel count, the passes of [`apply_by_weights`] always.
tile_pass!(
    Fused<'_, '_> => |p| fused_tile(p.rows.len()) == TILE,
    ByRows<'_> => |_p| true,
    ByChannels<'_> => |_p| true
);

/// Scratch floats [`apply_fused`] needs at this thread count.
pub(super) fn fused_after_len(s: &Conv2dShape, mid: usize, threads: usize) -> usize {
    let per_thread = threads.max(1) * fused_scratch_len(s.cout, mid);
    if by_weights(s, mid, threads) {
        per_thread.max(mid * (s.oh * s.ow).div_ceil(TILE) * TILE + threads * 2 * s.cout * TILE)
    } else {
        per_thread
    }
}

/// Whether [`apply_fused`] shares the adapter's weights between the threads instead of
/// the pixels: when the two weights hold more values than the output (ResNet-18's 14x14
/// and 7x7 stages), each thread would otherwise stream both whole weights for a few
/// tiles.
fn by_weights(s: &Conv2dShape, mid: usize, threads: usize) -> bool {
    threads > 1 && 2 * mid > s.n * s.oh * s.ow
}

/// [`apply_fused`] sharing the weights: per image, `h` of every tile by bottleneck rows
/// (each thread reads its rows of `down`), a join, then `y` by channels (its rows of `up`,
/// and the planes it writes).
fn apply_by_weights(
    s: &Conv2dShape,
    ad: &Adapter,
    out: &mut [f32],
    act: Option<Activation>,
    res: Option<&[f32]>,
    scratch: &mut [f32],
    threads: usize,
) {
    let (cout, mid, plane) = (s.cout, ad.mid, s.oh * s.ow);
    let stride = plane.div_ceil(TILE) * TILE;
    let (hs, pads) = scratch.split_at_mut(mid * stride);
    let k = Kernel::new(ad, cout, act);
    // Whole micro-tiles of rows and channels a thread.
    let rows_per = mid.div_ceil(threads).next_multiple_of(8).min(mid);
    let chans_per = cout.div_ceil(threads).next_multiple_of(8).min(cout);
    let pad_len = 2 * cout * TILE;
    for (i, image) in out.chunks_mut(cout * plane).enumerate() {
        let res = res.map(|r| &r[i * cout * plane..][..cout * plane]);
        let y: &[f32] = image;
        hs.par_chunks_mut(rows_per * stride).zip(pads.par_chunks_mut(pad_len)).enumerate().for_each(|(w, (h, pad))| {
            let rows = w * rows_per..((w + 1) * rows_per).min(mid);
            pulp::Arch::new().dispatch(ByRows { k, y, plane, rows, h, pad });
        });
        let h: &[f32] = hs;
        image.par_chunks_mut(chans_per * plane).zip(pads.par_chunks_mut(pad_len)).enumerate().for_each(
            |(w, (planes, pad))| {
                let c0 = w * chans_per;
                let chans = c0..(c0 + chans_per).min(cout);
                pulp::Arch::new().dispatch(ByChannels { k, planes, chans, plane, res, h, pad, act });
            },
        );
    }
}

/// The width the tile at `at` of a run of `plane` pixels is computed in: a whole tile, or
/// half of one for a tail that fits it.
fn tile_width(tile: usize, plane: usize, at: usize) -> usize {
    if plane - at > tile / 2 { tile } else { tile / 2 }
}

/// Phase one of [`apply_by_weights`]: bottleneck rows `rows` of every tile of image `y`
/// into `h` (rows a padded plane apart), a tail tile through `pad`.
struct ByRows<'a> {
    k: Kernel<'a>,
    y: &'a [f32],
    plane: usize,
    rows: std::ops::Range<usize>,
    h: &'a mut [f32],
    pad: &'a mut [f32],
}

impl ByRows<'_> {
    #[inline(always)]
    fn run<S: pulp::Simd, const MR: usize, const NV: usize, const HV: usize>(self, simd: S) {
        let ByRows { k, y, plane, rows, h, pad } = self;
        let stride = plane.div_ceil(TILE) * TILE;
        for at in (0..plane).step_by(TILE) {
            let ht = &mut h[at..];
            if at + TILE <= plane {
                k.down_rows::<S, MR, NV>(simd, (&y[at..], plane), rows.clone(), ht, stride, TILE);
                continue;
            }
            let rem = plane - at;
            let pad = &mut pad[..k.cout * TILE];
            for (c, d) in pad.chunks_mut(TILE).enumerate() {
                pad_row(d, &y[c * plane + at..][..rem]);
            }
            if tile_width(TILE, plane, at) < TILE {
                k.down_rows::<S, MR, HV>(simd, (pad, TILE), rows.clone(), ht, stride, TILE / 2);
            } else {
                k.down_rows::<S, MR, NV>(simd, (pad, TILE), rows.clone(), ht, stride, TILE);
            }
        }
        if k.inner.is_none() {
            elementwise::activation_chunk(k.ad.act, h);
        }
    }
}

/// Phase two of [`apply_by_weights`]: channels `chans` (their planes `planes`) of every
/// tile from every tile's `h`, plus the residual `res` (the image's), then `act`.
struct ByChannels<'a> {
    k: Kernel<'a>,
    planes: &'a mut [f32],
    chans: std::ops::Range<usize>,
    plane: usize,
    res: Option<&'a [f32]>,
    h: &'a [f32],
    pad: &'a mut [f32],
    act: Option<Activation>,
}

impl ByChannels<'_> {
    #[inline(always)]
    fn run<S: pulp::Simd, const MR: usize, const NV: usize, const HV: usize>(self, simd: S) {
        let ByChannels { k, planes, chans, plane, res, h, pad, act } = self;
        let (stride, c0, cout) = (plane.div_ceil(TILE) * TILE, chans.start, k.cout);
        let (py, pr) = pad.split_at_mut(cout * TILE);
        for at in (0..plane).step_by(TILE) {
            let ht = &h[at..];
            if at + TILE <= plane {
                let r = res.map(|data| Strided { data, stride: plane, at });
                let mut y = StridedMut { data: &mut *planes, stride: plane, c0, at };
                k.up_chans::<S, MR, NV, _, _>(simd, &mut y, (r.as_ref(), None), chans.clone(), (ht, stride), TILE);
                continue;
            }
            let rem = plane - at;
            for c in chans.clone() {
                pad_row(&mut py[c * TILE..][..TILE], &planes[(c - c0) * plane + at..][..rem]);
                if let Some(r) = res {
                    pad_row(&mut pr[c * TILE..][..TILE], &r[c * plane + at..][..rem]);
                }
            }
            let r = res.map(|_| Strided { data: &*pr, stride: TILE, at: 0 });
            let mut y = StridedMut { data: &mut *py, stride: TILE, c0: 0, at: 0 };
            if tile_width(TILE, plane, at) < TILE {
                k.up_chans::<S, MR, HV, _, _>(simd, &mut y, (r.as_ref(), None), chans.clone(), (ht, stride), TILE / 2);
            } else {
                k.up_chans::<S, MR, NV, _, _>(simd, &mut y, (r.as_ref(), None), chans.clone(), (ht, stride), TILE);
            }
            for c in chans.clone() {
                planes[(c - c0) * plane + at..][..rem].copy_from_slice(&py[c * TILE..][..rem]);
            }
        }
        if let Some(f) = act.filter(|_| k.outer.is_none()) {
            elementwise::activation_chunk(f, planes);
        }
    }
}

/// [`Strided`] that the kernel writes: channels from `c0` on (a thread's planes, or a
/// padded tail tile of `TILE`-wide rows).
struct StridedMut<'s> {
    data: &'s mut [f32],
    stride: usize,
    c0: usize,
    at: usize,
}

impl TileRows for StridedMut<'_> {
    #[inline(always)]
    fn row(&self, c: usize) -> &[f32] {
        &self.data[(c - self.c0) * self.stride + self.at..]
    }
}

impl TileRowsMut for StridedMut<'_> {
    #[inline(always)]
    fn row_mut(&mut self, c: usize) -> &mut [f32] {
        &mut self.data[(c - self.c0) * self.stride + self.at..]
    }
}

/// The adapter of one part of a conv split by rows (so holding every channel of its
/// pixels), on the planes its thread just wrote, image by image: [`Fused`] on the part's
/// rows, plus the residual `res` (the whole output's shape) and the step's activation.
pub(super) fn apply_part(
    s: &Conv2dShape,
    ad: &Adapter,
    part: &mut super::split::Part,
    act: Option<Activation>,
    res: Option<&[f32]>,
    scratch: &mut [f32],
) {
    let (cout, plane, n0) = (s.cout, s.oh * s.ow, part.n0);
    for i in 0..part.planes_mut().len() / cout {
        let n = n0 + i;
        let (lo, hi) = part.rows_of(n, s.oh);
        let rows = &mut part.planes_mut()[i * cout..][..cout];
        let res = res.map(|r| Strided { data: &r[n * cout * plane + lo * s.ow..], stride: plane, at: 0 });
        let tp = (hi - lo) * s.ow;
        pulp::Arch::new().dispatch(Fused { ad, rows, res, tp, act, scratch: &mut *scratch });
    }
}

/// One worker's run of `tp` pixels of one image: a segment of each channel plane, and of
/// the residual's.
struct Piece<'r> {
    rows: Vec<&'r mut [f32]>,
    res: Option<&'r [f32]>,
    tp: usize,
}

/// The adapter over `tp` pixels of every channel (`rows`, one segment of `tp` values per
/// channel), tile by tile: per tile `h = act(down · y + bd)` by micro-tiles of `MR`
/// bottleneck rows (sums in registers, `y` copied to scratch), stored to a tile of scratch,
/// then `y = y + up · h + bu (+ res)` by micro-tiles of `MR` channels, the step's
/// clamp applied as each vector is stored. A tail narrower than a tile goes through
/// scratch, zero-padded.
struct Fused<'a, 'r> {
    ad: &'a Adapter<'a>,
    rows: &'a mut [&'r mut [f32]],
    res: Option<Strided<'a>>,
    tp: usize,
    act: Option<Activation>,
    scratch: &'a mut [f32],
}

/// Channel rows of one tile: `row(c)` starts at the tile's first pixel.
trait TileRows {
    fn row(&self, c: usize) -> &[f32];
}

/// [`TileRows`] that [`Fused`] also writes.
trait TileRowsMut: TileRows {
    fn row_mut(&mut self, c: usize) -> &mut [f32];
}

/// Writable segments of the channel planes, from pixel `at` on.
struct SegmentsMut<'s, 'r> {
    rows: &'s mut [&'r mut [f32]],
    at: usize,
}

/// Channel planes `stride` apart (a residual's image, from some pixel on), seen from pixel
/// `at` on.
#[derive(Clone, Copy)]
struct Strided<'s> {
    data: &'s [f32],
    stride: usize,
    at: usize,
}

impl TileRows for Strided<'_> {
    #[inline(always)]
    fn row(&self, c: usize) -> &[f32] {
        &self.data[c * self.stride + self.at..]
    }
}

impl TileRows for SegmentsMut<'_, '_> {
    #[inline(always)]
    fn row(&self, c: usize) -> &[f32] {
        &self.rows[c][self.at..]
    }
}

impl TileRowsMut for SegmentsMut<'_, '_> {
    #[inline(always)]
    fn row_mut(&mut self, c: usize) -> &mut [f32] {
        &mut self.rows[c][self.at..]
    }
}

impl Fused<'_, '_> {
    #[inline(always)]
    fn run<S: pulp::Simd, const MR: usize, const NV: usize, const HV: usize>(self, simd: S) {
        let Fused { ad, rows, res, tp, act, scratch } = self;
        let (cout, mid) = (rows.len(), ad.mid);
        let k = Kernel::new(ad, cout, act);
        let tw = fused_tile(cout);
        let (h, rest) = scratch.split_at_mut(mid * tw);
        let (ty, rest) = rest.split_at_mut(cout * tw);
        let tr = &mut rest[..cout * tw];
        let full = tp / tw * tw;
        for at in (0..full).step_by(tw) {
            // The next tile's rows, a plane apart: more streams than the hardware
            // prefetcher follows.
            if at + 2 * tw <= tp {
                for row in rows.iter() {
                    for line in (at + tw..at + 2 * tw).step_by(LINE) {
                        prefetch(&row[line]);
                    }
                }
            }
            let r = res.map(|r| Strided { at, ..r });
            // The tile's rows side by side, for `down` to read at one stride.
            for (c, row) in rows.iter().enumerate() {
                ty[c * tw..][..tw].copy_from_slice(&row[at..at + tw]);
            }
            k.down_tile::<S, MR, NV>(simd, (ty, tw), h, tw);
            // The old `y` from the copy (in L1), not its planes: at two threads the adapter's
            // time 0.84-0.90x on ResNet-18's 56x56 and 28x28 layers.
            let (mut y, yin) = (SegmentsMut { rows: &mut *rows, at }, Strided { data: &*ty, stride: tw, at: 0 });
            k.up_tile::<S, MR, NV, _, _>(simd, &mut y, r.as_ref(), h, tw, Some(&yin));
        }
        if full < tp {
            let rem = tp - full;
            for (c, row) in rows.iter().enumerate() {
                pad_row(&mut ty[c * tw..][..tw], &row[full..tp]);
                if let Some(r) = res {
                    pad_row(&mut tr[c * tw..][..tw], &r.row(c)[full..tp]);
                }
            }
            let r = res.map(|_| Strided { data: &*tr, stride: tw, at: 0 });
            let half = tile_width(tw, tp, full) < tw;
            if half {
                k.down_tile::<S, MR, HV>(simd, (ty, tw), h, tw / 2);
            } else {
                k.down_tile::<S, MR, NV>(simd, (ty, tw), h, tw);
            }
            let mut y = StridedMut { data: &mut *ty, stride: tw, c0: 0, at: 0 };
            if half {
                k.up_tile::<S, MR, HV, _, _>(simd, &mut y, r.as_ref(), h, tw / 2, None);
            } else {
                k.up_tile::<S, MR, NV, _, _>(simd, &mut y, r.as_ref(), h, tw, None);
            }
            for (c, row) in rows.iter_mut().enumerate() {
                row[full..tp].copy_from_slice(&ty[c * tw..][..rem]);
            }
        }
        if let Some(f) = act.filter(|_| k.outer.is_none()) {
            for row in rows.iter_mut() {
                elementwise::activation_chunk(f, &mut row[..tp]);
            }
        }
    }
}

/// What every tile of [`Fused`] shares.
#[derive(Clone, Copy)]
struct Kernel<'a> {
    ad: &'a Adapter<'a>,
    cout: usize,
    /// The adapter's activation when it is a clamp (applied in registers).
    inner: Option<(f32, f32)>,
    /// The step's activation when it is a clamp.
    outer: Option<(f32, f32)>,
}

impl<'a> Kernel<'a> {
    fn new(ad: &'a Adapter<'a>, cout: usize, act: Option<Activation>) -> Kernel<'a> {
        Kernel { ad, cout, inner: clamp_bounds(ad.act), outer: act.and_then(clamp_bounds) }
    }

    /// The tile's `h = act(down · y + bd)`, `mid` rows of `cols` pixels in `h`.
    #[inline(always)]
    fn down_tile<S: pulp::Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        y: (&[f32], usize),
        h: &mut [f32],
        cols: usize,
    ) {
        let mid = self.ad.mid;
        let h = &mut h[..mid * cols];
        self.down_rows::<S, MR, NV>(simd, y, 0..mid, h, cols, cols);
        if self.inner.is_none() {
            elementwise::activation_chunk(self.ad.act, h);
        }
    }

    /// Bottleneck rows `rows` of the tile's `h` (before a non-clamp activation) for its
    /// first `cols` pixels, `NV` vectors at a time, into `h`, its rows `stride` floats
    /// apart from `rows.start`.
    #[inline(always)]
    fn down_rows<S: pulp::Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        (y, ys): (&[f32], usize),
        rows: std::ops::Range<usize>,
        h: &mut [f32],
        stride: usize,
        cols: usize,
    ) {
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let hs = stride / lanes;
        let (hv, _) = S::as_mut_simd_f32s(h);
        let mut m = rows.start;
        while m < rows.end {
            let left = rows.end - m;
            let mut step = 0;
            for j in (0..cols).step_by(NV * lanes) {
                let (y, at) = ((&y[j..], ys), (m - rows.start) * hs + j / lanes);
                step = if left >= MR {
                    self.down::<S, MR, NV>(simd, y, m, &mut hv[at..], hs)
                } else if left >= 4 && MR > 4 {
                    self.down::<S, 4, NV>(simd, y, m, &mut hv[at..], hs)
                } else if left >= 2 {
                    self.down::<S, 2, NV>(simd, y, m, &mut hv[at..], hs)
                } else {
                    self.down::<S, 1, NV>(simd, y, m, &mut hv[at..], hs)
                };
            }
            m += step;
        }
    }

    /// The tile's `y += up · h + bu (+ res)`, clamped; `y`'s old values read from `yin`
    /// where given (the tile's copy made for `down`, in L1) instead of from `y` itself.
    #[inline(always)]
    fn up_tile<S: pulp::Simd, const MR: usize, const NV: usize, Y: TileRowsMut, R: TileRows>(
        self,
        simd: S,
        y: &mut Y,
        res: Option<&R>,
        h: &[f32],
        cols: usize,
        yin: Option<&Strided>,
    ) {
        self.up_chans::<S, MR, NV, Y, R>(simd, y, (res, yin), 0..self.cout, (&h[..self.ad.mid * cols], cols), cols);
    }

    /// Channels `chans` of the tile's first `cols` pixels, `NV` vectors at a time: `y += up
    /// · h + bu (+ res)`, clamped; `h`'s rows `stride` floats apart; the old `y` from `yin`
    /// if given.
    #[inline(always)]
    fn up_chans<S: pulp::Simd, const MR: usize, const NV: usize, Y: TileRowsMut, R: TileRows>(
        self,
        simd: S,
        y: &mut Y,
        (res, yin): (Option<&R>, Option<&Strided>),
        chans: std::ops::Range<usize>,
        (h, stride): (&[f32], usize),
        cols: usize,
    ) {
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        let mut c = chans.start;
        while c < chans.end {
            let left = chans.end - c;
            let mut step = 0;
            for j in (0..cols).step_by(NV * lanes) {
                step = if left >= MR {
                    self.up::<S, MR, NV, Y, R>(simd, y, (res, yin), c, (h, j), stride)
                } else if left >= 4 && MR > 4 {
                    self.up::<S, 4, NV, Y, R>(simd, y, (res, yin), c, (h, j), stride)
                } else if left >= 2 {
                    self.up::<S, 2, NV, Y, R>(simd, y, (res, yin), c, (h, j), stride)
                } else {
                    self.up::<S, 1, NV, Y, R>(simd, y, (res, yin), c, (h, j), stride)
                };
            }
            c += step;
        }
    }

    /// Bottleneck rows `m0..m0 + MR` of the tile's `h`, into `hv`'s rows `hs` vectors
    /// apart.
    #[inline(always)]
    fn down<S: pulp::Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        (y, ystride): (&[f32], usize),
        m0: usize,
        hv: &mut [S::f32s],
        hs: usize,
    ) -> usize {
        let cout = self.cout;
        let a: [&[f32]; MR] = std::array::from_fn(|r| &self.ad.down[(m0 + r) * cout..][..cout]);
        let acc = strided_rows_product::<S, MR, NV>(simd, a, y, ystride);
        for (r, sums) in acc.iter().enumerate() {
            let b = simd.splat_f32s(self.ad.down_bias[m0 + r]);
            for (d, &v) in hv[r * hs..][..NV].iter_mut().zip(sums) {
                let z = simd.add_f32s(v, b);
                *d = self.inner.map_or(z, |cl| super::clamp_vector(simd, z, cl));
            }
        }
        MR
    }

    /// Channels `c0..c0 + MR` of the tile's `NV` vectors from pixel `j` on: `y += up · h
    /// + bu (+ res)`, clamped; `h`'s rows `stride` floats apart; the old `y` read from
    /// `yin` if given.
    #[inline(always)]
    fn up<S: pulp::Simd, const MR: usize, const NV: usize, Y: TileRowsMut, R: TileRows>(
        self,
        simd: S,
        y: &mut Y,
        (res, yin): (Option<&R>, Option<&Strided>),
        c0: usize,
        (h, j): (&[f32], usize),
        stride: usize,
    ) -> usize {
        let (mid, width) = (self.ad.mid, NV * size_of::<S::f32s>() / size_of::<f32>());
        let a: [&[f32]; MR] = std::array::from_fn(|r| &self.ad.up[(c0 + r) * mid..][..mid]);
        let acc = strided_rows_product::<S, MR, NV>(simd, a, &h[j..], stride);
        for (r, sums) in acc.iter().enumerate() {
            let c = c0 + r;
            let b = simd.splat_f32s(self.ad.up_bias[c]);
            let rv = res.map(|q| S::as_simd_f32s(&q.row(c)[j..][..width]).0);
            let yv = yin.map(|q| S::as_simd_f32s(&q.row(c)[j..][..width]).0);
            let (dst, _) = S::as_mut_simd_f32s(&mut y.row_mut(c)[j..][..width]);
            for v in 0..NV {
                let old = yv.map_or(dst[v], |q| q[v]);
                let mut z = simd.add_f32s(simd.add_f32s(sums[v], b), old);
                if let Some(rv) = rv {
                    z = simd.add_f32s(z, rv[v]);
                }
                dst[v] = self.outer.map_or(z, |cl| super::clamp_vector(simd, z, cl));
            }
        }
        MR
    }
}

#[cfg(test)]
mod tests {
    use super::super::split::split_shape;
    use super::super::{ConvAlgo, adapter_scratch_len, conv2d_adapter, pack_weight, packed_weight_len};
    use super::*;
    use crate::kernels::Epilogue;
    use crate::kernels::testutil::{assert_close, data};

    fn act64(act: Activation, v: f64) -> f64 {
        match act {
            Activation::Relu => v.max(0.0),
            Activation::Tanh => v.tanh(),
            Activation::Sigmoid => 1.0 / (1.0 + (-v).exp()),
            Activation::Silu => v / (1.0 + (-v).exp()),
            a => panic!("no reference for {a:?}"),
        }
    }

    /// Conv, scale and shift, adapter, ReLU: naive loops in f64, PyTorch's layouts.
    #[allow(clippy::too_many_arguments)]
    fn reference(
        s: &Conv2dShape,
        x: &[f32],
        w: &[f32],
        scale: &[f32],
        shift: &[f32],
        ad: &Adapter,
        act: Option<Activation>,
    ) -> Vec<f32> {
        let (cin_g, cout_g, plane) = (s.cin / s.groups, s.cout / s.groups, s.oh * s.ow);
        let mut y = vec![0.0f64; s.n * s.cout * plane];
        for n in 0..s.n {
            for co in 0..s.cout {
                let g = co / cout_g;
                for oy in 0..s.oh {
                    for ox in 0..s.ow {
                        let mut acc = 0.0f64;
                        for ci in 0..cin_g {
                            for ky in 0..s.kh {
                                for kx in 0..s.kw {
                                    let iy = (oy * s.stride_h + ky * s.dil_h) as isize - s.pad_h as isize;
                                    let ix = (ox * s.stride_w + kx * s.dil_w) as isize - s.pad_w as isize;
                                    if iy < 0 || ix < 0 || iy >= s.h as isize || ix >= s.w as isize {
                                        continue;
                                    }
                                    let xv = x[((n * s.cin + g * cin_g + ci) * s.h + iy as usize) * s.w + ix as usize];
                                    let wv = w[((co * cin_g + ci) * s.kh + ky) * s.kw + kx];
                                    acc += f64::from(xv) * f64::from(wv);
                                }
                            }
                        }
                        y[(n * s.cout + co) * plane + oy * s.ow + ox] =
                            acc * f64::from(scale[co]) + f64::from(shift[co]);
                    }
                }
            }
        }
        let mut out = vec![0.0f32; y.len()];
        for n in 0..s.n {
            for p in 0..plane {
                let at = |c: usize| (n * s.cout + c) * plane + p;
                let h: Vec<f64> = (0..ad.mid)
                    .map(|m| {
                        let d: f64 = (0..s.cout).map(|c| f64::from(ad.down[m * s.cout + c]) * y[at(c)]).sum();
                        act64(ad.act, d + f64::from(ad.down_bias[m]))
                    })
                    .collect();
                for c in 0..s.cout {
                    let u: f64 = (0..ad.mid).map(|m| f64::from(ad.up[c * ad.mid + m]) * h[m]).sum();
                    let z = y[at(c)] + u + f64::from(ad.up_bias[c]);
                    out[at(c)] = act.map_or(z, |a| a.reference(z)) as f32;
                }
            }
        }
        out
    }

    fn shape(
        n: usize,
        cin: usize,
        hw: (usize, usize),
        cout: usize,
        k: usize,
        stride: usize,
        groups: usize,
    ) -> Conv2dShape {
        let pad = k / 2;
        let oh = (hw.0 + 2 * pad - k) / stride + 1;
        let ow = (hw.1 + 2 * pad - k) / stride + 1;
        Conv2dShape {
            n,
            cin,
            h: hw.0,
            w: hw.1,
            cout,
            kh: k,
            kw: k,
            stride_h: stride,
            stride_w: stride,
            pad_h: pad,
            pad_w: pad,
            dil_h: 1,
            dil_w: 1,
            groups,
            oh,
            ow,
        }
    }

    /// `algo` on `s` with an adapter of `mid` channels, 1 and 2 threads, with and
    /// without the ReLU, against the reference; returns whether each thread count ran
    /// the adapter in the tiles.
    fn check(s: &Conv2dShape, algo: ConvAlgo, mid: usize, act: Activation) -> Vec<bool> {
        assert!(algo.supports(s), "{} on {s:?}", algo.name());
        let x = data(s.n * s.cin * s.h * s.w, 11);
        let fan_in = s.cin / s.groups * s.kh * s.kw;
        let w: Vec<f32> = data(fan_in * s.cout, 12).iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect();
        let scale: Vec<f32> = data(s.cout, 13).iter().map(|v| 0.5 + v).collect();
        let shift = data(s.cout, 14);
        let down: Vec<f32> = data(mid * s.cout, 15).iter().map(|v| v / (s.cout as f32).sqrt()).collect();
        let (down_bias, up_bias) = (data(mid, 16), data(s.cout, 18));
        let up: Vec<f32> = data(s.cout * mid, 17).iter().map(|v| v / (mid as f32).sqrt()).collect();
        let ad = Adapter { down: &down, down_bias: &down_bias, up: &up, up_bias: &up_bias, mid, act };
        let mut packed = vec![0.0; packed_weight_len(s, algo)];
        pack_weight(s, algo, &w, &mut packed);
        let mut in_tile = Vec::new();
        for step_act in [None, Some(Activation::Relu), Some(Activation::Hardswish)] {
            let relu = step_act == Some(Activation::Relu);
            let want = reference(s, &x, &w, &scale, &shift, &ad, step_act);
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: step_act };
            for threads in [1, 2, 3] {
                let need = adapter_scratch_len(s, algo, 0, mid, threads).expect("a size");
                let mut scratch = vec![f32::NAN; need];
                let mut out = vec![f32::NAN; want.len()];
                conv2d_adapter(s, algo, &packed, None, Some(&ad), &ep, &x, &mut out, &mut scratch, threads);
                let tol = if matches!(algo, ConvAlgo::Winograd4) { 1e-4 } else { 2e-5 };
                assert_close(&out, &want, tol);
                if relu && threads < 3 {
                    in_tile.push(super::super::adapter_in_tile(s, algo, threads));
                }
            }
        }
        in_tile
    }

    #[test]
    fn every_algorithm_matches_the_reference() {
        // Gemm1x1 and im2col split by rows: the adapter runs in the tiles.
        assert_eq!(check(&shape(2, 8, (9, 7), 16, 1, 1, 1), ConvAlgo::Gemm1x1, 4, Activation::Relu), [true, true]);
        assert_eq!(check(&shape(1, 5, (11, 9), 12, 3, 2, 1), ConvAlgo::Im2col, 3, Activation::Silu), [true, true]);
        assert_eq!(check(&shape(2, 6, (9, 10), 8, 3, 1, 1), ConvAlgo::Im2col, 2, Activation::Tanh), [true, true]);
        // Winograd, weight panels and depthwise: after the conv, over the output.
        assert_eq!(check(&shape(2, 8, (13, 12), 40, 3, 2, 1), ConvAlgo::Panels, 8, Activation::Relu), [false, false]);
        for algo in [ConvAlgo::Winograd2, ConvAlgo::Winograd4] {
            assert_eq!(check(&shape(2, 6, (13, 12), 8, 3, 1, 1), algo, 4, Activation::Relu), [false, false]);
        }
        assert_eq!(
            check(&shape(2, 8, (10, 9), 8, 3, 1, 8), ConvAlgo::Depthwise, 2, Activation::Sigmoid),
            [false, false]
        );
        // Groups: after the conv.
        assert_eq!(check(&shape(1, 8, (7, 6), 8, 3, 1, 2), ConvAlgo::Im2col, 4, Activation::Relu), [false, false]);
        // A stem-like layer (a direct conv without the adapter) of a 5x5 plane, split by
        // channels at two threads: the im2col register tiles, then the adapter after.
        let stem = shape(1, 3, (10, 10), 64, 3, 2, 1);
        assert!(super::super::direct::applies(&stem) && super::super::pointwise::applies_unfolded(&stem));
        assert_eq!(check(&stem, ConvAlgo::Im2col, 4, Activation::Relu), [true, false]);
    }

    #[test]
    fn a_channel_split_applies_it_after_the_conv() {
        let s = shape(1, 16, (4, 4), 64, 3, 1, 1);
        assert_eq!(split_shape(&s, ConvAlgo::Im2col, 2), (1, 2));
        assert_eq!(check(&s, ConvAlgo::Im2col, 16, Activation::Relu), [true, false]);
        let s = shape(1, 24, (5, 5), 64, 1, 1, 1);
        assert_eq!(check(&s, ConvAlgo::Gemm1x1, 8, Activation::Relu), [true, false]);
    }

    #[test]
    fn large_planes_and_several_images() {
        // Many tiles a part, split by rows (in the parts) on two and three threads.
        let s = shape(2, 4, (60, 60), 16, 3, 1, 1);
        check(&s, ConvAlgo::Winograd4, 4, Activation::Relu);
        let s = shape(3, 4, (30, 30), 16, 3, 1, 1);
        check(&s, ConvAlgo::Winograd2, 4, Activation::Relu);
        // Split by channels on two threads: after the conv, pixels shared.
        let s = shape(1, 8, (14, 14), 64, 3, 1, 1);
        assert_eq!(split_shape(&s, ConvAlgo::Winograd4, 2), (1, 2));
        check(&s, ConvAlgo::Winograd4, 32, Activation::Relu);
    }

    /// The adapter on planes `[n, cout, plane]` by the definition, in f64, then `act`.
    fn naive(y: &[f32], n: usize, cout: usize, plane: usize, ad: &Adapter, act: Option<Activation>) -> Vec<f32> {
        let mut out = vec![0.0f32; y.len()];
        for i in 0..n {
            for p in 0..plane {
                let at = |c: usize| f64::from(y[(i * cout + c) * plane + p]);
                let h: Vec<f64> = (0..ad.mid)
                    .map(|m| {
                        let d: f64 = (0..cout).map(|c| f64::from(ad.down[m * cout + c]) * at(c)).sum();
                        act64(ad.act, d + f64::from(ad.down_bias[m]))
                    })
                    .collect();
                for c in 0..cout {
                    let u: f64 = (0..ad.mid).map(|m| f64::from(ad.up[c * ad.mid + m]) * h[m]).sum();
                    let z = at(c) + u + f64::from(ad.up_bias[c]);
                    out[(i * cout + c) * plane + p] = act.map_or(z, |a| a.reference(z)) as f32;
                }
            }
        }
        out
    }

    /// [`apply_fused`] (AdaBN's way in) on planes of whole tiles, a tail of more and of less
    /// than half a tile, several images, pieces that cross images (3 images on 2 threads),
    /// bottlenecks that are not a whole micro-tile, and layers whose threads share the
    /// weights, against the definition.
    #[test]
    fn tiles_tails_and_pieces_match_the_definition() {
        for (n, cout, hw, mid, act) in [
            (1, 16, (8, 8), 8, Activation::Relu),
            (1, 16, (7, 7), 5, Activation::Relu),
            (3, 20, (9, 9), 5, Activation::Sigmoid),
            (2, 12, (4, 4), 3, Activation::Relu),
            (1, 19, (10, 5), 11, Activation::Tanh),
            // Weights larger than the output: shared by bottleneck rows and channels.
            (1, 32, (4, 5), 16, Activation::Sigmoid),
            (2, 40, (3, 3), 24, Activation::Relu),
            // ... over a whole tile and a tail.
            (1, 128, (9, 9), 64, Activation::Relu),
        ] {
            let s = shape(n, 4, hw, cout, 3, 1, 1);
            let plane = s.oh * s.ow;
            let (down, up) = (data(mid * cout, 21), data(cout * mid, 22));
            let (bd, bu) = (data(mid, 23), data(cout, 24));
            let ad = Adapter { down: &down, down_bias: &bd, up: &up, up_bias: &bu, mid, act };
            let y = data(n * cout * plane, 25);
            assert_eq!(by_weights(&s, mid, 2), 2 * mid > n * plane);
            for step_act in [None, Some(Activation::Relu), Some(Activation::Silu)] {
                let want = naive(&y, n, cout, plane, &ad, step_act);
                for threads in [1, 2, 3] {
                    let mut out = y.clone();
                    let mut scratch = vec![f32::NAN; threads * fused_scratch_len(cout, mid)];
                    super::super::adapter_after(&s, &ad, &mut out, step_act, &mut scratch, threads);
                    assert_close(&out, &want, 1e-5);
                }
            }
        }
    }

    /// [`Fused`] compiled for every SIMD width the machine has (each its own micro-tile
    /// and tail), on planes of whole tiles and a tail narrower or wider than half a tile,
    /// with a residual and ReLU.
    #[test]
    fn every_simd_width_matches_the_definition() {
        // Whole tiles, and (over 128 channels) half tiles.
        for (cout, mid) in [(13, 6), (131, 9)] {
            assert_eq!(fused_tile(cout) == TILE, cout <= 128);
            let tile = fused_tile(cout);
            for plane in [2 * tile + 7, tile + tile / 2 + 3] {
                simd_widths_match(cout, mid, plane);
            }
        }
    }

    fn simd_widths_match(cout: usize, mid: usize, plane: usize) {
        use crate::kernels::testutil::backends;
        let (down, up) = (data(mid * cout, 31), data(cout * mid, 32));
        let (bd, bu) = (data(mid, 33), data(cout, 34));
        let ad = Adapter { down: &down, down_bias: &bd, up: &up, up_bias: &bu, mid, act: Activation::Relu };
        let (y, res) = (data(cout * plane, 35), data(cout * plane, 36));
        let sum: Vec<f32> = y.iter().zip(&res).map(|(a, b)| a + b).collect();
        // The residual enters after the adapter: the definition on `y`, plus `res`, ReLU.
        let want: Vec<f32> = naive(&y, 1, cout, plane, &ad, None)
            .iter()
            .zip(&res)
            .map(|(&z, &r)| (f64::from(z) + f64::from(r)).max(0.0) as f32)
            .collect();
        assert!(sum.iter().any(|&v| v < 0.0), "ReLU has work to do");
        for b in backends() {
            let mut out = y.clone();
            let mut rows: Vec<&mut [f32]> = out.chunks_mut(plane).collect();
            let mut scratch = vec![f32::NAN; fused_scratch_len(cout, mid)];
            let res = Some(Strided { data: &res, stride: plane, at: 0 });
            let act = Some(Activation::Relu);
            b.run(Fused { ad: &ad, rows: &mut rows, res, tp: plane, act, scratch: &mut scratch });
            assert_close(&out, &want, 1e-5);
        }
    }

    /// A residual with an adapter is added after the adapter, then the activation: in the
    /// tiles (1x1, then a pass after), and after the conv (Winograd) in the adapter's last
    /// pass over small images (one of them split by channels) and over an image of several
    /// chunks, against the reference plus the sum.
    #[test]
    fn a_residual_comes_after_the_adapter() {
        use super::super::conv2d_fused;
        for (s, algo, mid) in [
            (shape(2, 8, (9, 7), 16, 1, 1, 1), ConvAlgo::Gemm1x1, 4),
            (shape(2, 6, (13, 12), 8, 3, 1, 1), ConvAlgo::Winograd2, 4),
            (shape(2, 8, (7, 7), 40, 3, 1, 1), ConvAlgo::Winograd2, 20),
            (shape(1, 4, (60, 60), 16, 3, 1, 1), ConvAlgo::Winograd2, 16),
            // Split by channels on two threads (a 5x5 plane, 64 channels), by rows on three.
            (shape(1, 8, (5, 5), 64, 3, 1, 1), ConvAlgo::Winograd2, 16),
        ] {
            let fan_in = s.cin * s.kh * s.kw;
            let x = data(s.n * s.cin * s.h * s.w, 41);
            let w: Vec<f32> = data(fan_in * s.cout, 42).iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect();
            let (scale, shift) = (data(s.cout, 43), data(s.cout, 44));
            let (down, up) = (data(mid * s.cout, 45), data(s.cout * mid, 46));
            let (down_bias, up_bias) = (data(mid, 47), data(s.cout, 48));
            let ad =
                Adapter { down: &down, down_bias: &down_bias, up: &up, up_bias: &up_bias, mid, act: Activation::Relu };
            let res = data(s.n * s.cout * s.oh * s.ow, 49);
            let mut packed = vec![0.0; packed_weight_len(&s, algo)];
            pack_weight(&s, algo, &w, &mut packed);
            let y = reference(&s, &x, &w, &scale, &shift, &ad, None);
            for act in [Some(Activation::Relu), Some(Activation::Silu)] {
                let want: Vec<f32> = y
                    .iter()
                    .zip(&res)
                    .map(|(&y, &r)| act64(act.expect("an activation"), f64::from(y) + f64::from(r)) as f32)
                    .collect();
                let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act };
                for threads in [1, 2, 3] {
                    if s.cout == 64 {
                        assert_eq!(split_shape(&s, algo, threads).1 > 1, threads == 2);
                    }
                    let mut scratch = vec![f32::NAN; adapter_scratch_len(&s, algo, 0, mid, threads).expect("a size")];
                    let mut out = vec![f32::NAN; want.len()];
                    conv2d_fused(
                        &s,
                        algo,
                        &packed,
                        None,
                        Some(&ad),
                        &ep,
                        &x,
                        Some(&res),
                        &mut out,
                        &mut scratch,
                        threads,
                    );
                    assert_close(&out, &want, 2e-5);
                }
            }
        }
    }

    #[test]
    fn bad_lengths_are_refused() {
        let (d, b) = (vec![0.0; 8], vec![0.0; 4]);
        let ad = Adapter { down: &d, down_bias: &b[..2], up: &d, up_bias: &b, mid: 2, act: Activation::Relu };
        assert_eq!(ad.check(4), Ok(()));
        let e = Adapter { up_bias: &b[..3], ..ad }.check(4).expect_err("short up bias");
        assert!(e.contains("adapter down has 8 values"), "{e}");
        let e = Adapter { mid: 0, ..ad }.check(4).expect_err("no bottleneck");
        assert!(e.contains("bottleneck of 0"), "{e}");
        assert!(ad.check(5).is_err());
    }
}
