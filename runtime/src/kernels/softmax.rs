//! Softmax along one axis, with a vectorisable `exp`.

use pulp::Simd;
use rayon::prelude::*;

/// Below this many elements softmax runs on the calling thread.
const PAR_MIN: usize = 1 << 14;
/// Elements per parallel task, roughly.
const CHUNK: usize = 1 << 13;
/// Columns processed together when the axis is not the last one.
const TILE: usize = 64;

/// Softmax along the middle axis of `x` viewed as `[outer, axis_len, inner]`:
/// `out = exp(x - max) / sum(exp(x - max))`, max and sum taken along that axis.
///
/// `inner == 1` (softmax over the last axis, attention rows) is the fast path: one pass
/// for the max, one that writes `exp` and sums it, one that scales. Otherwise the axis is
/// walked in tiles of columns. Work is split across threads by `outer` rows only.
/// A row containing NaN, or only `-inf`, comes out NaN, as in PyTorch.
pub fn softmax(x: &[f32], outer: usize, axis_len: usize, inner: usize, out: &mut [f32]) {
    debug_assert_eq!(check(&[outer, axis_len, inner], 1, &[out.len()]), Ok(()), "softmax preconditions");
    assert_eq!(x.len(), outer * axis_len * inner, "softmax: x is not [outer, axis_len, inner]");
    assert_eq!(out.len(), x.len(), "softmax: out and x differ in length");
    if x.is_empty() {
        return;
    }
    let block = axis_len * inner;
    if x.len() >= PAR_MIN && outer > 1 {
        let task = (CHUNK / block).max(1) * block;
        out.par_chunks_mut(task).zip(x.par_chunks(task)).for_each(|(o, x)| softmax_blocks(x, o, axis_len, inner));
    } else {
        softmax_blocks(x, out, axis_len, inner);
    }
}

/// Softmax of consecutive `[axis_len, inner]` blocks, compiled for the widest SIMD the
/// CPU has.
fn softmax_blocks(x: &[f32], out: &mut [f32], axis_len: usize, inner: usize) {
    pulp::Arch::new().dispatch(Blocks { x, out, axis_len, inner });
}

struct Blocks<'a> {
    x: &'a [f32],
    out: &'a mut [f32],
    axis_len: usize,
    inner: usize,
}

impl pulp::WithSimd for Blocks<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let block = self.axis_len * self.inner;
        for (o, x) in self.out.chunks_mut(block).zip(self.x.chunks(block)) {
            if self.inner == 1 { softmax_row(simd, x, o) } else { softmax_columns(x, o, self.axis_len, self.inner) }
        }
    }
}

