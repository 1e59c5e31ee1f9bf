//! A residual bottleneck adapter fused into the conv that produces its input
//! ([`Adapter`]): on the conv's output `y` after the epilogue's scale and shift,
//! `y + up · act(down · y + down_bias) + up_bias`, then the epilogue's ReLU.
//!
//! The adapter needs every channel of a pixel, so it runs on chunks of pixels holding all
//! `cout` channels, two small GEMMs per chunk (`h = down · y` to `mid` rows, `y += up · h`)
//! while the chunk is in cache:
//!
//! * the GEMM paths (Gemm1x1, Im2col) under a split by output rows compute every channel
//!   of a tile of pixels into one accumulator: [`apply_tile`] runs there, between the
//!   scale/shift and the copy to the output (`im2col.rs`), so the conv's output is
//!   written once, final;
//! * Winograd (whose output transform writes the planes directly), the depthwise loop and
//!   a split by output channels (each thread then holds only some channels of a pixel)
//!   finish the conv with scale and shift only, then [`apply_planes`] runs the two GEMMs
//!   on the output planes where they are, per chunk of pixels of one image (sized to stay
//!   in L2; the GEMMs read rows a plane apart): `down` reads the chunk, `up` adds into it
//!   and the bias and ReLU follow, instead of the separate steps' seven passes (down reads
//!   `y`; the add reads `y` and `up`'s output and writes; the ReLU reads and writes; `up`
//!   writes). Before, each chunk was gathered into scratch and scattered back: two copies
//!   of the activation, and a `Vec` of slices per chunk allocated on every call. On
//!   several threads the chunks' `down` is shared by chunks and `up` by channels (each
//!   thread then writes only its own planes), one join between them. An image that fits
//!   one chunk (a last stage's 7x7) shares `down` by bottleneck rows instead: each thread
//!   reads only its rows of the weight, and no GEMM is cut to an awkward width (a 7x7
//!   plane went to two threads as 32 + 17 pixels).

use rayon::prelude::*;

use super::Conv2dShape;
use crate::kernels::gemm::{MatMut, MatRef, sgemm};
use crate::kernels::{Activation, elementwise};

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

/// Pixels per chunk of [`apply_planes`]: the chunk of `cout` channels plus its `mid`
/// bottleneck rows in 256 KiB (half a typical L2), in multiples of 16 pixels (the GEMM's
/// vector width), at most the plane rounded up.
pub(super) fn chunk(cout: usize, mid: usize, plane: usize) -> usize {
    let per = (cout + mid).max(1);
    let p = (64 * 1024 / per).clamp(16, 4096) / 16 * 16;
    p.min(plane.div_ceil(16) * 16).max(16)
}

/// The pixels per chunk [`apply_planes`] uses and the chunks per image: [`chunk`]'s, made
/// smaller where that gives every thread the same number of chunks (a small image, or a
/// count of chunks the threads do not divide, would leave a thread idle).
fn chunks(s: &Conv2dShape, mid: usize, threads: usize) -> (usize, usize) {
    let plane = s.oh * s.ow;
    let p0 = chunk(s.cout, mid, plane);
    let (t, jobs0) = (threads.max(1), s.n * plane.div_ceil(p0));
    if t == 1 {
        return (p0, plane.div_ceil(p0));
    }
    // A count the threads divide, then chunks of equal size (a 14x14 image in chunks of
    // 160 pixels would leave one thread 160 and the other 36).
    let per_image = (jobs0.div_ceil(t) * t).div_ceil(s.n.max(1));
    let p = plane.div_ceil(per_image).div_ceil(16).saturating_mul(16).clamp(1, p0);
    (p, plane.div_ceil(p))
}

/// Scratch floats [`apply_planes`] needs at this thread count.
pub(super) fn planes_scratch_len(s: &Conv2dShape, mid: usize, threads: usize) -> usize {
    threads.max(1) * (s.cout + mid) * chunk(s.cout, mid, s.oh * s.ow)
}

/// The adapter on one tile `y` (`cout` rows of `tp` pixels, row-major, already scaled and
/// shifted), in place, then the step's activation `act`; `h` holds at least `mid · tp`
/// floats.
pub(super) fn apply_tile(ad: &Adapter, y: &mut [f32], cout: usize, tp: usize, h: &mut [f32], act: Option<Activation>) {
    apply_strided(ad, y, cout, tp, tp, h, act, None);
}

