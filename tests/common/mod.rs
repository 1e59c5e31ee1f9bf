//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use readi_compiler::passes::{self, Options, Outcome, Pass};
use readi_grammar::diag::{FileId, SourceMap};

mod scratch;
#[allow(unused_imports)] // Not every test crate writes files.
pub use scratch::Scratch;

/// Runs the `readi` binary from the repository root, without colour.
pub fn readi(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_readi"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("NO_COLOR", "1")
        .output()
        .expect("run readi")
}

/// The repository root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Compiles a file (path relative to the root) through the pipeline, with the files it
/// `use`s read relative to it, as `readi` reads them.
pub fn compile(rel: &str, overrides: &[(&str, &str)], stop_after: Option<Pass>) -> (SourceMap, Outcome) {
    let text = std::fs::read_to_string(root().join(rel)).unwrap_or_else(|e| panic!("read {rel}: {e}"));
    let mut sources = SourceMap::new();
    let file = sources.add(rel, &text);
    let opts = Options { stop_after, ..Options::with_overrides(overrides) };
    let mut read: Vec<(PathBuf, FileId)> = Vec::new();
    let out = passes::run_with_uses(file, &text, &opts, &mut |from, path| {
        let used = Path::new(sources.name(from)).parent().unwrap_or(Path::new("")).join(path);
        let full = root().join(&used).canonicalize().map_err(|e| format!("{}: {e}", used.display()))?;
        if let Some(&(_, id)) = read.iter().find(|(p, _)| *p == full) {
            return Ok((id, sources.text(id).to_string()));
        }
        let text = std::fs::read_to_string(&full).map_err(|e| format!("{}: {e}", used.display()))?;
        let id = sources.add(used.display().to_string(), &text);
        read.push((full, id));
        Ok((id, text))
    });
    (sources, out)
}

/// Compiles source text registered under `name`.
pub fn compile_text(
    name: &str,
    text: &str,
    overrides: &[(&str, &str)],
    stop_after: Option<Pass>,
) -> (SourceMap, Outcome) {
    let mut sources = SourceMap::new();
    let file = sources.add(name, text);
    let opts = Options { stop_after, ..Options::with_overrides(overrides) };
    let out = passes::run(file, text, &opts);
    (sources, out)
}

/// The path of a glob match relative to the root, with forward slashes.
pub fn rel_path(path: &Path) -> String {
    path.strip_prefix(root()).unwrap_or(path).to_string_lossy().replace('\\', "/")
}

/// The bytes of a plan file laid out as `Plan::write` lays it out (format version,
/// manifest, CRC-32 of the manifest text and of the tensors' bytes in manifest order),
/// without the checks `Plan::new` makes: what a hand-edited, re-checksummed file looks
/// like. `tensors` are `(name, shape, f32 bytes)` in manifest order; a name given twice is
/// stored once (its first bytes) but counted in the checksum each time, as the manifest
/// lists it.
pub fn plan_file_bytes(format_version: &str, json: String, tensors: &[(String, Vec<usize>, Vec<u8>)]) -> Vec<u8> {
    let typed: Vec<_> =
        tensors.iter().map(|(n, s, b)| (n.clone(), s.clone(), safetensors::Dtype::F32, b.clone())).collect();
    typed_plan_file_bytes(format_version, json, &typed)
}

/// [`plan_file_bytes`] with each tensor's container type given (f16 variant tensors).
pub fn typed_plan_file_bytes(
    format_version: &str,
    json: String,
    tensors: &[(String, Vec<usize>, safetensors::Dtype, Vec<u8>)],
) -> Vec<u8> {
    use std::collections::{HashMap, HashSet};
    let mut crc = crc32fast::Hasher::new();
    crc.update(json.as_bytes());
    let mut seen = HashSet::new();
    let mut views = Vec::new();
    for (name, shape, dtype, bytes) in tensors {
        crc.update(bytes);
        if seen.insert(name.as_str())
            && let Ok(view) = safetensors::tensor::TensorView::new(*dtype, shape.clone(), bytes)
        {
            views.push((name.clone(), view));
        }
    }
    let metadata = HashMap::from([
        ("readi.format_version".to_string(), format_version.to_string()),
        ("readi.manifest".to_string(), json),
        ("readi.checksum".to_string(), format!("{:08x}", crc.finalize())),
    ]);
    safetensors::serialize(views, Some(metadata)).expect("serialise the plan file")
}

