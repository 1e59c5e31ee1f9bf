//! Normalisations: inference BatchNorm, per-channel affine, LayerNorm.

use rayon::prelude::*;

use super::elementwise;
use super::reduce::sum;

/// Below this many elements a kernel runs on the calling thread.
const PAR_MIN: usize = 1 << 15;
/// Elements per parallel task, roughly.
const CHUNK: usize = 1 << 14;

/// Inference BatchNorm over axis 1 of `x` viewed as `[n, c, inner]`:
/// `y = (x - mean[c]) / sqrt(var[c] + eps) * weight[c] + bias[c]`.
///
/// Evaluated as `x * a + b` with `a = weight / sqrt(var + eps)`, `b = bias - mean * a`,
/// which is how PyTorch's CPU kernel evaluates it too. All parameters have length `c`.
#[allow(clippy::too_many_arguments)]
pub fn batchnorm(
    x: &[f32],
    n: usize,
    c: usize,
    inner: usize,
    weight: &[f32],
    bias: &[f32],
    mean: &[f32],
    var: &[f32],
    eps: f32,
    out: &mut [f32],
) {
    assert_eq!(x.len(), n * c * inner, "batchnorm: x is not [n, c, inner]");
    assert_eq!(out.len(), x.len(), "batchnorm: out and x differ in length");
    assert!([weight, bias, mean, var].iter().all(|p| p.len() == c), "batchnorm: parameters must have length c");
    for_row_segments(x, out, inner, |row, x, out| {
        let ch = row % c;
        let a = weight[ch] / (var[ch] + eps).sqrt();
        let b = bias[ch] - mean[ch] * a;
        for (o, &v) in out.iter_mut().zip(x) {
            *o = v * a + b;
        }
    });
}

/// `y = x * scale[c] + shift[c]`, then `max(y, 0)` if `relu`, over axis 1 of `x` viewed as
/// `[n, c, inner]`. A missing `scale` is 1, a missing `shift` 0; each present one has
/// length `c`.
#[allow(clippy::too_many_arguments)]
pub fn channel_affine(
    x: &[f32],
    n: usize,
    c: usize,
    inner: usize,
    scale: Option<&[f32]>,
    shift: Option<&[f32]>,
    relu: bool,
    out: &mut [f32],
) {
    assert_eq!(x.len(), n * c * inner, "channel_affine: x is not [n, c, inner]");
    assert_eq!(out.len(), x.len(), "channel_affine: out and x differ in length");
    assert!(scale.is_none_or(|s| s.len() == c), "channel_affine: scale must have length c");
    assert!(shift.is_none_or(|s| s.len() == c), "channel_affine: shift must have length c");
    for_row_segments(x, out, inner, |row, x, out| {
        let ch = row % c;
        let a = scale.map_or(1.0, |s| s[ch]);
        let b = shift.map_or(0.0, |s| s[ch]);
        if relu {
            for (o, &v) in out.iter_mut().zip(x) {
                *o = elementwise::relu(v * a + b);
            }
        } else {
            for (o, &v) in out.iter_mut().zip(x) {
                *o = v * a + b;
            }
        }
    });
}

/// LayerNorm over the last axis of `x` viewed as `[rows, features]`:
/// `y = (x - mean) / sqrt(var + eps) * weight + bias`, with the biased variance (divided
/// by `features`) as PyTorch. Two passes over each row (mean, then squared deviations), so
/// a large mean does not cancel the variance. `weight` and `bias`, when present, have
/// length `features`; missing, they are 1 and 0.
pub fn layernorm(
    x: &[f32],
    rows: usize,
    features: usize,
    weight: Option<&[f32]>,
    bias: Option<&[f32]>,
    eps: f32,
    out: &mut [f32],
) {
    assert_eq!(x.len(), rows * features, "layernorm: x is not [rows, features]");
    assert_eq!(out.len(), x.len(), "layernorm: out and x differ in length");
    assert!(weight.is_none_or(|w| w.len() == features), "layernorm: weight must have length features");
    assert!(bias.is_none_or(|b| b.len() == features), "layernorm: bias must have length features");
    if x.is_empty() {
        return;
    }
    let row = |x: &[f32], out: &mut [f32]| {
        let inv_n = 1.0 / features as f32;
        let mean = sum(x) * inv_n;
        // Squared deviations, written to `out` first so the sum vectorises.
        for (o, &v) in out.iter_mut().zip(x) {
            let d = v - mean;
            *o = d * d;
        }
        let rstd = 1.0 / (sum(out) * inv_n + eps).sqrt();
        match (weight, bias) {
            (Some(w), Some(b)) => {
                for (((o, &v), &w), &b) in out.iter_mut().zip(x).zip(w).zip(b) {
                    *o = (v - mean) * rstd * w + b;
                }
            }
            (Some(w), None) => {
                for ((o, &v), &w) in out.iter_mut().zip(x).zip(w) {
                    *o = (v - mean) * rstd * w;
                }
            }
            (None, Some(b)) => {
                for ((o, &v), &b) in out.iter_mut().zip(x).zip(b) {
                    *o = (v - mean) * rstd + b;
                }
            }
            (None, None) => {
                for (o, &v) in out.iter_mut().zip(x) {
                    *o = (v - mean) * rstd;
                }
            }
        }
    };
    if x.len() >= PAR_MIN && rows > 1 {
        let min_rows = (CHUNK / features).max(1);
        out.par_chunks_mut(features).zip(x.par_chunks(features)).with_min_len(min_rows).for_each(|(o, x)| row(x, o));
    } else {
        out.chunks_mut(features).zip(x.chunks(features)).for_each(|(o, x)| row(x, o));
    }
}

