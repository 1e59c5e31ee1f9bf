//! Kernels of the operators whose indices are values computed at run time
//! (`readi_plan::ops::select`): `argmax` / `argmin`, `topk`, `gather` /
//! `take_along_dim`, `index_select` at a computed index, `one_hot`, and `where` with a
//! number for a branch.
//!
//! An index is an f32 holding an integer. Every index a kernel reads is checked before it
//! is used: a value that is not an integer, or out of `0..size`, makes the kernel return
//! an `Err` naming it (the step then fails with `RunError::Step`), never a panic or a read
//! out of bounds. The output may then be partly written.

use std::cmp::Ordering;

/// The position an index value names along an axis of `size`, or why it names none.
#[inline]
fn position(v: f32, size: usize, at: usize, what: &str) -> Result<usize, String> {
    if v.fract() != 0.0 || !v.is_finite() {
        return Err(format!("{what} {v} (at flat position {at}) is not an integer"));
    }
    if v < 0.0 || v >= size as f32 {
        return Err(format!("{what} {v} (at flat position {at}) is out of range for an axis of size {size}"));
    }
    Ok(v as usize)
}

/// The (outer, size, inner) split of `shape` around `axis`.
fn split(shape: &[usize], axis: usize) -> (usize, usize, usize) {
    (shape[..axis].iter().product(), shape[axis], shape[axis + 1..].iter().product())
}

/// Checks an `argmax` / `argmin` of `x` along `axis` (all of it for `None`) into `out`.
pub fn check_arg_reduce(x: &[usize], axis: Option<usize>, out: &[usize]) -> Result<(), String> {
    let n: usize = out.iter().product();
    match axis {
        None if x.contains(&0) => Err(format!("argmax / argmin of an empty tensor {x:?}")),
        None if n != 1 => Err(format!("argmax / argmin of all of {x:?} into {out:?}")),
        None => Ok(()),
        Some(a) if a >= x.len() => Err(format!("argmax / argmin along axis {a} of {x:?}")),
        Some(a) if x[a] == 0 => Err(format!("argmax / argmin along axis {a} of {x:?}, which is empty")),
        Some(a) => {
            let (outer, _, inner) = split(x, a);
            if outer * inner != n {
                return Err(format!("argmax / argmin of {x:?} along {a} into {out:?}"));
            }
            Ok(())
        }
    }
}

/// `torch.argmax` (`max`) or `torch.argmin` of `x` along `axis` (of the flattened `x` for
/// `None`): the first position of the extreme value, a NaN counting as the extreme (the
/// first NaN wins, as torch).
pub fn arg_reduce(max: bool, x: &[f32], xs: &[usize], axis: Option<usize>, out: &mut [f32]) {
    let (outer, size, inner) = match axis {
        Some(a) => split(xs, a),
        None => (1, x.len(), 1),
    };
    assert_eq!(out.len(), outer * inner, "arg_reduce: out does not match its shape");
    for o in 0..outer {
        for i in 0..inner {
            let at = |j: usize| x[(o * size + j) * inner + i];
            let (mut best, mut bv) = (0, at(0));
            for j in 1..size {
                let v = at(j);
                if bv.is_nan() {
                    break;
                }
                if v.is_nan() || (max && v > bv) || (!max && v < bv) {
                    (best, bv) = (j, v);
                }
            }
            out[o * inner + i] = best as f32;
        }
    }
}

/// Checks a `topk` of `k` along `axis` of `x` into `out`.
pub fn check_topk(x: &[usize], k: usize, axis: usize, out: &[usize]) -> Result<(), String> {
    if axis >= x.len() || k > x[axis] {
        return Err(format!("topk of k = {k} along axis {axis} of {x:?}"));
    }
    if x[axis] > MAX_INDEXED {
        return Err(format!("topk along an axis of {} positions, more than an f32 index names exactly", x[axis]));
    }
    let mut want = x.to_vec();
    want[axis] = k;
    if want != out {
        return Err(format!("topk of {x:?} gives {want:?}, its output is {out:?}"));
    }
    Ok(())
}

