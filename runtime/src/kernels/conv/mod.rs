//! 2-D convolution, NCHW, with a fused per-channel epilogue.
//!
//! The compiler picks an algorithm per layer with [`choose`] and stores the weight packed
//! for it ([`pack_weight`]); at run time [`conv2d`] reads that packed weight. Algorithms:
//!
//! * [`ConvAlgo::Gemm1x1`]: 1x1, stride 1, no padding: the input already is the GEMM's
//!   right-hand matrix, so each tile of output pixels is one GEMM, no copy. Planes of up
//!   to 256 pixels (one group, no LoRA branch or adapter in the tile) skip the GEMM call
//!   and its packing: register tiles over the input planes in place, a few last pixels
//!   as dot products (`pointwise.rs`); Im2col layers of 7x7 planes run the same tiles
//!   over their unfolded rows.
//! * [`ConvAlgo::Im2col`]: any shape: a tile of output pixels is unfolded into a
//!   `(cin/groups·kh·kw) × tile` matrix, multiplied by the weight in one GEMM.
//! * [`ConvAlgo::Winograd4`], [`ConvAlgo::Winograd2`]: 3x3, stride 1, no dilation:
//!   Winograd F(4x4,3x3) / F(2x2,3x3). The weight is transformed once, in `pack_weight`;
//!   per block of tiles the input is transformed, 36 (16) GEMMs run over the channels, and
//!   the output transform writes the result. 4x (2.25x) fewer multiplications than a direct
//!   conv, at the cost of 4x (1.8x) more weight memory; rounding error relative to the
//!   output's scale ≈1e-5 for F(4x4) (about 5x im2col's), like im2col for F(2x2).
//! * [`ConvAlgo::Depthwise`]: one input channel per group: a direct loop, no GEMM.
//!
//! Threads split a layer by ranges of output rows, or, for small images with many output
//! channels, by ranges of output channels (see `split_shape`); each thread owns its slice
//! of the output planes and runs its GEMMs single-threaded on its own part of the
//! scratch. Threads synchronise within a layer only under a channel split of im2col or
//! Winograd: per tile (block) they first unfold (transform) the input together, then
//! each multiplies its channels (`im2col_shared`, `winograd_shared`). Every algorithm
//! applies the epilogue while copying a finished tile from its scratch to the output,
//! while the tile is still in cache.
//!
//! Only `gemm.rs` may use `unsafe`, so the Winograd transforms are plain Rust written to
//! auto-vectorise (fixed-size lane arrays), compiled for the widest SIMD the CPU has
//! through pulp (see the [module doc](super)): the input transform uses 16, 8 or 4
//! lanes as the tiles per row allow, the output transform 16.
//!
//! A layer may carry a LoRA branch ([`Lora`]: `y = conv(x, W) + B (A x)`, with `A` a conv
//! to `rank` channels of the layer's geometry and `B` a 1x1 conv back, pre-scaled), fused
//! into the same pass over the input: the GEMM paths multiply the same column tile (or
//! input) by `A` too and add `B t` to the accumulator; Winograd multiplies the same
//! transformed tiles by the transformed `A` and adds `B G` to the products before the
//! output transform (the transform is linear, so this is the transform of `W + B A`).
//! Either way the LoRA term is in the accumulator before the epilogue scales it, so a
//! folded BatchNorm scales it as it scales the conv. `A`'s few rows multiply the tile in
//! registers (`gemm::few_rows_product`: the GEMM library would pack the whole tile again
//! for them), and under a channel split each thread sums them over its share of the
//! channels while the shared tile (transform) is built. Groups and depthwise layers have no
//! fused branch ([`check`] refuses one): their LoRA runs as separate steps.
//!
//! A layer may also carry a residual bottleneck adapter on its output ([`Adapter`],
//! `adapter.rs`): `y + up · act(down · y + bd) + bu` between the epilogue's shift and its
//! ReLU, computed per tile of pixels (all channels) while the tile is in cache: inside the
//! GEMM paths' tile under a row split, in each thread's part right after the conv under
//! another row split, else in one threaded pass over the finished output.
//!
//! This file holds the geometry, the choice of algorithm, the weight packing, the
//! [`conv2d`] dispatch and the epilogue; `split.rs` the thread split, `im2col.rs` the GEMM
//! paths (Gemm1x1, Im2col), `pointwise.rs` the register tiles of small planes,
//! `direct.rs` the direct conv an im2col layer with few input channels per group (a stem,
//! RegNet's grouped convs) runs instead, `winograd.rs` Winograd, `depthwise.rs` the direct
//! loop (`depthwise/flat.rs` its 7x7 planes), and `tests.rs` the tests of every algorithm
//! against one reference.

use rayon::prelude::*;

use super::elementwise::{clamp_vector, relu};
use super::{Activation, Epilogue};

mod adapter;
mod depthwise;
mod direct;
mod im2col;
mod panels;
mod pointwise;
mod split;
mod winograd;

use self::depthwise::depthwise;
use self::im2col::{gemm_part, gemm_tile, im2col_shared};
use self::split::{Part, parts, split, split_shape};
use self::winograd::{F2, F2_G, F4, F4_G, Wino, pack_winograd, winograd_part, winograd_shared};

pub use self::adapter::Adapter;
pub use readi_plan::ops::{Conv2dShape, ConvAlgo};

/// The kernel's view of a conv layer at an input of `n x cin x h x w`
/// ([`readi_plan::ops::Conv2d::shape`], the one place it is built).
pub fn layer_shape(conv: &readi_plan::ops::Conv2d, n: usize, h: usize, w: usize) -> Conv2dShape {
    conv.shape(n, h, w)
}

