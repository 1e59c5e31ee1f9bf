//! The command line: `Cli`, one `Command` variant per command with its arguments and help
//! text, and the parsers of `NAME=VALUE`-style arguments.

use std::path::PathBuf;

use clap::{Parser, Subcommand, ValueEnum};
use readi_compiler::passes::{PIPELINE, Pass};

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
pub struct Cli {
    /// Colour diagnostics.
    #[arg(long, value_enum, default_value_t = ColorWhen::Auto, global = true)]
    pub color: ColorWhen,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ColorWhen {
    Auto,
    Always,
    Never,
}

#[derive(clap::Args, Clone, Default)]
pub struct ModelArgs {
    /// Set a model parameter, overriding its default (repeatable): `--set num_classes=10`.
    #[arg(long = "set", value_name = "NAME=VALUE", value_parser = parse_set)]
    pub set: Vec<(String, String)>,
    /// Refuse a model whose activations at batch size 1 take more than SIZE (one value,
    /// or the values alive at once): bytes, or with a suffix K, M, G, T (powers of 1024):
    /// `512M`, `2G` [default: 4G].
    #[arg(long, value_name = "SIZE", value_parser = parse_memory)]
    pub max_activation_memory: Option<usize>,
}

#[derive(Subcommand)]
pub enum Command {
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
        /// Stop after this pass (see `readi passes`). A back-end pass compiles with the
        /// weights and variants below; after `lower` the schedule is printed.
        #[arg(long, value_name = "PASS", value_parser = parse_pass)]
        stop_after: Option<Pass>,
        #[command(flatten)]
        model: ModelArgs,
        #[command(flatten)]
        backend: BackendArgs,
    },
    /// Write the graph as Graphviz DOT (to stdout, or to a file with -o).
    #[command(after_help = "Example:\n  readi graph models/resnet18.readi -o r18.dot && dot -Tsvg r18.dot > r18.svg")]
    Graph {
        file: PathBuf,
        /// Output file (default: stdout).
        #[arg(short, long)]
        output: Option<PathBuf>,
        /// Stop after this pass (see `readi passes`); a back-end pass compiles with the
        /// weights and variants below (before `lower`: the schedule is not a graph).
        #[arg(long, value_name = "PASS", value_parser = parse_pass)]
        stop_after: Option<Pass>,
        #[command(flatten)]
        model: ModelArgs,
        #[command(flatten)]
        backend: BackendArgs,
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
        /// it owns, or a PEFT adapter directory. A key given twice merges its files (a tensor
        /// in two of them is an error), as in deploy.yaml.
        #[arg(long = "variant", value_name = "KEY=PATH", value_parser = parse_variant_arg)]
        variants: Vec<(String, String)>,
        /// How LoRA runs: merged into the adapted weights per variant (no run-time cost), as
        /// a side branch (smaller variants), or chosen per layer (`auto`, under
        /// --memory-budget).
        #[arg(long, value_enum)]
        lora: Option<LoraArg>,
        /// Most bytes a variant may store, percent of the base plan's (e.g. `3`): LoRA layers
        /// become branches and variant-owned convs compact algorithms, least latency first.
        /// Implies `--lora auto` unless --lora is given.
        #[arg(long, value_name = "PCT", value_parser = parse_budget)]
        memory_budget: Option<f64>,
        /// Most re-merge work a variant switch may take, in milliseconds (default 1, and at
        /// most 2% of the model's measured conv time, which the first run after a switch
        /// pays): the layers merged on switch (one shared working copy per layer, re-merged
        /// when the variant changes; no latency, raw tensors per variant), their measured
        /// merge-and-pack times summed. 0: none is merged on switch.
        #[arg(long, value_name = "MS", value_parser = parse_switch_budget)]
        switch_budget: Option<f64>,
        /// Let the variants' values of the weights no strategy changes (a tuned head's)
        /// be stored at half precision, the largest first, where --memory-budget needs it
        /// (all of them without a budget). Lossy: the compile reports how far the outputs
        /// move on seeded inputs.
        #[arg(long)]
        variant_f16: bool,
        /// Print the per-layer strategy: merge or branch, algorithm, bytes per variant,
        /// predicted and measured latency, and the totals.
        #[arg(long)]
        explain: bool,
        /// A variant with seeded parameters (repeatable), as for `readi ir`.
        #[arg(long = "seeded-variant", value_name = "KEY")]
        seeded_variants: Vec<String>,
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
        /// Drop this prefix from the weights' and variant files' tensor names that have it
        /// (`module.`, `model.`: what training wrappers add).
        #[arg(long, value_name = "PREFIX")]
        strip_prefix: Option<String>,
        /// Also print a table of what the `prune` rules zeroed, layer by layer.
        #[arg(long, short)]
        verbose: bool,
        #[command(flatten)]
        model: ModelArgs,
    },
    /// Run a plan on inputs from .npy or .safetensors files (and .bin point clouds).
    #[command(after_help = "Examples:\n  readi run r18.plan --input image=img.npy --output logits.npy\n  \
                            readi run bev.plan --input camera=cams.npy --input lidar_bev=bev.npy --output out.safetensors")]
    Run {
        plan: PathBuf,
        /// An input, `NAME=FILE` (repeatable). Absent `optional` inputs are zeros.
        #[arg(long = "input", value_name = "NAME=FILE", value_parser = parse_set)]
        inputs: Vec<(String, String)>,
        /// Where to write outputs: a .safetensors or .json file (all outputs), a .npy file
        /// (the only output), or `NAME=FILE.npy` (or `.json`) for one output (repeatable).
        /// JSON is `{"NAME": {"dtype": "f32" | "i64" | "bool", "shape": [...], "data": [...]}}`,
        /// data flat in row-major order, floats in shortest round-trip form, NaN and
        /// infinities as null.
        #[arg(long = "output", value_name = "FILE")]
        outputs: Vec<String>,
        /// Worker threads, 1 to 256 (default: all cores).
        #[arg(long, value_parser = parse_threads)]
        threads: Option<usize>,
        /// Most memory a run may take (activation buffers, scratch, inputs, outputs): bytes, or
        /// with a unit, `512M`, `2G` (powers of 1024); default half the physical memory.
        #[arg(long, value_name = "BYTES", value_parser = parse_memory)]
        max_memory: Option<usize>,
        /// Let the idle worker threads sleep between steps instead of spinning through a
        /// run: less CPU taken from other processes, more latency on small steps.
        #[arg(long)]
        no_spin: bool,
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
        /// Worker threads, 1 to 256 (default: all cores).
        #[arg(long, value_parser = parse_threads)]
        threads: Option<usize>,
        /// Timed runs (at least 1).
        #[arg(long, default_value_t = 20, value_parser = parse_positive)]
        runs: usize,
        /// Untimed runs first.
        #[arg(long, default_value_t = 3)]
        warmup: usize,
        /// Batch size bound to the plan's symbolic batch dimension (at least 1).
        #[arg(long, default_value_t = 1, value_parser = parse_positive)]
        batch: usize,
        /// Also print the time of each step (the slowest first) and per kernel kind.
        #[arg(long)]
        profile: bool,
        /// How many of the slowest steps the profile lists; 0 lists every step (to compare
        /// a model layer by layer with another runtime's profile).
        #[arg(long, default_value_t = 12, requires = "profile")]
        steps: usize,
        /// Also measure this machine's peak f32 FLOP/s at the same thread count (about a
        /// second) and print the run's GFLOP/s as a fraction of it.
        #[arg(long)]
        peak: bool,
        /// The variant to time, by key; default the base model.
        #[arg(long, value_name = "KEY")]
        variant: Option<String>,
        /// An input from a file, `NAME=FILE` as for `readi run` (repeatable); the others are
        /// seeded. For models whose work depends on the data (a point cloud's voxels).
        #[arg(long = "input", value_name = "NAME=FILE", value_parser = parse_set)]
        inputs: Vec<(String, String)>,
        /// Also time switching between the timed variant and this one (repeatable): the
        /// switch itself (p50, p99) and the first run after a switch against the steady run
        /// that follows it, `--runs` switches.
        #[arg(long = "switch", value_name = "KEY")]
        switch: Vec<String>,
        /// Also time the plan under this variant (a key, or `base`) in alternating runs
        /// with the timed one, in a second session: one run of each a round, the order
        /// reversed every round, `--runs` rounds; prints the median of the rounds' ratios
        /// (what a variant costs over the base, steady on a machine whose speed drifts).
        #[arg(long, value_name = "KEY")]
        against: Option<String>,
        /// Most memory a run may take (activation buffers, scratch, inputs, outputs): bytes, or
        /// with a unit, `512M`, `2G` (powers of 1024); default half the physical memory.
        #[arg(long, value_name = "BYTES", value_parser = parse_memory)]
        max_memory: Option<usize>,
        /// Let the idle worker threads sleep between steps instead of spinning through a
        /// run: less CPU taken from other processes, more latency on small steps.
        #[arg(long)]
        no_spin: bool,
    },
    /// Describe a plan: inputs, outputs, parameters, bytes, schedule and buffers.
    #[command(after_help = "Example:\n  readi inspect r18.plan")]
    Inspect {
        plan: PathBuf,
        /// Also list every parameter and every step.
        #[arg(long)]
        verbose: bool,
        /// The memory limit to compare the plan's footprint with (as for `readi run`):
        /// bytes, or `512M`, `2G`; default half the physical memory.
        #[arg(long, value_name = "BYTES", value_parser = parse_memory)]
        max_memory: Option<usize>,
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
        /// Worker threads, 1 to 256 (default: all cores).
        #[arg(long, value_parser = parse_threads)]
        threads: Option<usize>,
        /// Most memory a run may take (activation buffers, scratch, inputs, outputs): bytes, or
        /// with a unit, `512M`, `2G` (powers of 1024); default half the physical memory.
        #[arg(long, value_name = "BYTES", value_parser = parse_memory)]
        max_memory: Option<usize>,
    },
    /// Compile the bundled BEVFusion-tiny model (or, with `--model bevfusion`, the paper's
    /// BEVFusion at a demo size) with seeded weights and variants; drive through changing conditions.
    Demo {
        /// The model to drive.
        #[arg(long, value_enum, default_value_t)]
        model: super::demo::DemoModel,
        /// Worker threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
        /// Frames of the drive to run (it repeats after 8).
        #[arg(long, default_value_t = 8)]
        frames: usize,
    },
}

