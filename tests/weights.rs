//! Binding weights: every problem is an error naming the tensor and showing the layer's
//! source line (rendered diagnostics are snapshots); f16/bf16 are converted; PyTorch's
//! `num_batches_tracked` counters are understood.

mod common;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_grammar::diag::SourceMap;
use safetensors::tensor::{Dtype, TensorView};

const SPEC: &str = "models/resnet18.readi";

fn module() -> (SourceMap, Module) {
    let (sources, out) = common::compile(SPEC, &[("num_classes", "10")], None);
    assert!(!out.diagnostics.has_errors());
    (sources, out.module.expect("module"))
}

/// Compiles with the given weights; returns the rendered diagnostics (errors or warnings).
fn attempt(weights: &WeightSet, allow_unused: bool) -> (bool, String) {
    let (sources, m) = module();
    match backend::compile(&m, weights, "r18.safetensors", &CompileOptions { allow_unused, ..Default::default() }) {
        Ok((_, warnings)) => (true, sources.render_all(&warnings, false)),
        Err(d) => (false, sources.render_all(&d, false)),
    }
}

fn seeded() -> WeightSet {
    backend::seeded_weights(&module().1.graph, 5)
}

#[test]
fn seeded_weights_compile_cleanly() {
    let (ok, text) = attempt(&seeded(), false);
    assert!(ok && text.is_empty(), "{text}");
}

#[test]
fn missing_tensor() {
    let mut w = seeded();
    w.tensors.remove("layer2.1.bn2.running_var");
    let (ok, text) = attempt(&w, false);
    assert!(!ok);
    insta::assert_snapshot!(text);
}

#[test]
fn misnamed_tensor_suggests_the_right_name() {
    let mut w = seeded();
    let t = w.tensors.remove("layer3.0.downsample.0.weight").expect("exists");
    w.tensors.insert("layer3.0.downsample.0.weights".into(), t);
    let (ok, text) = attempt(&w, false);
    assert!(!ok);
    insta::assert_snapshot!(text);
}

#[test]
fn wrong_shape() {
    let mut w = seeded();
    w.tensors.insert("fc.weight".into(), (vec![1000, 512], vec![0.0; 512_000]));
    let (ok, text) = attempt(&w, false);
    assert!(!ok);
    insta::assert_snapshot!(text);
}

#[test]
fn nan_in_a_tensor() {
    let mut w = seeded();
    let (_, data) = w.tensors.get_mut("layer1.1.conv2.weight").expect("exists");
    data[1234] = f32::NAN;
    let (ok, text) = attempt(&w, false);
    assert!(!ok);
    insta::assert_snapshot!(text);
}

#[test]
fn unexpected_tensor_is_an_error_or_a_warning() {
    let mut w = seeded();
    w.tensors.insert("aux_head.weight".into(), (vec![2], vec![0.0, 1.0]));
    let (ok, text) = attempt(&w, false);
    assert!(!ok);
    insta::assert_snapshot!("unexpected_tensor_error", text);
    let (ok, text) = attempt(&w, true);
    assert!(ok, "{text}");
    insta::assert_snapshot!("unexpected_tensor_warning", text);
}

