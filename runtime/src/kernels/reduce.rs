//! Reductions: `mean` over any set of axes, and the vectorised `sum` the other kernels use.

use pulp::Simd;
use rayon::prelude::*;

/// Below this many input elements a reduction runs on the calling thread.
const PAR_MIN: usize = 1 << 15;
/// Input elements each parallel task should cover, at least.
const TASK_WORK: usize = 1 << 14;
/// Output elements accumulated together when the last axis is kept.
const TILE: usize = 1024;

/// Sum of `x` in explicit SIMD vectors (`S::f32s`) with four accumulators: the loop runs
/// at full width for whatever `S` is, and the rounding error grows `4 · lanes` times
/// more slowly than a sequential sum's. (Lane arrays left to LLVM's auto-vectoriser were
/// fragile: depending on the code around them the accumulators ended up in memory.)
#[inline(always)]
pub(crate) fn sum_simd<S: Simd>(simd: S, x: &[f32]) -> f32 {
    sum_map_simd(simd, x, |v| v, |v| v)
}

/// `Σ f(x[i])`, as [`sum_simd`]; `fv` is `f` on a vector, `fs` on a scalar (the tail).
#[inline(always)]
pub(crate) fn sum_map_simd<S: Simd>(
    simd: S,
    x: &[f32],
    fv: impl Fn(S::f32s) -> S::f32s,
    fs: impl Fn(f32) -> f32,
) -> f32 {
    let (head, tail) = S::as_simd_f32s(x);
    let (quads, rest) = head.as_chunks::<4>();
    let zero = simd.splat_f32s(0.0);
    let (mut a0, mut a1, mut a2, mut a3) = (zero, zero, zero, zero);
    for q in quads {
        a0 = simd.add_f32s(a0, fv(q[0]));
        a1 = simd.add_f32s(a1, fv(q[1]));
        a2 = simd.add_f32s(a2, fv(q[2]));
        a3 = simd.add_f32s(a3, fv(q[3]));
    }
    for (i, &v) in rest.iter().enumerate() {
        match i {
            0 => a0 = simd.add_f32s(a0, fv(v)),
            1 => a1 = simd.add_f32s(a1, fv(v)),
            _ => a2 = simd.add_f32s(a2, fv(v)),
        }
    }
    let total = simd.reduce_sum_f32s(simd.add_f32s(simd.add_f32s(a0, a1), simd.add_f32s(a2, a3)));
    tail.iter().fold(total, |t, &v| t + fs(v))
}

/// Mean of `x` (row-major, `shape`) over `axes` (sorted, distinct, each `< shape.len()`).
///
/// `out` holds the kept axes in their original order, `shape` with the reduced axes
/// removed (or set to 1: keepdim does not change the memory). An empty `axes` copies; a
/// reduction over zero elements gives NaN, as PyTorch.
pub fn mean(x: &[f32], shape: &[usize], axes: &[usize], out: &mut [f32]) {
    assert_eq!(x.len(), shape.iter().product::<usize>(), "mean: x does not match its shape");
    assert!(axes.windows(2).all(|w| w[0] < w[1]), "mean: axes must be sorted and distinct");
    assert!(axes.iter().all(|&a| a < shape.len()), "mean: axis out of range");
    let count: usize = axes.iter().map(|&a| shape[a]).product();
    let kept_len: usize = (0..shape.len()).filter(|a| !axes.contains(a)).map(|a| shape[a]).product();
    assert_eq!(out.len(), kept_len, "mean: out does not match the kept axes");
    if out.is_empty() {
        return;
    }
    let v = View::new(shape, axes);
    let inv = 1.0 / count as f32;
    let run = |start: usize, out: &mut [f32]| pulp::Arch::new().dispatch(MeanPart { view: &v, x, start, out, inv });
    // Each output element costs `count` input reads; give every task enough of them.
    let per_task = TASK_WORK.div_ceil(count.max(1)).max(1);
    if x.len() >= PAR_MIN && out.len() > per_task {
        out.par_chunks_mut(per_task).enumerate().for_each(|(i, o)| run(i * per_task, o));
    } else {
        run(0, out);
    }
}

