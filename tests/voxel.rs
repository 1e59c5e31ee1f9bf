//! The lidar front end against independent references (tests/fixtures/voxel/,
//! `make_voxel_fixtures.py`): `voxelize` as mmcv's CPU hard voxelization, `dynamic_voxelize`
//! with a scatter mean, the HardSimpleVFE mean written with existing ops, and
//! `lidar_depth_map` as BEVFusion's `BaseDepthTransform.forward`; P changing between runs
//! of one session, C = 4 and 5, 1 and 2 threads; hostile points and attributes.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_runtime::exec::{Input, RunError, Session};
use readi_runtime::plan::Plan;

/// The front end at capacity 40 (T = 3) and 60 (dynamic) over a 16 x 16 x 4 grid, with
/// `voxel_mean` as its recipe: `sum(voxels, dim=1) / max(num_points, 1)`.
fn spec(c: usize) -> String {
    format!(
        "model vox {{\n  input points: f32[P, {c}] @lidar\n\n  \
         let v = voxelize(points, voxel_size=[0.5, 0.5, 1.0], point_cloud_range=[-4.0, -4.0, -2.0, 4.0, 4.0, 2.0], \
         max_num_points=3, max_voxels=40)\n  \
         output voxels = v[0]\n  output coords = v[1]\n  output num_points = v[2]\n  \
         output mean = sum(v[0], dim=1) / unsqueeze(to(maximum(v[2], 1), f32), 1)\n  \
         let d = dynamic_voxelize(points, [0.5, 0.5, 1.0], [-4, -4, -2, 4, 4, 2], max_voxels=60)\n  \
         output dyn_features = d[0]\n  output dyn_coords = d[1]\n}}\n"
    )
}

fn build(name: &str, text: &str) -> Plan {
    let (sources, out) = common::compile_text(name, text, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let (plan, _) = backend::compile(&module, &WeightSet::default(), "none", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    plan
}

/// The rendered diagnostics of a spec that must not compile.
fn refused(text: &str) -> String {
    let (sources, out) = common::compile_text("bad.readi", text, &[], None);
    if !out.diagnostics.has_errors() {
        let module = out.module.expect("module");
        match backend::compile(&module, &WeightSet::default(), "none", &CompileOptions::default()) {
            Ok(_) => panic!("compiled: {text}"),
            Err(d) => return sources.render_all(&d, false),
        }
    }
    sources.render_all(&out.diagnostics, false)
}

fn fixture() -> WeightSet {
    let path = common::root().join("tests/fixtures/voxel/voxel.io.safetensors");
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors("voxel.io.safetensors", &bytes).expect("fixture")
}

fn inputs<'a>(io: &'a WeightSet, case: &str) -> Vec<Input<'a>> {
    let prefix = format!("{case}.input.");
    io.tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix(prefix.as_str()).map(|name| Input { name, data, shape }))
        .collect()
}

fn compare(io: &WeightSet, case: &str, outputs: &[(String, readi_runtime::exec::Tensor)], threads: usize) {
    for (name, t) in outputs {
        let (shape, want) = &io.tensors[&format!("{case}.output.{name}")];
        assert_eq!(&t.shape, shape, "{case}: shape of {name}");
        if ["voxels", "coords", "num_points", "dyn_coords"].contains(&name.as_str()) {
            // Cells, counts and copied points: exactly the reference's.
            assert_eq!(&t.data, want, "{case}: {name} at {threads} threads");
            continue;
        }
        for (i, (&g, &w)) in t.data.iter().zip(want).enumerate() {
            let err = (g - w).abs() / w.abs().max(1.0);
            assert!(err <= 1e-5, "{case}: {name}[{i}] is {g}, the reference {w} at {threads} threads");
        }
    }
}