/// Picks the algorithm for a layer (at compile time; the batch size does not matter).
///
/// For 3x3 stride-1 undilated convs with at least 32 channels in and out per group (with
/// fewer, the transforms cost about what they save): Winograd F(4x4) when an image has at
/// least [`WINOGRAD_MIN_TILES`] of its 4x4 tiles and its weight (4x the original) stays
/// within 16 MiB, else F(2x2) when it has that many 2x2 tiles (or
/// [`WINOGRAD2_WIDE_MIN_TILES`], with [`WINOGRAD2_WIDE`] channels in and out) and its weight
/// (1.8x) within 32 MiB; a plain GEMM for 1x1 stride-1 convs; the direct loop for depthwise convs;
/// weight panels ([`ConvAlgo::Panels`]) for other kernels of one group on planes of at most
/// [`PANELS_MAX_PLANE`] pixels whose weight is too large for im2col's register tiles
/// (`pointwise::light_unfolded`: there, at 64 and 128 channels at 7x7, the tiles took
/// 0.92-0.95x the panels' time; at 256 and 512 channels the panels 0.85-0.98x the `gemm`
/// crate's, one and two threads, 2026-12-06, EPYC Zen 4); im2col for everything else.
pub fn choose(s: &Conv2dShape) -> ConvAlgo {
    let (cin_g, cout_g) = (s.cin_g(), s.cout_g());
    if cin_g == 1 && s.groups > 1 {
        return ConvAlgo::Depthwise;
    }
    if ConvAlgo::Gemm1x1.supports(s) {
        return ConvAlgo::Gemm1x1;
    }
    if s.is_winograd_shape() && cin_g >= 32 && cout_g >= 32 {
        let tiles = |m: usize| s.oh.div_ceil(m) * s.ow.div_ceil(m);
        let weight = s.cout * cin_g;
        if tiles(4) >= WINOGRAD_MIN_TILES && 36 * weight <= 4 << 20 {
            return ConvAlgo::Winograd4;
        }
        let wide = cin_g >= WINOGRAD2_WIDE && cout_g >= WINOGRAD2_WIDE;
        let enough = tiles(2) >= WINOGRAD_MIN_TILES || (wide && tiles(2) >= WINOGRAD2_WIDE_MIN_TILES);
        if enough && 16 * weight <= 8 << 20 {
            return ConvAlgo::Winograd2;
        }
    }
    if s.groups == 1 && s.oh * s.ow <= PANELS_MAX_PLANE && s.kh * s.kw > 1 && !pointwise::light_unfolded(s) {
        return ConvAlgo::Panels;
    }
    ConvAlgo::Im2col
}

/// Most output pixels per image of a layer [`choose`] computes by [`ConvAlgo::Panels`].
pub use self::panels::MAX_PLANE as PANELS_MAX_PLANE;

/// Tiles an image needs for [`choose`] to take a Winograd algorithm: each transformed
/// position is one GEMM with a column per tile, and with few columns the weight's
/// transformed copy (1.8x or 4x the original) is read for little work. Measured on
/// ResNet-18 (2026-12-05, a 2-core Xeon with two AVX-512 FMA units, `readi bench
/// --profile`, 5 alternating rounds, 1 / 2 threads): its 14x14 layers (16 tiles of 4x4,
/// 49 of 2x2) ran 0.70 / 0.75x as long by F(2x2) as by F(4x4), its 7x7 ones (16 tiles of
/// 2x2) 0.86 / 0.85x as long by im2col as by F(2x2); the 28x28 and 56x56 layers (49 and
/// 196 tiles of 4x4) stayed fastest by F(4x4). The whole model 0.91 / 0.92x. (Before,
/// the rule asked for 12 and 5 output rows; on the previous host, an AMD EPYC with
/// half the FMA throughput, the weight traffic weighed less against the arithmetic.)
pub const WINOGRAD_MIN_TILES: usize = 32;

/// Fewer 2x2 tiles an image may have for [`choose`] to take F(2x2) anyway when the layer
/// has at least [`WINOGRAD2_WIDE`] channels in and out per group: on 7x7 planes (16 tiles)
/// the 512-channel 3x3 convs of ResNet-18 and ResNet-50's last stage. Measured in the
/// model on the AMD EPYC (Zen 4, 2026-12-07; `step_compare` of two plans, 60 rounds, one /
/// two threads, F(2x2) over the weight panels): ResNet-18's three such layers 0.84-0.87 /
/// 0.85-0.88, the model 0.94 / 0.95. There the weight comes from memory and the panels
/// do 1.7x the multiply-adds for 0.56x its bytes. Alone, with the weight warm in L3, the
/// layers took 0.88-1.0x im2col's time by F(2x2), and 192- to 384-channel ones 0.96-1.21x
/// (none in the zoo): hence only the wide layers.
pub const WINOGRAD2_WIDE_MIN_TILES: usize = 16;

/// Channels in and out per group from which [`WINOGRAD2_WIDE_MIN_TILES`] applies.
pub const WINOGRAD2_WIDE: usize = 512;

/// Length of the weight packed for `algo` ([`ConvAlgo::packed_len`]).
pub fn packed_weight_len(s: &Conv2dShape, algo: ConvAlgo) -> usize {
    algo.packed_len(s)
}

