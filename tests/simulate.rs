//! The condition simulators (`readi simulate`): physical sanity of fog, snow, gamma and
//! blur, determinism, file formats and errors, and the CLI on real files.

mod common;

use common::readi;

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use readi::simulate::camera::{self, laplacian_variance, motion_blur, motion_kernel};
use readi::simulate::io::{self, Image, PngExtras};
use readi::simulate::lidar::{self, LidarReport, PointCloud};

const ALPHAS: [f64; 5] = [0.01, 0.03, 0.06, 0.1, 0.15];
const RATES: [f64; 5] = [0.5, 1.0, 1.5, 2.0, 2.5];
const KERNELS: [usize; 5] = [5, 10, 15, 20, 30];

/// A temporary directory for one test.
fn temp_dir(name: &str) -> common::Scratch {
    common::Scratch::new(&format!("simulate-{name}"))
}

/// A seeded synthetic scan: ranges uniform in [5, 80] m, azimuth all around, elevation in
/// the HDL-64E's field of view (−24.9° .. +2°), intensities uniform in [0.02, 0.9].
fn synthetic_cloud(n: usize, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut data = Vec::with_capacity(n * 4);
    for _ in 0..n {
        let r: f32 = rng.random_range(5.0..80.0);
        let az: f32 = rng.random_range(0.0..std::f32::consts::TAU);
        let el: f32 = rng.random_range(-24.9f32..2.0).to_radians();
        let intensity: f32 = rng.random_range(0.02..0.9);
        data.extend([r * el.cos() * az.cos(), r * el.cos() * az.sin(), r * el.sin(), intensity]);
    }
    PointCloud::new(4, data).expect("synthetic cloud")
}

fn range(p: &[f32]) -> f32 {
    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
}

fn seeded_image(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random::<f32>()).collect()
}

#[test]
fn fog_lowers_mean_intensity_and_adds_near_returns_monotonically() {
    let cloud = synthetic_cloud(20_000, 1);
    let reports: Vec<LidarReport> = ALPHAS.iter().map(|&a| lidar::fog(&cloud, a, 7, None).expect("fog").1).collect();
    eprintln!("alpha   MOR m   points  lost  fog  mean intensity  within 10 m");
    eprintln!(
        "clear       -   {:>6}     -    -  {:.4}          {}",
        cloud.len(),
        cloud.mean_intensity().expect("mean"),
        cloud.count_within(10.0)
    );
    for (a, r) in ALPHAS.iter().zip(&reports) {
        eprintln!(
            "{a:<5} {:>7.1}   {:>6} {:>5} {:>4}  {:.4}          {}",
            lidar::mor(*a),
            r.points_out,
            r.lost,
            r.scattered,
            r.mean_intensity_out.expect("mean"),
            r.near_out
        );
    }
    let clear = cloud.mean_intensity().expect("mean");
    assert!(reports[0].mean_intensity_out.expect("mean") < clear, "the lightest fog already lowers intensity");
    for w in reports.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        assert!(b.mean_intensity_out < a.mean_intensity_out, "mean intensity must fall: {a:?} then {b:?}");
        assert!(b.scattered > a.scattered, "fog returns must grow: {a:?} then {b:?}");
        assert!(b.near_out > a.near_out, "near returns must grow: {a:?} then {b:?}");
        assert!(b.lost + b.scattered > a.lost + a.scattered, "distorted points must grow");
    }
    assert!(reports[0].near_out >= reports[0].near_in);
    // Dense fog: the cloud is mostly weak returns near the sensor.
    let dense = &reports[4];
    assert!(dense.near_out > 3 * dense.near_in, "{dense:?}");
}

#[test]
fn fog_mor_is_about_50_m_at_alpha_0_06() {
    let mor = lidar::mor(0.06);
    assert!((49.0..51.0).contains(&mor), "MOR at 0.06 is {mor}");
    assert!(((-0.06 * mor).exp() - 0.05).abs() < 1e-12, "MOR is where 5% of the light remains");
    for w in ALPHAS.windows(2) {
        assert!(lidar::mor(w[1]) < lidar::mor(w[0]));
    }
}

