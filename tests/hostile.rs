//! Hostile plan files, input files and flags, as a user of the `readi` binary would try
//! them: each gets an error naming the file and the problem and exit status 1, never a
//! panic, an abort or a hang.
//!
//! Hostile plans are a valid plan (tests/cases/ok/all_ops.readi with seeded weights)
//! whose manifest is edited and written back with a correct checksum, as an attacker
//! would: the checksum guards against accidents only.

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;

use readi_compiler::backend::{self, CompileOptions};
use readi_runtime::plan::{Manifest, Plan};

use common::readi;

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A user error: exit status 1 and a message on stderr (not a panic: that is status 3, an
/// abort a signal).
#[track_caller]
fn refused(o: &Output) -> String {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(1), "expected exit status 1\nstdout: {}\nstderr: {err}", stdout(o));
    assert!(err.starts_with("error: ") || err.contains("\nerror: "), "{err}");
    err
}

/// A directory of its own for each test.
fn temp_dir(tag: &str) -> common::Scratch {
    common::Scratch::new(&format!("hostile-{tag}"))
}

fn s(p: &Path) -> String {
    p.to_str().expect("utf-8 path").to_string()
}

/// The manifest and tensor data of tests/cases/ok/all_ops.readi (every kernel; inputs
/// `img: [N, 4, 16, 16]` and optional `seq_in: [N, 10, 32]`) with seeded weights.
fn all_ops() -> (Manifest, Vec<Vec<f32>>) {
    let (sources, out) = common::compile("tests/cases/ok/all_ops.readi", &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let weights = backend::seeded_weights(&module.graph, 3);
    let plan = backend::compile(&module, &weights, "seeded", &CompileOptions::default()).expect("compiles").0;
    let tensors = (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect();
    (plan.manifest, tensors)
}

/// A plan file of `m` and `tensors` as `Plan::write` lays it out (format version,
/// manifest, CRC-32 of the manifest text and the tensors' bytes), without the checks
/// `Plan::new` makes: what a hand-edited file looks like.
fn plan_bytes(m: &Manifest, tensors: &[Vec<f32>]) -> Vec<u8> {
    let json = serde_json::to_string(m).expect("manifest as JSON");
    let stored: Vec<(String, Vec<usize>, Vec<u8>)> = m
        .tensors
        .iter()
        .zip(tensors)
        .map(|(spec, t)| (spec.name.clone(), spec.shape.clone(), t.iter().flat_map(|v| v.to_le_bytes()).collect()))
        .collect();
    common::plan_file_bytes(&m.format_version.to_string(), json, &stored)
}

/// Writes all_ops's plan with its manifest edited by `edit` to `dir/name`.
fn hostile_plan(dir: &Path, name: &str, edit: impl FnOnce(&mut Manifest)) -> PathBuf {
    let (mut m, tensors) = all_ops();
    edit(&mut m);
    let path = dir.join(name);
    std::fs::write(&path, plan_bytes(&m, &tensors)).expect("write plan");
    path
}

#[test]
fn the_unedited_plan_is_accepted() {
    // The helpers write what Plan::write writes: the edits below are the only fault.
    let (m, tensors) = all_ops();
    let dir = temp_dir("ok");
    let path = dir.join("ok.plan");
    std::fs::write(&path, plan_bytes(&m, &tensors)).expect("write");
    let plan = Plan::load(&path).expect("loads");
    assert_eq!(plan.manifest, m);
    let o = readi(&["inspect", &s(&path)]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn names_from_plans_are_printed_escaped() {
    let dir = temp_dir("escape");
    // Clear the screen, then a line that looks like readi's own output.
    let evil = "img\u{1b}[2J\nerror: all good";
    let path = hostile_plan(&dir, "escape.plan", |m| {
        m.model = "m\u{1b}]0;title\u{7}".into();
        m.inputs[0].name = evil.into();
        m.steps[0].path = "conv\u{1b}[31m".into();
    });
    let o = readi(&["inspect", &s(&path), "--verbose"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(!out.contains('\u{1b}') && !out.contains('\u{7}'), "raw escape sequences in: {out:?}");
    assert!(out.contains("model m\\u{1b}]0;title\\u{7}("), "{out}");
    assert!(out.contains("  img\\u{1b}[2J\\nerror: all good: f32[N, 4, 16, 16]"), "{out}");
    assert!(out.contains("conv\\u{1b}[31m"), "{out}");
    // In an error message too: the required input is not given.
    let err = refused(&readi(&["run", &s(&path)]));
    assert!(!err.contains('\u{1b}'), "{err:?}");
    assert!(err.contains("input `img\\u{1b}[2J\\nerror: all good` is required"), "{err}");
}

#[test]
fn symbols_in_shapes_are_printed_escaped() {
    // A shape's symbol is refused (symbols must be declared identifiers), and the error
    // that shows it must not carry its escape sequences to the terminal.
    let dir = temp_dir("escape-sym");
    let evil = "\u{1b}]0;owned\u{7}\u{1b}[2J";
    let path = hostile_plan(&dir, "sym.plan", |m| {
        let v = m.inputs[0].value;
        m.values[v].shape[0] = readi_runtime::plan::Dim::symbol(evil);
    });
    let err = refused(&readi(&["inspect", &s(&path)]));
    assert!(!err.contains('\u{1b}') && !err.contains('\u{7}'), "{err:?}");
    assert!(err.contains("\\u{1b}]0;owned\\u{7}\\u{1b}[2J"), "{err}");
}

/// The unedited all_ops plan at `dir/ok.plan`.
fn ok_plan(dir: &Path) -> PathBuf {
    hostile_plan(dir, "ok.plan", |_| {})
}

#[test]
fn a_batch_over_the_memory_limit_is_refused_before_allocating() {
    let dir = temp_dir("budget");
    let path = ok_plan(&dir);
    // 10^9 images of 4x16x16 floats: terabytes, refused by the default limit.
    let err = refused(&readi(&["bench", &s(&path), "--batch", "1000000000", "--runs", "1", "--warmup", "0"]));
    assert!(err.contains("over the limit of"), "{err}");
    assert!(err.contains("N = 1000000000") && err.contains("largest: "), "{err}");
    // The largest parts are named with their bytes.
    assert!(err.contains("bytes)"), "{err}");
    // A batch whose sizes overflow a 64-bit byte count.
    let err = refused(&readi(&["bench", &s(&path), "--batch", "18446744073709551615", "--runs", "1"]));
    assert!(err.contains("does not fit in memory"), "{err}");
    // A small limit refuses batch 1 too, in run and bench.
    let err = refused(&readi(&["bench", &s(&path), "--max-memory", "1K", "--runs", "1"]));
    assert!(err.contains("over the limit of 1.0 KiB (1024 bytes)"), "{err}");
    let o = readi(&["bench", &s(&path), "--max-memory", "64M", "--runs", "1", "--warmup", "0"]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn inspect_shows_the_recorded_footprint_and_the_limit() {
    let dir = temp_dir("footprint");
    let path = ok_plan(&dir);
    let o = readi(&["inspect", &s(&path), "--max-memory", "1G"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("memory at batch 1: "), "{out}");
    assert!(out.contains("memory limit 1.0 GiB (1073741824 bytes): batches up to "), "{out}");
    // A plan written before footprints were recorded loads and says so.
    let old = hostile_plan(&dir, "old.plan", |m| m.footprint = None);
    let o = readi(&["inspect", &s(&old)]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("memory: not recorded in the plan"), "{}", stdout(&o));
}

#[test]
fn a_huge_slot_count_is_refused_at_load() {
    let dir = temp_dir("slots");
    let path = hostile_plan(&dir, "slots.plan", |m| m.slots = 1 << 36);
    for cmd in ["inspect", "run", "bench"] {
        let err = refused(&readi(&[cmd, &s(&path)]));
        assert!(err.contains("activation buffers for") && err.contains("at most one per value"), "{err}");
    }
}

#[test]
fn a_value_no_step_writes_takes_no_memory() {
    // A huge value in a buffer that no step writes: nothing reads it, nothing is allocated.
    let dir = temp_dir("unread");
    let path = hostile_plan(&dir, "unread.plan", |m| {
        let slot = match m.values.iter().find_map(|v| match v.storage {
            readi_runtime::plan::Storage::Slot(s) => Some(s),
            _ => None,
        }) {
            Some(s) => s,
            None => panic!("a slot"),
        };
        let huge = readi_runtime::plan::Dim::from(1usize << 34);
        m.values.push(readi_runtime::plan::ValueSpec {
            shape: vec![huge.clone(), huge],
            storage: readi_runtime::plan::Storage::Slot(slot),
        });
    });
    let o = readi(&["bench", &s(&path), "--runs", "1", "--warmup", "0", "--max-memory", "64M"]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn zero_and_huge_counts_are_refused() {
    let dir = temp_dir("counts");
    let path = ok_plan(&dir);
    for (flag, value, want) in [
        ("--batch", "0", "at least 1"),
        ("--runs", "0", "at least 1"),
        ("--threads", "0", "1 to 256"),
        ("--threads", "100000", "1 to 256"),
        ("--max-memory", "0", "more than 0"),
        ("--max-memory", "12X", "unknown unit"),
    ] {
        let o = readi(&["bench", &s(&path), flag, value]);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{flag} {value}: {err}");
        assert!(err.contains(want), "{flag} {value}: {err}");
    }
    let o = readi(&["run", &s(&path), "--threads", "0"]);
    assert!(stderr(&o).contains("1 to 256"), "{}", stderr(&o));
}

/// A plan of one step: input `x` of `shape` (`None`: the batch symbol `N`), the step's
/// `kernel` writing `out` into buffer 0, the output `y`; `tensors` its stored tensors.
fn one_step(
    x: &[Option<usize>],
    kernel: readi_runtime::plan::Kernel,
    out: &[Option<usize>],
    tensors: &[(&str, Vec<usize>)],
) -> (Manifest, Vec<Vec<f32>>) {
    use readi_runtime::plan::{Dim, FORMAT_VERSION, InputSpec, OutputSpec, Step, Storage, TensorSpec, ValueSpec};
    let dims = |s: &[Option<usize>]| -> Vec<Dim> { s.iter().map(|d| d.map_or(Dim::symbol("N"), Dim::from)).collect() };
    let m = Manifest {
        format_version: FORMAT_VERSION,
        model: "one_step".into(),
        model_params: Vec::new(),
        symbols: vec!["N".into()],
        inputs: vec![InputSpec { name: "x".into(), shape: dims(x), modality: None, optional: false, value: 0 }],
        outputs: vec![OutputSpec::f32("y", 1)],
        values: vec![
            ValueSpec { shape: dims(x), storage: Storage::Input(0) },
            ValueSpec { shape: dims(out), storage: Storage::Slot(0) },
        ],
        steps: vec![Step { path: "the\u{1b}step".into(), kernel, inputs: vec![0], output: 1 }],
        slots: 1,
        tensors: tensors.iter().map(|(n, s)| TensorSpec::f32(n.to_string(), s.clone())).collect(),
        params: Vec::new(),
        variants: Vec::new(),
        conditions: None,
        footprint: None,
    };
    let data = tensors.iter().map(|(_, s)| vec![0.5; s.iter().product()]).collect();
    (m, data)
}

/// Writes a plan and returns `readi run`'s refusal of it, with `x` given at batch 1 of
/// `x_shape` (from an .npy file), so that any check (load, bind, kernel) can be reached.
fn run_refused(dir: &Path, name: &str, plan: (Manifest, Vec<Vec<f32>>), x_shape: &[usize]) -> String {
    let path = dir.join(name);
    std::fs::write(&path, plan_bytes(&plan.0, &plan.1)).expect("write plan");
    let x = dir.join(format!("{name}.x.npy"));
    write_npy(&x, x_shape);
    refused(&readi(&["run", &s(&path), "--input", &format!("x={}", s(&x))]))
}

/// A .npy file of f32 zeros of `shape` (version 1.0 header).
fn write_npy(path: &Path, shape: &[usize]) {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    let tuple = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {tuple}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend(std::iter::repeat_n(0u8, 4 * shape.iter().product::<usize>()));
    std::fs::write(path, bytes).expect("write npy");
}

#[test]
fn a_conv_algorithm_that_does_not_fit_its_layer_is_refused() {
    use readi_plan::ops::ConvAlgo;
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("algo");
    // all_ops's conv is 3x1, stride 2x1, two input channels per group: none of these fit.
    for algo in [ConvAlgo::Depthwise, ConvAlgo::Winograd2, ConvAlgo::Winograd4, ConvAlgo::Gemm1x1] {
        let path = hostile_plan(&dir, "algo.plan", |m| {
            if let Kernel::Conv2d { algo: a, .. } = &mut m.steps[0].kernel {
                *a = algo;
            }
        });
        let err = refused(&readi(&["run", &s(&path)]));
        assert!(err.contains("step 0 (`conv (+bn, relu#0)`)"), "{algo}: {err}");
        assert!(err.contains(&format!("conv algorithm `{algo}` cannot compute this layer")), "{algo}: {err}");
    }
}

#[test]
fn a_crafted_lora_branch_is_refused() {
    use readi_runtime::plan::{Kernel, LoraSpec, MAX_LORA_RANK};
    let dir = temp_dir("lora");
    // all_ops's first step is a grouped conv: no fused branch, whatever its tensors. Its
    // fc (a linear layer) gets branches with tensor indices out of range, rank 0, a rank
    // over the bound, tensors of the wrong size and an `A` marked raw. (A raw conv `A` of
    // the wrong length: tests/variants.rs, `a_raw_winograd_lora_a_is_packed_for_each_runs_variant`.)
    type Edit = fn(&mut readi_runtime::plan::Manifest);
    let cases: [(Edit, &str); 6] = [
        (
            |m| {
                if let Kernel::Conv2d { lora, weight, .. } = &mut m.steps[0].kernel {
                    *lora = Some(LoraSpec { a: *weight, b: *weight, rank: 1, a_raw: false });
                }
            },
            "needs one group",
        ),
        (
            |m| {
                let n = m.tensors.len();
                let fc = m.steps.iter_mut().find(|s| matches!(s.kernel, Kernel::Linear { .. })).expect("fc");
                if let Kernel::Linear { lora, .. } = &mut fc.kernel {
                    *lora = Some(LoraSpec { a: n, b: 0, rank: 2, a_raw: false });
                }
            },
            "reads tensor",
        ),
        (
            |m| {
                let fc = m.steps.iter_mut().find(|s| matches!(s.kernel, Kernel::Linear { .. })).expect("fc");
                if let Kernel::Linear { lora, weight, .. } = &mut fc.kernel {
                    *lora = Some(LoraSpec { a: *weight, b: *weight, rank: 0, a_raw: false });
                }
            },
            "LoRA rank 0",
        ),
        (
            |m| {
                let fc = m.steps.iter_mut().find(|s| matches!(s.kernel, Kernel::Linear { .. })).expect("fc");
                if let Kernel::Linear { lora, weight, .. } = &mut fc.kernel {
                    *lora = Some(LoraSpec { a: *weight, b: *weight, rank: MAX_LORA_RANK + 1, a_raw: false });
                }
            },
            "it must be 1 to",
        ),
        (
            |m| {
                let fc = m.steps.iter_mut().find(|s| matches!(s.kernel, Kernel::Linear { .. })).expect("fc");
                if let Kernel::Linear { lora, weight, .. } = &mut fc.kernel {
                    *lora = Some(LoraSpec { a: *weight, b: *weight, rank: 3, a_raw: false });
                }
            },
            "LoRA A `",
        ),
        (
            // A raw `A` is for convs (whose algorithm the runtime packs it for).
            |m| {
                let fc = m.steps.iter_mut().find(|s| matches!(s.kernel, Kernel::Linear { .. })).expect("fc");
                if let Kernel::Linear { lora, weight, .. } = &mut fc.kernel {
                    *lora = Some(LoraSpec { a: *weight, b: *weight, rank: 1, a_raw: true });
                }
            },
            "cannot be stored raw",
        ),
    ];
    for (i, (edit, want)) in cases.into_iter().enumerate() {
        let path = hostile_plan(&dir, &format!("lora{i}.plan"), edit);
        let err = refused(&readi(&["run", &s(&path)]));
        assert!(err.contains(want), "case {i}: {err}");
    }
}

#[test]
fn a_crafted_merge_on_switch_conv_is_refused() {
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("switch");
    // all_ops's conv merged on switch, its weight swapped for the fc's (not the raw
    // weight's length). (A raw weight read as packed, a packed LoRA A on a switched conv:
    // tests/variants.rs, `crafted_merge_on_switch_plans_are_refused`.)
    let path = hostile_plan(&dir, "switch.plan", |m| {
        let fc = m.steps.iter().find_map(|s| match s.kernel {
            Kernel::Linear { weight, .. } => Some(weight),
            _ => None,
        });
        if let (Kernel::Conv2d { switch, weight, .. }, Some(fc)) = (&mut m.steps[0].kernel, fc) {
            (*switch, *weight) = (true, fc);
        }
    });
    let err = refused(&readi(&["run", &s(&path)]));
    assert!(err.contains("step 0 (`conv (+bn, relu#0)`)") && err.contains("`raw` needs"), "{err}");
}

#[test]
fn a_crafted_adapter_is_refused() {
    use readi_plan::ops::Activation;
    use readi_runtime::plan::{AdapterSpec, Kernel};
    let dir = temp_dir("adapter");
    // all_ops's first step is a conv: an adapter on it with tensor indices out of range,
    // no bottleneck, one wider than the conv, and tensors of the wrong size.
    type Edit = fn(&mut readi_runtime::plan::Manifest);
    fn set(m: &mut readi_runtime::plan::Manifest, f: fn(usize, usize) -> AdapterSpec) {
        let n = m.tensors.len();
        if let Kernel::Conv2d { adapter, weight, .. } = &mut m.steps[0].kernel {
            *adapter = Some(f(*weight, n));
        }
    }
    let cases: [(Edit, &str); 4] = [
        (
            |m| set(m, |w, n| AdapterSpec { down: w, down_bias: w, up: n, up_bias: w, mid: 1, act: Activation::Relu }),
            "reads tensor",
        ),
        (
            |m| set(m, |w, _| AdapterSpec { down: w, down_bias: w, up: w, up_bias: w, mid: 0, act: Activation::Relu }),
            "adapter bottleneck of 0 channels",
        ),
        (
            |m| {
                set(m, |w, _| AdapterSpec {
                    down: w,
                    down_bias: w,
                    up: w,
                    up_bias: w,
                    mid: 1 << 20,
                    act: Activation::Relu,
                })
            },
            "it must be 1 to the conv's",
        ),
        (
            |m| set(m, |w, _| AdapterSpec { down: w, down_bias: w, up: w, up_bias: w, mid: 1, act: Activation::Gelu }),
            "adapter down `",
        ),
    ];
    for (i, (edit, want)) in cases.into_iter().enumerate() {
        let path = hostile_plan(&dir, &format!("adapter{i}.plan"), edit);
        let err = refused(&readi(&["run", &s(&path)]));
        assert!(err.contains(want) && err.contains("step 0"), "case {i}: {err}");
    }
}

#[test]
fn an_input_declared_unlike_its_value_is_refused() {
    let dir = temp_dir("declared");
    let path = hostile_plan(&dir, "declared.plan", |m| {
        m.inputs[0].shape[3] = readi_runtime::plan::Dim::from(8usize);
    });
    let err = refused(&readi(&["run", &s(&path)]));
    assert!(err.contains("input `img` is declared as [N, 4, 16, 8] but its value has shape [N, 4, 16, 16]"), "{err}");
}

#[test]
fn a_conv_kernel_larger_than_its_padded_input_is_refused() {
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("window");
    let path = hostile_plan(&dir, "window.plan", |m| {
        if let Kernel::Conv2d { conv, .. } = &mut m.steps[0].kernel {
            conv.window.kernel = [40, 1];
        }
    });
    let err = refused(&readi(&["run", &s(&path)]));
    assert!(err.contains("step 0 (`conv (+bn, relu#0)`)") && err.contains("does not fit"), "{err}");
    // A conv of one step whose kernel is larger than its input, the output declared as
    // if it fitted.
    use readi_plan::ops::{Conv2d, ConvAlgo, Window2};
    let window = Window2 { kernel: [5, 5], stride: [1, 1], padding: [0, 0], dilation: [1, 1] };
    let conv = Conv2d { in_channels: 1, out_channels: 1, window, groups: 1 };
    let kernel = Kernel::Conv2d {
        conv,
        algo: ConvAlgo::Im2col,
        weight: 0,
        epilogue: Default::default(),
        lora: None,
        switch: false,
        adapter: None,
        residual: false,
        channel_scale: false,
    };
    let plan =
        one_step(&[None, Some(1), Some(3), Some(3)], kernel, &[None, Some(1), Some(1), Some(1)], &[("w", vec![25])]);
    let err = run_refused(&dir, "small.plan", plan, &[1, 1, 3, 3]);
    assert!(err.contains("step 0 (`the\\u{1b}step`)") && err.contains("does not fit"), "{err}");
}

#[test]
fn a_crafted_conv_transpose_is_refused() {
    use readi_plan::ops::{ConvTranspose2d, Window2};
    use readi_runtime::plan::{EpilogueSpec, Kernel};
    let dir = temp_dir("convt");
    // in 2, out 4, kernel 2, stride 2: [N, 2, 3, 3] to [N, 4, 6, 6]; weight [2, 4, 2, 2], bias [4].
    let plan = |edit: &dyn Fn(&mut ConvTranspose2d), weight: usize, bias: usize| {
        let window = Window2 { kernel: [2, 2], stride: [2, 2], padding: [0, 0], dilation: [1, 1] };
        let mut conv = ConvTranspose2d { in_channels: 2, out_channels: 4, window, output_padding: [0, 0], groups: 1 };
        edit(&mut conv);
        let epilogue = EpilogueSpec { shift: Some(1), ..EpilogueSpec::default() };
        let kernel = Kernel::ConvTranspose2d { conv, weight: 0, epilogue };
        let tensors = [("w", vec![weight]), ("b", vec![bias])];
        one_step(&[None, Some(2), Some(3), Some(3)], kernel, &[None, Some(4), Some(6), Some(6)], &tensors)
    };
    // The unedited plan runs, so each refusal below is its edit's.
    let (m, data) = plan(&|_| {}, 32, 4);
    let path = dir.join("ok.plan");
    std::fs::write(&path, plan_bytes(&m, &data)).expect("write plan");
    let x = dir.join("x.npy");
    write_npy(&x, &[1, 2, 3, 3]);
    let o = readi(&["run", &s(&path), "--input", &format!("x={}", s(&x))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let x_shape = [1, 2, 3, 3];
    let err = run_refused(&dir, "weight.plan", plan(&|_| {}, 31, 4), &x_shape);
    assert!(err.contains("step 0 (`the\\u{1b}step`)"), "{err}");
    assert!(
        err.contains("conv_transpose2d weight `w` has 31 values (shape [31]), it needs 32 ([2, 4, 2, 2])"),
        "{err}"
    );
    let err = run_refused(&dir, "bias.plan", plan(&|_| {}, 32, 3), &x_shape);
    assert!(err.contains("epilogue tensor `b` has 3 values for 4 channels"), "{err}");
    let err = run_refused(&dir, "stride.plan", plan(&|c| c.window.stride = [0, 2], 32, 4), &x_shape);
    assert!(err.contains("stride 0x2, dilation 1: each must be at least 1"), "{err}");
    let err = run_refused(&dir, "outpad.plan", plan(&|c| c.output_padding = [2, 0], 32, 4), &x_shape);
    assert!(err.contains("output_padding 2x0 must be smaller than either stride 2 or dilation 1"), "{err}");
    let err = run_refused(&dir, "groups.plan", plan(&|c| c.groups = 3, 32, 4), &x_shape);
    assert!(err.contains("groups=3 must divide both 2 input and 4 output channels"), "{err}");
    // The output declared one row taller than the layer makes.
    let err = run_refused(&dir, "size.plan", plan(&|c| c.output_padding = [1, 0], 32, 4), &x_shape);
    assert!(
        err.contains("its output has shape [N, 4, 6, 6], but conv_transpose2d of its inputs gives [N, 4, 7, 6]"),
        "{err}"
    );
}

#[test]
fn a_crafted_conv3d_is_refused() {
    use readi_plan::ops::{Conv3d, Window3};
    use readi_runtime::plan::{EpilogueSpec, Kernel};
    let dir = temp_dir("conv3d");
    // in 2, out 4, kernel 2, stride 2: [N, 2, 4, 4, 4] to [N, 4, 2, 2, 2]; weight [4, 2, 2, 2, 2], bias [4].
    let x5 = [None, Some(2), Some(4), Some(4), Some(4)];
    let plan = |edit: &dyn Fn(&mut Conv3d), x: &[Option<usize>], weight: usize, bias: usize| {
        let window = Window3 { kernel: [2; 3], stride: [2; 3], padding: [0; 3], dilation: [1; 3] };
        let mut conv = Conv3d { in_channels: 2, out_channels: 4, window, groups: 1 };
        edit(&mut conv);
        let epilogue = EpilogueSpec { shift: Some(1), ..EpilogueSpec::default() };
        let kernel = Kernel::Conv3d { conv, weight: 0, epilogue };
        let tensors = [("w", vec![weight]), ("b", vec![bias])];
        one_step(x, kernel, &[None, Some(4), Some(2), Some(2), Some(2)], &tensors)
    };
    // The unedited plan runs, so each refusal below is its edit's.
    let (m, data) = plan(&|_| {}, &x5, 64, 4);
    let path = dir.join("ok.plan");
    std::fs::write(&path, plan_bytes(&m, &data)).expect("write plan");
    let x = dir.join("x.npy");
    write_npy(&x, &[1, 2, 4, 4, 4]);
    let o = readi(&["run", &s(&path), "--input", &format!("x={}", s(&x))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let x_shape = [1, 2, 4, 4, 4];
    let err = run_refused(&dir, "weight.plan", plan(&|_| {}, &x5, 63, 4), &x_shape);
    assert!(err.contains("step 0 (`the\\u{1b}step`)"), "{err}");
    assert!(err.contains("conv3d weight `w` has 63 values (shape [63]), it needs 64 ([4, 2, 2, 2, 2])"), "{err}");
    let err = run_refused(&dir, "bias.plan", plan(&|_| {}, &x5, 64, 3), &x_shape);
    assert!(err.contains("epilogue tensor `b` has 3 values for 4 channels"), "{err}");
    let err = run_refused(&dir, "stride.plan", plan(&|c| c.window.stride = [0, 2, 2], &x5, 64, 4), &x_shape);
    assert!(err.contains("stride 0x2x2, dilation 1: each must be at least 1"), "{err}");
    let err = run_refused(&dir, "groups.plan", plan(&|c| c.groups = 3, &x5, 64, 4), &x_shape);
    assert!(err.contains("groups=3 must divide both 2 input and 4 output channels"), "{err}");
    let err = run_refused(&dir, "rank.plan", plan(&|_| {}, &x5[..4], 64, 4), &x_shape[..4]);
    assert!(err.contains("conv3d expects a 5-D NCDHW tensor"), "{err}");
    // The output declared one slice shallower than the layer makes.
    let err = run_refused(&dir, "size.plan", plan(&|c| c.window.padding = [1, 0, 0], &x5, 64, 4), &x_shape);
    assert!(
        err.contains("its output has shape [N, 4, 2, 2, 2], but conv3d of its inputs gives [N, 4, 3, 2, 2]"),
        "{err}"
    );
}

#[test]
fn a_linear_with_zero_input_features_is_refused() {
    use readi_plan::ops::Linear;
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("linear0");
    let kernel = Kernel::Linear {
        linear: Linear { in_features: 0, out_features: 4 },
        weight: 0,
        epilogue: Default::default(),
        lora: None,
        panels: false,
    };
    let plan = one_step(&[None, Some(0)], kernel, &[None, Some(4)], &[("w", vec![0, 4])]);
    let err = run_refused(&dir, "linear0.plan", plan, &[1, 0]);
    assert!(err.contains("step 0 (`the\\u{1b}step`)"), "{err}");
    assert!(err.contains("linear from 0 to 4 features: both must be at least 1"), "{err}");
}

#[test]
fn an_upsample_of_an_empty_tensor_is_refused() {
    use readi_plan::ops::{Pure, Upsample, UpsampleMode};
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("upsample0");
    for mode in [UpsampleMode::Nearest, UpsampleMode::Bilinear] {
        let up = Upsample { size: [4, 4], scale: None, mode, align_corners: false };
        let plan = one_step(
            &[None, Some(2), Some(0), Some(3)],
            Kernel::Pure(Pure::Upsample(up)),
            &[None, Some(2), Some(4), Some(4)],
            &[],
        );
        let err = run_refused(&dir, "upsample0.plan", plan, &[1, 2, 0, 3]);
        assert!(err.contains("upsample0.plan: invalid plan at step 0 (`the\\u{1b}step`)"), "{err}");
        assert!(err.contains("upsample of an empty input [1, 2, 0, 3] to [1, 2, 4, 4]"), "{err}");
    }
}

#[test]
fn duplicate_output_names_are_refused() {
    let dir = temp_dir("outputs");
    let path = hostile_plan(&dir, "outputs.plan", |m| m.outputs[1].name = "pooled".into());
    let out = dir.join("out.safetensors");
    let err = refused(&readi(&["run", &s(&path), "--output", &s(&out)]));
    assert!(err.contains("output `pooled` is declared twice"), "{err}");
}

/// The manifest and tensors of tests/cases/ok/adapt_and_variants.readi with seeded
/// weights and two seeded variants: a plan with conditions.
fn with_conditions() -> (Manifest, Vec<Vec<f32>>) {
    let (sources, out) = common::compile("tests/cases/ok/adapt_and_variants.readi", &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let weights = backend::seeded_weights(&module.graph, 1);
    let keys = ["fog=0.03".to_string(), "gamma=0.25".to_string()];
    let variants = backend::seeded_variants(&module, &keys, 2);
    let (plan, _) = backend::compile_variants(&module, &weights, "seeded", &variants, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let tensors = (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect();
    (plan.manifest, tensors)
}

/// An edit of a manifest.
type Edit = dyn Fn(&mut Manifest);

#[test]
fn conditions_are_checked_at_load() {
    use readi_plan::conditions::KeySource;
    let dir = temp_dir("conditions");
    let cases: Vec<(&str, Box<Edit>)> = vec![
        (
            "reads input `camera`, which the plan does not have (its inputs: image, points)",
            Box::new(|m: &mut Manifest| {
                let c = m.conditions.as_mut().expect("conditions");
                for s in &mut c.selectors {
                    if let KeySource::Stat { input, .. } = &mut s.source {
                        *input = "camera".into();
                    }
                }
            }),
        ),
        (
            "the selector of axis `rain`: no such axis (the axes: gamma, fog)",
            Box::new(|m: &mut Manifest| m.conditions.as_mut().expect("conditions").selectors[0].axis = "rain".into()),
        ),
        (
            "arm 0 selects level 0.5, which the axis does not declare",
            Box::new(|m: &mut Manifest| {
                let c = m.conditions.as_mut().expect("conditions");
                let s = c.selectors.iter_mut().find(|s| !s.arms.is_empty()).expect("a selector with arms");
                s.arms[0].level = Some(0.5);
            }),
        ),
        (
            "axis `fog`: the name is not an identifier, or is declared twice",
            Box::new(|m: &mut Manifest| {
                let c = m.conditions.as_mut().expect("conditions");
                c.axes[0].name = "fog".into();
            }),
        ),
        (
            "the meld lambda of `radar`: no such modality",
            Box::new(|m: &mut Manifest| {
                let meld = m.conditions.as_mut().expect("conditions").meld.as_mut().expect("a meld rule");
                meld.weights[0].0 = "radar".into();
            }),
        ),
    ];
    let (m, tensors) = with_conditions();
    for (want, edit) in cases {
        let mut edited = m.clone();
        edit(&mut edited);
        let path = dir.join("conditions.plan");
        std::fs::write(&path, plan_bytes(&edited, &tensors)).expect("write plan");
        let err = refused(&readi(&["run", &s(&path), "--auto"]));
        assert!(err.contains("invalid plan manifest: ") && err.contains(want), "want `{want}`: {err}");
    }
}

/// A parameter's recorded owners (`owned_by`) are checked at load: a scope the plan's
/// conditions and inputs do not have is refused with the parameter's name, printed escaped.
#[test]
fn unknown_owning_scopes_are_refused_at_load() {
    let dir = temp_dir("owned-by");
    let (m, tensors) = with_conditions();
    let owned = m.params.iter().position(|p| p.owned_by.is_some()).expect("the variants own a parameter");
    let name = m.params[owned].name.clone();
    let cases: [(&str, String); 4] = [
        ("radar", format!("parameter `{name}`: owned by unknown scope `radar` (the plan's scopes: ")),
        ("missing=radar", "owned by unknown scope `missing=radar`".into()),
        ("fog=0.03", "owned by unknown scope `fog=0.03`".into()),
        ("\u{1b}[2J", "owned by unknown scope `\\u{1b}[2J`".into()),
    ];
    for (scope, want) in cases {
        let mut edited = m.clone();
        edited.params[owned].owned_by = Some(vec!["camera".into(), scope.into()]);
        let path = dir.join("owned.plan");
        std::fs::write(&path, plan_bytes(&edited, &tensors)).expect("write plan");
        let err = refused(&readi(&["inspect", &s(&path)]));
        assert!(err.contains("invalid plan manifest: ") && err.contains(&want), "want `{want}`: {err}");
        assert!(!err.contains('\u{1b}'), "{err:?}");
    }
    // The scopes a spec may name load: axes, modalities, `missing`, `missing=M`.
    let mut edited = m.clone();
    edited.params[owned].owned_by = Some(["fog", "camera", "missing", "missing=lidar"].map(String::from).to_vec());
    let path = dir.join("owned.plan");
    std::fs::write(&path, plan_bytes(&edited, &tensors)).expect("write plan");
    let o = readi(&["inspect", &s(&path)]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn metadata_no_selector_reads_is_refused() {
    let dir = temp_dir("meta");
    let (m, tensors) = with_conditions();
    let path = dir.join("meta.plan");
    std::fs::write(&path, plan_bytes(&m, &tensors)).expect("write plan");
    let err = refused(&readi(&["run", &s(&path), "--auto", "--meta", "weather.fog=0.05"]));
    assert!(
        err.contains("no selector reads metadata `weather.fog` (the plan's selectors read: `weather.fog_density`)"),
        "{err}"
    );
}

#[test]
fn an_output_flag_naming_no_output_is_refused() {
    let dir = temp_dir("output");
    let path = ok_plan(&dir);
    let x = dir.join("img.npy");
    write_npy(&x, &[1, 4, 16, 16]);
    let input = format!("img={}", s(&x));
    let file = dir.join("yy=out.npy");
    let err =
        refused(&readi(&["run", &s(&path), "--input", &input, "--output", &format!("yy={}", s(&dir.join("out.npy")))]));
    assert!(err.contains("the model has no output `yy` (its outputs: `pooled`, `tokens`, `avg`)"), "{err}");
    assert!(!dir.join("out.npy").exists() && !file.exists());
    // A known name writes that output; a path with `=` in its file name is a file.
    let o = readi(&["run", &s(&path), "--input", &input, "--output", &format!("avg={}", s(&dir.join("avg.npy")))]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.join("avg.npy").exists());
    let o = readi(&["run", &s(&path), "--input", &input, "--output", &s(&dir.join("all=outputs.safetensors"))]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.join("all=outputs.safetensors").exists());
}

#[test]
fn a_truncated_npy_input_is_reported_as_truncated() {
    let dir = temp_dir("truncated");
    let path = ok_plan(&dir);
    let x = dir.join("img.npy");
    write_npy(&x, &[1, 4, 16, 16]);
    let bytes = std::fs::read(&x).expect("read");
    std::fs::write(&x, &bytes[..bytes.len() - 100]).expect("write");
    let err = refused(&readi(&["run", &s(&path), "--input", &format!("img={}", s(&x))]));
    assert!(err.contains("img.npy: truncated .npy file"), "{err}");
    assert!(
        err.contains("its header declares shape [1, 4, 16, 16], 4096 bytes of data, but the file holds 3996"),
        "{err}"
    );
}

#[cfg(unix)]
#[test]
fn devices_and_directories_are_not_read_as_files() {
    let dir = temp_dir("devices");
    let path = ok_plan(&dir);
    // A plan that is a device, or a directory.
    let err = refused(&readi(&["inspect", "/dev/zero"]));
    assert!(err.contains("/dev/zero: not a regular file"), "{err}");
    let err = refused(&readi(&["run", &s(&dir)]));
    assert!(err.contains("not a regular file"), "{err}");
    // Inputs that are devices, whatever their name says.
    for name in ["zero.npy", "zero.safetensors"] {
        let link = dir.join(name);
        std::os::unix::fs::symlink("/dev/zero", &link).expect("symlink");
        let err = refused(&readi(&["run", &s(&path), "--input", &format!("img={}", s(&link))]));
        assert!(err.contains(&format!("{name}: it is not a regular file")), "{err}");
    }
    // An input file over the memory limit.
    let x = dir.join("img.npy");
    write_npy(&x, &[1, 4, 16, 16]);
    let err = refused(&readi(&["run", &s(&path), "--input", &format!("img={}", s(&x)), "--max-memory", "1K"]));
    assert!(err.contains("over the limit of 1024 bytes for this kind of file (--max-memory)"), "{err}");
}

#[test]
fn an_empty_tensor_with_huge_inner_axes_is_refused() {
    // [N, 0, 2^40, 2^40] holds no element, but a kernel multiplying its inner axes
    // would overflow: binding refuses it.
    use readi_plan::ops::{Activation, Pure};
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("empty-huge");
    let huge = 1usize << 40;
    let shape = [None, Some(0), Some(huge), Some(huge)];
    let plan = one_step(&shape, Kernel::Pure(Pure::Activation(Activation::Relu)), &shape, &[]);
    let path = dir.join("empty.plan");
    std::fs::write(&path, plan_bytes(&plan.0, &plan.1)).expect("write plan");
    let err = refused(&readi(&["bench", &s(&path), "--runs", "1", "--warmup", "0"]));
    assert!(err.contains("value 0 (input `x`) at N = 1 does not fit in memory"), "{err}");
}

#[test]
fn a_crafted_groupnorm_is_refused() {
    use readi_plan::ops::GroupNorm;
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("groupnorm");
    let x = [None, Some(6), Some(4), Some(4)];
    let gn = |num_groups, affine| GroupNorm { num_groups, num_channels: 6, eps: 1e-5, affine };
    // (norm, weight, bias, stored tensors, the refusal): tensors of the wrong size, a
    // missing bias on an affine norm, parameters on a plain one, groups that do not divide
    // the channels, a tensor index out of range.
    let six = || ("b", vec![6]);
    type Case = (GroupNorm, Option<usize>, Option<usize>, Vec<(&'static str, Vec<usize>)>, &'static str);
    let cases: [Case; 5] = [
        (
            gn(2, true),
            Some(0),
            Some(1),
            vec![("w", vec![5]), six()],
            "groupnorm tensor `w` has 5 values for 6 channels",
        ),
        (gn(2, true), Some(0), None, vec![("w", vec![6])], "groupnorm parameters do not match its `affine`"),
        (gn(2, false), Some(0), Some(1), vec![("w", vec![6]), six()], "groupnorm parameters do not match its `affine`"),
        (gn(4, true), Some(0), Some(1), vec![("w", vec![6]), six()], "6 channels do not divide into 4 groups"),
        (gn(3, true), Some(0), Some(7), vec![("w", vec![6]), six()], "reads tensor"),
    ];
    for (i, (norm, weight, bias, tensors, want)) in cases.into_iter().enumerate() {
        let plan = one_step(&x, Kernel::GroupNorm { norm, weight, bias }, &x, &tensors);
        let err = run_refused(&dir, &format!("groupnorm{i}.plan"), plan, &[1, 6, 4, 4]);
        assert!(err.contains("step 0 (`the\\u{1b}step`)") && err.contains(want), "case {i}: {err}");
    }
}

#[test]
fn a_crafted_index_out_of_range_is_refused() {
    use readi_plan::DType;
    use readi_plan::ops::{Fill, IndexSelect, Pure};
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("index");
    let take = |index: Vec<i64>| {
        Kernel::Pure(Pure::IndexSelect(IndexSelect { axis: 1, index_shape: vec![index.len()], index }))
    };
    // x: [N, 4]; an index of 4 (or -1) would read outside the axis.
    let plan = one_step(&[None, Some(4)], take(vec![0, 4]), &[None, Some(2)], &[]);
    let err = run_refused(&dir, "index.plan", plan, &[1, 4]);
    assert!(err.contains("index 4 (at flat position 1) is out of range for axis 1"), "{err}");
    let plan = one_step(&[None, Some(4)], take(vec![-1]), &[None, Some(1)], &[]);
    let err = run_refused(&dir, "negative.plan", plan, &[1, 4]);
    assert!(err.contains("index -1 (at flat position 0) is out of range"), "{err}");
    // The indices and the index shape disagree.
    let k = Kernel::Pure(Pure::IndexSelect(IndexSelect { axis: 1, index: vec![0, 1], index_shape: vec![3] }));
    let err = run_refused(&dir, "count.plan", one_step(&[None, Some(4)], k, &[None, Some(3)], &[]), &[1, 4]);
    assert!(err.contains("index_select has 2 indices for an index of shape [3]"), "{err}");
    // A constant generator is the compiler's: a plan step of one is refused.
    let fill = Kernel::Pure(Pure::Fill(Fill { shape: vec![1, 4], start: 0.0, step: 1.0, dtype: DType::F32 }));
    let err = run_refused(&dir, "fill.plan", one_step(&[None, Some(4)], fill, &[Some(1), Some(4)], &[]), &[1, 4]);
    assert!(err.contains("takes 0 tensor input(s), got 1"), "{err}");
}

/// A crafted `lss_bev_pool` step (one input instead of six; six that are one tensor; a
/// grid bound with a zero step) is refused at load with the step's name, never run.
#[test]
fn a_crafted_lss_bev_pool_is_refused() {
    use readi_plan::ops::{LssBevPool, Pure};
    use readi_runtime::plan::Kernel;
    let dir = temp_dir("bev");
    let op = LssBevPool {
        image_size: [64, 96],
        xbound: [-8.0, 8.0, 2.0],
        ybound: [-8.0, 8.0, 2.0],
        zbound: [-2.0, 2.0, 2.0],
        dbound: [2.0, 10.0, 2.0],
    };
    let x = [None, Some(2), Some(4), Some(4), Some(6)];
    let out = [None, Some(6), Some(8), Some(8)];
    let cases: [(LssBevPool, usize, &str); 3] = [
        (op.clone(), 1, "lss_bev_pool takes 6 tensor input(s), got 1"),
        (op.clone(), 6, "lss_bev_pool camera_intrinsics must have 4 axes"),
        (LssBevPool { xbound: [-8.0, 8.0, 0.0], ..op.clone() }, 6, "xbound needs a positive step"),
    ];
    for (k, (op, inputs, want)) in cases.into_iter().enumerate() {
        let mut plan = one_step(&x, Kernel::Pure(Pure::LssBevPool(op)), &out, &[]);
        plan.0.steps[0].inputs = vec![0; inputs];
        let err = run_refused(&dir, &format!("bev{k}.plan"), plan, &[1, 2, 4, 4, 6]);
        assert!(err.contains("the\\u{1b}step") && err.contains(want), "case {k}: {err}");
    }
}

/// A 1x1 conv step from one channel to `out` over its weight, tensor 0, with the flags of
/// its fused inputs.
fn pointwise_conv(out: i64, residual: bool, channel_scale: bool) -> readi_runtime::plan::Kernel {
    use readi_plan::ops::{Conv2d, ConvAlgo, Window2};
    let window = Window2 { kernel: [1, 1], stride: [1, 1], padding: [0, 0], dilation: [1, 1] };
    readi_runtime::plan::Kernel::Conv2d {
        conv: Conv2d { in_channels: 1, out_channels: out, window, groups: 1 },
        algo: ConvAlgo::Gemm1x1,
        weight: 0,
        epilogue: Default::default(),
        lora: None,
        switch: false,
        adapter: None,
        residual,
        channel_scale,
    }
}

#[test]
fn a_conv_residual_that_is_missing_or_misshapen_is_refused() {
    let dir = temp_dir("residual");
    let conv = |out: i64| pointwise_conv(out, true, false);
    // Flagged as adding a residual, but with one input.
    let plan =
        one_step(&[None, Some(1), Some(3), Some(3)], conv(1), &[None, Some(1), Some(3), Some(3)], &[("w", vec![1])]);
    let err = run_refused(&dir, "one.plan", plan, &[1, 1, 3, 3]);
    assert!(err.contains("step 0 (`the\\u{1b}step`)") && err.contains("takes 2 inputs, got 1"), "{err}");
    // A residual of one channel added to an output of two.
    let mut plan =
        one_step(&[None, Some(1), Some(3), Some(3)], conv(2), &[None, Some(2), Some(3), Some(3)], &[("w", vec![2])]);
    plan.0.steps[0].inputs = vec![0, 0];
    let err = run_refused(&dir, "shape.plan", plan, &[1, 1, 3, 3]);
    assert!(err.contains("residual input has shape [N, 1, 3, 3], not its output's [N, 2, 3, 3]"), "{err}");
}

#[test]
fn a_conv_channel_scale_that_is_missing_or_misshapen_is_refused() {
    let dir = temp_dir("channel_scale");
    let conv = pointwise_conv(1, false, true);
    let shape = [None, Some(1), Some(3), Some(3)];
    // Flagged as scaling its input's channels, but with one input.
    let plan = one_step(&shape, conv.clone(), &shape, &[("w", vec![1])]);
    let err = run_refused(&dir, "one.plan", plan, &[1, 1, 3, 3]);
    assert!(err.contains("step 0 (`the\\u{1b}step`)") && err.contains("takes 2 inputs, got 1"), "{err}");
    // A scale of the input's shape, not one value per channel.
    let mut plan = one_step(&shape, conv, &shape, &[("w", vec![1])]);
    plan.0.steps[0].inputs = vec![0, 0];
    let err = run_refused(&dir, "shape.plan", plan, &[1, 1, 3, 3]);
    assert!(err.contains("channel scale has shape [N, 1, 3, 3], not [N, C, 1, 1]"), "{err}");
}
