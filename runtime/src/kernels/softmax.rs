//! Softmax along one axis, with a vectorisable `exp`.

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
    assert_eq!(x.len(), outer * axis_len * inner, "softmax: x is not [outer, axis_len, inner]");
    assert_eq!(out.len(), x.len(), "softmax: out and x differ in length");
    if x.is_empty() {
        return;
    }
    let block = axis_len * inner;
    let run = |x: &[f32], out: &mut [f32]| {
        if inner == 1 { softmax_row(x, out) } else { softmax_columns(x, out, axis_len, inner) }
    };
    if x.len() >= PAR_MIN && outer > 1 {
        let min_blocks = (CHUNK / block).max(1);
        out.par_chunks_mut(block).zip(x.par_chunks(block)).with_min_len(min_blocks).for_each(|(o, x)| run(x, o));
    } else {
        out.chunks_mut(block).zip(x.chunks(block)).for_each(|(o, x)| run(x, o));
    }
}

/// Softmax of one contiguous row. Fixed-width lanes keep every loop vectorisable.
fn softmax_row(x: &[f32], out: &mut [f32]) {
    const L: usize = 16;
    let (xc, xr) = (x.chunks_exact(L), x.chunks_exact(L).remainder());
    let mut lanes = [f32::NEG_INFINITY; L];
    for c in xc.clone() {
        for (m, &v) in lanes.iter_mut().zip(c) {
            *m = m.max(v);
        }
    }
    let max = lanes.iter().chain(xr).fold(f32::NEG_INFINITY, |a, &b| a.max(b));
    let mut acc = [0f32; L];
    let mut oc = out.chunks_exact_mut(L);
    for (o, x) in (&mut oc).zip(xc) {
        for ((o, &v), a) in o.iter_mut().zip(x).zip(acc.iter_mut()) {
            let e = exp_fast(v - max);
            *o = e;
            *a += e;
        }
    }
    let mut total = 0.0;
    for (o, &v) in oc.into_remainder().iter_mut().zip(xr) {
        *o = exp_fast(v - max);
        total += *o;
    }
    let inv = 1.0 / (acc.iter().sum::<f32>() + total);
    out.iter_mut().for_each(|o| *o *= inv);
}

/// Softmax along the rows of a `[rows, inner]` block, for each column.
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
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Adding 1.5 * 2^23 rounds to an integer, which lands in the low mantissa bits.
    const ROUND: f32 = 12_582_912.0;
    let xc = x.clamp(-87.0, 88.0);
    let t = xc * LOG2E + ROUND;
    let n = t - ROUND;
    let r = xc - n * LN2_HI - n * LN2_LO;
    let mut p = 1.987_569_2e-4;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let er = p * r * r + r + 1.0;
    // 2^n: n + 127 in the exponent field.
    let scale = f32::from_bits(t.to_bits().wrapping_sub(ROUND.to_bits() - 127) << 23);
    if x < -87.0 { 0.0 } else { er * scale }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, data};

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
