//! Panel-packed right operands and the register-blocked product that reads them: the GEMM
//! of a linear layer whose weight was packed once, at compile time.
//!
//! The `gemm` crate packs its operands on every call; for a linear layer that is a pass
//! over the whole weight before any multiply, and at batch 1 a transformer's linears have
//! few rows (Swin-T's last stage: 49), so the weight is read twice as often as the
//! product needs. Here the weight `[out, in]` is stored as [`PANEL`]-column panels, each
//! `in x PANEL` row-major (`[ceil(out / PANEL)][in][PANEL]`, the last panel zero-padded):
//! a micro-tile of `MR` rows by one panel keeps its `MR x PANEL` sums in registers and
//! streams the panel once per tile, front to back.
//!
//! With AVX-512 (16 lanes) a tile is 8 rows by two vectors, with AVX2 (8 lanes) 3 rows by
//! four, with 4-lane vectors 2 rows by eight, and on scalars 2 rows by 32.

use pulp::Simd;

/// Columns per panel (the plan format's): two AVX-512 vectors, four AVX2 vectors.
pub use readi_plan::ops::PANEL;

/// Floats of a `k x n` right operand (`n` output columns) packed in panels.
pub fn packed_len(k: usize, n: usize) -> usize {
    n.div_ceil(PANEL) * k * PANEL
}

/// Packs a linear layer's weight in PyTorch's layout, `weight[j * k + i]` for output `j`
/// and input `i` (`n x k`), into `out` (`packed_len(k, n)` floats) as panels of its
/// transpose; columns past `n` are zero.
///
/// # Panics
/// If a slice length disagrees with the sizes.
pub fn pack(weight: &[f32], k: usize, n: usize, out: &mut [f32]) {
    assert_eq!(weight.len(), n * k, "panel pack: weight length");
    assert_eq!(out.len(), packed_len(k, n), "panel pack: packed length");
    for (p, panel) in out.chunks_mut(k * PANEL).enumerate() {
        for (i, row) in panel.chunks_mut(PANEL).enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                let j = p * PANEL + c;
                *v = if j < n { weight[j * k + i] } else { 0.0 };
            }
        }
    }
}

/// `out[rows x n] = x[rows x k] · B`, `B` (`k x n`) packed by [`pack`], on the calling
/// thread. `out` is overwritten.
///
/// # Panics
/// If a slice length disagrees with the sizes.
pub fn gemm(x: &[f32], rows: usize, k: usize, packed: &[f32], n: usize, out: &mut [f32]) {
    checked(x, rows, k, packed, n, out, false);
}

/// [`gemm`] adding to `out`: `out[rows x n] += x[rows x k] · B`.
///
/// # Panics
/// If a slice length disagrees with the sizes.
pub fn gemm_add(x: &[f32], rows: usize, k: usize, packed: &[f32], n: usize, out: &mut [f32]) {
    checked(x, rows, k, packed, n, out, true);
}

/// [`gemm`] or [`gemm_add`], the lengths checked.
fn checked(x: &[f32], rows: usize, k: usize, packed: &[f32], n: usize, out: &mut [f32], add: bool) {
    assert_eq!(x.len(), rows * k, "panel gemm: input length");
    assert_eq!(packed.len(), packed_len(k, n), "panel gemm: packed length");
    assert_eq!(out.len(), rows * n, "panel gemm: output length");
    if out.is_empty() {
        return;
    }
    if k == 0 {
        if !add {
            out.fill(0.0);
        }
        return;
    }
    pulp::Arch::new().dispatch(Gemm { x, rows, k, packed, n, out, add });
}

struct Gemm<'a> {
    x: &'a [f32],
    rows: usize,
    k: usize,
    packed: &'a [f32],
    n: usize,
    out: &'a mut [f32],
    /// Whether the product adds to `out` instead of overwriting it.
    add: bool,
}