/// Output elements `start..start + out.len()` of a mean, compiled for the widest SIMD the
/// CPU has.
struct MeanPart<'a> {
    view: &'a View,
    x: &'a [f32],
    start: usize,
    out: &'a mut [f32],
    inv: f32,
}

impl pulp::WithSimd for MeanPart<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        self.view.sum_into(simd, self.x, self.start, self.out);
        self.out.iter_mut().for_each(|o| *o *= self.inv);
    }
}

/// `x`'s shape with size-1 axes dropped and neighbouring axes of the same kind (kept or
/// reduced) merged, so that it alternates kept and reduced axes.
struct View {
    /// Kept axes, outermost first: (size, stride in x).
    kept: Vec<(usize, usize)>,
    /// Reduced axes, outermost first: (size, stride in x), excluding the last axis of x
    /// when that one is reduced (it is `run` then).
    reduced: Vec<(usize, usize)>,
    /// Length of the contiguous innermost run: the last axis, kept or reduced.
    run: usize,
    /// Whether the innermost axis is reduced.
    run_reduced: bool,
}

impl View {
    fn new(shape: &[usize], axes: &[usize]) -> View {
        // (size, reduced), outermost first, size-1 axes dropped, same-kind neighbours merged.
        let mut dims: Vec<(usize, bool)> = Vec::with_capacity(shape.len());
        for (a, &n) in shape.iter().enumerate() {
            let r = axes.contains(&a);
            if n == 1 {
                continue;
            }
            match dims.last_mut() {
                Some((m, lr)) if *lr == r => *m *= n,
                _ => dims.push((n, r)),
            }
        }
        if dims.is_empty() {
            dims.push((1, false));
        }
        let mut strides = vec![1usize; dims.len()];
        for i in (0..dims.len() - 1).rev() {
            strides[i] = strides[i + 1] * dims[i + 1].0;
        }
        let (run, run_reduced) = dims[dims.len() - 1];
        let outer = dims.len() - 1;
        let kept = (0..outer).filter(|&i| !dims[i].1).map(|i| (dims[i].0, strides[i])).collect();
        let reduced = (0..outer).filter(|&i| dims[i].1).map(|i| (dims[i].0, strides[i])).collect();
        View { kept, reduced, run, run_reduced }
    }

    /// Offset in x of kept index `k` (flat over the kept axes other than the run).
    fn kept_offset(&self, mut k: usize) -> usize {
        let mut off = 0;
        for &(n, s) in self.kept.iter().rev() {
            off += (k % n) * s;
            k /= n;
        }
        off
    }

    /// Offset in x of reduced index `r` (flat over `self.reduced`).
    fn reduced_offset(&self, mut r: usize) -> usize {
        let mut off = 0;
        for &(n, s) in self.reduced.iter().rev() {
            off += (r % n) * s;
            r /= n;
        }
        off
    }

    /// Writes the sums of output elements `start..start + out.len()` to `out`.
    #[inline(always)]
    fn sum_into<S: Simd>(&self, simd: S, x: &[f32], start: usize, out: &mut [f32]) {
        let combos: usize = self.reduced.iter().map(|d| d.0).product();
        if self.run_reduced {
            for (i, o) in out.iter_mut().enumerate() {
                let base = self.kept_offset(start + i);
                *o = (0..combos)
                    .map(|r| {
                        let b = base + self.reduced_offset(r);
                        sum_simd(simd, &x[b..b + self.run])
                    })
                    .sum();
            }
        } else {
            // Output elements come in rows of `run`; accumulate whole row segments.
            let mut pos = 0;
            while pos < out.len() {
                let g = start + pos;
                let (row, col) = (g / self.run, g % self.run);
                let n = (self.run - col).min(out.len() - pos);
                let base = self.kept_offset(row) + col;
                // In tiles that stay in L1 while every reduced row is added in.
                for t in (0..n).step_by(TILE) {
                    let tn = TILE.min(n - t);
                    let seg = &mut out[pos + t..pos + t + tn];
                    seg.fill(0.0);
                    for r in 0..combos {
                        let b = base + t + self.reduced_offset(r);
                        for (o, v) in seg.iter_mut().zip(&x[b..b + tn]) {
                            *o += v;
                        }
                    }
                }
                pos += n;
            }
        }
    }
}

