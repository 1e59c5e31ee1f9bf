//! `readi`: the command-line front end of the readi compiler.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand, ValueEnum};
use readi_compiler::elaborate::{ElabOptions, Literal};
use readi_compiler::passes::{self, Options, Outcome, PIPELINE, Pass};
use readi_compiler::print;
use readi_grammar::diag::{Diagnostics, FileId, SourceMap};

/// The bundled default model, used by `readi demo`.
const DEMO_MODEL: (&str, &str) = ("models/bevfusion_tiny.readi", include_str!("../models/bevfusion_tiny.readi"));

const EXAMPLES: &str = "\
Examples:
  readi demo                                 check and summarise the bundled BEVFusion-tiny model
  readi check models/*.readi                 check specs; exit status 1 on errors
  readi params models/resnet18.readi         parameter table with the total
  readi params models/resnet18.readi --set num_classes=10
  readi ir models/vit_encoder.readi --stop-after elaborate
  readi graph models/resnet18.readi -o resnet18.dot && dot -Tsvg resnet18.dot > resnet18.svg
  readi ast models/pointpillars_bev.readi    the file as the parser understood it";

#[derive(Parser)]
#[command(name = "readi", version, about = "Compiler for adaptive autonomous-driving perception networks (t-READi)", after_help = EXAMPLES)]
struct Cli {
    /// Colour diagnostics.
    #[arg(long, value_enum, default_value_t = ColorWhen::Auto, global = true)]
    color: ColorWhen,
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum ColorWhen {
    Auto,
    Always,
    Never,
}

#[derive(clap::Args, Clone, Default)]
struct ModelArgs {
    /// Set a model parameter, overriding its default (repeatable): `--set num_classes=10`.
    #[arg(long = "set", value_name = "NAME=VALUE", value_parser = parse_set)]
    set: Vec<(String, String)>,
}

#[derive(Subcommand)]
enum Command {
    /// Parse, elaborate and check spec files; report every error.
    #[command(after_help = "Example:\n  readi check models/*.readi")]
    Check {
        #[arg(required = true)]
        files: Vec<PathBuf>,
        #[command(flatten)]
        model: ModelArgs,
        /// Treat warnings as errors.
        #[arg(long)]
        deny_warnings: bool,
    },
    /// Print the file as the parser understood it (canonical source, precedence made explicit).
    #[command(after_help = "Example:\n  readi ast models/resnet18.readi")]
    Ast {
        file: PathBuf,
        /// Print the raw syntax tree (Rust debug form, with byte spans).
        #[arg(long)]
        debug: bool,
    },
    /// Print the graph IR after the pipeline, or after one pass.
    #[command(after_help = "Example:\n  readi ir models/resnet18.readi --stop-after elaborate")]
    Ir {
        file: PathBuf,
        /// Stop after this pass (see `readi passes`).
        #[arg(long, value_name = "PASS", value_parser = parse_pass)]
        stop_after: Option<Pass>,
        #[command(flatten)]
        model: ModelArgs,
    },
    /// Write the graph as Graphviz DOT (to stdout, or to a file with -o).
    #[command(after_help = "Example:\n  readi graph models/resnet18.readi -o r18.dot && dot -Tsvg r18.dot > r18.svg")]
    Graph {
        file: PathBuf,
        /// Output file (default: stdout).
        #[arg(short, long)]
        output: Option<PathBuf>,
        /// Stop after this pass (see `readi passes`).
        #[arg(long, value_name = "PASS", value_parser = parse_pass)]
        stop_after: Option<Pass>,
        #[command(flatten)]
        model: ModelArgs,
    },
    /// Print every parameter (name, shape, count) and the total.
    #[command(after_help = "Example:\n  readi params models/resnet18.readi --set num_classes=10")]
    Params {
        file: PathBuf,
        /// Also list buffers (BatchNorm running statistics).
        #[arg(long)]
        buffers: bool,
        #[command(flatten)]
        model: ModelArgs,
    },
    /// List the passes of the pipeline.
    Passes,
    /// Check and summarise the bundled BEVFusion-tiny model (no files needed).
    Demo,
}

fn parse_set(s: &str) -> Result<(String, String), String> {
    match s.split_once('=') {
        Some((k, v)) if !k.trim().is_empty() => Ok((k.trim().to_string(), v.trim().to_string())),
        _ => Err(format!("expected NAME=VALUE, got `{s}`")),
    }
}

fn parse_pass(s: &str) -> Result<Pass, String> {
    Pass::from_name(s).ok_or_else(|| {
        let names: Vec<&str> = PIPELINE.iter().map(|p| p.1).collect();
        format!("unknown pass `{s}`; passes: {}", names.join(", "))
    })
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Elaboration recurses with the model's nesting; give it room whatever the platform's
    // main-thread stack is.
    let worker = std::thread::Builder::new().stack_size(64 << 20).spawn(move || run(cli));
    match worker.map(|h| h.join()) {
        Ok(Ok(code)) => code,
        _ => {
            eprintln!("error: internal failure (please report this with the input file)");
            ExitCode::from(3)
        }
    }
}

/// A loaded source file, its pipeline outcome, and how to show its diagnostics.
struct Session {
    sources: SourceMap,
    color: bool,
}

impl Session {
    fn load(&mut self, path: &Path) -> Result<(FileId, String), ExitCode> {
        match std::fs::read(path) {
            Ok(bytes) => match String::from_utf8(bytes) {
                Ok(text) => Ok((self.sources.add(path.display().to_string(), text.clone()), text)),
                Err(e) => {
                    eprintln!(
                        "error: {} is not UTF-8 text (invalid byte at offset {})",
                        path.display(),
                        e.utf8_error().valid_up_to()
                    );
                    Err(ExitCode::from(2))
                }
            },
            Err(e) => {
                eprintln!("error: cannot read {}: {e}", path.display());
                Err(ExitCode::from(2))
            }
        }
    }

    fn report(&self, diags: &Diagnostics) {
        let mut err = std::io::stderr().lock();
        let _ = err.write_all(self.sources.render_all(diags, self.color).as_bytes());
    }

    fn compile(
        &mut self,
        path: &Path,
        model: &ModelArgs,
        stop_after: Option<Pass>,
    ) -> Result<(Outcome, FileId), ExitCode> {
        let (file, text) = self.load(path)?;
        let opts = options(model, stop_after);
        let out = passes::run(file, &text, &opts);
        self.report(&out.diagnostics);
        Ok((out, file))
    }
}

fn options(model: &ModelArgs, stop_after: Option<Pass>) -> Options {
    Options {
        elab: ElabOptions { overrides: model.set.iter().map(|(k, v)| (k.clone(), Literal::parse(v))).collect() },
        stop_after,
    }
}

fn summary_line(path: &str, diags: &Diagnostics) -> String {
    let plural = |n: usize, w: &str| format!("{n} {w}{}", if n == 1 { "" } else { "s" });
    let mut parts = Vec::new();
    if diags.error_count() > 0 {
        parts.push(plural(diags.error_count(), "error"));
    }
    if diags.warning_count() > 0 {
        parts.push(plural(diags.warning_count(), "warning"));
    }
    format!("{path}: {}", parts.join(", "))
}

fn run(cli: Cli) -> ExitCode {
    let color = match cli.color {
        ColorWhen::Always => true,
        ColorWhen::Never => false,
        ColorWhen::Auto => std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none(),
    };
    let mut s = Session { sources: SourceMap::new(), color };
    let result = match cli.command {
        Command::Check { files, model, deny_warnings } => cmd_check(&mut s, &files, &model, deny_warnings),
        Command::Ast { file, debug } => cmd_ast(&mut s, &file, debug),
        Command::Ir { file, stop_after, model } => with_module(&mut s, &file, &model, stop_after, |m| {
            print!("{}", print::to_text(m));
        }),
        Command::Graph { file, output, stop_after, model } => {
            let mut write_err = None;
            let code = with_module(&mut s, &file, &model, stop_after, |m| {
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
        Command::Params { file, buffers, model } => with_module(&mut s, &file, &model, None, |m| {
            print!("{}", print::param_table(m, buffers));
        }),
        Command::Passes => {
            for (_, name, doc) in PIPELINE {
                println!("{name:<16} {doc}");
            }
            Ok(())
        }
        Command::Demo => cmd_demo(&mut s),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(code) => code,
    }
}

/// Compiles a file and, if that succeeded, hands the module to `f`.
fn with_module(
    s: &mut Session,
    path: &Path,
    model: &ModelArgs,
    stop_after: Option<Pass>,
    f: impl FnOnce(&passes::Module),
) -> Result<(), ExitCode> {
    let (out, _) = s.compile(path, model, stop_after)?;
    if out.diagnostics.has_errors() {
        eprintln!("error: {}", summary_line(&path.display().to_string(), &out.diagnostics));
        return Err(ExitCode::FAILURE);
    }
    match &out.module {
        Some(m) => {
            f(m);
            Ok(())
        }
        None => {
            eprintln!("{}: nothing to show after pass `parse`; use `readi ast`", path.display());
            Err(ExitCode::FAILURE)
        }
    }
}

fn cmd_check(s: &mut Session, files: &[PathBuf], model: &ModelArgs, deny_warnings: bool) -> Result<(), ExitCode> {
    let mut failed = 0;
    for path in files {
        let start = Instant::now();
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
        let variants = m.and_then(|m| m.variants.as_ref()).map(|v| v.variant_keys().len()).unwrap_or(0);
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

fn cmd_ast(s: &mut Session, path: &Path, debug: bool) -> Result<(), ExitCode> {
    let (file, text) = s.load(path)?;
    let parsed = readi_grammar::parse(file, &text);
    s.report(&parsed.diagnostics);
    if parsed.diagnostics.has_errors() {
        eprintln!("error: {}", summary_line(&path.display().to_string(), &parsed.diagnostics));
        return Err(ExitCode::FAILURE);
    }
    if debug {
        println!("{:#?}", parsed.file);
    } else {
        print!("{}", readi_grammar::ast_print::to_source(&parsed.file));
    }
    Ok(())
}

fn cmd_demo(s: &mut Session) -> Result<(), ExitCode> {
    let (name, text) = DEMO_MODEL;
    let file = s.sources.add(name, text);
    let start = Instant::now();
    let out = passes::run(file, text, &Options::default());
    let elapsed = start.elapsed();
    s.report(&out.diagnostics);
    let Some(m) = out.module.filter(|_| !out.diagnostics.has_errors()) else {
        eprintln!("error: the bundled model does not check");
        return Err(ExitCode::FAILURE);
    };
    let g = &m.graph;
    println!("readi demo: the bundled {} model ({name})", g.name);
    println!("parsed, elaborated and checked in {:.1} ms\n", elapsed.as_secs_f64() * 1e3);
    let inputs: Vec<_> = g
        .input_nodes()
        .into_iter()
        .filter_map(|n| match &g.node(n).op {
            readi_compiler::ir::Op::Input(a) => Some((a, &g.node(n).outputs[0])),
            _ => None,
        })
        .collect();
    let width =
        inputs.iter().map(|(a, _)| a.name.len()).chain(g.outputs.iter().map(|o| o.name.len())).max().unwrap_or(0);
    println!("inputs:");
    for (a, ty) in &inputs {
        let m = a.modality.as_deref().map(|m| format!(" @{m}")).unwrap_or_default();
        let opt = if a.optional { " (optional)" } else { "" };
        println!("  {:<width$}  {ty}{m}{opt}", a.name);
    }
    println!("outputs:");
    for o in &g.outputs {
        println!("  {:<width$}  {}", o.name, g.value_type(o.value).map(|t| t.to_string()).unwrap_or_default());
    }
    println!("\n{} nodes, {} parameters", g.node_count(), print::thousands(g.parameter_count()));
    if let Some(plan) = &m.adapt {
        let p = g.parameter_count().max(1) as f64;
        let tuned = plan.tuned_elements(g);
        let added = plan.added_elements();
        println!("\nadaptation (per variant):");
        let w = plan.rules.iter().map(|r| r.text.len()).max().unwrap_or(0);
        for r in &plan.rules {
            let t: u64 = r.targets.iter().map(|t| t.tuned + t.added).sum();
            println!("  {:<w$}  {:>4} layers  {:>9} elements", r.text, r.targets.len(), print::thousands(t));
        }
        println!(
            "  exist budget {:.2}% ({} elements), add budget {:.2}% ({} elements)",
            100.0 * tuned as f64 / p,
            print::thousands(tuned),
            100.0 * added as f64 / p,
            print::thousands(added)
        );
    }
    if let Some(v) = &m.variants {
        let keys = v.variant_keys();
        println!("\nvariants ({}): {}", keys.len(), keys.join(" "));
        if let Some(meld) = &v.meld {
            let w: Vec<String> = meld.weights.iter().map(|(m, l)| format!("{m} {l}")).collect();
            println!("combined conditions are melded with lambda {}", w.join(", "));
        }
    }
    println!("\nnext: `readi ir {name}` for the graph, `readi params {name}` for every tensor");
    Ok(())
}