impl pulp::WithSimd for Gemm<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        match size_of::<S::f32s>() / size_of::<f32>() {
            16 => self.tiles::<S, 8, 2>(simd),
            8 => self.tiles::<S, 3, 4>(simd),
            4 => self.tiles::<S, 2, 8>(simd),
            _ => self.tiles::<S, 2, PANEL>(simd),
        }
    }
}

impl Gemm<'_> {
    /// Every block of [`MC`] rows, every [`KC`]-deep slice of `k`, every panel, tile by
    /// tile: `MR` rows at a time (then the rows left over, fewer at a time), each tile `NV`
    /// vectors wide (one panel).
    #[inline(always)]
    fn tiles<S: Simd, const MR: usize, const NV: usize>(self, simd: S) {
        let Gemm { x, rows, k, packed, n, out, add } = self;
        for m0 in (0..rows).step_by(MC) {
            let m1 = rows.min(m0 + MC);
            for k0 in (0..k).step_by(KC) {
                let depth = KC.min(k - k0);
                let t = Tiles { x, k, k0, depth, n, acc: add || k0 > 0 };
                for (p, panel) in packed.chunks_exact(k * PANEL).enumerate() {
                    let (bv, _) = S::as_simd_f32s(&panel[k0 * PANEL..][..depth * PANEL]);
                    let (c0, cols) = (p * PANEL, PANEL.min(n - p * PANEL));
                    let mut r = m0;
                    while r < m1 {
                        let left = m1 - r;
                        r += if left >= MR {
                            t.tile::<S, MR, NV>(simd, r, bv, c0, cols, out)
                        } else if left >= 4 && MR > 4 {
                            t.tile::<S, 4, NV>(simd, r, bv, c0, cols, out)
                        } else if left >= 2 {
                            t.tile::<S, 2, NV>(simd, r, bv, c0, cols, out)
                        } else {
                            t.tile::<S, 1, NV>(simd, r, bv, c0, cols, out)
                        };
                    }
                }
            }
        }
    }
}

/// Rows per block: a block's `MC x KC` slice of the input (256 KiB) stays in the L2
/// cache while every panel reads it.
const MC: usize = 256;

/// Rows of the product's depth per pass: a panel's `KC x PANEL` slice (32 KiB) stays in
/// the L1 cache while every tile of rows reads it.
const KC: usize = 256;

/// The pass over depths `k0..k0 + depth` of `x` (`k` columns) into `out` (`n` columns),
/// adding to what earlier passes wrote when `acc`.
#[derive(Clone, Copy)]
struct Tiles<'a> {
    x: &'a [f32],
    k: usize,
    k0: usize,
    depth: usize,
    n: usize,
    acc: bool,
}

impl Tiles<'_> {
    /// One tile: rows `r0..r0 + MR` of `x` times the panel slice `bv` (`depth` rows of
    /// `NV` vectors), into columns `c0..c0 + cols` of `out`. Returns `MR`.
    #[inline(always)]
    fn tile<S: Simd, const MR: usize, const NV: usize>(
        self,
        simd: S,
        r0: usize,
        bv: &[S::f32s],
        c0: usize,
        cols: usize,
        out: &mut [f32],
    ) -> usize {
        let Tiles { x, k, k0, depth, n, acc: add } = self;
        let lanes = size_of::<S::f32s>() / size_of::<f32>();
        assert_eq!(NV * lanes, PANEL, "panel gemm: {NV} vectors of {lanes} lanes per panel");
        let a: [&[f32]; MR] = std::array::from_fn(|r| &x[(r0 + r) * k + k0..][..depth]);
        let acc = product::<S, MR, NV>(simd, a, &bv[..depth * NV]);
        for (r, sums) in acc.iter().enumerate() {
            let row = &mut out[(r0 + r) * n + c0..][..cols];
            if cols == PANEL {
                let (dst, _) = S::as_mut_simd_f32s(row);
                for (d, s) in dst[..NV].iter_mut().zip(sums) {
                    *d = if add { simd.add_f32s(*d, *s) } else { *s };
                }
            } else {
                for (v, s) in sums.iter().enumerate() {
                    let lo = v * lanes;
                    if lo < cols {
                        let part = &mut row[lo..cols.min(lo + lanes)];
                        let s = if add { simd.add_f32s(simd.partial_load_f32s(part), *s) } else { *s };
                        simd.partial_store_f32s(part, s);
                    }
                }
            }
        }
        MR
    }
}

