//! Adapters fused into the conv that produces their input (`fuse_adapters`) against the
//! same plan with every adapter left as separate steps
//! (`CompileOptions::unfused_adapters`): ResNet-18 (64x64) and bevfusion_tiny with
//! seeded weights and variants, outputs within 1e-5 of the output's scale, at 1 and 2
//! threads; and switching variants on the fused plan, A -> B -> A, gives A's outputs bit
//! for bit.

mod common;

use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions};
use readi_runtime::exec::{Input, Session, Tensor};
use readi_runtime::plan::Plan;

fn module(rel: &str, overrides: &[(&str, &str)]) -> Module {
    let (sources, out) = common::compile(rel, overrides, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

/// The plan with `keys`' seeded variants, adapters fused or not.
fn plan(m: &Module, keys: &[&str], unfused_adapters: bool) -> Arc<Plan> {
    let keys: Vec<String> = keys.iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(m, &keys, 30);
    let opts = CompileOptions { unfused_adapters, ..Default::default() };
    let weights = backend::seeded_weights(&m.graph, 1);
    Arc::new(backend::compile_variants(m, &weights, "seeded", &sources, &opts).expect("compiles").0)
}

/// Seeded data for every input of the plan, at batch 1.
fn input_data(plan: &Plan) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    plan.manifest
        .input_shapes(1)
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let data = (0..n).map(|k| ((k * 7919 % 1000) as f32 / 500.0) - 1.0).collect();
            (name.to_string(), shape, data)
        })
        .collect()
}

fn run(session: &mut Session, key: &str, data: &[(String, Vec<usize>, Vec<f32>)]) -> Vec<(String, Tensor)> {
    session.set_variant(key).expect("known key");
    let inputs: Vec<Input<'_>> =
        data.iter().map(|(n, s, d)| Input { name: n.as_str(), data: d.as_slice(), shape: s.as_slice() }).collect();
    session.run(&inputs).expect("run")
}

/// Worst difference relative to the reference output's largest magnitude (at least 1).
fn rel_error(got: &[(String, Tensor)], want: &[(String, Tensor)]) -> f32 {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .map(|((n, a), (m, b))| {
            assert_eq!((n, &a.shape), (m, &b.shape));
            let scale = b.data.iter().fold(1.0f32, |s, v| s.max(v.abs()));
            a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max) / scale
        })
        .fold(0.0, f32::max)
}

fn bits(out: &[(String, Tensor)]) -> Vec<Vec<u32>> {
    out.iter().map(|(_, t)| t.data.iter().map(|v| v.to_bits()).collect()).collect()
}

/// The fused plan has `fused` adapters in its convs and at least `2 * fused` steps fewer than the
/// unfused one, and agrees with it under every key at 1 and 2 threads; then A -> B -> A.
fn check(rel: &str, overrides: &[(&str, &str)], keys: &[&str], fused: usize) {
    let m = module(rel, overrides);
    let (with, without) = (plan(&m, keys, false), plan(&m, keys, true));
    let count = |p: &Plan| p.manifest.steps.iter().filter(|s| s.kernel.adapter().is_some()).count();
    assert_eq!((count(&with), count(&without)), (fused, 0), "{rel}: fused adapters");
    // Unfused, each adapter is two steps: down (its activation fused in) and up, the sum
    // added in up's epilogue as its residual (and a ReLU after the sum fused there too);
    // up to four where those do not fuse.
    let (n, unfused) = (with.manifest.steps.len(), without.manifest.steps.len());
    assert!(n + 2 * fused <= unfused && unfused <= n + 4 * fused, "{rel}: {n} steps fused, {unfused} not");
    let data = input_data(&with);
    for threads in [1, 2] {
        let mut a = Session::new(with.clone(), threads).expect("session");
        let mut b = Session::new(without.clone(), threads).expect("session");
        for &key in keys.iter().chain(&["base"]) {
            let key = if key == "base" { with.variant_key(0).to_string() } else { key.to_string() };
            let e = rel_error(&run(&mut a, &key, &data), &run(&mut b, &key, &data));
            assert!(e <= 1e-5, "{rel}, {key}, {threads} threads: fused and unfused differ by {e:e}");
        }
    }
    // A -> B -> A on one session: A's outputs again, bit for bit, and B's differ.
    let mut s = Session::new(with.clone(), 2).expect("session");
    let first = run(&mut s, keys[0], &data);
    let other = run(&mut s, keys[1], &data);
    let again = run(&mut s, keys[0], &data);
    assert_eq!(bits(&first), bits(&again), "{rel}: A -> B -> A");
    assert_ne!(bits(&first), bits(&other), "{rel}: the variants differ");
}