/// Softmax of one contiguous row, in explicit SIMD vectors (`S::f32s`: 16 lanes with
/// AVX-512, 8 with AVX2, 1 on the baseline).
///
/// Explicit, because LLVM's auto-vectorisation of lane arrays was fragile here: it kept
/// the sum's accumulator array in memory (stalling on store forwarding each step) or
/// split the max into 4-wide vectors, depending on the code around it; 2.5x slower.
///
/// The `len % lanes` elements past the last whole vector are handled as the row's last
/// vector, overlapping the one before: the max does not mind, the sum masks the
/// overlapping lanes out, and the overlap is written twice with the same values.
/// A NaN anywhere makes the row NaN, through its `exp` in the sum.
#[inline(always)]
fn softmax_row<S: Simd>(simd: S, x: &[f32], out: &mut [f32]) {
    let n = x.len();
    let out = &mut out[..n];
    let lanes = S::F32_LANES;
    let (xh, _) = S::as_simd_f32s(x);
    let (_, xl) = S::as_rsimd_f32s(x);
    let Some(&last) = xl.last() else {
        return softmax_short_row(x, out);
    };
    let mut m = last;
    for &v in xh {
        m = simd.max_f32s(m, v);
    }
    let max = simd.splat_f32s(simd.reduce_max_f32s(m));
    let mut acc = simd.splat_f32s(0.0);
    let (oh, _) = S::as_mut_simd_f32s(out);
    // Four vectors' exps at a time, their steps interleaved ([`exp_simd`]), summed in the
    // same order as one at a time: 0.88-0.95x the time on ViT-B's 197-wide rows and on
    // 4096-wide ones, 1 and 2 threads (alternating calls, 2026-12-06); Swin's 49-wide
    // windows have three whole vectors and run as before.
    let whole = oh.len() / 4 * 4;
    let (o4, o1) = oh.split_at_mut(whole);
    let (x4, x1) = xh.split_at(whole);
    for (o, v) in o4.chunks_exact_mut(4).zip(x4.chunks_exact(4)) {
        let d = |i: usize| simd.sub_f32s(v[i], max);
        let e = exp_simd(simd, [d(0), d(1), d(2), d(3)]);
        for (o, e) in o.iter_mut().zip(e) {
            *o = e;
            acc = simd.add_f32s(acc, e);
        }
    }
    for (o, &v) in o1.iter_mut().zip(x1) {
        [*o] = exp_simd(simd, [simd.sub_f32s(v, max)]);
        acc = simd.add_f32s(acc, *o);
    }
    let rem = n % lanes;
    if rem > 0 {
        let [e] = exp_simd(simd, [simd.sub_f32s(last, max)]);
        // Lane i of the last vector is new if i >= lanes - rem.
        let iota = simd.partial_load_u32s(&IOTA[..lanes]);
        let new = simd.greater_than_or_equal_u32s(iota, simd.splat_u32s((lanes - rem) as u32));
        acc = simd.add_f32s(acc, simd.select_f32s(new, e, simd.splat_f32s(0.0)));
        if let Some(o) = S::as_mut_rsimd_f32s(out).1.last_mut() {
            *o = e;
        }
    }
    let inv = 1.0 / simd.reduce_sum_f32s(acc);
    let (oh, ot) = S::as_mut_simd_f32s(out);
    let vinv = simd.splat_f32s(inv);
    for o in oh {
        *o = simd.mul_f32s(*o, vinv);
    }
    for o in ot {
        *o *= inv;
    }
}

/// Lane indices, for masks.
const IOTA: [u32; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15];

/// [`softmax_row`] for rows shorter than one vector, in scalars.
#[inline(always)]
fn softmax_short_row(x: &[f32], out: &mut [f32]) {
    let max = x.iter().fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m });
    let mut sum = 0.0;
    for (o, &v) in out.iter_mut().zip(x) {
        *o = exp_fast(v - max);
        sum += *o;
    }
    let inv = 1.0 / sum;
    for o in out.iter_mut() {
        *o *= inv;
    }
}

/// [`exp_fast`] on `N` vectors, with fused multiply-adds where the CPU has them: same
/// reduction and polynomial, so within the same few ulp. The clamps are selects, which
/// keep NaN (pulp's min/max do not, on every backend). Each step runs over all `N`
/// vectors before the next: one vector's ~20 dependent steps leave the core's scheduler
/// waiting, `N` independent chains side by side keep both units busy.
#[inline(always)]
pub(crate) fn exp_simd<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    // Loops over the vectors, not `map` closures: those were not inlined into the
    // SIMD-enabled caller (a call per step, 11x slower).
    let c = |v: f32| simd.splat_f32s(v);
    let mut low = [simd.less_than_f32s(x[0], c(-87.0)); N];
    let mut xc = x;
    for i in 0..N {
        low[i] = simd.less_than_f32s(x[i], c(-87.0));
        xc[i] = simd.select_f32s(low[i], c(-87.0), x[i]);
        xc[i] = simd.select_f32s(simd.greater_than_f32s(xc[i], c(88.0)), c(88.0), xc[i]);
    }
    let mut out = exp_in_range(simd, xc);
    for i in 0..N {
        out[i] = simd.select_f32s(low[i], c(0.0), out[i]);
    }
    out
}

