//! What the AVX-512 paths that read rows in place share: the mask of a vector's lanes that
//! fall inside a row, and the masked load of those lanes (the rest filled), so that a
//! row's padding is never read nor copied (`conv/depthwise/in_place.rs`,
//! `pool/in_place.rs`).

use core::arch::x86_64::__m512;

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

/// [`load_or`] with zeros in the lanes outside the row.
#[inline(always)]
pub(crate) fn load_zero(simd: V4, row: &[f32], from: isize, m: u16) -> __m512 {
    debug_assert_eq!(m, m & row_mask(from, row.len() as isize), "rows512: a lane outside the row");
    // SAFETY: as `load_or`'s.
    #[allow(unsafe_code)]
    unsafe {
        simd.avx512f._mm512_maskz_loadu_ps(m, row.as_ptr().wrapping_offset(from))
    }
}
