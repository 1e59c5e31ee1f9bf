//! `readi ir`, `readi graph` and `readi passes`: the graph IR as text or as Graphviz DOT,
//! after the front end or after any pass, and the list of those passes.

use std::path::Path;
use std::process::ExitCode;

use readi_compiler::backend::{self, CompileOptions, LoraMode, WeightSet};
use readi_compiler::passes::{self, BackendInputs, PIPELINE, Pass};
use readi_compiler::{Module, print};

use super::args::{BackendArgs, LoraArg, ModelArgs};
use super::frontend::{Frontend, summary_line, with_module};
use super::{deploy, files};

/// `readi ir`: the module as IR text after the front end or after `stop_after`; after a
/// back-end pass it is compiled with `backend`'s weights and variants, and from `lower`
/// on the schedule is printed as `readi inspect` prints it.
pub fn run(
    s: &mut Frontend,
    file: &Path,
    model: &ModelArgs,
    stop_after: Option<Pass>,
    backend: &BackendArgs,
) -> Result<(), ExitCode> {
    if !stop_after.is_some_and(|p| p.is_backend()) {
        return with_module(s, file, model, stop_after, |m| print!("{}", print::to_text(m)));
    }
    let module = compiled(s, file, model, stop_after, backend)?;
    match &module.lowered {
        Some(l) => {
            print!("{}", readi::inspect::schedule(&l.manifest, true));
            print!("{}", readi::inspect::buffers(&l.manifest));
            print!("{}", readi::inspect::variant_tables(&l.manifest));
        }
        None => print!("{}", print::to_text(&module)),
    }
    Ok(())
}

/// `readi graph`: the graph as DOT, to stdout or to `output`, after the front end or
/// after `stop_after` (a back-end pass before `lower`).
pub fn graph(
    s: &mut Frontend,
    file: &Path,
    output: Option<&Path>,
    model: &ModelArgs,
    stop_after: Option<Pass>,
    backend: &BackendArgs,
) -> Result<(), ExitCode> {
    let dot = if stop_after.is_some_and(|p| p.is_backend()) {
        if stop_after.is_some_and(|p| p >= Pass::Lower) {
            eprintln!("error: after `lower` the model is a schedule, not a graph; use `readi ir --stop-after lower`");
            return Err(ExitCode::FAILURE);
        }
        print::to_dot(&compiled(s, file, model, stop_after, backend)?.graph)
    } else {
        let mut dot = String::new();
        with_module(s, file, model, stop_after, |m| dot = print::to_dot(&m.graph))?;
        dot
    };
    match output {
        Some(p) => std::fs::write(p, dot).map_err(|e| {
            eprintln!("error: cannot write {}: {e}", p.display());
            ExitCode::from(2)
        }),
        None => {
            print!("{dot}");
            Ok(())
        }
    }
}

/// The module after back-end pass `stop_after`, compiled with `backend`'s weights (or
/// seeded ones) and variants.
fn compiled(
    s: &mut Frontend,
    file: &Path,
    model: &ModelArgs,
    stop_after: Option<Pass>,
    backend: &BackendArgs,
) -> Result<Module, ExitCode> {
    let (out, _) = s.compile(file, model, None)?;
    let Some(mut module) = out.module.filter(|_| !out.diagnostics.has_errors()) else {
        eprintln!("error: {}", summary_line(&file.display().to_string(), &out.diagnostics));
        return Err(ExitCode::FAILURE);
    };
    let report = |s: &Frontend, d: readi_grammar::diag::Diagnostics| {
        s.report(&d);
        ExitCode::FAILURE
    };
    let (mut weights, name) = match &backend.weights {
        Some(path) => {
            let name = path.display().to_string();
            let bytes = files::read_bounded(path, files::MAX_WEIGHTS_BYTES).map_err(|e| {
                eprintln!("error: {e}");
                ExitCode::FAILURE
            })?;
            (WeightSet::from_safetensors(&name, &bytes).map_err(|d| report(s, d))?, name)
        }
        None => {
            eprintln!("note: seeded weights (seed {}); give --weights for a model's own", backend.seed);
            (backend::seeded_weights(&module.graph, backend.seed), format!("<seeded weights {}>", backend.seed))
        }
    };
    let mut sources = Vec::new();
    for files in deploy::regroup_by_value(deploy::variant_args(&backend.variants), &module) {
        sources.push(deploy::read_variant(&files, &module).map_err(|d| report(s, d))?);
    }
    super::compile::strip_prefix(backend.strip_prefix.as_deref(), (&mut weights, &name), &mut sources)
        .map_err(|d| report(s, d))?;
    sources.extend(backend::seeded_variants(&module, &backend.seeded_variants, backend.seed + 1));
    let lora = match backend.lora {
        Some(LoraArg::Branch) => LoraMode::Branch,
        Some(LoraArg::Auto) => LoraMode::Auto,
        _ => LoraMode::Merge,
    };
    let opts = CompileOptions { lora, melds: backend.melds.clone(), ..CompileOptions::default() };
    let inputs = BackendInputs { base: &weights, base_name: &name, variants: &sources, opts: &opts };
    let run = passes::run_backend(&mut module, &inputs, stop_after).map_err(|d| report(s, d))?;
    s.report(&run.warnings);
    for a in &run.applied {
        eprintln!("note: {}: {} x{}", a.pass.name(), a.rule, a.count);
    }
    Ok(module)
}

/// `readi passes`: the pipeline's passes in order, the names `--stop-after` takes.
pub fn passes() -> Result<(), ExitCode> {
    for (_, name, doc) in PIPELINE {
        println!("{name:<16} {doc}");
    }
    Ok(())
}