/// Hard and dynamic voxelization against the mmcv-semantics reference: points outside the
/// range (and on its ends), a voxel of six points with T = 3, more voxels than the
/// capacity; one session runs P = 300, 170, 300, so the binding follows P. Same bits at 1
/// and 2 threads.
#[test]
fn voxelization_matches_mmcv_as_points_vary() {
    let io = fixture();
    let plan = Arc::new(build("vox4.readi", &spec(4)));
    let kinds: Vec<&str> = plan.manifest.steps.iter().map(|s| s.kernel.name()).collect();
    assert_eq!(kinds.iter().filter(|k| **k == "voxelize").count(), 3, "{kinds:?}");
    assert_eq!(kinds.iter().filter(|k| **k == "dynamic_voxelize").count(), 2, "{kinds:?}");
    for threads in [1, 2] {
        let mut session = Session::new(Arc::clone(&plan), threads).expect("session");
        for case in ["c4a", "c4b", "c4a"] {
            let outputs = session.run(&inputs(&io, case)).expect("runs");
            assert_eq!(outputs.len(), 6);
            compare(&io, case, &outputs, threads);
            let n = &outputs.iter().find(|o| o.0 == "num_points").expect("num_points").1.data;
            assert!(n.iter().all(|&n| n >= 1.0) && n.contains(&3.0), "{case}: every row active, one full");
        }
    }
    let plan = Arc::new(build("vox5.readi", &spec(5)));
    let outputs = Session::new(plan, 2).expect("session").run(&inputs(&io, "c5")).expect("runs");
    compare(&io, "c5", &outputs, 2);
}

/// Fewer voxels than the capacity: the active rows are a prefix, the rest (-1, -1, -1)
/// with zero features and 0 points.
#[test]
fn inactive_rows_are_minus_one_and_zero() {
    let plan = Arc::new(build("vox4.readi", &spec(4)));
    let pts = [0.1, 0.1, 0.1, 1.0, 9.0, 0.0, 0.0, 2.0, 0.2, 0.3, 0.4, 3.0, -3.9, 3.9, -1.9, 4.0];
    let outputs = Session::new(plan, 1)
        .expect("session")
        .run(&[Input { name: "points", data: &pts, shape: &[4, 4] }])
        .expect("runs");
    let get = |n: &str| &outputs.iter().find(|o| o.0 == n).expect("output").1.data;
    assert_eq!(&get("coords")[..6], [2.0, 8.0, 8.0, 0.0, 15.0, 0.0]);
    assert!(get("coords")[6..].iter().all(|&c| c == -1.0));
    assert_eq!(&get("num_points")[..3], [2.0, 1.0, 0.0]);
    assert_eq!(&get("mean")[..4], [0.15, 0.2, 0.25, 2.0]);
    assert!(get("mean")[8..].iter().all(|&v| v == 0.0));
    assert!(get("voxels")[24..].iter().all(|&v| v == 0.0));
    assert!(get("dyn_coords")[6..].iter().all(|&c| c == -1.0));
}

const DEPTH: &str = "model depth {\n  input points: f32[P, 5] @lidar\n  input camera_intrinsics: f32[1, 2, 4, 4]\n  \
                     input camera2lidar: f32[1, 2, 4, 4]\n  input img_aug_matrix: f32[1, 2, 4, 4]\n  \
                     input lidar_aug_matrix: f32[1, 4, 4]\n\n  output depth = lidar_depth_map(points, \
                     camera_intrinsics, camera2lidar, img_aug_matrix, lidar_aug_matrix, image_size=[32, 48])\n}\n";

