//! Transposed 2-D convolution (PyTorch's `ConvTranspose2d`), NCHW, weight as PyTorch
//! stores it, `[cin, cout/groups, kh, kw]`, with a fused per-channel epilogue.
//!
//! GEMM and col2im: for one image and group, `cols = Wᵀ x` is a
//! `(cout/groups·kh·kw) × pixels` matrix whose row `(co, ky, kx)`, column `(iy, ix)` is
//! what input pixel `(iy, ix)` adds through tap `(ky, kx)` to output channel `co` at
//! `(iy·stride − pad + ky·dil, ix·stride − pad + kx·dil)`; a scatter-add puts it there.
//! The GEMM reads the weight in place (its transpose is a view with swapped strides) and
//! the input's pixels in tiles, so the scratch is one tile of `cols` per thread.
//!
//! Threads share a layer by blocks of output channels ([`split`]): a work unit is an image,
//! a group and a block of that group's channels, whose output planes are contiguous; each
//! thread owns a run of units and their planes, zeroes them, accumulates every tile of
//! its images' input into them and applies the epilogue, so threads never synchronise.
//! Blocks divide the group's channels, so no unit straddles a group. Allocates nothing.

use super::Epilogue;
use super::elementwise::relu;
use super::gemm::{MatMut, MatRef, sgemm};

pub use readi_plan::ops::ConvTranspose2dShape;

/// Most elements of the input, output or weight [`check`] accepts (as conv's).
const MAX_ELEMENTS: usize = 1 << 48;

/// How the threads share a layer: `(channels per unit, units, parts)`. Each group's
/// channels are cut into the fewest equal blocks (a divisor of the group's channel count)
/// that give every thread a unit; `parts` threads take runs of units.
fn split(s: &ConvTranspose2dShape, threads: usize) -> (usize, usize, usize) {
    let threads = threads.max(1);
    let cout_g = s.cout_g().max(1);
    let base = (s.n * s.groups).max(1);
    let blocks = if base >= threads {
        1
    } else {
        (threads.div_ceil(base)..=cout_g).find(|d| cout_g.is_multiple_of(*d)).unwrap_or(cout_g)
    };
    let cb = cout_g / blocks;
    let units = base * blocks;
    (cb, units, threads.min(units))
}

/// Input pixels per GEMM tile: a tile of `cols` of up to 1.5 MiB, in multiples of 16.
fn tile(s: &ConvTranspose2dShape, cb: usize) -> usize {
    let rows = (cb * s.kh * s.kw).max(1);
    let t = (384 * 1024 / rows).clamp(16, 4096) / 16 * 16;
    t.min((s.h * s.w).div_ceil(16) * 16)
}

/// Scratch floats [`conv_transpose2d`] needs at this thread count, `None` on overflow.
pub fn scratch_len(s: &ConvTranspose2dShape, threads: usize) -> Option<usize> {
    let (cb, _, parts) = split(s, threads);
    parts.checked_mul(cb.checked_mul(s.kh)?.checked_mul(s.kw)?)?.checked_mul(tile(s, cb))
}

/// The output length along one axis for input `len`, without output padding, as i128
/// (so no value of a `usize` overflows).
fn base_out(len: usize, k: usize, stride: usize, pad: usize, dil: usize) -> i128 {
    let [len, k, stride, pad, dil] = [len, k, stride, pad, dil].map(|v| v as i128);
    (len - 1) * stride - 2 * pad + dil * (k - 1) + 1
}

