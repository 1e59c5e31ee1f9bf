//! Merging a LoRA update into a weight, `W + factor · B A`, and packing a conv layer
//! merged on switch: the one definition of the merge arithmetic, which the compiler's
//! `merge_lora` calls too (so a layer merged at compile time and one merged by a session
//! at a switch compute each element the same way).
//!
//! Allocates nothing: the caller passes every buffer (a session sizes them at bind time).

use super::conv::{self, Conv2dShape, ConvAlgo};

/// `out = W + factor · B A`, element by element `(w + factor · Σ_r b[o, r] a[r, c])` in
/// f64, rounded once to f32, for `W` `[rows, cols]`, `A` `[rank, cols]` and `B`
/// `[rows, rank]`, all row-major (a conv's `A` is `[rank, cin · kh · kw]`, PyTorch's
/// layout, so `W` is the conv's raw weight).
///
/// # Panics
/// When the lengths disagree with `rank` (callers check them first).
pub fn merge_lora(w: &[f32], a: &[f32], b: &[f32], rank: usize, factor: f64, out: &mut [f32]) {
    assert!(rank > 0 && a.len().is_multiple_of(rank) && b.len().is_multiple_of(rank), "merge: rank {rank}");
    let (cols, rows) = (a.len() / rank, b.len() / rank);
    assert!(w.len() == rows * cols && out.len() == w.len(), "merge: W has {} values, B A {rows}x{cols}", w.len());
    for o in 0..rows {
        let bo = &b[o * rank..][..rank];
        for c in 0..cols {
            let d: f64 = (0..rank).map(|r| bo[r] as f64 * a[r * cols + c] as f64).sum();
            out[o * cols + c] = (w[o * cols + c] as f64 + factor * d) as f32;
        }
    }
}

/// Floats of the raw buffer [`switch_pack`] needs for a layer: the merged raw weight when
/// a LoRA update is merged into a weight packed in another layout (Winograd), else 0.
pub fn switch_tmp_len(s: &Conv2dShape, algo: ConvAlgo, lora: bool) -> usize {
    if lora && !algo.packs_as_is() { s.cout.saturating_mul(s.k()) } else { 0 }
}

/// A conv merged on switch: `out` = the raw `weight` (`[cout, cin/groups, kh, kw]`), with
/// `B A` of `lora` merged in (its `A` raw, `[rank, cin, kh, kw]`; `B` with its scale),
/// packed for `algo` (`conv::pack_weight`). `tmp` has [`switch_tmp_len`] floats.
pub fn switch_pack(
    s: &Conv2dShape,
    algo: ConvAlgo,
    weight: &[f32],
    lora: Option<&super::Lora<'_>>,
    tmp: &mut [f32],
    out: &mut [f32],
) {
    match lora {
        None => conv::pack_weight(s, algo, weight, out),
        // Packing is a copy: merge straight into the working copy.
        Some(l) if algo.packs_as_is() => merge_lora(weight, l.a, l.b, l.rank, 1.0, out),
        Some(l) => {
            let tmp = &mut tmp[..weight.len()];
            merge_lora(weight, l.a, l.b, l.rank, 1.0, tmp);
            conv::pack_weight(s, algo, tmp, out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merge_is_w_plus_factor_b_a() {
        // W [2, 3], A [1, 3], B [2, 1], by hand: W + 0.5 * B A.
        let (w, a, b) = ([1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0], [1.0f32, 0.0, -2.0], [2.0f32, -1.0]);
        let mut out = [0.0f32; 6];
        merge_lora(&w, &a, &b, 1, 0.5, &mut out);
        assert_eq!(out, [2.0, 2.0, 1.0, 3.5, 5.0, 7.0]);
    }

    #[test]
    fn switch_pack_is_the_merged_weight_packed() {
        let s = Conv2dShape::square(1, 3, 6, 4, 3, 1, 1, 1);
        let rank = 2;
        let w: Vec<f32> = (0..s.cout * s.k()).map(|i| (i % 7) as f32 * 0.1 - 0.3).collect();
        let a: Vec<f32> = (0..rank * s.k()).map(|i| (i % 5) as f32 * 0.2 - 0.4).collect();
        let b: Vec<f32> = (0..s.cout * rank).map(|i| (i % 3) as f32 * 0.3 - 0.3).collect();
        // Naive: the merged weight by its definition, then packed.
        let mut merged = w.clone();
        for o in 0..s.cout {
            for c in 0..s.k() {
                let d: f64 = (0..rank).map(|r| b[o * rank + r] as f64 * a[r * s.k() + c] as f64).sum();
                merged[o * s.k() + c] = (w[o * s.k() + c] as f64 + d) as f32;
            }
        }
        let l = crate::kernels::Lora { a: &a, b: &b, rank };
        for algo in [ConvAlgo::Im2col, ConvAlgo::Winograd2, ConvAlgo::Winograd4, ConvAlgo::Panels] {
            let mut want = vec![0.0; conv::packed_weight_len(&s, algo)];
            conv::pack_weight(&s, algo, &merged, &mut want);
            let mut tmp = vec![0.0; switch_tmp_len(&s, algo, true)];
            let mut got = vec![1.0; want.len()];
            switch_pack(&s, algo, &w, Some(&l), &mut tmp, &mut got);
            assert_eq!(got, want, "{algo:?}");
            switch_pack(&s, algo, &w, None, &mut tmp, &mut got);
            conv::pack_weight(&s, algo, &w, &mut want);
            assert_eq!(got, want, "{algo:?} without LoRA");
        }
    }
}