/// `torch.topk` along `axis`: per row, the `k` largest values (`largest`) or smallest, in
/// order, or (`indices`) their positions. Ties go to the lower position; NaN counts as
/// larger than every number.
///
/// A heap of the `k` best positions seen so far, kept in the row's own output (worst on
/// top), then sorted in place: `O(size log k)` and no memory but `out`.
pub fn topk(x: &[f32], xs: &[usize], k: usize, axis: usize, largest: bool, indices: bool, out: &mut [f32]) {
    let (outer, size, inner) = split(xs, axis);
    assert_eq!(out.len(), outer * k * inner, "topk: out does not match its shape");
    assert!(size <= MAX_INDEXED, "topk: {size} positions are more than an f32 index holds");
    if k == 0 {
        return;
    }
    for o in 0..outer {
        for i in 0..inner {
            let value = |p: usize| x[(o * size + p) * inner + i];
            // `p` before `q` in the output: the greater first (NaN greatest) for
            // `largest`, else the smaller, the lower position on ties.
            let before = |p: usize, q: usize| {
                let (a, b) = (value(p), value(q));
                let by_value = match (a.is_nan(), b.is_nan()) {
                    (true, true) => Ordering::Equal,
                    (true, false) => Ordering::Greater,
                    (false, true) => Ordering::Less,
                    _ => a.partial_cmp(&b).unwrap_or(Ordering::Equal),
                };
                let by_value = if largest { by_value.reverse() } else { by_value };
                by_value.then(p.cmp(&q)) == Ordering::Less
            };
            let slot = |j: usize| (o * k + j) * inner + i;
            let mut heap = Heap { out: &mut *out, slot: &slot, before: &before };
            for j in 0..k {
                heap.set(j, j);
            }
            for j in (0..k / 2).rev() {
                heap.sift_down(j, k);
            }
            for p in k..size {
                if before(p, heap.get(0)) {
                    heap.set(0, p);
                    heap.sift_down(0, k);
                }
            }
            // Heap sort: the worst to the back, one at a time.
            for end in (1..k).rev() {
                let (top, last) = (heap.get(0), heap.get(end));
                heap.set(0, last);
                heap.set(end, top);
                heap.sift_down(0, end);
            }
            if !indices {
                for j in 0..k {
                    out[slot(j)] = value(out[slot(j)] as usize);
                }
            }
        }
    }
}

/// Most positions an index in an f32 names exactly (2^24).
pub const MAX_INDEXED: usize = 1 << 24;

/// A binary heap of positions (stored as f32 in strided `out` slots), the position that
/// comes last in the output on top.
struct Heap<'a, S: Fn(usize) -> usize, B: Fn(usize, usize) -> bool> {
    out: &'a mut [f32],
    slot: &'a S,
    before: &'a B,
}

impl<S: Fn(usize) -> usize, B: Fn(usize, usize) -> bool> Heap<'_, S, B> {
    fn get(&self, j: usize) -> usize {
        self.out[(self.slot)(j)] as usize
    }

    fn set(&mut self, j: usize, p: usize) {
        self.out[(self.slot)(j)] = p as f32;
    }

    /// Restores the heap below `j` among the first `len` entries.
    fn sift_down(&mut self, mut j: usize, len: usize) {
        loop {
            let (l, r) = (2 * j + 1, 2 * j + 2);
            let mut worst = j;
            if l < len && (self.before)(self.get(worst), self.get(l)) {
                worst = l;
            }
            if r < len && (self.before)(self.get(worst), self.get(r)) {
                worst = r;
            }
            if worst == j {
                return;
            }
            let (a, b) = (self.get(j), self.get(worst));
            self.set(j, b);
            self.set(worst, a);
            j = worst;
        }
    }
}