/// The preconditions of [`mean`] over `axes` of `x`: the axes sorted, distinct and in
/// range, the output as long as the kept axes.
pub fn check_mean(x: &[usize], axes: &[usize], out: &[usize]) -> Result<(), String> {
    if !axes.windows(2).all(|w| w[0] < w[1]) || axes.iter().any(|&a| a >= x.len()) {
        return Err(format!("mean over axes {axes:?} of a value of shape {x:?}"));
    }
    let kept: usize = (0..x.len()).filter(|a| !axes.contains(a)).map(|a| x[a]).product();
    if kept != out.iter().product::<usize>() {
        return Err(format!("mean over axes {axes:?} of {x:?} cannot give {out:?}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

    /// Plain reference: for each input element, add it to the output element of its kept index.
    fn naive_mean(x: &[f32], shape: &[usize], axes: &[usize]) -> Vec<f32> {
        let kept: Vec<usize> = (0..shape.len()).filter(|a| !axes.contains(a)).collect();
        let out_len: usize = kept.iter().map(|&a| shape[a]).product();
        let count: usize = axes.iter().map(|&a| shape[a]).product();
        let mut acc = vec![0f64; out_len];
        for (flat, &v) in x.iter().enumerate() {
            // Multi-index of `flat`.
            let mut idx = vec![0; shape.len()];
            let mut r = flat;
            for a in (0..shape.len()).rev() {
                idx[a] = r % shape[a];
                r /= shape[a];
            }
            let o = kept.iter().fold(0, |o, &a| o * shape[a] + idx[a]);
            acc[o] += v as f64;
        }
        acc.iter().map(|&s| (s / count as f64) as f32).collect()
    }

    fn check(shape: &[usize], axes: &[usize]) {
        let x = data(shape.iter().product(), 7 + shape.len() as u64);
        let want = naive_mean(&x, shape, axes);
        let mut got = vec![f32::NAN; want.len()];
        mean(&x, shape, axes, &mut got);
        assert_close(&got, &want, 1e-5);
    }

    struct Sum<'a>(&'a [f32]);

    impl pulp::WithSimd for Sum<'_> {
        type Output = f32;
        #[inline(always)]
        fn with_simd<S: Simd>(self, simd: S) -> f32 {
            sum_simd(simd, self.0)
        }
    }

    #[test]
    fn sum_matches_f64_for_all_remainders() {
        for n in [0, 1, 5, 15, 16, 17, 33, 63, 64, 65, 100, 1000] {
            let x = data(n, n as u64);
            let want: f64 = x.iter().map(|&v| v as f64).sum();
            for b in backends() {
                assert_close(&[b.run(Sum(&x))], &[want as f32], 1e-6);
            }
        }
    }

    #[test]
    fn mean_over_start_middle_end_and_mixed_axes() {
        check(&[2, 3, 4, 5], &[3]);
        check(&[2, 3, 4, 5], &[2, 3]);
        check(&[2, 3, 4, 5], &[0]);
        check(&[2, 3, 4, 5], &[1]);
        check(&[2, 3, 4, 5], &[1, 2]);
        check(&[2, 3, 4, 5], &[0, 2]);
        check(&[2, 3, 4, 5], &[1, 3]);
        check(&[2, 3, 4, 5], &[0, 1, 2, 3]);
        check(&[2, 3, 4, 5], &[]);
        check(&[7], &[0]);
    }

    #[test]
    fn mean_with_size_one_axes() {
        check(&[1, 3, 1, 5], &[1]);
        check(&[1, 3, 1, 5], &[0, 2]);
        check(&[3, 1, 4], &[1]);
        check(&[3, 1, 4], &[0, 1]);
        check(&[1, 1], &[0, 1]);
    }

    #[test]
    fn mean_large_runs_in_parallel_and_matches() {
        // Big enough for the parallel path, both with the last axis kept and reduced.
        check(&[4, 96, 130], &[1]);
        check(&[64, 3, 257], &[2]);
        check(&[3, 20000], &[0]);
        check(&[2, 30000], &[1]);
    }

    #[test]
    fn mean_of_empty_axis_is_nan() {
        let mut out = [0f32; 2];
        mean(&[], &[2, 0], &[1], &mut out);
        assert!(out.iter().all(|v| v.is_nan()));
    }
}
