//! Fully connected layers and batched matrix products, on top of [`sgemm`].

use rayon::prelude::*;

use super::Epilogue;
use super::elementwise::relu;
use super::gemm::{MatMut, MatRef, sgemm};
use super::panel;

/// Output floats per GEMM block before its epilogue runs: up to 1 MiB, so the block is
/// still in L2 when the epilogue reads it. (Each GEMM call packs the weight again, so
/// blocks are as large as L2 allows.)
const BLOCK_FLOATS: usize = 256 * 1024;

/// Floats of a fused LoRA branch's `x Aᵀ` per chunk of rows, on the stack: at least one
/// row at the largest rank ([`super::conv::MAX_LORA_RANK`]).
const LORA_ROWS_FLOATS: usize = super::conv::MAX_LORA_RANK;

/// How a linear layer's weight is laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WeightLayout {
    /// PyTorch's `[out_features, in_features]`, read through strides.
    OutIn,
    /// `[in_features, out_features]`: the compiler stores weights this way, since GEMM
    /// reads a row-major right operand up to 1.8x faster (measured: 259 vs 469 GFLOP/s on
    /// ViT-S's fc2, 2 threads).
    InOut,
    /// Packed by [`panel::pack`] for [`panel::gemm`], which reads it without packing it
    /// again on every call: what the compiler stores for layers with few rows, where that
    /// pass over the weight costs most.
    Panels,
}

impl WeightLayout {
    /// Floats of an `in_features x out_features` weight in this layout, `None` on overflow.
    pub fn len(self, in_features: usize, out_features: usize) -> Option<usize> {
        match self {
            WeightLayout::OutIn | WeightLayout::InOut => in_features.checked_mul(out_features),
            WeightLayout::Panels => {
                out_features.div_ceil(panel::PANEL).checked_mul(panel::PANEL)?.checked_mul(in_features)
            }
        }
    }
}

/// `out[rows, out_features] = epilogue(x[rows, in_features] · weightᵀ)` for a weight in
/// `layout`, with the epilogue per output feature (a bias is its `shift`).
///
/// Blocks of rows are multiplied and then finished by the epilogue while in cache; with
/// enough rows the blocks are spread over `threads` threads of the current rayon pool,
/// otherwise the GEMM itself uses them.
///
/// # Panics
/// If a slice length disagrees with the sizes.
#[allow(clippy::too_many_arguments)]
pub fn linear(
    x: &[f32],
    rows: usize,
    in_features: usize,
    weight: &[f32],
    layout: WeightLayout,
    out_features: usize,
    ep: &Epilogue,
    out: &mut [f32],
    threads: usize,
) {
    linear_lora(x, rows, in_features, weight, layout, None, out_features, ep, out, threads)
}

/// A linear layer's fused LoRA branch ([`linear_lora`]) is a [`Lora`] with `A`
/// `[rank, in]` as PyTorch stores it.
pub use super::Lora;