/// Converts a PyTorch-layout weight `[cout, cin/groups, kh, kw]` to the layout `algo`
/// reads, into `out` (of [`packed_weight_len`] floats).
///
/// # Panics
/// If `algo` does not support the shape or a length is wrong.
pub fn pack_weight(s: &Conv2dShape, algo: ConvAlgo, weight: &[f32], out: &mut [f32]) {
    assert!(algo.supports(s), "conv: {} cannot compute {s:?}", algo.name());
    assert_eq!(weight.len(), s.cout * s.k(), "conv: weight length");
    assert_eq!(out.len(), packed_weight_len(s, algo), "conv: packed weight length");
    match algo {
        ConvAlgo::Gemm1x1 | ConvAlgo::Im2col | ConvAlgo::Depthwise => out.copy_from_slice(weight),
        ConvAlgo::Winograd2 => pack_winograd::<4>(s, &F2_G, weight, out),
        ConvAlgo::Winograd4 => pack_winograd::<6>(s, &F4_G, weight, out),
        ConvAlgo::Panels => super::panel::pack(weight, s.k(), s.cout, out),
    }
}

/// Floats of a layer's LoRA `A` at `rank` as the kernel of `algo` reads it
/// ([`ConvAlgo::lora_a_layout`]).
pub fn lora_a_len(s: &Conv2dShape, algo: ConvAlgo, rank: usize) -> usize {
    packed_weight_len(&lora_a_shape(s, rank), algo.lora_a_layout())
}

/// Packs a LoRA `A` at `rank` given raw (`[rank, cin/groups, kh, kw]`) for the kernel of
/// `algo`, into `out` ([`lora_a_len`] floats).
///
/// # Panics
/// As [`pack_weight`].
pub fn pack_lora_a(s: &Conv2dShape, algo: ConvAlgo, rank: usize, raw: &[f32], out: &mut [f32]) {
    pack_weight(&lora_a_shape(s, rank), algo.lora_a_layout(), raw, out);
}

/// A conv's fused LoRA branch ([`conv2d_lora`]) is a [`Lora`] whose `A` is packed for the
/// layer's algorithm as a conv to `rank` channels ([`pack_weight`] on [`lora_a_shape`]).
pub use super::Lora;

/// The shape of a layer's LoRA `A`: the layer with `rank` output channels.
pub fn lora_a_shape(s: &Conv2dShape, rank: usize) -> Conv2dShape {
    Conv2dShape { cout: rank, ..*s }
}

/// Scratch floats [`conv2d`] needs for this layer at this thread count.
pub fn scratch_len(s: &Conv2dShape, algo: ConvAlgo, threads: usize) -> usize {
    lora_scratch_len(s, algo, 0, threads)
}

/// Scratch floats [`conv2d_lora`] needs for this layer with a LoRA branch of `rank`
/// (0: none) at this thread count.
pub fn lora_scratch_len(s: &Conv2dShape, algo: ConvAlgo, rank: usize, threads: usize) -> usize {
    parts(s, algo, threads) * part_scratch(s, algo, rank)
}

/// Scratch floats [`conv2d_adapter`] needs with a LoRA branch of `rank` and an adapter
/// of `mid` bottleneck channels (0: none of either), or `None` if it overflows.
pub fn adapter_scratch_len(s: &Conv2dShape, algo: ConvAlgo, rank: usize, mid: usize, threads: usize) -> Option<usize> {
    let conv = checked_scratch_len(s, algo, rank, threads)?;
    if mid == 0 {
        return Some(conv);
    }
    // A tile's worth of work space (cannot overflow within `check`'s bounds): after the
    // conv, over its output, per thread, reusing the conv's scratch (also AdaBN's
    // [`adapter_after`]); in a part split by rows, beside the part's conv scratch.
    let work = adapter::fused_scratch_len(s.cout, mid);
    let after = conv.max(adapter::fused_after_len(s, mid, threads));
    let parts = parts(s, algo, threads);
    if adapter_in_tile(s, algo, threads) {
        // The bottleneck rows of a tile beside each part's scratch.
        let tile = parts.checked_mul(gemm_tile(s, algo))?.checked_mul(mid)?;
        return Some(after.max(conv.checked_add(tile)?));
    }
    if !adapter_in_parts(s, algo, threads) {
        return Some(after);
    }
    Some(after.max(parts.checked_mul(part_scratch(s, algo, rank).checked_add(work)?)?))
}

/// Scratch floats [`conv2d_scaled`] needs with an adapter of `mid` bottleneck channels
/// (0: none): the scaled weight, then [`adapter_scratch_len`] of one image; `None` if it
/// overflows.
pub fn scaled_scratch_len(s: &Conv2dShape, algo: ConvAlgo, mid: usize, threads: usize) -> Option<usize> {
    let one = Conv2dShape { n: 1, ..*s };
    adapter_scratch_len(&one, algo, 0, mid, threads)?.checked_add(s.cout.checked_mul(s.k())?)
}

