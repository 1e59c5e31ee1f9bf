//! Reductions over any set of axes (`sum`, `mean`, `max`, `min`, `var`, `std`), and the
//! vectorised `sum` the other kernels use.

use pulp::Simd;
use rayon::prelude::*;

pub use readi_plan::ops::ReduceKind;

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

/// Reduction of `x` (row-major, `shape`) over `axes` (sorted, distinct, each
/// `< shape.len()`), as PyTorch's `sum`, `mean`, `amax`, `amin`, `var` and `std`.
///
/// `out` holds the kept axes in their original order, `shape` with the reduced axes
/// removed (or set to 1: keepdim does not change the memory). An empty `axes` copies
/// (a variance of one element is then NaN with a correction of 1, as PyTorch). Over zero
/// elements a sum is 0, a mean, variance or deviation NaN, a max `-inf` and a min `inf`
/// (PyTorch refuses those two; the shape rule does too where it can see the axis).
/// `max` and `min` propagate NaN. A variance takes two passes (mean, then squared
/// deviations), so a large mean does not cancel it.
pub fn reduce(kind: ReduceKind, x: &[f32], shape: &[usize], axes: &[usize], out: &mut [f32]) {
    assert_eq!(x.len(), shape.iter().product::<usize>(), "reduce: x does not match its shape");
    assert!(axes.windows(2).all(|w| w[0] < w[1]), "reduce: axes must be sorted and distinct");
    assert!(axes.iter().all(|&a| a < shape.len()), "reduce: axis out of range");
    let count: usize = axes.iter().map(|&a| shape[a]).product();
    let kept_len: usize = (0..shape.len()).filter(|a| !axes.contains(a)).map(|a| shape[a]).product();
    assert_eq!(out.len(), kept_len, "reduce: out does not match the kept axes");
    if out.is_empty() {
        return;
    }
    let v = View::new(shape, axes);
    // Variances in a dispatch of their own: compiled into one function with the other
    // kinds, their closures were left out of line (measured 8x slower than a plain loop).
    let run = |start: usize, out: &mut [f32]| {
        let part = ReducePart { kind, view: &v, x, start, out, count };
        if kind.correction().is_some() {
            pulp::Arch::new().dispatch(VarPart(part));
        } else {
            pulp::Arch::new().dispatch(part);
        }
    };
    // Each output element costs `count` input reads (twice that for a variance); give
    // every task enough of them.
    let passes = if kind.correction().is_some() { 2 } else { 1 };
    let per_task = TASK_WORK.div_ceil(count.max(1) * passes).max(1);
    if x.len() >= PAR_MIN && out.len() > per_task {
        out.par_chunks_mut(per_task).enumerate().for_each(|(i, o)| run(i * per_task, o));
    } else {
        run(0, out);
    }
}

/// Mean of `x` over `axes`: [`reduce`] with [`ReduceKind::Mean`].
pub fn mean(x: &[f32], shape: &[usize], axes: &[usize], out: &mut [f32]) {
    reduce(ReduceKind::Mean, x, shape, axes, out);
}

/// Output elements `start..start + out.len()` of a reduction over `count` elements each,
/// compiled for the widest SIMD the CPU has.
struct ReducePart<'a> {
    kind: ReduceKind,
    view: &'a View,
    x: &'a [f32],
    start: usize,
    out: &'a mut [f32],
    count: usize,
}

impl pulp::WithSimd for ReducePart<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let ReducePart { kind, view, x, start, out, count } = self;
        match kind {
            ReduceKind::Sum => view.fold_into::<S, Add>(simd, x, start, out),
            ReduceKind::Mean => {
                view.fold_into::<S, Add>(simd, x, start, out);
                let inv = 1.0 / count as f32;
                out.iter_mut().for_each(|o| *o *= inv);
            }
            ReduceKind::Max => view.fold_into::<S, Max>(simd, x, start, out),
            ReduceKind::Min => view.fold_into::<S, Min>(simd, x, start, out),
            ReduceKind::Var { .. } | ReduceKind::Std { .. } => {
                VarPart(ReducePart { kind, view, x, start, out, count }).with_simd(simd)
            }
        }
    }
}

/// A [`ReducePart`] of a variance or standard deviation.
struct VarPart<'a>(ReducePart<'a>);

