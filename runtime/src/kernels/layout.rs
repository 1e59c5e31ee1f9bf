//! Data movement: axis permutation and concatenation, row-major; the 16x16 transpose in
//! AVX-512 registers that the permutes and the depthwise lanes path share.

#[cfg(target_arch = "x86_64")]
use core::arch::x86_64::__m512;

#[cfg(target_arch = "x86_64")]
use pulp::x86::V4;
use rayon::prelude::*;

/// Below this many elements a kernel runs on the calling thread.
const PAR_MIN: usize = 1 << 15;
/// Elements per parallel task, roughly.
const CHUNK: usize = 1 << 14;
/// Output rows a transposition fills together.
const TB: usize = 16;

/// Writes `x` (row-major, `shape`) with its axes permuted to `out`: output axis `i` is
/// input axis `perm[i]`, so `out` has shape `[shape[perm[0]], shape[perm[1]], ...]`.
///
/// Size-1 axes are dropped and axes that stay neighbours are merged first. What remains
/// is copied as whole rows when the last axis stays last (`[N,T,H,D] -> [N,H,T,D]`), 16
/// output rows at a time when the last two axes swap (`[B,M,N] -> [B,N,M]`, and
/// `NCHW <-> NHWC`, which merges to that) so each column reads 16 contiguous inputs, and
/// element by element otherwise (a strided gather: slow, and rare in practice).
pub fn permute(x: &[f32], shape: &[usize], perm: &[usize], out: &mut [f32]) {
    assert_eq!(x.len(), shape.iter().product::<usize>(), "permute: x does not match its shape");
    assert_eq!(out.len(), x.len(), "permute: out and x differ in length");
    assert_eq!(perm.len(), shape.len(), "permute: perm and shape differ in rank");
    let mut seen = vec![false; perm.len()];
    for &p in perm {
        assert!(p < perm.len() && !seen[p], "permute: {perm:?} is not a permutation");
        seen[p] = true;
    }
    if x.is_empty() {
        return;
    }
    let v = Permuted::new(shape, perm);
    let r = v.dims.len();
    let n = v.dims[r - 1];
    let sl = v.strides[r - 1];
    // Fills output rows (of length `n`) `first..` of `out`.
    let run = |first: usize, out: &mut [f32]| {
        if sl == 1 {
            for (o, b) in out.chunks_mut(n).zip(v.row_offsets(first)) {
                o.copy_from_slice(&x[b..b + n]);
            }
        } else if r >= 2 && v.strides[r - 2] == 1 {
            #[cfg(target_arch = "x86_64")]
            if let Some(simd) = V4::try_new() {
                // Compiled with AVX-512 enabled: everything it calls is inlined into it.
                return simd.vectorize(
                    #[inline(always)]
                    || swap_last_two(x, &v, first, out, Tiles16(simd)),
                );
            }
            swap_last_two(x, &v, first, out, NoTiles);
        } else {
            for (o, b) in out.chunks_mut(n).zip(v.row_offsets(first)) {
                for (j, o) in o.iter_mut().enumerate() {
                    *o = x[b + j * sl];
                }
            }
        }
    };
    let rows_per_task = (CHUNK / n).max(1).next_multiple_of(TB);
    if out.len() >= PAR_MIN && out.len() > rows_per_task * n {
        out.par_chunks_mut(rows_per_task * n).enumerate().for_each(|(t, o)| run(t * rows_per_task, o));
    } else {
        run(0, out);
    }
}

/// Output rows `first..` of a permutation whose last two axes swap (the output's last
/// axis has input stride `sl`, the one before it stride 1): up to [`TB`] output rows that
/// neighbour along that axis together, each column a short contiguous read. `tiles`
/// fills whole 16x16 blocks of a group of sixteen rows first where it can.
#[inline(always)]
fn swap_last_two(x: &[f32], v: &Permuted, first: usize, out: &mut [f32], tiles: impl ColumnTiles) {
    let r = v.dims.len();
    let (n, sl, m) = (v.dims[r - 1], v.strides[r - 1], v.dims[r - 2]);
    let rows = out.len() / n;
    let mut i = 0;
    while i < rows {
        let g = first + i;
        let k = TB.min(m - g % m).min(rows - i);
        let b = v.row_offset(g);
        let group = &mut out[i * n..(i + k) * n];
        let done = if k == TB { tiles.fill(x, b, sl, group, n) } else { 0 };
        for j in done..n {
            for (kk, &val) in x[b + j * sl..b + j * sl + k].iter().enumerate() {
                group[kk * n + j] = val;
            }
        }
        i += k;
    }
}

