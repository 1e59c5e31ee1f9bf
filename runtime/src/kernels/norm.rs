//! Normalisations: inference BatchNorm, per-channel affine, LayerNorm, GroupNorm.

use pulp::Simd;
use rayon::prelude::*;

use super::reduce::{sum_map_simd, sum_simd};
use super::{Activation, elementwise};

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
    affine_rows(x, out, inner, false, |row| {
        let ch = row % c;
        let a = weight[ch] / (var[ch] + eps).sqrt();
        (a, bias[ch] - mean[ch] * a)
    });
}

/// `y = act(x * scale[c] + shift[c])` over axis 1 of `x` viewed as
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
    act: Option<Activation>,
    out: &mut [f32],
) {
    debug_assert_eq!(
        check_channel_affine(&[n, c, inner], c, [scale.map(<[f32]>::len), shift.map(<[f32]>::len)], &[out.len()]),
        Ok(()),
        "channel_affine preconditions"
    );
    assert_eq!(x.len(), n * c * inner, "channel_affine: x is not [n, c, inner]");
    assert_eq!(out.len(), x.len(), "channel_affine: out and x differ in length");
    assert!(scale.is_none_or(|s| s.len() == c), "channel_affine: scale must have length c");
    assert!(shift.is_none_or(|s| s.len() == c), "channel_affine: shift must have length c");
    let relu = act == Some(Activation::Relu);
    if inner == 1 && c > 1 {
        // Rows of features ([n, c]: a sparse tensor's, BatchNorm1d's): the channel is the
        // fastest axis, so a row is one vector of coefficients, not c rows of one element.
        affine_channels_last(x, out, c, relu, scale, shift);
    } else {
        affine_rows(x, out, inner, relu, |row| {
            let ch = row % c;
            (scale.map_or(1.0, |s| s[ch]), shift.map_or(0.0, |s| s[ch]))
        });
    }
    if let Some(act) = act.filter(|a| *a != Activation::Relu) {
        elementwise::activation_in_place(act, out);
    }
}

/// LayerNorm over the last axis of `x` viewed as `[rows, features]`:
/// `y = (x - mean) / sqrt(var + eps) * weight + bias`, with the biased variance (divided
/// by `features`) as PyTorch. Two passes over each row (mean, then squared deviations), so
/// a large mean does not cancel the variance; both sums in explicit SIMD vectors. `weight` and `bias`, when present, have
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
    debug_assert_eq!(
        check_layernorm(&[rows, features], features, [weight.map(<[f32]>::len), bias.map(<[f32]>::len)], &[out.len()]),
        Ok(()),
        "layernorm preconditions"
    );
    assert_eq!(x.len(), rows * features, "layernorm: x is not [rows, features]");
    assert_eq!(out.len(), x.len(), "layernorm: out and x differ in length");
    assert!(weight.is_none_or(|w| w.len() == features), "layernorm: weight must have length features");
    assert!(bias.is_none_or(|b| b.len() == features), "layernorm: bias must have length features");
    if x.is_empty() {
        return;
    }
    let run = |x: &[f32], out: &mut [f32]| {
        pulp::Arch::new().dispatch(LayerNormRows { x, out, features, weight, bias, eps });
    };
    if x.len() >= PAR_MIN && rows > 1 {
        let task = (CHUNK / features).max(1) * features;
        out.par_chunks_mut(task).zip(x.par_chunks(task)).for_each(|(o, x)| run(x, o));
    } else {
        run(x, out);
    }
}

/// The mean of `x` and `1 / sqrt(var + eps)`, its biased variance taken in a second pass
/// over the deviations (`inv_n = 1 / x.len()`): the statistics of layernorm and groupnorm.
#[inline(always)]
fn mean_rstd<S: Simd>(simd: S, x: &[f32], inv_n: f32, eps: f32) -> (f32, f32) {
    let mean = sum_simd(simd, x) * inv_n;
    let vmean = simd.splat_f32s(mean);
    let sq_dev = |v| {
        let d = simd.sub_f32s(v, vmean);
        simd.mul_f32s(d, d)
    };
    let var = sum_map_simd(simd, x, sq_dev, |v| (v - mean) * (v - mean)) * inv_n;
    (mean, 1.0 / (var + eps).sqrt())
}

/// LayerNorm of consecutive rows, compiled for the widest SIMD the CPU has.
struct LayerNormRows<'a> {
    x: &'a [f32],
    out: &'a mut [f32],
    features: usize,
    weight: Option<&'a [f32]>,
    bias: Option<&'a [f32]>,
    eps: f32,
}