/// [`conv2d_fused`] of the input with its channels scaled per image, `conv(x · s)` for
/// `scale` `[n, cin]` (a squeeze-and-excitation's multiply, fused): image by image, the
/// conv with the weight's input channels scaled instead, into the front of `scratch`
/// (`cout · cin/groups · kh · kw` products an image, where scaling the input would take
/// `cin · h · w` and a pass over it). For the algorithms that store the weight as PyTorch's
/// ([`ConvAlgo::packs_as_is`]); no LoRA branch. `scratch` holds [`scaled_scratch_len`]
/// floats.
///
/// # Panics
/// If `algo` stores another layout or a length is wrong.
#[allow(clippy::too_many_arguments)]
pub fn conv2d_scaled(
    s: &Conv2dShape,
    algo: ConvAlgo,
    packed_weight: &[f32],
    adapter: Option<&Adapter>,
    ep: &Epilogue,
    x: &[f32],
    scale: &[f32],
    res: Option<&[f32]>,
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    assert!(algo.packs_as_is(), "conv: a channel scale on a {} weight", algo.name());
    assert_eq!(scale.len(), s.n * s.cin, "conv: channel scale length");
    assert_eq!(packed_weight.len(), s.cout * s.k(), "conv: weight length");
    let one = Conv2dShape { n: 1, ..*s };
    let (xl, ol, taps) = (s.cin * s.h * s.w, s.cout * s.oh * s.ow, s.kh * s.kw);
    let (w, rest) = scratch.split_at_mut(packed_weight.len());
    for n in 0..s.n {
        let sc = &scale[n * s.cin..][..s.cin];
        for (co, (dst, src)) in w.chunks_exact_mut(s.k()).zip(packed_weight.chunks_exact(s.k())).enumerate() {
            // Output channel `co` reads input channels `g · cin/groups ..` of its group.
            let sc = &sc[co / s.cout_g() * s.cin_g()..][..s.cin_g()];
            if taps == 1 {
                dst.iter_mut().zip(src).zip(sc).for_each(|((d, &v), &f)| *d = v * f);
            } else {
                for ((d, v), &f) in dst.chunks_exact_mut(taps).zip(src.chunks_exact(taps)).zip(sc) {
                    d.iter_mut().zip(v).for_each(|(d, &v)| *d = v * f);
                }
            }
        }
        let (xn, on) = (&x[n * xl..][..xl], &mut out[n * ol..][..ol]);
        conv2d_fused(&one, algo, w, None, adapter, ep, xn, res.map(|r| &r[n * ol..][..ol]), on, rest, threads);
    }
}

/// Whether [`conv2d_adapter`] computes a layer's adapter (not in its GEMM tiles) inside
/// each thread's part right after the conv: a split by rows, so that each part holds every
/// channel of its pixels. Else it runs over the finished output.
fn adapter_in_parts(s: &Conv2dShape, algo: ConvAlgo, threads: usize) -> bool {
    !matches!(algo, ConvAlgo::Depthwise | ConvAlgo::Panels)
        && !adapter_in_tile(s, algo, threads)
        && split_shape(s, algo, threads).1 == 1
}

/// Whether [`conv2d_adapter`] computes a layer's adapter inside its GEMM tiles: a GEMM
/// path of one group split by output rows, so each tile holds every channel of its pixels.
fn adapter_in_tile(s: &Conv2dShape, algo: ConvAlgo, threads: usize) -> bool {
    matches!(algo, ConvAlgo::Gemm1x1 | ConvAlgo::Im2col) && s.groups == 1 && split_shape(s, algo, threads).1 == 1
}

/// Most elements of a conv's input, output or weight [`check`] accepts: far beyond any
/// memory budget, and small enough that the kernel's own size arithmetic (tiles, parts,
/// scratch) cannot overflow.
const MAX_ELEMENTS: usize = 1 << 48;

/// [`lora_scratch_len`] for a layer that passed [`check`], or `None` if it overflows.
pub fn checked_scratch_len(s: &Conv2dShape, algo: ConvAlgo, rank: usize, threads: usize) -> Option<usize> {
    parts(s, algo, threads).checked_mul(part_scratch(s, algo, rank))
}

/// Most LoRA rank [`check`] accepts, the plan format's.
pub const MAX_LORA_RANK: usize = readi_plan::format::MAX_LORA_RANK;

