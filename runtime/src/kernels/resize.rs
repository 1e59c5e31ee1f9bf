//! Spatial upsampling of `[nc, h, w]` planes, nearest or bilinear, with PyTorch's index
//! mapping.

use rayon::prelude::*;

/// Below this many output elements upsampling runs on the calling thread.
const PAR_MIN: usize = 1 << 15;
/// Output elements per parallel task, roughly.
const CHUNK: usize = 1 << 14;
/// Output columns whose source indices and weights are computed together.
const TILE: usize = 128;

/// How `upsample` picks input values for an output position: PyTorch's legacy
/// `'nearest'` (not `'nearest-exact'`) or `'bilinear'` (no antialiasing).
pub use readi_plan::ops::UpsampleMode as ResizeMode;

/// The output-to-input index mapping along one axis, computed in f32 like PyTorch's CPU
/// kernels so that index choices agree at the boundaries.
#[derive(Clone, Copy, Debug)]
struct AxisMap {
    in_len: usize,
    out_len: usize,
    align_corners: bool,
    /// Input positions per output position.
    ratio: f32,
}

impl AxisMap {
    fn new(mode: ResizeMode, align_corners: bool, scale: Option<f64>, in_len: usize, out_len: usize) -> AxisMap {
        let align_corners = align_corners && mode == ResizeMode::Bilinear;
        let ratio = if align_corners {
            if out_len > 1 { (in_len - 1) as f32 / (out_len - 1) as f32 } else { 0.0 }
        } else {
            match scale {
                // PyTorch: `static_cast<float>(1.0 / scale)`, the division in f64.
                Some(s) if s > 0.0 => (1.0 / s) as f32,
                _ => in_len as f32 / out_len as f32,
            }
        };
        AxisMap { in_len, out_len, align_corners, ratio }
    }

    /// Nearest source index (PyTorch's `nearest_idx`): the same index when sizes agree,
    /// `o / 2` when the output is exactly twice the input, else `min(floor(o * ratio), in - 1)`.
    #[inline(always)]
    fn nearest(&self, o: usize) -> usize {
        if self.out_len == self.in_len {
            o
        } else if self.out_len == 2 * self.in_len {
            o >> 1
        } else {
            ((o as f32 * self.ratio).floor() as usize).min(self.in_len - 1)
        }
    }

    /// Linear source indices and weights `(i0, i1, w0, w1)` (PyTorch's
    /// `compute_source_index_and_lambda`): identity when sizes agree; otherwise the source
    /// position `o * ratio` (align_corners) or `max((o + 0.5) * ratio - 0.5, 0)`, its floor
    /// clamped to the input, and the next index unless at the edge.
    #[inline(always)]
    fn linear(&self, o: usize) -> (usize, usize, f32, f32) {
        if self.out_len == self.in_len {
            return (o, o, 1.0, 0.0);
        }
        let src =
            if self.align_corners { self.ratio * o as f32 } else { (self.ratio * (o as f32 + 0.5) - 0.5).max(0.0) };
        let i0 = (src.floor() as usize).min(self.in_len - 1);
        let w1 = (src - i0 as f32).clamp(0.0, 1.0);
        let i1 = if i0 + 1 < self.in_len { i0 + 1 } else { i0 };
        (i0, i1, 1.0 - w1, w1)
    }
}