#[test]
fn fog_returns_lie_on_their_ray_within_half_the_mor() {
    // Every ray along +x to a 10%-reflective wall at 80 m: beyond reach in fog 0.06
    // (margin (0.1 / 0.1)(50 / 80)² → 1, times e^-9.6), so each ray is either lost or fog.
    let data: Vec<f32> = (0..5000).flat_map(|_| [80.0, 0.0, 0.0, 0.1]).collect();
    let cloud = PointCloud::new(4, data).expect("cloud");
    let (out, report) = lidar::fog(&cloud, 0.06, 3, None).expect("fog");
    assert_eq!(report.lost + report.scattered, 5000);
    assert!(report.scattered > 250, "{report:?}");
    let half_mor = lidar::mor(0.06) as f32 / 2.0;
    for p in out.points() {
        assert!(p[1] == 0.0 && p[2] == 0.0, "off its ray: {p:?}");
        assert!((2.0..=half_mor + 1e-3).contains(&p[0]), "fog return at {} m", p[0]);
        assert!(p[3] < 0.1, "fog returns are weak: {p:?}");
    }
    // The 1/r² density puts most fog returns in the first metres.
    let ranges: Vec<f32> = out.points().map(|p| p[0]).collect();
    let below_5m = ranges.iter().filter(|&&r| r < 5.0).count();
    assert!(below_5m * 2 > ranges.len(), "{below_5m} of {}", ranges.len());
}

#[test]
fn fog_attenuates_kept_returns_by_two_way_beer_lambert() {
    // Bright targets at 5 m keep their point (margin 800·e^-1.5 in the densest fog; a fog
    // return would need speckle E > 100); only the intensity changes.
    let data: Vec<f32> = (0..100).flat_map(|_| [3.0, 4.0, 0.0, 0.8]).collect();
    let cloud = PointCloud::new(4, data).expect("cloud");
    for alpha in ALPHAS {
        let (out, report) = lidar::fog(&cloud, alpha, 0, None).expect("fog");
        assert_eq!((report.lost, report.scattered), (0, 0), "alpha {alpha}");
        let expected = 0.8 * (-2.0 * alpha * 5.0).exp();
        for p in out.points() {
            assert!((f64::from(p[3]) - expected).abs() < 1e-6, "alpha {alpha}: {} vs {expected}", p[3]);
        }
    }
}

#[test]
fn fog_keeps_a_0_to_255_intensity_scale() {
    let unit = synthetic_cloud(2000, 4);
    let data: Vec<f32> = unit.points().flat_map(|p| [p[0], p[1], p[2], p[3] * 255.0]).collect();
    let scaled = PointCloud::new(4, data).expect("cloud");
    let (a, ra) = lidar::fog(&unit, 0.06, 5, None).expect("fog");
    let (b, rb) = lidar::fog(&scaled, 0.06, 5, None).expect("fog");
    assert_eq!((ra.intensity_scale, rb.intensity_scale), (1.0, 255.0));
    assert_eq!((ra.lost, ra.scattered), (rb.lost, rb.scattered));
    for (p, q) in a.points().zip(b.points()) {
        assert!((p[3] * 255.0 - q[3]).abs() <= 1e-3 * q[3].max(1.0), "{p:?} vs {q:?}");
    }
}

#[test]
fn snow_adds_high_intensity_near_points_more_with_higher_rate() {
    // Intensities at most 0.5, so every return of 0.6 or more is a snowflake.
    let base = synthetic_cloud(20_000, 2);
    let data: Vec<f32> = base.points().flat_map(|p| [p[0], p[1], p[2], p[3] * 0.5]).collect();
    let cloud = PointCloud::new(4, data).expect("cloud");
    let mut counts = Vec::new();
    eprintln!("rate mm/h  points  lost  flakes  mean intensity  bright within 15 m");
    for rate in RATES {
        let (out, r) = lidar::snow(&cloud, rate, 11, None).expect("snow");
        let bright: Vec<&[f32]> = out.points().filter(|p| p[3] >= 0.6).collect();
        assert_eq!(bright.len(), r.scattered, "every flake is bright, nothing else is");
        assert!(bright.iter().all(|p| (1.0..=15.0 + 1e-3).contains(&range(p)) && p[3] <= 0.9 + 1e-6));
        eprintln!(
            "{rate:<9}  {:>6} {:>5} {:>7}  {:.4}          {}",
            r.points_out,
            r.lost,
            r.scattered,
            r.mean_intensity_out.expect("mean"),
            bright.len()
        );
        counts.push(bright.len());
    }
    assert!(counts.windows(2).all(|w| w[1] > w[0]), "{counts:?}");
    // Proportional to the rate: 1% of rays per mm/h, less the rays with no room for a flake.
    let ratio = counts[4] as f64 / counts[0] as f64;
    assert!((4.0..6.0).contains(&ratio), "2.5 vs 0.5 mm/h: {counts:?}");
    assert!((70..=130).contains(&counts[0]), "0.5% of 20 000 rays: {counts:?}");
}

