//! Plan files are untrusted: truncated, bit-flipped, wrong-version and inconsistent plans
//! are refused with an error naming the problem, never a panic.

mod common;

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions};
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::{Plan, PlanError, Storage};
use safetensors::SafeTensors;
use safetensors::tensor::TensorView;

/// A plan of tests/cases/ok/all_ops.readi (every kernel) with seeded weights.
fn plan() -> Plan {
    let (sources, out) = common::compile("tests/cases/ok/all_ops.readi", &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let weights = backend::seeded_weights(&module.graph, 3);
    backend::compile(&module, &weights, "seeded", &CompileOptions::default()).expect("compiles").0
}

/// `name` in a scratch directory of the test's own (removed when the guard drops).
fn temp(name: &str) -> (common::Scratch, PathBuf) {
    let dir = common::Scratch::new("planfile");
    let path = dir.join(name);
    (dir, path)
}

fn load_bytes(name: &str, bytes: &[u8]) -> Result<Plan, PlanError> {
    let (_dir, path) = temp(name);
    std::fs::write(&path, bytes).expect("write");
    Plan::load(&path)
}

#[test]
fn a_written_plan_loads_and_runs() {
    let p = plan();
    let bytes = p.to_bytes().expect("serialise");
    let loaded = load_bytes("ok.plan", &bytes).expect("loads");
    assert_eq!(loaded.manifest, p.manifest);
    for i in 0..p.manifest.tensors.len() {
        assert_eq!(loaded.tensor(i), p.tensor(i), "tensor {i}");
    }
    let mut s = Session::new(Arc::new(loaded), 1).expect("session");
    let img = vec![0.5f32; 4 * 16 * 16];
    let out = s.run(&[Input { name: "img", data: &img, shape: &[1, 4, 16, 16] }]).expect("runs");
    assert_eq!(out.len(), 3);
}

#[test]
fn truncated_plans_are_refused() {
    let bytes = plan().to_bytes().expect("serialise");
    for cut in [0, 4, 8, 100, bytes.len() / 2, bytes.len() - 4, bytes.len() - 1] {
        let e = load_bytes("cut.plan", &bytes[..cut]).expect_err("a truncated plan must not load");
        assert!(matches!(e, PlanError::Container { .. }), "cut at {cut}: {e}");
        assert!(e.to_string().contains("cut.plan") && e.to_string().contains("truncated"), "{e}");
    }
}

#[test]
fn every_flipped_bit_is_detected() {
    let bytes = plan().to_bytes().expect("serialise");
    let header = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize + 8;
    let mut positions: Vec<usize> = (0..bytes.len()).step_by(61).collect();
    positions.extend([0, 7, header - 1, header, bytes.len() - 1]);
    for pos in positions {
        for bit in [0, 5] {
            let mut b = bytes.clone();
            b[pos] ^= 1 << bit;
            let e = load_bytes("flip.plan", &b).expect_err("a flipped bit must be detected");
            if pos >= header {
                assert!(matches!(e, PlanError::Checksum { .. }), "flip in data at {pos}: {e}");
            }
        }
    }
}

/// Re-serialises a plan file with edited metadata.
fn with_metadata(bytes: &[u8], edit: impl FnOnce(&mut HashMap<String, String>)) -> Vec<u8> {
    let st = SafeTensors::deserialize(bytes).expect("valid");
    let (_, meta) = SafeTensors::read_metadata(bytes).expect("valid");
    let mut md = meta.metadata().clone().expect("metadata");
    edit(&mut md);
    let views: Vec<(String, TensorView<'_>)> = st.tensors();
    safetensors::serialize(views, Some(md)).expect("serialise")
}

#[test]
fn other_format_versions_are_refused() {
    let bytes = plan().to_bytes().expect("serialise");
    let edited = with_metadata(&bytes, |md| {
        md.insert("readi.format_version".into(), "999".into());
    });
    let e = load_bytes("v999.plan", &edited).expect_err("wrong version");
    assert!(matches!(e, PlanError::Version { .. }), "{e}");
    assert!(e.to_string().contains("version 999") && e.to_string().contains("recompile"), "{e}");
}

#[test]
fn version_2_plans_still_load() {
    // Version 2 wrote an epilogue's activation as `"relu": bool`; version 3 and later as
    // `"act"`.
    let p = plan();
    let json = serde_json::to_string(&p.manifest).expect("manifest");
    assert!(json.contains(r#""act":"Relu""#), "the case fuses a ReLU");
    let current = format!(r#""format_version":{}"#, readi_plan::format::FORMAT_VERSION);
    assert!(json.contains(&current), "{json}");
    let v2 = json.replace(r#""act":"Relu""#, r#""relu":true"#).replace(&current, r#""format_version":2"#);
    let tensors: Vec<(String, Vec<usize>, Vec<u8>)> = (0..p.manifest.tensors.len())
        .map(|i| {
            let t = &p.manifest.tensors[i];
            (t.name.clone(), t.shape.clone(), p.tensor(i).iter().flat_map(|v| v.to_le_bytes()).collect())
        })
        .collect();
    let loaded = load_bytes("v2.plan", &common::plan_file_bytes("2", v2, &tensors)).expect("a version 2 plan loads");
    assert_eq!(loaded.manifest.steps, p.manifest.steps);
    let img: Vec<f32> = (0..4 * 16 * 16).map(|i| (i % 7) as f32 * 0.25 - 0.7).collect();
    let input = [Input { name: "img", data: &img, shape: &[1, 4, 16, 16] }];
    let want = Session::new(Arc::new(p), 1).expect("session").run(&input).expect("runs");
    let got = Session::new(Arc::new(loaded), 1).expect("session").run(&input).expect("runs");
    assert_eq!(got, want);
}

#[test]
fn a_weights_file_is_not_a_plan() {
    let bytes = plan().to_bytes().expect("serialise");
    let plain = with_metadata(&bytes, |md| md.clear());
    let e = load_bytes("weights.safetensors", &plain).expect_err("not a plan");
    assert!(matches!(e, PlanError::NotAPlan { .. }), "{e}");
    let e = load_bytes("junk.plan", b"definitely not a plan").expect_err("junk");
    assert!(matches!(e, PlanError::Container { .. }), "{e}");
    let e = Plan::load(&temp("absent.plan").1).expect_err("missing file");
    assert!(matches!(e, PlanError::Io { .. }) && e.to_string().contains("absent.plan"), "{e}");
}

#[test]
fn out_of_range_indices_are_refused() {
    let p = plan();
    let tensors: Vec<Vec<f32>> = (0..p.manifest.tensors.len()).map(|i| p.tensor(i).to_vec()).collect();
    let mut m = p.manifest.clone();
    m.steps[3].inputs[0] = 9999;
    let e = Plan::new(m, tensors.clone()).expect_err("bad index");
    assert!(e.to_string().contains("reads value 9999"), "{e}");
    let mut m = p.manifest.clone();
    let last = m.steps.len() - 1;
    m.steps[0].inputs = vec![m.steps[last].output];
    let e = Plan::new(m, tensors).expect_err("read before write");
    assert!(e.to_string().contains("before it is written"), "{e}");
}

#[test]
fn inconsistent_shapes_are_refused_before_any_kernel_runs() {
    let p = plan();
    let tensors: Vec<Vec<f32>> = (0..p.manifest.tensors.len()).map(|i| p.tensor(i).to_vec()).collect();
    let mut m = p.manifest.clone();
    // Claim the first step writes one more channel than its kernel produces.
    let v = m.steps[0].output;
    assert!(matches!(m.values[v].storage, Storage::Slot(_)));
    let channels = m.values[v].shape[1].as_known().expect("a known channel count");
    m.values[v].shape[1] = readi_plan::Dim::known(channels + 1);
    let e = Plan::new(m, tensors).expect_err("must be refused").to_string();
    assert!(e.contains("step 0") && e.contains("its output has shape"), "{e}");
}

#[test]
fn run_errors_name_the_input() {
    let mut s = Session::new(Arc::new(plan()), 1).expect("session");
    let img = vec![0.5f32; 4 * 16 * 16];
    let e = s.run(&[]).expect_err("img is required");
    assert_eq!(e.to_string(), "input `img` is required but was not given");
    let e = s.run(&[Input { name: "imag", data: &img, shape: &[1, 4, 16, 16] }]).expect_err("typo");
    assert!(e.to_string().contains("no input `imag`") && e.to_string().contains("img, seq_in"), "{e}");
    let e = s.run(&[Input { name: "img", data: &img, shape: &[1, 4, 16, 8] }]).expect_err("shape");
    assert!(e.to_string().contains("4 * 16 * 8") || e.to_string().contains("do not fill"), "{e}");
    let e = s.run(&[Input { name: "img", data: &img[..512], shape: &[2, 4, 8, 8] }]).expect_err("shape");
    assert!(e.to_string().contains("axis 2 must be 16"), "{e}");
    let mut nan = img.clone();
    nan[17] = f32::NAN;
    let e = s.run(&[Input { name: "img", data: &nan, shape: &[1, 4, 16, 16] }]).expect_err("nan");
    assert!(e.to_string().contains("flat index 17"), "{e}");
}

#[test]
fn absent_optional_inputs_are_zeros() {
    let mut s = Session::new(Arc::new(plan()), 1).expect("session");
    let img = vec![0.25f32; 2 * 4 * 16 * 16];
    let zeros = vec![0.0f32; 2 * 10 * 32];
    let a = s.run(&[Input { name: "img", data: &img, shape: &[2, 4, 16, 16] }]).expect("runs without seq_in");
    let b = s
        .run(&[
            Input { name: "img", data: &img, shape: &[2, 4, 16, 16] },
            Input { name: "seq_in", data: &zeros, shape: &[2, 10, 32] },
        ])
        .expect("runs with zeros");
    assert_eq!(a, b);
}
