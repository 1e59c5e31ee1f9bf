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
//!   finish the conv with scale and shift only, then [`apply_planes`] reads the output
//!   once per chunk of pixels of one image (sized to stay in L2), threaded over the
//!   chunks, and writes it back final: one read and one write of the activation instead
//!   of the separate steps' seven (down reads `y`; the add reads `y` and `up`'s output and
//!   writes; the ReLU reads and writes; `up` writes).

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
    if t == 1 || jobs0.is_multiple_of(t) {
        return (p0, plane.div_ceil(p0));
    }
    let per_image = (jobs0.div_ceil(t) * t).div_ceil(s.n.max(1));
    let p = plane.div_ceil(per_image).div_ceil(16).saturating_mul(16).clamp(1, p0);
    (p, plane.div_ceil(p))
}

/// One chunk of pixels of one image, as one slice per channel.
type Job<'a> = Vec<&'a mut [f32]>;

/// Scratch floats [`apply_planes`] needs at this thread count.
pub(super) fn planes_scratch_len(s: &Conv2dShape, mid: usize, threads: usize) -> usize {
    threads.max(1) * (s.cout + mid) * chunk(s.cout, mid, s.oh * s.ow)
}

/// The adapter on one tile `y` (`cout` rows of `tp` pixels, row-major, already scaled and
/// shifted), in place, then the step's activation `act`; `h` holds at least `mid · tp`
/// floats.
pub(super) fn apply_tile(ad: &Adapter, y: &mut [f32], cout: usize, tp: usize, h: &mut [f32], act: Option<Activation>) {
    let (mid, y) = (ad.mid, &mut y[..cout * tp]);
    let h = &mut h[..mid * tp];
    sgemm(
        MatRef::row_major(ad.down, mid, cout),
        MatRef::row_major(y, cout, tp),
        MatMut::row_major(h, mid, tp),
        false,
        1,
    );
    bias_rows(h, ad.down_bias, tp, false);
    // A tile is one thread's work: its activations on this thread.
    elementwise::activation_chunk(ad.act, h);
    sgemm(MatRef::row_major(ad.up, cout, mid), MatRef::row_major(h, mid, tp), MatMut::row_major(y, cout, tp), true, 1);
    let relu = act == Some(Activation::Relu);
    bias_rows(y, ad.up_bias, tp, relu);
    if let Some(f) = act.filter(|_| !relu) {
        elementwise::activation_chunk(f, y);
    }
}

simd_fn! {
    /// Row `c` of `rows` (of `tp` values) plus `bias[c]`, then the ReLU if `relu`.
    fn bias_rows(rows: &mut [f32], bias: &[f32], tp: usize, relu: bool) {
        for (row, &b) in rows.chunks_mut(tp).zip(bias) {
            if relu {
                row.iter_mut().for_each(|v| *v = (*v + b).max(0.0));
            } else {
                row.iter_mut().for_each(|v| *v += b);
            }
        }
    }
}

/// The adapter on a conv's whole output `[n, cout, oh, ow]` (scaled and shifted), in
/// place, then the step's activation `act`: per chunk of [`chunk`] pixels of one image, copied
/// into scratch, adapted there and copied back; the chunks shared by `threads` threads,
/// each with its own part of `scratch` (at least [`planes_scratch_len`] floats).
pub(super) fn apply_planes(
    s: &Conv2dShape,
    ad: &Adapter,
    out: &mut [f32],
    act: Option<Activation>,
    scratch: &mut [f32],
    threads: usize,
) {
    let (cout, mid, plane) = (s.cout, ad.mid, s.oh * s.ow);
    if plane == 0 || s.n == 0 {
        return;
    }
    let (p, per_image) = chunks(s, mid, threads);
    // Each job: one chunk of one image, as one slice per channel.
    let mut jobs: Vec<Vec<&mut [f32]>> = (0..s.n * per_image).map(|_| Vec::with_capacity(cout)).collect();
    for (idx, pl) in out.chunks_mut(plane).enumerate() {
        let n = idx / cout;
        for (j, seg) in pl.chunks_mut(p).enumerate() {
            jobs[n * per_image + j].push(seg);
        }
    }
    let workers = threads.max(1).min(jobs.len());
    let per = (cout + mid) * p;
    let one = |job: &mut Vec<&mut [f32]>, scratch: &mut [f32]| {
        let tp = job[0].len();
        let (y, h) = scratch.split_at_mut(cout * tp);
        gather(job, y, tp);
        apply_tile(ad, y, cout, tp, h, act);
        scatter(job, y, tp);
    };
    if workers <= 1 {
        let scratch = &mut scratch[..per];
        jobs.iter_mut().for_each(|job| one(job, scratch));
        return;
    }
    // Contiguous runs of jobs per worker, so each owns one part of the scratch.
    let mut groups: Vec<(&mut [Job<'_>], &mut [f32])> = Vec::with_capacity(workers);
    let (mut rest, mut scratch) = (jobs.as_mut_slice(), &mut scratch[..workers * per]);
    for w in 0..workers {
        let take = (rest.len()) / (workers - w);
        let (mine, tail) = std::mem::take(&mut rest).split_at_mut(take);
        let (sc, sc_tail) = std::mem::take(&mut scratch).split_at_mut(per);
        groups.push((mine, sc));
        (rest, scratch) = (tail, sc_tail);
    }
    groups.par_iter_mut().for_each(|(jobs, scratch)| jobs.iter_mut().for_each(|job| one(job, scratch)));
}

simd_fn! {
    /// The chunk's channel slices into `y`, row-major `cout x tp`.
    fn gather(job: &[&mut [f32]], y: &mut [f32], tp: usize) {
        for (dst, src) in y.chunks_mut(tp).zip(job) {
            dst.copy_from_slice(src);
        }
    }
}

simd_fn! {
    /// `y` back into the chunk's channel slices.
    fn scatter(job: &mut [&mut [f32]], y: &[f32], tp: usize) {
        for (dst, src) in job.iter_mut().zip(y.chunks(tp)) {
            dst.copy_from_slice(src);
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
            for threads in [1, 2] {
                let need = adapter_scratch_len(s, algo, 0, mid, threads).expect("a size");
                let mut scratch = vec![f32::NAN; need];
                let mut out = vec![f32::NAN; want.len()];
                conv2d_adapter(s, algo, &packed, None, Some(&ad), &ep, &x, &mut out, &mut scratch, threads);
                let tol = if matches!(algo, ConvAlgo::Winograd4) { 1e-4 } else { 2e-5 };
                assert_close(&out, &want, tol);
                if relu {
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
    fn chunks_are_shared_evenly() {
        // One chunk of a 7x7 image becomes two for two threads; five of 56x56 six.
        assert_eq!(chunks(&shape(1, 8, (7, 7), 512, 3, 1, 1), 256, 2), (32, 2));
        assert_eq!(chunks(&shape(1, 8, (56, 56), 64, 3, 1, 1), 32, 2), (528, 6));
        assert_eq!(chunks(&shape(1, 8, (56, 56), 64, 3, 1, 1), 32, 1), (672, 5));
        check(&shape(1, 8, (7, 7), 64, 3, 1, 1), ConvAlgo::Winograd2, 32, Activation::Relu);
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