/// Checks a `gather` (`broadcast` false) or `take_along_dim` (true) of `x` at an index of
/// shape `index` along `axis` into `out`.
pub fn check_gather(x: &[usize], index: &[usize], axis: usize, broadcast: bool, out: &[usize]) -> Result<(), String> {
    if x.len() != index.len() || axis >= x.len() || out.len() != x.len() {
        return Err(format!("gather of {x:?} at an index {index:?} along {axis} into {out:?}"));
    }
    if x.len() > MAX_GATHER_RANK {
        return Err(format!("gather of {} axes, more than {MAX_GATHER_RANK}", x.len()));
    }
    for d in 0..x.len() {
        let ok = if d == axis {
            out[d] == index[d]
        } else if broadcast {
            (index[d] == out[d] || index[d] == 1) && (x[d] == out[d] || x[d] == 1)
        } else {
            index[d] == out[d] && index[d] <= x[d]
        };
        if !ok {
            return Err(format!("gather of {x:?} at an index {index:?} along {axis} into {out:?} (axis {d})"));
        }
    }
    Ok(())
}

/// Most axes a `gather` / `take_along_dim` kernel indexes (its position counters live on
/// the stack).
pub const MAX_GATHER_RANK: usize = 8;

/// `torch.gather` / `torch.take_along_dim`: `out[o] = x[o with axis `axis` replaced by
/// index[o]]`, where `x` and `index` are read at 0 along an axis of 1 that `out` has
/// larger (broadcasting) and at `o` along the others. Each index is checked first.
pub fn gather(
    x: (&[f32], &[usize]),
    index: (&[f32], &[usize]),
    axis: usize,
    out: &mut [f32],
    os: &[usize],
) -> Result<(), String> {
    let (x, xs) = x;
    let (idx, is) = index;
    assert_eq!(out.len(), os.iter().product::<usize>(), "gather: out does not match its shape");
    let rank = os.len();
    assert!(rank <= MAX_GATHER_RANK, "gather: {rank} axes");
    // Row-major strides, 0 on an axis of 1 (which every output position reads at 0).
    let strides = |s: &[usize]| {
        let mut st = [0usize; MAX_GATHER_RANK];
        let mut acc = 1;
        for d in (0..rank).rev() {
            st[d] = if s[d] == 1 { 0 } else { acc };
            acc *= s[d];
        }
        st
    };
    let (sx, si) = (strides(xs), strides(is));
    // Stride of `x` along `axis` whatever its size (an axis of 1 reads position 0 only).
    let ax_stride: usize = xs[axis + 1..].iter().product();
    let mut o_idx = [0usize; MAX_GATHER_RANK];
    for o in out.iter_mut() {
        let (mut xo, mut io) = (0, 0);
        for d in 0..rank {
            io += o_idx[d] * si[d];
            if d != axis {
                xo += o_idx[d] * sx[d];
            }
        }
        let p = position(idx[io], xs[axis], io, "index")?;
        *o = x[xo + p * ax_stride];
        for d in (0..rank).rev() {
            o_idx[d] += 1;
            if o_idx[d] < os[d] {
                break;
            }
            o_idx[d] = 0;
        }
    }
    Ok(())
}

/// Checks an `index_select` of `x` at a 1-D index of `n` positions along `axis` into
/// `out`.
pub fn check_index_select_at(x: &[usize], index: &[usize], axis: usize, out: &[usize]) -> Result<(), String> {
    if axis >= x.len() || index.len() != 1 {
        return Err(format!("index_select of {x:?} along {axis} at an index {index:?}"));
    }
    let mut want = x.to_vec();
    want[axis] = index[0];
    if want != out {
        return Err(format!("index_select of {x:?} along {axis} gives {want:?}, its output is {out:?}"));
    }
    Ok(())
}