#[test]
fn resnet18_fused_adapters_match_the_unfused_plan() {
    // One adapter per BasicBlock, before bn2: conv2's output, 8 of them.
    check("models/resnet18.readi", &[("img", "64"), ("num_classes", "10")], &["gamma=0.5", "blur=5"], 8);
}

#[test]
fn bevfusion_tiny_fused_adapters_match_the_unfused_plan() {
    let m = module("models/bevfusion_tiny.readi", &[]);
    let adapters = m.adapt.as_ref().map_or(0, |a| {
        a.injections.iter().filter(|i| matches!(i, readi_compiler::adapt::Injection::Adapter { .. })).count()
    });
    assert!(adapters > 0);
    // The camera variant owns the camera backbone's adapters; the lidar variant owns none
    // (its rules only tune), so its plan is the base schedule with its own values.
    check("models/bevfusion_tiny.readi", &[], &["gamma=0.25", "fog=0.06"], adapters);
}

/// A variant runs only the adapters and LoRA branches it gives: the others read the base
/// model's zero `up` / `B` (`VariantTensors::reads_zero`) and the kernels skip them. On
/// bevfusion_tiny a lidar variant gives none of the camera branch's, a camera one all.
#[test]
fn a_variant_runs_only_the_adaptations_it_gives() {
    let m = module("models/bevfusion_tiny.readi", &[]);
    let keys: Vec<String> = ["gamma=0.25", "fog=0.06"].iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(&m, &keys, 30);
    let opts = CompileOptions { lora: backend::LoraMode::Branch, ..Default::default() };
    let weights = backend::seeded_weights(&m.graph, 1);
    let p = backend::compile_variants(&m, &weights, "seeded", &sources, &opts).expect("compiles").0;
    let ups: Vec<usize> = p.manifest.steps.iter().filter_map(|s| s.kernel.adapter()).map(|a| a.up).collect();
    let bs: Vec<usize> = p.manifest.steps.iter().filter_map(|s| s.kernel.lora()).map(|l| l.b).collect();
    assert_eq!((ups.len(), bs.len()), (8, 8), "the camera backbone's adapters, the transformer's LoRA branches");
    let at = |key: &str| p.variant_tensors(p.variant_index(key).expect("a key")).expect("a variant");
    for t in ups.into_iter().chain(bs) {
        let name = &p.manifest.tensors[t].name;
        assert!(p.base_tensors().reads_zero(t), "{name}: the base runs no adaptation");
        assert!(at("fog=0.06").reads_zero(t), "{name}: not the lidar variant's");
        assert!(!at("gamma=0.25").reads_zero(t), "{name}: the camera variant's");
    }
}