#[test]
fn snow_attenuates_existing_returns_mildly() {
    let data: Vec<f32> = (0..1000).flat_map(|_| [0.0, 30.0, 0.0, 0.5]).collect();
    let cloud = PointCloud::new(4, data).expect("cloud");
    let (out, r) = lidar::snow(&cloud, 2.5, 0, None).expect("snow");
    let alpha = lidar::snow_extinction(2.5);
    assert!((alpha - 0.00749).abs() < 1e-5, "{alpha}");
    let expected = 0.5 * (-2.0 * alpha * 30.0).exp();
    let kept: Vec<f32> = out.points().filter(|p| p[3] < 0.6).map(|p| p[3]).collect();
    assert_eq!(kept.len() + r.scattered, 1000);
    assert!(kept.iter().all(|&i| (f64::from(i) - expected).abs() < 1e-6 && f64::from(i) > 0.6 * 0.5));
}

#[test]
fn lidar_simulation_is_deterministic_with_a_seed() {
    let cloud = synthetic_cloud(5000, 3);
    let bytes = |c: &PointCloud| c.data().iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>();
    let (a, _) = lidar::fog(&cloud, 0.1, 42, None).expect("fog");
    let (b, _) = lidar::fog(&cloud, 0.1, 42, None).expect("fog");
    let (c, _) = lidar::fog(&cloud, 0.1, 43, None).expect("fog");
    assert_eq!(bytes(&a), bytes(&b));
    assert_ne!(bytes(&a), bytes(&c), "another seed, another fog");
    let (a, _) = lidar::snow(&cloud, 2.0, 42, None).expect("snow");
    let (b, _) = lidar::snow(&cloud, 2.0, 42, None).expect("snow");
    assert_eq!(bytes(&a), bytes(&b));
}

#[test]
fn gamma_below_one_darkens_above_one_brightens_one_is_identity() {
    // Hand-computed: 0.5^(1/γ) and 0.2^(1/γ).
    let cases = [
        (0.25, 0.5, 0.0625),
        (0.5, 0.5, 0.25),
        (2.0, 0.5, std::f64::consts::FRAC_1_SQRT_2),
        (4.0, 0.5, 0.840_896_415),
        (0.5, 0.2, 0.04),
        (2.0, 0.2, 0.447_213_595),
    ];
    for (g, x, expected) in cases {
        let out = camera::gamma(&[x], g).expect("gamma")[0];
        assert!((f64::from(out) - expected).abs() < 1e-6, "{x}^(1/{g}) = {out}, expected {expected}");
    }
    let image = seeded_image(3 * 64 * 64, 9);
    assert_eq!(camera::gamma(&image, 1.0).expect("identity"), image, "gamma 1 is the identity, bit for bit");
    let mean = |v: &[f32]| camera::mean(v).expect("mean");
    eprintln!("gamma  mean (uniform image; expected γ/(1+γ))");
    let mut previous = 0.0;
    for g in [0.25, 0.5, 1.0, 2.0, 4.0] {
        let out = camera::gamma(&image, g).expect("gamma");
        let m = mean(&out);
        eprintln!("{g:<5}  {m:.4}  ({:.4})", g / (1.0 + g));
        // E[u^(1/γ)] for u uniform in [0, 1] is γ / (1 + γ).
        assert!((m - g / (1.0 + g)).abs() < 0.01, "gamma {g}: mean {m}");
        assert!(m > previous);
        previous = m;
        for (o, i) in out.iter().zip(&image) {
            match g {
                g if g < 1.0 => assert!(o <= i, "gamma {g} must darken: {i} -> {o}"),
                g if g > 1.0 => assert!(o >= i, "gamma {g} must brighten: {i} -> {o}"),
                _ => assert_eq!(o, i),
            }
        }
    }
    assert!(camera::gamma(&image, 5.0).expect_err("range").contains("outside the paper's range [0.25, 4]"));
}