impl pulp::WithSimd for LayerNormRows<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let inv_n = 1.0 / self.features as f32;
        for (out, x) in self.out.chunks_mut(self.features).zip(self.x.chunks(self.features)) {
            let (mean, rstd) = mean_rstd(simd, x, inv_n, self.eps);
            match (self.weight, self.bias) {
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
        }
    }
}

/// GroupNorm over `x` viewed as `[n, c, inner]` with `c` in `groups` groups of
/// consecutive channels: each group of each sample (`c / groups · inner` contiguous
/// values) normalised with its mean and biased variance, then
/// `y = x̂ · weight[ch] + bias[ch]` (missing: 1 and 0), as `nn.GroupNorm`. Two passes
/// for the statistics as [`layernorm`]; the normalisation and affine are one multiply-add
/// per element. Groups run in parallel when the input is large.
#[allow(clippy::too_many_arguments)]
pub fn groupnorm(
    x: &[f32],
    n: usize,
    c: usize,
    inner: usize,
    groups: usize,
    weight: Option<&[f32]>,
    bias: Option<&[f32]>,
    eps: f32,
    out: &mut [f32],
) {
    debug_assert_eq!(
        check_groupnorm(&[n, c, inner], c, groups, [weight.map(<[f32]>::len), bias.map(<[f32]>::len)], &[out.len()]),
        Ok(()),
        "groupnorm preconditions"
    );
    assert_eq!(x.len(), n * c * inner, "groupnorm: x is not [n, c, inner]");
    assert_eq!(out.len(), x.len(), "groupnorm: out and x differ in length");
    assert!(groups >= 1 && c.is_multiple_of(groups), "groupnorm: groups must divide the channels");
    assert!(weight.is_none_or(|w| w.len() == c) && bias.is_none_or(|b| b.len() == c), "groupnorm: parameters of c");
    let block = c / groups * inner;
    if block == 0 {
        return;
    }
    let run = |first: usize, x: &[f32], out: &mut [f32]| {
        pulp::Arch::new().dispatch(GroupNormBlocks { x, out, first, block, groups, inner, weight, bias, eps });
    };
    if x.len() >= PAR_MIN && n * groups > 1 {
        let per_task = (CHUNK / block).max(1);
        out.par_chunks_mut(per_task * block)
            .zip(x.par_chunks(per_task * block))
            .enumerate()
            .for_each(|(t, (o, x))| run(t * per_task, x, o));
    } else {
        run(0, x, out);
    }
}

/// GroupNorm of consecutive groups, the first of them group `first` (over all samples),
/// compiled for the widest SIMD the CPU has.
struct GroupNormBlocks<'a> {
    x: &'a [f32],
    out: &'a mut [f32],
    first: usize,
    /// Values per group: `c / groups · inner`.
    block: usize,
    groups: usize,
    inner: usize,
    weight: Option<&'a [f32]>,
    bias: Option<&'a [f32]>,
    eps: f32,
}

impl pulp::WithSimd for GroupNormBlocks<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let GroupNormBlocks { x, out, first, block, groups, inner, weight, bias, eps } = self;
        let inv_n = 1.0 / block as f32;
        for (k, (out, x)) in out.chunks_mut(block).zip(x.chunks(block)).enumerate() {
            let g = (first + k) % groups;
            let (mean, rstd) = mean_rstd(simd, x, inv_n, eps);
            let cpg = block / inner;
            for (ch, (o, x)) in out.chunks_mut(inner).zip(x.chunks(inner)).enumerate() {
                let cc = g * cpg + ch;
                let a = rstd * weight.map_or(1.0, |w| w[cc]);
                let b = bias.map_or(0.0, |b| b[cc]) - mean * a;
                for (o, &v) in o.iter_mut().zip(x) {
                    *o = v * a + b;
                }
            }
        }
    }
}

/// `out = x * a + b`, then `max(·, 0)` if `relu`, over `x` and `out` cut into rows of
/// length `inner`, with `(a, b) = coef(row)`. Rows are split where parallel chunks end;
/// parallel when large, so both many short rows and a few long ones spread across threads.
fn affine_rows<F>(x: &[f32], out: &mut [f32], inner: usize, relu: bool, coef: F)
where
    F: Fn(usize) -> (f32, f32) + Sync,
{
    let run = |start: usize, x: &[f32], out: &mut [f32]| {
        pulp::Arch::new().dispatch(AffineRows { x, out, start, inner, relu, coef: &coef });
    };
    if out.len() >= PAR_MIN {
        out.par_chunks_mut(CHUNK).zip(x.par_chunks(CHUNK)).enumerate().for_each(|(i, (o, x))| run(i * CHUNK, x, o));
    } else {
        run(0, x, out);
    }
}

