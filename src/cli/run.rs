//! `readi run`: a plan on inputs from files, with the base model, a variant by key, or the
//! variant the spec's selectors choose; outputs summarised and written to files.

use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;

use readi_plan::DType;
use readi_runtime::conditions;
use readi_runtime::exec::{Input, Session, SessionOptions, Tensor};
use readi_runtime::plan::escaped;

use super::{load_plan, tensor_io};

/// Which variant a run uses.
pub enum Choice {
    Base,
    Key(String),
    /// Chosen by the spec's selectors from the inputs and this metadata.
    Auto(Vec<(String, f64)>),
}

/// Values of an integer output printed.
const SHOWN: usize = 8;

/// Summary of a tensor for terminal output: shape, min, max, mean; for an i64 output its
/// type, min and max as integers and its first values, for a bool one how many are true.
fn describe(t: &Tensor, dtype: DType) -> String {
    match dtype {
        DType::I64 | DType::I32 => {
            let ints: Vec<i64> = t.data.iter().map(|&v| v as i64).collect();
            let (lo, hi) = (ints.iter().min().copied().unwrap_or(0), ints.iter().max().copied().unwrap_or(0));
            let first: Vec<String> = ints.iter().take(SHOWN).map(i64::to_string).collect();
            let more = if ints.len() > SHOWN { ", ..." } else { "" };
            return format!("{:?} i64  min {lo}  max {hi}  [{}{more}]", t.shape, first.join(", "));
        }
        DType::Bool => {
            let n = t.data.iter().filter(|&&v| v != 0.0).count();
            return format!("{:?} bool  {n} true of {}", t.shape, t.data.len());
        }
        _ => {}
    }
    let (mut lo, mut hi, mut sum) = (f32::INFINITY, f32::NEG_INFINITY, 0.0f64);
    for &v in &t.data {
        lo = lo.min(v);
        hi = hi.max(v);
        sum += v as f64;
    }
    let mean = if t.data.is_empty() { 0.0 } else { sum / t.data.len() as f64 };
    format!("{:?}  min {lo:.4}  max {hi:.4}  mean {mean:.4}", t.shape)
}

/// The values per row of a `.bin` point cloud given for input `name`: the known last axis
/// of the input, which must be `[P, C]`.
fn bin_columns(m: &readi_runtime::plan::Manifest, name: &str, file: &str) -> Result<usize, String> {
    let Some(spec) = m.inputs.iter().find(|s| s.name == name) else {
        return Err(format!("the plan has no input `{}` (given {})", escaped(name), escaped(file)));
    };
    match &spec.shape[..] {
        [_, c] if c.symbols().is_empty() && c.coef() >= 1 => Ok(c.coef() as usize),
        _ => Err(format!(
            "{}: a .bin point cloud is read into a [P, C] input with a known C; input `{}` is {}",
            escaped(file),
            escaped(name),
            readi_runtime::plan::show_shape(&spec.shape)
        )),
    }
}

/// A loaded input: its shape and data.
pub type Loaded = (Vec<usize>, Vec<f32>);

/// The `--input NAME=FILE` tensors: `.npy` / `.safetensors`, or a `.bin` point cloud read
/// into the `[P, C]` input's C columns; each at most `max_memory` bytes.
pub fn load_inputs(
    m: &readi_runtime::plan::Manifest,
    inputs: &[(String, String)],
    max_memory: usize,
) -> Result<Vec<(String, Loaded)>, String> {
    let mut loaded = Vec::with_capacity(inputs.len());
    for (name, file) in inputs {
        let path = Path::new(file);
        let t = if tensor_io::is_bin(path) {
            tensor_io::read_bin(path, bin_columns(m, name, file)?, max_memory)
        } else {
            tensor_io::read_input(name, path, max_memory)
        };
        loaded.push((name.clone(), t?));
    }
    Ok(loaded)
}