/// `got` against a reference `want` (shape, values) to `tol` (absolute, or relative above
/// 1); returns the worst error.
pub fn close(name: &str, got: &readi_runtime::exec::Tensor, want: &(Vec<usize>, Vec<f32>), tol: f32) -> f32 {
    assert_eq!(got.shape, want.0, "{name}: shape");
    let mut worst = 0.0f32;
    for (i, (&g, &w)) in got.data.iter().zip(&want.1).enumerate() {
        let err = (g - w).abs() / w.abs().max(1.0);
        assert!(err <= tol, "{name}[{i}]: {g}, torch {w} (error {err:e})");
        worst = worst.max(err);
    }
    eprintln!("{name}: max error vs torch {worst:e}");
    worst
}

/// models/bevfusion.readi at the reduced size of tests/fixtures/bevfusion/
/// make_full_fixtures.py's SIZES (two 64 x 96 views, an 8 x 8 BEV, 12 proposals), as
/// `--set` pairs.
pub const BEVFUSION_SMALL: &[(&str, &str)] = &[
    ("cams", "2"),
    ("img_h", "64"),
    ("img_w", "96"),
    ("embed", "4"),
    ("d2", "2"),
    ("h0", "1"),
    ("h1", "2"),
    ("h2", "2"),
    ("h3", "4"),
    ("window", "4"),
    ("neck_out", "16"),
    ("bev_ch", "8"),
    ("x_min", "-8.0"),
    ("x_max", "8.0"),
    ("cell", "1.0"),
    ("z_min", "-2.0"),
    ("z_max", "2.0"),
    ("z_cell", "4.0"),
    ("d_min", "1.0"),
    ("d_max", "9.0"),
    ("d_step", "1.0"),
    ("vx", "0.25"),
    ("max_points", "4"),
    ("max_voxels", "400"),
    ("nx", "64"),
    ("max_sites", "3000"),
    ("c0", "4"),
    ("c1", "6"),
    ("c2", "8"),
    ("c3", "8"),
    ("lidar_out", "6"),
    ("fused", "16"),
    ("second_out0", "16"),
    ("second_out1", "24"),
    ("layer_num", "2"),
    ("fpn_out", "16"),
    ("num_proposals", "12"),
    ("hidden", "32"),
    ("ffn", "48"),
    ("head_conv", "16"),
    ("range_x_min", "-5.0"),
    ("range_z_min", "-3.3"),
];

/// A fixture of tests/fixtures/bevfusion/ (weights or inputs and outputs).
pub fn bevfusion_fixture(name: &str) -> readi_compiler::backend::WeightSet {
    let path = root().join("tests/fixtures/bevfusion").join(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    readi_compiler::backend::WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

/// Compiles a model file with `overrides`, binding the bevfusion fixture `weights`.
pub fn bevfusion_plan(rel: &str, overrides: &[(&str, &str)], weights: &str) -> readi_runtime::plan::Plan {
    use readi_compiler::backend::{self, CompileOptions};
    let (sources, out) = compile(rel, overrides, None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("module");
    let (plan, _) = backend::compile(&module, &bevfusion_fixture(weights), weights, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    plan
}

/// Runs `plan` on the fixture's `input.*` tensors at 1 and 2 threads, asserts both give
/// the same bits, and returns the outputs by name.
pub fn run_at_1_and_2_threads(
    plan: readi_runtime::plan::Plan,
    io: &readi_compiler::backend::WeightSet,
) -> Vec<(String, readi_runtime::exec::Tensor)> {
    use readi_runtime::exec::{Input, Session};
    let inputs: Vec<Input<'_>> = io
        .tensors
        .iter()
        .filter_map(|(k, (shape, data))| k.strip_prefix("input.").map(|name| Input { name, data, shape }))
        .collect();
    let plan = std::sync::Arc::new(plan);
    let one = Session::new(std::sync::Arc::clone(&plan), 1).expect("session").run(&inputs).expect("runs");
    let two = Session::new(plan, 2).expect("session").run(&inputs).expect("runs");
    for ((name, a), (_, b)) in one.iter().zip(&two) {
        assert!(a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits()), "{name}: 1 and 2 threads differ");
    }
    one
}

/// The output `name` of a run.
pub fn output<'a>(outputs: &'a [(String, readi_runtime::exec::Tensor)], name: &str) -> &'a readi_runtime::exec::Tensor {
    &outputs.iter().find(|(n, _)| n == name).unwrap_or_else(|| panic!("no output {name}")).1
}