/// Most worker threads `--threads` accepts.
pub const MAX_THREADS: usize = 256;

/// `--threads`: 1 to [`MAX_THREADS`].
fn parse_threads(s: &str) -> Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(n @ 1..=MAX_THREADS) => Ok(n),
        Ok(n) => Err(format!("{n} threads: give 1 to {MAX_THREADS}")),
        Err(_) => Err(format!("`{s}` is not a thread count (1 to {MAX_THREADS})")),
    }
}

/// A count of at least 1 (`--batch`, `--runs`).
fn parse_positive(s: &str) -> Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(n) => Ok(n),
        Err(_) => Err(format!("`{s}` is not a positive whole number")),
    }
}

/// A memory size: bytes (`1048576`), or a number with a unit `K`, `M`, `G` or `T`
/// (powers of 1024; `KiB`, `MB` and `GiB` are read the same), `1.5G` too.
pub fn parse_memory(s: &str) -> Result<usize, String> {
    let t = s.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let shift = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "k" | "kb" | "kib" => 10,
        "m" | "mb" | "mib" => 20,
        "g" | "gb" | "gib" => 30,
        "t" | "tb" | "tib" => 40,
        _ => return Err(format!("`{s}`: unknown unit `{unit}`; write bytes, or a number with K, M, G or T")),
    };
    let bad = || format!("`{s}` is not a memory size (bytes, or a number with K, M, G or T: 512M, 2G)");
    let bytes = if let Ok(n) = number.parse::<u64>() {
        n.checked_mul(1u64 << shift).ok_or_else(bad)?
    } else {
        let x: f64 = number.parse().map_err(|_| bad())?;
        let b = x * (1u64 << shift) as f64;
        if !(b.is_finite() && b >= 0.0 && b < u64::MAX as f64) {
            return Err(bad());
        }
        b as u64
    };
    let bytes = usize::try_from(bytes).map_err(|_| bad())?;
    if bytes == 0 {
        return Err(format!("`{s}`: the memory limit must be more than 0 bytes"));
    }
    Ok(bytes)
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