/// The preconditions of [`conv_transpose2d`]: groups divide the channels, no kernel,
/// stride or dilation is 0, the output size is PyTorch's with an output padding smaller
/// than the stride or the dilation, and the lengths of the weight, input, output and
/// epilogue vectors fit the shape. The executor checks this at bind time.
pub fn check(
    s: &ConvTranspose2dShape,
    weight_len: usize,
    x_len: usize,
    out_len: usize,
    epilogue: [Option<usize>; 2],
) -> Result<(), String> {
    if s.groups == 0 || !s.cin.is_multiple_of(s.groups) || !s.cout.is_multiple_of(s.groups) {
        return Err(format!("groups={} must divide {} input and {} output channels", s.groups, s.cin, s.cout));
    }
    if s.cin == 0 || s.cout == 0 {
        return Err(format!("{} input and {} output channels: a transposed conv needs at least one", s.cin, s.cout));
    }
    if [s.kh, s.kw, s.stride_h, s.stride_w, s.dil_h, s.dil_w].contains(&0) {
        return Err(format!(
            "kernel {}x{}, stride {}x{}, dilation {}x{}: none may be 0",
            s.kh, s.kw, s.stride_h, s.stride_w, s.dil_h, s.dil_w
        ));
    }
    let product =
        |dims: &[usize]| dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).filter(|&n| n <= MAX_ELEMENTS);
    let (Some(w), Some(x), Some(o)) = (
        product(&[s.cin, s.cout_g(), s.kh, s.kw]),
        product(&[s.n, s.cin, s.h, s.w]),
        product(&[s.n, s.cout, s.oh, s.ow]),
    ) else {
        return Err(format!("the layer is too large ({s:?})"));
    };
    if [s.h, s.w, s.oh, s.ow, s.pad_h, s.pad_w].iter().any(|&v| v > MAX_ELEMENTS) || s.h == 0 || s.w == 0 {
        return Err(format!("input {}x{}, output {}x{}: out of range", s.h, s.w, s.oh, s.ow));
    }
    let axes = [
        ("height", s.h, s.oh, s.kh, s.stride_h, s.pad_h, s.dil_h),
        ("width", s.w, s.ow, s.kw, s.stride_w, s.pad_w, s.dil_w),
    ];
    for (axis, len, out, k, stride, pad, dil) in axes {
        let extra = out as i128 - base_out(len, k, stride, pad, dil);
        if out == 0 || extra < 0 || (extra >= stride as i128 && extra >= dil as i128) {
            return Err(format!(
                "output {axis} {out} is not PyTorch's for input {len}, kernel {k}, stride {stride}, padding {pad}, \
                 dilation {dil} (output padding must be 0 to below the stride or the dilation)"
            ));
        }
    }
    if weight_len != w {
        return Err(format!(
            "weight has {weight_len} values, [{}, {}, {}, {}] needs {w}",
            s.cin,
            s.cout_g(),
            s.kh,
            s.kw
        ));
    }
    if x_len != x || out_len != o {
        return Err(format!("input has {x_len} values (needs {x}), output {out_len} (needs {o})"));
    }
    if let Some(n) = epilogue.into_iter().flatten().find(|&n| n != s.cout) {
        return Err(format!("an epilogue vector has {n} values for {} output channels", s.cout));
    }
    Ok(())
}

/// Computes one layer: `out = epilogue(conv_transpose(x, weight))`; `scratch` holds at
/// least [`scratch_len`] floats.
///
/// # Panics
/// If the layer fails [`check`] or the scratch is short.
#[allow(clippy::too_many_arguments)]
pub fn conv_transpose2d(
    s: &ConvTranspose2dShape,
    weight: &[f32],
    ep: &Epilogue,
    x: &[f32],
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    let lens = [ep.scale.map(<[f32]>::len), ep.shift.map(<[f32]>::len)];
    if let Err(e) = check(s, weight.len(), x.len(), out.len(), lens) {
        panic!("conv_transpose2d: {e}");
    }
    let need = scratch_len(s, threads).unwrap_or(usize::MAX);
    assert!(scratch.len() >= need, "conv_transpose2d: scratch has {} floats, needs {need}", scratch.len());
    if out.is_empty() {
        return;
    }
    let (cb, units, parts) = split(s, threads);
    let job = Job { s, weight, ep, x, cb, tile: tile(s, cb) };
    job.units(out, scratch, 0, units, parts);
}

/// What every unit of one call reads.
struct Job<'a> {
    s: &'a ConvTranspose2dShape,
    weight: &'a [f32],
    ep: &'a Epilogue<'a>,
    x: &'a [f32],
    /// Output channels per unit.
    cb: usize,
    /// Input pixels per GEMM tile.
    tile: usize,
}