/// The preconditions of [`conv2d`] on a layer: the geometry is consistent (groups
/// divide the channels, the window fits the padded input and the output size is
/// PyTorch's), `algo` can compute it (Gemm1x1: 1x1, stride 1, no padding; Winograd: 3x3,
/// stride 1, no dilation; depthwise: one input channel per group), and the lengths of
/// the packed weight, the input, the output and the epilogue's vectors fit the shape.
/// A LoRA branch, `(rank, A's length, B's length)`, needs one group, not the depthwise
/// algorithm, a rank of 1 to [`MAX_LORA_RANK`], `A` packed for `algo` at rank `rank` and
/// `B` of `cout · rank`. The executor checks this at bind time; [`conv2d`] asserts it in
/// debug builds.
pub fn check(
    s: &Conv2dShape,
    algo: ConvAlgo,
    weight_len: usize,
    x_len: usize,
    out_len: usize,
    epilogue: [Option<usize>; 2],
    lora: Option<(usize, usize, usize)>,
) -> Result<(), String> {
    if s.groups == 0 || !s.cin.is_multiple_of(s.groups) || !s.cout.is_multiple_of(s.groups) {
        return Err(format!("groups={} must divide {} input and {} output channels", s.groups, s.cin, s.cout));
    }
    if s.cin == 0 || s.cout == 0 {
        return Err(format!("{} input and {} output channels: a conv needs at least one", s.cin, s.cout));
    }
    if [s.kh, s.kw, s.stride_h, s.stride_w, s.dil_h, s.dil_w].contains(&0) {
        return Err(format!(
            "kernel {}x{}, stride {}x{}, dilation {}x{}: none may be 0",
            s.kh, s.kw, s.stride_h, s.stride_w, s.dil_h, s.dil_w
        ));
    }
    let out = |len: usize, k: usize, st: usize, p: usize, d: usize| {
        let i = |v: usize| i64::try_from(v).ok();
        readi_plan::ops::window_out(i(len)?, i(k)?, i(st)?, i(p)?, i(d)?, false).and_then(|o| usize::try_from(o).ok())
    };
    if out(s.h, s.kh, s.stride_h, s.pad_h, s.dil_h) != Some(s.oh)
        || out(s.w, s.kw, s.stride_w, s.pad_w, s.dil_w) != Some(s.ow)
    {
        return Err(format!(
            "kernel {}x{} (dilation {}x{}, padding {}x{}) does not fit input {}x{} with output {}x{}",
            s.kh, s.kw, s.dil_h, s.dil_w, s.pad_h, s.pad_w, s.h, s.w, s.oh, s.ow
        ));
    }
    if !algo.supports(s) {
        let needs = match algo {
            ConvAlgo::Gemm1x1 => "a 1x1 kernel, stride 1 and no padding",
            ConvAlgo::Winograd2 | ConvAlgo::Winograd4 => "a 3x3 kernel, stride 1 and dilation 1",
            ConvAlgo::Depthwise => "one input channel per group (groups = input channels)",
            ConvAlgo::Panels => "one group",
            ConvAlgo::Im2col => "nothing",
        };
        return Err(format!(
            "conv algorithm `{}` cannot compute this layer (kernel {}x{}, stride {}x{}, padding {}x{}, dilation {}x{}, \
             {} input channels in {} groups): it needs {needs}",
            algo.name(),
            s.kh,
            s.kw,
            s.stride_h,
            s.stride_w,
            s.pad_h,
            s.pad_w,
            s.dil_h,
            s.dil_w,
            s.cin,
            s.groups
        ));
    }
    let product =
        |dims: &[usize]| dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).filter(|&n| n <= MAX_ELEMENTS);
    let (Some(_), Some(x), Some(o)) = (
        product(&[s.cin_g(), s.kh, s.kw, s.cout]),
        product(&[s.n, s.cin, s.h, s.w]),
        product(&[s.n, s.cout, s.oh, s.ow]),
    ) else {
        return Err(format!("the layer is too large ({s:?})"));
    };
    if weight_len != packed_weight_len(s, algo) {
        return Err(format!(
            "packed weight has {weight_len} values, `{}` needs {}",
            algo.name(),
            packed_weight_len(s, algo)
        ));
    }
    if x_len != x || out_len != o {
        return Err(format!("input has {x_len} values (needs {x}), output {out_len} (needs {o})"));
    }
    if let Some(n) = epilogue.into_iter().flatten().find(|&n| n != s.cout) {
        return Err(format!("an epilogue vector has {n} values for {} output channels", s.cout));
    }
    if let Some((rank, a_len, b_len)) = lora {
        if s.groups != 1 || algo == ConvAlgo::Depthwise {
            return Err(format!(
                "a fused LoRA branch needs one group and not the depthwise algorithm (groups={}, `{}`)",
                s.groups,
                algo.name()
            ));
        }
        if rank == 0 || rank > MAX_LORA_RANK {
            return Err(format!("LoRA rank {rank}: it must be 1 to {MAX_LORA_RANK}"));
        }
        let want_a = lora_a_len(s, algo, rank);
        if a_len != want_a || Some(b_len) != s.cout.checked_mul(rank) {
            return Err(format!(
                "LoRA A has {a_len} values (`{}` at rank {rank} needs {want_a}), B {b_len} (needs {} x {rank})",
                algo.name(),
                s.cout
            ));
        }
    }
    Ok(())
}

/// Computes one conv layer: `out = epilogue(conv(x, weight))`, where `packed_weight` came
/// from [`pack_weight`] for the same `algo`, `scratch` holds at least [`scratch_len`]
/// floats, and the epilogue's `scale`/`shift` (if any) have `cout` values.
///
/// # Panics
/// If a length disagrees with the shape, the output size is not PyTorch's, or `algo` does
/// not support the shape.
#[allow(clippy::too_many_arguments)]
pub fn conv2d(
    s: &Conv2dShape,
    algo: ConvAlgo,
    packed_weight: &[f32],
    ep: &Epilogue,
    x: &[f32],
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    conv2d_adapter(s, algo, packed_weight, None, None, ep, x, out, scratch, threads)
}

/// [`conv2d`] with a fused LoRA branch: `out = epilogue(conv(x, weight) + B (A x))`;
/// `scratch` holds at least [`lora_scratch_len`] floats.
///
/// # Panics
/// As [`conv2d`], and if the branch fails [`check`].
#[allow(clippy::too_many_arguments)]
pub fn conv2d_lora(
    s: &Conv2dShape,
    algo: ConvAlgo,
    packed_weight: &[f32],
    lora: Option<&Lora>,
    ep: &Epilogue,
    x: &[f32],
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    conv2d_adapter(s, algo, packed_weight, lora, None, ep, x, out, scratch, threads)
}

/// [`conv2d_lora`] with a fused adapter on the output:
/// `out = relu?(z + up · act(down · z + bd) + bu)` with `z = conv(x, weight) + B (A x)`
/// scaled and shifted by the epilogue, whose ReLU (if any) comes last; `scratch` holds at
/// least [`adapter_scratch_len`] floats.
///
/// # Panics
/// As [`conv2d_lora`], and if the adapter's lengths do not fit `cout`.
#[allow(clippy::too_many_arguments)]
pub fn conv2d_adapter(
    s: &Conv2dShape,
    algo: ConvAlgo,
    packed_weight: &[f32],
    lora: Option<&Lora>,
    adapter: Option<&Adapter>,
    ep: &Epilogue,
    x: &[f32],
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    conv2d_fused(s, algo, packed_weight, lora, adapter, ep, x, None, out, scratch, threads)
}