/// What `readi ir` compiles a back-end pass with.
#[derive(clap::Args, Clone, Default)]
pub struct BackendArgs {
    /// Base weights (safetensors); without, seeded weights (`--seed`).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// The seed of the seeded weights and variants.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// A variant's parameters, `KEY=PATH` (repeatable), as for `readi compile`.
    #[arg(long = "variant", value_name = "KEY=PATH", value_parser = parse_variant_arg)]
    pub variants: Vec<(String, String)>,
    /// A variant with seeded parameters (repeatable): `--seeded-variant fog=0.03`.
    #[arg(long = "seeded-variant", value_name = "KEY")]
    pub seeded_variants: Vec<String>,
    /// How LoRA runs (merged into the weights, or a side branch).
    #[arg(long, value_enum)]
    pub lora: Option<LoraArg>,
    /// A melded variant, `fog=0.06+gamma=0.5` (repeatable).
    #[arg(long = "meld", value_name = "KEY+KEY")]
    pub melds: Vec<String>,
    /// Drop this prefix from the tensor names that have it, as for `readi compile`.
    #[arg(long, value_name = "PREFIX")]
    pub strip_prefix: Option<String>,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum LoraArg {
    Merge,
    Branch,
    Auto,
}

/// A memory budget in percent: a finite number, at least 0.
fn parse_budget(s: &str) -> Result<f64, String> {
    match s.trim_end_matches('%').parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("`{s}` is not a percentage (a number, at least 0, e.g. `3`)")),
    }
}

