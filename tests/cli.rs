//! The `readi` binary: exit codes, outputs and help, run as a user would.

mod common;

use std::process::{Command, Output};

use common::readi;

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn check_accepts_every_bundled_model() {
    let o = readi(&[
        "check",
        "models/resnet18.readi",
        "models/vit_encoder.readi",
        "models/pointpillars_bev.readi",
        "models/bevfusion_tiny.readi",
        "models/resnet50.readi",
        "models/mobilenet_v2.readi",
        "models/mobilenet_v3_large.readi",
        "models/efficientnet_b0.readi",
        "models/convnext_tiny.readi",
        "models/vit_b_16.readi",
        "models/regnet_y_400mf.readi",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stdout(&o).lines().filter(|l| l.starts_with("ok  ")).count(), 11, "{}", stdout(&o));
}

#[test]
fn check_fails_with_located_diagnostics() {
    let o = readi(&["check", "tests/cases/errors/syntax_missing_comma.readi"]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("tests/cases/errors/syntax_missing_comma.readi:4:23"), "{err}");
    assert!(err.contains("expected `)`, `,` or an operator, found `kernel`"), "{err}");
    assert!(err.contains("^^^^^^"), "{err}");
}

#[test]
fn check_reports_every_file_and_fails_if_any_fails() {
    let o = readi(&["check", "models/resnet18.readi", "tests/cases/errors/unknown_name.readi"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stdout(&o).contains("ok  models/resnet18.readi"), "{}", stdout(&o));
    assert!(stderr(&o).contains("unknown name `cnv1`"), "{}", stderr(&o));
}

#[test]
fn missing_file_is_a_clear_error() {
    let o = readi(&["check", "no/such/file.readi"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("cannot read no/such/file.readi"), "{}", stderr(&o));
}

#[test]
fn params_prints_the_table_and_total() {
    let o = readi(&["params", "models/resnet18.readi"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("layer2.0.downsample.0.weight"), "{out}");
    assert!(out.contains("total: 11,689,512 parameters"), "{out}");
    let o = readi(&["params", "models/resnet18.readi", "--set", "num_classes=10"]);
    assert!(stdout(&o).contains("total: 11,181,642 parameters"), "{}", stdout(&o));
    let o = readi(&["params", "models/resnet18.readi", "--buffers"]);
    assert!(stdout(&o).contains("layer1.0.bn2.running_var"), "{}", stdout(&o));
}

#[test]
fn unknown_model_parameter_is_reported() {
    let o = readi(&["params", "models/resnet18.readi", "--set", "num_clases=10"]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("has no parameter `num_clases`") && err.contains("did you mean `num_classes`?"), "{err}");
}

#[test]
fn ir_stops_after_a_pass() {
    let o = readi(&["ir", "models/resnet18.readi", "--stop-after", "elaborate"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.starts_with("model resnet18(num_classes = 1000, img = 224)"), "{out}");
    assert!(!out.contains("\nadapt\n"), "the adapt plan comes from a later pass:\n{out}");
    let full = stdout(&readi(&["ir", "models/resnet18.readi"]));
    assert!(full.contains("\nadapt\n") && full.contains("\nvariants\n"), "{full}");
    let bad = readi(&["ir", "models/resnet18.readi", "--stop-after", "elaborat"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(stderr(&bad).contains("passes: parse, elaborate"), "{}", stderr(&bad));
}

#[test]
fn graph_writes_dot() {
    let dir = common::Scratch::new("cli");
    let path = dir.join("r18.dot");
    let o = readi(&["graph", "models/resnet18.readi", "-o", path.to_str().expect("utf-8 path")]);
    assert!(o.status.success(), "{}", stderr(&o));
    let dot = std::fs::read_to_string(&path).expect("dot written");
    assert!(dot.starts_with("digraph \"resnet18\""), "{dot}");
    assert!(dot.contains("subgraph cluster_"), "block instances are clusters");
    assert_eq!(dot.matches('{').count(), dot.matches('}').count(), "balanced braces");
}

#[test]
fn ast_prints_canonical_source() {
    let o = readi(&["ast", "models/vit_encoder.readi"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("block EncoderBlock(x: tensor, width: int, heads: int, mlp_ratio: int = 4) {"), "{out}");
    assert!(out.contains("lora rank=4 alpha=8 on blocks.*.{q,k,v,proj}"), "{out}");
}

#[test]
fn help_shows_examples() {
    let o = readi(&["--help"]);
    assert!(o.status.success());
    let out = stdout(&o);
    assert!(out.contains("Examples:") && out.contains("readi check models/*.readi"), "{out}");
    let o = readi(&["check", "--help"]);
    assert!(stdout(&o).contains("Example:"), "{}", stdout(&o));
}

#[test]
fn passes_lists_the_pipeline_in_order() {
    let out = stdout(&readi(&["passes"]));
    let names: Vec<&str> = out.lines().filter_map(|l| l.split_whitespace().next()).collect();
    let front = ["parse", "elaborate", "dead_code", "resolve_adapt", "inject_adapt", "check_variants"];
    let back = [
        "bind_weights",
        "bind_variants",
        "meld",
        "prune",
        "fold_constants",
        "drop_inactive",
        "choose_strategy",
        "commute_adapters",
        "merge_lora",
        "fuse_lora",
        "fold_batchnorm",
        "fuse_adapters",
        "fuse_epilogues",
        "choose_conv_algo",
        "pack_weights",
        "lower",
        "plan_buffers",
    ];
    assert_eq!(names, [&front[..], &back[..]].concat());
}

#[test]
fn demo_runs_on_the_embedded_model() {
    let o = Command::new(env!("CARGO_BIN_EXE_readi"))
        .arg("demo")
        .current_dir(std::env::temp_dir())
        .output()
        .expect("run readi demo");
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("bevfusion_tiny"), "{out}");
    assert!(out.contains("exist budget") && out.contains("add budget"), "{out}");
}

/// The BEVFusion demo's drive: the simulated weather and exposure, read back from the
/// sensor data and metadata by the spec's selectors, pick each frame's intended variant
/// (the meld for fog at dusk, missing=lidar without points) and the detector decodes boxes.
#[test]
fn the_bevfusion_demo_picks_each_conditions_variant() {
    let o = Command::new(env!("CARGO_BIN_EXE_readi"))
        .args(["demo", "--model", "bevfusion", "--threads", "2"])
        .current_dir(std::env::temp_dir())
        .output()
        .expect("run readi demo");
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    // The frame lines: `  <frame> <conditions> <points> <variant> ...`.
    let frame = |what: &str| {
        let mut frames =
            out.lines().filter(|l| l.trim_start().starts_with(|c: char| c.is_ascii_digit()) && l.contains(" us "));
        frames.find(|l| l.contains(what)).unwrap_or_else(|| panic!("no {what}: {out}"))
    };
    for (what, key) in [
        ("clear ", " base "),
        ("fog rising", " fog=0.03 "),
        ("dusk in dense fog", " fog=0.06+gamma=0.5 "),
        ("snow", " snow=1.5 "),
        ("tunnel: dark", " gamma=0.25 "),
        ("lidar lost", " missing=lidar "),
        ("cameras lost", " base "),
    ] {
        let line = frame(what);
        assert!(line.contains(key), "{what}: {line}");
        assert!(line.contains(" m, yaw "), "{what}: no box: {line}");
    }
    assert!(!out.contains("ignored"), "a selection the demo's plan cannot serve: {out}");
}

/// BEVFusion from files as a user runs it: the fixture sweep as a `.bin` through `readi
/// simulate --fog`, the views and calibration from a safetensors file, the fog variant
/// chosen from the metadata, the boxes printed and written as JSON.
#[test]
fn a_simulated_sweep_feeds_bevfusion_and_boxes_come_out() {
    let dir = common::Scratch::new("cli-bevfusion");
    let p = |name: &str| dir.join(name).to_str().expect("utf-8").to_string();
    let fixtures = common::root().join("tests/fixtures/bevfusion");
    let io = std::fs::read(fixtures.join("full.io.safetensors")).expect("fixture");
    let io = readi_compiler::backend::WeightSet::from_safetensors("full.io", &io).expect("fixture");
    let mut inputs = readi_compiler::backend::WeightSet::default();
    for (name, t) in &io.tensors {
        match name.strip_prefix("input.") {
            Some("points") => {
                let bytes: Vec<u8> = t.1.iter().flat_map(|v| v.to_le_bytes()).collect();
                std::fs::write(p("sweep.bin"), bytes).expect("write sweep");
            }
            Some(input) => {
                inputs.tensors.insert(input.to_string(), t.clone());
            }
            None => {}
        }
    }
    std::fs::write(p("inputs.safetensors"), inputs.to_safetensors().expect("serialises")).expect("write inputs");

    let weights = fixtures.join("full.weights.safetensors");
    let mut compile: Vec<String> =
        ["compile", "models/bevfusion.readi", "--weights", weights.to_str().expect("utf-8")].map(String::from).to_vec();
    compile.extend(["--seeded-variant", "fog=0.06", "-o", &p("bf.plan")].map(String::from));
    for (k, v) in common::BEVFUSION_SMALL {
        compile.extend(["--set".to_string(), format!("{k}={v}")]);
    }
    let o = readi(&compile.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", stderr(&o));
    let o = readi(&["simulate", &p("sweep.bin"), "--columns", "5", "--fog", "0.06", "-o", &p("fog.bin")]);
    assert!(o.status.success(), "{}", stderr(&o));

    let mut run = vec!["run".to_string(), p("bf.plan"), "--input".into(), format!("points={}", p("fog.bin"))];
    for name in ["camera", "camera_intrinsics", "camera2lidar", "img_aug_matrix", "lidar_aug_matrix"] {
        run.extend(["--input".to_string(), format!("{name}={}", p("inputs.safetensors"))]);
    }
    run.extend(["--auto", "--meta", "fog_density=0.06", "--output", &p("out.json")].map(String::from));
    let o = readi(&run.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("selected variant fog=0.06"), "{out}");
    assert!(out.contains("sample 0: ") && out.contains(" of 12 boxes kept") && out.contains("label  score"), "{out}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out.json")).expect("json")).expect("valid JSON");
    assert_eq!(json["boxes"]["shape"], serde_json::json!([1, 12, 9]), "{json}");
    assert_eq!(json["labels"]["dtype"], "i64");
}

/// Writes seeded weights for a spec to a temp safetensors file; returns (dir, weights path).
fn seeded_weights_file(spec: &str, overrides: &[(&str, &str)], tag: &str) -> (common::Scratch, std::path::PathBuf) {
    let module = common::compile(spec, overrides, None).1.module.expect("module");
    let dir = common::Scratch::new(&format!("cli-{tag}"));
    let path = dir.join("weights.safetensors");
    let bytes = readi_compiler::backend::seeded_weights(&module.graph, 11).to_safetensors().expect("serialises");
    std::fs::write(&path, bytes).expect("write weights");
    (dir, path)
}

#[test]
fn compile_run_bench_inspect() {
    let (dir, weights) = seeded_weights_file("models/resnet18.readi", &[("num_classes", "10"), ("img", "32")], "r18");
    let plan = dir.join("r18.plan");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let o = readi(&[
        "compile",
        "models/resnet18.readi",
        "--weights",
        &p(&weights),
        "-o",
        &p(&plan),
        "--set",
        "num_classes=10",
        "--set",
        "img=32",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("steps"), "{}", stdout(&o));

    let o = readi(&["inspect", &p(&plan)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("checksum ok") && out.contains("image: f32[N, 3, 32, 32] @camera"), "{out}");
    assert!(out.contains("parameters: 11,181,642"), "{out}");

    // An input as .npy, outputs as .npy and as .safetensors.
    let input = dir.join("image.npy");
    let t = readi_runtime::exec::Tensor { shape: vec![2, 3, 32, 32], data: vec![0.1; 2 * 3 * 32 * 32] };
    write_npy(&input, &t);
    let logits = dir.join("logits.npy");
    let all = dir.join("out.safetensors");
    let o = readi(&[
        "run",
        &p(&plan),
        "--input",
        &format!("image={}", p(&input)),
        "--output",
        &p(&logits),
        "--output",
        &p(&all),
        "--threads",
        "2",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("logits: [2, 10]"), "{}", stdout(&o));
    assert!(logits.exists() && all.exists());

    let o = readi(&["run", &p(&plan), "--input", &format!("img={}", p(&input))]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("no input `img`"), "{}", stderr(&o));

    let o = readi(&["bench", &p(&plan), "--runs", "3", "--warmup", "1", "--threads", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("median") && stdout(&o).contains("p90"), "{}", stdout(&o));
    // The work of a run, by hand from torchvision's ResNet-18 at 32x32 (multiply-adds:
    // output elements x products each): conv1 7x7 3->64 to 16x16; after the max pool,
    // layer1's four 3x3 64->64 convs at 8x8; layers 2 to 4 each a strided 3x3 conv, three
    // 3x3 convs and a 1x1 downsample, at 4x4, 2x2 and 1x1; fc 512->10.
    let conv1 = 64 * 16 * 16 * 3 * 49;
    let layer1 = 4 * 64 * 8 * 8 * 64 * 9;
    let stage = |c: u64, hw: u64| c * hw * (c / 2) * 9 + 3 * c * hw * c * 9 + c * hw * (c / 2);
    let want: u64 = conv1 + layer1 + stage(128, 16) + stage(256, 4) + stage(512, 1) + 512 * 10;
    let line = format!("work: {} multiply-adds a run", readi_compiler::print::thousands(want));
    assert!(stdout(&o).contains(&line), "want `{line}`:\n{}", stdout(&o));
    assert_eq!(stdout(&o).contains("peak resident memory: "), cfg!(target_os = "linux"), "{}", stdout(&o));

    // A corrupted plan is refused by every command that reads plans.
    let mut bytes = std::fs::read(&plan).expect("plan");
    let n = bytes.len();
    bytes[n - 10] ^= 0x40;
    let bad = dir.join("bad.plan");
    std::fs::write(&bad, bytes).expect("write");
    let o = readi(&["inspect", &p(&bad)]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("checksum mismatch"), "{}", stderr(&o));
}

#[test]
fn compile_reports_weight_errors_against_the_spec() {
    let (dir, _) = seeded_weights_file("models/resnet18.readi", &[], "bad");
    let plan = dir.join("x.plan");
    // Weights for 1000 classes, spec compiled for 10.
    let (_weights_dir, weights) = seeded_weights_file("models/resnet18.readi", &[], "bad1000");
    let o = readi(&[
        "compile",
        "models/resnet18.readi",
        "--weights",
        weights.to_str().expect("utf-8"),
        "-o",
        plan.to_str().expect("utf-8"),
        "--set",
        "num_classes=10",
    ]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("tensor `fc.weight`") && err.contains("models/resnet18.readi:45:"), "{err}");
    assert!(!plan.exists(), "no plan is written on error");
}

fn write_npy(path: &std::path::Path, t: &readi_runtime::exec::Tensor) {
    use ndarray_npy::WriteNpyExt;
    let a = ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&t.shape), t.data.clone()).expect("shape");
    a.write_npy(std::fs::File::create(path).expect("create")).expect("write npy");
}

/// A deployment manifest with a parameter file and a PEFT adapter per variant; `inspect`
/// prints the budget table; `--variant` selects a variant at run time.
#[test]
fn compile_a_deployment_with_variants() {
    use readi_compiler::backend::{WeightSet, seeded_tensor, variants::owned_params};
    let overrides = [("num_classes", "10"), ("img", "64")];
    let (dir, weights) = seeded_weights_file("models/resnet18.readi", &overrides, "deploy");
    let root = common::root();
    let module = common::compile("models/resnet18.readi", &overrides, None).1.module.expect("module");
    // The tuned and adapter tensors; the LoRA matrices come from the PEFT directory.
    let mut params = WeightSet::default();
    for (name, o) in owned_params(&module) {
        if !name.contains(".lora_") {
            params.tensors.insert(name.clone(), (o.shape.clone(), seeded_tensor(5, &name, &o.shape)));
        }
    }
    std::fs::write(dir.join("g025.safetensors"), params.to_safetensors().expect("serialises")).expect("write");
    let peft = root.join("tests/fixtures/variants/resnet18/gamma=0.25");
    let yaml = format!(
        "spec: {}\nset: {{num_classes: 10, img: 64}}\nweights: {}\nvariants:\n  - key: gamma=0.25\n    params: g025.safetensors\n    peft: {}\n  - key: blur=5\n    peft: {}\n",
        root.join("models/resnet18.readi").display(),
        weights.display(),
        peft.display(),
        root.join("tests/fixtures/variants/resnet18/blur=5").display(),
    );
    let manifest = dir.join("deploy.yaml");
    std::fs::write(&manifest, yaml).expect("write yaml");
    let plan = dir.join("r18v.plan");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let o = readi(&["compile", "--deploy", &p(&manifest), "-o", &p(&plan)]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("2 variants (LoRA merge)"), "{}", stdout(&o));
    // blur=5 gives only its LoRA: the rest keeps the base value, reported.
    assert!(
        stderr(&o).contains("1 variant gives part of what it owns") && stderr(&o).contains("blur=5 gives"),
        "{}",
        stderr(&o)
    );
    // The same from the command line; the PEFT directory's name holds `=` itself.
    let o = readi(&[
        "compile",
        "models/resnet18.readi",
        "--weights",
        &p(&weights),
        "--set",
        "num_classes=10",
        "--set",
        "img=64",
        "--variant",
        &format!("gamma=0.25={}", p(&dir.join("g025.safetensors"))),
        "--variant",
        &format!("gamma=0.25={}", p(&peft)),
        "-o",
        &p(&plan),
        "--strict",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("1 variant (LoRA merge)"), "{}", stdout(&o));
    let o = readi(&["compile", "--deploy", &p(&manifest), "-o", &p(&plan), "--strict"]);
    assert_eq!(o.status.code(), Some(1), "--strict refuses the fallback");

    let o = readi(&["compile", "--deploy", &p(&manifest), "-o", &p(&plan), "--lora", "branch"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = readi(&["inspect", &p(&plan)]);
    let out = stdout(&o);
    assert!(out.contains("exist budget") && out.contains("add budget"), "{out}");
    let row = out.lines().find(|l| l.trim_start().starts_with("gamma=0.25")).expect("a row per variant");
    assert!(row.contains('%'), "{row}");

    let o = readi(&["bench", &p(&plan), "--runs", "1", "--warmup", "0", "--variant", "gamma=0.25"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("(gamma=0.25)"), "{}", stdout(&o));
    let o = readi(&["bench", &p(&plan), "--runs", "1", "--variant", "gamma=0.3"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("gamma=0.25"), "lists the keys: {}", stderr(&o));
    // Switching: the switch alone there and back 2000 times per key, then one timed
    // switch per run; an unknown key fails before anything runs.
    let o =
        readi(&["bench", &p(&plan), "--runs", "2", "--warmup", "0", "--variant", "gamma=0.25", "--switch", "blur=5"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("switch gamma=0.25 <-> blur=5: 4000 switches: p50"), "{out}");
    assert!(out.contains("first run after a switch, against the steady run after it (2 switches)"), "{out}");
    let o = readi(&["bench", &p(&plan), "--runs", "1", "--switch", "blur=6"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("blur=6") && !stdout(&o).contains("median"), "{}", stderr(&o));
    // A variant against the base in alternating rounds; an unknown key fails before any run.
    let o = readi(&["bench", &p(&plan), "--runs", "3", "--variant", "gamma=0.25", "--against", "base"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let line = out
        .lines()
        .find(|l| l.starts_with("gamma=0.25 against base, 3 alternating rounds: median "))
        .unwrap_or_else(|| panic!("{out}"));
    let ratio: f64 = line
        .split("ratio ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|r| r.parse().ok())
        .unwrap_or_else(|| panic!("{line}"));
    assert!(ratio > 0.0 && ratio.is_finite(), "{line}");
    let o = readi(&["bench", &p(&plan), "--runs", "1", "--against", "blur=6"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("blur=6") && !stdout(&o).contains("median"), "{}", stderr(&o));

    // --auto: a dark, textured image selects gamma=0.25 by its brightness; a dark flat one
    // also reads as blurred, and two camera conditions without a meld rule are an error.
    let (n, h, w) = (2, 64, 64);
    let textured: Vec<f32> =
        (0..n * 3 * h * w).map(|i| 0.1 + if (i / w + i % w) % 2 == 0 { 0.05 } else { -0.05 }).collect();
    let image = dir.join("dark.npy");
    write_npy(&image, &readi_runtime::exec::Tensor { shape: vec![n, 3, h, w], data: textured });
    let o = readi(&["run", &p(&plan), "--auto", "--input", &format!("image={}", p(&image))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("selected variant gamma=0.25") && out.contains("brightness(image) = 0.1000"), "{out}");
    assert!(out.contains("ran variant gamma=0.25"), "{out}");
    write_npy(&image, &readi_runtime::exec::Tensor { shape: vec![n, 3, h, w], data: vec![0.1; n * 3 * h * w] });
    let o = readi(&["run", &p(&plan), "--auto", "--input", &format!("image={}", p(&image))]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("no meld rule"), "{}", stderr(&o));

    // A key the spec does not declare.
    std::fs::write(&manifest, std::fs::read_to_string(&manifest).expect("yaml").replace("key: blur=5", "key: blur=7"))
        .expect("write");
    let o = readi(&["compile", "--deploy", &p(&manifest), "-o", &p(&plan)]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("`blur=7` is not declared"), "{}", stderr(&o));
}

/// A model with a fog axis at 0.01, a camera axis and a meld rule, for the key tests.
const KEYS_SPEC: &str = "\
model keys {
  input image: f32[N, 3, 8, 8] @camera
  input points: f32[N, 3, 8, 8] @lidar
  cam = conv2d(image, 4, kernel=3, padding=1, bias=false)
  bn1 = batchnorm(cam)
  lid = conv2d(points, 4, kernel=3, padding=1, bias=false)
  bn2 = batchnorm(lid)
  head {
    fc = linear(flatten(global_avgpool(relu(bn1 + bn2)), start=1), 3)
  }
  output y = head.fc
}
adapt {
  tune batchnorm, head.*
}
variants {
  axis fog on lidar: 0.01, 0.03 clear 0
  axis gamma on camera: 0.25, 4 clear 1
  meld camera = 0.8, lidar = 0.2
}
";

/// `run`, `bench` and `adapt-bn` read `--variant` as a key, as `compile` does: `fog=0.010`
/// names `fog=0.01`, and a meld's parts may come in any order.
#[test]
fn variant_keys_are_read_by_meaning_by_every_command() {
    use readi_compiler::backend::{WeightSet, seeded_tensor, variants::owned_params};
    let dir = common::Scratch::new("cli-keys");
    let spec = dir.join("keys.readi");
    std::fs::write(&spec, KEYS_SPEC).expect("write spec");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let (_weights_dir, weights) = seeded_weights_file(&p(&spec), &[], "keys");
    let module = common::compile(&p(&spec), &[], None).1.module.expect("module");
    let mut args = vec!["compile".to_string(), p(&spec), "--weights".into(), p(&weights)];
    for (seed, key) in [(5, "fog=0.01"), (6, "gamma=0.25")] {
        let mut params = WeightSet::default();
        for (name, o) in owned_params(&module) {
            params.tensors.insert(name.clone(), (o.shape.clone(), seeded_tensor(seed, &name, &o.shape)));
        }
        let file = dir.join(format!("{key}.safetensors"));
        std::fs::write(&file, params.to_safetensors().expect("serialises")).expect("write");
        args.extend(["--variant".into(), format!("{key}={}", p(&file))]);
    }
    let plan = dir.join("keys.plan");
    args.extend(["--meld".into(), "fog=0.01+gamma=0.25".into(), "-o".into(), p(&plan)]);
    let o = readi(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", stderr(&o));
    // Both parts give every owned tensor: every layer is interpolated.
    assert!(
        stdout(&o).contains("variant `fog=0.01+gamma=0.25`: meld of fog=0.01 and gamma=0.25 (0 layers taken whole"),
        "{}",
        stdout(&o)
    );

    let (image, points) = (dir.join("image.npy"), dir.join("points.npy"));
    let shape = vec![2, 3, 8, 8];
    let values = |seed: usize| (0..2 * 3 * 64).map(|i| ((i * 37 + seed) % 101) as f32 / 101.0).collect();
    write_npy(&image, &readi_runtime::exec::Tensor { shape: shape.clone(), data: values(1) });
    write_npy(&points, &readi_runtime::exec::Tensor { shape: shape.clone(), data: values(2) });
    let (image_arg, points_arg) = (format!("image={}", p(&image)), format!("points={}", p(&points)));
    let plan_s = p(&plan);
    // Runs `--variant key` (the base without); returns stdout and the output's bytes.
    let run = |key: Option<&str>| {
        let out = dir.join("y.npy");
        let mut args = vec!["run", &plan_s, "--input", &image_arg, "--input", &points_arg];
        let out_s = p(&out);
        args.extend(["--output", &out_s]);
        if let Some(key) = key {
            args.extend(["--variant", key]);
        }
        let o = readi(&args);
        assert!(o.status.success(), "--variant {key:?}: {}", stderr(&o));
        (stdout(&o), std::fs::read(&out).expect("output written"))
    };
    let (_, base) = run(None);
    let (out, fog) = run(Some("fog=0.01"));
    assert!(out.contains("ran variant fog=0.01 "), "{out}");
    assert_ne!(fog, base, "the variant's tensors change the output");
    let (out, fog_long) = run(Some("fog=0.010"));
    assert!(out.contains("ran variant fog=0.01 "), "{out}");
    assert_eq!(fog_long, fog, "fog=0.010 is fog=0.01");
    let (out, meld) = run(Some("fog=0.01+gamma=0.25"));
    assert!(out.contains("ran variant fog=0.01+gamma=0.25 "), "{out}");
    assert_ne!(meld, fog);
    let (out, meld_swapped) = run(Some("gamma=0.250+fog=0.01"));
    assert!(out.contains("ran variant fog=0.01+gamma=0.25 "), "{out}");
    assert_eq!(meld_swapped, meld, "a meld's parts in either order name one variant");

    let o = readi(&["bench", &plan_s, "--runs", "1", "--warmup", "0", "--variant", "gamma=0.25+fog=0.010"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("(fog=0.01+gamma=0.25)"), "{}", stdout(&o));
    // Text that is not a key says why; a key the plan lacks names the nearest it has.
    let o = readi(&["run", &plan_s, "--input", &image_arg, "--input", &points_arg, "--variant", "fog=0.01+fog=0.03"]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(
        err.contains("`fog=0.01+fog=0.03` is not a variant key: `fog=0.01` and `fog=0.03` are on the same axis"),
        "{err}"
    );
    let o = readi(&["bench", &plan_s, "--runs", "1", "--variant", "gamma=0.25+fog=0.030"]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("no variant `gamma=0.25+fog=0.030`; did you mean `fog=0.01+gamma=0.25`?"), "{err}");

    // adapt-bn writes statistics under the canonical key of a meld given in any order.
    let mut sample = WeightSet::default();
    sample.tensors.insert("image".into(), (shape.clone(), values(3)));
    sample.tensors.insert("points".into(), (shape.clone(), values(4)));
    let sample_path = dir.join("sample.safetensors");
    std::fs::write(&sample_path, sample.to_safetensors().expect("serialises")).expect("write");
    let stats = dir.join("stats.safetensors");
    let o = readi(&[
        "adapt-bn",
        &plan_s,
        "--variant",
        "gamma=0.250+fog=0.010",
        "--samples",
        &p(&sample_path),
        "-o",
        &p(&stats),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("for variant `fog=0.01+gamma=0.25`"), "{}", stdout(&o));
    let o = readi(&["adapt-bn", &plan_s, "--variant", "fog=0.02", "--samples", &p(&sample_path), "-o", &p(&stats)]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("declares no variant `fog=0.02`"), "{}", stderr(&o));
    // The calibrator binds each batch under --max-memory: a limit the sample file fits but
    // the run's buffers do not is refused before they are allocated, naming the sample.
    let limit = (std::fs::metadata(&sample_path).expect("sample").len() + 64).to_string();
    let o = readi(&[
        "adapt-bn",
        &plan_s,
        "--variant",
        "fog=0.01",
        "--samples",
        &p(&sample_path),
        "-o",
        &p(&stats),
        "--max-memory",
        &limit,
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("sample.safetensors: the plan needs") && err.contains("over the limit of"), "{err}");
}

#[test]
fn ir_reaches_every_back_end_pass() {
    // After fold_batchnorm each BatchNorm of ResNet-18 is in its conv's epilogue.
    let o = readi(&["ir", "models/resnet18.readi", "--stop-after", "fold_batchnorm"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("conv1 (+bn1) = conv2d") && !out.contains("= batchnorm("), "{out}");
    assert!(stderr(&o).contains("seeded weights"), "{}", stderr(&o));
    // From lower on, the schedule, as readi inspect lists it.
    let o = readi(&["ir", "models/resnet18.readi", "--stop-after", "plan_buffers"]);
    let out = stdout(&o);
    assert!(out.starts_with("schedule: 24 steps") && out.contains("conv1 (+bn1, relu#0)"), "{out}");
    // Each block's residual add and ReLU run in its second conv's epilogue.
    assert!(
        out.contains("= conv2d[winograd4 scale shift +residual relu](%3, %2)")
            && out.contains("layer1.0.conv2 (+layer1.0.bn2, layer1.0.add#0, layer1.0.relu#1)")
            && !out.contains("= binary("),
        "{out}"
    );
    assert!(out.contains("buffers: 3 slots"), "{out}");
    // With seeded variants, the variant tables.
    let o = readi(&[
        "ir",
        "tests/cases/ok/adapt_and_variants.readi",
        "--stop-after",
        "lower",
        "--seeded-variant",
        "fog=0.030",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("variant fog=0.03: replaces"), "{}", stdout(&o));
    // A schedule is not a graph.
    let o = readi(&["graph", "models/resnet18.readi", "--stop-after", "lower"]);
    assert!(!o.status.success() && stderr(&o).contains("not a graph"), "{}", stderr(&o));
}

/// `readi compile` of a spec with a `prune` rule prints what it zeroed and how far the
/// outputs move; `--verbose` adds the table of layers.
#[test]
fn compile_reports_pruning() {
    let dir = common::Scratch::new("cli-prune");
    let text = std::fs::read_to_string("models/resnet18.readi").expect("read the spec");
    let spec = dir.join("r18p.readi");
    std::fs::write(&spec, text.replacen("adapt {", "adapt {\n  prune below=1e-3", 1)).expect("write spec");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let overrides = [("num_classes", "10"), ("img", "32")];
    let (_weights_dir, weights) = seeded_weights_file(&p(&spec), &overrides, "prune");
    let plan = dir.join("p.plan");
    let args = ["compile", &p(&spec), "--weights", &p(&weights), "-o", &p(&plan), "--set", "num_classes=10"];
    let o = readi(&[&args[..], &["--set", "img=32", "--verbose"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let line = out.lines().find(|l| l.starts_with("pruned ")).unwrap_or_else(|| panic!("no summary: {out}"));
    assert!(line.contains("shared weights") && line.contains("below 1e-3 in 20 layers"), "{line}");
    assert!(line.contains("outputs differ by at most"), "{line}");
    assert!(out.contains("layer4.1.conv2") && out.contains("output `logits`: max abs difference"), "{out}");
    // Without the rule, no summary.
    let o = readi(&[
        "compile",
        "models/resnet18.readi",
        "--weights",
        &p(&weights),
        "-o",
        &p(&plan),
        "--set",
        "num_classes=10",
        "--set",
        "img=32",
    ]);
    assert!(o.status.success() && !stdout(&o).contains("pruned"), "{}", stdout(&o));
}

/// Weights saved from a training wrapper (`module.` before every name) get one error that
/// names the prefix and the flag, not one per tensor; `--strip-prefix` then binds them
/// exactly as the plain file.
#[test]
fn a_common_name_prefix_is_named_and_stripped() {
    use readi_compiler::backend::WeightSet;
    let set = [("num_classes", "10"), ("img", "32")];
    let (dir, plain) = seeded_weights_file("models/resnet18.readi", &set, "prefix");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let base = WeightSet::from_safetensors("plain", &std::fs::read(&plain).expect("read")).expect("parses");
    let wrapped = WeightSet {
        tensors: base.tensors.iter().map(|(k, v)| (format!("module.{k}"), v.clone())).collect(),
        ..WeightSet::default()
    };
    let prefixed = dir.join("wrapped.safetensors");
    std::fs::write(&prefixed, wrapped.to_safetensors().expect("serialises")).expect("write");
    let compile = |weights: &std::path::Path, plan: &str, extra: &[&str]| {
        let mut args = vec!["compile", "models/resnet18.readi", "--set", "num_classes=10", "--set", "img=32"];
        let (w, o) = (p(weights), p(&dir.join(plan)));
        args.extend(["--weights", &w, "-o", &o]);
        args.extend(extra);
        readi(&args)
    };

    let o = compile(&prefixed, "x.plan", &[]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("--strip-prefix module."), "{err}");
    assert_eq!(err.matches("error[").count(), 1, "one error for the whole file:\n{err}");

    let o = compile(&prefixed, "stripped.plan", &["--strip-prefix", "module."]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = compile(&plain, "plain.plan", &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let tensors = |plan: &str| {
        let plan = readi_runtime::plan::Plan::load(&dir.join(plan)).expect("loads");
        (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect::<Vec<_>>()
    };
    assert!(tensors("stripped.plan") == tensors("plain.plan"), "stripped weights bind as the plain file's");

    let o = compile(&prefixed, "y.plan", &["--strip-prefix", "model."]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("no tensor in") && stderr(&o).contains("`model.`"), "{}", stderr(&o));
}

/// A deployment file holds only the adaptation and the conditions for a model written
/// elsewhere: `use` brings the model, and the file's own `adapt` and `variants` replace
/// the model file's. A `use` of a file that is not there is an error at its line.
#[test]
fn a_deployment_file_uses_a_model_file() {
    let dir = common::Scratch::new("cli-use");
    let model = common::root().join("models/resnet18.readi");
    let deploy = dir.join("deploy.readi");
    let text = format!(
        "use \"{}\"\nadapt {{\n  tune fc\n}}\nvariants {{\n  axis fog on camera: 0.01, 0.02 clear 0\n}}\n",
        model.display()
    );
    std::fs::write(&deploy, text).expect("write");
    let o = readi(&["params", deploy.to_str().expect("utf-8"), "--set", "img=32"]);
    assert!(o.status.success(), "{}", stderr(&o));
    // The variants own what this file's adapt section says: fc only (512 * 1000 + 1000).
    let out = stdout(&o);
    assert!(out.contains("11,689,512"), "{out}");
    assert!(out.contains("513,000 existing elements tuned"), "the deployment's rule decides what variants own:\n{out}");
    // The model file's own section adds LoRA and adapters (702,272 elements); replaced.
    assert!(out.contains(", 0 added"), "the model file's adapt section is replaced:\n{out}");

    let bad = dir.join("bad.readi");
    std::fs::write(&bad, "# a deployment\nuse \"missing.readi\"\n").expect("write");
    let o = readi(&["check", bad.to_str().expect("utf-8")]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("E0104") && err.contains("bad.readi:2:1") && err.contains("missing.readi"), "{err}");
}

/// A model whose outputs are i64 (top-k indices) and bool (a mask): `readi run` prints
/// their values as integers and writes them as int64 and bool (`.npy`, `.safetensors`
/// and `.json`), not as floats; the JSON holds the bits of the `.safetensors` file's
/// floats (shortest round-trip form), NaN as null.
#[test]
fn integer_and_bool_outputs_are_printed_and_written_as_such() {
    let dir = common::Scratch::new("cli-int");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let spec = dir.join("top.readi");
    let text = "model top {\n  input x: f32[1, 5]\n  let t = topk(x, 3)\n  output idx = t[1]\n  output \
                pos = x > 0.0\n  output val = t[0]\n  output s = sigmoid(x) / 3.0\n  output l = log(x)\n}\n";
    std::fs::write(&spec, text).expect("write spec");
    let plan = dir.join("top.plan");
    // The model has no parameters: an empty weights file.
    let weights = dir.join("none.safetensors");
    let empty: Vec<(String, safetensors::tensor::TensorView<'_>)> = Vec::new();
    std::fs::write(&weights, safetensors::serialize(empty, None).expect("serialize")).expect("write weights");
    let o = readi(&["compile", &p(&spec), "--weights", &p(&weights), "-o", &p(&plan)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let input = dir.join("x.npy");
    write_npy(&input, &readi_runtime::exec::Tensor { shape: vec![1, 5], data: vec![0.5, -2.0, 3.0, 1.0, -0.25] });
    let (idx, all) = (dir.join("idx.npy"), dir.join("all.safetensors"));
    let (json, one) = (dir.join("all.json"), dir.join("s.json"));
    let o = readi(&[
        "run",
        &p(&plan),
        "--input",
        &format!("x={}", p(&input)),
        "--output",
        &format!("idx={}", p(&idx)),
        "--output",
        &p(&all),
        "--output",
        &p(&json),
        "--output",
        &format!("s={}", p(&one)),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("idx: [1, 3] i64  min 0  max 3  [2, 3, 0]"), "{out}");
    assert!(out.contains("pos: [1, 5] bool  3 true of 5"), "{out}");
    assert!(out.contains("val: [1, 3]  min 0.5000  max 3.0000"), "{out}");
    use ndarray_npy::ReadNpyExt;
    let a = ndarray::ArrayD::<i64>::read_npy(std::fs::File::open(&idx).expect("open")).expect("an int64 .npy");
    assert_eq!(a.iter().copied().collect::<Vec<_>>(), [2, 3, 0]);
    let bytes = std::fs::read(&all).expect("read");
    let st = safetensors::SafeTensors::deserialize(&bytes).expect("safetensors");
    use safetensors::tensor::Dtype;
    assert_eq!(st.tensor("idx").expect("idx").dtype(), Dtype::I64);
    assert_eq!(st.tensor("pos").expect("pos").data(), &[1u8, 0, 1, 1, 0]);
    assert_eq!(st.tensor("pos").expect("pos").dtype(), Dtype::BOOL);
    assert_eq!(st.tensor("val").expect("val").dtype(), Dtype::F32);

    // JSON: every output, as the .safetensors file has it.
    let read_json = |path: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(path).expect("read json")).expect("valid JSON")
    };
    let doc = read_json(&json);
    let outputs = doc.as_object().expect("an object");
    let text = std::fs::read_to_string(&json).expect("read json");
    let at: Vec<usize> = ["idx", "pos", "val", "s", "l"]
        .iter()
        .map(|n| text.find(&format!("\"{n}\":{{\"dtype\"")).unwrap_or_else(|| panic!("{n} in {text}")))
        .collect();
    assert!(outputs.len() == 5 && at.is_sorted(), "in output order: {text}");
    for (name, got) in outputs {
        let want = st.tensor(name).expect("in the safetensors file");
        let shape: Vec<usize> = serde_json::from_value(got["shape"].clone()).expect("a shape");
        assert_eq!(shape, want.shape(), "{name}");
        let data = got["data"].as_array().expect("data");
        let b = want.data();
        match want.dtype() {
            Dtype::I64 => {
                assert_eq!(got["dtype"], "i64", "{name}");
                let ints: Vec<i64> = b.chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().expect("8"))).collect();
                assert_eq!(data.iter().map(|v| v.as_i64().expect("an integer")).collect::<Vec<_>>(), ints, "{name}");
            }
            Dtype::BOOL => {
                assert_eq!(got["dtype"], "bool", "{name}");
                let bools: Vec<bool> = b.iter().map(|&v| v != 0).collect();
                assert_eq!(data.iter().map(|v| v.as_bool().expect("a bool")).collect::<Vec<_>>(), bools, "{name}");
            }
            _ => {
                assert_eq!(got["dtype"], "f32", "{name}");
                let floats = b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4")));
                for (i, (v, w)) in data.iter().zip(floats).enumerate() {
                    match v.as_f64() {
                        Some(v) => assert_eq!((v as f32).to_bits(), w.to_bits(), "{name}[{i}]: {v} vs {w}"),
                        None => assert!(v.is_null() && !w.is_finite(), "{name}[{i}]: {v} vs {w}"),
                    }
                }
                assert_eq!(data.len(), b.len() / 4, "{name}");
            }
        }
    }
    assert!(outputs["l"]["data"].as_array().expect("l").iter().any(|v| v.is_null()), "log of a negative: null");
    // `NAME=FILE.json`: that output alone.
    let doc = read_json(&one);
    assert_eq!(doc.as_object().expect("an object").keys().collect::<Vec<_>>(), ["s"]);
    assert_eq!(doc["s"], outputs["s"]);
}

/// `readi compile --variant-f16` without a budget stores the variants' values of every
/// weight no strategy changes at f16 and says so with the measured output difference (both
/// plans run); `--explain` lists them; the plan file holds them as F16 tensors.
#[test]
fn compile_variant_f16_reports_what_it_stored() {
    let dir = common::Scratch::new("cli-f16");
    let p = |x: &std::path::Path| x.to_str().expect("utf-8").to_string();
    let overrides = [("num_classes", "10"), ("img", "32")];
    let (_weights_dir, weights) = seeded_weights_file("models/resnet18.readi", &overrides, "f16");
    let plan = dir.join("h.plan");
    let (weights, plan_arg) = (p(&weights), p(&plan));
    let compile = |extra: &[&str]| {
        let args = ["compile", "models/resnet18.readi", "--weights", &weights, "-o", &plan_arg];
        let sets = ["--set", "num_classes=10", "--set", "img=32", "--seeded-variant", "gamma=0.5"];
        readi(&[&args[..], &sets, extra].concat())
    };
    let o = compile(&["--variant-f16", "--explain"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let line = out.lines().find(|l| l.starts_with("stored the variants'")).unwrap_or_else(|| panic!("{out}"));
    // Seventeen weights, the largest (layer4's adapters) named first.
    assert!(line.contains("variants' layer4.0.bn2.adapter.down.weight, ") && line.contains(" and 13 more"), "{line}");
    assert!(line.contains("outputs differ by at most"), "{line}");
    assert!(out.contains("fc.weight stored f16:"), "the explain table lists it: {out}");
    let loaded = readi_runtime::plan::Plan::load(&plan).expect("loads");
    let half: Vec<&str> =
        loaded.manifest.tensors.iter().filter(|t| t.dtype == readi_plan::DType::F16).map(|t| t.name.as_str()).collect();
    // The classifier and the spec's adapters (1x1 convs of one algorithm), one per
    // variant each; nothing of the base.
    assert!(half.iter().all(|n| n.ends_with("#gamma=0.5")), "{half:?}");
    assert!(half.contains(&"fc.weight@t#gamma=0.5"), "{half:?}");
    assert_eq!(half.iter().filter(|n| n.contains(".adapter.")).count(), 16, "{half:?}");
    // Without the flag: none.
    let o = compile(&[]);
    assert!(o.status.success() && !stdout(&o).contains("stored the variants'"), "{}", stdout(&o));
}