/// [`conv2d_adapter`] with a residual input `res` of the output's shape added after the
/// scale and shift (and the adapter), before the activation: `out = act(z + res)`, a
/// ResNet block's `relu(bn(conv(x)) + identity)` in the conv's own epilogue. The GEMM and
/// Winograd paths add it as they write each output row, an adapter after the conv in its
/// own last pass; the depthwise loop, the direct conv and an adapter in the GEMM tiles add
/// it in one pass after.
///
/// # Panics
/// As [`conv2d_adapter`], and if `res` is not the output's length.
#[allow(clippy::too_many_arguments)]
pub fn conv2d_fused(
    s: &Conv2dShape,
    algo: ConvAlgo,
    packed_weight: &[f32],
    lora: Option<&Lora>,
    adapter: Option<&Adapter>,
    ep: &Epilogue,
    x: &[f32],
    res: Option<&[f32]>,
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    if let Some(r) = res {
        assert_eq!(r.len(), out.len(), "conv: residual length");
    }
    if let Some(a) = adapter
        && let Err(e) = a.check(s.cout)
    {
        panic!("conv: {e}");
    }
    let mid = adapter.map_or(0, |a| a.mid);
    let rank = lora.map_or(0, |l| l.rank);
    if let Some(l) = lora {
        assert!(s.groups == 1 && algo != ConvAlgo::Depthwise && l.rank > 0, "conv: LoRA on {s:?} with {algo:?}");
        assert_eq!(l.a.len(), lora_a_len(s, algo, l.rank), "conv: LoRA A length");
        assert_eq!(l.b.len(), s.cout * l.rank, "conv: LoRA B length");
    }
    debug_assert_eq!(
        check(
            s,
            algo,
            packed_weight.len(),
            x.len(),
            out.len(),
            [ep.scale.map(<[f32]>::len), ep.shift.map(<[f32]>::len)],
            lora.map(|l| (l.rank, l.a.len(), l.b.len()))
        ),
        Ok(()),
        "conv2d preconditions"
    );
    check_shape(s);
    assert!(algo.supports(s), "conv: {} cannot compute {s:?}", algo.name());
    assert_eq!(packed_weight.len(), packed_weight_len(s, algo), "conv: packed weight length");
    assert_eq!(x.len(), s.n * s.cin * s.h * s.w, "conv: input length");
    assert_eq!(out.len(), s.n * s.cout * s.oh * s.ow, "conv: output length");
    for v in [ep.scale, ep.shift].into_iter().flatten() {
        assert_eq!(v.len(), s.cout, "conv: epilogue length");
    }
    let need = adapter_scratch_len(s, algo, rank, mid, threads).unwrap_or(usize::MAX);
    assert!(scratch.len() >= need, "conv: scratch has {} floats, needs {need}", scratch.len());
    if out.is_empty() {
        return;
    }
    // Where the adapter runs: in the GEMM tiles, or after the conv over its output, the
    // conv's ReLU then deferred to after the adapter. Where the residual is added: as the
    // GEMM and Winograd paths write each row, or in a pass after everything else (the
    // activation then deferred to that pass).
    let in_tile = adapter.filter(|_| adapter_in_tile(s, algo, threads));
    let after = adapter.filter(|_| in_tile.is_none());
    // An adapter after the conv: in each part split by rows (every channel of its pixels),
    // on the planes its thread just wrote; else over the output once the conv is done.
    let in_parts = after.filter(|_| adapter_in_parts(s, algo, threads));
    let direct = algo == ConvAlgo::Im2col && lora.is_none() && adapter.is_none() && direct::applies(s);
    let res_in_rows = res.filter(|_| adapter.is_none() && algo != ConvAlgo::Depthwise && !direct);
    // An adapter after the conv adds the residual in its own last pass.
    let res_in_adapter = res.filter(|_| after.is_some());
    let res_after = res.filter(|_| res_in_rows.is_none() && res_in_adapter.is_none());
    let conv_ep = Epilogue { act: ep.act.filter(|_| after.is_none() && res_after.is_none()), ..*ep };
    // The activation an adapter after the conv applies (none when a pass after it adds the
    // residual and applies it).
    let ad_act = ep.act.filter(|_| res_after.is_none());
    if algo == ConvAlgo::Depthwise {
        depthwise(s, packed_weight, &conv_ep, x, out, threads);
    } else if algo == ConvAlgo::Panels {
        panels::conv(s, packed_weight, lora, &conv_ep, x, res_in_rows, out, scratch, threads);
    } else if direct {
        // A stem or a grouped conv of narrow groups: few input channels per group, which
        // im2col would unfold into shallow GEMMs.
        direct::conv(s, packed_weight, &conv_ep, x, out, scratch, threads);
    } else {
        let ep = &conv_ep;
        let conv_len = part_scratch(s, algo, rank) + in_tile.map_or(0, |a| a.mid * gemm_tile(s, algo));
        let per = conv_len + in_parts.map_or(0, |a| adapter::fused_scratch_len(s.cout, a.mid));
        let mut jobs: Vec<(Part, &mut [f32])> =
            split(out, res_in_rows, s, algo, threads).into_iter().zip(scratch.chunks_mut(per.max(1))).collect();
        let run = |(part, scratch): &mut (Part, &mut [f32])| {
            let (scratch, work) = scratch.split_at_mut(conv_len);
            match algo {
                ConvAlgo::Gemm1x1 if lora.is_none() && in_tile.is_none() && pointwise::applies(s, ep.act) => {
                    pointwise::part(s, packed_weight, ep, x, part, scratch)
                }
                ConvAlgo::Gemm1x1 | ConvAlgo::Im2col => {
                    gemm_part(s, algo, packed_weight, lora, in_tile, ep, x, part, scratch)
                }
                ConvAlgo::Winograd2 => winograd_part::<F2, 4, 2>(s, packed_weight, lora, ep, x, part, scratch),
                ConvAlgo::Winograd4 => winograd_part::<F4, 6, 4>(s, packed_weight, lora, ep, x, part, scratch),
                ConvAlgo::Depthwise | ConvAlgo::Panels => unreachable!("handled above"),
            }
            if let Some(a) = in_parts {
                adapter::apply_part(s, a, part, ad_act, res_in_adapter, work);
            }
        };
        // A split by channels (so more than one part) of a layer with an input to prepare.
        let by_channels = split_shape(s, algo, threads).1 > 1;
        if by_channels && algo != ConvAlgo::Gemm1x1 {
            // The parts share one input transform, or one unfolded tile.
            debug_assert!(
                in_parts.is_none() && in_tile.is_none(),
                "an adapter in parts or tiles needs a split by rows"
            );
            match algo {
                ConvAlgo::Winograd2 => winograd_shared::<F2, 4, 2>(s, packed_weight, lora, ep, x, &mut jobs),
                ConvAlgo::Winograd4 => winograd_shared::<F4, 6, 4>(s, packed_weight, lora, ep, x, &mut jobs),
                _ => im2col_shared(s, packed_weight, lora, ep, x, &mut jobs),
            }
        } else if jobs.len() == 1 {
            run(&mut jobs[0]);
        } else {
            jobs.par_iter_mut().for_each(run);
        }
    }
    if let Some(a) = after.filter(|_| in_parts.is_none()) {
        adapter::apply_fused(s, a, out, ad_act, res_in_adapter, scratch, threads);
    }
    if let Some(r) = res_after {
        crate::kernels::elementwise::add_in_place(out, r, ep.act);
    }
}