/// How [`swap_last_two`] fills the columns of a group of sixteen output rows before its
/// scalar loop takes the rest.
trait ColumnTiles: Copy {
    /// Fills columns `0..c` of `group` (sixteen rows of `n`; column `j` from the sixteen
    /// inputs at `b + j sl`) and returns `c`.
    fn fill(self, x: &[f32], b: usize, sl: usize, group: &mut [f32], n: usize) -> usize;
}

/// No SIMD: the scalar loop does every column.
#[derive(Clone, Copy)]
struct NoTiles;

impl ColumnTiles for NoTiles {
    #[inline(always)]
    fn fill(self, _: &[f32], _: usize, _: usize, _: &mut [f32], _: usize) -> usize {
        0
    }
}

/// AVX-512: sixteen columns at a time, sixteen vector loads (one per column, sixteen
/// rows' values), a [`transpose16`], sixteen vector stores (one per row). The scalar loop
/// stores one float at a time, `n` apart: ConvNeXt-T's permutes around its layer norms
/// took 0.45-0.6x its time with the tiles (0.15 to 0.07 ms each on its 56x56 stage; its 41
/// permutes 2.9 to 1.5 ms a run at one thread, 2.7 to 1.3 at two; the model 0.984x and
/// 0.974x; Swin-T's patch-embedding permute 0.67x; the two paths alternating run by run in
/// one process, 2026-12-06).
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct Tiles16(V4);

#[cfg(target_arch = "x86_64")]
impl ColumnTiles for Tiles16 {
    #[inline(always)]
    fn fill(self, x: &[f32], b: usize, sl: usize, group: &mut [f32], n: usize) -> usize {
        use pulp::{Simd, cast};
        let simd = self.0;
        let whole = n / TB * TB;
        let mut j = 0;
        while j < whole {
            let mut rows: [__m512; TB] = [cast(simd.splat_f32s(0.0)); TB];
            for (c, row) in rows.iter_mut().enumerate() {
                *row = cast(V4::as_simd_f32s(&x[b + (j + c) * sl..][..TB]).0[0]);
            }
            let t = transpose16(simd, rows);
            for (kk, v) in t.into_iter().enumerate() {
                V4::as_mut_simd_f32s(&mut group[kk * n + j..][..TB]).0[0] = cast(v);
            }
            j += TB;
        }
        whole
    }
}

/// The transpose of a 16x16 block held as sixteen row vectors: unpacks of pairs of rows,
/// then shuffles of 64-bit pairs, then two rounds of 128-bit lane shuffles.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn transpose16(simd: V4, r: [__m512; 16]) -> [__m512; 16] {
    const L: usize = 16;
    // Loops over arrays rather than `array::from_fn`: its closures were compiled apart
    // from the AVX-512 function, each intrinsic a call.
    let f = simd.avx512f;
    let mut t = r;
    for i in 0..L / 2 {
        t[2 * i] = f._mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = f._mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    // u[4k + j]: rows 4k..4k + 4, column pairs.
    let mut u = t;
    for k in 0..L / 4 {
        u[4 * k] = f._mm512_shuffle_ps::<0x44>(t[4 * k], t[4 * k + 2]);
        u[4 * k + 1] = f._mm512_shuffle_ps::<0xEE>(t[4 * k], t[4 * k + 2]);
        u[4 * k + 2] = f._mm512_shuffle_ps::<0x44>(t[4 * k + 1], t[4 * k + 3]);
        u[4 * k + 3] = f._mm512_shuffle_ps::<0xEE>(t[4 * k + 1], t[4 * k + 3]);
    }
    let mut v = u;
    for half in 0..2 {
        for j in 0..4 {
            let (a, b) = (u[8 * half + j], u[8 * half + 4 + j]);
            v[8 * half + j] = f._mm512_shuffle_f32x4::<0x88>(a, b);
            v[8 * half + 4 + j] = f._mm512_shuffle_f32x4::<0xDD>(a, b);
        }
    }
    let mut w = v;
    for i in 0..L / 2 {
        w[i] = f._mm512_shuffle_f32x4::<0x88>(v[i], v[8 + i]);
        w[8 + i] = f._mm512_shuffle_f32x4::<0xDD>(v[i], v[8 + i]);
    }
    w
}

/// A permutation reduced to the fewest output axes, each with its input stride.
struct Permuted {
    dims: Vec<usize>,
    strides: Vec<usize>,
}

