//! Lidar conditions of the paper (§ Benchmark): fog after Hahner et al. 2021 and snow
//! after Hahner et al. 2022, simplified to closed forms on point clouds.
//!
//! A point cloud is `N x C` float32, row-major: x, y, z in metres in the sensor frame,
//! intensity, then up to four extra columns (nuScenes' ring index, STF's channel) that
//! are carried along unchanged. Each point is one ray of a single-return sensor.
//!
//! # The sensor model both conditions share
//!
//! Intensity is taken as range-compensated reflectivity ρ = intensity / full scale
//! (KITTI: full scale 1; nuScenes: 255). A return's received power relative to the
//! detection threshold in clear air, its *margin*, follows the lidar equation for an
//! extended target, power ∝ ρ / R²:
//!
//! ```text
//! m_clear(R, ρ) = max(1, max(ρ, ρ_min) / R² / K)
//! K = min(0.10 / (50 m)², min over the cloud's returns of max(ρ, ρ_min) / R²)
//! ```
//!
//! K, the weakest detectable ρ/R², comes from the Velodyne HDL-64E data sheet (50 m on
//! 10%-reflective pavement) unless the cloud itself holds weaker returns: the sensor that
//! recorded it saw all of them, so it is at least that sensitive. `ρ_min` =
//! [`MIN_REFLECTIVITY`] keeps the many zero-intensity returns of real clouds from counting
//! as infinitely weak. Through a medium of extinction coefficient α the pulse travels to
//! the target and back (two-way Beer–Lambert, Hahner et al. 2021's hard-target term):
//!
//! ```text
//! m(R) = m_clear(R, ρ) · exp(−2αR)       intensity' = intensity · exp(−2αR)
//! ```
//!
//! and the return is lost when m < 1. A scatterer in front of the target (fog droplets,
//! a snowflake) returns its own pulse; the sensor reports the stronger of the two
//! (strongest-return mode), so a scattered return replaces the ray's point when its
//! margin exceeds the target's. Point counts therefore only fall: N' = N − lost.
//!
//! # Determinism
//!
//! One ChaCha8 stream (`rand::rngs::ChaCha8Rng`) seeded with `seed` (`seed_from_u64`)
//! draws a fixed number of uniforms per point in input order, whatever the branch taken.
//! So the same seed gives the same bytes, and across severities the draws are coupled:
//! with one seed, a denser fog scatters a superset of the rays a lighter one scatters,
//! which makes the simulated trends monotone frame by frame, not only on average.

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};

/// Columns of a point: x, y, z, intensity, then extras carried along.
pub const MIN_COLUMNS: usize = 4;
/// At most four extra columns (nuScenes' ring index or time lag, STF's channel, ...).
pub const MAX_COLUMNS: usize = 8;

/// Meteorological optical range: the distance at which a beam keeps 5% of its power
/// (Koschmieder's contrast threshold), `MOR = ln(1 / 0.05) / α = ln 20 / α`.
pub const MOR_TRANSMISSION: f64 = 0.05;

/// The HDL-64E data sheet: 50 m range on 10%-reflective pavement. With the 1/R² law
/// this gives 141 m for 80% reflectivity (the data sheet says 120 m for cars). Used
/// for the detection threshold K unless the cloud proves the sensor more sensitive.
pub const REF_RANGE_M: f64 = 50.0;
/// See [`REF_RANGE_M`].
pub const REF_REFLECTIVITY: f64 = 0.10;
/// Reflectivity floor in the margin (2%: black rubber), see the module doc.
pub const MIN_REFLECTIVITY: f64 = 0.02;

/// The paper's fog densities: α ∈ {0.01, 0.02, 0.03, 0.06, 0.1, 0.12, 0.15} 1/m.
pub const FOG_ALPHA_RANGE: (f64, f64) = (0.01, 0.15);
/// Fog returns start here: the transmitter and receiver fields of view overlap fully
/// beyond about 1 m (Hahner et al. 2021 use R₂ = 1 m), and the pulse (20 ns half-power
/// width, c·τ/2 = 3 m) smears the first metres; we take 2 m.
pub const FOG_MIN_RANGE_M: f64 = 2.0;
/// The mean fog-return margin is `α / FOG_UNIT_ALPHA`. Hahner et al. take the backscatter
/// coefficient β = 0.046 / MOR ∝ α, so the fog's return grows linearly with α. The
/// scale is set so that at α = 0.03 a ray whose target is out of reach shows a fog
/// return 5% of the time, exp(−1 / (0.03 / a)) = 0.05 → a = 0.03 · ln 20 ≈ 0.0899 1/m,
/// the order of the paper's "≈5% distorted points at α = 0.03".
pub const FOG_UNIT_ALPHA: f64 = 0.03 * 2.995_732_273_553_991;

