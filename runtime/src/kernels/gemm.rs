//! Single-precision matrix product, a checked safe wrapper over the `gemm` crate.
//!
//! This is the one module of the runtime kernels allowed `unsafe` throughout (elsewhere one
//! statement is: the depthwise register block's vector read, `conv/depthwise.rs`, after a
//! bound check per block): the `gemm` crate takes raw pointers and strides. [`sgemm`] first proves, with explicit checks, that every
//! element the product can touch lies inside its slice and that no two destination
//! elements share memory; only then does it call the crate.
//!
//! It also holds the register micro-kernel of the products written here, which reads its
//! rows unchecked after cutting each to the loop's length: [`rows_product`] for rows that
//! lie anywhere (linear layers in panels, `panel.rs`), [`strided_rows_product`] for rows a
//! stride apart in one slice (the register tiles of small 1x1 and 7x7 im2col layers,
//! `conv/pointwise.rs`; both projections of a conv's bottleneck adapter,
//! `conv/adapter.rs`).

#![allow(unsafe_code)]

use gemm::Parallelism;

/// A read-only strided view of a `rows × cols` matrix: element `(i, j)` is
/// `data[i * row_stride + j * col_stride]`.
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a> {
    /// Backing storage; must hold every element of the view.
    pub data: &'a [f32],
    /// Number of rows.
    pub rows: usize,
    /// Number of columns.
    pub cols: usize,
    /// Distance between consecutive rows, in elements.
    pub row_stride: usize,
    /// Distance between consecutive columns, in elements.
    pub col_stride: usize,
}

/// A writable strided view of a `rows × cols` matrix; same indexing as [`MatRef`]. Distinct
/// elements must not share memory (checked by [`sgemm`]).
#[derive(Debug)]
pub struct MatMut<'a> {
    /// Backing storage; must hold every element of the view.
    pub data: &'a mut [f32],
    /// Number of rows.
    pub rows: usize,
    /// Number of columns.
    pub cols: usize,
    /// Distance between consecutive rows, in elements.
    pub row_stride: usize,
    /// Distance between consecutive columns, in elements.
    pub col_stride: usize,
}

impl<'a> MatRef<'a> {
    /// A dense row-major `rows × cols` matrix at the start of `data`.
    pub fn row_major(data: &'a [f32], rows: usize, cols: usize) -> Self {
        MatRef { data, rows, cols, row_stride: cols, col_stride: 1 }
    }

    /// A dense column-major `rows × cols` matrix at the start of `data`.
    pub fn col_major(data: &'a [f32], rows: usize, cols: usize) -> Self {
        MatRef { data, rows, cols, row_stride: 1, col_stride: rows }
    }

    /// The transposed view of the same storage (no copy).
    pub fn t(self) -> Self {
        MatRef { rows: self.cols, cols: self.rows, row_stride: self.col_stride, col_stride: self.row_stride, ..self }
    }
}

impl<'a> MatMut<'a> {
    /// A dense row-major `rows × cols` matrix at the start of `data`.
    pub fn row_major(data: &'a mut [f32], rows: usize, cols: usize) -> Self {
        MatMut { data, rows, cols, row_stride: cols, col_stride: 1 }
    }
}

/// One past the largest offset a `rows × cols` view with these strides reads, or `None`
/// on overflow. An empty view touches nothing.
fn extent(rows: usize, cols: usize, row_stride: usize, col_stride: usize) -> Option<usize> {
    if rows == 0 || cols == 0 {
        return Some(0);
    }
    (rows - 1).checked_mul(row_stride)?.checked_add((cols - 1).checked_mul(col_stride)?)?.checked_add(1)
}

/// A stride as the crate wants it. A stride along an axis of length ≤ 1 is never
/// multiplied by anything but zero, so it is normalised to 1 to keep it in `isize` range.
fn stride(len: usize, s: usize) -> isize {
    if len <= 1 { 1 } else { isize::try_from(s).expect("sgemm: stride does not fit in isize") }
}

