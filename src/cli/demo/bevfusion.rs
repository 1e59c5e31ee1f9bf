//! `readi demo --model bevfusion`: the paper's network, models/bevfusion.readi (embedded
//! with the part files it uses), at a demo size that runs in about a second a frame, with
//! seeded weights and variants; a drive through a synthetic street ([`scene`]) whose
//! sweeps and six views go through the condition simulators (`readi simulate`'s fog,
//! snow and exposure), the variant chosen per frame by the spec's selectors, and the
//! boxes the detector finds. With seeded weights the boxes show the plumbing (points and
//! images in, decoded boxes out), not a trained detector.

use std::process::ExitCode;
use std::time::Instant;

use readi_compiler::passes::{self, Options};
use readi_compiler::print;
use readi_grammar::diag::FileId;
use readi_runtime::conditions;
use readi_runtime::exec::{Input, Session};

use super::super::frontend::Frontend;
use super::scene;
use readi::simulate::lidar::PointCloud;

/// models/bevfusion.readi and the files it uses, by the path `use` names them with.
const FILES: &[(&str, &str)] = &[
    ("models/bevfusion.readi", include_str!("../../../models/bevfusion.readi")),
    ("models/bevfusion/swin.readi", include_str!("../../../models/bevfusion/swin.readi")),
    ("models/bevfusion/camera.readi", include_str!("../../../models/bevfusion/camera.readi")),
    ("models/bevfusion/lidar.readi", include_str!("../../../models/bevfusion/lidar.readi")),
    ("models/bevfusion/decoder.readi", include_str!("../../../models/bevfusion/decoder.readi")),
    ("models/bevfusion/common.readi", include_str!("../../../models/bevfusion/common.readi")),
];

/// The demo size: six 128 x 352 views (half the config's), Swin-T at half width, a
/// +-32 m grid (80 x 80 BEV cells of 0.8 m), half the decoder's channels, 100 proposals.
const SIZE: &[(&str, &str)] = &[
    ("img_h", "128"),
    ("img_w", "352"),
    ("embed", "48"),
    ("neck_out", "128"),
    ("x_min", "-32.0"),
    ("x_max", "32.0"),
    ("cell", "0.4"),
    ("d_max", "40.0"),
    ("vx", "0.1"),
    ("nx", "640"),
    ("max_voxels", "40000"),
    ("max_sites", "60000"),
    ("fused", "128"),
    ("second_out0", "64"),
    ("second_out1", "128"),
    ("fpn_out", "128"),
    ("num_proposals", "100"),
    ("range_x_min", "-40.0"),
    ("range_y_min", "-40.0"),
    ("range_x_max", "40.0"),
    ("range_y_max", "40.0"),
];
const CAMS: usize = 6;
const H: usize = 128;
const W: usize = 352;

/// Variants the demo compiles, seeded, and the meld it serves fog at dusk with.
const VARIANTS: &[&str] = &["fog=0.03", "fog=0.06", "fog=0.1", "snow=1.5", "gamma=0.25", "gamma=0.5", "missing=lidar"];
const MELDS: &[&str] = &["fog=0.06+gamma=0.5"];

/// One stretch of the drive: the weather (fog density alpha, snowfall rate), the
/// camera's exposure and which sensors deliver.
struct Stretch {
    what: &'static str,
    fog: f64,
    snow: f64,
    gamma: f64,
    lidar: bool,
    camera: bool,
}

const DRIVE: &[Stretch] = &[
    Stretch { what: "clear", fog: 0.0, snow: 0.0, gamma: 1.0, lidar: true, camera: true },
    Stretch { what: "fog rising", fog: 0.03, snow: 0.0, gamma: 1.0, lidar: true, camera: true },
    Stretch { what: "dense fog", fog: 0.06, snow: 0.0, gamma: 1.0, lidar: true, camera: true },
    Stretch { what: "dusk in dense fog", fog: 0.06, snow: 0.0, gamma: 0.5, lidar: true, camera: true },
    Stretch { what: "snow", fog: 0.0, snow: 1.5, gamma: 1.0, lidar: true, camera: true },
    Stretch { what: "tunnel: dark", fog: 0.0, snow: 0.0, gamma: 0.25, lidar: true, camera: true },
    Stretch { what: "lidar lost", fog: 0.0, snow: 0.0, gamma: 1.0, lidar: false, camera: true },
    Stretch { what: "cameras lost", fog: 0.0, snow: 0.0, gamma: 1.0, lidar: true, camera: false },
];