/// [`linear`] with a fused LoRA branch: `out = epilogue(x Wᵀ + (x Aᵀ) Bᵀ)`, the branch
/// computed per block of rows while the block's input is in cache, added before the
/// epilogue.
///
/// # Panics
/// As [`linear`], and if `A` or `B` does not have `rank · in_features` or
/// `out_features · rank` values.
#[allow(clippy::too_many_arguments)]
pub fn linear_lora(
    x: &[f32],
    rows: usize,
    in_features: usize,
    weight: &[f32],
    layout: WeightLayout,
    lora: Option<&Lora>,
    out_features: usize,
    ep: &Epilogue,
    out: &mut [f32],
    threads: usize,
) {
    if let Some(l) = lora {
        assert!(l.rank > 0 && l.rank <= LORA_ROWS_FLOATS, "linear: LoRA rank {}", l.rank);
        assert_eq!(l.a.len(), l.rank * in_features, "linear: LoRA A length");
        assert_eq!(l.b.len(), out_features * l.rank, "linear: LoRA B length");
    }
    debug_assert_eq!(
        check(
            &[rows, in_features],
            in_features,
            out_features,
            layout,
            weight.len(),
            &[rows, out_features],
            [ep.scale.map(<[f32]>::len), ep.shift.map(<[f32]>::len)],
            lora.map(|l| (l.rank, l.a.len(), l.b.len()))
        ),
        Ok(()),
        "linear preconditions"
    );
    assert_eq!(x.len(), rows * in_features, "linear: input length");
    assert_eq!(Some(weight.len()), layout.len(in_features, out_features), "linear: weight length");
    assert_eq!(out.len(), rows * out_features, "linear: output length");
    for v in [ep.scale, ep.shift].into_iter().flatten() {
        assert_eq!(v.len(), out_features, "linear: epilogue length");
    }
    if out.is_empty() {
        return;
    }
    // weightᵀ as an in_features × out_features view (none in panels, which only
    // `panel::gemm` reads).
    let wt = match layout {
        WeightLayout::OutIn => {
            Some(MatRef { data: weight, rows: in_features, cols: out_features, row_stride: 1, col_stride: in_features })
        }
        WeightLayout::InOut => Some(MatRef::row_major(weight, in_features, out_features)),
        WeightLayout::Panels => None,
    };
    let block_rows = (BLOCK_FLOATS / out_features).max(1);
    let block = |rows_out: &mut [f32], x_rows: &[f32], gemm_threads: usize| {
        let r = rows_out.len() / out_features;
        match wt {
            Some(wt) => sgemm(
                MatRef::row_major(x_rows, r, in_features),
                wt,
                MatMut::row_major(rows_out, r, out_features),
                false,
                gemm_threads,
            ),
            // One thread per block: the rows are split over the threads below.
            None => panel::gemm(x_rows, r, in_features, weight, out_features, rows_out),
        }
        if let Some(l) = lora {
            // t = x Aᵀ, then out += t Bᵀ, over as many rows at a time as `t` fits on the
            // stack (kernels allocate nothing).
            let mut buf = [0.0f32; LORA_ROWS_FLOATS];
            let step = (LORA_ROWS_FLOATS / l.rank).max(1);
            let at = MatRef::row_major(l.a, l.rank, in_features).t();
            let bt = MatRef::row_major(l.b, out_features, l.rank).t();
            for r0 in (0..r).step_by(step) {
                let rr = step.min(r - r0);
                let t = &mut buf[..rr * l.rank];
                let xr = MatRef::row_major(&x_rows[r0 * in_features..][..rr * in_features], rr, in_features);
                sgemm(xr, at, MatMut::row_major(t, rr, l.rank), false, 1);
                let dst = MatMut::row_major(&mut rows_out[r0 * out_features..][..rr * out_features], rr, out_features);
                sgemm(MatRef::row_major(t, rr, l.rank), bt, dst, true, 1);
            }
        }
        epilogue_rows(rows_out, out_features, ep);
    };
    if in_features == 0 {
        block(out, x, threads);
    } else if layout == WeightLayout::Panels && lora.is_none() && rows == 1 && threads > 1 {
        // One row (a classifier at batch 1): the threads share the panels, each its own
        // range of output columns.
        let per = out_features.div_ceil(panel::PANEL).div_ceil(threads) * panel::PANEL;
        out.par_chunks_mut(per).zip(weight.par_chunks(per * in_features)).enumerate().for_each(|(i, (o, w))| {
            let (c0, n) = (i * per, o.len());
            panel::gemm(x, 1, in_features, w, n, o);
            let ep = Epilogue {
                scale: ep.scale.map(|v| &v[c0..c0 + n]),
                shift: ep.shift.map(|v| &v[c0..c0 + n]),
                act: ep.act,
            };
            epilogue_rows(o, n, &ep);
        });
    } else if threads > 1 && rows >= 16 * threads {
        // Rows split evenly over the threads, each thread's share in cache-sized blocks.
        let share = rows.div_ceil(threads);
        out.par_chunks_mut(share * out_features).zip(x.par_chunks(share * in_features)).for_each(|(o, xs)| {
            for (ob, xb) in o.chunks_mut(block_rows * out_features).zip(xs.chunks(block_rows * in_features)) {
                block(ob, xb, 1);
            }
        });
    } else {
        for (ob, xb) in out.chunks_mut(block_rows * out_features).zip(x.chunks(block_rows * in_features)) {
            block(ob, xb, threads);
        }
    }
}

