//! Camera conditions of the paper (§ Benchmark): exposure as a gamma curve and motion
//! blur as a convolution with a Gaussian-weighted line kernel.
//!
//! Images are float pixels. Both conditions act per pixel or per plane, so the layout
//! only matters for blur, which runs over the last two axes (H, W): `[C, H, W]`,
//! `[N, C, H, W]`, `[N, 6, C, H, W]` as the models take them.

use std::collections::BTreeMap;

/// The paper's exposure levels span γ ∈ {0.25, 0.5, 1, 2, 4}; values outside are refused.
pub const GAMMA_RANGE: (f64, f64) = (0.25, 4.0);

/// The paper's blur levels are kernel sizes {5, 10, 15, 20, 30}; sizes outside are refused.
pub const BLUR_KERNEL_RANGE: (usize, usize) = (5, 30);

/// The Gaussian weighting along the blur line, σ for kernel size k: OpenCV's default for
/// a size-k Gaussian kernel (`getGaussianKernel` with σ ≤ 0), which is what "a Gaussian
/// kernel of size k" means in most image pipelines:
///
/// ```text
/// σ(k) = 0.3 · ((k − 1)/2 − 1) + 0.8        k = 5: 1.1   15: 2.6   30: 4.85
/// ```
///
/// The end taps sit at 1.8σ (k = 5) to 3σ (k = 30): a tapered line, not a box, whose
/// length grows with k.
pub fn blur_sigma(k: usize) -> f64 {
    0.3 * ((k as f64 - 1.0) / 2.0 - 1.0) + 0.8
}

/// Pixel values may exceed [0, 1] by this much (rounding in earlier processing); they are
/// clamped. Anything further out is an error.
pub const RANGE_TOLERANCE: f32 = 1e-4;

/// Checks γ against [`GAMMA_RANGE`].
pub fn check_gamma(gamma: f64) -> Result<(), String> {
    let (lo, hi) = GAMMA_RANGE;
    if gamma.is_finite() && (lo..=hi).contains(&gamma) {
        Ok(())
    } else {
        Err(format!(
            "gamma {gamma} is outside the paper's range [{lo}, {hi}] (γ < 1 under-exposed, 1 unchanged, γ > 1 over-exposed)"
        ))
    }
}

/// Checks a blur kernel size against [`BLUR_KERNEL_RANGE`].
pub fn check_kernel(k: usize) -> Result<(), String> {
    let (lo, hi) = BLUR_KERNEL_RANGE;
    if (lo..=hi).contains(&k) {
        Ok(())
    } else {
        Err(format!("blur kernel size {k} is outside the paper's range [{lo}, {hi}] (sizes 5, 10, 15, 20, 30)"))
    }
}

/// Checks that pixels are finite and in [0, 1] (within [`RANGE_TOLERANCE`]); the error
/// names the first bad element by flat index.
pub fn check_unit_range(pixels: &[f32]) -> Result<(), String> {
    for (i, &v) in pixels.iter().enumerate() {
        if !v.is_finite() {
            return Err(format!("element {i} is {v}; pixels must be finite"));
        }
        if !(-RANGE_TOLERANCE..=1.0 + RANGE_TOLERANCE).contains(&v) {
            let hint = if v > 1.0 && v <= 255.0 { " (8-bit scale? divide by 255)" } else { "" };
            return Err(format!(
                "element {i} is {v}; gamma needs pixels in [0, 1]{hint} (not mean/std-normalised ones)"
            ));
        }
    }
    Ok(())
}

/// Exposure change by a gamma curve, pixel-wise:
///
/// ```text
/// out = clamp(in, 0, 1) ^ (1 / γ)
/// ```
///
/// With pixels in [0, 1], γ < 1 raises them to a power above 1 and darkens the image
/// (under-exposed, as the paper classes γ ∈ [0, 1)); γ > 1 brightens it (over-exposed);
/// γ = 1 returns the input unchanged, bit for bit. 0 and 1 are fixed points.
/// Example: in = 0.5, γ = 0.5 → 0.25; γ = 2 → 0.7071; γ = 4 → 0.8409; γ = 0.25 → 0.0625.
pub fn gamma(pixels: &[f32], gamma: f64) -> Result<Vec<f32>, String> {
    check_gamma(gamma)?;
    check_unit_range(pixels)?;
    if gamma == 1.0 {
        return Ok(pixels.iter().map(|v| v.clamp(0.0, 1.0)).collect());
    }
    let exponent = 1.0 / gamma;
    Ok(pixels.iter().map(|&v| (f64::from(v.clamp(0.0, 1.0)).powf(exponent) as f32).clamp(0.0, 1.0)).collect())
}