pub fn run(
    plan_path: &Path,
    inputs: &[(String, String)],
    outputs: &[String],
    options: SessionOptions,
    choice: Choice,
    drop_views: &[(String, Vec<usize>)],
) -> Result<(), ExitCode> {
    let plan = load_plan(plan_path)?;
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let destinations = destinations(&plan.manifest, outputs).map_err(fail)?;
    let mut loaded = load_inputs(&plan.manifest, inputs, options.max_memory).map_err(fail)?;
    for (name, views) in drop_views {
        let Some((_, (shape, data))) = loaded.iter_mut().find(|(n, _)| n == name) else {
            return Err(fail(format!("--drop-views names `{name}`, which is not given with --input")));
        };
        conditions::drop_views(data, shape, views).map_err(|e| fail(format!("input `{name}`: {e}")))?;
    }
    let mut session = Session::with_options(plan.clone(), options).map_err(|e| fail(e.to_string()))?;
    let given: Vec<Input<'_>> = loaded.iter().map(|(name, (shape, data))| Input { name, data, shape }).collect();
    match choice {
        Choice::Base => {
            if let Some((key, why)) = conditions::missing_variant(&plan, &given) {
                println!("{why}");
                session.set_variant_key(&key).map_err(|e| fail(e.to_string()))?;
            }
        }
        Choice::Key(key) => session.set_variant(&key).map_err(|e| fail(e.to_string()))?,
        Choice::Auto(meta) => {
            let t = Instant::now();
            let sel = conditions::select(&plan, &given, &meta).map_err(|e| fail(e.to_string()))?;
            let us = t.elapsed().as_secs_f64() * 1e6;
            println!("selected variant {} ({us:.0} us):", sel.key);
            for r in &sel.reasons {
                println!("  {r}");
            }
            session.set_variant_key(&sel.key).map_err(|e| fail(e.to_string()))?;
        }
    }
    let start = Instant::now();
    let result = session.run(&given).map_err(|e| fail(format!("{}: {e}", plan_path.display())))?;
    let elapsed = start.elapsed();
    // The element type the model gives each output (f32 in plans before version 7).
    let dtype_of = |name: &str| plan.manifest.outputs.iter().find(|o| o.name == name).map_or(DType::F32, |o| o.dtype);
    let dtypes: Vec<DType> = result.iter().map(|(n, _)| dtype_of(n)).collect();
    for ((name, t), &d) in result.iter().zip(&dtypes) {
        println!("{}: {}", escaped(name), describe(t, d));
    }
    println!(
        "ran variant {} in {:.2} ms on {} threads",
        session.last_variant().map_or("base", |v| plan.variant_key(v)),
        elapsed.as_secs_f64() * 1e3,
        session.threads()
    );
    for dest in destinations {
        match dest {
            Destination::One(name, file) => {
                if let Some((_, t)) = result.iter().find(|(n, _)| n == name) {
                    tensor_io::write_one(Path::new(file), name, t, dtype_of(name)).map_err(fail)?;
                }
            }
            Destination::All(file) => tensor_io::write_outputs(Path::new(file), &result, &dtypes).map_err(fail)?,
        }
    }
    Ok(())
}

/// Where `--output` writes.
enum Destination<'a> {
    /// `NAME=FILE.npy` (or `.json`, `.safetensors`): one output.
    One(&'a str, &'a str),
    /// `FILE`: every output (or the only one).
    All(&'a str),
}

/// Reads the `--output` arguments before anything runs: `NAME=FILE` names an output of
/// the plan (an unknown name is an error listing them); an argument whose part before
/// `=` holds a path separator is a file name (`./a=b.npy`).
fn destinations<'a>(m: &readi_runtime::plan::Manifest, specs: &'a [String]) -> Result<Vec<Destination<'a>>, String> {
    let mut out = Vec::with_capacity(specs.len());
    for spec in specs {
        match spec.split_once('=') {
            Some((name, file)) if !name.contains(['/', '\\']) => {
                if !m.outputs.iter().any(|o| o.name == name) {
                    let names: Vec<String> = m.outputs.iter().map(|o| format!("`{}`", escaped(&o.name))).collect();
                    return Err(format!(
                        "--output {}: the model has no output `{}` (its outputs: {}); to write a file whose name \
                         holds `=`, write it as ./{}",
                        escaped(spec),
                        escaped(name),
                        names.join(", "),
                        escaped(spec)
                    ));
                }
                out.push(Destination::One(name, file));
            }
            _ => out.push(Destination::All(spec)),
        }
    }
    Ok(out)
}