#[test]
fn blur_of_an_impulse_is_the_hand_derived_kernel() {
    // k = 5, σ = 0.3·((5−1)/2 − 1) + 0.8 = 1.1: exp(−t²/2.42) for t = −2..2 is
    // (0.191495, 0.661515, 1, 0.661515, 0.191495), sum 2.706020, normalised:
    let expected = [0.070_766, 0.244_460, 0.369_546, 0.244_460, 0.070_766];
    let mut impulse = vec![0.0f32; 11 * 11];
    impulse[5 * 11 + 5] = 1.0;
    let out = motion_blur(&impulse, 11, 11, 5, 0.0).expect("blur");
    for y in 0..11 {
        for x in 0..11 {
            let want = if y == 5 && (3..=7).contains(&x) { expected[x - 3] } else { 0.0 };
            assert!((out[y * 11 + x] - want).abs() < 1e-6, "({y}, {x}): {} vs {want}", out[y * 11 + x]);
        }
    }
    // At 90° the same kernel stands vertically.
    let out = motion_blur(&impulse, 11, 11, 5, 90.0).expect("blur");
    for (i, want) in expected.iter().enumerate() {
        assert!((out[(3 + i) * 11 + 5] - want).abs() < 1e-6);
    }
    let taps = motion_kernel(5, 0.0).expect("kernel");
    assert_eq!(taps.iter().map(|t| t.dx).collect::<Vec<_>>(), [-2, -1, 0, 1, 2]);
}

#[test]
fn blur_preserves_the_mean() {
    // A random interior inside a constant border at least k/2 wide: with edge clamping
    // and a kernel summing to 1, the sum is exactly preserved.
    let (h, w, border) = (80, 96, 16);
    let noise = seeded_image(h * w, 5);
    let image: Vec<f32> = (0..h * w)
        .map(|i| {
            let (y, x) = (i / w, i % w);
            if y < border || y >= h - border || x < border || x >= w - border { 0.5 } else { noise[i] }
        })
        .collect();
    let before = camera::mean(&image).expect("mean");
    for k in KERNELS {
        for angle in [0.0, 30.0, 90.0, 135.0] {
            let out = motion_blur(&image, h, w, k, angle).expect("blur");
            let after = camera::mean(&out).expect("mean");
            assert!((after - before).abs() < 1e-5, "k {k} angle {angle}: {before} -> {after}");
        }
    }
    let flat = vec![0.3f32; 3 * 20 * 20];
    let out = motion_blur(&flat, 20, 20, 30, 17.0).expect("blur");
    assert!(out.iter().all(|v| (v - 0.3).abs() < 1e-6), "a constant image stays constant");
}

#[test]
fn blur_lowers_laplacian_variance_monotonically_with_kernel_size() {
    // Broadband content: noise, and a scene of random rectangles (edges at all scales).
    // (A pure periodic pattern need not be monotone: a truncated Gaussian has sidelobes.)
    let (h, w) = (64, 64);
    let noise = seeded_image(h * w, 6);
    let mut scene = vec![0.5f32; h * w];
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for _ in 0..12 {
        let (y0, x0) = (rng.random_range(0..h - 8), rng.random_range(0..w - 8));
        let (y1, x1) = (rng.random_range(y0 + 4..h), rng.random_range(x0 + 4..w));
        let grey: f32 = rng.random();
        for y in y0..y1 {
            scene[y * w + x0..y * w + x1].fill(grey);
        }
    }
    let image = [noise, scene].concat();
    for angle in [0.0, 45.0, 90.0] {
        let sharpness = |data: &[f32]| [0, 1].map(|p| laplacian_variance(&data[p * h * w..][..h * w], h, w));
        let mut previous = sharpness(&image);
        for k in KERNELS {
            let now = sharpness(&motion_blur(&image, h, w, k, angle).expect("blur"));
            for p in 0..2 {
                assert!(now[p] < previous[p], "plane {p}, angle {angle}, k {k}: {} not below {}", now[p], previous[p]);
            }
            previous = now;
        }
    }
}