/// An adapter before a BatchNorm of rows of features (`[N, C]`, as a sparse tensor's: the
/// lidar encoder's residual blocks) is two linears; the variant's output against a naive
/// evaluation of `bn(h + up(relu(down(h))))`, `h = linear(x)`, from its seeded tensors.
#[test]
fn an_adapter_on_rows_of_features_is_two_linears() {
    let spec = "block Res(x: tensor) {\n  fc = linear(x, 8)\n  bn = batchnorm(fc)\n  return relu(bn)\n}\n\
        model rows {\n  input x: f32[5, 6] @lidar\n  res = Res(x)\n  output y = res\n}\n\
        adapt lidar { adapter squeeze=2 act=relu in Res before bn }\n\
        variants { axis fog on lidar: 0.1 clear 0 }\n";
    let (sources, out) = common::compile_text("rows.readi", spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = vec!["fog=0.1".to_string()];
    let variants = backend::seeded_variants(&m, &keys, 4);
    let base = backend::seeded_weights(&m.graph, 3);
    let plan = Arc::new(
        backend::compile_variants(&m, &base, "seeded", &variants, &CompileOptions::default()).expect("compiles").0,
    );
    let x: Vec<f32> = (0..30).map(|k| ((k * 37 % 19) as f32 / 9.0) - 1.0).collect();
    let mut session = Session::new(plan, 1).expect("session");
    session.set_variant("fog=0.1").expect("key");
    let got = session.run(&[Input { name: "x", data: &x, shape: &[5, 6] }]).expect("runs");

    let get = |name: &str| -> Vec<f64> {
        let t = variants[0].weights.tensors.get(name).or_else(|| base.tensors.get(name));
        t.unwrap_or_else(|| panic!("no tensor {name}")).1.iter().map(|&v| v as f64).collect()
    };
    // `y[r, o] = sum_i w[o, i] a[r, i] + b[o]` over rows of `a`.
    let linear = |a: &[f64], cin: usize, w: &[f64], b: &[f64]| -> Vec<f64> {
        let cout = b.len();
        (0..a.len() / cin * cout)
            .map(|k| b[k % cout] + (0..cin).map(|i| w[k % cout * cin + i] * a[k / cout * cin + i]).sum::<f64>())
            .collect()
    };
    let xs: Vec<f64> = x.iter().map(|&v| v as f64).collect();
    let h = linear(&xs, 6, &get("res.fc.weight"), &get("res.fc.bias"));
    let down: Vec<f64> = linear(&h, 8, &get("res.bn.adapter.down.weight"), &get("res.bn.adapter.down.bias"))
        .into_iter()
        .map(|v| v.max(0.0))
        .collect();
    let up = linear(&down, 4, &get("res.bn.adapter.up.weight"), &get("res.bn.adapter.up.bias"));
    let (gamma, beta, mean, var) =
        (get("res.bn.weight"), get("res.bn.bias"), get("res.bn.running_mean"), get("res.bn.running_var"));
    let want: Vec<f32> = (0..40)
        .map(|k| {
            let c = k % 8;
            let z = h[k] + up[k];
            (((z - mean[c]) / (var[c] + 1e-5).sqrt() * gamma[c] + beta[c]).max(0.0)) as f32
        })
        .collect();
    assert!(up.iter().any(|v| v.abs() > 1e-3), "the adapter adds nothing");
    common::close("y", &got[0].1, &(vec![5, 8], want), 1e-5);
}

/// Writes `resnet18.plan` (adapters fused), `resnet18_unfused.plan` and
/// `resnet18_no_adapters.plan` (the spec without its adapter rules), likewise for
/// bevfusion_tiny, each with one seeded variant (`gamma=0.5`, `gamma=0.25`), into the directory
/// `READI_ADAPTER_PLANS`, for timing with `readi bench --variant KEY`:
///
///     READI_ADAPTER_PLANS=/tmp/ap cargo test --test adapters -- --ignored write_bench_plans
#[test]
#[ignore = "writes plan files for measurements"]
fn write_bench_plans() {
    let dir = std::path::PathBuf::from(std::env::var("READI_ADAPTER_PLANS").expect("READI_ADAPTER_PLANS"));
    std::fs::create_dir_all(&dir).expect("create the directory");
    for (name, rel, overrides, key) in [
        ("resnet18", "models/resnet18.readi", &[("num_classes", "1000")][..], "gamma=0.5"),
        ("bevfusion_tiny", "models/bevfusion_tiny.readi", &[][..], "gamma=0.25"),
    ] {
        let m = module(rel, overrides);
        let src = std::fs::read_to_string(common::root().join(rel)).expect("read the spec");
        let stripped: String =
            src.lines().filter(|l| !l.trim_start().starts_with("adapter ")).map(|l| format!("{l}\n")).collect();
        let (sources, out) = common::compile_text(rel, &stripped, overrides, None);
        assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
        let bare = out.module.expect("module");
        for (suffix, p) in [
            ("", plan(&m, &[key], false)),
            ("_unfused", plan(&m, &[key], true)),
            ("_no_adapters", plan(&bare, &[key], false)),
        ] {
            p.write(&dir.join(format!("{name}{suffix}.plan"))).expect("write the plan");
        }
    }
}