/// Calls `f(row, x_segment, out_segment)` over `x` and `out` cut into rows of length
/// `inner`, splitting rows where parallel chunks end; parallel when large, so both many
/// short rows and a few long ones spread across threads.
fn for_row_segments<F>(x: &[f32], out: &mut [f32], inner: usize, f: F)
where
    F: Fn(usize, &[f32], &mut [f32]) + Sync,
{
    let run = |start: usize, x: &[f32], out: &mut [f32]| {
        let mut pos = 0;
        while pos < out.len() {
            let g = start + pos;
            let n = (inner - g % inner).min(out.len() - pos);
            f(g / inner, &x[pos..pos + n], &mut out[pos..pos + n]);
            pos += n;
        }
    };
    if out.len() >= PAR_MIN {
        out.par_chunks_mut(CHUNK).zip(x.par_chunks(CHUNK)).enumerate().for_each(|(i, (o, x))| run(i * CHUNK, x, o));
    } else {
        run(0, x, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, data};

    fn positive(len: usize, seed: u64) -> Vec<f32> {
        data(len, seed).iter().map(|v| v + 1.5).collect()
    }

    #[test]
    fn batchnorm_matches_formula() {
        for (n, c, inner) in [(2, 3, 5), (1, 1, 1), (3, 4, 1), (1, 7, 13), (2, 16, 1500)] {
            let x = data(n * c * inner, 1);
            let (w, b, m, v) = (data(c, 2), data(c, 3), data(c, 4), positive(c, 5));
            let eps = 1e-5;
            let mut got = vec![f32::NAN; x.len()];
            batchnorm(&x, n, c, inner, &w, &b, &m, &v, eps, &mut got);
            let mut want = vec![0.0; x.len()];
            for i in 0..n {
                for ch in 0..c {
                    for k in 0..inner {
                        let j = (i * c + ch) * inner + k;
                        want[j] = (x[j] - m[ch]) / (v[ch] + eps).sqrt() * w[ch] + b[ch];
                    }
                }
            }
            assert_close(&got, &want, 1e-5);
        }
    }

    #[test]
    fn channel_affine_each_option() {
        for (n, c, inner) in [(2, 3, 5), (1, 1, 1), (3, 4, 1), (2, 16, 1500)] {
            let x = data(n * c * inner, 6);
            let (scale, shift) = (data(c, 7), data(c, 8));
            for (sc, sh, relu) in [
                (Some(&scale[..]), Some(&shift[..]), false),
                (Some(&scale[..]), None, true),
                (None, Some(&shift[..]), true),
                (None, None, false),
                (Some(&scale[..]), Some(&shift[..]), true),
            ] {
                let mut got = vec![f32::NAN; x.len()];
                channel_affine(&x, n, c, inner, sc, sh, relu, &mut got);
                let want: Vec<f32> = (0..x.len())
                    .map(|j| {
                        let ch = j / inner % c;
                        let y = x[j] * sc.map_or(1.0, |s| s[ch]) + sh.map_or(0.0, |s| s[ch]);
                        if relu && y < 0.0 { 0.0 } else { y }
                    })
                    .collect();
                assert_eq!(
                    got,
                    want,
                    "n={n} c={c} inner={inner} scale={} shift={} relu={relu}",
                    sc.is_some(),
                    sh.is_some()
                );
            }
        }
    }

    fn naive_layernorm(x: &[f32], features: usize, w: Option<&[f32]>, b: Option<&[f32]>, eps: f32) -> Vec<f32> {
        let mut out = Vec::with_capacity(x.len());
        for row in x.chunks(features) {
            let mean = row.iter().map(|&v| v as f64).sum::<f64>() / features as f64;
            let var = row.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / features as f64;
            for (j, &v) in row.iter().enumerate() {
                let y = (v as f64 - mean) / (var + eps as f64).sqrt();
                out.push((y * w.map_or(1.0, |w| w[j] as f64) + b.map_or(0.0, |b| b[j] as f64)) as f32);
            }
        }
        out
    }

    #[test]
    fn layernorm_matches_f64_reference() {
        for (rows, features) in [(1, 1), (3, 7), (5, 64), (1, 333), (300, 200)] {
            let x = data(rows * features, 9);
            let (w, b) = (data(features, 10), data(features, 11));
            for (wo, bo) in [(Some(&w[..]), Some(&b[..])), (Some(&w[..]), None), (None, Some(&b[..])), (None, None)] {
                let mut got = vec![f32::NAN; x.len()];
                layernorm(&x, rows, features, wo, bo, 1e-5, &mut got);
                assert_close(&got, &naive_layernorm(&x, features, wo, bo, 1e-5), 1e-4);
            }
        }
    }

    #[test]
    fn layernorm_is_stable_with_a_large_mean() {
        // A one-pass E[x²] - E[x]² in f32 loses everything here: the variance is ~1e-2 next
        // to a squared mean of 1e8.
        let x: Vec<f32> = data(4 * 256, 12).iter().map(|v| 1e4 + 0.1 * v).collect();
        let mut got = vec![0.0; x.len()];
        layernorm(&x, 4, 256, None, None, 1e-5, &mut got);
        assert_close(&got, &naive_layernorm(&x, 256, None, None, 1e-5), 2e-2);
    }
}
