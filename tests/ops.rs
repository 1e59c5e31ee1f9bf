//! Operators against PyTorch: each spec in tests/fixtures/ops/ run on the inputs and
//! weights its script there wrote, against the outputs torch computed, to 1e-5 (absolute,
//! or relative to values above 1); NaN and infinities where torch has them.
//!
//! - `activations.readi` (`make_activation_fixtures.py`): activations and unary
//!   functions; its conv + batchnorm + act and linear + act chains must compile to one
//!   fused kernel each.
//! - `convs.readi` (`make_conv_fixtures.py`): transposed and 1-D convolutions, at 1 and 2
//!   threads.
//! - `reductions.readi` (`make_reduction_fixtures.py`): sum, mean, max, min, var
//!   (corrections 0 and 1), std; adaptive pooling to divisible, non-divisible and larger
//!   sizes; groupnorm with affine weights, without, and in one group; pixel (un)shuffle.
//! - `movement.readi` (`make_movement_fixtures.py`): pad, roll and slicing, which must
//!   equal torch's values exactly.
//! - `conv3d.readi` (`make_conv3d_fixtures.py`): 3-D convolutions (padding, stride,
//!   dilation, groups, depthwise, 1x1x1) and BatchNorm3d, at 1 and 2 threads.
//! - `bev_pool.readi` (`make_bev_pool_fixtures.py`): BEVFusion's camera-to-BEV view
//!   transform (`lss_bev_pool`) under two calibrations, to 1e-4, at 1 and 2 threads.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_plan::ops::Pure;
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::{Kernel, Plan};

const SPEC: &str = "tests/fixtures/ops/activations.readi";