/// Upsamples `x` (`[nc, h, w]`) into `out` (`[nc, oh, ow]`) as PyTorch's `nn.Upsample` /
/// `F.interpolate` with `mode='nearest'` or `'bilinear'`.
///
/// `scale` is the user's `scale_factor` (h, w) when one was given (and not recomputed):
/// then the source position of output index `o` is derived from `o / scale`, otherwise
/// from `o * in / out`. With `align_corners` (bilinear only; ignored for nearest) the
/// ratio is `(in - 1) / (out - 1)` and `scale` is ignored. An axis whose output size
/// equals its input size is copied, whatever the scale. Preconditions: `h, w >= 1` when
/// the output is non-empty.
#[allow(clippy::too_many_arguments)]
pub fn upsample(
    mode: ResizeMode,
    align_corners: bool,
    scale: Option<(f64, f64)>,
    x: &[f32],
    nc: usize,
    h: usize,
    w: usize,
    out: &mut [f32],
    oh: usize,
    ow: usize,
) {
    debug_assert_eq!(check(&[1, nc, h, w], &[1, nc, oh, ow]), Ok(()), "upsample preconditions");
    assert_eq!(x.len(), nc * h * w, "upsample: x is not [nc, h, w]");
    assert_eq!(out.len(), nc * oh * ow, "upsample: out is not [nc, oh, ow]");
    if out.is_empty() {
        return;
    }
    assert!(h > 0 && w > 0, "upsample: empty input with a non-empty output");
    let my = AxisMap::new(mode, align_corners, scale.map(|s| s.0), h, oh);
    let mx = AxisMap::new(mode, align_corners, scale.map(|s| s.1), w, ow);
    let run = |first: usize, out: &mut [f32]| upsample_rows(mode, &my, &mx, x, h, w, oh, ow, first, out);
    let rows_per_task = (CHUNK / ow).max(1);
    if out.len() >= PAR_MIN && nc * oh > rows_per_task {
        out.par_chunks_mut(rows_per_task * ow).enumerate().for_each(|(t, o)| run(t * rows_per_task, o));
    } else {
        run(0, out);
    }
}

simd_fn! {
    /// Fills output rows `first..` (counted over all planes) of an upsampling of `x`
    /// (`[nc, h, w]`) to `[nc, oh, ow]` into `out`.
    #[allow(clippy::too_many_arguments)]
    fn upsample_rows(
        mode: ResizeMode,
        my: &AxisMap,
        mx: &AxisMap,
        x: &[f32],
        h: usize,
        w: usize,
        oh: usize,
        ow: usize,
        first: usize,
        out: &mut [f32],
    ) {
        let rows = out.len() / ow;
        for c0 in (0..ow).step_by(TILE) {
            let cw = TILE.min(ow - c0);
            match mode {
                ResizeMode::Nearest => {
                    let mut src = [0usize; TILE];
                    for (j, s) in src[..cw].iter_mut().enumerate() {
                        *s = mx.nearest(c0 + j);
                    }
                    let mut prev: Option<(usize, usize)> = None;
                    for i in 0..rows {
                        let (plane, oy) = ((first + i) / oh, (first + i) % oh);
                        let sy = my.nearest(oy);
                        let dst = i * ow + c0;
                        // Rows repeated by the upsampling are copied from the previous one.
                        if let Some((pi, _)) = prev.filter(|&(_, key)| key == plane * h + sy) {
                            out.copy_within(pi * ow + c0..pi * ow + c0 + cw, dst);
                            continue;
                        }
                        let xr = &x[(plane * h + sy) * w..(plane * h + sy + 1) * w];
                        let dst = &mut out[dst..dst + cw];
                        if mx.out_len == 2 * mx.in_len {
                            // Each input column twice (c0 is even): no gather.
                            let xr = &xr[c0 / 2..];
                            let mut pairs = dst.chunks_exact_mut(2);
                            for (pair, &v) in (&mut pairs).zip(xr) {
                                pair[0] = v;
                                pair[1] = v;
                            }
                            if let [last] = pairs.into_remainder() {
                                *last = xr[cw / 2];
                            }
                        } else {
                            for (o, &s) in dst.iter_mut().zip(&src[..cw]) {
                                *o = xr[s];
                            }
                        }
                        prev = Some((i, plane * h + sy));
                    }
                }
                ResizeMode::Bilinear => {
                    let (mut x0, mut x1) = ([0usize; TILE], [0usize; TILE]);
                    let (mut w0, mut w1) = ([0f32; TILE], [0f32; TILE]);
                    for j in 0..cw {
                        (x0[j], x1[j], w0[j], w1[j]) = mx.linear(c0 + j);
                    }
                    // Separable: each input row is interpolated horizontally once into
                    // `hrow` (keyed by its row index over all planes in `key`), and output
                    // rows blend two of them, a contiguous vectorised loop. Upsampling
                    // reads each input row for about two output rows in a row.
                    let mut hrow = [[0f32; TILE]; 2];
                    let mut key = [usize::MAX; 2];
                    for i in 0..rows {
                        let (plane, oy) = ((first + i) / oh, (first + i) % oh);
                        let (y0, y1, v0, v1) = my.linear(oy);
                        let (k0, k1) = (plane * h + y0, plane * h + y1);
                        for k in [k0, k1] {
                            if key.contains(&k) {
                                continue;
                            }
                            // Replace the slot not holding the other row needed.
                            let slot = if key[0] == k0 || key[0] == k1 { 1 } else { 0 };
                            let r = &x[k * w..(k + 1) * w];
                            let taps = x0.iter().zip(&x1).zip(w0.iter().zip(&w1));
                            for (o, ((&i0, &i1), (&a0, &a1))) in hrow[slot][..cw].iter_mut().zip(taps) {
                                *o = r[i0] * a0 + r[i1] * a1;
                            }
                            key[slot] = k;
                        }
                        let (top, bottom) = (&hrow[usize::from(key[0] != k0)], &hrow[usize::from(key[0] != k1)]);
                        let dst = &mut out[i * ow + c0..i * ow + c0 + cw];
                        for ((o, &t), &b) in dst.iter_mut().zip(top).zip(bottom) {
                            *o = t * v0 + b * v1;
                        }
                    }
                }
            }
        }
    }
}