/// [`apply_tile`] on `cout` rows of `tp` pixels `stride` apart (a chunk of an image's
/// channel planes, read and written where they are), adding the residual `res` (laid out
/// as `y`) before the activation.
#[allow(clippy::too_many_arguments)]
fn apply_strided(
    ad: &Adapter,
    y: &mut [f32],
    cout: usize,
    tp: usize,
    stride: usize,
    h: &mut [f32],
    act: Option<Activation>,
    res: Option<&[f32]>,
) {
    let h = &mut h[..ad.mid * tp];
    down(ad, y, cout, tp, stride, h);
    up(ad, h, y, 0..cout, tp, stride, act, res);
}

/// `h = act(down · y + down_bias)` for `cout` rows of `tp` pixels of `y`, `stride` apart.
fn down(ad: &Adapter, y: &[f32], cout: usize, tp: usize, stride: usize, h: &mut [f32]) {
    down_rows(ad, 0..ad.mid, y, cout, tp, stride, h);
}

/// The bottleneck rows `rows` of [`down`] into `h` (`rows.len()` rows of `tp`).
fn down_rows(
    ad: &Adapter,
    rows: std::ops::Range<usize>,
    y: &[f32],
    cout: usize,
    tp: usize,
    stride: usize,
    h: &mut [f32],
) {
    let (m, h) = (rows.len(), &mut h[..rows.len() * tp]);
    let y = MatRef { data: y, rows: cout, cols: tp, row_stride: stride, col_stride: 1 };
    let w = MatRef::row_major(&ad.down[rows.start * cout..][..m * cout], m, cout);
    sgemm(w, y, MatMut::row_major(h, m, tp), false, 1);
    bias_rows(h, &ad.down_bias[rows], None, tp, tp, false);
    // A tile is one thread's work: its activations on this thread.
    elementwise::activation_chunk(ad.act, h);
}

/// `y[c] += up[c] · h + up_bias[c] (+ res[c])`, then `act`, for the channels `chans` of `y`
/// (its rows `0..chans.len()`, `tp` pixels, `stride` apart; `res` laid out as `y`).
#[allow(clippy::too_many_arguments)]
fn up(
    ad: &Adapter,
    h: &[f32],
    y: &mut [f32],
    chans: std::ops::Range<usize>,
    tp: usize,
    stride: usize,
    act: Option<Activation>,
    res: Option<&[f32]>,
) {
    let (mid, rows) = (ad.mid, chans.len());
    let w = MatRef::row_major(&ad.up[chans.start * mid..][..rows * mid], rows, mid);
    let dst = MatMut { data: &mut *y, rows, cols: tp, row_stride: stride, col_stride: 1 };
    sgemm(w, MatRef::row_major(&h[..mid * tp], mid, tp), dst, true, 1);
    let relu = act == Some(Activation::Relu);
    bias_rows(y, &ad.up_bias[chans], res, tp, stride, relu);
    if let Some(f) = act.filter(|_| !relu) {
        for row in y.chunks_mut(stride).take(rows) {
            elementwise::activation_chunk(f, &mut row[..tp]);
        }
    }
}

simd_fn! {
    /// The first `tp` values of row `c` of `rows` (rows `stride` apart) plus `bias[c]` and,
    /// if given, the same values of `res` (laid out as `rows`), then the ReLU if `relu`.
    fn bias_rows(rows: &mut [f32], bias: &[f32], res: Option<&[f32]>, tp: usize, stride: usize, relu: bool) {
        for (c, (row, &b)) in rows.chunks_mut(stride).zip(bias).enumerate() {
            let row = &mut row[..tp];
            match res.map(|r| &r[c * stride..][..tp]) {
                Some(r) if relu => row.iter_mut().zip(r).for_each(|(v, &r)| *v = (*v + b + r).max(0.0)),
                Some(r) => row.iter_mut().zip(r).for_each(|(v, &r)| *v += b + r),
                None if relu => row.iter_mut().for_each(|v| *v = (*v + b).max(0.0)),
                None => row.iter_mut().for_each(|v| *v += b),
            }
        }
    }
}