/// Whether distinct `(i, j)` map to distinct offsets: the smaller stride must be nonzero
/// and the larger one must step past a whole run of the smaller.
fn injective(rows: usize, cols: usize, row_stride: usize, col_stride: usize) -> bool {
    match (rows > 1, cols > 1) {
        (false, false) => true,
        (true, false) => row_stride > 0,
        (false, true) => col_stride > 0,
        (true, true) => {
            let ((inner_len, inner), outer) = if row_stride <= col_stride {
                ((rows, row_stride), col_stride)
            } else {
                ((cols, col_stride), row_stride)
            };
            inner > 0 && outer > (inner_len - 1) * inner
        }
    }
}

#[track_caller]
fn check_fits(what: &str, len: usize, rows: usize, cols: usize, row_stride: usize, col_stride: usize) {
    let need = extent(rows, cols, row_stride, col_stride);
    assert!(
        need.is_some_and(|need| need <= len),
        "sgemm: {what} ({rows}x{cols}, strides {row_stride}/{col_stride}) does not fit its {len} elements"
    );
}

/// `c = a · b`, or `c += a · b` when `accumulate`, in f32.
///
/// `threads ≤ 1` runs on the calling thread; more lets the `gemm` crate split the work
/// over that many threads of the current rayon pool.
///
/// # Panics
/// If the shapes disagree (`a` is `m × k`, `b` is `k × n`, `c` is `m × n`), a view does not
/// fit its slice, or two elements of `c` share memory.
#[track_caller]
pub fn sgemm(a: MatRef, b: MatRef, c: MatMut, accumulate: bool, threads: usize) {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    assert!(
        b.rows == k && c.rows == m && c.cols == n,
        "sgemm: shapes disagree: a {}x{}, b {}x{}, c {}x{}",
        a.rows,
        a.cols,
        b.rows,
        b.cols,
        c.rows,
        c.cols
    );
    check_fits("a", a.data.len(), m, k, a.row_stride, a.col_stride);
    check_fits("b", b.data.len(), k, n, b.row_stride, b.col_stride);
    check_fits("c", c.data.len(), m, n, c.row_stride, c.col_stride);
    let (rs, cs) = (c.row_stride, c.col_stride);
    assert!(injective(m, n, rs, cs), "sgemm: elements of c overlap (strides {rs}/{cs})");
    if m == 0 || n == 0 {
        return;
    }
    let parallelism = if threads <= 1 { Parallelism::None } else { Parallelism::Rayon(threads) };
    // SAFETY: the checks above establish everything `gemm::gemm` dereferences:
    // - every offset `i*rs + j*cs` of `a` (i < m, j < k), `b` (i < k, j < n) and `c`
    //   (i < m, j < n) is below its slice's length (`check_fits`), and all strides fit in
    //   `isize` (`stride`), so no pointer leaves its allocation;
    // - `c` is borrowed mutably, so it cannot overlap `a` or `b`, and distinct elements of
    //   `c` are distinct memory (`injective`), so the crate's threads never write the same
    //   element;
    // - when `k == 0` the crate reads neither `a` nor `b` and only writes `c`;
    // - `read_dst == false` means `c` is not read (it may hold anything).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.data.as_mut_ptr(),
            stride(n, c.col_stride),
            stride(m, c.row_stride),
            accumulate,
            a.data.as_ptr(),
            stride(k, a.col_stride),
            stride(m, a.row_stride),
            b.data.as_ptr(),
            stride(n, b.col_stride),
            stride(k, b.row_stride),
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

/// Asks the CPU to bring the cache line holding `v` into the L1 cache (x86-64; nothing
/// elsewhere): for kernels whose rows lie a plane apart, too many streams for the
/// hardware prefetcher to follow.
#[inline(always)]
pub(crate) fn prefetch(v: &f32) {
    prefetch_into::<false>(v)
}

/// [`prefetch`] into the L2 cache only: for streams read from farther away (L3, memory),
/// where the L1 cache's few outstanding misses would bound the rate.
#[inline(always)]
pub(crate) fn prefetch_l2(v: &f32) {
    prefetch_into::<true>(v)
}

/// [`prefetch`] (into L1) or [`prefetch_l2`].
#[inline(always)]
fn prefetch_into<const L2: bool>(v: &f32) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE, which `_mm_prefetch` needs, is part of x86-64; a prefetch reads
    // nothing into the program and cannot fault (`v` is a valid reference anyway).
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T0, _MM_HINT_T1, _mm_prefetch};
        let p = (v as *const f32).cast();
        if L2 { _mm_prefetch::<_MM_HINT_T1>(p) } else { _mm_prefetch::<_MM_HINT_T0>(p) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = v;
}