impl pulp::WithSimd for VarPart<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let ReducePart { kind, view, x, start, out, count } = self.0;
        let correction = kind.correction().unwrap_or(0);
        let div = (count as i64).saturating_sub(correction).max(0) as f32;
        view.var_into(simd, x, start, out, count, div);
        if matches!(kind, ReduceKind::Std { .. }) {
            out.iter_mut().for_each(|o| *o = o.sqrt());
        }
    }
}

/// An associative reduction of values, on vectors and on scalars alike.
trait Fold: Sized {
    /// The identity.
    const INIT: f32;
    fn vec<S: Simd>(simd: S, acc: S::f32s, v: S::f32s) -> S::f32s;
    fn one(acc: f32, v: f32) -> f32;
    /// `F` over a contiguous slice.
    #[inline(always)]
    fn slice<S: Simd>(simd: S, x: &[f32]) -> f32 {
        fold_simd::<S, Self>(simd, x)
    }
}

struct Add;
/// The maximum; a NaN, once in the accumulator, stays (as PyTorch's `amax`).
struct Max;
/// The minimum, NaN propagating as [`Max`].
struct Min;

impl Fold for Add {
    const INIT: f32 = 0.0;
    #[inline(always)]
    fn vec<S: Simd>(simd: S, acc: S::f32s, v: S::f32s) -> S::f32s {
        simd.add_f32s(acc, v)
    }
    #[inline(always)]
    fn one(acc: f32, v: f32) -> f32 {
        acc + v
    }
    /// [`sum_simd`], whose lanes add up as a tree.
    #[inline(always)]
    fn slice<S: Simd>(simd: S, x: &[f32]) -> f32 {
        sum_simd(simd, x)
    }
}

impl Fold for Max {
    const INIT: f32 = f32::NEG_INFINITY;
    /// `acc` if it is NaN or not below `v`, else `v` (which may be NaN): two selects,
    /// not a read-modify-write select (see the module notes in `kernels`).
    #[inline(always)]
    fn vec<S: Simd>(simd: S, acc: S::f32s, v: S::f32s) -> S::f32s {
        let keep = simd.select_f32s(simd.less_than_or_equal_f32s(v, acc), acc, v);
        simd.select_f32s(simd.equal_f32s(acc, acc), keep, acc)
    }
    #[inline(always)]
    fn one(acc: f32, v: f32) -> f32 {
        if acc.is_nan() || v <= acc { acc } else { v }
    }
}

impl Fold for Min {
    const INIT: f32 = f32::INFINITY;
    #[inline(always)]
    fn vec<S: Simd>(simd: S, acc: S::f32s, v: S::f32s) -> S::f32s {
        let keep = simd.select_f32s(simd.greater_than_or_equal_f32s(v, acc), acc, v);
        simd.select_f32s(simd.equal_f32s(acc, acc), keep, acc)
    }
    #[inline(always)]
    fn one(acc: f32, v: f32) -> f32 {
        if acc.is_nan() || v >= acc { acc } else { v }
    }
}

/// `F` over `x` in explicit SIMD vectors with four accumulators, as [`sum_simd`].
#[inline(always)]
fn fold_simd<S: Simd, F: Fold>(simd: S, x: &[f32]) -> f32 {
    let (head, tail) = S::as_simd_f32s(x);
    let (quads, rest) = head.as_chunks::<4>();
    let init = simd.splat_f32s(F::INIT);
    let (mut a0, mut a1, mut a2, mut a3) = (init, init, init, init);
    for q in quads {
        a0 = F::vec(simd, a0, q[0]);
        a1 = F::vec(simd, a1, q[1]);
        a2 = F::vec(simd, a2, q[2]);
        a3 = F::vec(simd, a3, q[3]);
    }
    for (i, &v) in rest.iter().enumerate() {
        match i {
            0 => a0 = F::vec(simd, a0, v),
            1 => a1 = F::vec(simd, a1, v),
            _ => a2 = F::vec(simd, a2, v),
        }
    }
    let acc = F::vec(simd, F::vec(simd, a0, a1), F::vec(simd, a2, a3));
    // The lanes, through a buffer wide enough for any vector (16 lanes of AVX-512).
    let mut lanes = [F::INIT; 16];
    let (slots, _) = S::as_mut_simd_f32s(&mut lanes);
    slots[0] = acc;
    let total = lanes.iter().fold(F::INIT, |t, &v| F::one(t, v));
    tail.iter().fold(total, |t, &v| F::one(t, v))
}