/// [`exp_simd`] for inputs already within `-87..=89` (or NaN, which stays NaN): the
/// Cody-Waite reduction, the polynomial and the scaling by `2^n`, without the clamps.
/// From about 88.4 (`n = 128`) the scale, and so the result, is infinite.
#[inline(always)]
pub(crate) fn exp_in_range<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let c = |v: f32| simd.splat_f32s(v);
    let (mut t, mut n, mut r, mut p) = (x, x, x, [c(EXP_POLY[0]); N]);
    for i in 0..N {
        t[i] = simd.mul_add_e_f32s(x[i], c(std::f32::consts::LOG2_E), c(ROUND));
        n[i] = simd.sub_f32s(t[i], c(ROUND));
    }
    for i in 0..N {
        r[i] = simd.mul_add_e_f32s(n[i], c(-LN2_HI), x[i]);
        r[i] = simd.mul_add_e_f32s(n[i], c(-LN2_LO), r[i]);
    }
    for &k in &EXP_POLY[1..] {
        for i in 0..N {
            p[i] = simd.mul_add_e_f32s(p[i], r[i], c(k));
        }
    }
    let mut out = x;
    for i in 0..N {
        let er = simd.mul_add_e_f32s(simd.mul_f32s(p[i], r[i]), r[i], simd.add_f32s(r[i], c(1.0)));
        let bits = simd.sub_u32s(simd.transmute_u32s_f32s(t[i]), simd.splat_u32s(ROUND.to_bits() - 127));
        let scale = simd.transmute_f32s_u32s(simd.wrapping_dyn_shl_u32s(bits, simd.splat_u32s(23)));
        out[i] = simd.mul_f32s(er, scale);
    }
    out
}

/// Softmax along the rows of a `[rows, inner]` block, for each column.
#[inline(always)]
fn softmax_columns(x: &[f32], out: &mut [f32], rows: usize, inner: usize) {
    for c0 in (0..inner).step_by(TILE) {
        let w = TILE.min(inner - c0);
        let cols = |r: usize| r * inner + c0..r * inner + c0 + w;
        let mut max = [f32::NEG_INFINITY; TILE];
        for r in 0..rows {
            for (m, &v) in max.iter_mut().zip(&x[cols(r)]) {
                *m = m.max(v);
            }
        }
        let mut sum = [0f32; TILE];
        for r in 0..rows {
            for (((o, &v), &m), s) in out[cols(r)].iter_mut().zip(&x[cols(r)]).zip(&max).zip(sum.iter_mut()) {
                let e = exp_fast(v - m);
                *o = e;
                *s += e;
            }
        }
        let inv = sum.map(|s| 1.0 / s);
        for r in 0..rows {
            for (o, &i) in out[cols(r)].iter_mut().zip(&inv) {
                *o *= i;
            }
        }
    }
}

/// `e^x` in f32 from arithmetic only (no libm call), so loops over it vectorise.
///
/// Cody–Waite reduction `x = n ln 2 + r`, `|r| <= ln 2 / 2`, then Cephes' `expf`
/// polynomial for `e^r`, scaled by `2^n` built from its bits. Within about 2 ulp of the
/// exact value on `[-87, 88]`; 0 below -87 (where e^x is under 1.7e-38) and for `-inf`;
/// `e^88` above 88; NaN stays NaN.
#[inline(always)]
pub(crate) fn exp_fast(x: f32) -> f32 {
    let xc = x.clamp(-87.0, 88.0);
    let t = xc * std::f32::consts::LOG2_E + ROUND;
    let n = t - ROUND;
    let r = xc - n * LN2_HI - n * LN2_LO;
    let mut p = EXP_POLY[0];
    for &k in &EXP_POLY[1..] {
        p = p * r + k;
    }
    let er = p * r * r + r + 1.0;
    // 2^n: n + 127 in the exponent field.
    let scale = f32::from_bits(t.to_bits().wrapping_sub(ROUND.to_bits() - 127) << 23);
    if x < -87.0 { 0.0 } else { er * scale }
}

/// `ln 2` in two parts for the Cody–Waite reduction: `n · LN2_HI` is exact.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Adding 1.5 · 2^23 rounds to an integer, which lands in the low mantissa bits.
const ROUND: f32 = 12_582_912.0;
/// Cephes' `expf` polynomial for `(e^r - 1 - r) / r²`, highest power first.
const EXP_POLY: [f32; 6] = [1.987_569_2e-4, 1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5];

