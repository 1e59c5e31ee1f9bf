//! `readi`: the command-line front end of the readi compiler and runtime.

mod cli;

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use clap::{Parser, Subcommand, ValueEnum};
use cli::{adapt_bn, demo, deploy, tensor_io};
use readi_compiler::backend::{self, CompileOptions, LoraMode, WeightSet};
use readi_compiler::passes::{self, Options, Outcome, PIPELINE, Pass};
use readi_compiler::print;
use readi_grammar::diag::{Diagnostics, FileId, SourceMap};
use readi_runtime::exec::{Input, Session, Tensor};
use readi_runtime::plan::Plan;

const EXAMPLES: &str = "\
Examples:
  readi demo                                 compile and run the bundled BEVFusion-tiny model
  readi compile models/resnet18.readi --weights resnet18.safetensors -o resnet18.plan
  readi run resnet18.plan --input image=img.npy --output logits.npy
  readi bench resnet18.plan --threads 2 --runs 50
  readi inspect resnet18.plan
  readi check models/*.readi                 check specs; exit status 1 on errors
  readi params models/resnet18.readi         parameter table with the total
  readi params models/resnet18.readi --set num_classes=10
  readi ir models/vit_encoder.readi --stop-after elaborate
  readi graph models/resnet18.readi -o resnet18.dot && dot -Tsvg resnet18.dot > resnet18.svg
  readi ast models/pointpillars_bev.readi    the file as the parser understood it
  readi simulate 000042.bin -o fog.bin --fog 0.06 --seed 1    the paper's fog, snow, gamma, blur";

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
    /// Compile a spec, its weights (safetensors, PyTorch names) and its variants into a plan file.
    #[command(
        after_help = "Examples:\n  readi compile models/resnet18.readi --weights r18.safetensors -o r18.plan\n  \
                            readi compile models/resnet18.readi --weights r18.safetensors -o r18.plan \\\n      \
                            --variant gamma=0.25=g025.safetensors --variant gamma=0.25=adapters/g025\n  \
                            readi compile --deploy deploy.yaml -o r18.plan"
    )]
    Compile {
        /// The spec (not with --deploy).
        #[arg(required_unless_present = "deploy", conflicts_with = "deploy")]
        spec: Option<PathBuf>,
        /// Base weights: a safetensors file of the model's state_dict (f32, f16 or bf16).
        #[arg(long, required_unless_present = "deploy", conflicts_with = "deploy")]
        weights: Option<PathBuf>,
        /// A deployment manifest (YAML) naming the spec, the base weights and the variants.
        #[arg(long)]
        deploy: Option<PathBuf>,
        /// A variant's parameters, `KEY=PATH` (repeatable): a safetensors file of the tensors
        /// it owns, or a PEFT adapter directory; give a key twice to combine both.
        #[arg(long = "variant", value_name = "KEY=PATH", value_parser = parse_variant_arg)]
        variants: Vec<(String, String)>,
        /// How LoRA runs: merged into the adapted weights per variant (no run-time cost) or
        /// as a side branch (smaller variants).
        #[arg(long, value_enum)]
        lora: Option<LoraArg>,
        /// An owned parameter a variant does not give is an error (else a warning; it keeps
        /// the base value).
        #[arg(long)]
        strict: bool,
        /// A melded variant for a combined condition, `fog=0.06+gamma=0.5` (repeatable): the
        /// spec's meld rule interpolates the given variants' parameters.
        #[arg(long = "meld", value_name = "KEY+KEY")]
        melds: Vec<String>,
        /// The plan file to write.
        #[arg(short, long)]
        output: PathBuf,
        /// Warn about tensors the model does not use instead of failing.
        #[arg(long)]
        allow_unused: bool,
        #[command(flatten)]
        model: ModelArgs,
    },
    /// Run a plan on inputs from .npy or .safetensors files.
    #[command(after_help = "Examples:\n  readi run r18.plan --input image=img.npy --output logits.npy\n  \
                            readi run bev.plan --input camera=cams.npy --input lidar_bev=bev.npy --output out.safetensors")]
    Run {
        plan: PathBuf,
        /// An input, `NAME=FILE` (repeatable). Absent `optional` inputs are zeros.
        #[arg(long = "input", value_name = "NAME=FILE", value_parser = parse_set)]
        inputs: Vec<(String, String)>,
        /// Where to write outputs: a .safetensors file (all outputs), a .npy file (the
        /// only output), or `NAME=FILE.npy` for one output (repeatable).
        #[arg(long = "output", value_name = "FILE")]
        outputs: Vec<String>,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// The variant to run, by key (`fog=0.03`); default the base model.
        #[arg(long, value_name = "KEY", conflicts_with = "auto")]
        variant: Option<String>,
        /// Choose the variant from the inputs and metadata by the spec's selectors, and
        /// print which and why.
        #[arg(long)]
        auto: bool,
        /// Run metadata for `--auto`, `NAME=VALUE` (repeatable), e.g. `fog_density=0.05`.
        #[arg(long = "meta", value_name = "NAME=VALUE", value_parser = parse_meta)]
        meta: Vec<(String, f64)>,
        /// Dropped views of a multi-view input, `NAME=V,V` (e.g. `camera=1,4`): zero-filled.
        #[arg(long = "drop-views", value_name = "NAME=V,V", value_parser = parse_views)]
        drop_views: Vec<(String, Vec<usize>)>,
    },
    /// Time a plan on seeded random inputs: median and p90 latency.
    #[command(after_help = "Example:\n  readi bench r18.plan --threads 2 --runs 50")]
    Bench {
        plan: PathBuf,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Timed runs.
        #[arg(long, default_value_t = 20)]
        runs: usize,
        /// Untimed runs first.
        #[arg(long, default_value_t = 3)]
        warmup: usize,
        /// Batch size bound to the plan's symbolic batch dimension.
        #[arg(long, default_value_t = 1)]
        batch: usize,
        /// Also print the time of each step (the slowest first) and per kernel kind.
        #[arg(long)]
        profile: bool,
        /// The variant to time, by key; default the base model.
        #[arg(long, value_name = "KEY")]
        variant: Option<String>,
    },
    /// Describe a plan: inputs, outputs, parameters, bytes, schedule and buffers.
    #[command(after_help = "Example:\n  readi inspect r18.plan")]
    Inspect {
        plan: PathBuf,
        /// Also list every parameter and every step.
        #[arg(long)]
        verbose: bool,
    },
    /// Apply the paper's conditions to an input: lidar fog or snow, camera gamma and/or blur.
    #[command(after_help = readi::simulate::EXAMPLES)]
    Simulate(readi::simulate::SimulateArgs),
    /// AdaBN: re-estimate every BatchNorm's statistics for a variant by running the base
    /// model over unlabelled samples of its condition; writes a variant parameter file.
    #[command(
        name = "adapt-bn",
        after_help = "Each sample file is one batch: a .npy (single-input models) or a .safetensors holding the \
                      inputs by name.\n\nExample:\n  readi adapt-bn r18.plan --variant gamma=0.25 --samples dark/*.npy \
                      -o gamma_0.25.safetensors\n  \
                      readi compile models/resnet18.readi --weights r18.safetensors \
                      --variant gamma=0.25=gamma_0.25.safetensors -o r18.plan"
    )]
    AdaptBn {
        /// The plan, whose base model runs.
        plan: PathBuf,
        /// The variant the statistics are for, by key (`gamma=0.25`).
        #[arg(long, value_name = "KEY")]
        variant: String,
        /// Sample files, one batch each, processed in order.
        #[arg(long, value_name = "FILE", num_args = 1.., required = true)]
        samples: Vec<PathBuf>,
        /// The safetensors file to write (`<bn>.running_mean`, `<bn>.running_var`).
        #[arg(short, long)]
        output: PathBuf,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Compile the bundled BEVFusion-tiny model with seeded weights and variants; drive through changing conditions.
    Demo {
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Frames of the drive to run (it repeats after 8).
        #[arg(long, default_value_t = 8)]
        frames: usize,
    },
}

fn parse_set(s: &str) -> Result<(String, String), String> {
    match s.split_once('=') {
        Some((k, v)) if !k.trim().is_empty() => Ok((k.trim().to_string(), v.trim().to_string())),
        _ => Err(format!("expected NAME=VALUE, got `{s}`")),
    }
}

/// `KEY=PATH`, where the key is itself `name=value` (`fog=0.03=fog.safetensors`): the path
/// starts after the key's second `=`, so paths may hold `=` too.
fn parse_variant_arg(s: &str) -> Result<(String, String), String> {
    let split = s.find('=').and_then(|first| s[first + 1..].find('=').map(|second| first + 1 + second));
    match split.map(|at| (s[..at].trim(), s[at + 1..].trim())) {
        Some((k, v)) if !k.is_empty() && !v.is_empty() => Ok((k.to_string(), v.to_string())),
        _ => Err(format!("expected KEY=PATH with KEY like fog=0.03 (for example fog=0.03=fog.safetensors), got `{s}`")),
    }
}

fn parse_meta(s: &str) -> Result<(String, f64), String> {
    let (k, v) = parse_set(s)?;
    v.parse::<f64>().ok().filter(|v| v.is_finite()).map(|v| (k, v)).ok_or(format!("`{s}`: the value must be a number"))
}

fn parse_views(s: &str) -> Result<(String, Vec<usize>), String> {
    let (k, v) = parse_set(s)?;
    let views: Result<Vec<usize>, _> = v.split(',').map(|x| x.trim().parse::<usize>()).collect();
    views.map(|views| (k, views)).map_err(|_| format!("`{s}`: expected NAME=V,V with view numbers, e.g. camera=1,4"))
}

/// Which variant a run uses.
enum Choice {
    Base,
    Key(String),
    /// Chosen by the spec's selectors from the inputs and this metadata.
    Auto(Vec<(String, f64)>),
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum LoraArg {
    Merge,
    Branch,
}

fn parse_pass(s: &str) -> Result<Pass, String> {
    Pass::from_name(s).ok_or_else(|| {
        let names: Vec<&str> = PIPELINE.iter().map(|p| p.1).collect();
        format!("unknown pass `{s}`; passes: {}", names.join(", "))
    })
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Printing to a closed pipe panics in `println!`; that is reported below, not as a crash.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if !panic_message(info.payload()).is_some_and(|m| m.contains("Broken pipe")) {
            default_hook(info);
        }
    }));
    // Elaboration recurses with the model's nesting; give it room whatever the platform's
    // main-thread stack is.
    let worker = std::thread::Builder::new().stack_size(64 << 20).spawn(move || run(cli));
    match worker.map(|h| h.join()) {
        Ok(Ok(code)) => code,
        // `readi ... | head`: the reader went away; stop quietly, as Unix tools do.
        Ok(Err(panic)) if panic_message(panic.as_ref()).is_some_and(|m| m.contains("Broken pipe")) => {
            ExitCode::from(141)
        }
        _ => {
            eprintln!("error: internal failure (please report this with the input file)");
            ExitCode::from(3)
        }
    }
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> Option<&str> {
    payload.downcast_ref::<String>().map(String::as_str).or_else(|| payload.downcast_ref::<&str>().copied())
}

/// A loaded source file, its pipeline outcome, and how to show its diagnostics.
struct Frontend {
    sources: SourceMap,
    color: bool,
}

impl Frontend {
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
    Options { stop_after, ..Options::with_overrides(&model.set) }
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
    let mut s = Frontend { sources: SourceMap::new(), color };
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
        Command::Compile { spec, weights, deploy, variants, lora, strict, melds, output, allow_unused, model } => {
            let args = CompileArgs { spec, weights, deploy, variants, lora, strict, melds, allow_unused, model };
            cmd_compile(&mut s, args, &output)
        }
        Command::Run { plan, inputs, outputs, threads, variant, auto, meta, drop_views } => {
            let choice = match variant {
                Some(v) => Choice::Key(v),
                None if auto => Choice::Auto(meta),
                None => Choice::Base,
            };
            cmd_run(&plan, &inputs, &outputs, threads, choice, &drop_views)
        }
        Command::Bench { plan, threads, runs, warmup, batch, profile, variant } => {
            cmd_bench(&plan, threads, runs, warmup, batch, profile, variant.as_deref())
        }
        Command::Inspect { plan, verbose } => cmd_inspect(&plan, verbose),
        Command::Demo { threads, frames } => demo::run(&mut s, threads_or_default(threads), frames),
        Command::Simulate(args) => cmd_simulate(&args),
        Command::AdaptBn { plan, variant, samples, output, threads } => {
            cmd_adapt_bn(&plan, &variant, &samples, &output, threads)
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(code) => code,
    }
}

/// Compiles a file and, if that succeeded, hands the module to `f`.
fn with_module(
    s: &mut Frontend,
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

fn cmd_check(s: &mut Frontend, files: &[PathBuf], model: &ModelArgs, deny_warnings: bool) -> Result<(), ExitCode> {
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

fn cmd_ast(s: &mut Frontend, path: &Path, debug: bool) -> Result<(), ExitCode> {
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

fn threads_or_default(threads: Option<usize>) -> usize {
    threads.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)).max(1)
}

fn load_plan(path: &Path) -> Result<Arc<Plan>, ExitCode> {
    match Plan::load(path) {
        Ok(p) => Ok(Arc::new(p)),
        Err(e) => {
            eprintln!("error: {e}");
            Err(ExitCode::FAILURE)
        }
    }
}

struct CompileArgs {
    spec: Option<PathBuf>,
    weights: Option<PathBuf>,
    deploy: Option<PathBuf>,
    variants: Vec<(String, String)>,
    lora: Option<LoraArg>,
    strict: bool,
    melds: Vec<String>,
    allow_unused: bool,
    model: ModelArgs,
}

fn cmd_compile(s: &mut Frontend, args: CompileArgs, output: &Path) -> Result<(), ExitCode> {
    let start = Instant::now();
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let mut model = args.model;
    let mut melds = args.melds.clone();
    let (spec, weights, mut variant_files, mut lora) = match &args.deploy {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).map_err(|e| fail(format!("cannot read {}: {e}", path.display())))?;
            let d = deploy::parse(path, &text).map_err(fail)?;
            model.set.extend(d.set);
            melds.extend(d.melds);
            let lora = match d.lora.as_deref() {
                None => None,
                Some("merge") => Some(LoraMode::Merge),
                Some("branch") => Some(LoraMode::Branch),
                Some(other) => {
                    return Err(fail(format!("{}: `lora` is `{other}`; use merge or branch", path.display())));
                }
            };
            (d.spec, d.weights, d.variants, lora)
        }
        None => match (args.spec, args.weights) {
            (Some(spec), Some(weights)) => (spec, weights, Vec::new(), None),
            _ => return Err(fail("give a spec and --weights, or --deploy".into())),
        },
    };
    variant_files.extend(deploy::variant_args(&args.variants));
    if let Some(l) = args.lora {
        lora = Some(match l {
            LoraArg::Merge => LoraMode::Merge,
            LoraArg::Branch => LoraMode::Branch,
        });
    }
    let (out, _) = s.compile(&spec, &model, None)?;
    let Some(module) = out.module.filter(|_| !out.diagnostics.has_errors()) else {
        eprintln!("error: {}", summary_line(&spec.display().to_string(), &out.diagnostics));
        return Err(ExitCode::FAILURE);
    };
    let wname = weights.display().to_string();
    let bytes = std::fs::read(&weights).map_err(|e| fail(format!("cannot read {wname}: {e}")))?;
    let report = |s: &Frontend, d: Diagnostics| {
        s.report(&d);
        ExitCode::FAILURE
    };
    let set = WeightSet::from_safetensors(&wname, &bytes).map_err(|d| report(s, d))?;
    let mut sources = Vec::new();
    for files in &variant_files {
        sources.push(deploy::read_variant(files, &module).map_err(|d| report(s, d))?);
    }
    let opts =
        CompileOptions { allow_unused: args.allow_unused, lora: lora.unwrap_or_default(), strict: args.strict, melds };
    let (plan, warnings) = backend::compile_variants(&module, &set, &wname, &sources, &opts).map_err(|d| {
        s.report(&d);
        eprintln!("error: {}", summary_line(&wname, &d));
        ExitCode::FAILURE
    })?;
    s.report(&warnings);
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
    Ok(())
}

/// Summary of a tensor for terminal output: shape, min, max, mean.
fn describe(t: &Tensor) -> String {
    let (mut lo, mut hi, mut sum) = (f32::INFINITY, f32::NEG_INFINITY, 0.0f64);
    for &v in &t.data {
        lo = lo.min(v);
        hi = hi.max(v);
        sum += v as f64;
    }
    let mean = if t.data.is_empty() { 0.0 } else { sum / t.data.len() as f64 };
    format!("{:?}  min {lo:.4}  max {hi:.4}  mean {mean:.4}", t.shape)
}

fn cmd_simulate(args: &readi::simulate::SimulateArgs) -> Result<(), ExitCode> {
    match readi::simulate::run(args) {
        Ok(summary) => {
            println!("{summary}");
            Ok(())
        }
        Err(e) => {
            eprintln!("error: {e}");
            Err(ExitCode::FAILURE)
        }
    }
}

fn cmd_run(
    plan_path: &Path,
    inputs: &[(String, String)],
    outputs: &[String],
    threads: Option<usize>,
    choice: Choice,
    drop_views: &[(String, Vec<usize>)],
) -> Result<(), ExitCode> {
    let plan = load_plan(plan_path)?;
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let mut loaded = Vec::new();
    for (name, file) in inputs {
        loaded.push((name.clone(), tensor_io::read_input(name, Path::new(file)).map_err(fail)?));
    }
    for (name, views) in drop_views {
        let Some((_, (shape, data))) = loaded.iter_mut().find(|(n, _)| n == name) else {
            return Err(fail(format!("--drop-views names `{name}`, which is not given with --input")));
        };
        readi_runtime::conditions::drop_views(data, shape, views).map_err(|e| fail(format!("input `{name}`: {e}")))?;
    }
    let mut session = Session::new(plan.clone(), threads_or_default(threads)).map_err(|e| fail(e.to_string()))?;
    let given: Vec<Input<'_>> = loaded.iter().map(|(name, (shape, data))| Input { name, data, shape }).collect();
    match choice {
        Choice::Base => {
            if let Some((key, why)) = plan.missing_variant(&given) {
                println!("{why}");
                session.set_variant(&key).map_err(|e| fail(e.to_string()))?;
            }
        }
        Choice::Key(key) => session.set_variant(&key).map_err(|e| fail(e.to_string()))?,
        Choice::Auto(meta) => {
            let t = Instant::now();
            let sel = plan.select(&given, &meta).map_err(|e| fail(e.to_string()))?;
            let us = t.elapsed().as_secs_f64() * 1e6;
            println!("selected variant {} ({us:.0} us):", sel.key);
            for r in &sel.reasons {
                println!("  {r}");
            }
            session.set_variant(&sel.key).map_err(|e| fail(e.to_string()))?;
        }
    }
    let start = Instant::now();
    let result = session.run(&given).map_err(|e| fail(e.to_string()))?;
    let elapsed = start.elapsed();
    for (name, t) in &result {
        println!("{name}: {}", describe(t));
    }
    println!(
        "ran variant {} in {:.2} ms on {} threads",
        session.last_variant().map_or("base", |v| plan.variant_key(v)),
        elapsed.as_secs_f64() * 1e3,
        session.threads()
    );
    let names: Vec<&str> = result.iter().map(|(n, _)| n.as_str()).collect();
    for spec in outputs {
        match spec.split_once('=').filter(|(n, _)| names.contains(n)) {
            Some((name, file)) => {
                let t = result.iter().find(|(n, _)| n == name).map(|(_, t)| t);
                if let Some(t) = t {
                    tensor_io::write_npy(Path::new(file), t).map_err(fail)?;
                }
            }
            None => tensor_io::write_outputs(Path::new(spec), &result).map_err(fail)?,
        }
    }
    Ok(())
}

/// Seeded inputs for every input of a plan at the given batch size.
fn synthetic_inputs(plan: &Plan, batch: usize, seed: u64) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let mut state = seed;
    plan.manifest
        .input_shapes(batch)
        .into_iter()
        .map(|(name, shape)| {
            let n = shape.iter().product();
            let data = (0..n)
                .map(|_| {
                    state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
                })
                .collect();
            (name.to_string(), shape, data)
        })
        .collect()
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn cmd_bench(
    plan_path: &Path,
    threads: Option<usize>,
    runs: usize,
    warmup: usize,
    batch: usize,
    profile: bool,
    variant: Option<&str>,
) -> Result<(), ExitCode> {
    let plan = load_plan(plan_path)?;
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let threads = threads_or_default(threads);
    let mut session = Session::new(plan.clone(), threads).map_err(|e| fail(e.to_string()))?;
    if let Some(key) = variant {
        session.set_variant(key).map_err(|e| fail(e.to_string()))?;
    }
    let data = synthetic_inputs(&plan, batch.max(1), 42);
    let given: Vec<Input<'_>> = data.iter().map(|(name, shape, d)| Input { name, data: d, shape }).collect();
    for _ in 0..warmup {
        session.run(&given).map_err(|e| fail(e.to_string()))?;
    }
    if profile {
        session.enable_profiling();
    }
    let mut times = Vec::with_capacity(runs.max(1));
    for _ in 0..runs.max(1) {
        let t = Instant::now();
        session.run(&given).map_err(|e| fail(e.to_string()))?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    println!(
        "{} ({}): batch {}, {} threads, {} runs: median {:.2} ms, p90 {:.2} ms, min {:.2} ms",
        plan.manifest.model,
        session.variant(),
        batch.max(1),
        threads,
        times.len(),
        percentile(&times, 0.5),
        percentile(&times, 0.9),
        times[0]
    );
    if let Some(p) = session.profile() {
        print!("{}", readi::inspect::profile(&plan.manifest, p, times.len()));
    }
    Ok(())
}

fn cmd_inspect(plan_path: &Path, verbose: bool) -> Result<(), ExitCode> {
    let plan = load_plan(plan_path)?;
    print!("{}", readi::inspect::plan(&plan, plan_path, verbose));
    Ok(())
}

fn cmd_adapt_bn(
    plan: &Path,
    variant: &str,
    samples: &[PathBuf],
    output: &Path,
    threads: Option<usize>,
) -> Result<(), ExitCode> {
    let args = adapt_bn::Args { plan, variant, samples, output, threads: threads_or_default(threads) };
    adapt_bn::run(&args).map_err(|msg| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    })
}