/// `out = x * scale + shift` (then ReLU) on rows of `c` channels, the channel fastest;
/// threaded over whole rows. A missing scale is 1, a missing shift 0.
fn affine_channels_last(
    x: &[f32],
    out: &mut [f32],
    c: usize,
    relu: bool,
    scale: Option<&[f32]>,
    shift: Option<&[f32]>,
) {
    let rows = |out: &mut [f32], x: &[f32]| {
        for (o, x) in out.chunks_exact_mut(c).zip(x.chunks_exact(c)) {
            match (scale, shift) {
                (Some(a), Some(b)) => {
                    o.iter_mut().zip(x).zip(a.iter().zip(b)).for_each(|((o, &v), (&a, &b))| *o = v * a + b)
                }
                (Some(a), None) => o.iter_mut().zip(x).zip(a).for_each(|((o, &v), &a)| *o = v * a),
                (None, Some(b)) => o.iter_mut().zip(x).zip(b).for_each(|((o, &v), &b)| *o = v + b),
                (None, None) => o.copy_from_slice(x),
            }
            if relu {
                o.iter_mut().for_each(|v| *v = elementwise::relu(*v));
            }
        }
    };
    if out.len() >= PAR_MIN {
        let chunk = CHUNK.div_ceil(c) * c;
        out.par_chunks_mut(chunk).zip(x.par_chunks(chunk)).for_each(|(o, x)| rows(o, x));
    } else {
        rows(out, x);
    }
}

/// [`affine_rows`] on elements `start..start + out.len()`, compiled for the widest SIMD
/// the CPU has. (`coef` runs once per row, outside the vectorised loops.)
struct AffineRows<'a, F> {
    x: &'a [f32],
    out: &'a mut [f32],
    start: usize,
    inner: usize,
    relu: bool,
    coef: &'a F,
}

impl<F: Fn(usize) -> (f32, f32)> pulp::WithSimd for AffineRows<'_, F> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, _simd: S) {
        let AffineRows { x, out, start, inner, relu, coef } = self;
        let mut pos = 0;
        while pos < out.len() {
            let g = start + pos;
            let n = (inner - g % inner).min(out.len() - pos);
            let (a, b) = coef(g / inner);
            let (x, out) = (&x[pos..pos + n], &mut out[pos..pos + n]);
            if relu {
                for (o, &v) in out.iter_mut().zip(x) {
                    *o = elementwise::relu(v * a + b);
                }
            } else {
                for (o, &v) in out.iter_mut().zip(x) {
                    *o = v * a + b;
                }
            }
            pos += n;
        }
    }
}

/// The preconditions of [`channel_affine`] on a value of shape `x` (`[n, c, ...]`): at
/// least two axes, `c` the affine's channels, vectors of `c` values, an output of `x`'s
/// length.
pub fn check_channel_affine(
    x: &[usize],
    channels: usize,
    vectors: [Option<usize>; 2],
    out: &[usize],
) -> Result<(), String> {
    if x.len() < 2 || x[1] != channels {
        return Err(format!("channel_affine of {channels} channels on a value of shape {x:?}"));
    }
    if let Some(n) = vectors.into_iter().flatten().find(|&n| n != channels) {
        return Err(format!("channel_affine vector has {n} values for {channels} channels"));
    }
    if x.iter().product::<usize>() != out.iter().product::<usize>() {
        return Err(format!("channel_affine output {out:?} differs from its input {x:?}"));
    }
    Ok(())
}

/// The preconditions of [`layernorm`] on a value of shape `x`: its last axis holds
/// `features` ≥ 1 values, the weight and bias `features` each, the output `x`'s length.
pub fn check_layernorm(x: &[usize], features: usize, params: [Option<usize>; 2], out: &[usize]) -> Result<(), String> {
    if x.last() != Some(&features) || features == 0 {
        return Err(format!("layernorm over {features} features (at least 1) on a value of shape {x:?}"));
    }
    if let Some(n) = params.into_iter().flatten().find(|&n| n != features) {
        return Err(format!("layernorm parameter has {n} values for {features} features"));
    }
    if x.iter().product::<usize>() != out.iter().product::<usize>() {
        return Err(format!("layernorm output {out:?} differs from its input {x:?}"));
    }
    Ok(())
}