/// The paper's snowfall rates: β ∈ {0.5, 1.0, 1.5, 2.0, 2.5} mm/h (liquid equivalent).
pub const SNOW_RATE_RANGE: (f64, f64) = (0.5, 2.5);
/// Probability per ray and per mm/h that a snowflake inside [`SNOW_MIN_RANGE_M`],
/// [`SNOW_MAX_RANGE_M`] intercepts the beam: 1% per mm/h, 0.5% .. 2.5% over the paper's
/// rates. The paper finds snow distorts lidar less than fog; this keeps it so.
pub const SNOW_HIT_PER_MMH: f64 = 0.01;
/// Flakes closer than this are inside the transmitter/receiver blind zone (as fog).
pub const SNOW_MIN_RANGE_M: f64 = 1.0;
/// Flakes farther than this cover too little of the diverging beam to trigger it.
pub const SNOW_MAX_RANGE_M: f64 = 15.0;
/// Snow reflects strongly: Hahner et al. 2022 give a flake 90% reflectivity; a flake
/// covers a fraction of the beam, uniform in [2/3, 1] here, so the reported reflectivity
/// is uniform in [0.6, 0.9].
pub const SNOW_REFLECTIVITY: f64 = 0.9;
/// Visibility in snow: about 1 km at 1 mm/h, V ≈ 1000 m / β, so heavy snow (2.5 mm/h)
/// brings it to 400 m, the US weather service's "heavy snow" visibility (≤ 1/4 mile).
/// The real relation scatters by 3–10x with crystal type (Rasmussen et al. 1999). The
/// extinction coefficient is then ln 20 / V.
pub const SNOW_VISIBILITY_M_PER_MMH: f64 = 1000.0;

/// Returns within this range of the sensor count as "near" in the reports.
pub const NEAR_RANGE_M: f32 = 10.0;

/// An `N x columns` point cloud, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud {
    columns: usize,
    data: Vec<f32>,
}

impl PointCloud {
    /// Checks the layout and the values: finite, intensity ≥ 0. Errors name the row.
    pub fn new(columns: usize, data: Vec<f32>) -> Result<Self, String> {
        if !(MIN_COLUMNS..=MAX_COLUMNS).contains(&columns) {
            return Err(format!(
                "a point cloud has {MIN_COLUMNS} to {MAX_COLUMNS} columns (x, y, z, intensity, extras), not {columns}"
            ));
        }
        if !data.len().is_multiple_of(columns) {
            return Err(format!("{} values are not whole rows of {columns}", data.len()));
        }
        for (row, p) in data.chunks_exact(columns).enumerate() {
            if let Some(c) = p.iter().position(|v| !v.is_finite()) {
                return Err(format!("point {row} has {} in column {c}; points must be finite", p[c]));
            }
            if p[3] < 0.0 {
                return Err(format!("point {row} has a negative intensity ({})", p[3]));
            }
        }
        Ok(PointCloud { columns, data })
    }

    pub fn columns(&self) -> usize {
        self.columns
    }

    pub fn len(&self) -> usize {
        self.data.len() / self.columns
    }

    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The rows.
    pub fn points(&self) -> impl Iterator<Item = &[f32]> {
        self.data.chunks_exact(self.columns)
    }

    /// The values, row-major.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Mean intensity; `None` for an empty cloud.
    pub fn mean_intensity(&self) -> Option<f64> {
        (!self.is_empty()).then(|| self.points().map(|p| f64::from(p[3])).sum::<f64>() / self.len() as f64)
    }

    /// Points closer than `range` metres to the sensor.
    pub fn count_within(&self, range: f32) -> usize {
        self.points().filter(|p| range_of(p) < range).count()
    }

    /// The intensity full scale: 1 when every intensity is at most 1 (KITTI), 255 when at
    /// most 255 (nuScenes, STF), else the largest intensity.
    pub fn intensity_scale(&self) -> f32 {
        let max = self.points().map(|p| p[3]).fold(0.0f32, f32::max);
        if max <= 1.0 {
            1.0
        } else if max <= 255.0 {
            255.0
        } else {
            max
        }
    }
}

/// What a simulation did, for the one-line summary.
#[derive(Clone, Debug, PartialEq)]
pub struct LidarReport {
    pub points_in: usize,
    pub points_out: usize,
    /// Returns that fell below the detection threshold and no scatterer replaced.
    pub lost: usize,
    /// Rays whose point is now a fog or snowflake return.
    pub scattered: usize,
    pub mean_intensity_in: Option<f64>,
    pub mean_intensity_out: Option<f64>,
    /// Points within [`NEAR_RANGE_M`] before and after.
    pub near_in: usize,
    pub near_out: usize,
    /// The full scale intensities were divided by.
    pub intensity_scale: f32,
}