#[test]
fn kitti_bin_round_trip() {
    let dir = temp_dir("bin");
    let cloud = synthetic_cloud(1000, 8);
    let path = dir.join("000001.bin");
    io::write_cloud(&path, &cloud).expect("write");
    let bytes = std::fs::read(&path).expect("read bytes");
    assert_eq!(bytes.len(), 1000 * 16, "KITTI: 16 bytes a point");
    assert_eq!(&bytes[..4], &cloud.data()[0].to_le_bytes(), "little-endian float32 x first");
    assert_eq!(io::read_cloud(&path, 4).expect("read"), cloud);
    let npy = dir.join("cloud.npy");
    io::write_cloud(&npy, &cloud).expect("write npy");
    assert_eq!(io::read_cloud(&npy, 4).expect("read npy"), cloud);
    // Five columns (nuScenes) through --columns 5.
    let five = PointCloud::new(5, (0..50).map(|i| i as f32).collect()).expect("five");
    io::write_cloud(&path, &five).expect("write");
    assert_eq!(io::read_cloud(&path, 5).expect("read 5"), five);
}

#[test]
fn bad_files_give_clear_errors() {
    let dir = temp_dir("bad");
    let truncated = dir.join("truncated.bin");
    std::fs::write(&truncated, vec![0u8; 16 * 3 + 5]).expect("write");
    let err = io::read_cloud(&truncated, 4).expect_err("truncated");
    assert!(err.contains("truncated.bin: 53 bytes is not a whole number of 16-byte points"), "{err}");

    let wrong = dir.join("wrong.npy");
    io::write_npy(&wrong, &[10, 3], &[0.0; 30]).expect("write");
    let err = io::read_cloud(&wrong, 4).expect_err("wrong shape");
    assert!(err.contains("wrong.npy: shape [10, 3] is not a point cloud [N, 4]"), "{err}");

    let ints = dir.join("ints.npy");
    {
        use ndarray_npy::WriteNpyExt;
        let a = ndarray::Array2::<i64>::zeros((4, 4));
        a.write_npy(std::fs::File::create(&ints).expect("create")).expect("write ints");
    }
    let err = io::read_cloud(&ints, 4).expect_err("dtype");
    assert!(err.contains("ints.npy: dtype '<i8'; expected float32"), "{err}");

    let nan = dir.join("nan.npy");
    let mut values = vec![1.0f32; 16];
    values[13] = f32::NAN;
    io::write_npy(&nan, &[4, 4], &values).expect("write");
    let err = io::read_cloud(&nan, 4).expect_err("nan");
    assert!(err.contains("nan.npy: point 3 has NaN in column 1"), "{err}");

    let cut = dir.join("cut.npy");
    io::write_npy(&cut, &[100, 4], &[0.5; 400]).expect("write");
    let bytes = std::fs::read(&cut).expect("read");
    std::fs::write(&cut, &bytes[..bytes.len() - 100]).expect("truncate");
    let err = io::read_cloud(&cut, 4).expect_err("truncated npy");
    assert!(err.contains("cut.npy: cannot read the .npy array"), "{err}");

    let hwc = dir.join("hwc.npy");
    io::write_npy(&hwc, &[32, 32, 3], &[0.5; 32 * 32 * 3]).expect("write");
    let err = io::read_image(&hwc).expect_err("channels last");
    assert!(err.contains("hwc.npy: shape [32, 32, 3] looks channels-last"), "{err}");

    let png = dir.join("broken.png");
    std::fs::write(&png, b"\x89PNG\r\n\x1a\nnot really").expect("write");
    let err = io::read_image(&png).expect_err("broken png");
    assert!(err.contains("broken.png: not a readable PNG"), "{err}");
}

#[test]
fn png_round_trip_keeps_pixels_and_alpha() {
    let dir = temp_dir("png");
    let (w, h) = (7u32, 5u32);
    let raw: Vec<u8> = (0..w * h * 4).map(|i| (i * 37 % 256) as u8).collect();
    let src = dir.join("rgba.png");
    image::RgbaImage::from_raw(w, h, raw.clone()).expect("buffer").save(&src).expect("save png");
    let img = io::read_image(&src).expect("read png");
    assert_eq!(img.shape, [3, 5, 7]);
    assert_eq!(img.data[0], f32::from(raw[0]) / 255.0);
    assert!(matches!(&img.png, Some(PngExtras { alpha: Some(a), sixteen_bit: false }) if a.len() == 35));
    let out = dir.join("out.png");
    io::write_image(&out, &Image { data: camera::gamma(&img.data, 1.0).expect("gamma 1"), ..img.clone() })
        .expect("write");
    let back = image::open(&out).expect("open").to_rgba8();
    assert_eq!(back.into_raw(), raw, "gamma 1 through PNG is lossless, alpha included");
}