/// The adapter on a conv's whole output `[n, cout, oh, ow]` (scaled and shifted), in
/// place, plus the residual `res` (of the output's shape) if given, then the step's
/// activation `act`, per chunk of [`chunk`] pixels of one image,
/// read and written where it is (two GEMMs on the planes, rows a plane apart; nothing
/// copied, nothing allocated). On one thread chunk by chunk; on more, per image and per
/// round of chunks whose bottleneck rows fit `scratch` (at least [`planes_scratch_len`]
/// floats): every chunk's `down` (the threads sharing the chunks, reading the planes, or,
/// when the image is one chunk, sharing the bottleneck rows), then `up` (the threads
/// sharing the channels, each writing its own planes).
#[allow(clippy::too_many_arguments)]
pub(super) fn apply_planes(
    s: &Conv2dShape,
    ad: &Adapter,
    out: &mut [f32],
    act: Option<Activation>,
    res: Option<&[f32]>,
    scratch: &mut [f32],
    threads: usize,
) {
    let (cout, mid, plane) = (s.cout, ad.mid, s.oh * s.ow);
    if plane == 0 || s.n == 0 {
        return;
    }
    let (p, per_image) = chunks(s, mid, threads);
    let workers = threads.max(1).min(s.n * per_image);
    // Chunk `j` of `p` pixels: its first pixel and its width.
    let chunk_px = |p: usize, j: usize| (j * p, p.min(plane - j * p));
    if workers <= 1 {
        let h = &mut scratch[..mid * p];
        for (i, image) in out.chunks_mut(cout * plane).enumerate() {
            let r = res.map(|r| &r[i * cout * plane..]);
            for j in 0..per_image {
                let (p0, tp) = chunk_px(p, j);
                apply_strided(ad, &mut image[p0..], cout, tp, plane, h, act, r.map(|r| &r[p0..]));
            }
        }
        return;
    }
    // Channels per worker in `up`, in whole vectors of 8 rows of the weight.
    let per_worker = cout.div_ceil(workers).next_multiple_of(8).min(cout);
    // A small image (a last stage's 7x7) that fits one chunk stays one: its `down` is
    // shared by bottleneck rows, so each thread reads only its rows of the weight and
    // works on the whole plane (chunks of 25 and 24 pixels would be GEMMs of awkward
    // widths). Larger images: `down` shared by chunks.
    let by_rows = plane <= chunk(cout, mid, plane);
    let (p, per_image) = if by_rows { (plane, 1) } else { (p, per_image) };
    let mid_per = mid.div_ceil(workers).next_multiple_of(8).min(mid);
    // Chunks per round: as many bottleneck chunks as the scratch holds, at least one per
    // worker (the scratch holds `workers · (cout + mid)` chunks' worth).
    let round = (scratch.len() / (mid * p)).clamp(1, per_image);
    for (i, image) in out.chunks_mut(cout * plane).enumerate() {
        let r = res.map(|r| &r[i * cout * plane..]);
        for j0 in (0..per_image).step_by(round) {
            let js = j0..(j0 + round).min(per_image);
            let hs = &mut scratch[..js.len() * mid * p];
            let y: &[f32] = image;
            if by_rows {
                hs.par_chunks_mut(mid_per * p).enumerate().for_each(|(w, h)| {
                    let rows = w * mid_per..(w * mid_per + mid_per).min(mid);
                    down_rows(ad, rows, y, cout, p, plane, h);
                });
            } else {
                hs.par_chunks_mut(mid * p).zip(js.clone()).for_each(|(h, j)| {
                    let (p0, tp) = chunk_px(p, j);
                    down(ad, &y[p0..], cout, tp, plane, h);
                });
            }
            let hs: &[f32] = hs;
            image.par_chunks_mut(per_worker * plane).enumerate().for_each(|(w, planes)| {
                let c0 = w * per_worker;
                let chans = c0..(c0 + per_worker).min(cout);
                for (h, j) in hs.chunks(mid * p).zip(js.clone()) {
                    let (p0, tp) = chunk_px(p, j);
                    let r = r.map(|r| &r[c0 * plane + p0..]);
                    up(ad, h, &mut planes[p0..], chans.clone(), tp, plane, act, r);
                }
            });
        }
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
        // Winograd and depthwise: after the conv, over the output.
        for algo in [ConvAlgo::Winograd2, ConvAlgo::Winograd4] {
            assert_eq!(check(&shape(2, 6, (13, 12), 8, 3, 1, 1), algo, 4, Activation::Relu), [false, false]);
        }
        assert_eq!(
            check(&shape(2, 8, (10, 9), 8, 3, 1, 8), ConvAlgo::Depthwise, 2, Activation::Sigmoid),
            [false, false]
        );
        // Groups: after the conv.
        assert_eq!(check(&shape(1, 8, (7, 6), 8, 3, 1, 2), ConvAlgo::Im2col, 4, Activation::Relu), [false, false]);
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
    fn planes_of_several_chunks() {
        // 60x60 = 3600 pixels at 16 + 4 channels: chunks of 3264, two per image.
        let s = shape(2, 4, (60, 60), 16, 3, 1, 1);
        assert_eq!(chunk(16, 4, 3600), 3264);
        check(&s, ConvAlgo::Winograd4, 4, Activation::Relu);
        // Odd chunk counts over two threads.
        let s = shape(3, 4, (30, 30), 16, 3, 1, 1);
        check(&s, ConvAlgo::Winograd2, 4, Activation::Relu);
    }

    #[test]
    fn rounds_of_chunks_and_uneven_channel_shares() {
        // 100x100 at 16 + 16 channels on two threads: six chunks of 1680 pixels, whose
        // bottleneck rows (16 x 1680 each) fill the scratch (2 x 32 x 2048) four at a
        // time: two rounds. Three threads share 20 channels as 8, 8 and 4.
        let s = shape(1, 4, (100, 100), 16, 3, 1, 1);
        assert_eq!(chunks(&s, 16, 2), (1680, 6));
        assert_eq!(planes_scratch_len(&s, 16, 2) / (16 * 1680), 4);
        let (down, up) = (data(16 * 16, 21), data(16 * 16, 22));
        let (bd, bu) = (data(16, 23), data(16, 24));
        let ad = Adapter { down: &down, down_bias: &bd, up: &up, up_bias: &bu, mid: 16, act: Activation::Relu };
        let y = data(16 * 10_000, 25);
        let run = |threads: usize| {
            let mut out = y.clone();
            let mut scratch = vec![f32::NAN; planes_scratch_len(&s, 16, threads)];
            apply_planes(&s, &ad, &mut out, Some(Activation::Relu), None, &mut scratch, threads);
            out
        };
        let one = run(1);
        // One thread against a naive loop at a few pixels, then two threads against one.
        for p in [0, 1679, 1680, 9999] {
            for c in [0, 7, 15] {
                let at = |c: usize| f64::from(y[c * 10_000 + p]);
                let h: Vec<f64> = (0..16)
                    .map(|m| {
                        ((0..16).map(|k| f64::from(down[m * 16 + k]) * at(k)).sum::<f64>() + f64::from(bd[m])).max(0.0)
                    })
                    .collect();
                let z = at(c) + (0..16).map(|m| f64::from(up[c * 16 + m]) * h[m]).sum::<f64>() + f64::from(bu[c]);
                assert!((f64::from(one[c * 10_000 + p]) - z.max(0.0)).abs() < 1e-4, "pixel {p} channel {c}");
            }
        }
        assert_close(&run(2), &one, 1e-6);
        check(&shape(2, 4, (9, 9), 20, 3, 1, 1), ConvAlgo::Winograd2, 5, Activation::Silu);
    }

    #[test]
    fn chunks_are_shared_evenly() {
        // Five chunks of 56x56 become six for two threads.
        assert_eq!(chunks(&shape(1, 8, (56, 56), 64, 3, 1, 1), 32, 2), (528, 6));
        assert_eq!(chunks(&shape(1, 8, (56, 56), 64, 3, 1, 1), 32, 1), (672, 5));
        // Two chunks of 14x14 at 256 + 128 channels: 112 and 84 pixels, not 160 and 36.
        assert_eq!(chunks(&shape(1, 8, (14, 14), 256, 3, 1, 1), 128, 2), (112, 2));
    }

    #[test]
    fn a_small_image_shares_the_bottleneck_rows() {
        // 7x7 at 40 + 20 channels fits one chunk: `down` split by bottleneck rows (16 + 4
        // on two threads, 8 + 8 + 4 on three), `up` by channels (24 + 16).
        let s = shape(2, 8, (7, 7), 40, 3, 1, 1);
        assert!(s.oh * s.ow <= chunk(40, 20, 49));
        check(&s, ConvAlgo::Winograd2, 20, Activation::Relu);
        check(&shape(1, 8, (7, 7), 64, 3, 1, 1), ConvAlgo::Winograd2, 32, Activation::Silu);
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
                    if mid == 16 && threads > 1 {
                        assert!(chunks(&s, mid, threads).1 > 1, "several chunks an image");
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