fn range_of(p: &[f32]) -> f32 {
    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
}

/// `MOR = ln(1 / 0.05) / α`: 49.9 m at α = 0.06.
pub fn mor(alpha: f64) -> f64 {
    (1.0 / MOR_TRANSMISSION).ln() / alpha
}

/// The snow extinction coefficient for a rate in mm/h: `ln 20 / (1000 m / β)`.
pub fn snow_extinction(rate: f64) -> f64 {
    (1.0 / MOR_TRANSMISSION).ln() * rate / SNOW_VISIBILITY_M_PER_MMH
}

/// The weakest detectable ρ/R², K (module doc): the data sheet's, or the cloud's weakest
/// return's when that is weaker. Returns closer than 1 m do not count.
pub fn detection_threshold(cloud: &PointCloud, scale: f32) -> f64 {
    let sheet = REF_REFLECTIVITY / (REF_RANGE_M * REF_RANGE_M);
    cloud
        .points()
        .map(|p| (f64::from(range_of(p)), f64::from(p[3] / scale)))
        .filter(|&(r, _)| r >= 1.0)
        .map(|(r, rho)| rho.max(MIN_REFLECTIVITY) / (r * r))
        .fold(sheet, f64::min)
}

/// The clear-air margin of a return for detection threshold `k` (module doc).
pub fn clear_margin(range: f64, reflectivity: f64, k: f64) -> f64 {
    let r = range.max(1e-3);
    (reflectivity.max(MIN_REFLECTIVITY) / (r * r) / k).max(1.0)
}

fn check_level(what: &str, unit: &str, v: f64, (lo, hi): (f64, f64)) -> Result<(), String> {
    if v.is_finite() && (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(format!("{what} {v} is outside the paper's range [{lo}, {hi}] {unit}"))
    }
}

/// Full scale for intensities: the given one (must be positive) or the cloud's own.
fn scale_for(cloud: &PointCloud, scale: Option<f32>) -> Result<f32, String> {
    match scale {
        Some(s) if s.is_finite() && s > 0.0 => Ok(s),
        Some(s) => Err(format!("intensity scale {s} must be a positive number")),
        None => Ok(cloud.intensity_scale()),
    }
}

/// Moves a point along its ray to `range` with a new intensity; extras stay.
fn along_ray(p: &[f32], range: f64, intensity: f32, out: &mut Vec<f32>) {
    let k = (range / f64::from(range_of(p))) as f32;
    out.extend([p[0] * k, p[1] * k, p[2] * k, intensity]);
    out.extend_from_slice(&p[4..]);
}

/// Fog of extinction coefficient `alpha` (1/m), after Hahner et al. 2021, "Fog Simulation
/// on Real LiDAR Point Clouds for 3D Object Detection in Adverse Weather" (ICCV).
///
/// For each ray with target range R and reflectivity ρ, with the module's margin m(R):
///
/// - The target return is attenuated: `intensity' = intensity · exp(−2αR)`; it is lost
///   when m(R) < 1.
/// - The fog in front of the target returns a soft-target pulse. Its margin is
///   `F = (α / a) · E`, `a` = [`FOG_UNIT_ALPHA`]: the mean grows with the backscatter
///   coefficient β ∝ α (Hahner et al.), and E ~ Exp(1) is the speckle of a return summed
///   over many random droplets. If F ≥ 1 and F > m(R), the ray reports the fog: the point
///   moves along its ray to a range r drawn with density ∝ 1/r² on
///   [2 m, min(R, MOR/2)] (the fog's backscatter falls as 1/r² and, beyond MOR/2, the
///   two-way transmission exp(−2α·MOR/2) = 5%), with the reflectivity a return of margin
///   F at r reports: `ρ = F · K · r²` (very weak: under 1% of full scale on the tests'
///   synthetic scan).
///
/// So fog lowers intensities, removes far and dark returns and clusters weak returns
/// near the sensor, all more so as α grows. Draws per point: E, then r.
pub fn fog(
    cloud: &PointCloud,
    alpha: f64,
    seed: u64,
    intensity_scale: Option<f32>,
) -> Result<(PointCloud, LidarReport), String> {
    check_level("fog alpha", "1/m", alpha, FOG_ALPHA_RANGE)?;
    let scale = scale_for(cloud, intensity_scale)?;
    let k = detection_threshold(cloud, scale);
    let half_mor = mor(alpha) / 2.0;
    let mean_fog = alpha / FOG_UNIT_ALPHA;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::with_capacity(cloud.data.len());
    let (mut lost, mut scattered) = (0, 0);
    for p in cloud.points() {
        let (u_speckle, u_range): (f64, f64) = (rng.random(), rng.random());
        let range = f64::from(range_of(p));
        let transmission = (-2.0 * alpha * range).exp();
        let margin = clear_margin(range, f64::from(p[3] / scale), k) * transmission;
        let fog_margin = mean_fog * -(1.0 - u_speckle).ln();
        let far = range.min(half_mor);
        if far > FOG_MIN_RANGE_M && fog_margin >= 1.0 && fog_margin > margin {
            // Inverse CDF of the density ∝ 1/r² on [near, far].
            let near = FOG_MIN_RANGE_M;
            let r = 1.0 / (1.0 / near - u_range * (1.0 / near - 1.0 / far));
            let reflectivity = (fog_margin * k * r * r).min(1.0);
            along_ray(p, r, reflectivity as f32 * scale, &mut out);
            scattered += 1;
        } else if margin >= 1.0 {
            out.extend([p[0], p[1], p[2], (f64::from(p[3]) * transmission) as f32]);
            out.extend_from_slice(&p[4..]);
        } else {
            lost += 1;
        }
    }
    finish(cloud, out, lost, scattered, scale)
}