impl Permuted {
    fn new(shape: &[usize], perm: &[usize]) -> Permuted {
        let mut in_strides = vec![1; shape.len()];
        for a in (0..shape.len().saturating_sub(1)).rev() {
            in_strides[a] = in_strides[a + 1] * shape[a + 1];
        }
        let (mut dims, mut strides): (Vec<usize>, Vec<usize>) = (Vec::new(), Vec::new());
        for &a in perm {
            let (d, s) = (shape[a], in_strides[a]);
            if d == 1 {
                continue;
            }
            // The previous output axis merges with this one if it is this one's outer
            // neighbour in the input too.
            match (dims.last_mut(), strides.last_mut()) {
                (Some(pd), Some(ps)) if *ps == s * d => {
                    *pd *= d;
                    *ps = s;
                }
                _ => {
                    dims.push(d);
                    strides.push(s);
                }
            }
        }
        if dims.is_empty() {
            dims.push(1);
            strides.push(1);
        }
        Permuted { dims, strides }
    }

    /// Input offsets of the first elements of output rows `first`, `first + 1`, ...: one
    /// [`Permuted::row_offset`], then an odometer over the outer axes. A division and a
    /// remainder per axis per row cost about what copying a short row does: Swin-T's
    /// permutes (rows of 32 floats in its attention) took 0.89x their time with the
    /// odometer, 2.48 to 2.20 ms a run at one thread, 1.77 to 1.57 at two (the two
    /// alternating run by run in one process, 2026-12-06).
    fn row_offsets(&self, first: usize) -> RowOffsets<'_> {
        let outer = self.dims.len() - 1;
        let mut idx = vec![0; outer];
        let mut row = first;
        for a in (0..outer).rev() {
            idx[a] = row % self.dims[a];
            row /= self.dims[a];
        }
        RowOffsets { v: self, idx, off: self.row_offset(first) }
    }

    /// Input offset of the first element of output row `row` (rows run along the last axis).
    fn row_offset(&self, mut row: usize) -> usize {
        let mut off = 0;
        for (&d, &s) in self.dims.iter().zip(&self.strides).rev().skip(1) {
            off += (row % d) * s;
            row /= d;
        }
        off
    }
}

/// [`Permuted::row_offsets`]: the output's outer indices and the current row's offset.
struct RowOffsets<'a> {
    v: &'a Permuted,
    idx: Vec<usize>,
    off: usize,
}

impl Iterator for RowOffsets<'_> {
    type Item = usize;

    fn next(&mut self) -> Option<usize> {
        let current = self.off;
        for (a, i) in self.idx.iter_mut().enumerate().rev() {
            *i += 1;
            self.off += self.v.strides[a];
            if *i < self.v.dims[a] {
                break;
            }
            *i = 0;
            self.off -= self.v.dims[a] * self.v.strides[a];
        }
        Some(current)
    }
}

/// Splits `src` into its even elements, written to `out` from `even_at`, and its odd ones,
/// from `odd_at` (two runs that must not overlap): a strided row's columns by phase, so
/// that a stride-2 window's taps are contiguous loads. A loop per phase: one loop writing
/// both stays scalar. The stride-2 depthwise and direct convs' padded copy
/// (`conv::pad_phases`) and the stride-2 pooling rows use it.
#[inline(always)]
pub(crate) fn split_phases(src: &[f32], out: &mut [f32], even_at: usize, odd_at: usize) {
    let n = src.len();
    for (d, pair) in out[even_at..][..n / 2].iter_mut().zip(src.chunks_exact(2)) {
        *d = pair[0];
    }
    for (d, pair) in out[odd_at..][..n / 2].iter_mut().zip(src.chunks_exact(2)) {
        *d = pair[1];
    }
    if n % 2 == 1 {
        out[even_at + n / 2] = src[n - 1];
    }
}