/// nuScenes' ten classes, the head's label order.
const CLASSES: [&str; 10] = [
    "car",
    "truck",
    "construction_vehicle",
    "bus",
    "trailer",
    "barrier",
    "motorcycle",
    "bicycle",
    "pedestrian",
    "traffic_cone",
];

/// A frame's sweep (rows of five) and views, each `None` when the sensor is lost.
type Sensors = (Option<Vec<f32>>, Option<Vec<f32>>);

/// A frame's sensor data under `s`: the sweep through the fog or snow simulator, the views
/// through the exposure model and the sensor's noise; a lost sensor delivers nothing.
fn sensors(frame: usize, s: &Stretch) -> Result<Sensors, String> {
    let cars = scene::cars(frame);
    let points = if s.lidar {
        let cloud = PointCloud::new(5, scene::sweep(&cars))?;
        let seed = 7 + frame as u64;
        let cloud = if s.fog > 0.0 {
            readi::simulate::lidar::fog(&cloud, s.fog, seed, None)?.0
        } else if s.snow > 0.0 {
            readi::simulate::lidar::snow(&cloud, s.snow, seed, None)?.0
        } else {
            cloud
        };
        Some(cloud.data().to_vec())
    } else {
        None
    };
    let views = if s.camera {
        let v = scene::views(&cars, CAMS, H, W);
        let mut v = if s.gamma == 1.0 { v } else { readi::simulate::camera::gamma(&v, s.gamma)? };
        // The sensor's noise (after the exposure, as in a camera): uniform, std 0.05.
        let mut uniform = super::super::uniform(0x9E37_79B9_7F4A_7C15u64 ^ frame as u64);
        for p in &mut v {
            *p = (*p + 0.173 * (uniform() - 0.5)).clamp(0.0, 1.0);
        }
        Some(v)
    } else {
        None
    };
    Ok((points, views))
}