/// The adapter of a conv step on the conv's finished output (scaled and shifted, no
/// activation yet), then the activation `act`: what [`conv2d_adapter`] computes after the conv
/// when not in its tiles. For AdaBN, which normalises a conv's output itself; `scratch`
/// holds at least [`adapter_scratch_len`] floats.
///
/// # Panics
/// If the adapter's or the output's lengths do not fit the shape.
pub fn adapter_after(
    s: &Conv2dShape,
    ad: &Adapter,
    out: &mut [f32],
    act: Option<Activation>,
    scratch: &mut [f32],
    threads: usize,
) {
    if let Err(e) = ad.check(s.cout) {
        panic!("conv: {e}");
    }
    assert_eq!(out.len(), s.n * s.cout * s.oh * s.ow, "conv: output length");
    let need = adapter::fused_after_len(s, ad.mid, threads);
    assert!(scratch.len() >= need, "conv: adapter scratch");
    adapter::apply_fused(s, ad, out, act, None, scratch, threads);
}

#[track_caller]
fn check_shape(s: &Conv2dShape) {
    assert!(
        s.groups > 0 && s.cin.is_multiple_of(s.groups) && s.cout.is_multiple_of(s.groups),
        "conv: groups must divide channels"
    );
    assert!(s.kh > 0 && s.kw > 0 && s.stride_h > 0 && s.stride_w > 0 && s.dil_h > 0 && s.dil_w > 0, "conv: {s:?}");
    let out = |len: usize, k: usize, st: usize, p: usize, d: usize| {
        let i = |v: usize| i64::try_from(v).ok();
        readi_plan::ops::window_out(i(len)?, i(k)?, i(st)?, i(p)?, i(d)?, false).and_then(|o| usize::try_from(o).ok())
    };
    assert!(
        out(s.h, s.kh, s.stride_h, s.pad_h, s.dil_h) == Some(s.oh)
            && out(s.w, s.kw, s.stride_w, s.pad_w, s.dil_w) == Some(s.ow),
        "conv: output size {}x{} is not PyTorch's for {s:?}",
        s.oh,
        s.ow
    );
}

/// Where the SIMD vectors of an output row of `ow` values start, `width` (the lanes, at most
/// `ow`) apart, the last one overlapping the one before it so that it ends with the row:
/// the row walk of the register paths (`depthwise.rs`, `direct.rs`, `pool/in_place.rs`).
#[inline(always)]
pub(crate) fn vector_starts(ow: usize, width: usize) -> impl Iterator<Item = usize> {
    (0..ow.div_ceil(width)).map(move |i| (i * width).min(ow - width))
}

/// Stores `acc · scale + shift`, clamped to `clamp`'s bounds if given (a ReLU, ReLU6 or
/// clamp: [`Epilogue::clamp`]), into `out`: one vector, or the first `out.len()` lanes of
/// one through the stack for a row narrower than a vector (pulp's partial stores are
/// calls). The register paths' store.
#[inline(always)]
fn store_vector<S: pulp::Simd>(
    simd: S,
    acc: S::f32s,
    scale: S::f32s,
    shift: S::f32s,
    clamp: Option<(f32, f32)>,
    out: &mut [f32],
) {
    let mut y = simd.mul_add_f32s(acc, scale, shift);
    if let Some(bounds) = clamp {
        y = clamp_vector(simd, y, bounds);
    }
    let lanes = size_of::<S::f32s>() / size_of::<f32>();
    if out.len() == lanes {
        S::as_mut_simd_f32s(out).0[0] = y;
    } else {
        let mut lane = [0.0f32; 16];
        let lane = &mut lane[..lanes];
        S::as_mut_simd_f32s(lane).0[0] = y;
        out.copy_from_slice(&lane[..out.len()]);
    }
}