fn fixture(name: &str) -> WeightSet {
    let path = common::root().join("tests/fixtures/ops").join(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

fn plan() -> Plan {
    compile(SPEC, "activations.weights.safetensors")
}

fn compile(spec: &str, weights: &str) -> Plan {
    let (sources, out) = common::compile(spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let (plan, _) = backend::compile(&module, &fixture(weights), weights, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    plan
}

#[test]
fn activations_match_pytorch() {
    matches_pytorch(plan(), "activations.io.safetensors", 2);
}

#[test]
fn transposed_and_1d_convs_match_pytorch() {
    for threads in [1, 2] {
        matches_pytorch(
            compile("tests/fixtures/ops/convs.readi", "convs.weights.safetensors"),
            "convs.io.safetensors",
            threads,
        );
    }
}

#[test]
fn transposed_convs_take_their_bias_and_activation() {
    let plan = compile("tests/fixtures/ops/convs.readi", "convs.weights.safetensors");
    let steps = &plan.manifest.steps;
    let step = |name: &str| steps.iter().find(|s| s.path.starts_with(name)).unwrap_or_else(|| panic!("no {name}"));
    let Kernel::ConvTranspose2d { epilogue, .. } = &step("t1").kernel else { panic!("t1 is {:?}", step("t1")) };
    assert!(epilogue.shift.is_some() && epilogue.act.is_none(), "{epilogue:?}");
    let Kernel::ConvTranspose2d { epilogue, .. } = &step("t4").kernel else { panic!("t4 is {:?}", step("t4")) };
    assert!(epilogue.shift.is_some() && epilogue.act.is_some(), "the ReLU is not fused: {epilogue:?}");
    // A BatchNorm after a transposed conv stays a channel affine, which takes the ReLU.
    assert!(matches!(step("b5").kernel, Kernel::ChannelAffine { ref epilogue, .. } if epilogue.act.is_some()));
    // conv1d: a conv2d between two reshapes, the BatchNorm and ReLU fused into it.
    let c2: Vec<&Kernel> = steps.iter().filter(|s| s.path.starts_with("c2")).map(|s| &s.kernel).collect();
    let [Kernel::Pure(Pure::Reshape(_)), Kernel::Conv2d { epilogue, .. }, Kernel::Pure(Pure::Reshape(_))] = &c2[..]
    else {
        panic!("c2 is {c2:?}")
    };
    assert!(epilogue.bn.is_some() && epilogue.act.is_some(), "{epilogue:?}");
}

#[test]
fn reductions_pooling_groupnorm_and_pixel_shuffle_match_pytorch() {
    let plan = compile("tests/fixtures/ops/reductions.readi", "reductions.weights.safetensors");
    // Adaptive pooling with bins that are all alike runs as the plain pooling it equals.
    let kinds: Vec<&str> = plan.manifest.steps.iter().map(|s| s.kernel.name()).collect();
    for k in ["sum", "mean", "max", "min", "var", "std", "adaptive_avgpool", "adaptive_maxpool", "global_avgpool"] {
        assert!(kinds.contains(&k), "no `{k}` step in {kinds:?}");
    }
    for k in ["pool", "groupnorm", "pixel_shuffle", "pixel_unshuffle"] {
        assert!(kinds.contains(&k), "no `{k}` step in {kinds:?}");
    }
    matches_pytorch(plan, "reductions.io.safetensors", 2);
}

/// Runs `plan` on the fixture's `input.*` tensors at `threads` threads and compares every
/// output with the fixture's `output.*`.
fn matches_pytorch(plan: Plan, io: &str, threads: usize) {
    let plan = Arc::new(plan);
    let io = fixture(io);
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let outputs = Session::new(plan, threads).expect("session").run(&inputs).expect("runs");
    assert_eq!(outputs.len(), io.tensors.keys().filter(|k| k.starts_with("output.")).count());
    for (name, t) in &outputs {
        let (shape, want) = &io.tensors[&format!("output.{name}")];
        assert_eq!(&t.shape, shape, "shape of {name}");
        let mut worst = 0.0f32;
        for (i, (&g, &w)) in t.data.iter().zip(want).enumerate() {
            if w.is_nan() || w.is_infinite() {
                assert!(g.is_nan() == w.is_nan() && (w.is_nan() || g == w), "{name}[{i}]: {g}, torch {w}");
                continue;
            }
            let err = (g - w).abs() / w.abs().max(1.0);
            assert!(err <= 1e-5, "{name}[{i}]: {g}, torch {w} (error {err:e})");
            worst = worst.max(err);
        }
        eprintln!("{name}: max error vs torch {worst:e}");
    }
}

#[test]
fn conv_and_linear_activations_run_in_the_epilogue() {
    let plan = plan();
    let steps = &plan.manifest.steps;
    for chain in ["b1", "b2", "b3", "b4", "c5", "fc1", "fc2", "fc3", "fc4"] {
        let step = steps.iter().find(|s| s.path.contains(chain)).unwrap_or_else(|| panic!("no step for {chain}"));
        let ep = step.kernel.epilogue().unwrap_or_else(|| panic!("{chain}: {:?} has no epilogue", step.kernel));
        assert!(ep.act.is_some(), "{chain}: the activation is not fused into {}", step.path);
    }
    // No activation step is left reading a conv's, linear's or affine's output.
    let fusable = |v: usize| {
        steps.iter().any(|s| {
            s.output == v
                && matches!(s.kernel, Kernel::Conv2d { .. } | Kernel::Linear { .. } | Kernel::ChannelAffine { .. })
        })
    };
    for s in steps {
        if matches!(s.kernel, Kernel::Pure(readi_plan::ops::Pure::Activation(_))) {
            assert!(!fusable(s.inputs[0]), "{} was not fused", s.path);
        }
    }
}

/// A transposed conv's weight in a conv's layout (`[out, in/groups, kh, kw]`), and a
/// conv1d's with the 2-D kernel height: errors naming the tensor, both shapes and the
/// layer's source line.
#[test]
fn conv_weights_of_the_wrong_layout_are_refused() {
    let spec = "tests/fixtures/ops/convs.readi";
    let (sources, out) = common::compile(spec, &[], None);
    let module = out.module.expect("module");
    let cases = [
        ("t2.weight", vec![4, 3, 3, 3], "[6, 2, 3, 3]", ":11:8"),
        ("c1.weight", vec![6, 4, 1, 3], "[6, 4, 3]", ":21:8"),
    ];
    for (name, shape, want, line) in cases {
        let mut weights = fixture("convs.weights.safetensors");
        let n = shape.iter().product();
        weights.tensors.insert(name.into(), (shape.clone(), vec![0.0; n]));
        let d = backend::compile(&module, &weights, "convs.weights.safetensors", &CompileOptions::default())
            .expect_err("a wrong shape");
        let text = sources.render_all(&d, false);
        let got = format!("{shape:?}");
        assert!(text.contains(name) && text.contains(want) && text.contains(&got), "{text}");
        assert!(text.contains(&format!("convs.readi{line}")), "{text}");
    }
}

/// pad (three modes, cropping), roll and every way of slicing against PyTorch:
/// tests/fixtures/ops/movement.readi on the inputs make_movement_fixtures.py wrote. Data
/// movement copies values, so they must be exactly torch's.
#[test]
fn movement_matches_pytorch() {
    let spec = "tests/fixtures/ops/movement.readi";
    let (sources, out) = common::compile(spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let none = WeightSet::default();
    let (plan, _) = backend::compile(&module, &none, "none", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let io = fixture("movement.io.safetensors");
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let outputs = Session::new(Arc::new(plan), 2).expect("session").run(&inputs).expect("runs");
    assert_eq!(outputs.len(), io.tensors.keys().filter(|k| k.starts_with("output.")).count());
    for (name, t) in &outputs {
        let (shape, want) = &io.tensors[&format!("output.{name}")];
        assert_eq!(&t.shape, shape, "shape of {name}");
        assert_eq!(&t.data, want, "{name}");
    }
}

/// torchvision Swin-T's relative position bias (the bias table at the real int64
/// `relative_position_index` buffer) and its shifted-window attention mask (built in the
/// spec from `arange`, comparisons and `where`) equal torch's, and both are constants: the
/// plan only adds them, one step each; the rows of a model input picked at the index are
/// one `index_select` step holding the index.
#[test]
fn swin_relative_position_bias_and_attention_mask_match_torchvision() {
    let plan = compile("tests/fixtures/ops/swin_pieces.readi", "swin_pieces.weights.safetensors");
    let m = &plan.manifest;
    let kernels: Vec<&Kernel> = m.steps.iter().map(|s| &s.kernel).collect();
    let [
        Kernel::Pure(Pure::Binary(readi_plan::ops::BinaryOp::Add)),
        Kernel::Pure(Pure::Binary(readi_plan::ops::BinaryOp::Add)),
        Kernel::Pure(Pure::IndexSelect(pick)),
    ] = &kernels[..]
    else {
        panic!("the constants are not folded: {:#?}", m.steps.iter().map(|s| &s.path).collect::<Vec<_>>())
    };
    assert_eq!((pick.axis, pick.index.len()), (1, 2401));
    let name = "relative_position_index";
    let p = m.params.iter().find(|p| p.name == name).expect("the buffer in the parameter table");
    assert!(p.stored_as.contains("folded into `"), "{name}: {}", p.stored_as);
    for threads in [1, 2] {
        matches_pytorch(
            compile("tests/fixtures/ops/swin_pieces.readi", "swin_pieces.weights.safetensors"),
            "swin_pieces.io.safetensors",
            threads,
        );
    }
}

#[test]
fn conv3ds_match_pytorch() {
    for threads in [1, 2] {
        matches_pytorch(
            compile("tests/fixtures/ops/conv3d.readi", "conv3d.weights.safetensors"),
            "conv3d.io.safetensors",
            threads,
        );
    }
}

/// A conv3d takes its bias and a following activation into its epilogue; a BatchNorm3d
/// after it stays a channel affine (over the 5-D value), which takes the ReLU.
#[test]
fn conv3ds_take_their_bias_and_activation() {
    let plan = compile("tests/fixtures/ops/conv3d.readi", "conv3d.weights.safetensors");
    let steps = &plan.manifest.steps;
    let step = |name: &str| steps.iter().find(|s| s.path.starts_with(name)).unwrap_or_else(|| panic!("no {name}"));
    let Kernel::Conv3d { epilogue, .. } = &step("s1").kernel else { panic!("s1 is {:?}", step("s1")) };
    assert!(epilogue.shift.is_none() && epilogue.act.is_none(), "{epilogue:?}");
    assert!(matches!(step("b1").kernel, Kernel::ChannelAffine { ref epilogue, .. } if epilogue.act.is_some()));
    let Kernel::Conv3d { epilogue, .. } = &step("g").kernel else { panic!("g is {:?}", step("g")) };
    assert!(epilogue.shift.is_some() && epilogue.act.is_some(), "the bias or ReLU is not fused: {epilogue:?}");
    let Kernel::Conv3d { epilogue, .. } = &step("pw").kernel else { panic!("pw is {:?}", step("pw")) };
    assert!(epilogue.shift.is_some() && epilogue.act.is_none(), "{epilogue:?}");
    let convs = steps.iter().filter(|s| matches!(s.kernel, Kernel::Conv3d { .. })).count();
    assert_eq!(convs, 6, "{steps:?}");
}

/// A conv3d weight without its depth (a conv2d's), and in a transposed conv's layout
/// (`[in, out/groups, ...]`): errors naming the tensor, both shapes and the layer's line.
#[test]
fn conv3d_weights_of_the_wrong_layout_are_refused() {
    let spec = "tests/fixtures/ops/conv3d.readi";
    let (sources, out) = common::compile(spec, &[], None);
    let module = out.module.expect("module");
    let cases = [
        ("s1.weight", vec![8, 4, 3, 3], "[8, 4, 3, 3, 3]", ":8:8"),
        ("g.weight", vec![4, 3, 3, 3, 3], "[6, 2, 3, 3, 3]", ":15:7"),
    ];
    for (name, shape, want, line) in cases {
        let mut weights = fixture("conv3d.weights.safetensors");
        let n = shape.iter().product();
        weights.tensors.insert(name.into(), (shape.clone(), vec![0.0; n]));
        let d = backend::compile(&module, &weights, "conv3d.weights.safetensors", &CompileOptions::default())
            .expect_err("a wrong shape");
        let text = sources.render_all(&d, false);
        let got = format!("{shape:?}");
        assert!(text.contains(name) && text.contains(want) && text.contains(&got), "{text}");
        assert!(text.contains(&format!("conv3d.readi{line}")), "{text}");
    }
}

/// The inputs of case `case` of bev_pool.io.safetensors and torch's output.
fn bev_case<'a>(io: &'a WeightSet, case: &str) -> (Vec<Input<'a>>, &'a (Vec<usize>, Vec<f32>)) {
    let prefix = format!("{case}.input.");
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix(prefix.as_str()).map(|name| Input { name, data, shape }))
        .collect();
    assert_eq!(inputs.len(), 6, "{case}");
    (inputs, &io.tensors[&format!("{case}.output.bev")])
}

/// BEVFusion's view transform against a torch port of `get_geometry` + `bev_pool`: with
/// identity augmentations, then on the same session with the augmented calibration (the
/// cached geometry must follow it) and back; each at 1 and 2 threads, the same bits at
/// both. A singular intrinsics matrix is refused naming the step.
#[test]
fn lss_bev_pool_matches_bevfusion_and_follows_the_calibration() {
    let spec = "tests/fixtures/ops/bev_pool.readi";
    let (sources, out) = common::compile(spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let (plan, _) = backend::compile(&module, &WeightSet::default(), "none", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let kinds: Vec<&str> = plan.manifest.steps.iter().map(|s| s.kernel.name()).collect();
    assert_eq!(kinds, ["lss_bev_pool"]);
    let plan = Arc::new(plan);
    let io = fixture("bev_pool.io.safetensors");
    let mut first: Vec<Vec<f32>> = Vec::new();
    for threads in [1, 2] {
        let mut session = Session::new(Arc::clone(&plan), threads).expect("session");
        for (i, case) in ["identity", "augmented", "identity"].into_iter().enumerate() {
            let (inputs, (shape, want)) = bev_case(&io, case);
            let outputs = session.run(&inputs).expect("runs");
            let t = &outputs[0].1;
            assert_eq!(&t.shape, shape, "{case}");
            let mut worst = 0.0f32;
            for (j, (&g, &w)) in t.data.iter().zip(want).enumerate() {
                let err = (g - w).abs() / w.abs().max(1.0);
                assert!(err <= 1e-4, "{case} at {threads} threads, bev[{j}]: {g}, torch {w} (error {err:e})");
                worst = worst.max(err);
            }
            eprintln!("{case} at {threads} threads: max error vs torch {worst:e}");
            assert!(t.data.iter().filter(|v| **v != 0.0).count() > 20, "{case}: an empty grid");
            if threads == 1 {
                first.push(t.data.clone());
            } else {
                assert!(first[i].iter().zip(&t.data).all(|(a, b)| a.to_bits() == b.to_bits()), "{case}: threads");
            }
        }
        // A camera without a focal length: refused, naming the step and the camera.
        let (inputs, _) = bev_case(&io, "augmented");
        let (_, k) = &io.tensors["augmented.input.camera_intrinsics"];
        let mut singular = k.clone();
        singular[16] = 0.0;
        let inputs: Vec<Input<'_>> = inputs
            .into_iter()
            .map(|i| if i.name == "camera_intrinsics" { Input { data: &singular, ..i } } else { i })
            .collect();
        let e = session.run(&inputs).expect_err("a singular intrinsics matrix");
        assert!(
            matches!(&e, readi_runtime::exec::RunError::Step { detail, .. } if detail == "camera_intrinsics[0, 1] is singular"),
            "{e:?}"
        );
        assert!(e.to_string().starts_with("lss_bev_pool#0 cannot run on its inputs"), "{e}");
        // The session still runs a good calibration afterwards.
        let (inputs, (_, want)) = bev_case(&io, "identity");
        let outputs = session.run(&inputs).expect("runs after the error");
        assert!(outputs[0].1.data.iter().zip(want).all(|(g, w)| (g - w).abs() <= 1e-4 * w.abs().max(1.0)));
    }
}

/// A TransFusion head's query selection and every run-time index operator against
/// PyTorch (tests/fixtures/ops/index.readi, make_index_fixtures.py), at 1 and 2 threads:
/// top-k scores and indices, class and cell by `//` and `%`, the features gathered at
/// the cells three ways, one-hot classes, argmax / argmin, maximum / minimum, atan2,
/// floor division and remainder. Integer outputs must be torch's exactly, and the plan
/// records them as i64 (a comparison as bool).
#[test]
fn run_time_indices_match_pytorch() {
    use readi_plan::DType;
    let spec = "tests/fixtures/ops/index.readi";
    let (sources, out) = common::compile(spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let (plan, _) = backend::compile(&module, &WeightSet::default(), "none", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let kinds: Vec<&str> = plan.manifest.steps.iter().map(|s| s.kernel.name()).collect();
    for k in ["topk", "gather", "take_along_dim", "index_select", "one_hot", "argmax", "argmin", "where"] {
        assert!(kinds.contains(&k), "no `{k}` step in {kinds:?}");
    }
    assert!(
        plan.manifest.steps.iter().any(|s| matches!(s.kernel, Kernel::Pure(Pure::IndexSelectAt(_)))),
        "index_select at the cells reads them at run time"
    );
    let dtype = |name: &str| plan.manifest.outputs.iter().find(|o| o.name == name).expect("an output").dtype;
    for name in ["indices", "classes", "cells", "labels", "best_class", "coldest", "class_floor"] {
        assert_eq!(dtype(name), DType::I64, "{name}");
    }
    assert_eq!(dtype("is_peak"), DType::Bool);
    assert_eq!(dtype("scores"), DType::F32);
    let integer: Vec<String> =
        plan.manifest.outputs.iter().filter(|o| o.dtype != DType::F32).map(|o| o.name.clone()).collect();
    let plan = Arc::new(plan);
    let io = fixture("index.io.safetensors");
    for threads in [1, 2] {
        let inputs: Vec<Input<'_>> = io
            .tensors
            .iter()
            .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
            .collect();
        let outputs = Session::new(plan.clone(), threads).expect("session").run(&inputs).expect("runs");
        assert_eq!(outputs.len(), io.tensors.keys().filter(|k| k.starts_with("output.")).count());
        for (name, t) in &outputs {
            let (shape, want) = &io.tensors[&format!("output.{name}")];
            assert_eq!(&t.shape, shape, "shape of {name}");
            if integer.contains(name)
                || ["gathered", "taken", "selected", "scores", "smallest"].contains(&name.as_str())
            {
                // Indices, and values copied at them: exactly torch's.
                assert_eq!(&t.data, want, "{name} at {threads} threads");
                continue;
            }
            for (i, (&g, &w)) in t.data.iter().zip(want).enumerate() {
                let err = (g - w).abs() / w.abs().max(1.0);
                assert!(err <= 1e-5, "{name}[{i}]: {g}, torch {w} (error {err:e}) at {threads} threads");
            }
        }
    }
}

/// An index computed at run time that is out of range fails the run at the step that
/// reads it, naming the value: a crafted input cannot make `gather` read past its data.
#[test]
fn a_run_time_index_out_of_range_is_a_step_error() {
    use readi_runtime::exec::RunError;
    let text = "model m {\n  input x: f32[1, 5]\n  input i: f32[1, 3]\n  output y = gather(x, 1, to(i, i64))\n  \
                output z = one_hot(to(i, i64), 5)\n}\n";
    let (sources, out) = common::compile_text("gather.readi", text, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let (plan, _) = backend::compile(&module, &WeightSet::default(), "none", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let gather_path = plan.manifest.steps.iter().find(|s| s.kernel.name() == "gather").expect("a gather").path.clone();
    let mut s = Session::new(Arc::new(plan), 1).expect("session");
    let x = [10.0, 11.0, 12.0, 13.0, 14.0];
    let run = |s: &mut Session, i: &[f32]| {
        s.run(&[Input { name: "x", data: &x, shape: &[1, 5] }, Input { name: "i", data: i, shape: &[1, 3] }])
    };
    let y = run(&mut s, &[4.0, 0.0, 2.0]).expect("in range");
    assert_eq!(y[0].1.data, [14.0, 10.0, 12.0]);
    for (i, want) in [([0.0, 5.0, 1.0], "index 5 (at flat position 1) is out of range"), ([-1.0, 0.0, 0.0], "index -1")]
    {
        let e = run(&mut s, &i).expect_err("out of range");
        let RunError::Step { step, detail } = &e else { panic!("{e:?}") };
        assert_eq!(step, &gather_path);
        assert!(detail.contains(want), "{e}");
    }
}
