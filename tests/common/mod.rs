//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use readi_compiler::passes::{self, Options, Outcome, Pass};
use readi_grammar::diag::SourceMap;

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

/// Compiles a file (path relative to the root) through the pipeline.
pub fn compile(rel: &str, overrides: &[(&str, &str)], stop_after: Option<Pass>) -> (SourceMap, Outcome) {
    let text = std::fs::read_to_string(root().join(rel)).unwrap_or_else(|e| panic!("read {rel}: {e}"));
    compile_text(rel, &text, overrides, stop_after)
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