fn parse_switch_budget(s: &str) -> Result<f64, String> {
    match s.trim_end_matches("ms").parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("`{s}` is not a time in milliseconds (a number, at least 0, e.g. `1`)")),
    }
}

fn parse_pass(s: &str) -> Result<Pass, String> {
    Pass::from_name(s).ok_or_else(|| {
        let names: Vec<&str> = PIPELINE.iter().map(|p| p.1).collect();
        format!("unknown pass `{s}`; passes: {}", names.join(", "))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_sizes() {
        assert_eq!(parse_memory("1048576"), Ok(1 << 20));
        assert_eq!(parse_memory("512M"), Ok(512 << 20));
        assert_eq!(parse_memory("2G"), Ok(2 << 30));
        assert_eq!(parse_memory("2GiB"), Ok(2 << 30));
        assert_eq!(parse_memory("1.5g"), Ok(3 << 29));
        assert_eq!(parse_memory("64 KiB"), Ok(64 << 10));
        assert!(parse_memory("0").expect_err("zero").contains("more than 0"));
        assert!(parse_memory("12X").expect_err("unit").contains("unknown unit"));
        assert!(parse_memory("-1G").is_err());
        assert!(parse_memory("99999999999T").is_err());
        assert!(parse_memory("").is_err());
    }

    #[test]
    fn counts_and_threads() {
        assert_eq!(parse_positive("3"), Ok(3));
        assert!(parse_positive("0").expect_err("zero").contains("at least 1"));
        assert_eq!(parse_threads("256"), Ok(256));
        assert!(parse_threads("0").expect_err("zero").contains("1 to 256"));
        assert!(parse_threads("100000").expect_err("too many").contains("1 to 256"));
    }
}