/// Builds a safetensors file from (name, dtype, shape, bytes).
fn file(entries: &[(&str, Dtype, Vec<usize>, Vec<u8>)]) -> Vec<u8> {
    let views: Vec<(String, TensorView<'_>)> =
        entries.iter().map(|(n, d, s, b)| (n.to_string(), TensorView::new(*d, s.clone(), b).expect("view"))).collect();
    safetensors::serialize(views, None).expect("serialise")
}

#[test]
fn integer_weights_are_a_dtype_error() {
    let bytes = file(&[("fc.weight", Dtype::I32, vec![2], vec![0; 8])]);
    let d = WeightSet::from_safetensors("ints.safetensors", &bytes).expect_err("ints are not weights");
    let text = SourceMap::new().render_all(&d, false);
    assert!(text.contains("ints.safetensors: tensor `fc.weight` has dtype I32"), "{text}");
}

#[test]
fn truncated_weights_file_is_an_error() {
    let bytes = seeded().to_safetensors().expect("serialises");
    let d = WeightSet::from_safetensors("cut.safetensors", &bytes[..bytes.len() - 3]).expect_err("truncated");
    let text = SourceMap::new().render_all(&d, false);
    assert!(text.contains("cut.safetensors: not a valid safetensors file") && text.contains("truncated"), "{text}");
}

#[test]
fn half_precision_is_converted_and_counters_are_understood() {
    let w = seeded();
    let mut entries = Vec::new();
    for (name, (shape, data)) in &w.tensors {
        let bytes: Vec<u8> = data.iter().flat_map(|v| half::f16::from_f32(*v).to_le_bytes()).collect();
        entries.push((name.as_str(), Dtype::F16, shape.clone(), bytes));
    }
    // PyTorch's BatchNorm counters, as `model.state_dict()` saves them.
    entries.push(("bn1.num_batches_tracked", Dtype::I64, vec![], 7i64.to_le_bytes().to_vec()));
    let bytes = file(&entries);
    let set = WeightSet::from_safetensors("r18-f16.safetensors", &bytes).expect("f16 converts");
    let (a, b) = (&set.tensors["fc.weight"].1, &w.tensors["fc.weight"].1);
    let err = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(err > 0.0 && err < 1e-3, "f16 rounding error {err}");
    let (ok, text) = attempt(&set, false);
    assert!(ok, "{text}");
}

/// A model reading an int64 buffer (`buffer(..., dtype=i64)`) as an index.
const INDEX_SPEC: &str = "model m {
  input x: f32[N, 3, 4]
  table = parameter([5, 4])
  idx = buffer([3], dtype=i64)
  output y = x + index_select(table, 0, idx)
}
";

fn ints(v: &[i64]) -> Vec<u8> {
    v.iter().flat_map(|i| i.to_le_bytes()).collect()
}

