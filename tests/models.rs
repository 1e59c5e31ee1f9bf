//! The bundled models against independent references: the parameter totals torchvision
//! reports, and full state_dict tables (key, dtype, shape) and output shapes written by
//! PyTorch (tests/fixtures/make_param_tables.py).

mod common;

use std::collections::BTreeMap;

use common::compile;
use readi_compiler::Module;
use readi_compiler::ir::Dim;

fn module(rel: &str, overrides: &[(&str, &str)]) -> Module {
    let (sources, out) = compile(rel, overrides, None);
    assert!(
        out.diagnostics.is_empty(),
        "{rel} should check without diagnostics:\n{}",
        sources.render_all(&out.diagnostics, false)
    );
    out.module.expect("a module")
}

#[test]
fn resnet18_counts_torchvisions_parameters() {
    // torchvision.models.resnet18(): 11,689,512 parameters; with num_classes=10: 11,181,642.
    assert_eq!(module("models/resnet18.readi", &[]).graph.parameter_count(), 11_689_512);
    assert_eq!(module("models/resnet18.readi", &[("num_classes", "10")]).graph.parameter_count(), 11_181_642);
}

#[test]
fn bevfusion_parts_count_the_references_parameters() {
    // The plain-PyTorch ports at the nuScenes config's sizes, `--count`:
    // make_lidar_fixtures.py (encoders.lidar.backbone) 2,694,352; make_bevfusion_fixtures.py
    // (encoders.camera.neck + vtransform) 3,202,022, (fuser + decoder + heads.object) 6,386,334;
    // make_swin_fixtures.py (encoders.camera.backbone, mmdet's Swin-T with out_indices
    // [1, 2, 3]) 27,520,506: torchvision's swin_t 28,288,354 without its head (769,000) and
    // final norm (1,536), with mmdet's three output norms (2,688); make_full_fixtures.py (the
    // whole detector) 39,803,214, their sum.
    for (rel, count) in [
        ("models/bevfusion/lidar.readi", 2_694_352),
        ("models/bevfusion/camera.readi", 3_202_022),
        ("models/bevfusion/decoder.readi", 6_386_334),
        ("models/bevfusion/swin.readi", 27_520_506),
        ("models/bevfusion.readi", 39_803_214),
    ] {
        assert_eq!(module(rel, &[]).graph.parameter_count(), count, "{rel}");
    }
}

struct Reference {
    params: BTreeMap<String, String>,
    count: u64,
    outputs: BTreeMap<String, String>,
}

fn reference(name: &str) -> Reference {
    let path = common::root().join("tests/fixtures/torch").join(format!("{name}.txt"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut r = Reference { params: BTreeMap::new(), count: 0, outputs: BTreeMap::new() };
    for line in text.lines() {
        let mut parts = line.splitn(3, ' ');
        match (parts.next(), parts.next(), parts.next()) {
            (Some("param"), Some(key), Some(rest)) => {
                r.params.insert(key.to_string(), rest.replace(' ', ""));
            }
            (Some("count"), Some(n), None) => r.count = n.parse().expect("a count"),
            (Some("output"), Some(o), Some(shape)) => {
                r.outputs.insert(o.to_string(), shape.replace(' ', ""));
            }
            _ => panic!("bad line in {name}.txt: {line}"),
        }
    }
    r
}

/// Compares readi's state_dict table and output shapes (batch N = 2) with PyTorch's.
fn assert_matches_pytorch(rel: &str, overrides: &[(&str, &str)], reference_name: &str) {
    let m = module(rel, overrides);
    let r = reference(reference_name);
    let ours: BTreeMap<String, String> = m
        .graph
        .param_table()
        .into_iter()
        // The base model's state_dict: without the slots adaptation rules add.
        .filter(|(_, _, slot)| slot.kind != readi_compiler::ir::SlotKind::Added)
        .map(|(name, _, slot)| (name, format!("{}{:?}", slot.dtype.as_str(), slot.shape).replace(' ', "")))
        .collect();
    let missing: Vec<_> = r.params.keys().filter(|k| !ours.contains_key(*k)).collect();
    let extra: Vec<_> = ours.keys().filter(|k| !r.params.contains_key(*k)).collect();
    assert!(missing.is_empty() && extra.is_empty(), "{rel}: keys missing {missing:?}, extra {extra:?}");
    for (k, v) in &r.params {
        assert_eq!(&ours[k], v, "{rel}: shape of {k}");
    }
    assert_eq!(m.graph.parameter_count(), r.count, "{rel}: parameter count");

    let two = Dim::known(2);
    for o in &m.graph.outputs {
        let t = m.graph.value_type(o.value).expect("typed output");
        let dims: Vec<String> = t
            .shape
            .iter()
            .map(|d| match d.symbols() {
                [s] if s == "N" => d.checked_div(&Dim::symbol("N")).and_then(|k| k.checked_mul(&two)).expect("N"),
                _ => d.clone(),
            })
            .map(|d| d.to_string())
            .collect();
        assert_eq!(Some(&format!("[{}]", dims.join(","))), r.outputs.get(&o.name), "{rel}: output {}", o.name);
    }
    assert_eq!(m.graph.outputs.len(), r.outputs.len(), "{rel}: number of outputs");
}

#[test]
fn resnet18_state_dict_matches_torchvision() {
    assert_matches_pytorch("models/resnet18.readi", &[], "resnet18");
    assert_matches_pytorch("models/resnet18.readi", &[("num_classes", "10")], "resnet18_c10");
}

#[test]
fn vit_encoder_state_dict_matches_pytorch() {
    assert_matches_pytorch("models/vit_encoder.readi", &[], "vit_encoder");
}

#[test]
fn pointpillars_state_dict_matches_pytorch() {
    assert_matches_pytorch("models/pointpillars_bev.readi", &[], "pointpillars_bev");
}

#[test]
fn bevfusion_tiny_checks_cleanly_with_both_optional_sensors() {
    let m = module("models/bevfusion_tiny.readi", &[]);
    let optional: Vec<bool> = m
        .graph
        .input_nodes()
        .into_iter()
        .map(|n| matches!(&m.graph.node(n).op, readi_compiler::ir::Op::Input(a) if a.optional))
        .collect();
    assert_eq!(optional, vec![true, true]);
    let v = m.variants.as_ref().expect("variants");
    assert_eq!(v.meld.as_ref().map(|m| m.weights.clone()), Some(vec![("camera".into(), 0.8), ("lidar".into(), 0.2)]));
}
