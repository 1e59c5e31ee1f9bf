//! Max pooling with a 3x3 window at stride 2 (ResNet's, after the stem), with AVX-512 and
//! rows of at least 16 outputs: each input row read where it lies, in vectors.
//!
//! Sixteen outputs of a row need 33 input columns from `2 ox - pad` on: two full loads
//! and the first lane of a third, their lanes outside the row (the padding, or past it
//! with `ceil_mode`) filled with `-inf`, which changes no maximum. Along each input row two
//! permutes split the first two vectors into even and odd columns, the windows' first and
//! second columns, and a third shifts the even ones one lane on for their third column
//! (`rows512::even_odd`, `next_column`: the depthwise path's stride-2 taps); the maximum
//! of the three is that row's share of sixteen windows. A plane goes by columns of sixteen
//! outputs, the output rows downwards, so that the row two windows share (the last of one,
//! the first of the next) is read and combined once. NaN propagates: each maximum adds its
//! operands where either is NaN.
//!
//! Measured on the 2-core AMD EPYC (Zen 4, 2026-12-07, `kernel_speed maxpool`: ResNet's
//! layer, [64, 112, 112] to 56x56, alone, one / two threads): 124 / 64 us against the
//! generic rows' 252 / 129 (`pool_rows`: each window row through a stack buffer, its even
//! and odd columns split by scalar copies, selects for the maxima); row by row, every
//! window's three rows loaded, 178 / 92. ORT took 128 us in the model.

use core::arch::x86_64::{__m512, _CMP_UNORD_Q};

use pulp::x86::V4;
use pulp::{Simd, cast};

use super::{Pool2dShape, PoolKind, window};
use crate::kernels::conv::vector_starts;
use crate::kernels::rows512::{L, even_odd, load_or, next_column, row_mask};

/// Whether a pooling takes this path: max, a 3x3 window at stride 2, padding of at most
/// one, output rows of at least a vector, AVX-512 at run time.
pub(super) fn applies(kind: PoolKind, s: &Pool2dShape) -> bool {
    kind == PoolKind::Max
        && (s.kh, s.kw, s.stride_h, s.stride_w) == (3, 3, 2, 2)
        && s.pad_h <= 1
        && s.pad_w <= 1
        && s.ow >= L
        && V4::try_new().is_some()
}

/// Output rows `first..` (counted over all planes) of a pooling [`applies`] takes, into
/// `out`.
pub(super) fn rows(s: &Pool2dShape, x: &[f32], first: usize, out: &mut [f32]) {
    let simd = V4::try_new().expect("pool::in_place::applies checks AVX-512");
    let task = Task { s, x, first, out };
    // Compiled with AVX-512 enabled: everything `run` calls is inlined into it.
    simd.vectorize(
        #[inline(always)]
        move || task.run(simd),
    )
}

/// What a task hands to the AVX-512 code as one value (see `conv/depthwise/in_place.rs`'s
/// `Task` for why).
struct Task<'a> {
    s: &'a Pool2dShape,
    x: &'a [f32],
    first: usize,
    out: &'a mut [f32],
}

impl Task<'_> {
    #[inline(always)]
    fn run(self, simd: V4) {
        let Task { s, x, first, out } = self;
        let w = s.w as isize;
        // The task's rows, plane by plane; in each, vector column by vector column, the
        // output rows downwards, each window's last row (the next one's first) carried.
        let mut row = first;
        let mut out = out;
        while !out.is_empty() {
            let (plane, oy0) = (row / s.oh, row % s.oh);
            let n = (s.oh - oy0).min(out.len() / s.ow);
            let (dst, rest) = std::mem::take(&mut out).split_at_mut(n * s.ow);
            let xp = &x[plane * s.h * s.w..][..s.h * s.w];
            for ox in vector_starts(s.ow, L) {
                let col = (2 * ox) as isize - s.pad_w as isize;
                let m = [row_mask(col, w), row_mask(col + L as isize, w), row_mask(col + 2 * L as isize, w) & 1];
                let mut carried: Option<(usize, __m512)> = None;
                for oy in oy0..oy0 + n {
                    // At least one row: the window starts inside the input or its padding of
                    // at most one, and ends at least one row later.
                    let wy = window(oy, s.h, 3, 2, s.pad_h);
                    let mut y = match carried {
                        Some((r, v)) if r == wy.start => v,
                        _ => across(simd, &xp[wy.start * s.w..][..s.w], col, m),
                    };
                    for r in wy.start + 1..wy.end {
                        let v = across(simd, &xp[r * s.w..][..s.w], col, m);
                        y = max_nan(simd, y, v);
                        carried = Some((r, v));
                    }
                    V4::as_mut_simd_f32s(&mut dst[(oy - oy0) * s.ow + ox..][..L]).0[0] = cast(y);
                }
            }
            out = rest;
            row += n;
        }
    }
}

/// The maxima of the three columns of the windows of sixteen outputs along one input
/// `row`: columns `col..col + 33`, the lanes of `m` inside the row, `-inf` elsewhere.
#[inline(always)]
fn across(simd: V4, row: &[f32], col: isize, m: [u16; 3]) -> __m512 {
    let low = simd.avx512f._mm512_set1_ps(f32::NEG_INFINITY);
    let a = load_or(simd, low, row, col, m[0]);
    let b = load_or(simd, low, row, col + L as isize, m[1]);
    let c = load_or(simd, low, row, col + 2 * L as isize, m[2]);
    // The even columns, the odd ones, and the even ones one on (the last from `c`).
    let (left, mid) = even_odd(simd, a, b);
    let right = next_column(simd, left, c, 0);
    max_nan(simd, max_nan(simd, left, mid), right)
}

/// The larger of `a` and `b` lane by lane, NaN where either is NaN (their sum there).
#[inline(always)]
fn max_nan(simd: V4, a: __m512, b: __m512) -> __m512 {
    let f = simd.avx512f;
    let either = f._mm512_cmp_ps_mask::<_CMP_UNORD_Q>(a, b);
    f._mm512_mask_add_ps(f._mm512_max_ps(a, b), either, a, b)
}
