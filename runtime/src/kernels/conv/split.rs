//! How the threads share one conv layer: by ranges of output rows (in whole Winograd tile
//! rows) or of output channels ([`split_shape`]); [`split`] hands each thread its [`Part`],
//! its own slices of the output planes, so threads never synchronise over the output (a
//! split by channels shares the unfolded tile or the Winograd input transform:
//! `im2col_shared`, `winograd_shared`).

use super::{Conv2dShape, ConvAlgo};

/// Output rows move between threads in units of this many rows (a Winograd tile row).
fn row_unit(algo: ConvAlgo) -> usize {
    match algo {
        ConvAlgo::Winograd2 => 2,
        ConvAlgo::Winograd4 => 4,
        _ => 1,
    }
}

/// How the threads share a layer: `(row parts, channel parts)`, one of them 1.
///
/// By output rows (in whole row units) when each thread gets enough pixels or tiles for
/// an efficient GEMM; by output channels when the image is small and the weight large
/// (late layers at small batch): then each thread reads only its rows of the weight,
/// at the price of unfolding or transforming the whole input itself.
pub(super) fn split_shape(s: &Conv2dShape, algo: ConvAlgo, threads: usize) -> (usize, usize) {
    let threads = threads.max(1);
    let unit = row_unit(algo);
    let units = s.n * s.oh.div_ceil(unit);
    // GEMM columns (pixels or tiles) per thread under a row split.
    let cols = units * s.ow.div_ceil(unit) / threads;
    let least = if unit > 1 {
        CHANNEL_SPLIT_TILES
    } else if expansion(s, algo) {
        EXPANSION_SPLIT_COLS
    } else {
        CHANNEL_SPLIT_COLS
    };
    if threads > 1 && s.groups == 1 && cols < least && s.cout >= 32 * threads {
        (1, threads)
    } else {
        (threads.min(units.max(1)), 1)
    }
}

/// GEMM columns per thread below which a layer with enough output channels is split by
/// channels. At 64, MobileNetV2's 14x14 expansions (98 pixels a thread) ran 1.1-1.3x
/// faster on two threads than on one: each thread packed the whole weight for GEMMs of
/// 98 columns. At 256 (14x14 planes split by channels, 28x28 ones still by rows) six CNNs
/// of the zoo ran 0.960-0.982x as long on two threads (MobileNetV2 0.977, ResNet-50
/// 0.978, ResNet-18 0.976, RegNetY-400MF 0.982, EfficientNet-B0 0.977, MobileNetV3-Large
/// 0.960; `benches/ab.py`, 8 alternating rounds, 2026-12-05); at 512 ResNet-18 and
/// RegNetY-400MF lost again (1.05, 1.02).
const CHANNEL_SPLIT_COLS: usize = 256;

/// Whether a layer is a 1x1 expansion: at least four output channels per input channel,
/// so that it writes four times what it reads.
fn expansion(s: &Conv2dShape, algo: ConvAlgo) -> bool {
    algo == ConvAlgo::Gemm1x1 && s.cout >= 4 * s.cin
}

/// GEMM columns per thread below which a 1x1 expansion ([`expansion`]) is split by
/// channels: each thread then writes whole planes, one contiguous block of the output,
/// and reads all of the (four times smaller) input. Split by rows, the two threads'
/// halves of every plane interleave in memory: writing 192 planes of 784 floats that
/// way took 2.9x as long as writing them in two contiguous halves (a loop of stores,
/// 2-core AMD EPYC, 2026-12-06), the cores' prefetchers pulling each other's lines.
/// MobileNetV2's 28x28 expansions (32 to 192 channels, 392 pixels a thread) then took
/// 0.82-0.91x the time at two threads, ResNet-50's 128 to 512 0.93-0.96x, EfficientNet-B0's
/// and MobileNetV3's 40 to 240 and 40 to 120 0.85-0.97x (old and new split alternating
/// run by run in one process, 300-400 pairs). Layers that do not expand lost: RegNetY's
/// 28x28 104 to 104 convs, between grouped convs split by rows, took 1.10-1.24x.
const EXPANSION_SPLIT_COLS: usize = 512;

