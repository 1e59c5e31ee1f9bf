//! AdaBN (`readi adapt-bn`, `readi_runtime::calibrate`): BatchNorm statistics re-estimated
//! from unlabelled batches must equal PyTorch's, every BatchNorm in train mode with
//! `momentum=None` after `reset_running_stats()` (tests/fixtures/make_fixtures.py,
//! `--only adabn`: torchvision ResNet-18 with readi's seeded weights at 48x48, three
//! batches of two), to 1e-4.

mod common;

use common::readi;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, VariantSource, WeightSet};
use readi_runtime::calibrate::{BnCalibrator, BnStats, CalibrateError};
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::{Kernel, Plan};

const SEED: u64 = 2024;
const OVERRIDES: [(&str, &str); 2] = [("num_classes", "10"), ("img", "48")];
const BATCHES: usize = 3;

fn module() -> Module {
    module_with(&OVERRIDES)
}

fn module_with(overrides: &[(&str, &str)]) -> Module {
    let (sources, out) = common::compile("models/resnet18.readi", overrides, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

fn seeded_bytes(m: &Module) -> Vec<u8> {
    backend::seeded_weights(&m.graph, SEED).to_safetensors().expect("serialises")
}

/// The seeded plan, with the given seeded variants, written to a file and loaded again so
/// that what the plan records for AdaBN goes through the file format.
fn plan(variants: &[&str], tag: &str) -> Arc<Plan> {
    plan_with(variants, tag, |_| {})
}

/// [`plan`], with the variants' parameters edited first.
fn plan_with(variants: &[&str], tag: &str, edit: impl Fn(&mut Vec<VariantSource>)) -> Arc<Plan> {
    let m = module();
    let weights = WeightSet::from_safetensors("seeded.safetensors", &seeded_bytes(&m)).expect("valid");
    let keys: Vec<String> = variants.iter().map(|k| k.to_string()).collect();
    let mut sources = backend::seeded_variants(&m, &keys, SEED + 1);
    edit(&mut sources);
    let (plan, _) = backend::compile_variants(&m, &weights, "seeded.safetensors", &sources, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{d:?}"));
    let dir = temp_dir(tag);
    let path = dir.join("r18.plan");
    plan.write(&path).expect("write plan");
    let loaded = Plan::load(&path).expect("load plan");
    assert_eq!(loaded.manifest, plan.manifest);
    Arc::new(loaded)
}

fn temp_dir(tag: &str) -> common::Scratch {
    common::Scratch::new(&format!("adabn-{tag}"))
}

fn fixture_path(name: &str) -> PathBuf {
    common::root().join("tests/fixtures/adabn").join(name)
}

fn read_fixture(name: &str) -> WeightSet {
    let path = fixture_path(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

/// The sample batches: `image` of each.
fn batches() -> Vec<(Vec<usize>, Vec<f32>)> {
    (0..BATCHES).map(|i| read_fixture(&format!("batch{i}.safetensors")).tensors["image"].clone()).collect()
}

fn calibrate(plan: Arc<Plan>) -> (BnCalibrator, Vec<BnStats>) {
    let mut cal = BnCalibrator::new(plan, 2).expect("calibrator");
    for (shape, data) in &batches() {
        cal.add_batch(&[Input { name: "image", data, shape }]).expect("batch");
    }
    let stats = cal.statistics().expect("statistics");
    (cal, stats)
}

fn max_abs_error(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Compares statistics by PyTorch name with the fixture's; returns the max errors of
/// running_mean and running_var.
fn compare(label: &str, stats: &[(String, Vec<f32>)]) -> (f32, f32) {
    let want = read_fixture("expected.safetensors");
    let mut names: Vec<&str> = stats.iter().map(|(n, _)| n.as_str()).collect();
    names.sort();
    let expected: Vec<&str> = want.tensors.keys().map(String::as_str).collect();
    assert_eq!(names, expected, "{label}: the same BatchNorm statistics as PyTorch");
    let (mut mean_err, mut var_err) = (0.0f32, 0.0f32);
    for (name, got) in stats {
        let err = max_abs_error(got, &want.tensors[name].1);
        let worst = if name.ends_with(".running_mean") { &mut mean_err } else { &mut var_err };
        *worst = worst.max(err);
    }
    eprintln!("{label}: max abs error vs PyTorch: running_mean {mean_err:e}, running_var {var_err:e}");
    assert!(mean_err <= 1e-4 && var_err <= 1e-4, "{label}: running_mean {mean_err:e}, running_var {var_err:e}");
    (mean_err, var_err)
}

fn by_name(stats: &[BnStats]) -> Vec<(String, Vec<f32>)> {
    stats
        .iter()
        .flat_map(|s| {
            [
                (format!("{}.running_mean", s.name), s.running_mean.clone()),
                (format!("{}.running_var", s.name), s.running_var.clone()),
            ]
        })
        .collect()
}

#[test]
fn adabn_matches_pytorch_train_mode_statistics() {
    let plan = plan(&[], "base");
    let (cal, stats) = calibrate(plan.clone());
    assert_eq!(cal.layers().len(), 20, "every BatchNorm of ResNet-18, each folded into its conv");
    assert_eq!((cal.batches(), cal.samples()), (BATCHES, 2 * BATCHES));
    assert!(plan.manifest.steps.iter().all(|s| !matches!(s.kernel, Kernel::ChannelAffine { .. })));
    compare("adabn, folded BatchNorms", &by_name(&stats));
}

/// With variants the adapters run before every `bn2`. The back end moves an adapter behind
/// its BatchNorm (so the BatchNorm folds into the conv) only when no variant's BatchNorm
/// scale is near zero; a variant with `bn2.weight = 0` keeps all eight unfused, as
/// channel-affine steps: the other path of the calibrator. The base's adapters are zero,
/// so PyTorch's statistics are the same.
#[test]
fn adabn_matches_pytorch_with_unfused_batchnorms() {
    let folded = plan(&["gamma=0.25"], "variants-folded");
    let affine =
        |p: &Plan| p.manifest.steps.iter().filter(|s| matches!(s.kernel, Kernel::ChannelAffine { .. })).count();
    assert_eq!(affine(&folded), 0, "adapters move behind their BatchNorms");
    let plan = plan_with(&["gamma=0.25"], "variants", |sources| {
        for (name, (_, data)) in sources[0].weights.tensors.iter_mut() {
            if name.ends_with(".bn2.weight") {
                data.fill(0.0);
            }
        }
    });
    assert_eq!(affine(&plan), 8, "the bn2 of every block is unfused");
    let (_, stats) = calibrate(plan);
    compare("adabn, with channel-affine BatchNorms", &by_name(&stats));
}

#[test]
fn calibrating_leaves_normal_runs_unchanged() {
    let plan = plan(&[], "unchanged");
    let data = batches();
    let (shape, x) = &data[0];
    let inputs = [Input { name: "image", data: x, shape }];
    let mut session = Session::new(plan.clone(), 2).expect("session");
    let before = session.run(&inputs).expect("run");
    let _ = calibrate(plan.clone());
    let after = session.run(&inputs).expect("run");
    let fresh = Session::new(plan, 2).expect("session").run(&inputs).expect("run");
    for out in [&after, &fresh] {
        let same = before[0].1.data.iter().zip(&out[0].1.data).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "calibration changed a normal run's outputs");
    }
}

/// A batch that fails adds nothing; later batches calibrate as before.
#[test]
fn a_failed_batch_adds_nothing() {
    let plan = plan(&[], "failed");
    let data = batches();
    let mut cal = BnCalibrator::new(plan, 2).expect("calibrator");
    for (k, (shape, x)) in data.iter().enumerate() {
        if k == 1 {
            let mut bad = x.clone();
            bad[7] = f32::NAN;
            let e = cal.add_batch(&[Input { name: "image", data: &bad, shape }]).expect_err("NaN");
            assert!(e.to_string().contains("input `image` holds NaN at flat index 7"), "{e}");
            let e = cal.add_batch(&[Input { name: "img", data: x, shape }]).expect_err("name");
            assert!(e.to_string().contains("no input `img`"), "{e}");
        }
        cal.add_batch(&[Input { name: "image", data: x, shape }]).expect("batch");
    }
    assert_eq!(cal.batches(), BATCHES);
    compare("adabn after failed batches", &by_name(&cal.statistics().expect("stats")));
}

/// At 32x32 `layer4` is 1x1: a batch of one gives its BatchNorms one value per channel,
/// which PyTorch refuses in train mode too.
#[test]
fn one_value_per_channel_is_refused() {
    let m = module_with(&[("num_classes", "10"), ("img", "32")]);
    let w = backend::seeded_weights(&m.graph, SEED);
    let (plan, _) = backend::compile(&m, &w, "seeded", &CompileOptions::default()).expect("compiles");
    let mut cal = BnCalibrator::new(Arc::new(plan), 1).expect("calibrator");
    let x = vec![0.5; 3 * 32 * 32];
    let e = cal.add_batch(&[Input { name: "image", data: &x, shape: &[1, 3, 32, 32] }]).expect_err("n = 1");
    assert!(matches!(&e, CalibrateError::OneValue { layer, .. } if layer == "layer4.0.bn1"), "{e}");
    assert!(e.to_string().contains("one value per channel (input shape [1, 512, 1, 1])"), "{e}");
    assert_eq!(cal.batches(), 0);
    assert_eq!(cal.statistics().err(), Some(CalibrateError::NoBatches));
    let x = vec![0.5; 2 * 3 * 32 * 32];
    cal.add_batch(&[Input { name: "image", data: &x, shape: &[2, 3, 32, 32] }]).expect("two samples");
}

#[test]
fn plans_without_batchnorm_records_ask_for_recompiling() {
    let plan = plan(&[], "old");
    let mut manifest = plan.manifest.clone();
    for step in &mut manifest.steps {
        match &mut step.kernel {
            Kernel::Conv2d { epilogue, .. } | Kernel::ChannelAffine { epilogue, .. } => epilogue.bn = None,
            _ => {}
        }
    }
    let tensors = (0..manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect();
    let old = Plan::new(manifest, tensors).expect("a valid plan without BatchNorm records");
    let e = BnCalibrator::new(Arc::new(old), 1).err().expect("refused");
    assert!(matches!(e, CalibrateError::NotRecorded { ref missing } if missing.len() == 20), "{e}");
    assert!(e.to_string().contains("recompile the plan") && e.to_string().contains("bn1"), "{e}");

    // A model without BatchNorm.
    let small = [("img", "32"), ("patch", "8"), ("width", "32"), ("depth", "1"), ("heads", "2")];
    let (_, out) = common::compile("models/vit_encoder.readi", &small, None);
    let vit = out.module.expect("module");
    let w = backend::seeded_weights(&vit.graph, 1);
    let (p, _) = backend::compile(&vit, &w, "seeded", &CompileOptions::default()).expect("compiles");
    let e = BnCalibrator::new(Arc::new(p), 1).err().expect("refused");
    assert_eq!(e.to_string(), "model `vit_encoder` has no BatchNorm layer: there are no statistics to estimate");
}

/// The BatchNorm records are validated at load like every index of a plan.
#[test]
fn bad_batchnorm_records_are_refused() {
    let plan = plan(&[], "bad");
    let tensors = || (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect::<Vec<_>>();
    let edit = |f: &dyn Fn(&mut readi_runtime::plan::BnInfo)| {
        let mut m = plan.manifest.clone();
        for step in &mut m.steps {
            if let Kernel::Conv2d { epilogue, .. } = &mut step.kernel
                && let Some(bn) = &mut epilogue.bn
                && bn.name == "layer1.0.bn1"
            {
                f(bn);
            }
        }
        Plan::new(m, tensors()).err().map(|e| e.to_string()).unwrap_or_default()
    };
    let n = plan.manifest.tensors.len();
    assert!(edit(&|bn| bn.weight = n + 3).contains(&format!("reads tensor {} of {n}", n + 3)));
    assert!(edit(&|bn| bn.bias = 0).contains("has shape"), "conv1's packed weight is not [64]");
    assert!(edit(&|bn| bn.eps = f64::NAN).contains("eps NaN"));
    assert!(edit(&|bn| bn.name = "bn1".into()).contains("used by another step"));
    assert!(edit(&|_| {}).is_empty(), "unchanged records are valid");
}

// --- The CLI ------------------------------------------------------------------------

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn p(path: &Path) -> String {
    path.to_str().expect("utf-8 path").to_string()
}

/// `readi compile` -> `readi adapt-bn` -> `readi compile --variant KEY=stats` -> `readi run
/// --variant KEY`: the statistics equal PyTorch's, and the variant's outputs equal
/// PyTorch's adapted model in eval mode.
#[test]
fn cli_adapt_bn_end_to_end() {
    let dir = temp_dir("cli");
    let weights = dir.join("r18.safetensors");
    std::fs::write(&weights, seeded_bytes(&module())).expect("write weights");
    let set = ["--set", "num_classes=10", "--set", "img=48"];
    let base = dir.join("base.plan");
    let o =
        readi(&[&["compile", "models/resnet18.readi", "--weights", &p(&weights), "-o", &p(&base)], &set[..]].concat());
    assert!(o.status.success(), "{}", text(&o.stderr));

    let samples: Vec<String> = (0..BATCHES).map(|i| p(&fixture_path(&format!("batch{i}.safetensors")))).collect();
    let stats = dir.join("gamma_0.25.safetensors");
    // The key as written by hand (`0.250`) names the declared `gamma=0.25`.
    let (base_s, stats_s) = (p(&base), p(&stats));
    let mut args = vec!["adapt-bn", &base_s, "--variant", "gamma=0.250", "-o", &stats_s, "--threads", "2", "--samples"];
    args.extend(samples.iter().map(String::as_str));
    let o = readi(&args);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = text(&o.stdout);
    assert!(out.contains("20 BatchNorm layers of resnet18 re-estimated over 3 batches (6 samples)"), "{out}");
    assert!(out.contains("for variant `gamma=0.25`"), "the key as declared: {out}");

    let got = WeightSet::from_safetensors("stats", &std::fs::read(&stats).expect("stats written")).expect("valid");
    let got: Vec<(String, Vec<f32>)> = got.tensors.into_iter().map(|(k, (_, v))| (k, v)).collect();
    compare("readi adapt-bn", &got);

    let adapted = dir.join("adapted.plan");
    let variant = format!("gamma=0.25={}", p(&stats));
    let o = readi(
        &[
            &["compile", "models/resnet18.readi", "--weights", &p(&weights), "-o", &p(&adapted), "--variant", &variant],
            &set[..],
        ]
        .concat(),
    );
    assert!(o.status.success(), "{}", text(&o.stderr));
    // Only the statistics: the rest of what the variant owns keeps the base value.
    assert!(text(&o.stderr).contains("gamma=0.25 gives"), "{}", text(&o.stderr));

    let logits = dir.join("logits.npy");
    let input = format!("image={}", samples[0]);
    let o = readi(&["run", &p(&adapted), "--variant", "gamma=0.25", "--input", &input, "--output", &p(&logits)]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let want = &read_fixture("adapted_logits.safetensors").tensors["logits"];
    let got = {
        use ndarray_npy::ReadNpyExt;
        let a = ndarray::ArrayD::<f32>::read_npy(std::fs::File::open(&logits).expect("logits")).expect("npy");
        (a.shape().to_vec(), a.iter().copied().collect::<Vec<f32>>())
    };
    assert_eq!(got.0, want.0);
    let err = max_abs_error(&got.1, &want.1);
    eprintln!("adapted variant logits: max abs error vs PyTorch eval with the new statistics {err:e}");
    assert!(err <= 1e-4, "the adapted variant differs from PyTorch by {err:e}");
}

#[test]
fn cli_adapt_bn_errors_name_the_file() {
    let dir = temp_dir("cli-errors");
    let weights = dir.join("r18.safetensors");
    std::fs::write(&weights, seeded_bytes(&module())).expect("write weights");
    let plan_path = dir.join("base.plan");
    let o = readi(&[
        "compile",
        "models/resnet18.readi",
        "--weights",
        &p(&weights),
        "-o",
        &p(&plan_path),
        "--set",
        "num_classes=10",
        "--set",
        "img=48",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = p(&dir.join("stats.safetensors"));
    let good = p(&fixture_path("batch0.safetensors"));
    let adapt = |variant: &str, sample: &str, plan: &str| {
        let o = readi(&["adapt-bn", plan, "--variant", variant, "--samples", &good, sample, "-o", &out]);
        assert_eq!(o.status.code(), Some(1), "{}", text(&o.stdout));
        text(&o.stderr)
    };
    let plan = p(&plan_path);

    let e = adapt("gama=0.25", &good, &plan);
    assert!(e.contains("declares no variant `gama=0.25`; did you mean `gamma=0.25`?"), "{e}");
    let e = adapt("base", &good, &plan);
    assert!(e.contains("`base` is the base model"), "{e}");

    // Wrong shape (.npy), NaN, a file without the input, a missing file.
    let npy = dir.join("small.npy");
    write_npy(&npy, &[2, 3, 16, 16], &[0.5; 2 * 3 * 16 * 16]);
    let e = adapt("gamma=0.25", &p(&npy), &plan);
    assert!(e.contains(&format!("{}: input `image` has shape [2, 3, 16, 16]", p(&npy))), "{e}");
    let nan = dir.join("nan.npy");
    let mut data = vec![0.5; 2 * 3 * 48 * 48];
    data[5] = f32::NAN;
    write_npy(&nan, &[2, 3, 48, 48], &data);
    let e = adapt("gamma=0.25", &p(&nan), &plan);
    assert!(e.contains(&format!("{}: input `image` holds NaN at flat index 5", p(&nan))), "{e}");
    let two = dir.join("two.safetensors");
    let mut set = WeightSet::default();
    set.tensors.insert("image".into(), (vec![2], vec![0.0; 2]));
    set.tensors.insert("label".into(), (vec![2], vec![0.0; 2]));
    std::fs::write(&two, set.to_safetensors().expect("serialises")).expect("write");
    let e = adapt("gamma=0.25", &p(&two), &plan);
    assert!(e.contains(&format!("{}: tensor `label` is not an input of model `resnet18`", p(&two))), "{e}");
    let e = adapt("gamma=0.25", "no/such/batch.npy", &plan);
    assert!(e.contains("cannot read no/such/batch.npy"), "{e}");
    assert!(!Path::new(&out).exists(), "nothing is written on error");

    // A plan from before BatchNorm records: written as this readi would, without them.
    let loaded = Plan::load(&plan_path).expect("load");
    let mut manifest = loaded.manifest.clone();
    for step in &mut manifest.steps {
        if let Kernel::Conv2d { epilogue, .. } = &mut step.kernel {
            epilogue.bn = None;
        }
    }
    let tensors = (0..manifest.tensors.len()).map(|i| loaded.tensor(i).to_vec()).collect();
    let old_path = dir.join("old.plan");
    Plan::new(manifest, tensors).expect("valid").write(&old_path).expect("write");
    let e = adapt("gamma=0.25", &good, &p(&old_path));
    assert!(e.contains("recompile the plan"), "{e}");
}

fn write_npy(path: &Path, shape: &[usize], data: &[f32]) {
    use ndarray_npy::WriteNpyExt;
    let a = ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(shape), data.to_vec()).expect("shape");
    a.write_npy(std::fs::File::create(path).expect("create")).expect("write npy");
}

// ---- Scoped ownership: adapt-bn writes what the variant owns ----

const SCOPED: &str = "tests/cases/ok/adapt_scoped.readi";

/// A module of `source` (tests/cases/ok/adapt_scoped.readi or an edit of it).
fn scoped_module(source: &str) -> Module {
    let (sources, out) = common::compile_text(SCOPED, source, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

/// `source` written to `dir`, its seeded weights, and its base plan compiled by `readi
/// compile`: (spec, weights, plan).
fn scoped_plan(dir: &Path, source: &str) -> (String, String, String) {
    let spec = dir.join("scoped.readi");
    std::fs::write(&spec, source).expect("write spec");
    let weights = dir.join("scoped.safetensors");
    let bytes = backend::seeded_weights(&scoped_module(source).graph, SEED).to_safetensors().expect("serialises");
    std::fs::write(&weights, bytes).expect("write weights");
    let plan = dir.join("base.plan");
    let o = readi(&["compile", &p(&spec), "--weights", &p(&weights), "-o", &p(&plan)]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    (p(&spec), p(&weights), p(&plan))
}

/// Two sample batches of adapt_scoped's inputs (`image` [2, 3, 8, 8], `points` [2, 4, 8, 8]).
fn scoped_samples(dir: &Path) -> Vec<String> {
    let mut state = 0x2545_f491_u32;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        (state as f32 / u32::MAX as f32) * 2.0 - 0.5
    };
    (0..2)
        .map(|i| {
            let mut set = WeightSet::default();
            set.tensors.insert("image".into(), (vec![2, 3, 8, 8], (0..2 * 3 * 64).map(|_| next()).collect()));
            set.tensors.insert("points".into(), (vec![2, 4, 8, 8], (0..2 * 4 * 64).map(|_| next()).collect()));
            let path = dir.join(format!("sample{i}.safetensors"));
            std::fs::write(&path, set.to_safetensors().expect("serialises")).expect("write sample");
            p(&path)
        })
        .collect()
}

/// `readi adapt-bn PLAN --variant KEY`: its output, and the file's tensors by name.
fn adapt_bn(plan: &str, key: &str, samples: &[String], out: &Path) -> (std::process::Output, WeightSet) {
    let out_s = p(out);
    let mut args = vec!["adapt-bn", plan, "--variant", key, "-o", &out_s, "--samples"];
    args.extend(samples.iter().map(String::as_str));
    let o = readi(&args);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let set = WeightSet::from_safetensors("stats", &std::fs::read(out).expect("stats written")).expect("valid");
    (o, set)
}

fn names(set: &WeightSet) -> Vec<&str> {
    let mut n: Vec<&str> = set.tensors.keys().map(String::as_str).collect();
    n.sort();
    n
}

/// On adapt_scoped (camera variants own `cam.bn`, lidar and lost-lidar variants `lid.bn`):
/// each variant's file holds its own BatchNorms' statistics only, equal to those an
/// unscoped run computes, and compiles with `--variant`; a meld not declared as a variant
/// gets its parts' BatchNorms; a plan without the ownership record writes every
/// BatchNorm's, as before.
#[test]
fn cli_adapt_bn_writes_only_the_variants_batchnorms() {
    let dir = temp_dir("scoped");
    let source = std::fs::read_to_string(common::root().join(SCOPED)).expect("read spec");
    let (spec, weights, plan) = scoped_plan(&dir, &source);
    let samples = scoped_samples(&dir);
    let o = readi(&["inspect", &plan, "--verbose"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let listing = text(&o.stdout);
    let line = |name: &str| listing.lines().find(|l| l.trim_start().starts_with(name)).unwrap_or_default().to_string();
    assert!(line("cam.bn.running_var ").ends_with("; owned by camera"), "{listing}");
    assert!(line("lid.bn.running_var ").ends_with("; owned by lidar, missing=lidar"), "{listing}");
    assert!(line("head.weight ").ends_with("; owned by every variant"), "{listing}");
    assert!(!line("cam.conv.weight ").contains("owned by"), "{listing}");

    // The old plan first: every BatchNorm, and a note saying why.
    let loaded = Plan::load(Path::new(&plan)).expect("load");
    let mut manifest = loaded.manifest.clone();
    assert!(manifest.records_ownership());
    for param in &mut manifest.params {
        param.owned_by = None;
    }
    let tensors = (0..manifest.tensors.len()).map(|i| loaded.tensor(i).to_vec()).collect();
    let old = dir.join("old.plan");
    Plan::new(manifest, tensors).expect("valid").write(&old).expect("write");
    let (o, all) = adapt_bn(&p(&old), "gamma=0.5", &samples, &dir.join("all.safetensors"));
    assert!(text(&o.stderr).contains("does not record which variants own its parameters"), "{}", text(&o.stderr));
    assert!(text(&o.stdout).contains("2 BatchNorm layers of m re-estimated"), "{}", text(&o.stdout));
    let stats = ["running_mean", "running_var"];
    let both: Vec<String> = ["cam.bn", "lid.bn"].iter().flat_map(|b| stats.map(|s| format!("{b}.{s}"))).collect();
    assert_eq!(names(&all), both);
    // What the scoped plan refuses: the lidar branch's statistics are not the camera variant's.
    let variant = format!("gamma=0.5={}", p(&dir.join("all.safetensors")));
    let o = readi(&["compile", &spec, "--weights", &weights, "-o", &p(&dir.join("v.plan")), "--variant", &variant]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stdout));
    assert!(text(&o.stderr).contains("`lid.bn.running_mean` is outside the scope of variant"), "{}", text(&o.stderr));

    let cases: [(&str, &[&str]); 4] = [
        ("gamma=0.5", &["cam.bn"]),
        ("fog=0.03", &["lid.bn"]),
        ("missing=lidar", &["lid.bn"]),
        // Not a variant of the plan (none is compiled): decided from the recorded scopes.
        ("fog=0.06+gamma=2", &["cam.bn", "lid.bn"]),
    ];
    for (key, bns) in cases {
        let out = dir.join(format!("{key}.safetensors"));
        let (o, got) = adapt_bn(&plan, key, &samples, &out);
        let want: Vec<String> = bns.iter().flat_map(|b| stats.map(|s| format!("{b}.{s}"))).collect();
        assert_eq!(names(&got), want, "{key}");
        for (name, (shape, values)) in &got.tensors {
            assert_eq!((shape, values), (&all.tensors[name].0, &all.tensors[name].1), "{key}: {name}");
        }
        let stdout = text(&o.stdout);
        let skipped = 2 - bns.len();
        let line = if skipped == 0 {
            "2 BatchNorm layers of m re-estimated".to_string()
        } else {
            "1 BatchNorm layer of m re-estimated".to_string()
        };
        assert!(stdout.contains(&line), "{key}: {stdout}");
        assert_eq!(stdout.contains(&format!("; 1 skipped, not owned by `{key}`")), skipped == 1, "{key}: {stdout}");
        if key.contains('+') {
            continue;
        }
        let variant = format!("{key}={}", p(&out));
        let o = readi(&["compile", &spec, "--weights", &weights, "-o", &p(&dir.join("v.plan")), "--variant", &variant]);
        assert!(o.status.success(), "{key}: {}", text(&o.stderr));
    }
}

/// A variant whose scopes tune no BatchNorm gets an error naming it and its scopes, and
/// nothing is written; so does a spec whose rules tune no BatchNorm at all.
#[test]
fn cli_adapt_bn_refuses_a_variant_owning_no_batchnorm() {
    let dir = temp_dir("scoped-none");
    let source = std::fs::read_to_string(common::root().join(SCOPED)).expect("read spec");
    let no_lid_bn = source.replace("  tune lid.bn\n", "");
    assert_ne!(no_lid_bn, source);
    let (_, _, plan) = scoped_plan(&dir, &no_lid_bn);
    let samples = scoped_samples(&dir);
    let out = dir.join("stats.safetensors");
    let refuse = |plan: &str, key: &str| {
        let o = readi(&["adapt-bn", plan, "--variant", key, "-o", &p(&out), "--samples", &samples[0]]);
        assert_eq!(o.status.code(), Some(1), "{key}: {}", text(&o.stdout));
        assert!(!out.exists(), "{key}: nothing is written");
        text(&o.stderr)
    };
    let e = refuse(&plan, "fog=0.03");
    assert!(
        e.contains(
            "variant `fog=0.03` owns no BatchNorm statistics (its scopes: `lidar`, `fog`): add `tune batchnorm` to an \
             adapt section that covers it"
        ),
        "{e}"
    );
    // The camera variants still own theirs.
    let (_, got) = adapt_bn(&plan, "gamma=0.5", &samples, &out);
    assert_eq!(names(&got), ["cam.bn.running_mean", "cam.bn.running_var"]);
    std::fs::remove_file(&out).expect("remove");

    // Unscoped, without `tune batchnorm`: no variant owns a BatchNorm.
    let dir2 = dir.join("unscoped");
    std::fs::create_dir_all(&dir2).expect("dir");
    let start = source.find("adapt {").expect("the unscoped section");
    let end = source.find("variants {").expect("the variants section");
    let unscoped = format!("{}adapt {{\n  tune head\n}}\n{}", &source[..start], &source[end..]);
    let (_, _, plan) = scoped_plan(&dir2, &unscoped);
    let e = refuse(&plan, "gamma=0.5");
    assert!(e.contains("variant `gamma=0.5` owns no BatchNorm statistics (it is in the scope of no scoped"), "{e}");
}

/// What the plan records of each parameter's owners decides every key as the compiler's
/// tensor table does: each declared key, each meld of two, the base.
#[test]
fn recorded_ownership_agrees_with_the_compiler() {
    let source = std::fs::read_to_string(common::root().join(SCOPED)).expect("read spec");
    let m = scoped_module(&source);
    let weights = backend::seeded_weights(&m.graph, SEED);
    let plan = backend::compile(&m, &weights, "seeded", &CompileOptions::default()).expect("compiles").0;
    let owned = readi_compiler::weights::variants::owned_params(&m);
    let manifest = &plan.manifest;
    let c = manifest.conditions.as_ref().expect("conditions");
    let declared = c.keys();
    let mut keys = declared.clone();
    for a in &declared {
        for b in &declared {
            if a.to_string() < b.to_string() && a.parts()[0].axis() != b.parts()[0].axis() {
                keys.push(readi_plan::VariantKey::parse(&format!("{a}+{b}")).expect("a meld"));
            }
        }
    }
    keys.push(readi_plan::VariantKey::base());
    assert!(keys.len() > 8, "{keys:?}");
    let mut owners = 0;
    for param in &manifest.params {
        for key in &keys {
            let want = owned.get(&param.name).is_some_and(|o| o.is_owned_by(key));
            assert_eq!(param.is_owned_by(key, Some(c)), want, "{} under {key}", param.name);
            owners += usize::from(want);
        }
    }
    assert!(owners > 20, "{owners}");
    // The camera branch: `camera` only; the head: every variant.
    let find = |n: &str| manifest.params.iter().find(|p| p.name == n).expect(n);
    assert_eq!(find("cam.bn.running_var").owned_by, Some(vec!["camera".to_string()]));
    assert_eq!(find("head.weight").owned_by, Some(vec![]));
    assert_eq!(find("cam.conv.weight").owned_by, None);
}