/// The `MR x NV`-vector sums of the rows `a` (each `depth = a[0].len()` long) times the
/// first `depth` rows of `b` (each at least `NV` vectors), in registers: per step `i`,
/// `a[r][i]` broadcast and multiplied into row `i` of `b`, for every `r`. `b` comes one
/// row at a time, so its rows may lie anywhere (a packed panel, or planes a plane apart).
#[inline(always)]
pub(crate) fn rows_product<'b, S: pulp::Simd, const MR: usize, const NV: usize>(
    simd: S,
    a: [&[f32]; MR],
    b: impl Iterator<Item = &'b [S::f32s]>,
) -> [[S::f32s; NV]; MR]
where
    S::f32s: 'b,
{
    let depth = a[0].len();
    // Every row cut to `depth`: panics here if one is shorter, never in the loop.
    let a: [&[f32]; MR] = a.map(|row| &row[..depth]);
    // SAFETY: `i < depth` (the zip below ends there) and `a[r].len() == depth` (cut
    // above). Checked indexing here kept a compare and branch per row per step and
    // spilled the row pointers: 1.03-1.07x the time of the adapter's tiles.
    let at = |r: usize, i: usize| simd.splat_f32s(unsafe { *a[r].get_unchecked(i) });
    let mut b = b.zip(0..depth);
    // The sums start from the first row's products (see [`strided_rows_product`]).
    let Some((b0, _)) = b.next() else {
        return [[simd.splat_f32s(0.0); NV]; MR];
    };
    let b0 = &b0[..NV];
    let mut acc: [[S::f32s; NV]; MR] = std::array::from_fn(|r| {
        let ar = at(r, 0);
        std::array::from_fn(|v| simd.mul_f32s(ar, b0[v]))
    });
    for (bi, i) in b {
        let bi = &bi[..NV];
        for (r, sums) in acc.iter_mut().enumerate() {
            let ai = at(r, i);
            for (s, &bv) in sums.iter_mut().zip(bi) {
                *s = simd.mul_add_f32s(ai, bv, *s);
            }
        }
    }
    acc
}

/// [`rows_product`] over rows of `b` `stride` floats apart (row `i` is `b[i · stride..]`,
/// `NV` vectors of it): the bounds of the last row are checked once, so the loop reads
/// with neither a compare nor a slice per step. Through an iterator of row slices the
/// loop kept two compares and branches, two reloads from the stack and ten register
/// moves per step beside its 18 multiply-adds (`perf annotate`, 6x3 tiles).
///
/// # Panics
/// If the last row does not fit in `b` or a row of `a` is shorter than `a[0]`.
#[inline(always)]
pub(crate) fn strided_rows_product<S: pulp::Simd, const MR: usize, const NV: usize>(
    simd: S,
    a: [&[f32]; MR],
    b: &[f32],
    stride: usize,
) -> [[S::f32s; NV]; MR] {
    let depth = a[0].len();
    let a: [&[f32]; MR] = a.map(|row| &row[..depth]);
    let lanes = size_of::<S::f32s>() / size_of::<f32>();
    if depth == 0 {
        return [[simd.splat_f32s(0.0); NV]; MR];
    }
    let end = (depth - 1).checked_mul(stride).and_then(|o| o.checked_add(NV * lanes));
    assert!(end.is_some_and(|e| e <= b.len()), "strided_rows_product: {depth} rows {stride} apart overrun {}", b.len());
    // SAFETY (both reads): `i < depth`, so `i · stride + NV · lanes <= b.len()` (checked
    // above) and `i < a[r].len()` (cut above); `read_unaligned` reads a vector at any
    // address.
    let row = |i: usize| -> [S::f32s; NV] {
        std::array::from_fn(|v| unsafe { b.as_ptr().add(i * stride + v * lanes).cast::<S::f32s>().read_unaligned() })
    };
    let at = |r: usize, i: usize| simd.splat_f32s(unsafe { *a[r].get_unchecked(i) });
    // The sums start from the first row's products, not from zeros: an array of zeros
    // this size is a `memset` of the stack that LLVM does not keep in registers (5% of
    // an adapter's time, `perf`).
    let b0 = row(0);
    let mut acc: [[S::f32s; NV]; MR] = std::array::from_fn(|r| {
        let ar = at(r, 0);
        std::array::from_fn(|v| simd.mul_f32s(ar, b0[v]))
    });
    for i in 1..depth {
        let bi = row(i);
        for (r, sums) in acc.iter_mut().enumerate() {
            let ai = at(r, i);
            for (s, &bv) in sums.iter_mut().zip(&bi) {
                *s = simd.mul_add_f32s(ai, bv, *s);
            }
        }
    }
    acc
}

