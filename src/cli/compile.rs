//! `readi compile`: a spec, its weights and its variants (from the command line or a
//! deployment manifest) into a plan file.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use readi_compiler::backend::{self, CompileOptions, LoraMode, WeightSet};
use readi_compiler::print;
use readi_grammar::diag::Diagnostics;

use super::args::{LoraArg, ModelArgs};
use super::frontend::{Frontend, summary_line};
use super::{deploy, files};

/// The arguments of `readi compile` but the output file.
pub struct CompileArgs {
    pub spec: Option<PathBuf>,
    pub weights: Option<PathBuf>,
    pub deploy: Option<PathBuf>,
    pub variants: Vec<(String, String)>,
    pub lora: Option<LoraArg>,
    pub memory_budget: Option<f64>,
    pub switch_budget: Option<f64>,
    pub variant_f16: bool,
    pub explain: bool,
    pub seeded_variants: Vec<String>,
    pub strict: bool,
    pub melds: Vec<String>,
    pub allow_unused: bool,
    /// Dropped from the tensor names that start with it (`--strip-prefix`).
    pub strip_prefix: Option<String>,
    /// Print the per-layer pruning table.
    pub verbose: bool,
    pub model: ModelArgs,
}

/// `--strip-prefix`: drops `prefix` from the base weights' and the variants' tensor names
/// that have it. A base file with no such name is an error (a mistyped prefix); a
/// variant file may lack it.
pub fn strip_prefix(
    prefix: Option<&str>,
    (base, base_name): (&mut WeightSet, &str),
    variants: &mut [backend::VariantSource],
) -> Result<(), Diagnostics> {
    let Some(prefix) = prefix else { return Ok(()) };
    if base.strip_prefix(base_name, prefix)? == 0 {
        return Err(Diagnostics(vec![readi_grammar::diag::Diagnostic::error(
            readi_grammar::diag::Code::Weights,
            format!("--strip-prefix `{prefix}`: no tensor in `{base_name}` starts with it"),
        )]));
    }
    for v in variants {
        v.weights.strip_prefix(&v.origin, prefix)?;
    }
    Ok(())
}