/// The `MR x NV`-vector sums of the rows `a` (each `depth` long) times `b` (`depth` rows
/// of `NV` vectors), in registers.
#[inline(always)]
fn product<S: Simd, const MR: usize, const NV: usize>(simd: S, a: [&[f32]; MR], b: &[S::f32s]) -> [[S::f32s; NV]; MR] {
    crate::kernels::gemm::rows_product(simd, a, b.chunks_exact(NV))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, data};

    /// `x · Wᵀ` by the definition, in f64.
    fn naive(x: &[f32], rows: usize, k: usize, w: &[f32], n: usize) -> Vec<f32> {
        let mut out = vec![0.0; rows * n];
        for r in 0..rows {
            for j in 0..n {
                let s: f64 = (0..k).map(|i| x[r * k + i] as f64 * w[j * k + i] as f64).sum();
                out[r * n + j] = s as f32;
            }
        }
        out
    }

    #[test]
    fn pack_puts_each_weight_in_its_panel_column() {
        // W is 3 outputs x 2 inputs: W[j][i] = 10 j + i.
        let w = [0.0, 1.0, 10.0, 11.0, 20.0, 21.0];
        let mut p = vec![f32::NAN; packed_len(2, 3)];
        pack(&w, 2, 3, &mut p);
        assert_eq!(p.len(), 2 * PANEL);
        assert_eq!(&p[..4], &[0.0, 10.0, 20.0, 0.0]);
        assert_eq!(&p[PANEL..PANEL + 4], &[1.0, 11.0, 21.0, 0.0]);
        assert!(p[3..PANEL].iter().chain(&p[PANEL + 3..]).all(|&v| v == 0.0), "padding is zero");
    }

    #[test]
    fn gemm_matches_the_definition_on_odd_shapes() {
        // Rows around every tile height, columns around the panel width, k = 1.
        for (rows, k, n) in
            [(1, 1, 1), (3, 5, 7), (8, 16, 32), (9, 17, 33), (25, 31, 64), (13, 1, 95), (49, 40, 65), (5, 600, 40)]
        {
            let x = data(rows * k, rows as u64);
            let w = data(n * k, 100 + n as u64);
            let mut p = vec![0.0; packed_len(k, n)];
            pack(&w, k, n, &mut p);
            let mut out = vec![f32::NAN; rows * n];
            gemm(&x, rows, k, &p, n, &mut out);
            assert_close(&out, &naive(&x, rows, k, &w, n), 1e-5);
        }
    }

    #[test]
    fn gemm_on_every_simd_width_matches() {
        use crate::kernels::testutil::backends;
        let (rows, k, n) = (11, 23, 45);
        let x = data(rows * k, 7);
        let w = data(n * k, 8);
        let mut p = vec![0.0; packed_len(k, n)];
        pack(&w, k, n, &mut p);
        let want = naive(&x, rows, k, &w, n);
        for b in backends() {
            let mut out = vec![f32::NAN; rows * n];
            b.run(Gemm { x: &x, rows, k, packed: &p, n, out: &mut out, add: false });
            assert_close(&out, &want, 1e-5);
        }
    }

    #[test]
    fn gemm_with_no_inputs_is_zero() {
        let mut out = vec![f32::NAN; 6];
        gemm(&[], 2, 0, &[], 3, &mut out);
        assert_eq!(out, vec![0.0; 6]);
    }
}