/// The preconditions of [`upsample`] on a 4-D value `x` giving `out`: the same planes,
/// and a non-empty input wherever the output is not empty.
pub fn check(x: &[usize], out: &[usize]) -> Result<(), String> {
    let (&[n, c, h, w], &[on, oc, oh, ow]) = (x, out) else {
        return Err(format!("upsample of {x:?} to {out:?}: both must be 4-D"));
    };
    if (n, c) != (on, oc) {
        return Err(format!("upsample of {x:?} to {out:?} changes the planes"));
    }
    let out_len = [on, oc, oh, ow].iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    if (h == 0 || w == 0) && out_len != Some(0) {
        return Err(format!("upsample of an empty input {x:?} to {out:?}"));
    }
    Ok(())
}

/// `pixel_shuffle` by `r` of `x` (`[n, c·r², h, w]`) into `out` (`[n, c, h·r, w·r]`),
/// `out[n, c, y·r + i, x·r + j] = x[n, c·r² + i·r + j, y, x]`, or with `inverse` its
/// inverse `pixel_unshuffle` of `x` (`[n, c, h·r, w·r]`) into `out` (`[n, c·r², h, w]`),
/// as PyTorch's: `c`, `h` and `w` are those of the two shapes as written here. A copy, one
/// output row at a time, in parallel when large.
#[allow(clippy::too_many_arguments)]
pub fn pixel_shuffle(inverse: bool, r: usize, x: &[f32], n: usize, c: usize, h: usize, w: usize, out: &mut [f32]) {
    assert!(r >= 1, "pixel_shuffle: factor 0");
    let len = n * c * r * r * h * w;
    assert!(x.len() == len && out.len() == len, "pixel_shuffle: x or out is not [n, c·r², h, w]");
    if len == 0 {
        return;
    }
    // Output rows: `[n, c, h·r]` of `w·r` (shuffle) or `[n, c·r², h]` of `w` (unshuffle).
    let row = if inverse { w } else { w * r };
    let rows = |first: usize, out: &mut [f32]| {
        for (k, o) in out.chunks_mut(row).enumerate() {
            let g = first + k;
            if inverse {
                // Row (s, cc·r² + i·r + j, y) reads row y·r + i of (s, cc) at stride r from j.
                let (y, ch) = (g % h, g / h);
                let (sc, ij) = (ch / (r * r), ch % (r * r));
                let (i, j) = (ij / r, ij % r);
                let src = &x[(sc * h * r + y * r + i) * w * r..][..w * r];
                for (o, &v) in o.iter_mut().zip(src.iter().skip(j).step_by(r)) {
                    *o = v;
                }
            } else {
                // Row (s, cc, y·r + i) interleaves rows y of channels (s, cc·r² + i·r + j).
                let (yi, sc) = (g % (h * r), g / (h * r));
                let (y, i) = (yi / r, yi % r);
                for j in 0..r {
                    let src = &x[((sc * r * r + i * r + j) * h + y) * w..][..w];
                    for (xx, &v) in src.iter().enumerate() {
                        o[xx * r + j] = v;
                    }
                }
            }
        }
    };
    if len >= PAR_MIN && len / row > 1 {
        let per_task = (CHUNK / row).max(1);
        out.par_chunks_mut(per_task * row).enumerate().for_each(|(t, o)| rows(t * per_task, o));
    } else {
        rows(0, out);
    }
}