impl Job<'_> {
    /// Units `u0..u1` on `parts` threads: `out` holds their planes, `scratch` a tile of
    /// `cols` per part. Halves the range until one part is left.
    fn units(&self, out: &mut [f32], scratch: &mut [f32], u0: usize, u1: usize, parts: usize) {
        let per_unit = self.cb * self.s.oh * self.s.ow;
        let per_part = self.cb * self.s.kh * self.s.kw * self.tile;
        if parts <= 1 || u1 - u0 <= 1 {
            for (u, planes) in (u0..u1).zip(out.chunks_mut(per_unit)) {
                self.unit(u, planes, &mut scratch[..per_part]);
            }
            return;
        }
        let half = parts / 2;
        let um = u0 + (u1 - u0) * half / parts;
        let (lo, hi) = out.split_at_mut((um - u0) * per_unit);
        let (slo, shi) = scratch.split_at_mut(half * per_part);
        rayon::join(|| self.units(lo, slo, u0, um, half), || self.units(hi, shi, um, u1, parts - half));
    }

    /// Unit `u`: channels `c0..c0 + cb` of one image (a block of one group), into
    /// `planes`.
    fn unit(&self, u: usize, planes: &mut [f32], cols: &mut [f32]) {
        let s = self.s;
        let (cin_g, cout_g, khw, hw) = (s.cin_g(), s.cout_g(), s.kh * s.kw, s.h * s.w);
        let first = u * self.cb;
        let (n, c0) = (first / s.cout, first % s.cout);
        let g = c0 / cout_g;
        let rows = self.cb * khw;
        let k_all = cout_g * khw;
        planes.fill(0.0);
        let xg = &self.x[(n * s.cin + g * cin_g) * hw..][..cin_g * hw];
        // Wᵀ restricted to the unit's channels: row (co, ky, kx), column ci.
        let wg = &self.weight[g * cin_g * k_all + (c0 - g * cout_g) * khw..];
        let lhs = MatRef { data: wg, rows, cols: cin_g, row_stride: 1, col_stride: k_all };
        let mut p0 = 0;
        while p0 < hw {
            let tp = self.tile.min(hw - p0);
            let rhs = MatRef { data: &xg[p0..], rows: cin_g, cols: tp, row_stride: hw, col_stride: 1 };
            let c = &mut cols[..rows * tp];
            sgemm(lhs, rhs, MatMut::row_major(c, rows, tp), false, 1);
            scatter(s, self.cb, c, p0, tp, planes);
            p0 += tp;
        }
        finish_planes(s, planes, c0, self.ep);
    }
}

simd_fn! {
    /// Adds a tile of `cols` (rows `(co, ky, kx)` for `cb` channels, columns the input
    /// pixels `p0..p0 + tp`) into the channels' output planes.
    fn scatter(s: &ConvTranspose2dShape, cb: usize, cols: &[f32], p0: usize, tp: usize, planes: &mut [f32]) {
        let (oh, ow) = (s.oh as isize, s.ow as isize);
        let plane = s.oh * s.ow;
        for (cl, out) in planes.chunks_mut(plane).enumerate().take(cb) {
            for ky in 0..s.kh {
                let dy = (ky * s.dil_h) as isize - s.pad_h as isize;
                for kx in 0..s.kw {
                    let r = (cl * s.kh + ky) * s.kw + kx;
                    let src = &cols[r * tp..][..tp];
                    let dx = (kx * s.dil_w) as isize - s.pad_w as isize;
                    // Input columns whose output column is inside: ix in ix_lo..ix_hi.
                    let ix_lo = ((-dx).max(0) as usize).div_ceil(s.stride_w).min(s.w);
                    let ix_hi = if ow - dx <= 0 { 0 } else { ((ow - dx) as usize).div_ceil(s.stride_w).min(s.w) };
                    let mut p = p0;
                    let mut off = 0;
                    while off < tp {
                        let (iy, ix0) = (p / s.w, p % s.w);
                        let run = (s.w - ix0).min(tp - off);
                        let oy = (iy * s.stride_h) as isize + dy;
                        let (a, b) = (ix_lo.clamp(ix0, ix0 + run), ix_hi.clamp(ix0, ix0 + run));
                        if oy >= 0 && oy < oh && a < b {
                            let ox0 = ((a * s.stride_w) as isize + dx) as usize;
                            let dst = &mut out[oy as usize * s.ow..][..s.ow];
                            strided_add(&mut dst[ox0..], &src[off + a - ix0..off + b - ix0], s.stride_w);
                        }
                        p += run;
                        off += run;
                    }
                }
            }
        }
    }
}

/// `dst[i · stride] += src[i]`.
#[inline(always)]
fn strided_add(dst: &mut [f32], src: &[f32], stride: usize) {
    if stride == 1 {
        dst[..src.len()].iter_mut().zip(src).for_each(|(d, &v)| *d += v);
    } else {
        dst.iter_mut().step_by(stride).zip(src).for_each(|(d, &v)| *d += v);
    }
}