pub fn run(s: &mut Frontend, args: CompileArgs, output: &Path) -> Result<(), ExitCode> {
    let start = Instant::now();
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let mut model = args.model;
    let mut melds = args.melds.clone();
    let (spec, weights, variant_files, mut lora) = match &args.deploy {
        Some(path) => {
            let bytes = files::read_bounded(path, files::MAX_CONFIG_BYTES).map_err(fail)?;
            let text = String::from_utf8(bytes).map_err(|_| fail(format!("{} is not UTF-8 text", path.display())))?;
            let d = deploy::parse(path, &text).map_err(fail)?;
            model.set.extend(d.set);
            melds.extend(d.melds);
            let lora = match d.lora.as_deref() {
                None => None,
                Some("merge") => Some(LoraMode::Merge),
                Some("branch") => Some(LoraMode::Branch),
                Some("auto") => Some(LoraMode::Auto),
                Some(other) => {
                    return Err(fail(format!("{}: `lora` is `{other}`; use merge, branch or auto", path.display())));
                }
            };
            (d.spec, d.weights, d.variants, lora)
        }
        None => match (args.spec, args.weights) {
            (Some(spec), Some(weights)) => (spec, weights, Vec::new(), None),
            _ => return Err(fail("give a spec and --weights, or --deploy".into())),
        },
    };
    // A key given twice, in the manifest, on the command line or both, merges its files.
    let entries = variant_files.into_iter().flat_map(|v| v.files.into_iter().map(move |f| (v.key.clone(), f)));
    let variant_files = deploy::group_by_key(entries.chain(deploy::variant_arg_files(&args.variants)));
    if let Some(l) = args.lora {
        lora = Some(match l {
            LoraArg::Merge => LoraMode::Merge,
            LoraArg::Branch => LoraMode::Branch,
            LoraArg::Auto => LoraMode::Auto,
        });
    }
    // A budget lets the strategy choose per layer unless a mode was given.
    if args.memory_budget.is_some() && lora.is_none() {
        lora = Some(LoraMode::Auto);
    }
    let (out, _) = s.compile(&spec, &model, None)?;
    let Some(module) = out.module.filter(|_| !out.diagnostics.has_errors()) else {
        eprintln!("error: {}", summary_line(&spec.display().to_string(), &out.diagnostics));
        return Err(ExitCode::FAILURE);
    };
    let wname = weights.display().to_string();
    let bytes = files::read_bounded(&weights, files::MAX_WEIGHTS_BYTES).map_err(fail)?;
    let report = |s: &Frontend, d: Diagnostics| {
        s.report(&d);
        ExitCode::FAILURE
    };
    let mut set = WeightSet::from_safetensors(&wname, &bytes).map_err(|d| report(s, d))?;
    let mut sources = Vec::new();
    for files in &deploy::regroup_by_value(variant_files, &module) {
        sources.push(deploy::read_variant(files, &module).map_err(|d| report(s, d))?);
    }
    strip_prefix(args.strip_prefix.as_deref(), (&mut set, &wname), &mut sources).map_err(|d| report(s, d))?;
    sources.extend(backend::seeded_variants(&module, &args.seeded_variants, 2));
    let opts = CompileOptions {
        allow_unused: args.allow_unused,
        lora: lora.unwrap_or_default(),
        strict: args.strict,
        melds,
        memory_budget: args.memory_budget,
        switch_budget: args.switch_budget,
        explain: args.explain,
        variant_f16: args.variant_f16,
        ..CompileOptions::default()
    };
    let (plan, warnings, strategy) =
        backend::compile_explained(&module, &set, &wname, &sources, &opts).map_err(|d| {
            s.report(&d);
            eprintln!("error: {}", summary_line(&wname, &d));
            ExitCode::FAILURE
        })?;
    s.report(&warnings);
    if args.explain {
        match &strategy {
            Some(st) => print!("{}", readi_compiler::passes::choose_strategy::explain(st)),
            None => println!("no layer has a strategy to choose (no LoRA layer or variant-owned conv, or no variants)"),
        }
    }
    plan.write(output).map_err(|e| fail(e.to_string()))?;
    let m = &plan.manifest;
    let variants = match m.variants.len() {
        0 => String::new(),
        1 => format!(", 1 variant (LoRA {})", opts.lora.name()),
        n => format!(", {n} variants (LoRA {})", opts.lora.name()),
    };
    println!(
        "wrote {}: {} steps, {} tensors ({}){variants}, {} activation buffers, {:.0} ms",
        output.display(),
        m.steps.len(),
        m.tensors.len(),
        print::bytes(plan.tensor_bytes() as u64),
        m.slots,
        start.elapsed().as_secs_f64() * 1e3
    );
    for line in backend::meld_summary(&module, &set, &wname, &sources, &opts).map_err(|d| report(s, d))? {
        println!("{line}");
    }
    let plan = std::sync::Arc::new(plan);
    let half =
        backend::half_summary(&module, &set, &wname, &sources, &opts, std::sync::Arc::clone(&plan), strategy.as_ref())
            .map_err(|d| report(s, d))?;
    if let Some(h) = half {
        println!("{}", h.line());
    }
    let summary = backend::prune_summary(&module, &set, &wname, &sources, &opts, plan).map_err(|d| report(s, d))?;
    if let Some(p) = summary {
        print!("{}", prune_text(&p, args.verbose));
    }
    Ok(())
}

/// What the `prune` rules did: one line, and with `verbose` a table of the layers.
pub fn prune_text(p: &backend::PruneSummary, verbose: bool) -> String {
    use std::fmt::Write;
    let (zeroed, total) = p.totals();
    let pct = |z: u64, t: u64| if t == 0 { 0.0 } else { 100.0 * z as f64 / t as f64 };
    let mut thresholds: Vec<f64> = p.layers.iter().map(|l| l.below).collect();
    thresholds.sort_by(f64::total_cmp);
    thresholds.dedup();
    let below: Vec<String> = thresholds.iter().map(|t| format!("{t:e}")).collect();
    let worst = p.output_difference.iter().map(|(_, d)| *d).fold(0.0f32, f32::max);
    let mut out = format!(
        "pruned {} of {} shared weights ({:.1}%) below {} in {} layers; outputs differ by at most {worst:.2e} on \
         seeded inputs\n",
        print::thousands(zeroed),
        print::thousands(total),
        pct(zeroed, total),
        below.join(", "),
        p.layers.len()
    );
    if verbose {
        let width = p.layers.iter().map(|l| l.layer.len()).max().unwrap_or(5).max(5);
        let _ = writeln!(out, "  {:width$}  {:>12}  {:>12}  {:>6}  below", "layer", "zeroed", "of", "%");
        for l in &p.layers {
            let _ = writeln!(
                out,
                "  {:width$}  {:>12}  {:>12}  {:>5.1}%  {:e}",
                l.layer,
                print::thousands(l.zeroed),
                print::thousands(l.total),
                pct(l.zeroed, l.total),
                l.below
            );
        }
        for (name, d) in &p.output_difference {
            let _ = writeln!(out, "  output `{name}`: max abs difference {d:.3e} vs the unpruned plan");
        }
    }
    out
}