/// Winograd tiles per thread below which a layer with enough output channels is split by
/// channels. When each thread of a channel split still transformed the whole input
/// itself, ResNet-18's 56x56 layers (F(4x4), 98 tiles a thread) ran 0.69-0.82x as long
/// split by rows on two threads, the model 0.95x (a 2-core Xeon, 2026-12-05, 5
/// alternating rounds); at 16 (its 28x28 layers, 24 tiles of 4x4 a thread, and 14x14
/// ones, 24 of 2x2, split by rows too) the model took 1.08x as long as at 32; 64
/// measured the same as 32. With the threads sharing the input transform
/// (`winograd_shared`), 128 (the 56x56 layers by channels too) took ResNet-18 1.07x as
/// long and ResNet-50 1.01x, 32 1.01x and 1.03x (8 rounds): 64 stays.
const CHANNEL_SPLIT_TILES: usize = 64;

/// How many threads share the layer.
pub(super) fn parts(s: &Conv2dShape, algo: ConvAlgo, threads: usize) -> usize {
    if algo == ConvAlgo::Panels {
        // One scratch: the threads share the panels of one product.
        return 1;
    }
    let (r, c) = split_shape(s, algo, threads);
    r * c
}

/// `parts + 1` boundaries splitting `0..units` evenly.
fn split_bounds(units: usize, parts: usize) -> Vec<usize> {
    (0..=parts).map(|i| i * units / parts).collect()
}

/// One thread's share of the output: output channels `c0..c1` of the global output rows
/// `r0..r1` (global row = `image · oh + oy`; row units never straddle images), as one
/// slice per (image, channel) plane.
pub(super) struct Part<'a> {
    pub(super) r0: usize,
    pub(super) r1: usize,
    c0: usize,
    c1: usize,
    /// First image touched.
    pub(super) n0: usize,
    /// Planes of images `n0..`, channel-major within an image: `planes[(n − n0)·(c1 − c0)
    /// + c − c0]` holds rows `max(r0 − n·oh, 0)..min(r1 − n·oh, oh)` of that plane.
    planes: Vec<&'a mut [f32]>,
    /// The same rows of the conv's residual input, one slice per entry of `planes`, when
    /// it adds one as it writes; empty otherwise.
    residuals: Vec<&'a [f32]>,
}

impl<'a> Part<'a> {
    /// The rows of image `n` this part owns, as `(first, end)` within the image.
    pub(super) fn rows_of(&self, n: usize, oh: usize) -> (usize, usize) {
        (self.r0.saturating_sub(n * oh).min(oh), self.r1.saturating_sub(n * oh).min(oh))
    }

    /// The part's slice of the plane of image `n`, channel `c`.
    pub(super) fn plane(&mut self, n: usize, c: usize) -> &mut [f32] {
        let i = (n - self.n0) * (self.c1 - self.c0) + c - self.c0;
        self.planes[i]
    }

    /// The residual's values at the pixels of [`Part::plane`]`(n, c)`, if the conv adds one.
    pub(super) fn residual(&self, n: usize, c: usize) -> Option<&'a [f32]> {
        self.residuals.get((n - self.n0) * (self.c1 - self.c0) + c - self.c0).copied()
    }

    /// Its slices of the planes, per image it touches and channel within an image (see
    /// `planes`).
    pub(super) fn planes_mut(&mut self) -> &mut [&'a mut [f32]] {
        &mut self.planes
    }

    /// The channels of group `g` this part computes.
    pub(super) fn channels_of(&self, g: usize, cout_g: usize) -> std::ops::Range<usize> {
        self.c0.max(g * cout_g)..self.c1.min((g + 1) * cout_g)
    }
}