/// The preconditions of [`pixel_shuffle`] by `r` (or its inverse) from `x` to `out`, both
/// 4-D: the element counts agree and the sizes are those of the shape rule.
pub fn check_pixel_shuffle(inverse: bool, r: usize, x: &[usize], out: &[usize]) -> Result<(), String> {
    let (small, big) = if inverse { (out, x) } else { (x, out) };
    match (small, big) {
        (&[n, crr, h, w], &[n2, c, hr, wr])
            if r >= 1
                && n == n2
                && Some(crr) == c.checked_mul(r * r)
                && Some(hr) == h.checked_mul(r)
                && Some(wr) == w.checked_mul(r) =>
        {
            Ok(())
        }
        _ => Err(format!("pixel shuffle by {r} of {x:?} cannot give {out:?}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, data};

    /// The ratio PyTorch maps with along one axis, in f64.
    fn ratio(align_corners: bool, scale: Option<f64>, n_in: usize, n_out: usize) -> f64 {
        match (align_corners, scale) {
            (true, _) if n_out > 1 => (n_in - 1) as f64 / (n_out - 1) as f64,
            (true, _) => 0.0,
            (false, Some(s)) => 1.0 / s,
            (false, None) => n_in as f64 / n_out as f64,
        }
    }

    /// Bilinear as a sum over every input pixel of tent weights `max(0, 1 - |src - i|)`, with
    /// the source position clamped to `[0, in - 1]`; an axis of unchanged size is copied.
    #[allow(clippy::too_many_arguments)]
    fn naive_bilinear(
        x: &[f32],
        nc: usize,
        h: usize,
        w: usize,
        oh: usize,
        ow: usize,
        ac: bool,
        scale: Option<(f64, f64)>,
    ) -> Vec<f32> {
        let src = |o: usize, n_in: usize, n_out: usize, s: Option<f64>| -> f64 {
            if n_in == n_out {
                return o as f64;
            }
            let r = ratio(ac, s, n_in, n_out);
            let p = if ac { o as f64 * r } else { (o as f64 + 0.5) * r - 0.5 };
            p.clamp(0.0, (n_in - 1) as f64)
        };
        let tent = |d: f64| (1.0 - d.abs()).max(0.0);
        let mut out = Vec::new();
        for p in 0..nc {
            for oy in 0..oh {
                let sy = src(oy, h, oh, scale.map(|s| s.0));
                for ox in 0..ow {
                    let sx = src(ox, w, ow, scale.map(|s| s.1));
                    let mut acc = 0.0;
                    for iy in 0..h {
                        for ix in 0..w {
                            acc += tent(sy - iy as f64) * tent(sx - ix as f64) * x[(p * h + iy) * w + ix] as f64;
                        }
                    }
                    out.push(acc as f32);
                }
            }
        }
        out
    }

    /// Nearest: output index `o` reads input `floor(o * ratio)`, clamped; an unchanged size
    /// copies and an exact doubling halves (both PyTorch special cases).
    fn naive_nearest(
        x: &[f32],
        nc: usize,
        h: usize,
        w: usize,
        oh: usize,
        ow: usize,
        scale: Option<(f64, f64)>,
    ) -> Vec<f32> {
        let src = |o: usize, n_in: usize, n_out: usize, s: Option<f64>| -> usize {
            match n_out {
                _ if n_out == n_in => o,
                _ if n_out == 2 * n_in => o / 2,
                _ => ((o as f64 * ratio(false, s, n_in, n_out)).floor() as usize).min(n_in - 1),
            }
        };
        let mut out = Vec::new();
        for p in 0..nc {
            for oy in 0..oh {
                for ox in 0..ow {
                    let (iy, ix) = (src(oy, h, oh, scale.map(|s| s.0)), src(ox, w, ow, scale.map(|s| s.1)));
                    out.push(x[(p * h + iy) * w + ix]);
                }
            }
        }
        out
    }

    fn run(
        mode: ResizeMode,
        ac: bool,
        scale: Option<(f64, f64)>,
        x: &[f32],
        nc: usize,
        hw: (usize, usize),
        ohw: (usize, usize),
    ) -> Vec<f32> {
        let mut out = vec![f32::NAN; nc * ohw.0 * ohw.1];
        upsample(mode, ac, scale, x, nc, hw.0, hw.1, &mut out, ohw.0, ohw.1);
        out
    }

    /// Output size for a scale factor, as PyTorch: floor(in * scale).
    fn scaled(n: usize, s: f64) -> usize {
        (n as f64 * s).floor() as usize
    }

    #[test]
    fn upsample_matches_naive_for_scales_and_sizes() {
        // (h, w, scale_factor, size)
        type Case = (usize, usize, Option<(f64, f64)>, Option<(usize, usize)>);
        let cases: &[Case] = &[
            (4, 5, Some((2.0, 2.0)), None),
            (3, 5, Some((1.5, 2.5)), None),
            (5, 3, Some((3.0, 1.7)), None),
            (1, 4, Some((4.0, 2.0)), None),
            (7, 6, None, Some((10, 13))),
            (6, 4, None, Some((6, 9))),
            (3, 3, None, Some((1, 5))),
            (5, 7, None, Some((3, 2))),
            (64, 80, Some((2.0, 2.0)), None),
        ];
        for &(h, w, scale, size) in cases {
            let (oh, ow) = size.unwrap_or_else(|| {
                let s = scale.expect("a case has a scale or a size");
                (scaled(h, s.0), scaled(w, s.1))
            });
            let x = data(3 * h * w, (h * 7 + w) as u64);
            let got = run(ResizeMode::Nearest, false, scale, &x, 3, (h, w), (oh, ow));
            assert_eq!(got, naive_nearest(&x, 3, h, w, oh, ow, scale), "nearest {h}x{w} -> {oh}x{ow} {scale:?}");
            for ac in [false, true] {
                let got = run(ResizeMode::Bilinear, ac, scale, &x, 3, (h, w), (oh, ow));
                let want = naive_bilinear(&x, 3, h, w, oh, ow, ac, scale);
                assert_close(&got, &want, 1e-5);
            }
        }
    }

    #[test]
    fn upsample_nearest_matches_pytorch() {
        // x = torch.arange(15.).reshape(1, 1, 3, 5)
        let x: Vec<f32> = (0..15).map(|v| v as f32).collect();
        // F.interpolate(x, scale_factor=(1.5, 2.5), mode='nearest')
        let got = run(ResizeMode::Nearest, false, Some((1.5, 2.5)), &x, 1, (3, 5), (4, 12));
        #[rustfmt::skip]
        let want = [
            0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0,
            0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0,
            5.0, 5.0, 5.0, 6.0, 6.0, 7.0, 7.0, 7.0, 8.0, 8.0, 9.0, 9.0,
            10.0, 10.0, 10.0, 11.0, 11.0, 12.0, 12.0, 12.0, 13.0, 13.0, 14.0, 14.0,
        ];
        assert_eq!(got, want);
        // F.interpolate(x, size=(5, 7), mode='nearest'): ratio in / out.
        let got = run(ResizeMode::Nearest, false, None, &x, 1, (3, 5), (5, 7));
        #[rustfmt::skip]
        let want = [
            0.0, 0.0, 1.0, 2.0, 2.0, 3.0, 4.0,
            0.0, 0.0, 1.0, 2.0, 2.0, 3.0, 4.0,
            5.0, 5.0, 6.0, 7.0, 7.0, 8.0, 9.0,
            5.0, 5.0, 6.0, 7.0, 7.0, 8.0, 9.0,
            10.0, 10.0, 11.0, 12.0, 12.0, 13.0, 14.0,
        ];
        assert_eq!(got, want);
    }

    #[test]
    fn upsample_nearest_size_special_cases_match_pytorch() {
        // An exact doubling reads o / 2 even when the scale is not 2:
        // F.interpolate(torch.arange(10.).reshape(1, 1, 1, 10), scale_factor=(1.0, 2.05), mode='nearest')
        let x: Vec<f32> = (0..10).map(|v| v as f32).collect();
        let got = run(ResizeMode::Nearest, false, Some((1.0, 2.05)), &x, 1, (1, 10), (1, 20));
        let want: Vec<f32> = (0..20).map(|o| (o / 2) as f32).collect();
        assert_eq!(got, want);
        // An unchanged size copies: floor(5 * 1.1) = 5 and the result is arange(5.), not
        // floor(o / 1.1). F.interpolate(torch.arange(5.).reshape(1, 1, 1, 5), scale_factor=(1.0, 1.1))
        let x: Vec<f32> = (0..5).map(|v| v as f32).collect();
        assert_eq!(run(ResizeMode::Nearest, false, Some((1.0, 1.1)), &x, 1, (1, 5), (1, 5)), x);
    }

    #[test]
    fn upsample_bilinear_matches_pytorch() {
        // x = torch.arange(15.).reshape(1, 1, 3, 5)
        let x: Vec<f32> = (0..15).map(|v| v as f32).collect();
        // F.interpolate(x, scale_factor=(1.5, 2.5), mode='bilinear', align_corners=False)
        let got = run(ResizeMode::Bilinear, false, Some((1.5, 2.5)), &x, 1, (3, 5), (4, 12));
        #[rustfmt::skip]
        let want = [
            0.0, 0.10000001, 0.5, 0.90000004, 1.3000001, 1.7, 2.1000001, 2.5, 2.9, 3.3, 3.7, 4.0,
            2.5, 2.6, 3.0, 3.4, 3.8, 4.2, 4.6000004, 5.0, 5.4, 5.8, 6.2, 6.5,
            5.8333335, 5.9333334, 6.333334, 6.7333336, 7.1333337, 7.5333333, 7.9333344, 8.333334, 8.733334, 9.133333, 9.533334, 9.833334,
            9.166667, 9.266666, 9.666667, 10.066667, 10.466667, 10.866667, 11.266667, 11.666667, 12.066667, 12.466667, 12.866667, 13.166667,
        ];
        assert_close(&got, &want, 1e-6);
        // F.interpolate(x, size=(4, 7), mode='bilinear', align_corners=True)
        let got = run(ResizeMode::Bilinear, true, None, &x, 1, (3, 5), (4, 7));
        #[rustfmt::skip]
        let want = [
            0.0, 0.6666667, 1.3333334, 2.0, 2.6666667, 3.3333335, 4.0,
            3.3333335, 4.0, 4.6666665, 5.3333335, 6.0, 6.666667, 7.3333335,
            6.666667, 7.3333335, 8.0, 8.666667, 9.333333, 10.0, 10.666667,
            10.0, 10.666667, 11.333333, 12.0, 12.666667, 13.333334, 14.0,
        ];
        assert_close(&got, &want, 1e-6);
        // F.interpolate(x, scale_factor=1.2, mode='bilinear'): the height keeps its size
        // (floor(3 * 1.2) = 3), so that axis is copied, not mapped with ratio 1 / 1.2.
        let got = run(ResizeMode::Bilinear, false, Some((1.2, 1.2)), &x, 1, (3, 5), (3, 6));
        #[rustfmt::skip]
        let want = [
            0.0, 0.75, 1.5833333, 2.4166665, 3.25, 4.0,
            5.0, 5.75, 6.5833335, 7.4166665, 8.25, 9.0,
            10.0, 10.75, 11.583333, 12.416666, 13.25, 14.0,
        ];
        assert_close(&got, &want, 1e-6);
    }

    #[test]
    fn upsample_to_one_pixel() {
        // F.interpolate(x, size=(1, 1), mode='bilinear', align_corners=True) reads x[0, 0];
        // with align_corners=False it reads the centre, (in / out) * 0.5 - 0.5 = 1 and 2 here.
        let x: Vec<f32> = (0..15).map(|v| v as f32).collect();
        assert_eq!(run(ResizeMode::Bilinear, true, None, &x, 1, (3, 5), (1, 1)), [0.0]);
        assert_eq!(run(ResizeMode::Bilinear, false, None, &x, 1, (3, 5), (1, 1)), [7.0]);
    }

    #[test]
    fn pixel_shuffle_and_unshuffle_match_the_index_formula() {
        for (n, c, h, w, r) in [(1, 1, 1, 1, 1), (2, 3, 4, 5, 2), (1, 2, 3, 2, 3), (1, 4, 64, 70, 2)] {
            let x = data(n * c * r * r * h * w, 21);
            let mut got = vec![f32::NAN; x.len()];
            pixel_shuffle(false, r, &x, n, c, h, w, &mut got);
            // torch: out[s, cc, y*r + i, xx*r + j] = x[s, cc*r*r + i*r + j, y, xx].
            let mut want = vec![0f32; x.len()];
            for s in 0..n {
                for cc in 0..c {
                    for y in 0..h {
                        for i in 0..r {
                            for xx in 0..w {
                                for j in 0..r {
                                    let o = ((s * c + cc) * h * r + y * r + i) * w * r + xx * r + j;
                                    want[o] = x[((s * c * r * r + cc * r * r + i * r + j) * h + y) * w + xx];
                                }
                            }
                        }
                    }
                }
            }
            assert_eq!(got, want, "shuffle {n} {c} {h} {w} by {r}");
            let mut back = vec![f32::NAN; x.len()];
            pixel_shuffle(true, r, &got, n, c, h, w, &mut back);
            assert_eq!(back, x, "unshuffle {n} {c} {h} {w} by {r}");
            assert_eq!(check_pixel_shuffle(false, r, &[n, c * r * r, h, w], &[n, c, h * r, w * r]), Ok(()));
            assert_eq!(check_pixel_shuffle(true, r, &[n, c, h * r, w * r], &[n, c * r * r, h, w]), Ok(()));
        }
        assert!(check_pixel_shuffle(false, 2, &[1, 4, 3, 3], &[1, 1, 6, 7]).is_err());
        assert!(check_pixel_shuffle(true, 2, &[1, 4, 3, 3], &[1, 16, 1, 1]).is_err());
    }
}