/// Runs the BEVFusion demo; `frames` frames of the drive (it repeats when longer).
pub fn run(s: &mut Frontend, threads: usize, frames: usize) -> Result<(), ExitCode> {
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let (name, text) = FILES[0];
    let file = s.sources.add(name, text);
    let mut added: Vec<(&str, FileId)> = vec![(name, file)];
    let start = Instant::now();
    let opts = Options::with_overrides(SIZE);
    let out = passes::run_with_uses(file, text, &opts, &mut |from, path| {
        // Paths relative to the using file, as on disk.
        let dir = s.sources.name(from).rsplit_once('/').map_or("", |(d, _)| d);
        let mut parts: Vec<&str> = dir.split('/').filter(|p| !p.is_empty()).collect();
        for seg in path.split('/') {
            match seg {
                ".." => {
                    parts.pop();
                }
                "." | "" => {}
                seg => parts.push(seg),
            }
        }
        let full = parts.join("/");
        let (n, t) = FILES.iter().find(|(n, _)| *n == full).ok_or_else(|| format!("`{full}` is not embedded"))?;
        if let Some(&(_, id)) = added.iter().find(|(a, _)| a == n) {
            return Ok((id, t.to_string()));
        }
        let id = s.sources.add(*n, *t);
        added.push((n, id));
        Ok((id, t.to_string()))
    });
    let check_ms = start.elapsed().as_secs_f64() * 1e3;
    s.report(&out.diagnostics);
    let Some(m) = out.module.filter(|_| !out.diagnostics.has_errors()) else {
        return Err(fail("the bundled BEVFusion model does not check".into()));
    };
    super::describe_model(&m, name, check_ms);
    let sizes: Vec<String> = SIZE.iter().map(|(k, v)| format!("{k}={v}")).collect();
    println!("  at the demo size: {}", sizes.join(" "));

    let start = Instant::now();
    eprintln!("compiling with seeded weights and {} seeded variants ...", VARIANTS.len());
    let plan = super::seeded_plan(s, &m, VARIANTS, MELDS)?;
    let mf = &plan.manifest;
    println!(
        "\ncompiled in {:.1} s: {} steps, {} of weights, variants {}",
        start.elapsed().as_secs_f64(),
        mf.steps.len(),
        print::bytes(plan.tensor_bytes() as u64),
        plan.variant_keys().skip(1).collect::<Vec<_>>().join(" ")
    );

    let [k, c2l, aug, lidar_aug] = scene::calibration(CAMS, H, W);
    let calibration = [
        ("camera_intrinsics", vec![1, CAMS, 4, 4], k),
        ("camera2lidar", vec![1, CAMS, 4, 4], c2l),
        ("img_aug_matrix", vec![1, CAMS, 4, 4], aug),
        ("lidar_aug_matrix", vec![1, 4, 4], lidar_aug),
    ];
    let mut session = Session::new(plan.clone(), threads).map_err(|e| fail(e.to_string()))?;
    println!("\na drive on {threads} threads: a street of cars seen by a 32-beam lidar and six cameras, the weather");
    println!("applied by readi's simulators, each frame's variant chosen by the spec's selectors:");
    println!(
        "  {:<5} {:<18} {:>6} {:<22} {:>9} {:>8}  boxes kept, best",
        "frame", "conditions", "points", "variant", "switch", "run"
    );
    for frame in 0..frames {
        let stretch = &DRIVE[frame % DRIVE.len()];
        let (points, views) = sensors(frame, stretch).map_err(fail)?;
        let point_shape = [points.as_ref().map_or(0, |p| p.len() / 5), 5];
        let mut given: Vec<Input<'_>> =
            calibration.iter().map(|(n, shape, d)| Input { name: n, data: d, shape }).collect();
        if let Some(p) = &points {
            given.push(Input { name: "points", data: p, shape: &point_shape });
        }
        let view_shape = [1, CAMS, 3, H, W];
        if let Some(v) = &views {
            given.push(Input { name: "camera", data: v, shape: &view_shape });
        }
        let meta = vec![("fog_density".to_string(), stretch.fog), ("snowfall_rate".to_string(), stretch.snow)];
        let selection = conditions::select(&plan, &given, &meta).map_err(|e| fail(e.to_string()))?;
        let t = Instant::now();
        session.set_variant_key(&selection.key).map_err(|e| fail(e.to_string()))?;
        let switch_us = t.elapsed().as_secs_f64() * 1e6;
        let t = Instant::now();
        let result = session.run(&given).map_err(|e| fail(e.to_string()))?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let detections = super::super::run::Detections::of(&result);
        let kept = detections.as_ref().map(|d| d.kept(0)).unwrap_or_default();
        let best = match (&detections, kept.first()) {
            (Some(d), Some(&j)) => {
                let class = CLASSES.get(d.labels.data[j] as usize).copied().unwrap_or("?");
                let v = d.box7(j);
                format!("{class} {:.2} at ({:.1}, {:.1}) m, yaw {:.2}", d.scores.data[j], v[0], v[1], v[6])
            }
            _ => String::from("none"),
        };
        let pts = if points.is_some() { point_shape[0].to_string() } else { "-".into() };
        println!(
            "  {frame:<5} {:<18} {pts:>6} {:<22} {switch_us:>6.2} us {ms:>5.0} ms  {}, {best}",
            stretch.what,
            selection.key.to_string(),
            kept.len()
        );
        super::print_reasons(&selection);
    }
    println!(
        "\nseeded weights: the boxes show the path from points and pixels to decoded boxes, not a trained detector;"
    );
    println!("docs/bevfusion.md compiles a BEVFusion checkpoint and runs it on nuScenes files");
    Ok(())
}