/// Splits the output `[n, cout, oh, ow]` into the parts [`split_shape`] asks for, each
/// seeing the residual `res` (of the output's shape) at its own pixels.
pub(super) fn split<'a>(
    out: &'a mut [f32],
    res: Option<&'a [f32]>,
    s: &Conv2dShape,
    algo: ConvAlgo,
    threads: usize,
) -> Vec<Part<'a>> {
    let (row_parts, chan_parts) = split_shape(s, algo, threads);
    let unit = row_unit(algo);
    let per_image = s.oh.div_ceil(unit);
    let rows: Vec<usize> = split_bounds(s.n * per_image, row_parts)
        .iter()
        .map(|&u| (u / per_image) * s.oh + ((u % per_image) * unit).min(s.oh))
        .collect();
    let chans: Vec<usize> = if chan_parts == 1 {
        vec![0, s.cout]
    } else {
        split_bounds(s.cout / 8, chan_parts).iter().map(|c| c * 8).collect()
    };
    let chans = {
        let mut c = chans;
        *c.last_mut().expect("bounds") = s.cout;
        c
    };
    let mut parts: Vec<Part<'a>> = Vec::new();
    for r in rows.windows(2) {
        for c in chans.windows(2) {
            parts.push(Part {
                r0: r[0],
                r1: r[1],
                c0: c[0],
                c1: c[1],
                n0: r[0] / s.oh,
                planes: Vec::new(),
                residuals: Vec::new(),
            });
        }
    }
    let plane_len = s.oh * s.ow;
    for (idx, plane) in out.chunks_mut(plane_len).enumerate() {
        let (n, c) = (idx / s.cout, idx % s.cout);
        let mut rest = plane;
        let res_plane = res.map(|r| &r[idx * plane_len..][..plane_len]);
        for part in parts.iter_mut().filter(|p| (p.c0..p.c1).contains(&c)) {
            let (lo, hi) = part.rows_of(n, s.oh);
            if lo < hi {
                let (mine, tail) = std::mem::take(&mut rest).split_at_mut((hi - lo) * s.ow);
                part.planes.push(mine);
                part.residuals.extend(res_plane.map(|r| &r[lo * s.ow..hi * s.ow]));
                rest = tail;
            }
        }
    }
    parts
}

/// One part's own scratch under a split by channels ([`shared_scratch`]): the part, its
/// scratch before and after the shared cut (`share` floats of the end cut off).
pub(super) type Own<'a, 'p> = (&'a mut Part<'p>, &'a mut [f32], &'a mut [f32]);

/// The parts of a split by channels with one work area they share: each part's scratch
/// cut around `at..at + len`, the first part's cut being the shared area, and the last
/// `share` floats of each part's scratch its share of a sum over the input channels
/// (a LoRA branch's projection, [`sum_shares`]). Returns that area, the shares, and per
/// part the part with its scratch before and after the cut.
///
/// # Panics
/// If the parts do not all own the same rows (a split by rows).
#[allow(clippy::type_complexity)]
pub(super) fn shared_scratch<'a, 'p>(
    jobs: &'a mut [(Part<'p>, &mut [f32])],
    at: usize,
    len: usize,
    share: usize,
) -> (&'a mut [f32], Vec<&'a mut [f32]>, Vec<Own<'a, 'p>>) {
    let rows = jobs.first().map(|(p, _)| (p.r0, p.r1));
    assert!(jobs.iter().all(|(p, _)| Some((p.r0, p.r1)) == rows), "shared scratch: a split by rows");
    let mut shared: &mut [f32] = &mut [];
    let (mut shares, mut own) = (Vec::with_capacity(jobs.len()), Vec::with_capacity(jobs.len()));
    for (i, (part, scratch)) in jobs.iter_mut().enumerate() {
        let (scratch, mine) = scratch.split_at_mut(scratch.len() - share);
        let (before, rest) = scratch.split_at_mut(at);
        let (cut, after) = rest.split_at_mut(len);
        if i == 0 {
            shared = cut;
        }
        shares.push(mine);
        own.push((part, before, after));
    }
    (shared, shares, own)
}

/// `out` = the sum of the first `out.len()` floats of every share (the parts' sums over
/// their shares of the input channels).
pub(super) fn sum_shares(out: &mut [f32], shares: &[&mut [f32]]) {
    let Some((first, rest)) = shares.split_first() else { return };
    out.copy_from_slice(&first[..out.len()]);
    for share in rest {
        out.iter_mut().zip(share.iter()).for_each(|(a, b)| *a += b);
    }
}

/// `area` cut into `parts` runs, one per share of `channels` (as even as the count
/// allows), `per` floats a channel; each with its channels.
pub(super) fn channel_shares(
    area: &mut [f32],
    channels: usize,
    parts: usize,
    per: usize,
) -> Vec<(std::ops::Range<usize>, &mut [f32])> {
    // As `split_bounds` cuts, without its list.
    let bound = |i: usize| i * channels / parts;
    let mut rest = area;
    (0..parts)
        .map(|i| {
            let (mine, tail) = std::mem::take(&mut rest).split_at_mut((bound(i + 1) - bound(i)) * per);
            rest = tail;
            (bound(i)..bound(i + 1), mine)
        })
        .collect()
}