/// `torch.index_select(x, axis, index)` at an index computed at run time: every position
/// checked first, then the slices copied as the baked `index_select` copies them.
pub fn index_select_at(x: &[f32], xs: &[usize], axis: usize, index: &[f32], out: &mut [f32]) -> Result<(), String> {
    let (outer, n, inner) = split(xs, axis);
    assert_eq!(out.len(), outer * index.len() * inner, "index_select: out does not match its shape");
    for (j, &v) in index.iter().enumerate() {
        position(v, n, j, "index")?;
    }
    if out.is_empty() {
        return Ok(());
    }
    let rows = out.chunks_exact_mut(inner.max(1));
    // Every index was checked above.
    let from = (0..outer).flat_map(|o| index.iter().map(move |&v| (o * n + v as usize) * inner));
    for (row, start) in rows.zip(from) {
        row.copy_from_slice(&x[start..start + inner]);
    }
    Ok(())
}

/// Checks a `one_hot` of `x` into `out`: `out` is `x` with an axis of `classes` more.
pub fn check_one_hot(x: &[usize], classes: usize, out: &[usize]) -> Result<(), String> {
    if classes == 0 {
        return Err("one_hot in 0 classes".into());
    }
    if out.len() != x.len() + 1 || out[..x.len()] != *x || out[x.len()] != classes {
        return Err(format!("one_hot of {x:?} in {classes} classes into {out:?}"));
    }
    Ok(())
}