simd_fn! {
    /// [`epilogue_row`] over every row (of `out_features`) of a block, vectorised.
    fn epilogue_rows(rows: &mut [f32], out_features: usize, ep: &Epilogue<'_>) {
        if ep.scale.is_none() && ep.shift.is_none() && ep.act.is_none() {
            return;
        }
        for row in rows.chunks_mut(out_features) {
            epilogue_row(row, ep);
        }
        ep.finish_act(rows);
    }
}

/// `row[j] = act(row[j] · scale[j] + shift[j])` over one output row.
#[inline(always)]
fn epilogue_row(row: &mut [f32], ep: &Epilogue) {
    match (ep.scale, ep.shift) {
        (None, None) => {}
        (Some(sc), None) => row.iter_mut().zip(sc).for_each(|(v, s)| *v *= s),
        (None, Some(sh)) => row.iter_mut().zip(sh).for_each(|(v, b)| *v += b),
        (Some(sc), Some(sh)) => row.iter_mut().zip(sc.iter().zip(sh)).for_each(|(v, (s, b))| *v = *v * s + b),
    }
    if ep.relu() {
        row.iter_mut().for_each(|v| *v = relu(*v));
    }
}

/// Batched matrix product with torch.matmul's semantics for operands of rank ≥ 2: the last
/// two axes are multiplied (`[.., m, k] · [.., k, n] → [.., m, n]`), the leading (batch)
/// axes broadcast with NumPy's rules. `out_shape` must be the broadcast result.
///
/// When `b` has no batch axes of its own (a weight-like operand), all of `a`'s batches
/// become one tall GEMM.
///
/// # Panics
/// If a rank is below 2, the inner sizes differ, the batch axes do not broadcast to
/// `out_shape`'s, or a slice length disagrees with its shape.
pub fn matmul(
    a: &[f32],
    a_shape: &[usize],
    b: &[f32],
    b_shape: &[usize],
    out: &mut [f32],
    out_shape: &[usize],
    threads: usize,
) {
    debug_assert_eq!(check_matmul(a_shape, b_shape, out_shape), Ok(()), "matmul preconditions");
    assert!(a_shape.len() >= 2 && b_shape.len() >= 2, "matmul: operands need rank ≥ 2: {a_shape:?}, {b_shape:?}");
    let (a_batch, &[m, k]) = a_shape.split_at(a_shape.len() - 2) else { unreachable!("rank ≥ 2") };
    let (b_batch, &[kb, n]) = b_shape.split_at(b_shape.len() - 2) else { unreachable!("rank ≥ 2") };
    assert_eq!(k, kb, "matmul: inner sizes differ: {a_shape:?} · {b_shape:?}");
    let rank = a_batch.len().max(b_batch.len());
    assert_eq!(out_shape.len(), rank + 2, "matmul: output rank");
    assert_eq!(&out_shape[rank..], &[m, n], "matmul: output matrix shape");
    let batch = &out_shape[..rank];
    // Element strides of each operand's matrices along the output's batch axes (0 where
    // the operand broadcasts).
    let strides = |shape: &[usize], mat: usize| -> Vec<usize> {
        let mut st = vec![0; rank];
        let mut step = mat;
        for (i, &d) in shape.iter().enumerate().rev() {
            let axis = rank - shape.len() + i;
            assert!(
                d == batch[axis] || d == 1,
                "matmul: batch axes {a_shape:?} and {b_shape:?} do not broadcast to {out_shape:?}"
            );
            st[axis] = if d == 1 { 0 } else { step };
            step *= d;
        }
        st
    };
    let (sa, sb) = (strides(a_batch, m * k), strides(b_batch, k * n));
    assert_eq!(a.len(), a_shape.iter().product::<usize>(), "matmul: a length");
    assert_eq!(b.len(), b_shape.iter().product::<usize>(), "matmul: b length");
    assert_eq!(out.len(), out_shape.iter().product::<usize>(), "matmul: output length");
    let batches: usize = batch.iter().product();
    if out.is_empty() {
        return;
    }
    if sb.iter().all(|&s| s == 0) && a_batch.iter().product::<usize>() == batches {
        // One [batches·m, k] · [k, n] product.
        let rows = batches * m;
        sgemm(
            MatRef::row_major(a, rows, k),
            MatRef::row_major(b, k, n),
            MatMut::row_major(out, rows, n),
            false,
            threads,
        );
        return;
    }
    let offset = |mut idx: usize, st: &[usize]| {
        let mut off = 0;
        for (axis, &d) in batch.iter().enumerate().rev() {
            off += (idx % d) * st[axis];
            idx /= d;
        }
        off
    };
    let one = |(i, o): (usize, &mut [f32]), gemm_threads: usize| {
        let (oa, ob) = (offset(i, &sa), offset(i, &sb));
        sgemm(
            MatRef::row_major(&a[oa..oa + m * k], m, k),
            MatRef::row_major(&b[ob..ob + k * n], k, n),
            MatMut::row_major(o, m, n),
            false,
            gemm_threads,
        );
    };
    if threads > 1 && batches >= threads {
        out.par_chunks_mut(m * n).enumerate().for_each(|io| one(io, 1));
    } else {
        out.chunks_mut(m * n).enumerate().for_each(|io| one(io, threads));
    }
}

