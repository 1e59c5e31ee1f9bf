//! `readi check`: parse, elaborate and check spec files; one line per file, every error reported.
//! A file of blocks alone (a library that model files `use`) is parsed, not elaborated: its
//! blocks are checked where a model instantiates them.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use readi_compiler::print;

use super::args::ModelArgs;
use super::frontend::{Frontend, summary_line};

pub fn run(s: &mut Frontend, files: &[PathBuf], model: &ModelArgs, deny_warnings: bool) -> Result<(), ExitCode> {
    let mut failed = 0;
    for path in files {
        let start = Instant::now();
        if let Some(blocks) = s.library_blocks(path) {
            let plural = if blocks == 1 { "" } else { "s" };
            println!(
                "ok  {}: a library of {blocks} block{plural} (no model: a model file `use`s it, which checks its blocks)",
                path.display()
            );
            continue;
        }
        let (out, _) = match s.compile(path, model, None) {
            Ok(x) => x,
            Err(_) => {
                failed += 1;
                continue;
            }
        };
        let name = path.display().to_string();
        let bad = out.diagnostics.has_errors() || (deny_warnings && out.diagnostics.warning_count() > 0);
        if bad {
            failed += 1;
            eprintln!("error: {}", summary_line(&name, &out.diagnostics));
            continue;
        }
        let m = out.module.as_ref();
        let (nodes, params) = m.map(|m| (m.graph.node_count(), m.graph.parameter_count())).unwrap_or((0, 0));
        let variants = m.and_then(|m| m.variants.as_ref()).map(|v| v.keys().len()).unwrap_or(0);
        let warn = if out.diagnostics.is_empty() {
            String::new()
        } else {
            format!(" ({})", summary_line("", &out.diagnostics).trim_start_matches(": "))
        };
        println!(
            "ok  {name}: {nodes} nodes, {} parameters, {variants} variants, {:.1} ms{warn}",
            print::thousands(params),
            start.elapsed().as_secs_f64() * 1e3
        );
    }
    if failed > 0 { Err(ExitCode::FAILURE) } else { Ok(()) }
}
