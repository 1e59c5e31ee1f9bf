//! What the AVX-512 paths that read rows in place share: the mask of a vector's lanes that
//! fall inside a row, and the masked load of those lanes (the rest filled), so that a
//! row's padding is never read nor copied; and at stride 2, the split of 32 consecutive
//! columns into their even and odd ones (`conv/depthwise/in_place.rs`,
//! `pool/in_place.rs`).

use core::arch::x86_64::{__m512, __m512i};

use pulp::cast;
use pulp::x86::V4;

/// Floats a vector holds (AVX-512).
pub(crate) const L: usize = 16;

/// The lanes of a vector loaded from column `from` of a row of `w` floats that fall
/// inside the row.
#[inline(always)]
pub(crate) fn row_mask(from: isize, w: isize) -> u16 {
    let lo = (-from).clamp(0, L as isize);
    let hi = (w - from).clamp(0, L as isize);
    if hi <= lo { 0 } else { (((1u32 << hi) - 1) & !((1u32 << lo) - 1)) as u16 }
}

/// The lanes `m` of the sixteen floats from column `from` of `row`, `fill`'s lanes
/// elsewhere; `m` from [`row_mask`], so only columns inside the row are read.
#[inline(always)]
pub(crate) fn load_or(simd: V4, fill: __m512, row: &[f32], from: isize, m: u16) -> __m512 {
    debug_assert_eq!(m, m & row_mask(from, row.len() as isize), "rows512: a lane outside the row");
    // SAFETY: the masked load reads only the lanes of `m`, columns `from + i` inside
    // `0..row.len()` (`row_mask`); masked-off lanes do not fault, so the address before or
    // past the row (`wrapping_offset`) is never dereferenced.
    #[allow(unsafe_code)]
    unsafe {
        simd.avx512f._mm512_mask_loadu_ps(fill, m, row.as_ptr().wrapping_offset(from))
    }
}

/// The even and odd columns of the 32 in `a` then `b` (two permutes).
#[inline(always)]
pub(crate) fn even_odd(simd: V4, a: __m512, b: __m512) -> (__m512, __m512) {
    let f = simd.avx512f;
    let even: __m512i = cast(pulp::u32x16(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30));
    let odd: __m512i = cast(pulp::u32x16(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31));
    (f._mm512_permutex2var_ps(a, even, b), f._mm512_permutex2var_ps(a, odd, b))
}

/// The lanes of `t` one on, the last one lane `m` of `c`: at stride 2 the tap two columns
/// after `t`'s, its last column from a third load (one permute).
#[inline(always)]
pub(crate) fn next_column(simd: V4, t: __m512, c: __m512, m: u32) -> __m512 {
    let lanes: __m512i = cast(pulp::u32x16(1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16 + m));
    simd.avx512f._mm512_permutex2var_ps(t, lanes, c)
}
