//! Condition simulators: the paper's camera and lidar variations (§ Benchmark), applied
//! to inputs so that variants can be made and evaluated (`readi simulate`).
//!
//! | condition | module | parameter | paper's levels |
//! | --- | --- | --- | --- |
//! | exposure | [`camera::gamma`] | γ: `out = in^(1/γ)` | 0.25, 0.5, 1, 2, 4 |
//! | motion blur | [`camera::motion_blur`] | kernel size k, σ = 0.3((k−1)/2 − 1) + 0.8 | 5, 10, 15, 20, 30 |
//! | fog | [`lidar::fog`] | α in 1/m, MOR = ln 20 / α | 0.01 … 0.15 |
//! | snow | [`lidar::snow`] | snowfall rate β in mm/h | 0.5 … 2.5 |
//!
//! The functions are pure: they take slices or a [`lidar::PointCloud`] and return new
//! data, the lidar ones seeded. [`io`] reads and writes the files; [`run`] is the CLI.
//! Formulas, constants and sources: `docs/simulate.md` and each function's doc.

pub mod camera;
pub mod io;
pub mod lidar;

use std::path::PathBuf;

use io::Format;

/// Examples for `readi simulate --help`.
pub const EXAMPLES: &str = "\
Examples:
  readi simulate 000042.bin -o fog06.bin --fog 0.06 --seed 1     KITTI cloud, MOR 50 m
  readi simulate sweep.pcd.bin --columns 5 -o snow.bin --snow 1.5 nuScenes cloud (5 columns)
  readi simulate cams.npy -o dark.npy --gamma 0.5                 [N, 6, 3, H, W] float images
  readi simulate frame.png -o blurred.png --blur 15 --angle 30
  readi simulate frame.png -o night.png --blur 10 --gamma 0.25   camera conditions combine";

/// `readi simulate`: one lidar condition, or one or both camera conditions.
#[derive(clap::Args, Clone, Debug)]
#[command(group(clap::ArgGroup::new("condition").required(true).multiple(true).args(["fog", "snow", "gamma", "blur"])))]
pub struct SimulateArgs {
    /// A point cloud (KITTI .bin, .npy [N, 4]: x, y, z, intensity) or an image (.png, .npy float in [0, 1]).
    pub input: PathBuf,
    /// Where to write the result; the format follows the extension (.bin/.npy, .png/.npy).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Lidar fog: extinction coefficient alpha in 1/m, 0.01 to 0.15 (MOR = ln 20 / alpha: 50 m at 0.06).
    #[arg(long, value_name = "ALPHA", conflicts_with_all = ["snow", "gamma", "blur"])]
    pub fog: Option<f64>,
    /// Lidar snow: snowfall rate in mm/h (liquid equivalent), 0.5 to 2.5.
    #[arg(long, value_name = "RATE", conflicts_with_all = ["gamma", "blur"])]
    pub snow: Option<f64>,
    /// Camera exposure: out = in^(1/gamma), gamma 0.25 to 4; below 1 darkens (under-exposed).
    #[arg(long)]
    pub gamma: Option<f64>,
    /// Camera motion blur: kernel size 5 to 30, a Gaussian-weighted line (OpenCV's sigma for size k). Applied before gamma.
    #[arg(long, value_name = "K")]
    pub blur: Option<usize>,
    /// Blur direction in degrees, counter-clockwise from horizontal.
    #[arg(long, value_name = "DEG", default_value_t = 0.0, requires = "blur", allow_negative_numbers = true)]
    pub angle: f64,
    /// Seed of the lidar simulators' random draws; the same seed gives the same bytes.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Values per point in .bin files: 4 for KITTI, 5 for nuScenes (extras are carried along).
    #[arg(long, value_name = "C", default_value_t = 4)]
    pub columns: usize,
    /// Full-scale intensity (default: 1 if every intensity is at most 1, else 255).
    #[arg(long, value_name = "S")]
    pub intensity_scale: Option<f32>,
}

fn show(v: Option<f64>) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.4}"))
}

/// Runs `readi simulate`: reads the input, applies the conditions, writes the output
/// and returns the one-line summary. Errors name the file and what is wrong.
pub fn run(args: &SimulateArgs) -> Result<String, String> {
    let (input, output) = (&args.input, &args.output);
    let out_format = Format::of(output)?;
    if let Some(level) = args.fog.or(args.snow) {
        if out_format == Format::Png {
            return Err(format!("{}: a point cloud is written to .bin or .npy, not .png", output.display()));
        }
        let cloud = io::read_cloud(input, args.columns)?;
        let (what, (result, r)) = match args.fog {
            Some(alpha) => (
                format!("fog alpha {alpha} 1/m (MOR {:.1} m)", lidar::mor(alpha)),
                lidar::fog(&cloud, level, args.seed, args.intensity_scale)?,
            ),
            None => (format!("snow {level} mm/h"), lidar::snow(&cloud, level, args.seed, args.intensity_scale)?),
        };
        io::write_cloud(output, &result)?;
        let scattered = if args.fog.is_some() { "fog returns" } else { "snowflake returns" };
        return Ok(format!(
            "{what}, seed {}: {} -> {} points ({} lost, {} {scattered}); mean intensity {} -> {} (full scale {}); \
             within {} m {} -> {}; wrote {}",
            args.seed,
            r.points_in,
            r.points_out,
            r.lost,
            r.scattered,
            show(r.mean_intensity_in),
            show(r.mean_intensity_out),
            r.intensity_scale,
            lidar::NEAR_RANGE_M,
            r.near_in,
            r.near_out,
            output.display()
        ));
    }
    if out_format == Format::Bin {
        return Err(format!("{}: an image is written to .png or .npy, not .bin", output.display()));
    }
    let mut image = io::read_image(input)?;
    let (planes, h, w) = image.planes().map_err(|e| format!("{}: {e}", input.display()))?;
    let mean_before = camera::mean(&image.data);
    let mut steps = Vec::new();
    let mut sharpness = None;
    if let Some(k) = args.blur {
        let before = mean_sharpness(&image.data, planes, h, w);
        image.data =
            camera::motion_blur(&image.data, h, w, k, args.angle).map_err(|e| format!("{}: {e}", input.display()))?;
        sharpness = Some((before, mean_sharpness(&image.data, planes, h, w)));
        steps.push(format!("blur {k} at {}°", args.angle));
    }
    if let Some(g) = args.gamma {
        image.data = camera::gamma(&image.data, g).map_err(|e| format!("{}: {e}", input.display()))?;
        steps.push(format!("gamma {g}"));
    }
    io::write_image(output, &image)?;
    let sharp =
        sharpness.map_or_else(String::new, |(a, b)| format!(", sharpness (Laplacian variance) {a:.3e} -> {b:.3e}"));
    Ok(format!(
        "{}: image {:?} mean {} -> {}{sharp}; wrote {}",
        steps.join(", then "),
        image.shape,
        show(mean_before),
        show(camera::mean(&image.data)),
        output.display()
    ))
}

fn mean_sharpness(data: &[f32], planes: usize, h: usize, w: usize) -> f64 {
    let total: f64 = data.chunks_exact(h * w).map(|p| camera::laplacian_variance(p, h, w)).sum();
    total / planes.max(1) as f64
}