/// The preconditions of [`linear`] as the executor calls it on a value of shape
/// `x_shape` (rows: every axis but the last): at least one axis, the last of
/// `in_features` values (0 is allowed: the output is the epilogue of zero), a weight of
/// `in_features × out_features`, an output of `rows × out_features` and epilogue
/// vectors of `out_features`; a LoRA branch `(rank, A's length, B's length)` of a rank
/// of 1 to [`super::conv::MAX_LORA_RANK`], `A` of `rank × in_features` and `B` of
/// `out_features × rank`. Checked at bind time; [`linear`] asserts it in debug builds.
#[allow(clippy::too_many_arguments)]
pub fn check(
    x_shape: &[usize],
    in_features: usize,
    out_features: usize,
    layout: WeightLayout,
    weight_len: usize,
    out_shape: &[usize],
    epilogue: [Option<usize>; 2],
    lora: Option<(usize, usize, usize)>,
) -> Result<(), String> {
    let Some((&last, rows)) = x_shape.split_last() else { return Err("linear of a scalar".into()) };
    if last != in_features {
        return Err(format!("linear needs {in_features} input features, its input is {x_shape:?}"));
    }
    if Some(weight_len) != layout.len(in_features, out_features) {
        return Err(format!("linear weight has {weight_len} values for {in_features} x {out_features} ({layout:?})"));
    }
    let rows = numel(rows).ok_or("linear: too many rows")?;
    if numel(out_shape) != rows.checked_mul(out_features) {
        return Err(format!("linear output {out_shape:?} is not {rows} rows of {out_features}"));
    }
    if let Some(n) = epilogue.into_iter().flatten().find(|&n| n != out_features) {
        return Err(format!("linear epilogue vector has {n} values for {out_features} outputs"));
    }
    if let Some((rank, a_len, b_len)) = lora {
        let max = super::conv::MAX_LORA_RANK;
        if rank == 0 || rank > max {
            return Err(format!("LoRA rank {rank}: it must be 1 to {max}"));
        }
        if Some(a_len) != rank.checked_mul(in_features) || Some(b_len) != rank.checked_mul(out_features) {
            return Err(format!(
                "LoRA A has {a_len} values (needs {rank} x {in_features}), B {b_len} (needs {out_features} x {rank})"
            ));
        }
    }
    Ok(())
}

