//! Conditions in the field on bevfusion_tiny: variants chosen from the inputs and run
//! metadata, missing sensors, dropped cameras and melded variants.

mod common;

use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, VariantSource};
use readi_compiler::passes::{self, BackendInputs, Pass};
use readi_runtime::conditions;
use readi_runtime::exec::{Input, RunError, Session, Tensor};
use readi_runtime::plan::Plan;

fn module() -> Module {
    let (sources, out) = common::compile("models/bevfusion_tiny.readi", &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

const KEYS: [&str; 4] = ["gamma=0.25", "fog=0.06", "missing=lidar", "blur=30"];
const MELD: &str = "fog=0.06+gamma=0.25";

fn plan(m: &Module) -> (Arc<Plan>, Vec<VariantSource>) {
    let keys: Vec<String> = KEYS.iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(m, &keys, 50);
    let opts = CompileOptions { melds: vec![MELD.into()], ..Default::default() };
    let weights = backend::seeded_weights(&m.graph, 1);
    let plan = backend::compile_variants(m, &weights, "seeded", &sources, &opts).expect("compiles").0;
    (Arc::new(plan), sources)
}

/// A frame: six camera views of constant `brightness` with a fine checker pattern (sharp),
/// and a lidar BEV grid with `density` of its cells set.
fn frame(brightness: f32, density: f64) -> (Vec<f32>, Vec<f32>) {
    let (h, w) = (128, 352);
    let camera: Vec<f32> = (0..6 * 3 * h * w)
        .map(|i| {
            let (y, x) = ((i / w) % h, i % w);
            brightness + if (x + y) % 2 == 0 { 0.05 } else { -0.05 }
        })
        .collect();
    let cells = 64 * 128 * 128;
    let every = (1.0 / density).round() as usize;
    let lidar: Vec<f32> = (0..cells).map(|i| if i % every == 0 { 0.5 } else { 0.0 }).collect();
    (camera, lidar)
}

const CAMERA: [usize; 5] = [1, 6, 3, 128, 352];
const LIDAR: [usize; 4] = [1, 64, 128, 128];

fn inputs<'a>(camera: Option<&'a [f32]>, lidar: Option<&'a [f32]>) -> Vec<Input<'a>> {
    let mut v = Vec::new();
    if let Some(c) = camera {
        v.push(Input { name: "camera", data: c, shape: &CAMERA });
    }
    if let Some(l) = lidar {
        v.push(Input { name: "lidar_bev", data: l, shape: &LIDAR });
    }
    v
}

fn meta(fog: f64) -> Vec<(String, f64)> {
    vec![("fog_density".into(), fog)]
}

#[test]
fn selectors_choose_variants_and_say_why() {
    let m = module();
    let (plan, _) = plan(&m);
    let (clear_cam, lidar) = frame(0.5, 0.01);
    let (dark_cam, _) = frame(0.1, 0.01);
    let select = |cam: &[f32], lid: Option<&[f32]>, fog: f64| {
        conditions::select(&plan, &inputs(Some(cam), lid), &meta(fog)).expect("selects")
    };

    let s = select(&clear_cam, Some(&lidar), 0.0);
    assert_eq!(s.key.to_string(), "base", "{:?}", s.reasons);
    let s = select(&dark_cam, Some(&lidar), 0.0);
    assert_eq!(s.key.to_string(), "gamma=0.25");
    assert!(s.reasons.iter().any(|r| r.starts_with("gamma: brightness(camera) = 0.1000")), "{:?}", s.reasons);
    let s = select(&clear_cam, Some(&lidar), 0.055);
    assert_eq!(s.key.to_string(), "fog=0.06", "the nearest level: {:?}", s.reasons);
    let s = select(&dark_cam, Some(&lidar), 0.06);
    assert_eq!(s.key.to_string(), MELD, "fog and dark at once: the melded variant: {:?}", s.reasons);
    let s = select(&clear_cam, None, 0.06);
    assert_eq!(s.key.to_string(), "missing=lidar", "a lost lidar; its fog selector is skipped: {:?}", s.reasons);
    // Without selection, the missing-modality policy still holds.
    let (key, why) = conditions::missing_variant(&plan, &inputs(Some(&clear_cam), None)).expect("the policy's variant");
    assert_eq!(key.to_string(), "missing=lidar");
    assert!(why.contains("`lidar_bev` is absent"), "{why}");
    assert_eq!(conditions::missing_variant(&plan, &inputs(Some(&clear_cam), Some(&lidar))), None);
    assert_eq!(conditions::missing_variant(&plan, &inputs(None, Some(&lidar))), None, "camera's policy is zero_fill");
    // A level the plan has no variant for falls back to the nearest compiled one.
    let s = select(&clear_cam, Some(&lidar), 0.15);
    assert_eq!(s.key.to_string(), "fog=0.06");
    assert!(s.reasons.iter().any(|r| r.contains("no `fog=0.15`")), "{:?}", s.reasons);
    // A blurred camera: a flat image has no Laplacian variance.
    let flat = vec![0.5f32; clear_cam.len()];
    assert_eq!(select(&flat, Some(&lidar), 0.0).key.to_string(), "blur=30");
}

#[test]
fn a_dropped_camera_is_not_read_as_darkness() {
    let m = module();
    let (plan, _) = plan(&m);
    let (mut cam, lidar) = frame(0.5, 0.01);
    conditions::drop_views(&mut cam, &CAMERA, &[1, 4]).expect("views exist");
    let per_view = 3 * 128 * 352;
    assert!(cam[per_view..2 * per_view].iter().all(|v| *v == 0.0) && cam[0] != 0.0);
    let s = conditions::select(&plan, &inputs(Some(&cam), Some(&lidar)), &[]).expect("selects");
    assert_eq!(s.key.to_string(), "base", "brightness over the four views present is 0.5: {:?}", s.reasons);
    assert!(conditions::drop_views(&mut cam, &CAMERA, &[6]).is_err());
    let e = conditions::drop_views(&mut cam, &[6, 3, 128, 352], &[1]).expect_err("4-D is not multi-view");
    assert!(e.contains("not multi-view"), "{e}");
}

fn run(plan: &Arc<Plan>, key: &str, given: &[Input<'_>]) -> Result<Vec<(String, Tensor)>, RunError> {
    let mut s = Session::new(plan.clone(), 2).expect("session");
    s.set_variant(key).expect("key");
    s.run(given)
}

#[test]
fn zero_fill_equals_an_explicit_zero_input() {
    let m = module();
    let (plan, _) = plan(&m);
    let (cam, _) = frame(0.5, 0.01);
    let zeros = vec![0.0f32; LIDAR.iter().product()];
    for key in ["base", "gamma=0.25"] {
        let absent = run(&plan, key, &inputs(Some(&cam), None)).expect("runs without lidar");
        let explicit = run(&plan, key, &inputs(Some(&cam), Some(&zeros))).expect("runs");
        for ((_, a), (_, b)) in absent.iter().zip(&explicit) {
            assert!(a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits()), "{key}");
        }
    }
    // Nothing given at all: both modalities are optional here, so this runs too; a model
    // with a required input refuses (tests/cli.rs and the runtime's tests cover that).
    assert!(run(&plan, "base", &[]).is_ok());
}

#[test]
fn a_melded_variant_interpolates_its_parts_parameters() {
    let m = module();
    let keys: Vec<String> = ["gamma=0.25", "fog=0.06"].iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(&m, &keys, 50);
    let base = backend::seeded_weights(&m.graph, 1);
    // Run the back end to the `meld` pass and read the melded variant from the table.
    let opts = CompileOptions { melds: vec![MELD.into()], ..Default::default() };
    let inputs = BackendInputs { base: &base, base_name: "seeded", variants: &sources, opts: &opts };
    let mut melded = m.clone();
    passes::run_backend(&mut melded, &inputs, Some(Pass::Meld)).expect("melds");
    let table = melded.tensors.expect("a tensor table");
    assert_eq!(table.variants[2].key.to_string(), MELD);
    // The paper's rule, with the spec's lambdas camera (gamma) 0.8, lidar (fog) 0.2: the
    // adapt sections are scoped, so a layer only one part owns (the camera branch, the
    // lidar branch) comes whole from it; the layers both own (fuser, head) are
    // interpolated. Seeded variants give every tensor they own, so ownership per tensor is
    // ownership per layer here.
    let (mut whole, mut mixed) = (0, 0);
    for name in table.owned.keys() {
        let v = table.value(name, 3).expect("bound");
        let given: Vec<&Vec<f32>> = sources.iter().filter_map(|s| s.weights.tensors.get(name).map(|t| &t.1)).collect();
        match given.as_slice() {
            [] => assert_eq!(v, table.value(name, 0).expect("base"), "{name}: no part owns it"),
            [only] => {
                assert!(v.iter().zip(only.iter()).all(|(x, y)| x.to_bits() == y.to_bits()), "{name}: taken whole");
                whole += 1;
            }
            [c, l] => {
                for i in 0..v.len() {
                    let want = 0.8 * c[i] as f64 + 0.2 * l[i] as f64;
                    assert!((v[i] as f64 - want).abs() <= 1e-6 * want.abs().max(1.0), "{name}[{i}]");
                }
                mixed += 1;
            }
            _ => unreachable!("two parts"),
        }
    }
    assert!(whole > 0 && mixed > 0, "{whole} tensors taken whole, {mixed} interpolated");
    // The camera branch's LoRA is the camera part's alone: its A and B come whole and the
    // layer's weight stays the base's (an overlapping LoRA is melded on B A: tests/meld.rs).
    let layer = "camera.transformer.blocks.0.q";
    assert_eq!(table.value(&format!("{layer}.weight"), 3), table.value(&format!("{layer}.weight"), 0));
    for ab in ["A", "B"] {
        let name = format!("{layer}.lora_{ab}.weight");
        assert_eq!(table.value(&name, 3).expect("melded"), sources[0].weights.tensors[&name].1.as_slice(), "{name}");
    }
    // Two camera axes at once: no meld rule weighs them apart.
    let both_camera: Vec<String> = ["gamma=0.25", "blur=30"].iter().map(|k| k.to_string()).collect();
    let cam = backend::seeded_variants(&m, &both_camera, 50);
    let opts = CompileOptions { melds: vec!["blur=30+gamma=0.25".into()], ..Default::default() };
    let e = backend::compile_variants(&m, &base, "seeded", &cam, &opts).expect_err("same modality");
    assert!(e.0[0].message.contains("two parts weigh on `camera`"), "{:?}", e.0[0].message);
}

#[test]
fn a_meld_needs_its_parts_and_declared_keys() {
    let m = module();
    let keys: Vec<String> = ["gamma=0.25", "fog=0.06"].iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(&m, &keys, 50);
    let weights = backend::seeded_weights(&m.graph, 1);
    let compile = |meld: &str| {
        let opts = CompileOptions { melds: vec![meld.into()], ..Default::default() };
        backend::compile_variants(&m, &weights, "seeded", &sources, &opts)
    };
    let e = compile("fog=0.1+gamma=0.25").expect_err("fog=0.1 is not given");
    assert!(e.0[0].message.contains("no variant `fog=0.1` is given"), "{}", e.0[0].message);
    let e = compile("fog=0.07+gamma=0.25").expect_err("fog=0.07 is not declared");
    assert!(e.0[0].message.contains("not a combination of declared keys"), "{}", e.0[0].message);
    // Parts in any order and spelling name the canonical key.
    let plan = compile("gamma=0.250+fog=0.06").expect("melds").0;
    assert!(plan.variant_index(MELD).is_some());
}
