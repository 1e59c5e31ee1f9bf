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

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, LoraMode, VariantSource, WeightSet, peft};
use readi_compiler::ir::SlotKind;
use readi_grammar::diag::SourceMap;
use readi_runtime::exec::{Input, Session};

/// The metadata of a fixture: the seed, the `--set` overrides and the conv weights' gain;
/// its tensors are the input, the logits and torchvision's int64 buffers.
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

/// The model the fixture was made with (its overrides) and its seeded weights, every conv
/// weight scaled by the fixture's gain, through a safetensors file.
fn seeded_model(name: &str, fx: &Fixture) -> (SourceMap, Module, WeightSet) {
    let rel = format!("models/{name}.readi");
    let overrides: Vec<(&str, &str)> = fx.overrides.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
    let (sources, out) = common::compile(&rel, &overrides, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let mut weights = backend::seeded_weights(&module.graph, fx.seed);
    for (key, (shape, data)) in weights.tensors.iter_mut() {
        if key.ends_with(".weight") && shape.len() == 4 {
            data.iter_mut().for_each(|v| *v *= fx.gain);
        }
        // An int64 buffer is torchvision's own, stored once per name in the fixture.
        if weights.integer.contains(key) {
            let last = key.rsplit('.').next().unwrap_or(key);
            let (want_shape, want) = fx.tensors.tensors.get(&format!("buffer.{last}")).unwrap_or_else(|| {
                panic!("{name}: the fixture has no `buffer.{last}` for {key}");
            });
            assert_eq!(want_shape, shape, "{name}: shape of {key}");
            data.clone_from(want);
        }
    }
    let bytes = weights.to_safetensors().expect("serialises");
    let weights = WeightSet::from_safetensors("seeded.safetensors", &bytes).expect("valid safetensors");
    (sources, module, weights)
}

fn check_parity(name: &str) {
    let fx = fixture(name);
    let (sources, module, weights) = seeded_model(name, &fx);
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
const ZOO: [&str; 8] = [
    "resnet50",
    "mobilenet_v2",
    "mobilenet_v3_large",
    "efficientnet_b0",
    "convnext_tiny",
    "swin_t",
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

/// Compiled at the parity fixture's size with seeded weights, no step of `name`'s plan
/// reads only stored tensors (`fold_constants` computed each such value once, at compile
/// time), no step permutes a stored tensor, and the plan's parameter table lists the
/// state_dict's names, each of `folded` saying where it was folded and stored no more.
fn check_folded(name: &str, folded: &[&str]) {
    use readi_plan::format::{Kernel, Storage};
    use readi_plan::ops::Pure;
    let fx = fixture(name);
    let (sources, module, weights) = seeded_model(name, &fx);
    let (plan, _) = backend::compile(&module, &weights, "seeded", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let m = &plan.manifest;
    let stored = |v: usize| matches!(m.values[v].storage, Storage::Tensor(_));
    for step in &m.steps {
        // (An expand of ViT's class token to the batch, a symbolic size, stays a step.)
        let known = m.values[step.output].shape.iter().all(|d| d.as_known().is_some());
        assert!(!known || !step.inputs.iter().all(|&v| stored(v)), "step `{}` reads only stored tensors", step.path);
        if matches!(step.kernel, Kernel::Pure(Pure::Permute(_))) {
            assert!(!step.inputs.iter().any(|&v| stored(v)), "step `{}` permutes a stored tensor", step.path);
        }
    }
    for &key in folded {
        let p = m.params.iter().find(|p| p.name == key).expect("the state_dict's name in the parameter table");
        // ("constant-folded into" for a weight; an index buffer is "folded into" the value.)
        assert!(p.stored_as.contains("folded into"), "{key}: {}", p.stored_as);
        assert!(!m.tensors.iter().any(|t| t.name == key), "the raw {key} is stored too");
    }
    assert_eq!(m.params.len(), module.graph.param_table().len(), "the parameter table lists the spec's parameters");
}

/// ViT's attention reads `in_proj_weight` transposed; `fold_constants` transposes it once,
/// at compile time (a permute of a weight would be 7 MB per layer per run at 224).
#[test]
fn vit_b_16_transposes_no_weight_at_run_time() {
    check_folded("vit_b_16", &["encoder.layers.encoder_layer_0.self_attention.in_proj_weight"]);
}

/// A PEFT LoRA fixture of tests/fixtures/zoo/make_zoo_peft_fixtures.py: r=4,
/// lora_alpha=8 on the `kinds` under each of the `layers`, with non-zero B, saved by
/// `save_pretrained`. The directory is read as PEFT wrote it and compiled as a LoRA-only
/// variant over the seeded base of the model's parity test, with LoRA merged and as a
/// branch, and run at 1 and 2 threads: the base, the variant against PEFT's merged model
/// (`merge_and_unload`: W + (alpha / r) B A, which is what readi computes; torchvision
/// never calls the forward of some of these layers, see the script), then the base
/// again, bit for bit. The one compile warning counts what the adapter gives (its LoRA
/// matrices) of what the variant owns (the tuned norms and head, every layer's LoRA).
fn check_peft(name: &str, layers: &[&str], kinds: &[&str]) {
    let fx = fixture(name);
    let (sources, module, weights) = seeded_model(name, &fx);
    let path = common::root().join(format!("tests/fixtures/zoo/peft/{name}.safetensors"));
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).expect("fixture header");
    let key = header.metadata().as_ref().expect("fixture metadata")["variant"].clone();
    let peft_fx = WeightSet::from_safetensors("peft fixture", &bytes).expect("fixture");

    let dir = common::root().join(format!("tests/fixtures/zoo/peft/{name}/{key}"));
    let config = std::fs::read_to_string(dir.join(peft::CONFIG_FILE)).expect("adapter config");
    let adapter = std::fs::read(dir.join(peft::WEIGHTS_FILE)).expect("adapter weights");
    let lora = peft::read_adapter(&dir.display().to_string(), &config, &adapter, &module)
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let mut got_layers: Vec<String> =
        lora.tensors.keys().filter_map(|k| k.strip_suffix(".lora_A.weight")).map(str::to_string).collect();
    got_layers.sort();
    let mut want_layers: Vec<String> =
        layers.iter().flat_map(|l| kinds.iter().map(move |k| format!("{l}.{k}"))).collect();
    want_layers.sort();
    assert_eq!(got_layers, want_layers, "the adapter's LoRA layers");
    assert_eq!(lora.tensors.len(), 2 * got_layers.len(), "A and B of each layer, nothing else");
    let source = VariantSource { key: key.clone(), weights: lora, origin: dir.display().to_string() };

    let image = &fx.tensors.tensors["input.image"];
    let (logits_shape, base_want) = &fx.tensors.tensors["output.logits"];
    let (variant_shape, variant_want) = &peft_fx.tensors[&format!("{key}.logits")];
    assert_eq!(variant_shape, logits_shape);
    assert!(max_abs_error(base_want, variant_want) > 1e-2, "the adapter should change the logits");
    for mode in [LoraMode::Merge, LoraMode::Branch] {
        let opts = CompileOptions { lora: mode, ..Default::default() };
        let (plan, warnings) =
            backend::compile_variants(&module, &weights, "seeded.safetensors", std::slice::from_ref(&source), &opts)
                .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
        // The variant gives only its LoRA matrices: the tuned norms and head, and the LoRA
        // of the other layers, keep the base value (zero for LoRA), in one warning.
        let text = sources.render_all(&warnings, false);
        assert_eq!(warnings.0.len(), 1, "{text}");
        let given = 2 * got_layers.len();
        assert!(text.contains(&format!("{key} gives {given} of ")) && text.contains("keeps the base value"), "{text}");
        let fused = plan.manifest.steps.iter().filter(|s| s.kernel.lora().is_some()).count();
        assert_eq!(fused, if mode == LoraMode::Branch { got_layers.len() } else { 0 }, "LoRA {}", mode.name());
        let plan = Arc::new(plan);
        for threads in [1, 2] {
            let mut session = Session::new(plan.clone(), threads).expect("session");
            let mut run = |variant: &str| {
                session.set_variant(variant).expect("a known variant");
                let outs = session.run(&[Input { name: "image", data: &image.1, shape: &image.0 }]).expect("run");
                let [(oname, got)] = &outs[..] else { panic!("{name}: one output expected") };
                assert_eq!(oname, "logits");
                assert_eq!(&got.shape, logits_shape);
                got.data.clone()
            };
            let at = format!("LoRA {} at {threads} thread(s)", mode.name());
            let base = run("base");
            let err = max_abs_error(&base, base_want);
            assert!(err <= 1e-4, "{name} base: logits differ from torchvision by {err:e}, {at}");
            let got = run(&key);
            let err = max_abs_error(&got, variant_want);
            eprintln!("{name} {key}: logits max abs error vs PEFT (merged) {err:e}, {at}");
            assert!(err <= 1e-4, "{name} {key}: logits differ from PEFT by {err:e}, {at}");
            let again = run("base");
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&again), bits(&base), "{name}: base after {key} is not the base, {at}");
        }
    }
}

/// PEFT's LoRA on vit_b_16's `self_attention.out_proj`, `mlp.0` and `mlp.3` of encoder
/// layers 0 and 11.
#[test]
fn vit_b_16_peft_lora_matches_peft() {
    let layers = ["encoder.layers.encoder_layer_0", "encoder.layers.encoder_layer_11"];
    check_peft("vit_b_16", &layers, &["self_attention.out_proj", "mlp.0", "mlp.3"]);
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

#[test]
fn swin_t_state_dict_matches_torchvision() {
    check_table("swin_t");
}

/// At 56x56, batch 2: the first stage's 14x14 map rolls and masks its shifted blocks, the
/// second's 7x7 is one window (no shift), the last two are padded up to a window, and the
/// second PatchMerging pads 7x7 to 8x8. Swin's int64 `relative_position_index` is
/// torchvision's, bound from the checkpoint.
#[test]
fn swin_t_matches_torchvision() {
    check_parity("swin_t");
}

/// Swin's relative position bias (its table at the int64 index, permuted) and the
/// shifted-window mask cost nothing at run time.
#[test]
fn swin_t_folds_its_position_bias_and_mask() {
    let attn = "features.1.1.attn";
    check_folded(
        "swin_t",
        &[&format!("{attn}.relative_position_bias_table"), &format!("{attn}.relative_position_index")],
    );
}

/// PEFT's LoRA on swin_t's fused `attn.qkv` and `attn.proj` of a shifted block of the first
/// stage and a block of the last.
#[test]
fn swin_t_peft_lora_matches_peft() {
    check_peft("swin_t", &["features.1.1", "features.7.0"], &["attn.qkv", "attn.proj"]);
}