/// Copies input plane `xc` into the interior of its zero-padded copy `out` (rows of `cols =
/// w + 2 pad_w`, the input's rows from row `pad_h`, column `pad_w`); the border is left as it
/// is, zero. Every tap of a stride-1 output then lies inside the copy.
#[inline(always)]
fn pad_interior(s: &Conv2dShape, xc: &[f32], cols: usize, out: &mut [f32]) {
    for (iy, src) in xc.chunks_exact(s.w).enumerate() {
        out[(iy + s.pad_h) * cols + s.pad_w..][..s.w].copy_from_slice(src);
    }
}

/// Copies input plane `xc` into the interiors of its zero-padded copy split by column
/// phase, so that a row's taps are contiguous loads at the conv's column stride: at stride
/// 1 one phase, [`pad_interior`]; at stride 2 padded column `p` goes to column `p / 2` of
/// phase `p % 2`, the phases `rows x cols` planes one after the other in `out`. The
/// border is left as it is, zero.
#[inline(always)]
fn pad_phases(s: &Conv2dShape, xc: &[f32], rows: usize, cols: usize, out: &mut [f32]) {
    if s.stride_w == 1 {
        return pad_interior(s, xc, cols, out);
    }
    debug_assert_eq!(s.stride_w, 2, "pad_phases: strides 1 and 2");
    for (iy, src) in xc.chunks_exact(s.w).enumerate() {
        let row = |phase: usize| (phase * rows + iy + s.pad_h) * cols;
        // The even input columns to one phase, the odd ones to the other.
        let pad = s.pad_w;
        let (e0, o0) = if pad.is_multiple_of(2) { (row(0), row(1)) } else { (row(1), row(0)) };
        let (even_at, odd_at) = (e0 + pad / 2, o0 + pad.div_ceil(2));
        crate::kernels::layout::split_phases(src, out, even_at, odd_at);
    }
}

/// Writes `act(acc · scale[c] + shift[c] + res)` into `dst`, `res` the residual's values
/// at the same pixels (when the conv adds one).
#[inline(always)]
fn finish(dst: &mut [f32], acc: &[f32], c: usize, ep: &Epilogue, res: Option<&[f32]>) {
    let dst = &mut dst[..acc.len()];
    affine(dst, acc, c, ep, res);
    ep.finish_act(dst);
}

/// [`finish`] but for an activation other than a ReLU: `acc · scale[c] + shift[c] + res`
/// into `dst`, then the ReLU if the epilogue has one.
#[inline(always)]
fn affine(dst: &mut [f32], acc: &[f32], c: usize, ep: &Epilogue, res: Option<&[f32]>) {
    let scale = ep.scale.map_or(1.0, |v| v[c]);
    let shift = ep.shift.map_or(0.0, |v| v[c]);
    let dst = &mut dst[..acc.len()];
    if let Some(res) = res {
        let res = &res[..acc.len()];
        let it = dst.iter_mut().zip(acc).zip(res);
        if ep.relu() {
            it.for_each(|((d, &a), &r)| *d = relu(a * scale + shift + r));
        } else {
            it.for_each(|((d, &a), &r)| *d = a * scale + shift + r);
        }
    } else {
        match (ep.scale.is_some(), ep.relu()) {
            (true, true) => dst.iter_mut().zip(acc).for_each(|(d, &a)| *d = relu(a * scale + shift)),
            (true, false) => dst.iter_mut().zip(acc).for_each(|(d, &a)| *d = a * scale + shift),
            (false, true) => dst.iter_mut().zip(acc).for_each(|(d, &a)| *d = relu(a + shift)),
            (false, false) => dst.iter_mut().zip(acc).for_each(|(d, &a)| *d = a + shift),
        }
    }
}

/// `src` into the start of `dst`, the rest of `dst` zero: a tail tile's row, padded
/// (the adapter's and the register tiles' tails).
fn pad_row(dst: &mut [f32], src: &[f32]) {
    let (head, rest) = dst.split_at_mut(src.len());
    head.copy_from_slice(src);
    rest.fill(0.0);
}

/// One part's scratch; `rank` rows more of the tile (of the transformed block) for a
/// LoRA branch's `A x`.
fn part_scratch(s: &Conv2dShape, algo: ConvAlgo, rank: usize) -> usize {
    // Past an im2col tile's unfolded rows, the register tiles' tail scratch, where they
    // take the layer (also a layer the direct conv takes, when an adapter sends it down
    // the GEMM path).
    let registers = if pointwise::applies_unfolded(s) { pointwise::scratch_len(s.k()) } else { 0 };
    match algo {
        ConvAlgo::Gemm1x1 => (gemm_tile(s, algo) * (s.cout_g() + rank)).max(pointwise::scratch_len(s.cin)),
        // A LoRA branch's `t` (rank rows of a tile), and under a channel split each part's
        // share of it (`im2col_shared`). The direct conv (a stem, narrow groups) reads one
        // image's padded input from the scratch.
        ConvAlgo::Im2col if direct::applies(s) => {
            (gemm_tile(s, algo) * (s.cout_g() + s.k() + 2 * rank) + registers).max(direct::scratch_len(s))
        }
        ConvAlgo::Im2col => gemm_tile(s, algo) * (s.cout_g() + s.k() + 2 * rank) + registers,
        ConvAlgo::Winograd2 => Wino::new::<4, 2>(s).scratch(rank),
        ConvAlgo::Winograd4 => Wino::new::<6, 4>(s).scratch(rank),
        ConvAlgo::Depthwise => 0,
        ConvAlgo::Panels => panels::scratch_len(s, rank),
    }
}

#[cfg(test)]
mod tests;
