//! The model zoo (models/<name>.readi) against torchvision, from the fixtures
//! tests/fixtures/zoo/make_zoo_fixtures.py writes:
//!
//! - the spec's state_dict table (every key with its dtype and shape, `num_batches_tracked`
//!   included, and the parameter count) equals torchvision's (`<name>.txt`), so a
//!   torchvision checkpoint binds with no renaming;
//! - compiled with readi's seeded weights (through a safetensors file, as a user's export
//!   would be, with every conv weight scaled by the fixture's `conv_gain`), each model
//!   matches the logits torchvision computes with the same weights (`<name>.safetensors`)
//!   to 1e-4 (max abs), at 1 and at 2 threads.

mod common;

use std::collections::BTreeMap;
use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_compiler::ir::SlotKind;
use readi_runtime::exec::{Input, Session};

/// The metadata of a fixture: the seed, the `--set` overrides and the conv weights' gain.
struct Fixture {
    seed: u64,
    overrides: Vec<(String, String)>,
    gain: f32,
    tensors: WeightSet,
}

fn fixture(name: &str) -> Fixture {
    let path = common::root().join("tests/fixtures/zoo").join(format!("{name}.safetensors"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).expect("fixture header");
    let meta = header.metadata().clone().expect("fixture metadata");
    let overrides = meta["overrides"]
        .split(',')
        .map(|kv| kv.split_once('=').expect("key=value"))
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    Fixture {
        seed: meta["seed"].parse().expect("seed"),
        overrides,
        gain: meta["conv_gain"].parse().expect("conv_gain"),
        tensors: WeightSet::from_safetensors(name, &bytes).expect("fixture"),
    }
}

/// `param`, `count` and `output` lines of torchvision's table.
fn torchvision_table(name: &str) -> (BTreeMap<String, String>, u64, String) {
    let path = common::root().join("tests/fixtures/zoo").join(format!("{name}.txt"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (mut params, mut count, mut output) = (BTreeMap::new(), 0, String::new());
    for line in text.lines() {
        match line.splitn(3, ' ').collect::<Vec<_>>()[..] {
            ["param", key, rest] => {
                params.insert(key.to_string(), rest.replace(' ', ""));
            }
            ["count", n] => count = n.parse().expect("a count"),
            ["output", "logits", shape] => output = shape.replace(' ', ""),
            _ => panic!("bad line in {name}.txt: {line}"),
        }
    }
    (params, count, output)
}

fn check_table(name: &str) {
    let rel = format!("models/{name}.readi");
    let (sources, out) = common::compile(&rel, &[], None);
    assert!(out.diagnostics.is_empty(), "{rel}: {}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let ours: BTreeMap<String, String> = m
        .graph
        .param_table()
        .into_iter()
        .filter(|(_, _, slot)| slot.kind != SlotKind::Added)
        .map(|(key, _, slot)| (key, format!("{}{:?}", slot.dtype.as_str(), slot.shape).replace(' ', "")))
        .collect();
    let (theirs, count, output) = torchvision_table(name);
    let missing: Vec<_> = theirs.keys().filter(|k| !ours.contains_key(*k)).collect();
    let extra: Vec<_> = ours.keys().filter(|k| !theirs.contains_key(*k)).collect();
    assert!(missing.is_empty() && extra.is_empty(), "{rel}: keys missing {missing:?}, extra {extra:?}");
    for (k, v) in &theirs {
        assert_eq!(&ours[k], v, "{rel}: dtype and shape of {k}");
    }
    assert_eq!(m.graph.parameter_count(), count, "{rel}: parameter count");
    let [o] = &m.graph.outputs[..] else { panic!("{rel}: one output expected") };
    assert_eq!(o.name, "logits");
    let t = m.graph.value_type(o.value).expect("typed output");
    assert_eq!(format!("[2,{}]", t.shape[1]), output, "{rel}: logits at batch 2");
}

fn max_abs_error(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

fn check_parity(name: &str) {
    let rel = format!("models/{name}.readi");
    let fx = fixture(name);
    let overrides: Vec<(&str, &str)> = fx.overrides.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    let (sources, out) = common::compile(&rel, &overrides, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let mut weights = backend::seeded_weights(&module.graph, fx.seed);
    for (key, (shape, data)) in weights.tensors.iter_mut() {
        if key.ends_with(".weight") && shape.len() == 4 {
            data.iter_mut().for_each(|v| *v *= fx.gain);
        }
    }
    let bytes = weights.to_safetensors().expect("serialises");
    let weights = WeightSet::from_safetensors("seeded.safetensors", &bytes).expect("valid safetensors");
    let (plan, warnings) = backend::compile(&module, &weights, "seeded.safetensors", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    assert!(warnings.is_empty(), "{}", sources.render_all(&warnings, false));
    let plan = Arc::new(plan);

    let (shape, data) = &fx.tensors.tensors["input.image"];
    let (want_shape, want) = &fx.tensors.tensors["output.logits"];
    for threads in [1, 2] {
        let mut session = Session::new(plan.clone(), threads).expect("session");
        let outs = session.run(&[Input { name: "image", data, shape }]).expect("run");
        let [(oname, got)] = &outs[..] else { panic!("{name}: one output expected") };
        assert_eq!(oname, "logits");
        assert_eq!(&got.shape, want_shape, "{name}: shape of logits");
        let err = max_abs_error(&got.data, want);
        eprintln!("{name}: logits max abs error vs torchvision {err:e} at {threads} thread(s)");
        assert!(err <= 1e-4, "{name}: logits differ from torchvision by {err:e} at {threads} thread(s)");
    }
}

/// The zoo, in the order of the README's table.
const ZOO: [&str; 7] = [
    "resnet50",
    "mobilenet_v2",
    "mobilenet_v3_large",
    "efficientnet_b0",
    "convnext_tiny",
    "vit_b_16",
    "regnet_y_400mf",
];

/// `readi params` reports torchvision's parameter count for each model, with 1000 classes.
#[test]
fn readi_params_counts_torchvisions_parameters() {
    for name in ZOO {
        let rel = format!("models/{name}.readi");
        let o = common::readi(&["params", &rel]);
        let stdout = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "readi params {rel}: {}", String::from_utf8_lossy(&o.stderr));
        let (_, count, _) = torchvision_table(name);
        let total = stdout.lines().find(|l| l.starts_with("total: ")).expect("a total line");
        let shown: u64 = total["total: ".len()..]
            .split_whitespace()
            .next()
            .map(|n| n.replace(',', ""))
            .and_then(|n| n.parse().ok())
            .expect("a count");
        assert_eq!(shown, count, "readi params {rel}: {total}");
    }
}

#[test]
fn resnet50_state_dict_matches_torchvision() {
    check_table("resnet50");
}

#[test]
fn resnet50_matches_torchvision() {
    check_parity("resnet50");
}

#[test]
fn mobilenet_v2_state_dict_matches_torchvision() {
    check_table("mobilenet_v2");
}

#[test]
fn mobilenet_v2_matches_torchvision() {
    check_parity("mobilenet_v2");
}

#[test]
fn mobilenet_v3_large_state_dict_matches_torchvision() {
    check_table("mobilenet_v3_large");
}

#[test]
fn mobilenet_v3_large_matches_torchvision() {
    check_parity("mobilenet_v3_large");
}

#[test]
fn efficientnet_b0_state_dict_matches_torchvision() {
    check_table("efficientnet_b0");
}

#[test]
fn efficientnet_b0_matches_torchvision() {
    check_parity("efficientnet_b0");
}

#[test]
fn convnext_tiny_state_dict_matches_torchvision() {
    check_table("convnext_tiny");
}

#[test]
fn convnext_tiny_matches_torchvision() {
    check_parity("convnext_tiny");
}

#[test]
fn vit_b_16_state_dict_matches_torchvision() {
    check_table("vit_b_16");
}

/// At 32x32 (torchvision's `image_size=32`: 4 patches and the class token), batch 2.
#[test]
fn vit_b_16_matches_torchvision() {
    check_parity("vit_b_16");
}

/// torchvision's `block1-0`-style names, spelt as quoted layer names.
#[test]
fn regnet_y_400mf_state_dict_matches_torchvision() {
    check_table("regnet_y_400mf");
}

/// At 40x40 (the last stage runs at 2x2), batch 2.
#[test]
fn regnet_y_400mf_matches_torchvision() {
    check_parity("regnet_y_400mf");
}