simd_fn! {
    /// The epilogue in place on the unit's planes, channels `c0..`.
    fn finish_planes(s: &ConvTranspose2dShape, planes: &mut [f32], c0: usize, ep: &Epilogue<'_>) {
        for (i, p) in planes.chunks_mut(s.oh * s.ow).enumerate() {
            let c = c0 + i;
            let scale = ep.scale.map_or(1.0, |v| v[c]);
            let shift = ep.shift.map_or(0.0, |v| v[c]);
            match (ep.scale.is_some(), ep.relu()) {
                (true, true) => p.iter_mut().for_each(|a| *a = relu(*a * scale + shift)),
                (true, false) => p.iter_mut().for_each(|a| *a = *a * scale + shift),
                (false, true) => p.iter_mut().for_each(|a| *a = relu(*a + shift)),
                (false, false) if ep.shift.is_some() => p.iter_mut().for_each(|a| *a += shift),
                (false, false) => {}
            }
            ep.finish_act(p);
        }
    }
}

/// The naive scatter loop: every input pixel, channel and tap added to its output pixel,
/// then the epilogue; the reference of the tests and benchmarks.
pub fn reference(s: &ConvTranspose2dShape, weight: &[f32], ep: &Epilogue, x: &[f32], out: &mut [f32]) {
    let (cin_g, cout_g) = (s.cin_g(), s.cout_g());
    out.fill(0.0);
    for n in 0..s.n {
        for ci in 0..s.cin {
            let g = ci / cin_g;
            for iy in 0..s.h {
                for ix in 0..s.w {
                    let v = x[((n * s.cin + ci) * s.h + iy) * s.w + ix];
                    for col in 0..cout_g {
                        let co = g * cout_g + col;
                        for ky in 0..s.kh {
                            let oy = (iy * s.stride_h + ky * s.dil_h) as isize - s.pad_h as isize;
                            if oy < 0 || oy >= s.oh as isize {
                                continue;
                            }
                            for kx in 0..s.kw {
                                let ox = (ix * s.stride_w + kx * s.dil_w) as isize - s.pad_w as isize;
                                if ox < 0 || ox >= s.ow as isize {
                                    continue;
                                }
                                let wv = weight[((ci * cout_g + col) * s.kh + ky) * s.kw + kx];
                                out[((n * s.cout + co) * s.oh + oy as usize) * s.ow + ox as usize] += v * wv;
                            }
                        }
                    }
                }
            }
        }
    }
    let plane = s.oh * s.ow;
    for (i, p) in out.chunks_mut(plane.max(1)).enumerate() {
        let c = i % s.cout;
        for a in p.iter_mut() {
            *a = *a * ep.scale.map_or(1.0, |v| v[c]) + ep.shift.map_or(0.0, |v| v[c]);
            if let Some(act) = ep.act {
                *a = act.reference(*a as f64) as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdata::data;
    use readi_plan::ops::{Activation, ConvTranspose2d, Window2};

    /// `(n, cin, h, w, cout, [kh, kw], [stride], [pad], [out_pad], [dil], groups)`.
    type Case = (usize, usize, usize, usize, usize, [i64; 2], [i64; 2], [i64; 2], [i64; 2], [i64; 2], usize);

    fn shape(c: &Case) -> ConvTranspose2dShape {
        let &(n, cin, h, w, cout, kernel, stride, padding, output_padding, dilation, groups) = c;
        let op = ConvTranspose2d {
            in_channels: cin as i64,
            out_channels: cout as i64,
            window: Window2 { kernel, stride, padding, dilation },
            output_padding,
            groups: groups as i64,
        };
        op.shape(n, h, w)
    }

    const CASES: &[Case] = &[
        // SECOND's deblock (small): k=2, s=2.
        (1, 8, 5, 7, 8, [2, 2], [2, 2], [0, 0], [0, 0], [1, 1], 1),
        // k=3, s=2, p=1, op=1: the exact double; two images.
        (2, 3, 4, 5, 5, [3, 3], [2, 2], [1, 1], [1, 1], [1, 1], 1),
        // Groups, rectangular kernel and stride, padding cropping more than a tap.
        (1, 6, 3, 4, 4, [3, 2], [3, 1], [2, 1], [2, 0], [1, 1], 2),
        // Dilation with output padding below it, stride 1; depthwise groups.
        (2, 3, 5, 3, 3, [3, 3], [1, 1], [1, 0], [1, 1], [2, 2], 3),
        // Stride above the kernel: gaps that only the bias fills.
        (1, 2, 3, 3, 3, [2, 1], [3, 4], [0, 0], [1, 3], [1, 1], 1),
        // One input pixel; many output channels of an odd count (blocks of 1 on 2 threads).
        (1, 5, 1, 1, 7, [4, 4], [2, 2], [1, 1], [0, 0], [1, 1], 1),
        // Tiles: more input pixels than one tile holds.
        (1, 4, 70, 75, 6, [2, 2], [2, 2], [0, 0], [0, 0], [1, 1], 1),
    ];

    fn run(s: &ConvTranspose2dShape, w: &[f32], ep: &Epilogue, x: &[f32], threads: usize) -> Vec<f32> {
        let mut out = vec![f32::NAN; s.n * s.cout * s.oh * s.ow];
        let mut scratch = vec![f32::NAN; scratch_len(s, threads).expect("fits")];
        conv_transpose2d(s, w, ep, x, &mut out, &mut scratch, threads);
        out
    }

    fn close(got: &[f32], want: &[f32], what: &str) {
        assert_eq!(got.len(), want.len(), "{what}");
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            assert!((g - w).abs() <= 1e-4 * w.abs().max(1.0), "{what}[{i}]: {g} vs {w}");
        }
    }

    #[test]
    fn matches_the_scatter_loop() {
        for (k, c) in CASES.iter().enumerate() {
            let s = shape(c);
            let x = data(s.n * s.cin * s.h * s.w, 2 * k as u64);
            let w = data(s.weight_len(), 2 * k as u64 + 1);
            let bias = data(s.cout, 99);
            let scale = data(s.cout, 98);
            let eps = [
                Epilogue { scale: None, shift: None, act: None },
                Epilogue { scale: None, shift: Some(&bias), act: Some(Activation::Relu) },
                Epilogue { scale: Some(&scale), shift: Some(&bias), act: Some(Activation::Silu) },
            ];
            for ep in &eps {
                let mut want = vec![0.0; s.n * s.cout * s.oh * s.ow];
                reference(&s, &w, ep, &x, &mut want);
                for threads in [1, 2, 3] {
                    close(&run(&s, &w, ep, &x, threads), &want, &format!("case {k} at {threads} threads {ep:?}"));
                }
            }
        }
    }

    #[test]
    fn hand_computed_values() {
        // 1 channel, 2x2 input [[1, 2], [3, 4]], kernel [[1, 10], [100, 1000]], stride 2:
        // each input pixel stamps the kernel scaled by itself into its own 2x2 block.
        let s = shape(&(1, 1, 2, 2, 1, [2, 2], [2, 2], [0, 0], [0, 0], [1, 1], 1));
        let out = run(&s, &[1.0, 10.0, 100.0, 1000.0], &Epilogue::default(), &[1.0, 2.0, 3.0, 4.0], 1);
        #[rustfmt::skip]
        let want = [
            1.0, 10.0, 2.0, 20.0,
            100.0, 1000.0, 200.0, 2000.0,
            3.0, 30.0, 4.0, 40.0,
            300.0, 3000.0, 400.0, 4000.0,
        ];
        assert_eq!(out, want);
        // Stride 1, kernel [1, 1] over [1, 2]: overlapping taps add: [1, 3, 2].
        let s = shape(&(1, 1, 1, 2, 1, [1, 2], [1, 1], [0, 0], [0, 0], [1, 1], 1));
        assert_eq!(run(&s, &[1.0, 1.0], &Epilogue::default(), &[1.0, 2.0], 1), [1.0, 3.0, 2.0]);
    }

    #[test]
    fn check_refuses_what_the_kernel_cannot_run() {
        let s = shape(&CASES[1]);
        let (x, o) = (s.n * s.cin * s.h * s.w, s.n * s.cout * s.oh * s.ow);
        assert_eq!(check(&s, s.weight_len(), x, o, [None, Some(s.cout)]), Ok(()));
        let e = check(&s, s.weight_len() - 1, x, o, [None, None]).expect_err("short weight");
        assert!(e.contains("weight has"), "{e}");
        let e = check(&ConvTranspose2dShape { stride_h: 0, ..s }, s.weight_len(), x, o, [None, None]).expect_err("0");
        assert!(e.contains("none may be 0"), "{e}");
        // An output two rows taller than the formula: output padding 2 >= stride 2.
        let tall = ConvTranspose2dShape { oh: s.oh + 1, ..s };
        let e = check(&tall, s.weight_len(), x, s.n * s.cout * tall.oh * s.ow, [None, None]).expect_err("tall");
        assert!(e.contains("not PyTorch's"), "{e}");
        let e = check(&ConvTranspose2dShape { groups: 2, ..s }, s.weight_len(), x, o, [None, None]).expect_err("g");
        assert!(e.contains("groups=2"), "{e}");
        let e = check(&s, s.weight_len(), x, o, [Some(1), None]).expect_err("epilogue");
        assert!(e.contains("epilogue"), "{e}");
    }
}