/// `c = a · b` for a few rows of `a` (a LoRA branch's `A`, rank rows), reading `b` in
/// place, rows `b.row_stride` apart and columns contiguous: [`strided_rows_product`]
/// register tiles of up to 4 rows by 4 vectors of columns. Through [`sgemm`] the `gemm`
/// crate packs all of `b` for a handful of rows: a rank-4 branch on ResNet-18's layer4
/// (4608 x 49 unfolded rows) cost as much as packing the tile for the conv itself.
/// Columns past the last whole vector read a vector across the row's end into the next
/// row (the last row's by scalar products), so the view must not be its slice's last row
/// cut short; `c`'s columns must be contiguous.
///
/// # Panics
/// If the shapes disagree, a view does not fit its slice, or a stride is not as above.
#[track_caller]
pub(crate) fn few_rows_product(a: MatRef, b: MatRef, c: MatMut) {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    assert!(b.rows == k && c.rows == m && c.cols == n, "few_rows_product: shapes disagree");
    assert!(a.col_stride == 1 && b.col_stride == 1 && c.col_stride == 1, "few_rows_product: strided columns");
    check_fits("few_rows_product a", a.data.len(), m, k, a.row_stride, 1);
    check_fits("few_rows_product b", b.data.len(), k, n, b.row_stride, 1);
    check_fits("few_rows_product c", c.data.len(), m, n, c.row_stride, 1);
    assert!(m <= 1 || c.row_stride >= n, "few_rows_product: rows of c overlap");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        for i in 0..m {
            c.data[i * c.row_stride..][..n].fill(0.0);
        }
        return;
    }
    pulp::Arch::new().dispatch(FewRows { a, b, c });
}

struct FewRows<'a> {
    a: MatRef<'a>,
    b: MatRef<'a>,
    c: MatMut<'a>,
}

impl pulp::WithSimd for FewRows<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let FewRows { a, b, mut c } = self;
        let mut r = 0;
        while r < a.rows {
            r += match a.rows - r {
                1 => few_rows::<S, 1>(simd, &a, &b, &mut c, r),
                2 | 3 => few_rows::<S, 2>(simd, &a, &b, &mut c, r),
                _ => few_rows::<S, 4>(simd, &a, &b, &mut c, r),
            };
        }
    }
}

/// Rows `r..r + MR` of [`few_rows_product`]; returns `MR`. One pass over `b` per four
/// vectors of columns (up to 16 accumulators): `b` streams from L2 once for a tile of 49
/// pixels (two passes, 2.3x the time, when it went by pairs and single vectors).
#[inline(always)]
fn few_rows<S: pulp::Simd, const MR: usize>(simd: S, a: &MatRef, b: &MatRef, c: &mut MatMut, r: usize) -> usize {
    let (n, lanes) = (b.cols, size_of::<S::f32s>() / size_of::<f32>());
    let rows: [&[f32]; MR] = std::array::from_fn(|i| &a.data[(r + i) * a.row_stride..][..a.cols]);
    let mut p = 0;
    while p < n {
        let nv = (n - p).div_ceil(lanes).min(4);
        p = match nv {
            4 => few_cols::<S, MR, 4>(simd, rows, b, c, r, p),
            3 => few_cols::<S, MR, 3>(simd, rows, b, c, r, p),
            2 => few_cols::<S, MR, 2>(simd, rows, b, c, r, p),
            _ => few_cols::<S, MR, 1>(simd, rows, b, c, r, p),
        };
    }
    MR
}