/// The maximum of `x` with NaN propagating (`-inf` for an empty slice), as
/// [`sum_simd`] for the sum.
#[inline(always)]
pub(crate) fn max_simd<S: Simd>(simd: S, x: &[f32]) -> f32 {
    fold_simd::<S, Max>(simd, x)
}

/// The larger of `acc` and `v`, NaN in either winning.
#[inline(always)]
pub(crate) fn max_nan(acc: f32, v: f32) -> f32 {
    if v.is_nan() { v } else { Max::one(acc, v) }
}

/// `sum[i] += d` and `sq[i] += d * d` with `d = x[i] - k[i]`, over four slices of one
/// length, in SIMD vectors.
#[inline(always)]
fn shifted_rows<S: Simd>(simd: S, sum: &mut [f32], sq: &mut [f32], k: &[f32], x: &[f32]) {
    let (sh, st) = S::as_mut_simd_f32s(sum);
    let (qh, qt) = S::as_mut_simd_f32s(sq);
    let (kh, kt) = S::as_simd_f32s(k);
    let (xh, xt) = S::as_simd_f32s(x);
    for (((s, q), &k), &v) in sh.iter_mut().zip(qh.iter_mut()).zip(kh).zip(xh) {
        let d = simd.sub_f32s(v, k);
        *s = simd.add_f32s(*s, d);
        *q = simd.mul_add_f32s(d, d, *q);
    }
    for (((s, q), &k), &v) in st.iter_mut().zip(qt.iter_mut()).zip(kt).zip(xt) {
        let d = v - k;
        *s += d;
        *q += d * d;
    }
}

/// `out[i] += x[i]` over two slices of one length, in SIMD vectors.
#[inline(always)]
pub(crate) fn add_rows<S: Simd>(simd: S, out: &mut [f32], x: &[f32]) {
    fold_rows::<S, Add>(simd, out, x)
}

/// `out[i] = max(out[i], x[i])`, NaN propagating, over two slices of one length.
#[inline(always)]
pub(crate) fn max_rows<S: Simd>(simd: S, out: &mut [f32], x: &[f32]) {
    fold_rows::<S, Max>(simd, out, x)
}

