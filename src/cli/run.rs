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
    print!("{}", detections(&result, 10));
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

/// A detector's outputs `boxes [B, K, >= 7]` (x, y, z, l, w, h, yaw, ...), `scores [B, K]`,
/// `labels [B, K]` and, if present, `keep [B, K]` (else a score above 0 keeps a box).
pub struct Detections<'a> {
    pub boxes: &'a Tensor,
    pub scores: &'a Tensor,
    pub labels: &'a Tensor,
    keep: Option<&'a Tensor>,
}

impl<'a> Detections<'a> {
    /// The detector outputs of a run, or `None` for other models.
    pub fn of(result: &'a [(String, Tensor)]) -> Option<Detections<'a>> {
        let get = |n: &str| result.iter().find(|(name, _)| name == n).map(|(_, t)| t);
        let (boxes, scores, labels) = (get("boxes")?, get("scores")?, get("labels")?);
        let (&[b, k, width], [sb, sk], [lb, lk]) = (&boxes.shape[..], &scores.shape[..], &labels.shape[..]) else {
            return None;
        };
        if width < 7 || (*sb, *sk, *lb, *lk) != (b, k, b, k) {
            return None;
        }
        let keep = get("keep").filter(|t| t.shape == scores.shape);
        Some(Detections { boxes, scores, labels, keep })
    }

    /// Samples and boxes per sample.
    pub fn size(&self) -> (usize, usize) {
        (self.scores.shape[0], self.scores.shape[1])
    }

    /// Sample `s`'s kept boxes, best score first, as flat row indices.
    pub fn kept(&self, s: usize) -> Vec<usize> {
        let k = self.size().1;
        let keeps = |j: usize| self.keep.map_or(self.scores.data[j] > 0.0, |t| t.data[j] != 0.0);
        let mut rows: Vec<usize> = (s * k..(s + 1) * k).filter(|&j| keeps(j)).collect();
        rows.sort_by(|&x, &y| self.scores.data[y].total_cmp(&self.scores.data[x]));
        rows
    }

    /// Row `j`'s x, y, z, l, w, h, yaw.
    pub fn box7(&self, j: usize) -> &[f32] {
        let width = self.boxes.shape[2];
        &self.boxes.data[j * width..j * width + 7]
    }
}

/// A detector's boxes as a table: each sample's kept boxes, the `top` best by score.
/// Empty for other models.
fn detections(result: &[(String, Tensor)], top: usize) -> String {
    let Some(d) = Detections::of(result) else {
        return String::new();
    };
    let (b, k) = d.size();
    let mut out = String::new();
    for s in 0..b {
        let rows = d.kept(s);
        out += &format!("sample {s}: {} of {k} boxes kept", rows.len());
        if rows.len() > top {
            out += &format!(", the {top} best:");
        }
        out += "\n      label  score        x        y        z      l      w      h     yaw\n";
        for &j in rows.iter().take(top) {
            let v = d.box7(j);
            out += &format!(
                "  {:>9} {:>6.3} {:>8.2} {:>8.2} {:>8.2} {:>6.2} {:>6.2} {:>6.2} {:>7.3}\n",
                d.labels.data[j] as i64, d.scores.data[j], v[0], v[1], v[2], v[3], v[4], v[5], v[6]
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(shape: &[usize], data: Vec<f32>) -> Tensor {
        Tensor { shape: shape.to_vec(), data }
    }

    /// Kept boxes only, best first; a model without box outputs prints nothing.
    #[test]
    fn detections_lists_the_kept_boxes_by_score() {
        let mut boxes = vec![0.0; 3 * 9];
        boxes[0] = 1.0;
        boxes[9] = 2.0;
        boxes[18] = 3.0;
        let result = vec![
            ("boxes".to_string(), t(&[1, 3, 9], boxes)),
            ("scores".to_string(), t(&[1, 3], vec![0.2, 0.9, 0.5])),
            ("labels".to_string(), t(&[1, 3], vec![4.0, 7.0, 1.0])),
            ("keep".to_string(), t(&[1, 3], vec![1.0, 1.0, 0.0])),
        ];
        let text = detections(&result, 10);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "sample 0: 2 of 3 boxes kept", "{text}");
        assert_eq!(lines.len(), 4, "{text}");
        assert!(lines[2].trim_start().starts_with("7  0.900     2.00"), "{text}");
        assert!(lines[3].trim_start().starts_with("4  0.200     1.00"), "{text}");
        assert_eq!(detections(&result[1..], 10), "");
    }
}
