//! Indexing, selection, casts and constant fills: `index_select` with its indices in the
//! step (`readi_plan::ops::IndexSelect`), `where`, casts and the `arange` / `full`
//! generators the compiler folds constants with.
//!
//! Every value is an f32: an integer one is exact (the compiler keeps indices below
//! 2^24), a bool one 0 or 1.

use readi_plan::DType;

use super::elementwise::broadcast_strides;

/// Checks an `index_select` of `index` (`index_len` positions, each checked at plan load
/// against the axis) along `axis` of `x` into `out`.
pub fn check_index_select(
    x: &[usize],
    axis: usize,
    index: &[i64],
    index_shape: &[usize],
    out: &[usize],
) -> Result<(), String> {
    if axis >= x.len() {
        return Err(format!("index_select along axis {axis} of {x:?}"));
    }
    if let Some(&v) = index.iter().find(|&&v| v < 0 || v as usize >= x[axis]) {
        return Err(format!("index {v} is out of range for axis {axis} of {x:?}"));
    }
    if index_shape.iter().product::<usize>() != index.len() {
        return Err(format!("{} indices for an index of shape {index_shape:?}", index.len()));
    }
    let mut want = x[..axis].to_vec();
    want.extend_from_slice(index_shape);
    want.extend_from_slice(&x[axis + 1..]);
    if want != out {
        return Err(format!("index_select of {x:?} along {axis} gives {want:?}, its output is {out:?}"));
    }
    Ok(())
}

/// `numpy.take(x, index, axis)`: for every outer position, the rows `index[j]` of axis
/// `axis` (each `inner` values long, copied whole) one after the other.
pub fn index_select(x: &[f32], xs: &[usize], axis: usize, index: &[i64], out: &mut [f32]) {
    let outer: usize = xs[..axis].iter().product();
    let inner: usize = xs[axis + 1..].iter().product();
    let n = xs[axis];
    assert_eq!(out.len(), outer * index.len() * inner, "index_select: out does not match its shape");
    if out.is_empty() {
        return;
    }
    let rows = out.chunks_exact_mut(inner.max(1));
    let from = (0..outer).flat_map(|o| index.iter().map(move |&i| (o * n + i as usize) * inner));
    for (row, start) in rows.zip(from) {
        row.copy_from_slice(&x[start..start + inner]);
    }
}

/// Checks a `where` of a condition, two branches and an output of these shapes: each
/// input broadcasts to the output.
pub fn check_where(c: &[usize], a: &[usize], b: &[usize], out: &[usize]) -> Result<(), String> {
    for s in [c, a, b] {
        let ok = s.len() <= out.len() && s.iter().zip(&out[out.len() - s.len()..]).all(|(&d, &o)| d == o || d == 1);
        if !ok {
            return Err(format!("where: {s:?} does not broadcast to {out:?}"));
        }
    }
    Ok(())
}

/// `torch.where(c, a, b)` with broadcasting: `a` where `c` is non-zero, else `b`. Rows of
/// the last axis run as a plain select loop when no input broadcasts along it.
pub fn where_select(
    c: (&[f32], &[usize]),
    a: (&[f32], &[usize]),
    b: (&[f32], &[usize]),
    out: &mut [f32],
    os: &[usize],
) {
    assert_eq!(out.len(), os.iter().product::<usize>(), "where: out does not match its shape");
    if out.is_empty() {
        return;
    }
    if os.is_empty() {
        out[0] = if c.0[0] != 0.0 { a.0[0] } else { b.0[0] };
        return;
    }
    let r = os.len();
    let (sc, sa, sb) = (broadcast_strides(c.1, os), broadcast_strides(a.1, os), broadcast_strides(b.1, os));
    let w = os[r - 1];
    let mut idx = vec![0usize; r - 1];
    for row in out.chunks_mut(w) {
        let at = |st: &[usize]| (0..r - 1).map(|k| idx[k] * st[k]).sum::<usize>();
        let (oc, oa, ob) = (at(&sc), at(&sa), at(&sb));
        let (lc, la, lb) = (sc[r - 1], sa[r - 1], sb[r - 1]);
        if lc == 1 && la == 1 && lb == 1 {
            let (cr, ar, br) = (&c.0[oc..oc + w], &a.0[oa..oa + w], &b.0[ob..ob + w]);
            for (((o, &cv), &av), &bv) in row.iter_mut().zip(cr).zip(ar).zip(br) {
                *o = if cv != 0.0 { av } else { bv };
            }
        } else {
            for (j, o) in row.iter_mut().enumerate() {
                *o = if c.0[oc + j * lc] != 0.0 { a.0[oa + j * la] } else { b.0[ob + j * lb] };
            }
        }
        for k in (0..r - 1).rev() {
            idx[k] += 1;
            if idx[k] < os[k] {
                break;
            }
            idx[k] = 0;
        }
    }
}

/// A cast to `to`: to f32 a copy, to i64 rounded towards zero, to bool whether non-zero
/// (1 or 0).
pub fn cast(to: DType, x: &[f32], out: &mut [f32]) {
    assert_eq!(x.len(), out.len(), "cast: x and out differ in length");
    match to {
        DType::I64 | DType::I32 => out.iter_mut().zip(x).for_each(|(o, &v)| *o = v.trunc()),
        DType::Bool => out.iter_mut().zip(x).for_each(|(o, &v)| *o = if v != 0.0 { 1.0 } else { 0.0 }),
        _ => out.copy_from_slice(x),
    }
}

