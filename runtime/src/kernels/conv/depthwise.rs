//! [`ConvAlgo::Depthwise`](super::ConvAlgo::Depthwise), one input channel per group: a
//! direct loop per output plane with the epilogue, parallel over the planes; no GEMM, no
//! scratch.

use rayon::prelude::*;

use super::Conv2dShape;
use crate::kernels::Epilogue;

/// Direct conv for one input channel per group, parallel over output planes.
pub(super) fn depthwise(s: &Conv2dShape, w: &[f32], ep: &Epilogue, x: &[f32], out: &mut [f32], threads: usize) {
    let plane = s.oh * s.ow;
    let one = |(idx, dst): (usize, &mut [f32])| {
        let (n, c) = (idx / s.cout, idx % s.cout);
        let g = c / s.cout_g();
        let xc = &x[(n * s.cin + g) * s.h * s.w..][..s.h * s.w];
        let k = &w[c * s.kh * s.kw..][..s.kh * s.kw];
        depthwise_plane(s, xc, k, c, ep, dst);
    };
    if threads <= 1 {
        out.chunks_mut(plane).enumerate().for_each(one);
    } else {
        out.par_chunks_mut(plane).enumerate().for_each(one);
    }
}

simd_fn! {
    /// One output plane (channel `c`) of a depthwise conv, with the epilogue.
    fn depthwise_plane(s: &Conv2dShape, xc: &[f32], k: &[f32], c: usize, ep: &Epilogue<'_>, dst: &mut [f32]) {
        depthwise_acc(s, xc, k, dst);
        let acc_scale = ep.scale.map_or(1.0, |v| v[c]);
        let shift = ep.shift.map_or(0.0, |v| v[c]);
        if ep.relu() {
            dst.iter_mut().for_each(|d| *d = (*d * acc_scale + shift).max(0.0));
        } else {
            dst.iter_mut().for_each(|d| *d = *d * acc_scale + shift);
        }
        ep.finish_act(dst);
    }
}

/// The accumulation of a depthwise conv plane into `dst`.
#[inline(always)]
fn depthwise_acc(s: &Conv2dShape, xc: &[f32], k: &[f32], dst: &mut [f32]) {
    dst.fill(0.0);
    let (h, w) = (s.h as isize, s.w as isize);
    for (oy, row) in dst.chunks_mut(s.ow).enumerate() {
        for ky in 0..s.kh {
            let iy = (oy * s.stride_h + ky * s.dil_h) as isize - s.pad_h as isize;
            if iy < 0 || iy >= h {
                continue;
            }
            let src = &xc[iy as usize * s.w..][..s.w];
            for kx in 0..s.kw {
                let wv = k[ky * s.kw + kx];
                let dx = (kx * s.dil_w) as isize - s.pad_w as isize;
                let ox_lo = ((-dx).max(0) as usize).div_ceil(s.stride_w).min(s.ow);
                let ox_hi = if w - dx <= 0 { 0 } else { ((w - dx) as usize).div_ceil(s.stride_w).min(s.ow) };
                if ox_lo >= ox_hi {
                    continue;
                }
                let ix0 = ((ox_lo * s.stride_w) as isize + dx) as usize;
                let body = &mut row[ox_lo..ox_hi];
                if s.stride_w == 1 {
                    for (d, &v) in body.iter_mut().zip(&src[ix0..]) {
                        *d += wv * v;
                    }
                } else {
                    for (d, &v) in body.iter_mut().zip(src[ix0..].iter().step_by(s.stride_w)) {
                        *d += wv * v;
                    }
                }
            }
        }
    }
}
