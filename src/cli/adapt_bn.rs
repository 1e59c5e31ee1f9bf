//! `readi adapt-bn`: AdaBN. Runs a plan's base model over unlabelled samples of a
//! condition and writes the re-estimated running statistics of the BatchNorms the
//! variant owns (every BatchNorm's for a plan that does not record ownership), a variant
//! parameter file for `readi compile --variant KEY=FILE` (see
//! `readi_runtime::calibrate` for what is computed).

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use readi_grammar::diag::suggest;
use readi_plan::VariantKey;
use readi_plan::format::{escaped, scope_covers};
use readi_runtime::calibrate::{BnCalibrator, BnStats};
use readi_runtime::exec::{Input, SessionOptions};
use readi_runtime::plan::{BASE_VARIANT, Plan};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use super::tensor_io;

/// What `readi adapt-bn` was asked to do.
pub struct Args<'a> {
    pub plan: &'a Path,
    pub variant: &'a str,
    pub samples: &'a [PathBuf],
    pub output: &'a Path,
    pub threads: usize,
    /// `--max-memory`: each batch's footprint is checked against it before it runs.
    pub max_memory: usize,
}

/// Runs `readi adapt-bn`; the error is the message to print.
pub fn adapt(args: &Args<'_>) -> Result<(), String> {
    let start = Instant::now();
    let plan = Arc::new(Plan::load(args.plan).map_err(|e| e.to_string())?);
    let key = check_key(&plan, args.variant)?;
    let owned = owned_statistics(&plan, &key)?;
    let shown = args.plan.display();
    let options = SessionOptions::default().threads(args.threads).max_memory(args.max_memory);
    let mut cal = BnCalibrator::with_options(plan.clone(), options).map_err(|e| format!("{shown}: {e}"))?;
    let bar = ProgressBar::new(args.samples.len() as u64);
    if let Ok(style) = ProgressStyle::with_template("{spinner} adapt-bn [{bar:30}] {pos}/{len} batches {msg}") {
        bar.set_style(style.progress_chars("=> "));
    }
    for path in args.samples {
        bar.set_message(path.display().to_string());
        // One batch in memory at a time: read, run, drop.
        let batch = read_batch(&plan, path, args.max_memory, &bar)?;
        let inputs: Vec<Input<'_>> = batch.iter().map(|(name, shape, data)| Input { name, data, shape }).collect();
        cal.add_batch(&inputs).map_err(|e| {
            bar.abandon();
            format!("{}: {e}", path.display())
        })?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let stats = cal.statistics().map_err(|e| e.to_string())?;
    let written = write_stats(args.output, &stats, &key, &cal, &plan.manifest.model, owned.as_ref())?;
    let count = |n: usize, one: &str, many: &str| format!("{n} {}", if n == 1 { one } else { many });
    let skipped = stats.len() - written;
    let not_owned = if skipped == 0 { String::new() } else { format!("; {skipped} skipped, not owned by `{key}`") };
    println!(
        "adapt-bn: {} of {} re-estimated over {} ({}) in {:.2} s on {}{not_owned}",
        count(written, "BatchNorm layer", "BatchNorm layers"),
        plan.manifest.model,
        count(cal.batches(), "batch", "batches"),
        count(cal.samples(), "sample", "samples"),
        start.elapsed().as_secs_f64(),
        count(cal.threads(), "thread", "threads")
    );
    println!(
        "wrote {}: running_mean and running_var of each for variant `{key}` (it keeps the base's BatchNorm weight and bias)",
        args.output.display()
    );
    println!("next: readi compile SPEC --weights BASE.safetensors --variant {key}={} -o PLAN", args.output.display());
    Ok(())
}

/// The variant key, read as a [`VariantKey`] (so `fog=0.030` is `fog=0.03` and a meld's
/// parts may come in any order) and checked against the keys the plan's spec declares when
/// the plan lists them: every part of the key must be declared.
fn check_key(plan: &Plan, text: &str) -> Result<VariantKey, String> {
    let m = &plan.manifest;
    let declared = m.conditions.as_ref().map(|c| c.keys()).unwrap_or_default();
    let shown: Vec<String> = declared.iter().map(|k| k.to_string()).collect();
    let hint = || match suggest(text, shown.iter().map(String::as_str)) {
        Some(s) => format!("did you mean `{s}`? "),
        None => String::new(),
    };
    let key = VariantKey::parse(text).map_err(|e| {
        if declared.is_empty() {
            e.to_string()
        } else {
            format!("{e}; {}(model `{}` declares {})", hint(), m.model, shown.join(", "))
        }
    })?;
    if key.is_base() {
        return Err(format!("`{BASE_VARIANT}` is the base model; AdaBN estimates statistics for a variant's key"));
    }
    if declared.is_empty() {
        if plan.variant_index_of(&key).is_none() {
            eprintln!(
                "note: the plan does not list the variant keys its spec declares; `{key}` is checked when the \
                 statistics are compiled (`readi compile --variant {key}=FILE`)"
            );
        }
        return Ok(key);
    }
    if key.part_keys().all(|p| declared.contains(&p)) {
        return Ok(key);
    }
    Err(format!("model `{}` declares no variant `{text}`; {}(its variants: {})", m.model, hint(), shown.join(", ")))
}

/// The BatchNorm statistics (`<bn>.running_mean`, `<bn>.running_var`) the variant `key`
/// owns, or `None` (every BatchNorm's, said in a note) when the plan does not record
/// ownership. An error when it owns none: compiling the file would refuse every tensor.
fn owned_statistics(plan: &Plan, key: &VariantKey) -> Result<Option<HashSet<String>>, String> {
    let m = &plan.manifest;
    if !m.records_ownership() {
        eprintln!(
            "note: the plan does not record which variants own its parameters (compiled before it was, or its \
             variants own nothing); writing every BatchNorm's statistics"
        );
        return Ok(None);
    }
    let c = m.conditions.as_ref();
    let is_stat = |n: &str| n.ends_with(".running_mean") || n.ends_with(".running_var");
    let owned: HashSet<String> =
        m.params.iter().filter(|p| is_stat(&p.name) && p.is_owned_by(key, c)).map(|p| p.name.clone()).collect();
    if owned.is_empty() {
        let mut scopes: Vec<&str> = Vec::new();
        for s in m.params.iter().flat_map(|p| p.owned_by.iter().flatten()) {
            if scope_covers(s, key, c) && !scopes.contains(&s.as_str()) {
                scopes.push(s);
            }
        }
        let its = if scopes.is_empty() {
            "it is in the scope of no scoped `adapt` section".to_string()
        } else {
            let shown: Vec<String> = scopes.iter().map(|s| format!("`{}`", escaped(s))).collect();
            format!("its scopes: {}", shown.join(", "))
        };
        return Err(format!(
            "variant `{key}` owns no BatchNorm statistics ({its}): add `tune batchnorm` to an adapt section that \
             covers it"
        ));
    }
    Ok(Some(owned))
}

/// A batch: per input, name, shape and data.
type Batch = Vec<(String, Vec<usize>, Vec<f32>)>;

/// Reads one sample file: a `.npy` for a model with one input, or a `.safetensors` holding
/// the inputs by name (a single tensor serves a single-input model whatever its name).
/// Absent optional inputs are left to the runtime (zero-filled).
fn read_batch(plan: &Plan, path: &Path, limit: usize, bar: &ProgressBar) -> Result<Batch, String> {
    let shown = path.display();
    let inputs = &plan.manifest.inputs;
    let names: Vec<&str> = inputs.iter().map(|i| i.name.as_str()).collect();
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    if ext == "npy" {
        let [only] = inputs.as_slice() else {
            return Err(format!(
                "{shown}: a .npy sample holds one tensor, but the model has {} inputs ({}); give .safetensors samples \
                 holding each input by name",
                inputs.len(),
                names.join(", ")
            ));
        };
        let (shape, data) = tensor_io::read_input(&only.name, path, limit)?;
        return Ok(vec![(only.name.clone(), shape, data)]);
    }
    if ext != "safetensors" {
        return Err(format!("{shown}: samples are read from .npy or .safetensors files"));
    }
    let bytes = tensor_io::read_limited(path, limit)?;
    let st = SafeTensors::deserialize(&bytes).map_err(|e| format!("{shown}: not a safetensors file ({e})"))?;
    let held: Vec<String> = st.names().into_iter().map(String::from).collect();
    let single = inputs.len() == 1 && held.len() == 1;
    if !single && let Some(extra) = held.iter().find(|n| !names.contains(&n.as_str())) {
        return Err(format!(
            "{shown}: tensor `{extra}` is not an input of model `{}` (its inputs: {})",
            plan.manifest.model,
            names.join(", ")
        ));
    }
    drop(st);
    drop(bytes);
    let mut batch = Vec::with_capacity(inputs.len());
    for spec in inputs {
        if !single && !held.contains(&spec.name) {
            if spec.optional {
                bar.println(format!("note: {shown} has no `{}`; the optional input is zero-filled", spec.name));
                continue;
            }
            return Err(format!("{shown}: no tensor for input `{}` (it holds: {})", spec.name, held.join(", ")));
        }
        let (shape, data) = tensor_io::read_input(&spec.name, path, limit)?;
        batch.push((spec.name.clone(), shape, data));
    }
    Ok(batch)
}

/// Writes `<bn>.running_mean` and `<bn>.running_var` (f32) of every BatchNorm, or of those
/// in `owned`, with what made them in the metadata; returns how many BatchNorms it wrote.
fn write_stats(
    out: &Path,
    stats: &[BnStats],
    key: &VariantKey,
    cal: &BnCalibrator,
    model: &str,
    owned: Option<&HashSet<String>>,
) -> Result<usize, String> {
    let bytes = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
    let keep = |name: &String| owned.is_none_or(|o| o.contains(name));
    let mut written = 0;
    let mut data: Vec<(String, Vec<u8>, usize)> = Vec::new();
    for s in stats {
        let pair = [
            (format!("{}.running_mean", s.name), bytes(&s.running_mean), s.running_mean.len()),
            (format!("{}.running_var", s.name), bytes(&s.running_var), s.running_var.len()),
        ];
        let before = data.len();
        data.extend(pair.into_iter().filter(|(name, ..)| keep(name)));
        written += usize::from(data.len() > before);
    }
    let mut views = Vec::with_capacity(data.len());
    for (name, b, n) in &data {
        let view = TensorView::new(Dtype::F32, vec![*n], b).map_err(|e| format!("{name}: {e}"))?;
        views.push((name.clone(), view));
    }
    let metadata = HashMap::from([
        ("readi.adapt_bn.model".to_string(), model.to_string()),
        ("readi.adapt_bn.variant".to_string(), key.to_string()),
        ("readi.adapt_bn.batches".to_string(), cal.batches().to_string()),
        ("readi.adapt_bn.samples".to_string(), cal.samples().to_string()),
    ]);
    let file = safetensors::serialize(views, Some(metadata)).map_err(|e| e.to_string())?;
    std::fs::write(out, file).map_err(|e| format!("cannot write {}: {e}", out.display()))?;
    Ok(written)
}

/// `readi adapt-bn` as dispatched: [`adapt`], its error printed.
pub fn run(
    plan: &Path,
    variant: &str,
    samples: &[PathBuf],
    output: &Path,
    session: SessionOptions,
) -> Result<(), ExitCode> {
    let args = Args { plan, variant, samples, output, threads: session.threads, max_memory: session.max_memory };
    adapt(&args).map_err(|msg| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    })
}