/// Concatenates `inputs` (each `(data, shape)`, row-major) along `axis` into `out`.
///
/// All inputs have the same rank and the same sizes except along `axis`; `out` has their
/// shape with `axis` the sum of theirs. Each input contributes one contiguous block per
/// index of the axes before `axis`.
pub fn concat(inputs: &[(&[f32], &[usize])], axis: usize, out: &mut [f32]) {
    let Some(&(_, first)) = inputs.first() else {
        assert!(out.is_empty(), "concat: no inputs for a non-empty output");
        return;
    };
    assert!(axis < first.len(), "concat: axis {axis} out of range for rank {}", first.len());
    let outer: usize = first[..axis].iter().product();
    let inner: usize = first[axis + 1..].iter().product();
    for (d, s) in inputs {
        assert_eq!(d.len(), s.iter().product::<usize>(), "concat: an input does not match its shape");
        assert!(
            s.len() == first.len() && (0..s.len()).all(|a| a == axis || s[a] == first[a]),
            "concat: {s:?} and {first:?} differ off axis {axis}"
        );
    }
    let row: usize = inputs.iter().map(|(_, s)| s[axis] * inner).sum();
    assert_eq!(out.len(), outer * row, "concat: out does not match the concatenated shape");
    if out.is_empty() {
        return;
    }
    let fill = |o: usize, dst: &mut [f32]| {
        let mut at = 0;
        for (d, s) in inputs {
            let n = s[axis] * inner;
            dst[at..at + n].copy_from_slice(&d[o * n..(o + 1) * n]);
            at += n;
        }
    };
    if out.len() < PAR_MIN {
        out.chunks_mut(row).enumerate().for_each(|(o, dst)| fill(o, dst));
    } else if outer > 1 {
        let min_rows = (CHUNK / row).max(1);
        out.par_chunks_mut(row).enumerate().with_min_len(min_rows).for_each(|(o, dst)| fill(o, dst));
    } else {
        // One big block per input: split each copy instead.
        let mut at = 0;
        for (d, _) in inputs {
            out[at..at + d.len()]
                .par_chunks_mut(CHUNK)
                .zip(d.par_chunks(CHUNK))
                .for_each(|(o, s)| o.copy_from_slice(s));
            at += d.len();
        }
    }
}

/// The preconditions of [`permute`]: `perm` is a permutation of `x`'s axes and `out` is
/// `x` permuted.
pub fn check_permute(x: &[usize], perm: &[usize], out: &[usize]) -> Result<(), String> {
    let mut seen = vec![false; x.len()];
    let ok = perm.len() == x.len()
        && perm.iter().all(|&p| p < x.len() && !std::mem::replace(&mut seen[p], true))
        && out.len() == x.len()
        && perm.iter().zip(out).all(|(&p, &o)| x[p] == o);
    if !ok {
        return Err(format!("permute {perm:?} of {x:?} cannot give {out:?}"));
    }
    Ok(())
}