/// Snowfall of `rate` mm/h (liquid equivalent), after Hahner et al. 2022, "LiDAR Snowfall
/// Simulation for Robust 3D Object Detection" (CVPR), simplified from their per-beam
/// particle sampling to one interception draw per ray.
///
/// - Snow attenuates like a thin fog of extinction `ln 20 · β / 1000 m`
///   ([`snow_extinction`]: visibility 1000 m / β): `intensity' = intensity · exp(−2α_s R)`,
///   lost when the margin falls below 1 (rare: α_s ≤ 0.0075 1/m).
/// - With probability `0.01 · β` a snowflake intercepts the ray at a range uniform in
///   [1 m, min(R, 15 m)]. It reflects strongly (90% reflectivity, beam covered by a
///   fraction uniform in [2/3, 1]: intensity uniform in [0.6, 0.9] of full scale) and
///   replaces the target's point when its margin is the larger, which at these ranges it
///   nearly always is.
///
/// Draws per point: hit, range, covered fraction.
pub fn snow(
    cloud: &PointCloud,
    rate: f64,
    seed: u64,
    intensity_scale: Option<f32>,
) -> Result<(PointCloud, LidarReport), String> {
    check_level("snowfall rate", "mm/h", rate, SNOW_RATE_RANGE)?;
    let scale = scale_for(cloud, intensity_scale)?;
    let k = detection_threshold(cloud, scale);
    let alpha = snow_extinction(rate);
    let p_hit = SNOW_HIT_PER_MMH * rate;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::with_capacity(cloud.data.len());
    let (mut lost, mut scattered) = (0, 0);
    for p in cloud.points() {
        let (u_hit, u_range, u_cover): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
        let range = f64::from(range_of(p));
        let transmission = (-2.0 * alpha * range).exp();
        let margin = clear_margin(range, f64::from(p[3] / scale), k) * transmission;
        let far = range.min(SNOW_MAX_RANGE_M);
        let flake = (u_hit < p_hit && far > SNOW_MIN_RANGE_M).then(|| {
            let r = SNOW_MIN_RANGE_M + u_range * (far - SNOW_MIN_RANGE_M);
            let reflectivity = SNOW_REFLECTIVITY * (2.0 + u_cover) / 3.0;
            (r, reflectivity, clear_margin(r, reflectivity, k) * (-2.0 * alpha * r).exp())
        });
        match flake {
            Some((r, reflectivity, flake_margin)) if flake_margin > margin => {
                along_ray(p, r, reflectivity as f32 * scale, &mut out);
                scattered += 1;
            }
            _ if margin >= 1.0 => {
                out.extend([p[0], p[1], p[2], (f64::from(p[3]) * transmission) as f32]);
                out.extend_from_slice(&p[4..]);
            }
            _ => lost += 1,
        }
    }
    finish(cloud, out, lost, scattered, scale)
}