/// BEVFusion's sparse depth image against its code (in float64) on two augmented cameras:
/// the same pixels set, the depths to 1e-5, three points on one pixel (the last wins) and
/// a point behind the camera kept with its depth clamped to 1e-5, as BEVFusion does.
#[test]
fn depth_map_matches_bevfusion() {
    let io = fixture();
    let plan = Arc::new(build("depth.readi", DEPTH));
    let (shape, want) = &io.tensors["depth.output.depth"];
    for threads in [1, 2] {
        let outputs =
            Session::new(Arc::clone(&plan), threads).expect("session").run(&inputs(&io, "depth")).expect("runs");
        let got = &outputs[0].1;
        assert_eq!(&got.shape, shape);
        for (i, (&g, &w)) in got.data.iter().zip(want).enumerate() {
            assert_eq!(g == 0.0, w == 0.0, "pixel {i}: {g}, BEVFusion {w}");
            assert!((g - w).abs() <= 1e-5 * w.abs().max(1.0), "pixel {i}: {g}, BEVFusion {w}");
        }
        assert!(got.data.iter().any(|&d| d > 0.0 && d < 1e-4), "the point behind the camera");
    }
    // A batch of two frames' matrices for one frame's points is refused at bind.
    let two = DEPTH.replace("[1, 2, 4, 4]", "[2, 2, 4, 4]").replace("[1, 4, 4]", "[2, 4, 4]");
    let mut s = Session::new(Arc::new(build("depth2.readi", &two)), 1).expect("session");
    let data: Vec<Vec<f32>> = inputs(&io, "depth").iter().map(|i| [i.data, i.data].concat()).collect();
    let shapes: Vec<Vec<usize>> = inputs(&io, "depth")
        .iter()
        .map(|i| if i.name == "points" { i.shape.to_vec() } else { [&[2], &i.shape[1..]].concat() })
        .collect();
    let two_in: Vec<Input<'_>> = inputs(&io, "depth")
        .iter()
        .zip(&data)
        .zip(&shapes)
        .map(|((i, d), s)| Input { name: i.name, data: if i.name == "points" { i.data } else { d }, shape: s })
        .collect();
    let e = s.run(&two_in).expect_err("two frames");
    assert!(e.to_string().contains("batch of 1"), "{e}");
}

/// A NaN or an infinity in the points fails the run naming the input; the session
/// runs good points afterwards. No points at all (P = 0) is refused naming the input.
#[test]
fn hostile_points_are_refused() {
    let plan = Arc::new(build("vox4.readi", &spec(4)));
    let mut s = Session::new(plan, 1).expect("session");
    let mut pts = vec![0.5f32; 12];
    pts[6] = f32::NAN;
    let e = s.run(&[Input { name: "points", data: &pts, shape: &[3, 4] }]).expect_err("NaN");
    // The session refuses it naming the input; the kernel checks again (for a folded
    // constant), naming the row.
    assert!(matches!(&e, RunError::NotFinite { name, index: 6, .. } if name == "points"), "{e:?}");
    pts[6] = f32::INFINITY;
    assert!(s.run(&[Input { name: "points", data: &pts, shape: &[3, 4] }]).is_err(), "inf");
    pts[6] = 0.5;
    s.run(&[Input { name: "points", data: &pts, shape: &[3, 4] }]).expect("good points run");
    let e = s.run(&[Input { name: "points", data: &[], shape: &[0, 4] }]).expect_err("P = 0");
    assert!(matches!(&e, RunError::InputShape { name, .. } if name == "points"), "{e:?}");
    let depth = Arc::new(build("depth.readi", DEPTH));
    let io = fixture();
    let mut bad = io.tensors["depth.input.points"].1.clone();
    bad[7] = f32::NAN;
    let ins: Vec<Input<'_>> = inputs(&io, "depth")
        .into_iter()
        .map(|i| if i.name == "points" { Input { data: &bad, ..i } } else { i })
        .collect();
    let e = Session::new(depth, 1).expect("session").run(&ins).expect_err("NaN");
    assert!(matches!(&e, RunError::NotFinite { name, index: 7, .. } if name == "points"), "{e:?}");
}