/// `out[i] = F(out[i], x[i])` over two slices of one length, in SIMD vectors.
#[inline(always)]
fn fold_rows<S: Simd, F: Fold>(simd: S, out: &mut [f32], x: &[f32]) {
    let (oh, ot) = S::as_mut_simd_f32s(out);
    let (xh, xt) = S::as_simd_f32s(x);
    for (o, &v) in oh.iter_mut().zip(xh) {
        *o = F::vec(simd, *o, v);
    }
    for (o, &v) in ot.iter_mut().zip(xt) {
        *o = F::one(*o, v);
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

    /// Writes `F` over each of output elements `start..start + out.len()` to `out`.
    #[inline(always)]
    fn fold_into<S: Simd, F: Fold>(&self, simd: S, x: &[f32], start: usize, out: &mut [f32]) {
        let combos: usize = self.reduced.iter().map(|d| d.0).product();
        if self.run_reduced {
            for (i, o) in out.iter_mut().enumerate() {
                let base = self.kept_offset(start + i);
                *o = (0..combos).fold(F::INIT, |acc, r| {
                    let b = base + self.reduced_offset(r);
                    F::one(acc, F::slice(simd, &x[b..b + self.run]))
                });
            }
        } else {
            // Tiles of the output (see `tile_at`), written without a closure, which was
            // left out of line (and so out of the SIMD dispatch).
            let mut pos = 0;
            while pos < out.len() {
                let (base, tn) = self.tile_at(start + pos, out.len() - pos);
                let seg = &mut out[pos..pos + tn];
                seg.fill(F::INIT);
                for r in 0..combos {
                    let b = base + self.reduced_offset(r);
                    fold_rows::<S, F>(simd, seg, &x[b..b + tn]);
                }
                pos += tn;
            }
        }
    }

    /// Writes the variance of each of output elements `start..start + out.len()` over
    /// `count` elements to `out`: squared deviations from the mean, summed, over `div`.
    #[inline(always)]
    fn var_into<S: Simd>(&self, simd: S, x: &[f32], start: usize, out: &mut [f32], count: usize, div: f32) {
        let combos: usize = self.reduced.iter().map(|d| d.0).product();
        let inv = 1.0 / count as f32;
        if self.run_reduced {
            let run = self.run;
            for (i, o) in out.iter_mut().enumerate() {
                let base = self.kept_offset(start + i);
                let mut sum = 0.0;
                for r in 0..combos {
                    let b = base + self.reduced_offset(r);
                    sum += sum_simd(simd, &x[b..b + run]);
                }
                let mean = sum * inv;
                let vmean = simd.splat_f32s(mean);
                let mut sq = 0.0;
                for r in 0..combos {
                    let b = base + self.reduced_offset(r);
                    let sq_dev = |v| {
                        let d = simd.sub_f32s(v, vmean);
                        simd.mul_f32s(d, d)
                    };
                    sq += sum_map_simd(simd, &x[b..b + run], sq_dev, |v| (v - mean) * (v - mean));
                }
                *o = sq / div;
            }
        } else {
            // One pass over x, with the data shifted by its first reduced row (`k`):
            // var = (sum d^2 - (sum d)^2 / n) / div with d = x - k. The shift keeps the
            // sums small where the mean is large (a sample is within a few deviations of
            // the mean), and the one pass reads x once instead of twice.
            let mut pos = 0;
            let mut sq = [0f32; TILE];
            while pos < out.len() {
                let (base, tn) = self.tile_at(start + pos, out.len() - pos);
                let seg = &mut out[pos..pos + tn];
                seg.fill(0.0);
                let sq = &mut sq[..tn];
                sq.fill(0.0);
                let k = &x[base..base + tn];
                for off in self.reduced_offsets(combos) {
                    shifted_rows(simd, seg, sq, k, &x[base + off..base + off + tn]);
                }
                for (o, &q) in seg.iter_mut().zip(sq.iter()) {
                    // Rounding can take it below 0; a NaN stays NaN.
                    *o = super::elementwise::relu(q - *o * *o * inv) / div;
                }
                pos += tn;
            }
        }
    }

    /// The offsets in x of reduced indices `0..combos`, in order: multiples of the stride
    /// when one axis is reduced (no division per row), [`View::reduced_offset`] otherwise.
    #[inline(always)]
    fn reduced_offsets(&self, combos: usize) -> impl Iterator<Item = usize> + '_ {
        let single = match self.reduced[..] {
            [(_, stride)] => Some(stride),
            _ => None,
        };
        (0..combos).map(move |r| single.map_or_else(|| self.reduced_offset(r), |stride| r * stride))
    }

    /// With the last axis kept: the tile of output elements starting at `g` (global),
    /// at most `left` long, within one row of `run` and at most [`TILE`] long (it stays in
    /// L1 while every reduced row is added in): `(offset in x at reduced index 0, length)`.
    #[inline(always)]
    fn tile_at(&self, g: usize, left: usize) -> (usize, usize) {
        let (row, col) = (g / self.run, g % self.run);
        let n = (self.run - col).min(left).min(TILE);
        (self.kept_offset(row) + col, n)
    }
}