/// The preconditions of [`matmul`]: ranks ≥ 2, equal inner sizes, batch axes that
/// broadcast to the output's, the output's matrix `m × n`.
pub fn check_matmul(a: &[usize], b: &[usize], out: &[usize]) -> Result<(), String> {
    let fail = || Err(format!("matmul of {a:?} and {b:?} cannot give {out:?}"));
    if a.len() < 2 || b.len() < 2 {
        return fail();
    }
    let (ab, am) = a.split_at(a.len() - 2);
    let (bb, bm) = b.split_at(b.len() - 2);
    let rank = ab.len().max(bb.len());
    if am[1] != bm[0] {
        return Err(format!("matmul: inner sizes differ: {a:?} · {b:?}"));
    }
    if out.len() != rank + 2 || out[rank..] != [am[0], bm[1]] {
        return fail();
    }
    let fits = |batch: &[usize]| batch.iter().rev().zip(out[..rank].iter().rev()).all(|(&d, &o)| d == o || d == 1);
    if !fits(ab) || !fits(bb) {
        return Err(format!("matmul: batch axes {a:?} and {b:?} do not broadcast to {out:?}"));
    }
    Ok(())
}

fn numel(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::Activation;
    use crate::kernels::testutil::{assert_close, data};

    /// Plain f64 `a[m, k] · b[k, n]` over row-major slices.
    fn naive(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> Vec<f64> {
        let mut out = vec![0.0; m * n];
        for i in 0..m {
            for j in 0..n {
                out[i * n + j] = (0..k).map(|p| f64::from(a[i * k + p]) * f64::from(b[p * n + j])).sum();
            }
        }
        out
    }

    #[test]
    fn linear_matches_reference_with_epilogues() {
        for (rows, fin, fout) in [(1, 7, 5), (3, 1, 4), (37, 19, 23), (200, 64, 48), (70, 33, 1)] {
            let x = data(rows * fin, 1);
            let w = data(fout * fin, 2);
            let scale: Vec<f32> = data(fout, 3).iter().map(|v| v + 1.5).collect();
            let shift = data(fout, 4);
            // weightᵀ, for the reference.
            let wt: Vec<f32> = (0..fin * fout).map(|i| w[(i % fout) * fin + i / fout]).collect();
            let acc = naive(&x, &wt, rows, fin, fout);
            let eps = [
                Epilogue::default(),
                Epilogue { scale: None, shift: Some(&shift), act: None },
                Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) },
                Epilogue { scale: Some(&scale), shift: None, act: None },
                Epilogue { scale: None, shift: Some(&shift), act: Some(Activation::Gelu) },
                Epilogue { scale: None, shift: None, act: Some(Activation::LeakyRelu { negative_slope: 0.1 }) },
            ];
            for ep in &eps {
                let want: Vec<f32> = acc
                    .iter()
                    .enumerate()
                    .map(|(i, &a)| {
                        let j = i % fout;
                        let y =
                            a * ep.scale.map_or(1.0, |s| f64::from(s[j])) + ep.shift.map_or(0.0, |s| f64::from(s[j]));
                        ep.act.map_or(y, |act| act.reference(y)) as f32
                    })
                    .collect();
                for threads in [1, 2, 3] {
                    let mut out = vec![f32::NAN; rows * fout];
                    linear(&x, rows, fin, &w, WeightLayout::OutIn, fout, ep, &mut out, threads);
                    assert_close(&out, &want, 1e-4);
                    let mut out = vec![f32::NAN; rows * fout];
                    linear(&x, rows, fin, &wt, WeightLayout::InOut, fout, ep, &mut out, threads);
                    assert_close(&out, &want, 1e-4);
                }
            }
        }
    }

    #[test]
    fn linear_lora_matches_a_separate_branch() {
        // Row counts under and over the thread split (16 per thread) and over one block.
        for (rows, fin, fout, rank) in [(1, 7, 5, 1), (37, 19, 23, 4), (200, 64, 48, 8), (5000, 9, 70, 3)] {
            let x = data(rows * fin, 21);
            let w = data(fout * fin, 22);
            let a = data(rank * fin, 23);
            let b = data(fout * rank, 24);
            let scale: Vec<f32> = data(fout, 25).iter().map(|v| v + 1.5).collect();
            let shift = data(fout, 26);
            let wt: Vec<f32> = (0..fin * fout).map(|i| w[(i % fout) * fin + i / fout]).collect();
            let at: Vec<f32> = (0..fin * rank).map(|i| a[(i % rank) * fin + i / rank]).collect();
            let bt: Vec<f32> = (0..rank * fout).map(|i| b[(i % fout) * rank + i / fout]).collect();
            // The base layer and the branch, separately, in f64.
            let base = naive(&x, &wt, rows, fin, fout);
            let t: Vec<f32> = naive(&x, &at, rows, fin, rank).into_iter().map(|v| v as f32).collect();
            let t64 = naive(&t, &bt, rows, rank, fout);
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) };
            let want: Vec<f32> = (0..rows * fout)
                .map(|i| {
                    let j = i % fout;
                    ((base[i] + t64[i]) * f64::from(scale[j]) + f64::from(shift[j])).max(0.0) as f32
                })
                .collect();
            let lora = Lora { a: &a, b: &b, rank };
            let fields = Some((rank, a.len(), b.len()));
            assert_eq!(
                check(&[rows, fin], fin, fout, WeightLayout::InOut, wt.len(), &[rows, fout], [Some(fout); 2], fields),
                Ok(())
            );
            // The same weight in panels (`panel::pack` from PyTorch's layout).
            let mut packed = vec![0.0; WeightLayout::Panels.len(fin, fout).expect("fits")];
            crate::kernels::panel::pack(&w, fin, fout, &mut packed);
            assert_eq!(
                check(
                    &[rows, fin],
                    fin,
                    fout,
                    WeightLayout::Panels,
                    packed.len(),
                    &[rows, fout],
                    [Some(fout); 2],
                    fields
                ),
                Ok(())
            );
            for threads in [1, 2] {
                for (layout, weight) in [(WeightLayout::InOut, &wt), (WeightLayout::Panels, &packed)] {
                    let mut out = vec![f32::NAN; rows * fout];
                    linear_lora(&x, rows, fin, weight, layout, Some(&lora), fout, &ep, &mut out, threads);
                    assert_close(&out, &want, 1e-4);
                }
            }
        }
        let packed_len =
            |fin, fout| check(&[1, fin], fin, fout, WeightLayout::Panels, fin * fout, &[1, fout], [None, None], None);
        assert!(packed_len(3, 32).is_ok(), "32 outputs fill one panel exactly");
        assert!(packed_len(3, 33).expect_err("a short panel weight").contains("Panels"));
        let bad =
            |l| check(&[2, 3], 3, 4, WeightLayout::InOut, 12, &[2, 4], [None, None], Some(l)).expect_err("bad LoRA");
        assert!(bad((0, 0, 0)).contains("rank 0"));
        assert!(bad((2, 6, 7)).contains("B 7"));
        assert!(bad((2, 5, 8)).contains("A has 5"));
    }

    /// One row with the weight in panels, its output columns shared by 2 and 3 threads:
    /// ranges of whole panels, the last one short, with the bias, scale and GELU of each
    /// range's own columns.
    #[test]
    fn one_row_in_panels_splits_its_columns_over_threads() {
        for (fin, fout) in [(40, 1000), (7, 33), (16, 64), (5, 31)] {
            let x = data(fin, 1);
            let w = data(fout * fin, 2);
            let (scale, shift) = (data(fout, 3), data(fout, 4));
            let wt: Vec<f32> = (0..fin * fout).map(|i| w[(i % fout) * fin + i / fout]).collect();
            let base = naive(&x, &wt, 1, fin, fout);
            let want: Vec<f32> = (0..fout)
                .map(|j| {
                    let v = base[j] * f64::from(scale[j]) + f64::from(shift[j]);
                    Activation::Gelu.reference(v) as f32
                })
                .collect();
            let mut packed = vec![0.0; WeightLayout::Panels.len(fin, fout).expect("fits")];
            crate::kernels::panel::pack(&w, fin, fout, &mut packed);
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Gelu) };
            for threads in [1, 2, 3] {
                let mut out = vec![f32::NAN; fout];
                linear(&x, 1, fin, &packed, WeightLayout::Panels, fout, &ep, &mut out, threads);
                assert_close(&out, &want, 1e-4);
            }
        }
    }

    #[test]
    fn linear_with_no_inputs_is_the_epilogue_of_zero() {
        let shift = [1.0, -2.0];
        let mut out = vec![f32::NAN; 6];
        let ep = Epilogue { scale: None, shift: Some(&shift), act: Some(Activation::Relu) };
        linear(&[], 3, 0, &[], WeightLayout::OutIn, 2, &ep, &mut out, 2);
        assert_eq!(out, [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]);
    }

    /// torch.matmul by hand: broadcast batch axes, multiply the last two.
    fn matmul_reference(a: &[f32], ash: &[usize], b: &[f32], bsh: &[usize], osh: &[usize]) -> Vec<f32> {
        let (m, k, n) = (ash[ash.len() - 2], ash[ash.len() - 1], bsh[bsh.len() - 1]);
        let rank = osh.len() - 2;
        let batches: usize = osh[..rank].iter().product();
        let mut out = Vec::new();
        for bi in 0..batches {
            // Multi-index of the output batch, then each operand's (broadcast) batch index.
            let mut idx = vec![0; rank];
            let mut r = bi;
            for ax in (0..rank).rev() {
                idx[ax] = r % osh[ax];
                r /= osh[ax];
            }
            let flat = |sh: &[usize]| {
                let lead = &sh[..sh.len() - 2];
                lead.iter()
                    .enumerate()
                    .fold(0, |acc, (i, &d)| acc * d + if d == 1 { 0 } else { idx[rank - lead.len() + i] })
            };
            let (oa, ob) = (flat(ash) * m * k, flat(bsh) * k * n);
            out.extend(naive(&a[oa..oa + m * k], &b[ob..ob + k * n], m, k, n).into_iter().map(|v| v as f32));
        }
        out
    }

    #[test]
    fn matmul_broadcasts_like_torch() {
        let cases: [(&[usize], &[usize], &[usize]); 7] = [
            (&[2, 3, 4, 5], &[5, 6], &[2, 3, 4, 6]),
            (&[1, 4, 5], &[3, 5, 6], &[3, 4, 6]),
            (&[3, 4, 5], &[1, 5, 6], &[3, 4, 6]),
            (&[2, 1, 4, 5], &[3, 5, 6], &[2, 3, 4, 6]),
            (&[4, 5], &[2, 5, 6], &[2, 4, 6]),
            (&[7, 9], &[9, 3], &[7, 3]),
            (&[2, 3, 1, 5], &[2, 3, 5, 1], &[2, 3, 1, 1]),
        ];
        for (ash, bsh, osh) in cases {
            let a = data(ash.iter().product(), 5);
            let b = data(bsh.iter().product(), 6);
            let want = matmul_reference(&a, ash, &b, bsh, osh);
            for threads in [1, 2] {
                let mut out = vec![f32::NAN; osh.iter().product()];
                matmul(&a, ash, &b, bsh, &mut out, osh, threads);
                assert_close(&out, &want, 1e-4);
            }
        }
    }

    #[test]
    #[should_panic(expected = "do not broadcast")]
    fn matmul_rejects_mismatched_batches() {
        let mut out = vec![0.0; 2 * 4 * 6];
        matmul(&[0.0; 2 * 4 * 5], &[2, 4, 5], &[0.0; 3 * 5 * 6], &[3, 5, 6], &mut out, &[2, 4, 6], 1);
    }

    #[test]
    #[should_panic(expected = "inner sizes differ")]
    fn matmul_rejects_inner_mismatch() {
        let mut out = vec![0.0; 4 * 6];
        matmul(&[0.0; 20], &[4, 5], &[0.0; 24], &[4, 6], &mut out, &[4, 6], 1);
    }
}
