//! `readi ir`, `readi graph` and `readi passes`: the graph IR as text or as Graphviz DOT,
//! after the whole pipeline or after one pass, and the list of those passes.

use std::path::Path;
use std::process::ExitCode;

use readi_compiler::passes::{PIPELINE, Pass};
use readi_compiler::print;

use super::args::ModelArgs;
use super::frontend::{Frontend, with_module};

/// `readi ir`: the module as IR text.
pub fn run(s: &mut Frontend, file: &Path, model: &ModelArgs, stop_after: Option<Pass>) -> Result<(), ExitCode> {
    with_module(s, file, model, stop_after, |m| {
        print!("{}", print::to_text(m));
    })
}

/// `readi graph`: the graph as DOT, to stdout or to `output`.
pub fn graph(
    s: &mut Frontend,
    file: &Path,
    output: Option<&Path>,
    model: &ModelArgs,
    stop_after: Option<Pass>,
) -> Result<(), ExitCode> {
    let mut write_err = None;
    let code = with_module(s, file, model, stop_after, |m| {
        let dot = print::to_dot(&m.graph);
        match &output {
            Some(p) => {
                if let Err(e) = std::fs::write(p, dot) {
                    write_err = Some(format!("error: cannot write {}: {e}", p.display()));
                }
            }
            None => print!("{dot}"),
        }
    });
    match write_err {
        Some(e) => {
            eprintln!("{e}");
            Err(ExitCode::from(2))
        }
        None => code,
    }
}

/// `readi passes`: the pipeline's passes in order, the names `--stop-after` takes.
pub fn passes() -> Result<(), ExitCode> {
    for (_, name, doc) in PIPELINE {
        println!("{name:<16} {doc}");
    }
    Ok(())
}