/// The preconditions of [`reduce`] over `axes` of `x`: the axes sorted, distinct and in
/// range, the output as long as the kept axes.
pub fn check_reduce(kind: ReduceKind, x: &[usize], axes: &[usize], out: &[usize]) -> Result<(), String> {
    let name = kind.name();
    if !axes.windows(2).all(|w| w[0] < w[1]) || axes.iter().any(|&a| a >= x.len()) {
        return Err(format!("{name} over axes {axes:?} of a value of shape {x:?}"));
    }
    let kept: usize = (0..x.len()).filter(|a| !axes.contains(a)).map(|a| x[a]).product();
    if kept != out.iter().product::<usize>() {
        return Err(format!("{name} over axes {axes:?} of {x:?} cannot give {out:?}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

    const KINDS: [ReduceKind; 8] = [
        ReduceKind::Sum,
        ReduceKind::Mean,
        ReduceKind::Max,
        ReduceKind::Min,
        ReduceKind::Var { correction: 1 },
        ReduceKind::Var { correction: 0 },
        ReduceKind::Var { correction: 3 },
        ReduceKind::Std { correction: 1 },
    ];

    /// Plain reference: the values of each output element gathered by their kept index,
    /// then reduced in f64 by the textbook formula.
    fn naive(kind: ReduceKind, x: &[f32], shape: &[usize], axes: &[usize]) -> Vec<f32> {
        let kept: Vec<usize> = (0..shape.len()).filter(|a| !axes.contains(a)).collect();
        let out_len: usize = kept.iter().map(|&a| shape[a]).product();
        let mut groups = vec![Vec::new(); out_len];
        for (flat, &v) in x.iter().enumerate() {
            // Multi-index of `flat`.
            let mut idx = vec![0; shape.len()];
            let mut r = flat;
            for a in (0..shape.len()).rev() {
                idx[a] = r % shape[a];
                r /= shape[a];
            }
            let o = kept.iter().fold(0, |o, &a| o * shape[a] + idx[a]);
            groups[o].push(v as f64);
        }
        let var = |g: &[f64], c: i64| {
            let n = g.len() as f64;
            let m = g.iter().sum::<f64>() / n;
            g.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - c as f64).max(0.0)
        };
        groups
            .iter()
            .map(|g| {
                let v = match kind {
                    ReduceKind::Sum => g.iter().sum(),
                    ReduceKind::Mean => g.iter().sum::<f64>() / g.len() as f64,
                    ReduceKind::Max => {
                        g.iter().fold(f64::NEG_INFINITY, |a, &v| if v > a || v.is_nan() { v } else { a })
                    }
                    ReduceKind::Min => g.iter().fold(f64::INFINITY, |a, &v| if v < a || v.is_nan() { v } else { a }),
                    ReduceKind::Var { correction } => var(g, correction),
                    ReduceKind::Std { correction } => var(g, correction).sqrt(),
                };
                v as f32
            })
            .collect()
    }

    fn check(shape: &[usize], axes: &[usize]) {
        let x = data(shape.iter().product(), 7 + shape.len() as u64);
        for kind in KINDS {
            let want = naive(kind, &x, shape, axes);
            let mut got = vec![f32::NAN; want.len()];
            reduce(kind, &x, shape, axes, &mut got);
            // Sums of up to 30000 values in [-1, 1]: absolute error grows with them.
            let tol = if kind == ReduceKind::Sum { 1e-5 * (x.len() as f32).sqrt().max(1.0) } else { 1e-5 };
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                let ok = (g.is_nan() && w.is_nan()) || g == w || (g - w).abs() <= tol * w.abs().max(1.0);
                assert!(ok, "{kind:?} over {axes:?} of {shape:?}, element {i}: {g} vs {w}");
            }
        }
    }

    struct Fold1<'a, F>(&'a [f32], std::marker::PhantomData<F>);

    impl<F: Fold> pulp::WithSimd for Fold1<'_, F> {
        type Output = f32;
        #[inline(always)]
        fn with_simd<S: Simd>(self, simd: S) -> f32 {
            fold_simd::<S, F>(simd, self.0)
        }
    }

    #[test]
    fn max_and_min_on_every_backend_propagate_nan() {
        for n in [1, 5, 15, 16, 17, 33, 64, 65, 100] {
            let mut x = data(n, n as u64);
            let (mx, mn) = (x.iter().copied().fold(f32::MIN, f32::max), x.iter().copied().fold(f32::MAX, f32::min));
            for b in backends() {
                assert_eq!(b.run(Fold1::<Max>(&x, Default::default())), mx, "max of {n}");
                assert_eq!(b.run(Fold1::<Min>(&x, Default::default())), mn, "min of {n}");
            }
            // A NaN anywhere (first, middle, in the tail) wins, as torch.amax.
            for at in [0, n / 2, n - 1] {
                let keep = x[at];
                x[at] = f32::NAN;
                for b in backends() {
                    assert!(b.run(Fold1::<Max>(&x, Default::default())).is_nan(), "max of {n}, NaN at {at}");
                    assert!(b.run(Fold1::<Min>(&x, Default::default())).is_nan(), "min of {n}, NaN at {at}");
                }
                x[at] = keep;
            }
        }
        // Over a kept last axis too (the row-wise path).
        let mut x = data(3 * 40, 3);
        x[41] = f32::NAN;
        let mut got = [0f32; 40];
        reduce(ReduceKind::Max, &x, &[3, 40], &[0], &mut got);
        assert!(got[1].is_nan() && got.iter().enumerate().all(|(i, v)| i == 1 || !v.is_nan()), "{got:?}");
        reduce(ReduceKind::Min, &x, &[3, 40], &[0], &mut got);
        assert!(got[1].is_nan());
    }

    #[test]
    fn var_and_std_by_hand() {
        // [1, 2, 3, 4]: mean 2.5, squared deviations 5; torch.var 5/3, correction=0 5/4.
        let x = [1.0, 2.0, 3.0, 4.0];
        let mut out = [0f32];
        reduce(ReduceKind::Var { correction: 1 }, &x, &[4], &[0], &mut out);
        assert_eq!(out[0], 5.0 / 3.0);
        reduce(ReduceKind::Var { correction: 0 }, &x, &[4], &[0], &mut out);
        assert_eq!(out[0], 1.25);
        reduce(ReduceKind::Std { correction: 0 }, &x, &[4], &[0], &mut out);
        assert_eq!(out[0], 1.25f32.sqrt());
        // One element with Bessel's correction: 0 / 0 (torch: nan); a correction above
        // the count divides by 0 (torch: inf).
        reduce(ReduceKind::Var { correction: 1 }, &[3.0], &[1], &[0], &mut out);
        assert!(out[0].is_nan());
        reduce(ReduceKind::Var { correction: 5 }, &x, &[4], &[0], &mut out);
        assert_eq!(out[0], f32::INFINITY);
    }

    #[test]
    fn var_is_stable_with_a_large_mean() {
        // A one-pass E[x²] - E[x]² in f32 loses everything here, on both paths.
        let x: Vec<f32> = data(4 * 256, 12).iter().map(|v| 1e4 + 0.1 * v).collect();
        for (shape, axes) in [(&[4, 256][..], &[1][..]), (&[256, 4], &[0])] {
            let kind = ReduceKind::Var { correction: 1 };
            let want = naive(kind, &x, shape, axes);
            let mut got = vec![0.0; 4];
            reduce(kind, &x, shape, axes, &mut got);
            assert_close(&got, &want, 1e-4);
        }
        // The kept-last-axis path's one shifted pass: tiles past TILE, one reduced axis
        // and two (its offsets by stride and by index), rows that are all alike (variance
        // 0, never negative).
        let x: Vec<f32> = data(3 * 4 * 5 * 600, 13).iter().map(|v| 1e4 + 0.1 * v).collect();
        for (shape, axes) in [(&[15, 2400][..], &[0][..]), (&[3, 4, 5, 600], &[0, 2])] {
            for correction in [0, 1] {
                let kind = ReduceKind::Var { correction };
                let want = naive(kind, &x, shape, axes);
                let mut got = vec![f32::NAN; want.len()];
                reduce(kind, &x, shape, axes, &mut got);
                // Variances of about 3e-3: 1e-6 absolute is a relative 3e-4.
                assert_close(&got, &want, 1e-6);
            }
        }
        let same = vec![3.5f32; 6 * 1500];
        let mut got = vec![f32::NAN; 1500];
        reduce(ReduceKind::Var { correction: 1 }, &same, &[6, 1500], &[0], &mut got);
        assert!(got.iter().all(|&v| v == 0.0), "{:?}", &got[..4]);
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
    fn reductions_over_start_middle_end_and_mixed_axes() {
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
    fn reductions_with_size_one_axes() {
        check(&[1, 3, 1, 5], &[1]);
        check(&[1, 3, 1, 5], &[0, 2]);
        check(&[3, 1, 4], &[1]);
        check(&[3, 1, 4], &[0, 1]);
        check(&[1, 1], &[0, 1]);
    }

    #[test]
    fn reductions_large_run_in_parallel_and_match() {
        // Big enough for the parallel path, both with the last axis kept and reduced.
        check(&[4, 96, 130], &[1]);
        check(&[64, 3, 257], &[2]);
        check(&[3, 20000], &[0]);
        check(&[2, 30000], &[1]);
    }

    #[test]
    fn reductions_of_an_empty_axis() {
        let mut out = [0f32; 2];
        mean(&[], &[2, 0], &[1], &mut out);
        assert!(out.iter().all(|v| v.is_nan()));
        reduce(ReduceKind::Sum, &[], &[2, 0], &[1], &mut out);
        assert_eq!(out, [0.0, 0.0]);
        reduce(ReduceKind::Var { correction: 0 }, &[], &[2, 0], &[1], &mut out);
        assert!(out.iter().all(|v| v.is_nan()));
    }

    #[test]
    fn reductions_over_several_axes_of_odd_shapes() {
        check(&[3, 5, 7], &[0, 2]);
        check(&[5, 1, 3, 2, 7], &[1, 3, 4]);
        check(&[17, 9], &[0]);
        check(&[2, 3, 1100], &[0, 1]);
        check(&[1, 2, 1100, 3], &[0, 3]);
    }
}