fn finish(
    cloud: &PointCloud,
    out: Vec<f32>,
    lost: usize,
    scattered: usize,
    scale: f32,
) -> Result<(PointCloud, LidarReport), String> {
    let result = PointCloud::new(cloud.columns, out)?;
    let report = LidarReport {
        points_in: cloud.len(),
        points_out: result.len(),
        lost,
        scattered,
        mean_intensity_in: cloud.mean_intensity(),
        mean_intensity_out: result.mean_intensity(),
        near_in: cloud.count_within(NEAR_RANGE_M),
        near_out: result.count_within(NEAR_RANGE_M),
        intensity_scale: scale,
    };
    Ok((result, report))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(rows: &[[f32; 4]]) -> PointCloud {
        PointCloud::new(4, rows.iter().flatten().copied().collect()).expect("cloud")
    }

    #[test]
    fn mor_is_about_50_m_at_0_06() {
        assert!((mor(0.06) - 49.93).abs() < 0.01, "{}", mor(0.06));
        assert!((mor(0.01) - 299.57).abs() < 0.01);
        // At MOR the one-way transmission is 5%.
        assert!(((-0.06 * mor(0.06)).exp() - 0.05).abs() < 1e-12);
    }

    #[test]
    fn clear_margin_follows_the_data_sheet_or_the_cloud() {
        let near = cloud(&[[10.0, 0.0, 0.0, 0.5]]);
        let k = detection_threshold(&near, 1.0);
        assert!((k - 0.1 / 2500.0).abs() < 1e-15, "the data sheet's: {k}");
        assert!((clear_margin(50.0, 0.10, k) - 1.0).abs() < 1e-12);
        assert!((clear_margin(25.0, 0.10, k) - 4.0).abs() < 1e-12);
        assert_eq!(clear_margin(100.0, 0.10, k), 1.0, "detected returns have margin at least 1");
        assert_eq!(clear_margin(10.0, 0.0, k), clear_margin(10.0, MIN_REFLECTIVITY, k));
        // A dark return at 100 m proves a more sensitive sensor.
        let far = cloud(&[[10.0, 0.0, 0.0, 0.5], [0.0, 100.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0]]);
        assert!((detection_threshold(&far, 1.0) - 0.02 / 10_000.0).abs() < 1e-15);
    }

    #[test]
    fn fog_attenuates_a_near_bright_return_by_two_way_beer_lambert() {
        // A 90% target at 5 m: margin 900 in clear air, 900·e^-1.5 = 200 in fog 0.15; the
        // fog margin (0.15 / 0.0899)·E exceeds that only for E > 120, p = e^-120.
        let c = cloud(&[[3.0, 4.0, 0.0, 0.9]]);
        let (out, report) = fog(&c, 0.15, 7, None).expect("fog");
        assert_eq!((report.lost, report.scattered), (0, 0));
        let expect = 0.9 * (-2.0f64 * 0.15 * 5.0).exp();
        assert!((f64::from(out.data()[3]) - expect).abs() < 1e-6, "{:?}", out.data());
        assert_eq!(&out.data()[..3], &[3.0, 4.0, 0.0]);
    }

    #[test]
    fn extra_columns_are_carried() {
        let rows: Vec<f32> = (0..200).flat_map(|i| [60.0, 0.0, i as f32 * 0.01, 0.3, 7.0]).collect();
        let c = PointCloud::new(5, rows).expect("cloud");
        let (out, report) = fog(&c, 0.15, 1, None).expect("fog");
        assert!(report.scattered > 0, "{report:?}");
        assert!(out.points().all(|p| p[4] == 7.0));
    }

    #[test]
    fn bad_clouds_and_levels_are_refused() {
        assert!(PointCloud::new(3, vec![0.0; 6]).expect_err("3 columns").contains("not 3"));
        assert!(PointCloud::new(4, vec![0.0; 6]).expect_err("rows").contains("whole rows"));
        assert!(PointCloud::new(4, vec![0.0, f32::NAN, 0.0, 0.0]).expect_err("nan").contains("point 0 has NaN"));
        assert!(PointCloud::new(4, vec![1.0, 0.0, 0.0, -1.0]).expect_err("neg").contains("negative intensity"));
        let c = cloud(&[[10.0, 0.0, 0.0, 0.5]]);
        assert!(fog(&c, 0.5, 0, None).expect_err("alpha").contains("[0.01, 0.15]"));
        assert!(snow(&c, 0.1, 0, None).expect_err("rate").contains("[0.5, 2.5]"));
        assert!(fog(&c, 0.06, 0, Some(0.0)).is_err());
    }

    #[test]
    fn intensity_scale_is_inferred() {
        assert_eq!(cloud(&[[1.0, 0.0, 0.0, 0.99]]).intensity_scale(), 1.0);
        assert_eq!(cloud(&[[1.0, 0.0, 0.0, 37.0]]).intensity_scale(), 255.0);
    }
}