/// One tap of a 2-D kernel: `out[y][x] += weight * in[y + dy][x + dx]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tap {
    pub dy: isize,
    pub dx: isize,
    pub weight: f32,
}

/// The motion-blur kernel of size k along direction `angle_deg` (degrees counter-clockwise
/// from the +x axis as the image is displayed; 0 = horizontal, 90 = vertical):
///
/// ```text
/// t_i = i − (k − 1)/2,   i = 0 .. k−1           (positions along the line, in pixels)
/// w_i = exp(−t_i² / (2σ²)) / Σ_j exp(−t_j² / (2σ²)),   σ = blur_sigma(k)
/// tap i sits at (dx, dy) = (t_i cos θ, −t_i sin θ)
/// ```
///
/// A tap off the pixel grid (any angle but multiples of 90°, or half-pixel positions
/// when k is even) is split bilinearly over its four neighbours, so the weights always
/// sum to 1 and a constant image stays constant. For k odd and θ = 0 the kernel is the
/// 1-D row `w_0 .. w_{k−1}` exactly; for k = 5: σ = 1.1 and
/// w = (0.070766, 0.244460, 0.369546, 0.244460, 0.070766).
pub fn motion_kernel(k: usize, angle_deg: f64) -> Result<Vec<Tap>, String> {
    check_kernel(k)?;
    if !angle_deg.is_finite() {
        return Err(format!("blur angle {angle_deg} is not a finite number of degrees"));
    }
    let sigma = blur_sigma(k);
    let centre = (k as f64 - 1.0) / 2.0;
    let raw: Vec<f64> = (0..k).map(|i| (-(i as f64 - centre).powi(2) / (2.0 * sigma * sigma)).exp()).collect();
    let total: f64 = raw.iter().sum();
    let (sin, cos) = angle_deg.to_radians().sin_cos();
    // Snap direction cosines that are zero or one up to rounding (cos 90° = 6e-17), so
    // axis-aligned kernels land exactly on the grid.
    let snap = |v: f64| if (v - v.round()).abs() < 1e-9 { v.round() } else { v };
    let (sin, cos) = (snap(sin), snap(cos));
    let mut taps: BTreeMap<(isize, isize), f64> = BTreeMap::new();
    for (i, w) in raw.iter().enumerate() {
        let t = i as f64 - centre;
        let (x, y) = (snap(t * cos), snap(-t * sin));
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        for (dy, wy) in [(0.0, 1.0 - fy), (1.0, fy)] {
            for (dx, wx) in [(0.0, 1.0 - fx), (1.0, fx)] {
                let part = w / total * wy * wx;
                if part > 0.0 {
                    *taps.entry(((y0 + dy) as isize, (x0 + dx) as isize)).or_insert(0.0) += part;
                }
            }
        }
    }
    Ok(taps.into_iter().map(|((dy, dx), w)| Tap { dy, dx, weight: w as f32 }).collect())
}