fn floats(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Compiles INDEX_SPEC with a weights file of these entries: the plan, or the rendered
/// errors.
fn index_compile(entries: &[(&str, Dtype, Vec<usize>, Vec<u8>)]) -> Result<readi_runtime::plan::Plan, String> {
    let (sources, out) = common::compile_text("index.readi", INDEX_SPEC, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let set = WeightSet::from_safetensors("index.safetensors", &file(entries))
        .map_err(|d| SourceMap::new().render_all(&d, false))?;
    backend::compile(&module, &set, "index.safetensors", &CompileOptions::default())
        .map(|(p, _)| p)
        .map_err(|d| sources.render_all(&d, false))
}

fn table() -> (&'static str, Dtype, Vec<usize>, Vec<u8>) {
    ("table", Dtype::F32, vec![5, 4], floats(&(0..20).map(|i| i as f32).collect::<Vec<_>>()))
}

#[test]
fn an_int64_buffer_binds_by_name_and_indexes() {
    use readi_runtime::exec::{Input, Session};
    let plan = index_compile(&[table(), ("idx", Dtype::I64, vec![3], ints(&[4, 0, 2]))]).expect("compiles");
    // The lookup is folded: the plan only adds it to the input.
    assert_eq!(plan.manifest.steps.len(), 1, "{:?}", plan.manifest.steps);
    let x = vec![0.0f32; 12];
    let mut s = Session::new(std::sync::Arc::new(plan), 1).expect("session");
    let out = s.run(&[Input { name: "x", data: &x, shape: &[1, 3, 4] }]).expect("runs");
    let want: Vec<f32> = [4, 0, 2].iter().flat_map(|&r| (0..4).map(move |c| (r * 4 + c) as f32)).collect();
    assert_eq!(out[0].1.data, want);
}

#[test]
fn int64_buffers_are_checked_for_type_shape_and_range() {
    let float_idx = index_compile(&[table(), ("idx", Dtype::F32, vec![3], floats(&[0.0, 1.0, 2.0]))]);
    let e = float_idx.expect_err("a float tensor for an i64 buffer");
    assert!(e.contains("tensor `idx` in `index.safetensors` is float, but buffer `idx` needs int64"), "{e}");
    assert!(e.contains("index.readi:4:"), "{e}");
    let int_table = index_compile(&[
        ("table", Dtype::I64, vec![5, 4], ints(&[0; 20])),
        ("idx", Dtype::I64, vec![3], ints(&[0; 3])),
    ]);
    let e = int_table.expect_err("an int64 tensor for an f32 parameter");
    assert!(e.contains("tensor `table` in `index.safetensors` is int64, but parameter `table` needs f32"), "{e}");
    let e = index_compile(&[table(), ("idx", Dtype::I64, vec![4], ints(&[0; 4]))]).expect_err("a wrong shape");
    assert!(e.contains("tensor `idx` in `index.safetensors` has shape [4], but buffer `idx` needs [3]"), "{e}");
    let e = index_compile(&[table(), ("idx", Dtype::I64, vec![3], ints(&[0, 5, 1]))]).expect_err("out of range");
    assert!(e.contains("index 5 (at flat position 1) is out of range for axis 0 of f32[5, 4]"), "{e}");
    assert!(e.contains("index.readi:5:"), "the error points at the index_select: {e}");
    let e = index_compile(&[table(), ("idx", Dtype::I64, vec![3], ints(&[0, 1 << 40, 1]))]).expect_err("too large");
    assert!(e.contains("int64 tensor `idx` holds 1099511627776 at flat index 1"), "{e}");
}

/// An index computed from a model input is read when the plan runs: the rows it names,
/// and an error naming the step and the value for one out of range (no panic, no read
/// past the table).
#[test]
fn an_index_computed_at_run_time_is_read_and_checked_as_the_plan_runs() {
    use readi_plan::ops::Pure;
    use readi_runtime::exec::{Input, RunError, Session};
    use readi_runtime::plan::Kernel;
    let text = "model m {\n  input x: f32[2, 4]\n  table = parameter([10, 3])\n  output y = index_select(table, 0, to(x[0], i64))\n}\n";
    let (sources, out) = common::compile_text("runtime_index.readi", text, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let weights = backend::seeded_weights(&module.graph, 1);
    let (plan, _) = backend::compile(&module, &weights, "seeded", &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let step = plan.manifest.steps.iter().find(|s| matches!(s.kernel, Kernel::Pure(Pure::IndexSelectAt(_))));
    let path = step.expect("an index_select step reading its index").path.clone();
    let table = &weights.tensors["table"].1;
    let mut session = Session::new(std::sync::Arc::new(plan), 1).expect("session");
    // `to(.., i64)` rounds towards zero: 2.7 is row 2.
    let x = [2.7, 0.0, 9.0, 1.0, 5.0, 5.0, 5.0, 5.0];
    let y = session.run(&[Input { name: "x", data: &x, shape: &[2, 4] }]).expect("runs");
    let want: Vec<f32> = [2, 0, 9, 1].iter().flat_map(|&r| table[r * 3..r * 3 + 3].to_vec()).collect();
    assert_eq!(y[0].1.data, want);
    let x = [2.0, 10.0, 0.0, 1.0, 5.0, 5.0, 5.0, 5.0];
    let e = session.run(&[Input { name: "x", data: &x, shape: &[2, 4] }]).expect_err("10 is past the table");
    let RunError::Step { step, detail } = &e else { panic!("{e:?}") };
    assert_eq!(step, &path);
    assert!(detail.contains("index 10 (at flat position 1) is out of range for an axis of size 10"), "{e}");
    assert!(e.to_string().contains("cannot run on its inputs"), "{e}");
}