/// Bad attributes are compile errors at the argument, with its line.
#[test]
fn bad_attributes_are_refused_at_the_argument() {
    let call = |args: &str| {
        format!("model m {{\n  input points: f32[P, 4]\n  let v = voxelize(points, {args})\n  output c = v[1]\n}}\n")
    };
    let ok = "voxel_size=[0.5, 0.5, 1.0], point_cloud_range=[-4, -4, -2, 4, 4, 2], max_num_points=3, max_voxels=40";
    for (args, want) in [
        (ok.replace("[0.5, 0.5, 1.0]", "[0.5, 0.0, 1.0]"), "voxel_size"),
        (ok.replace("[0.5, 0.5, 1.0]", "[0.5, 0.5]"), "voxel_size"),
        (ok.replace("[-4, -4, -2, 4, 4, 2]", "[-4, -4, -2, 4, 4]"), "point_cloud_range"),
        (ok.replace("[-4, -4, -2, 4, 4, 2]", "[4, -4, -2, -4, 4, 2]"), "point_cloud_range"),
        (ok.replace("max_voxels=40", "max_voxels=0"), "max_voxels"),
        (ok.replace("max_num_points=3", "max_num_points=-1"), "max_num_points"),
        (ok.replace("[0.5, 0.5, 1.0]", "[0.00001, 0.00001, 0.00001]"), "point_cloud_range"),
    ] {
        let text = refused(&call(&args));
        assert!(text.contains(want) && text.contains(":3:"), "{args}: {text}");
    }
    let text = refused(
        "model m {\n  input points: f32[P, 2]\n  let v = dynamic_voxelize(points, [1, 1, 1], [0, 0, 0, 4, 4, 4], max_voxels=4)\n  output c = v[1]\n}\n",
    );
    assert!(text.contains("points") && text.contains(":3:"), "{text}");
    let text = refused(&DEPTH.replace("image_size=[32, 48]", "image_size=[0, 48]"));
    assert!(text.contains("image_size"), "{text}");
    let text = refused(&DEPTH.replace("input camera2lidar: f32[1, 2, 4, 4]", "input camera2lidar: f32[1, 3, 4, 4]"));
    assert!(text.contains("camera2lidar"), "{text}");
}

/// `readi run --input points=sweep.bin` reads a KITTI / nuScenes point cloud (rows of the
/// input's C little-endian f32 values), the same as the `.npy` of those points; a file
/// that is not a whole number of rows is refused naming it.
#[test]
fn the_cli_reads_bin_point_clouds() {
    let dir = common::Scratch::new("voxel-cli");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let spec = dir.join("vox5.readi");
    std::fs::write(&spec, spec_text_for_cli()).expect("spec");
    let plan = dir.join("vox5.plan");
    // The model stores no tensors: an empty safetensors file (an 8-byte length and `{}`).
    let weights = dir.join("none.safetensors");
    std::fs::write(&weights, [&2u64.to_le_bytes()[..], b"{}"].concat()).expect("weights");
    let o = common::readi(&["compile", &p(&spec), "--weights", &p(&weights), "-o", &p(&plan)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let io = fixture();
    let (shape, pts) = &io.tensors["c5.input.points"];
    let bin = dir.join("sweep.bin");
    std::fs::write(&bin, pts.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).expect("bin");
    let out = dir.join("out.safetensors");
    let o = common::readi(&["run", &p(&plan), "--input", &format!("points={}", p(&bin)), "--output", &p(&out)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let got = WeightSet::from_safetensors("out", &std::fs::read(&out).expect("out")).expect("outputs");
    assert_eq!(shape, &[250, 5]);
    assert_eq!(got.tensors["coords"], io.tensors["c5.output.coords"]);
    assert_eq!(got.tensors["num_points"], io.tensors["c5.output.num_points"]);
    // 1249 floats are not rows of 5.
    std::fs::write(&bin, pts[..1249].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).expect("bin");
    let o = common::readi(&["run", &p(&plan), "--input", &format!("points={}", p(&bin)), "--output", &p(&out)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("sweep.bin") && err.contains("not a positive multiple of 20"), "{err}");
}

fn spec_text_for_cli() -> String {
    "model vox {\n  input points: f32[P, 5] @lidar\n  let v = voxelize(points, voxel_size=[0.5, 0.5, 1.0], \
     point_cloud_range=[-4.0, -4.0, -2.0, 4.0, 4.0, 2.0], max_num_points=3, max_voxels=40)\n  \
     output coords = v[1]\n  output num_points = v[2]\n}\n"
        .into()
}