/// `F.one_hot(x, classes)`: per value, a row of `classes` zeros with a 1 at the value,
/// each value checked first (an integer in `0..classes`).
pub fn one_hot(x: &[f32], classes: usize, out: &mut [f32]) -> Result<(), String> {
    assert_eq!(out.len(), x.len() * classes, "one_hot: out does not match its shape");
    out.fill(0.0);
    for (j, (&v, row)) in x.iter().zip(out.chunks_exact_mut(classes.max(1))).enumerate() {
        row[position(v, classes, j, "class")?] = 1.0;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::data;

    /// Row-major multi-index of `flat` in `shape`.
    fn unravel(mut flat: usize, shape: &[usize]) -> Vec<usize> {
        let mut idx = vec![0; shape.len()];
        for d in (0..shape.len()).rev() {
            idx[d] = flat % shape[d];
            flat /= shape[d];
        }
        idx
    }

    fn ravel(idx: &[usize], shape: &[usize]) -> usize {
        idx.iter().zip(shape).fold(0, |a, (&i, &n)| a * n + i)
    }

    #[test]
    fn argmax_and_argmin_take_the_first_extreme() {
        let xs = [3, 4, 5];
        let mut x = data(60, 1);
        // Ties: position 3 along axis 1 repeats position 1's value; position 1 must win.
        for o in 0..3 {
            for i in 0..5 {
                x[(o * 4 + 3) * 5 + i] = x[(o * 4 + 1) * 5 + i];
            }
        }
        for max in [true, false] {
            for axis in 0..3 {
                let mut out_shape = xs.to_vec();
                out_shape.remove(axis);
                let n: usize = out_shape.iter().product();
                let mut got = vec![-1.0; n];
                arg_reduce(max, &x, &xs, Some(axis), &mut got);
                for (f, &g) in got.iter().enumerate() {
                    let mut idx = unravel(f, &out_shape);
                    idx.insert(axis, 0);
                    let vals: Vec<f32> = (0..xs[axis])
                        .map(|j| {
                            idx[axis] = j;
                            x[ravel(&idx, &xs)]
                        })
                        .collect();
                    let ext = vals.iter().copied().fold(vals[0], |a, v| if max { a.max(v) } else { a.min(v) });
                    let want = vals.iter().position(|&v| v == ext).expect("present");
                    assert_eq!(g, want as f32, "max {max} axis {axis} at {f}");
                }
            }
        }
        let mut flat = [0.0];
        arg_reduce(true, &[1.0, 5.0, 5.0, 2.0], &[2, 2], None, &mut flat);
        assert_eq!(flat, [1.0]);
        arg_reduce(true, &[1.0, f32::NAN, 9.0, f32::NAN], &[4], None, &mut flat);
        assert_eq!(flat, [1.0], "the first NaN is the maximum");
        arg_reduce(false, &[1.0, 0.0, f32::NAN], &[3], None, &mut flat);
        assert_eq!(flat, [2.0], "NaN is the minimum too");
    }

    #[test]
    fn topk_matches_a_full_sort() {
        let xs = [2, 7, 3];
        let x = data(42, 2);
        for (k, largest) in [(3, true), (7, false), (1, true), (0, true)] {
            let mut vals = vec![0.0; 2 * k * 3];
            let mut idx = vec![0.0; 2 * k * 3];
            topk(&x, &xs, k, 1, largest, false, &mut vals);
            topk(&x, &xs, k, 1, largest, true, &mut idx);
            for o in 0..2 {
                for i in 0..3 {
                    let mut row: Vec<(f32, usize)> = (0..7).map(|j| (x[(o * 7 + j) * 3 + i], j)).collect();
                    // A stable sort keeps the lower position first on ties.
                    row.sort_by(|a, b| if largest { b.0.total_cmp(&a.0) } else { a.0.total_cmp(&b.0) });
                    for (j, &(v, p)) in row.iter().take(k).enumerate() {
                        let at = (o * k + j) * 3 + i;
                        assert_eq!((vals[at], idx[at]), (v, p as f32), "k {k} row {o},{i} #{j}");
                    }
                }
            }
        }
        // A long row of few distinct values (ties everywhere) and some NaNs.
        let mut long: Vec<f32> = data(301, 3).iter().map(|v| (v * 3.0).round()).collect();
        for j in [7, 150, 299] {
            long[j] = f32::NAN;
        }
        for k in [1, 2, 17, 100, 301] {
            for largest in [true, false] {
                let mut row: Vec<(f32, usize)> = long.iter().copied().zip(0..).collect();
                // NaN above every number; -0 and 0 equal, as comparisons have them.
                let nan_last = |a: f32, b: f32| {
                    a.is_nan().cmp(&b.is_nan()).then(a.partial_cmp(&b).unwrap_or(std::cmp::Ordering::Equal))
                };
                row.sort_by(|a, b| if largest { nan_last(b.0, a.0) } else { nan_last(a.0, b.0) });
                let (mut vals, mut idx) = (vec![0.0; k], vec![0.0; k]);
                topk(&long, &[301], k, 0, largest, false, &mut vals);
                topk(&long, &[301], k, 0, largest, true, &mut idx);
                for (j, &(v, p)) in row.iter().take(k).enumerate() {
                    assert_eq!(idx[j], p as f32, "k {k} largest {largest} #{j}");
                    assert!(vals[j].to_bits() == v.to_bits(), "k {k} largest {largest} #{j}: {} not {v}", vals[j]);
                }
            }
        }
        // Ties go to the lower position; NaN is the largest.
        let mut out = [0.0; 3];
        topk(&[2.0, 5.0, 5.0, f32::NAN], &[4], 3, 0, true, true, &mut out);
        assert_eq!(out, [3.0, 1.0, 2.0]);
        topk(&[2.0, 5.0, 5.0, 1.0], &[4], 3, 0, false, true, &mut out);
        assert_eq!(out, [3.0, 0.0, 1.0]);
    }

    /// `torch.gather` as its documentation writes it, with broadcasting for
    /// `take_along_dim`: `out[i][j][k] = x[i][index[i][j][k]][k]` along axis 1.
    fn naive_gather(x: &[f32], xs: &[usize], idx: &[f32], is: &[usize], axis: usize, os: &[usize]) -> Vec<f32> {
        (0..os.iter().product())
            .map(|f| {
                let o = unravel(f, os);
                let bi: Vec<usize> = o.iter().zip(is).map(|(&v, &n)| if n == 1 { 0 } else { v }).collect();
                let mut bx: Vec<usize> = o.iter().zip(xs).map(|(&v, &n)| if n == 1 { 0 } else { v }).collect();
                bx[axis] = idx[ravel(&bi, is)] as usize;
                x[ravel(&bx, xs)]
            })
            .collect()
    }

    #[test]
    fn gather_and_take_along_dim_match_the_definition() {
        let x = data(2 * 5 * 4, 3);
        let xs = [2, 5, 4];
        let cases: [(&[usize], &[usize], usize, bool); 5] = [
            (&[2, 3, 4], &[2, 3, 4], 1, false),
            (&[1, 6, 2], &[1, 6, 2], 1, false),
            (&[2, 5, 2], &[2, 5, 2], 2, false),
            (&[1, 3, 1], &[2, 3, 4], 1, true),
            (&[2, 1, 7], &[2, 5, 7], 2, true),
        ];
        for (k, (is, os, axis, broadcast)) in cases.into_iter().enumerate() {
            let n: usize = is.iter().product();
            let idx: Vec<f32> = (0..n).map(|i| ((i * 7 + k) % xs[axis]) as f32).collect();
            check_gather(&xs, is, axis, broadcast, os).expect("valid shapes");
            let want = naive_gather(&x, &xs, &idx, is, axis, os);
            let mut got = vec![f32::NAN; want.len()];
            gather((&x, &xs), (&idx, is), axis, &mut got, os).expect("indices in range");
            assert_eq!(got, want, "case {k}");
        }
        assert!(check_gather(&xs, &[2, 6, 4], 2, false, &[2, 6, 4]).is_err(), "axis 1 larger than the input's");
        assert!(check_gather(&xs, &[2, 3, 4], 1, false, &[2, 3, 5]).is_err());
    }

    #[test]
    fn a_bad_index_is_an_error() {
        let x = [1.0, 2.0, 3.0];
        let mut out = [0.0; 2];
        let e = gather((&x, &[3]), (&[1.0, 3.0], &[2]), 0, &mut out, &[2]).expect_err("3 is past the end");
        assert!(e.contains("index 3 (at flat position 1) is out of range for an axis of size 3"), "{e}");
        let e = gather((&x, &[3]), (&[0.5, 1.0], &[2]), 0, &mut out, &[2]).expect_err("not an integer");
        assert!(e.contains("0.5") && e.contains("not an integer"), "{e}");
        assert!(gather((&x, &[3]), (&[-1.0, 1.0], &[2]), 0, &mut out, &[2]).is_err(), "negative");
        assert!(gather((&x, &[3]), (&[f32::NAN, 1.0], &[2]), 0, &mut out, &[2]).is_err(), "NaN");
        assert!(index_select_at(&x, &[3], 0, &[2.0, 7.0], &mut out).is_err());
        assert!(one_hot(&[0.0, 3.0], 3, &mut [0.0; 6]).is_err(), "class 3 of 3");
        assert!(one_hot(&[0.0, 1.5], 3, &mut [0.0; 6]).is_err());
    }

    #[test]
    fn index_select_at_and_one_hot_match_the_definition() {
        let xs = [2, 5, 3];
        let x = data(30, 4);
        let index = [4.0, 0.0, 4.0, 2.0];
        let mut got = vec![0.0; 2 * 4 * 3];
        index_select_at(&x, &xs, 1, &index, &mut got).expect("in range");
        for o in 0..2 {
            for (j, &p) in index.iter().enumerate() {
                for i in 0..3 {
                    assert_eq!(got[(o * 4 + j) * 3 + i], x[(o * 5 + p as usize) * 3 + i]);
                }
            }
        }
        let mut oh = vec![9.0; 4 * 5];
        one_hot(&index, 5, &mut oh).expect("in range");
        for (j, &p) in index.iter().enumerate() {
            for c in 0..5 {
                assert_eq!(oh[j * 5 + c], if c == p as usize { 1.0 } else { 0.0 });
            }
        }
    }
}