/// Columns from `p`, `NV` vectors of them (the last may be partial), of rows `r..r + MR`
/// of [`few_rows_product`]; returns the next column. A partial vector reads across each
/// row's end into the next row, all but the last row, which goes by scalars.
#[inline(always)]
fn few_cols<S: pulp::Simd, const MR: usize, const NV: usize>(
    simd: S,
    rows: [&[f32]; MR],
    b: &MatRef,
    c: &mut MatMut,
    r: usize,
    p: usize,
) -> usize {
    let (k, n, stride) = (b.rows, b.cols, b.row_stride);
    let lanes = size_of::<S::f32s>() / size_of::<f32>();
    let end = (p + NV * lanes).min(n);
    let whole = p + NV * lanes <= n;
    // Rows summed in registers: all of them for whole vectors; for a partial one every
    // row but the last, when its vectors stay in `b`.
    let depth = if whole {
        k
    } else if k >= 2 && (k - 2) * stride + p + NV * lanes <= b.data.len() {
        k - 1
    } else {
        0
    };
    let cut: [&[f32]; MR] = rows.map(|row| &row[..depth]);
    let acc = strided_rows_product::<S, MR, NV>(simd, cut, &b.data[p..], stride);
    // By index, not `acc.iter().zip(rows)`: through that iterator the sums stayed in
    // memory, and the loop above stored all 16 of them on every step (`perf annotate`):
    // 16-18 GFMA/s on ResNet-18's layer4 branch (4 x 4608 x 49), 50 GFMA/s by index.
    for i in 0..MR {
        let row = rows[i];
        let out = &mut c.data[(r + i) * c.row_stride + p..][..end - p];
        for (chunk, v) in out.chunks_mut(lanes).zip(acc[i]) {
            simd.partial_store_f32s(chunk, v);
        }
        for (j, o) in out.iter_mut().enumerate() {
            *o += (depth..k).map(|d| row[d] * b.data[d * stride + p + j]).sum::<f32>();
        }
    }
    end
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

    /// Element `(i, j)` of a strided view.
    fn at(m: &MatRef, i: usize, j: usize) -> f64 {
        f64::from(m.data[i * m.row_stride + j * m.col_stride])
    }

    /// `c = a·b (+ c)` in f64 over the views, returned densely row-major.
    fn reference(a: &MatRef, b: &MatRef, c0: Option<&[f32]>) -> Vec<f32> {
        let (m, k, n) = (a.rows, a.cols, b.cols);
        (0..m * n)
            .map(|idx| {
                let (i, j) = (idx / n, idx % n);
                let acc: f64 = (0..k).map(|p| at(a, i, p) * at(b, p, j)).sum();
                (acc + c0.map_or(0.0, |c| f64::from(c[idx]))) as f32
            })
            .collect()
    }

    #[test]
    fn products_of_odd_shapes_and_threads() {
        for (m, k, n) in [(1, 1, 1), (3, 5, 7), (17, 1, 9), (33, 65, 17), (128, 96, 130), (5, 300, 2), (1, 64, 50)] {
            let (a, b) = (data(m * k, 1), data(k * n, 2));
            let (ar, br) = (MatRef::row_major(&a, m, k), MatRef::row_major(&b, k, n));
            let want = reference(&ar, &br, None);
            for threads in [1, 2] {
                let mut c = vec![f32::NAN; m * n];
                sgemm(ar, br, MatMut::row_major(&mut c, m, n), false, threads);
                assert_close(&c, &want, 1e-4);
            }
        }
    }

    #[test]
    fn accumulate_adds_to_c() {
        let (m, k, n) = (19, 23, 29);
        let (a, b, c0) = (data(m * k, 3), data(k * n, 4), data(m * n, 5));
        let (ar, br) = (MatRef::row_major(&a, m, k), MatRef::row_major(&b, k, n));
        let want = reference(&ar, &br, Some(&c0));
        for threads in [1, 2] {
            let mut c = c0.clone();
            sgemm(ar, br, MatMut::row_major(&mut c, m, n), true, threads);
            assert_close(&c, &want, 1e-4);
        }
    }

    #[test]
    fn strided_and_transposed_views() {
        let (m, k, n) = (13, 11, 9);
        // a: every other column of a wider buffer; b: the transpose of a column-major
        // store; c: a column-major window inside a larger, guarded buffer.
        let abuf = data(m * 2 * k, 6);
        let a = MatRef { data: &abuf, rows: m, cols: k, row_stride: 2 * k, col_stride: 2 };
        let bbuf = data(k * n, 7);
        let b = MatRef::row_major(&bbuf, n, k).t();
        assert_eq!((b.rows, b.cols, b.row_stride, b.col_stride), (k, n, 1, k));
        let want = reference(&a, &b, None);
        let ld = m + 3;
        let mut cbuf = vec![f32::NAN; ld * n + 5];
        sgemm(a, b, MatMut { data: &mut cbuf[2..], rows: m, cols: n, row_stride: 1, col_stride: ld }, false, 2);
        let got: Vec<f32> = (0..m * n).map(|idx| cbuf[2 + (idx % n) * ld + idx / n]).collect();
        assert_close(&got, &want, 1e-4);
        // Untouched outside the window.
        assert!(cbuf[..2].iter().all(|v| v.is_nan()));
        assert!((0..n).all(|j| cbuf[2 + j * ld + m..2 + j * ld + ld].iter().all(|v| v.is_nan())));
        // Column-major helper matches.
        let cm: Vec<f32> = (0..m * k).map(|idx| abuf[(idx % m) * 2 * k + 2 * (idx / m)]).collect();
        let a2 = MatRef::col_major(&cm, m, k);
        let mut c2 = vec![0.0; m * n];
        sgemm(a2, b, MatMut::row_major(&mut c2, m, n), false, 1);
        assert_close(&c2, &want, 1e-4);
    }

    #[test]
    fn empty_inner_dimension_zeroes_or_keeps_c() {
        let mut c = vec![7.0; 6];
        sgemm(MatRef::row_major(&[], 2, 0), MatRef::row_major(&[], 0, 3), MatMut::row_major(&mut c, 2, 3), true, 1);
        assert_eq!(c, [7.0; 6]);
        sgemm(MatRef::row_major(&[], 2, 0), MatRef::row_major(&[], 0, 3), MatMut::row_major(&mut c, 2, 3), false, 1);
        assert_eq!(c, [0.0; 6]);
    }

    #[test]
    #[should_panic(expected = "does not fit")]
    fn rejects_a_view_past_its_slice() {
        let a = [0.0; 11];
        let mut c = [0.0; 9];
        sgemm(
            MatRef::row_major(&a, 3, 4),
            MatRef::row_major(&[0.0; 12], 4, 3),
            MatMut::row_major(&mut c, 3, 3),
            false,
            1,
        );
    }

    #[test]
    #[should_panic(expected = "shapes disagree")]
    fn rejects_mismatched_shapes() {
        let mut c = [0.0; 9];
        sgemm(
            MatRef::row_major(&[0.0; 12], 3, 4),
            MatRef::row_major(&[0.0; 9], 3, 3),
            MatMut::row_major(&mut c, 3, 3),
            false,
            1,
        );
    }

    #[test]
    #[should_panic(expected = "overlap")]
    fn rejects_overlapping_destination() {
        let mut c = [0.0; 16];
        let c = MatMut { data: &mut c, rows: 3, cols: 3, row_stride: 2, col_stride: 1 };
        sgemm(MatRef::row_major(&[0.0; 6], 3, 2), MatRef::row_major(&[0.0; 6], 2, 3), c, false, 2);
    }

    /// The strided product of 3 rows by 2 vectors against f64 sums.
    struct Strided {
        depth: usize,
        stride: usize,
        b_len: usize,
    }

    impl pulp::WithSimd for Strided {
        type Output = ();
        fn with_simd<S: pulp::Simd>(self, simd: S) {
            let lanes = size_of::<S::f32s>() / size_of::<f32>();
            let Strided { depth, stride, b_len } = self;
            let a = data(3 * depth, 1);
            let b = data(b_len, 2);
            let rows: [&[f32]; 3] = std::array::from_fn(|r| &a[r * depth..][..depth]);
            let acc = strided_rows_product::<S, 3, 2>(simd, rows, &b, stride);
            for (r, sums) in acc.iter().enumerate() {
                let mut got = vec![0.0f32; 2 * lanes];
                S::as_mut_simd_f32s(&mut got).0.copy_from_slice(sums);
                let want: Vec<f32> = (0..2 * lanes)
                    .map(|j| {
                        (0..depth).map(|i| f64::from(rows[r][i]) * f64::from(b[i * stride + j])).sum::<f64>() as f32
                    })
                    .collect();
                assert_close(&got, &want, 1e-5);
            }
        }
    }

    #[test]
    fn strided_rows_product_sums_rows_a_stride_apart() {
        // The last row ends exactly at the end of `b`, rows wider than their vectors, and a
        // stride that puts every row off the vector alignment; no depth at all.
        for (depth, stride) in [(1, 0), (5, 37), (40, 49), (3, 96), (0, 7)] {
            // Room for the widest backend's two vectors (16 lanes) past the last row.
            let need = if depth == 0 { 0 } else { (depth - 1) * stride + 2 * 16 };
            for b in backends() {
                b.run(Strided { depth, stride, b_len: need });
                b.run(Strided { depth, stride, b_len: need + 3 });
            }
        }
    }

    /// Every row count from 1 to 9 (tiles of 4, 2 and 1 rows), column counts around the
    /// vector widths of every backend (whole pairs, single vectors, a tail, a tail only),
    /// dense and padded strides of `b` and `c`, and the last row of `b` ending at its
    /// slice's end, against products in f64.
    #[test]
    fn few_rows_product_of_every_shape_and_backend() {
        for m in 1..=9 {
            for k in [1, 2, 3, 37] {
                for n in [1, 3, 8, 15, 16, 17, 31, 33, 49] {
                    for (bs, cs) in [(n, n), (n + 5, n + 3)] {
                        let a = data(m * k, 20);
                        let bdata = data((k - 1) * bs + n, 21);
                        let ar = MatRef::row_major(&a, m, k);
                        let br = MatRef { data: &bdata, rows: k, cols: n, row_stride: bs, col_stride: 1 };
                        let want: Vec<f32> = (0..m * n)
                            .map(|idx| {
                                let (i, j) = (idx / n, idx % n);
                                (0..k).map(|p| f64::from(a[i * k + p]) * f64::from(bdata[p * bs + j])).sum::<f64>()
                                    as f32
                            })
                            .collect();
                        for be in backends() {
                            let mut c = vec![f32::NAN; (m - 1) * cs + n];
                            let cm = MatMut { data: &mut c, rows: m, cols: n, row_stride: cs, col_stride: 1 };
                            be.run(FewRows { a: ar, b: br, c: cm });
                            let got: Vec<f32> = (0..m * n).map(|idx| c[idx / n * cs + idx % n]).collect();
                            assert_close(&got, &want, 1e-5);
                        }
                    }
                }
            }
        }
        // No depth: zeros.
        let mut c = vec![f32::NAN; 6];
        few_rows_product(MatRef::row_major(&[], 2, 0), MatRef::row_major(&[], 0, 3), MatMut::row_major(&mut c, 2, 3));
        assert_eq!(c, [0.0; 6]);
    }

    #[test]
    #[should_panic(expected = "overrun")]
    fn strided_rows_product_refuses_a_short_b() {
        struct Short;
        impl pulp::WithSimd for Short {
            type Output = ();
            fn with_simd<S: pulp::Simd>(self, simd: S) {
                let lanes = size_of::<S::f32s>() / size_of::<f32>();
                let a = [1.0f32; 4];
                // Four rows 10 apart need 30 + 2 vectors; one float short.
                let b = vec![1.0f32; 30 + 2 * lanes - 1];
                strided_rows_product::<S, 1, 2>(simd, [&a], &b, 10);
            }
        }
        pulp::Arch::new().dispatch(Short);
    }

    #[test]
    fn injectivity_rule() {
        assert!(injective(3, 3, 3, 1));
        assert!(injective(3, 3, 1, 3));
        assert!(!injective(3, 3, 2, 1));
        assert!(!injective(2, 2, 0, 1));
        assert!(injective(1, 5, 0, 1));
        assert!(!injective(1, 5, 7, 0));
        assert!(injective(4, 1, 9, 0));
    }
}