/// Motion blur of every `height x width` plane in `planes` (the last two axes of the
/// tensor) with [`motion_kernel`]: `out[y][x] = Σ w · in[clamp(y+dy)][clamp(x+dx)]`, edges
/// clamped (replicated). Any finite values are accepted (blur is linear).
pub fn motion_blur(planes: &[f32], height: usize, width: usize, k: usize, angle_deg: f64) -> Result<Vec<f32>, String> {
    let taps = motion_kernel(k, angle_deg)?;
    let plane = height * width;
    if plane == 0 || !planes.len().is_multiple_of(plane) {
        return Err(format!("{} values are not whole {height}x{width} planes", planes.len()));
    }
    if let Some(i) = planes.iter().position(|v| !v.is_finite()) {
        return Err(format!("element {i} is {}; pixels must be finite", planes[i]));
    }
    let clamp = |v: isize, n: usize| v.clamp(0, n as isize - 1) as usize;
    let mut out = vec![0.0f32; planes.len()];
    for (src, dst) in planes.chunks_exact(plane).zip(out.chunks_exact_mut(plane)) {
        for tap in &taps {
            let cols: Vec<usize> = (0..width).map(|x| clamp(x as isize + tap.dx, width)).collect();
            for y in 0..height {
                let row = &src[clamp(y as isize + tap.dy, height) * width..][..width];
                for (o, &c) in dst[y * width..][..width].iter_mut().zip(&cols) {
                    *o += tap.weight * row[c];
                }
            }
        }
    }
    Ok(out)
}

/// A sharpness measure: the variance of the 4-neighbour Laplacian over the interior
/// pixels of one plane (higher = sharper; blur lowers it); 0 for planes under 3x3. The
/// same measure as the `laplacian_var` selector statistic, which it calls.
pub fn laplacian_variance(plane: &[f32], height: usize, width: usize) -> f64 {
    if height < 3 || width < 3 || plane.len() < height * width {
        return 0.0;
    }
    use readi_runtime::conditions::{Statistic, statistic};
    statistic(Statistic::LaplacianVar, &plane[..height * width], &[height, width])
}

/// The mean of some values (f64 accumulation); `None` when empty.
pub fn mean(values: &[f32]) -> Option<f64> {
    (!values.is_empty()).then(|| values.iter().map(|&v| f64::from(v)).sum::<f64>() / values.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gamma_matches_hand_values_and_validates() {
        let out = gamma(&[0.0, 0.25, 0.5, 1.0], 0.5).expect("gamma 0.5");
        assert_eq!(out[0], 0.0);
        assert!((out[1] - 0.0625).abs() < 1e-7 && (out[2] - 0.25).abs() < 1e-7 && out[3] == 1.0, "{out:?}");
        let out = gamma(&[0.5], 2.0).expect("gamma 2");
        assert!((out[0] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
        assert!(gamma(&[0.5], 0.2).expect_err("out of range").contains("[0.25, 4]"));
        assert!(gamma(&[0.5], f64::NAN).is_err());
        assert!(gamma(&[1.5], 2.0).expect_err("above 1").contains("element 0 is 1.5"));
        assert!(gamma(&[0.2, f32::NAN], 2.0).expect_err("nan").contains("element 1 is NaN"));
        assert!(gamma(&[128.0], 2.0).expect_err("8-bit").contains("divide by 255"));
    }

    #[test]
    fn kernel_is_normalised_for_every_size_and_angle() {
        for k in [5, 6, 10, 15, 20, 30] {
            for angle in [0.0, 30.0, 45.0, 90.0, 137.0, -20.0] {
                let taps = motion_kernel(k, angle).expect("kernel");
                let sum: f32 = taps.iter().map(|t| t.weight).sum();
                assert!((sum - 1.0).abs() < 1e-5, "k={k} angle={angle}: sum {sum}");
            }
        }
        let vertical = motion_kernel(5, 90.0).expect("vertical");
        assert!(vertical.iter().all(|t| t.dx == 0) && vertical.len() == 5, "{vertical:?}");
        assert!(motion_kernel(4, 0.0).is_err() && motion_kernel(31, 0.0).is_err());
        assert!(motion_kernel(5, f64::INFINITY).is_err());
    }

    #[test]
    fn blur_rejects_bad_planes() {
        assert!(motion_blur(&[0.0; 10], 3, 3, 5, 0.0).expect_err("not whole planes").contains("3x3"));
        assert!(motion_blur(&[f32::NAN; 9], 3, 3, 5, 0.0).is_err());
    }

    #[test]
    fn laplacian_variance_of_flat_and_checkerboard() {
        assert_eq!(laplacian_variance(&[0.3; 16], 4, 4), 0.0);
        let board: Vec<f32> = (0..16).map(|i| ((i / 4 + i % 4) % 2) as f32).collect();
        assert!(laplacian_variance(&board, 4, 4) > 1.0);
    }
}