/// `start + i * step` at flat position `i`, computed in f64 as `torch.arange` does for
/// integer steps (every value exact).
pub fn fill(start: f64, step: f64, out: &mut [f32]) {
    for (i, o) in out.iter_mut().enumerate() {
        *o = (start + i as f64 * step) as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::data;

    #[test]
    fn index_select_matches_a_naive_loop() {
        // (shape, axis, index): Swin's table lookup, a middle axis, an empty index.
        let cases: [(&[usize], usize, Vec<i64>); 4] = [
            (&[169, 3], 0, (0..2401).map(|i| (i * 7 % 169) as i64).collect()),
            (&[2, 5, 4], 1, vec![4, 0, 0, 2, 1, 3]),
            (&[3, 6], 1, vec![5]),
            (&[7, 2], 0, vec![]),
        ];
        for (k, (xs, axis, index)) in cases.into_iter().enumerate() {
            let x = data(xs.iter().product(), k as u64);
            let outer: usize = xs[..axis].iter().product();
            let inner: usize = xs[axis + 1..].iter().product();
            let mut want = Vec::new();
            for o in 0..outer {
                for &i in &index {
                    for e in 0..inner {
                        want.push(x[(o * xs[axis] + i as usize) * inner + e]);
                    }
                }
            }
            let mut os = xs[..axis].to_vec();
            os.push(index.len());
            os.extend_from_slice(&xs[axis + 1..]);
            assert_eq!(check_index_select(xs, axis, &index, &[index.len()], &os), Ok(()));
            let mut got = vec![f32::NAN; want.len()];
            index_select(&x, xs, axis, &index, &mut got);
            assert_eq!(got, want, "case {k}");
        }
    }

    #[test]
    fn index_select_checks_refuse_bad_indices() {
        assert!(check_index_select(&[4, 2], 0, &[4], &[1], &[1, 2]).is_err());
        assert!(check_index_select(&[4, 2], 0, &[-1], &[1], &[1, 2]).is_err());
        assert!(check_index_select(&[4, 2], 2, &[0], &[1], &[1, 2]).is_err());
        assert!(check_index_select(&[4, 2], 0, &[0], &[1], &[2, 2]).is_err());
    }

    #[test]
    fn where_matches_a_naive_loop() {
        // (condition, a, b, out): same shapes, a row condition, a column branch, scalars.
        type Shapes<'a> = (&'a [usize], &'a [usize], &'a [usize], &'a [usize]);
        let cases: [Shapes; 4] = [
            (&[3, 4], &[3, 4], &[3, 4], &[3, 4]),
            (&[2, 1, 5], &[4, 5], &[1], &[2, 4, 5]),
            (&[4, 5], &[4, 1], &[5], &[4, 5]),
            (&[], &[], &[], &[]),
        ];
        for (k, (cs, as_, bs, os)) in cases.into_iter().enumerate() {
            let cond: Vec<f32> = data(cs.iter().product(), k as u64).iter().map(|v| (*v > 0.0) as u8 as f32).collect();
            let a = data(as_.iter().product(), 10 + k as u64);
            let b = data(bs.iter().product(), 20 + k as u64);
            let n: usize = os.iter().product();
            // Naive: the flat output position to each input's position by its own strides.
            let at = |s: &[usize], mut flat: usize| {
                let mut pos = 0;
                let mut stride = 1;
                for a in (0..os.len()).rev() {
                    let i = flat % os[a];
                    flat /= os[a];
                    if let Some(off) = (a + s.len()).checked_sub(os.len()) {
                        if s[off] != 1 {
                            pos += i * stride;
                        }
                        stride *= s[off];
                    }
                }
                pos
            };
            let want: Vec<f32> =
                (0..n).map(|i| if cond[at(cs, i)] != 0.0 { a[at(as_, i)] } else { b[at(bs, i)] }).collect();
            assert_eq!(check_where(cs, as_, bs, os), Ok(()));
            let mut got = vec![f32::NAN; n];
            where_select((&cond, cs), (&a, as_), (&b, bs), &mut got, os);
            assert_eq!(got, want, "case {k}");
        }
        assert!(check_where(&[3], &[4], &[4], &[4]).is_err());
    }

    #[test]
    fn casts_and_fills() {
        let x = [-1.5f32, 0.0, 2.7, -0.0];
        let mut out = [0.0f32; 4];
        cast(DType::I64, &x, &mut out);
        assert_eq!(out, [-1.0, 0.0, 2.0, -0.0]);
        cast(DType::Bool, &x, &mut out);
        assert_eq!(out, [1.0, 0.0, 1.0, 0.0]);
        cast(DType::F32, &x, &mut out);
        assert_eq!(out, x);
        let mut a = [0.0f32; 5];
        fill(3.0, -2.0, &mut a);
        assert_eq!(a, [3.0, 1.0, -1.0, -3.0, -5.0]);
    }
}