/// The preconditions of [`concat`] along `axis`: at least one input, all of the output's
/// rank, equal to it off `axis`, their sizes along `axis` summing to its.
pub fn check_concat(inputs: &[&[usize]], axis: usize, out: &[usize]) -> Result<(), String> {
    if inputs.is_empty() || axis >= out.len() {
        return Err(format!("concat of {} inputs along axis {axis} into {out:?}", inputs.len()));
    }
    let mut along = 0usize;
    for s in inputs {
        if s.len() != out.len() || (0..s.len()).any(|a| a != axis && s[a] != out[a]) {
            return Err(format!("concat input {s:?} differs from the output {out:?} off axis {axis}"));
        }
        along = along.checked_add(s[axis]).ok_or("concat: the axis overflows")?;
    }
    if along != out[axis] {
        return Err(format!("concat inputs sum to {along} along axis {axis}, the output has {}", out[axis]));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::data;

    /// For each output multi-index, reads the input at the index with axes put back.
    fn naive_permute(x: &[f32], shape: &[usize], perm: &[usize]) -> Vec<f32> {
        let out_shape: Vec<usize> = perm.iter().map(|&p| shape[p]).collect();
        (0..x.len())
            .map(|flat| {
                let mut oi = vec![0; perm.len()];
                let mut r = flat;
                for a in (0..perm.len()).rev() {
                    oi[a] = r % out_shape[a];
                    r /= out_shape[a];
                }
                let mut ii = vec![0; perm.len()];
                for (a, &p) in perm.iter().enumerate() {
                    ii[p] = oi[a];
                }
                x[ii.iter().zip(shape).fold(0, |o, (&i, &n)| o * n + i)]
            })
            .collect()
    }

    fn check_permute(shape: &[usize], perm: &[usize]) {
        let x = data(shape.iter().product(), shape.len() as u64);
        let mut got = vec![f32::NAN; x.len()];
        permute(&x, shape, perm, &mut got);
        assert_eq!(got, naive_permute(&x, shape, perm), "{shape:?} {perm:?}");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn transpose16_is_the_transpose() {
        use pulp::{Simd, cast};
        const L: usize = 16;
        let Some(simd) = V4::try_new() else { return };
        let m: Vec<f32> = (0..L * L).map(|i| i as f32).collect();
        let rows: [__m512; L] = std::array::from_fn(|i| cast(simd.partial_load_f32s(&m[i * L..][..L])));
        let t = transpose16(simd, rows);
        let mut got = vec![0.0f32; L * L];
        for (i, v) in t.into_iter().enumerate() {
            simd.partial_store_f32s(&mut got[i * L..][..L], cast(v));
        }
        for i in 0..L {
            for j in 0..L {
                assert_eq!(got[i * L + j], m[j * L + i], "({i}, {j})");
            }
        }
    }

    #[test]
    fn permute_common_transposes() {
        check_permute(&[2, 5, 3, 4], &[0, 2, 1, 3]);
        check_permute(&[3, 17, 19], &[0, 2, 1]);
        check_permute(&[17, 33], &[1, 0]);
        check_permute(&[2, 3, 5, 7], &[0, 2, 3, 1]);
        check_permute(&[2, 5, 7, 3], &[0, 3, 1, 2]);
        check_permute(&[2, 3, 4, 5], &[0, 1, 3, 2]);
    }

    #[test]
    fn permute_generic_and_degenerate() {
        check_permute(&[3, 4, 5], &[2, 0, 1]);
        check_permute(&[3, 4, 5], &[1, 2, 0]);
        check_permute(&[2, 3, 4, 5], &[3, 1, 0, 2]);
        check_permute(&[2, 3, 2, 3, 2], &[4, 2, 0, 3, 1]);
        check_permute(&[2, 3, 4], &[0, 1, 2]);
        check_permute(&[1, 5, 1, 3], &[2, 3, 0, 1]);
        check_permute(&[1, 1], &[1, 0]);
        check_permute(&[6], &[0]);
        check_permute(&[], &[]);
        let mut out: [f32; 0] = [];
        permute(&[], &[3, 0], &[1, 0], &mut out);
    }

    #[test]
    fn permute_large_runs_in_parallel_and_matches() {
        check_permute(&[2, 197, 12, 64], &[0, 2, 1, 3]);
        check_permute(&[3, 300, 129], &[0, 2, 1]);
        check_permute(&[1, 64, 40, 41], &[0, 2, 3, 1]);
        check_permute(&[40, 50, 30], &[2, 0, 1]);
    }

    /// For each output multi-index, finds the input whose range along `axis` holds it.
    fn naive_concat(inputs: &[(Vec<f32>, Vec<usize>)], axis: usize) -> Vec<f32> {
        let mut shape = inputs[0].1.clone();
        shape[axis] = inputs.iter().map(|(_, s)| s[axis]).sum();
        let len: usize = shape.iter().product();
        (0..len)
            .map(|flat| {
                let mut idx = vec![0; shape.len()];
                let mut r = flat;
                for a in (0..shape.len()).rev() {
                    idx[a] = r % shape[a];
                    r /= shape[a];
                }
                let (mut k, mut at) = (0, idx[axis]);
                while at >= inputs[k].1[axis] {
                    at -= inputs[k].1[axis];
                    k += 1;
                }
                idx[axis] = at;
                let s = &inputs[k].1;
                inputs[k].0[idx.iter().zip(s).fold(0, |o, (&i, &n)| o * n + i)]
            })
            .collect()
    }

    fn check_concat(shapes: &[&[usize]], axis: usize) {
        let inputs: Vec<(Vec<f32>, Vec<usize>)> =
            shapes.iter().enumerate().map(|(i, s)| (data(s.iter().product(), i as u64 + 1), s.to_vec())).collect();
        let refs: Vec<(&[f32], &[usize])> = inputs.iter().map(|(d, s)| (&d[..], &s[..])).collect();
        let want = naive_concat(&inputs, axis);
        let mut got = vec![f32::NAN; want.len()];
        concat(&refs, axis, &mut got);
        assert_eq!(got, want, "{shapes:?} axis {axis}");
    }

    #[test]
    fn concat_along_first_middle_last() {
        check_concat(&[&[2, 3, 4], &[1, 3, 4], &[3, 3, 4]], 0);
        check_concat(&[&[2, 3, 4], &[2, 1, 4], &[2, 5, 4]], 1);
        check_concat(&[&[2, 3, 4], &[2, 3, 1], &[2, 3, 2]], 2);
        check_concat(&[&[2, 3, 4], &[2, 0, 4], &[2, 2, 4]], 1);
        check_concat(&[&[5]], 0);
        check_concat(&[&[1, 2], &[1, 2]], 1);
    }

    #[test]
    fn concat_large_runs_in_parallel_and_matches() {
        check_concat(&[&[2, 64, 30, 30], &[2, 32, 30, 30]], 1);
        check_concat(&[&[40000], &[30000]], 0);
        check_concat(&[&[1, 5000, 3], &[1, 7000, 3]], 1);
    }
}