/// The preconditions of [`softmax`] along `axis` of a value of shape `x`: the axis
/// exists, the output has `x`'s length.
pub fn check(x: &[usize], axis: usize, out: &[usize]) -> Result<(), String> {
    if axis >= x.len() {
        return Err(format!("softmax along axis {axis} of a value of shape {x:?}"));
    }
    if x.iter().product::<usize>() != out.iter().product::<usize>() {
        return Err(format!("softmax output {out:?} differs from its input {x:?}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

    /// Plain softmax in f64, one (outer, inner) column at a time.
    fn naive(x: &[f32], outer: usize, len: usize, inner: usize) -> Vec<f32> {
        let mut out = vec![0.0; x.len()];
        for o in 0..outer {
            for i in 0..inner {
                let at = |k: usize| (o * len + k) * inner + i;
                let max = (0..len).map(|k| x[at(k)] as f64).fold(f64::NEG_INFINITY, f64::max);
                let sum: f64 = (0..len).map(|k| (x[at(k)] as f64 - max).exp()).sum();
                for k in 0..len {
                    out[at(k)] = ((x[at(k)] as f64 - max).exp() / sum) as f32;
                }
            }
        }
        out
    }

    fn check(outer: usize, len: usize, inner: usize, magnitude: f32) {
        let x: Vec<f32> =
            data(outer * len * inner, (outer + len + inner) as u64).iter().map(|v| v * magnitude).collect();
        let mut got = vec![f32::NAN; x.len()];
        softmax(&x, outer, len, inner, &mut got);
        assert_close(&got, &naive(&x, outer, len, inner), 1e-6);
    }

    #[test]
    fn exp_fast_within_a_few_ulp() {
        let mut x = -87.0f32;
        while x <= 88.0 {
            let want = (x as f64).exp();
            let got = exp_fast(x) as f64;
            assert!(((got - want) / want).abs() < 2.5e-7, "exp({x}) = {got}, want {want}");
            x += 0.0137;
        }
        assert_eq!(exp_fast(0.0), 1.0);
        assert_eq!(exp_fast(-100.0), 0.0);
        assert_eq!(exp_fast(f32::NEG_INFINITY), 0.0);
        assert!(exp_fast(f32::NAN).is_nan());
    }

    #[test]
    fn softmax_last_axis() {
        check(1, 1, 1, 1.0);
        check(3, 7, 1, 1.0);
        check(5, 16, 1, 3.0);
        check(2, 33, 1, 3.0);
        check(200, 197, 1, 4.0);
    }

    #[test]
    fn softmax_rows_on_every_simd_backend() {
        // Every remainder modulo 16 and 8, and rows shorter than a vector.
        for len in (1..=40).chain([196, 197]) {
            let (outer, inner) = (3, 1);
            let x: Vec<f32> = data(outer * len, len as u64).iter().map(|v| v * 4.0).collect();
            let want = naive(&x, outer, len, inner);
            for b in backends() {
                let mut got = vec![f32::NAN; x.len()];
                b.run(Blocks { x: &x, out: &mut got, axis_len: len, inner });
                assert_close(&got, &want, 1e-6);
            }
        }
        let nan = [1.0, f32::NAN, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];
        for b in backends() {
            let mut got = [0.0; 17];
            b.run(Blocks { x: &nan, out: &mut got, axis_len: 17, inner: 1 });
            assert!(got.iter().all(|v| v.is_nan()), "{b:?}: {got:?}");
        }
    }

    #[test]
    fn softmax_middle_and_first_axis() {
        check(2, 5, 3, 2.0);
        check(1, 4, 130, 2.0);
        check(3, 1, 7, 2.0);
        check(4, 19, 64, 2.0);
        check(8, 10, 300, 2.0);
    }

    #[test]
    fn softmax_large_magnitudes_and_masking() {
        // Subtracting the max keeps ±1e4 finite: the largest entry wins outright.
        check(4, 9, 1, 1e4);
        check(2, 9, 5, 1e4);
        let x = [1000.0, 999.0, -1e30, f32::NEG_INFINITY];
        let mut got = [0.0; 4];
        softmax(&x, 1, 4, 1, &mut got);
        let e = (-1.0f64).exp();
        assert_close(&got, &[(1.0 / (1.0 + e)) as f32, (e / (1.0 + e)) as f32, 0.0, 0.0], 1e-6);
        // A fully masked row is NaN, as torch.softmax(torch.full((4,), -inf), 0).
        let mut got = [0.0; 4];
        softmax(&[f32::NEG_INFINITY; 4], 1, 4, 1, &mut got);
        assert!(got.iter().all(|v| v.is_nan()));
    }
}