#[test]
fn cli_simulates_fog_on_a_kitti_bin() {
    let dir = temp_dir("cli-bin");
    let input = dir.join("000042.bin");
    io::write_cloud(&input, &synthetic_cloud(3000, 12)).expect("write");
    let (a, b) = (dir.join("fog-a.bin"), dir.join("fog-b.bin"));
    for out in [&a, &b] {
        let o = readi(&[
            "simulate",
            input.to_str().expect("utf-8"),
            "-o",
            out.to_str().expect("utf-8"),
            "--fog",
            "0.06",
            "--seed",
            "9",
        ]);
        let stdout = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert!(stdout.starts_with("fog alpha 0.06 1/m (MOR 49.9 m), seed 9: 3000 -> "), "{stdout}");
        assert!(stdout.contains("mean intensity 0.4") && stdout.contains("fog returns"), "{stdout}");
    }
    assert_eq!(std::fs::read(&a).expect("a"), std::fs::read(&b).expect("b"), "same seed, same bytes");
    let out = io::read_cloud(&a, 4).expect("output is a KITTI cloud");
    assert!(out.len() < 3000 && out.mean_intensity() < synthetic_cloud(3000, 12).mean_intensity());

    let snow = dir.join("snow.npy");
    let o = readi(&["simulate", input.to_str().expect("utf-8"), "-o", snow.to_str().expect("utf-8"), "--snow", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("snowflake returns"));
    assert_eq!(io::read_cloud(&snow, 4).expect("npy output").columns(), 4);

    std::fs::write(dir.join("cut.bin"), [0u8; 20]).expect("write");
    let o = readi(&["simulate", dir.join("cut.bin").to_str().expect("utf-8"), "-o", "x.bin", "--fog", "0.06"]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("cut.bin: 20 bytes is not a whole number of 16-byte points"), "{err}");
    let o = readi(&["simulate", input.to_str().expect("utf-8"), "-o", "x.bin", "--fog", "0.5"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("fog alpha 0.5 is outside the paper's range [0.01, 0.15]"));
    let o = readi(&["simulate", input.to_str().expect("utf-8"), "-o", "x.png", "--gamma", "0.5"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("000042.bin is a point cloud; gamma and blur apply to images"));
}

#[test]
fn cli_simulates_gamma_and_blur_on_a_png() {
    let dir = temp_dir("cli-png");
    let input = dir.join("frame.png");
    let (w, h) = (48u32, 32u32);
    let raw: Vec<u8> = seeded_image((w * h * 3) as usize, 13).iter().map(|v| (v * 255.0).round() as u8).collect();
    image::RgbImage::from_raw(w, h, raw.clone()).expect("buffer").save(&input).expect("save");
    let dark = dir.join("dark.png");
    let o = readi(&["simulate", input.to_str().expect("utf-8"), "-o", dark.to_str().expect("utf-8"), "--gamma", "0.5"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.starts_with("gamma 0.5: image [3, 32, 48] mean 0.4986 -> 0.33"), "{stdout}");
    let out = image::open(&dark).expect("open").to_rgb8().into_raw();
    let mean = |v: &[u8]| v.iter().map(|&b| f64::from(b)).sum::<f64>() / v.len() as f64;
    assert!(mean(&out) < 0.75 * mean(&raw), "gamma 0.5 darkens: {} -> {}", mean(&raw), mean(&out));

    let both = dir.join("both.npy");
    let o = readi(&[
        "simulate",
        input.to_str().expect("utf-8"),
        "-o",
        both.to_str().expect("utf-8"),
        "--blur",
        "15",
        "--angle",
        "-30",
        "--gamma",
        "2",
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.starts_with("blur 15 at -30°, then gamma 2: image [3, 32, 48]"), "{stdout}");
    assert!(stdout.contains("sharpness (Laplacian variance)"), "{stdout}");
    let (shape, _) = io::read_npy(&both).expect("npy output");
    assert_eq!(shape, [3, 32, 48]);

    let o = readi(&["simulate", input.to_str().expect("utf-8"), "-o", "x.png", "--blur", "3"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("blur kernel size 3 is outside the paper's range [5, 30]"));
    let o = readi(&["simulate", input.to_str().expect("utf-8"), "-o", "x.bin", "--fog", "0.06"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("frame.png is an image; fog and snow apply to lidar"));
}