/// The preconditions of [`groupnorm`] on a value of shape `x` (`[n, c, ...]`): at least
/// two axes, `c` the norm's channels, `groups` dividing them, parameters of `c` values, an
/// output of `x`'s length.
pub fn check_groupnorm(
    x: &[usize],
    channels: usize,
    groups: usize,
    params: [Option<usize>; 2],
    out: &[usize],
) -> Result<(), String> {
    if x.len() < 2 || x[1] != channels {
        return Err(format!("groupnorm of {channels} channels on a value of shape {x:?}"));
    }
    if groups == 0 || !channels.is_multiple_of(groups) {
        return Err(format!("groupnorm: {channels} channels in {groups} groups"));
    }
    if let Some(n) = params.into_iter().flatten().find(|&n| n != channels) {
        return Err(format!("groupnorm parameter has {n} values for {channels} channels"));
    }
    if x.iter().product::<usize>() != out.iter().product::<usize>() {
        return Err(format!("groupnorm output {out:?} differs from its input {x:?}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

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
        for (n, c, inner) in [(2, 3, 5), (1, 1, 1), (3, 4, 1), (2, 16, 1500), (5000, 16, 1)] {
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
                channel_affine(&x, n, c, inner, sc, sh, relu.then_some(Activation::Relu), &mut got);
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
    fn layernorm_on_every_simd_backend() {
        for features in [1, 5, 8, 15, 16, 17, 63, 64, 65, 384] {
            let x = data(3 * features, features as u64);
            let (w, b) = (data(features, 10), data(features, 11));
            let want = naive_layernorm(&x, features, Some(&w), Some(&b), 1e-5);
            for be in backends() {
                let mut got = vec![f32::NAN; x.len()];
                be.run(LayerNormRows { x: &x, out: &mut got, features, weight: Some(&w), bias: Some(&b), eps: 1e-5 });
                assert_close(&got, &want, 1e-4);
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

    fn naive_groupnorm(
        x: &[f32],
        (n, c, inner, groups): (usize, usize, usize, usize),
        w: Option<&[f32]>,
        b: Option<&[f32]>,
        eps: f64,
    ) -> Vec<f32> {
        let cpg = c / groups;
        let mut out = vec![0f32; x.len()];
        for s in 0..n {
            for g in 0..groups {
                let idx: Vec<usize> =
                    (g * cpg..(g + 1) * cpg).flat_map(|ch| (0..inner).map(move |k| (s * c + ch) * inner + k)).collect();
                let m = idx.iter().map(|&i| x[i] as f64).sum::<f64>() / idx.len() as f64;
                let var = idx.iter().map(|&i| (x[i] as f64 - m).powi(2)).sum::<f64>() / idx.len() as f64;
                for &i in &idx {
                    let ch = i / inner % c;
                    let y = (x[i] as f64 - m) / (var + eps).sqrt();
                    out[i] = (y * w.map_or(1.0, |w| w[ch] as f64) + b.map_or(0.0, |b| b[ch] as f64)) as f32;
                }
            }
        }
        out
    }

    #[test]
    fn groupnorm_matches_f64_reference() {
        // (n, c, inner, groups): one group (a LayerNorm over C·HW), one channel per group
        // (InstanceNorm), odd sizes, a large input (the parallel path), inner 1.
        for (n, c, inner, groups) in
            [(2, 6, 5, 3), (1, 4, 7, 1), (3, 5, 9, 5), (2, 8, 1, 4), (2, 64, 300, 32), (1, 6, 20000, 2)]
        {
            let x: Vec<f32> = data(n * c * inner, 13).iter().map(|v| 3.0 + 2.0 * v).collect();
            let (w, b) = (data(c, 14), data(c, 15));
            for (wo, bo) in [(Some(&w[..]), Some(&b[..])), (None, None), (Some(&w[..]), None)] {
                let mut got = vec![f32::NAN; x.len()];
                groupnorm(&x, n, c, inner, groups, wo, bo, 1e-5, &mut got);
                assert_close(&got, &naive_groupnorm(&x, (n, c, inner, groups), wo, bo, 1e-5), 1e-4);
            }
        }
        assert_eq!(check_groupnorm(&[2, 6, 5], 6, 3, [Some(6), Some(6)], &[60]), Ok(()));
        assert!(check_groupnorm(&[2, 6, 5], 6, 4, [None, None], &[60]).is_err());
        assert!(check_groupnorm(&[2, 6, 5], 6, 3, [Some(5), Some(6)], &[60]).is_err());
        assert!(check_groupnorm(&[2, 6, 5], 8, 4, [None, None], &[60]).is_err());
    }
}
