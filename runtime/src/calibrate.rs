//! AdaBN: re-estimating every BatchNorm's running statistics from unlabelled data.
//!
//! A [`BnCalibrator`] runs a plan's base model over batches of samples from a new
//! condition, as PyTorch does with every BatchNorm in train mode, `momentum=None` and
//! `reset_running_stats()`, under `no_grad`:
//!
//! * each BatchNorm normalises its input with the statistics of the current batch (mean
//!   and biased variance over every axis but the channel axis 1), then applies its gamma
//!   and beta, so the layers after it see what PyTorch's train-mode forward computes;
//! * its running mean is the average over batches of the batch means, its running
//!   variance the average of the unbiased batch variances (`n / (n - 1)` times the
//!   biased one, `n` the values per channel in the batch): PyTorch's cumulative moving
//!   average, every batch weighted equally.
//!
//! A plan holds BatchNorms folded into a conv's epilogue or as a channel-affine step; the
//! epilogue's [`BnInfo`] gives the name, eps, gamma, beta and any folded conv bias. At a
//! BatchNorm step the calibrator runs the step with only the conv bias as its epilogue
//! (the BatchNorm's input), accumulates the statistics in f64, and normalises the buffer
//! in place (with the step's fused ReLU). Every other step runs as in [`Session::run`],
//! whose executor is untouched. One batch is in memory at a time; buffers are reused for
//! batches of one size.

use std::collections::HashSet;
use std::fmt;
use std::sync::Arc;

use rayon::prelude::*;

use crate::exec::{Bound, Input, Run, RunError, Session, SessionOptions, run_step};
use readi_plan::ops::{Activation, batchnorm_channel};

use crate::plan::{AdapterSpec, BnInfo, EpilogueSpec, Kernel, Plan, Step, Storage, escaped};

/// Why calibration failed.
#[derive(Clone, Debug, PartialEq)]
pub enum CalibrateError {
    /// Running the plan failed (inputs, a corrupt plan).
    Run(RunError),
    /// The model has no BatchNorm layer.
    NoBatchNorm { model: String },
    /// The plan was compiled before BatchNorm layers were recorded in plans.
    NotRecorded { missing: Vec<String> },
    /// A BatchNorm sees a single value per channel in a batch: no variance.
    OneValue { layer: String, shape: Vec<usize> },
    /// A batch statistic is NaN or infinite.
    NotFinite { layer: String, channel: usize },
    /// Statistics were asked for before any batch.
    NoBatches,
    /// A tensor AdaBN derives (a running statistic, or the batch's normalisation scale
    /// and shift) is NaN or infinite although the batch statistics are finite.
    Derived { tensor: String, index: usize, value: f32, cause: String },
}

impl fmt::Display for CalibrateError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CalibrateError::Run(e) => e.fmt(f),
            CalibrateError::NoBatchNorm { model } => {
                let model = escaped(model);
                write!(f, "model `{model}` has no BatchNorm layer: there are no statistics to estimate")
            }
            CalibrateError::NotRecorded { missing } => {
                let shown: Vec<String> = missing.iter().take(3).map(|n| escaped(n).into_owned()).collect();
                let more = if missing.len() > 3 { format!(" and {} more", missing.len() - 3) } else { String::new() };
                write!(
                    f,
                    "the plan does not record the BatchNorm parameters AdaBN needs ({}{more}); it was compiled by an \
                     older readi: recompile the plan",
                    shown.join(", ")
                )
            }
            CalibrateError::OneValue { layer, shape } => write!(
                f,
                "BatchNorm `{}` sees one value per channel (input shape {shape:?}); PyTorch refuses this in train \
                 mode: give batches of more samples",
                escaped(layer)
            ),
            CalibrateError::NotFinite { layer, channel } => {
                write!(f, "BatchNorm `{}`: the batch statistics of channel {channel} are not finite", escaped(layer))
            }
            CalibrateError::NoBatches => f.write_str("no batch has been calibrated"),
            CalibrateError::Derived { tensor, index, value, cause } => {
                write!(f, "derived tensor `{tensor}` is {value} at flat index {index}: {cause}")
            }
        }
    }
}

impl std::error::Error for CalibrateError {}

impl From<RunError> for CalibrateError {
    fn from(e: RunError) -> CalibrateError {
        CalibrateError::Run(e)
    }
}

/// The re-estimated statistics of one BatchNorm, under its PyTorch name:
/// `<name>.running_mean`, `<name>.running_var`.
#[derive(Clone, Debug, PartialEq)]
pub struct BnStats {
    pub name: String,
    pub running_mean: Vec<f32>,
    pub running_var: Vec<f32>,
}

/// One BatchNorm of the schedule and its accumulators.
struct Layer {
    info: BnInfo,
    step: usize,
    /// The step computing the BatchNorm's input: the original step with only the folded
    /// conv bias as its epilogue.
    pre: Step,
    act: Option<Activation>,
    /// A fused adapter after the BatchNorm, before its activation: applied to the
    /// normalised output, as the step applies it to its own.
    adapter: Option<AdapterSpec>,
    /// Sums over committed batches of the batch mean and the unbiased batch variance.
    sum_mean: Vec<f64>,
    sum_var: Vec<f64>,
    /// The current batch's mean and unbiased variance, committed when the batch succeeds.
    batch_mean: Vec<f64>,
    batch_var: Vec<f64>,
}

/// Re-estimates BatchNorm statistics (AdaBN) by running a plan's base model over batches;
/// see the [module docs](self).
///
/// ```no_run
/// # use std::sync::Arc;
/// # use readi_runtime::{calibrate::BnCalibrator, exec::Input, plan::Plan};
/// # fn f(plan: Arc<Plan>, batches: &[Vec<f32>]) -> Result<(), Box<dyn std::error::Error>> {
/// let mut cal = BnCalibrator::new(plan, 2)?;
/// for b in batches {
///     cal.add_batch(&[Input { name: "image", data: b, shape: &[2, 3, 32, 32] }])?;
/// }
/// for s in cal.statistics()? {
///     println!("{}.running_mean: {:?}", s.name, &s.running_mean[..4]);
/// }
/// # Ok(()) }
/// ```
pub struct BnCalibrator {
    session: Session,
    layers: Vec<Layer>,
    /// Per step of the schedule, the index of its BatchNorm in `layers`.
    at_step: Vec<Option<usize>>,
    batches: usize,
    samples: usize,
}

impl BnCalibrator {
    /// A calibrator for `plan`'s BatchNorm layers, running on `threads` threads. Fails if
    /// the model has none, or if the plan does not record them (compiled by an older
    /// readi: every BatchNorm whose statistics the plan uses needs its [`BnInfo`]).
    pub fn new(plan: Arc<Plan>, threads: usize) -> Result<BnCalibrator, CalibrateError> {
        BnCalibrator::with_options(plan, SessionOptions { threads, ..SessionOptions::default() })
    }

    /// [`BnCalibrator::new`] with the session's options: threads and the memory limit
    /// every batch is bound under.
    pub fn with_options(plan: Arc<Plan>, options: SessionOptions) -> Result<BnCalibrator, CalibrateError> {
        let m = &plan.manifest;
        let mut layers = Vec::new();
        let mut at_step = vec![None; m.steps.len()];
        for (k, step) in m.steps.iter().enumerate() {
            let Some(ep) = step.kernel.epilogue() else { continue };
            let Some(info) = &ep.bn else { continue };
            // The BatchNorm's input: the conv plus its own bias, or the affine's input.
            let identity = EpilogueSpec { scale: None, shift: info.conv_bias, act: None, bn: None };
            let kernel = match &step.kernel {
                // A fused LoRA branch is part of what the BatchNorm reads.
                // A fused adapter reads the BatchNorm's output: not part of its input.
                // So is a channel scale on its input (the step's last input, which the
                // stand-in reads as its last too).
                Kernel::Conv2d { conv, algo, weight, lora, switch, channel_scale, .. } => Kernel::Conv2d {
                    conv: conv.clone(),
                    algo: *algo,
                    weight: *weight,
                    epilogue: identity,
                    lora: *lora,
                    switch: *switch,
                    adapter: None,
                    residual: false,
                    channel_scale: *channel_scale,
                },
                // Validation: a BnInfo is only on conv and channel-affine steps.
                Kernel::ChannelAffine { affine, .. } => {
                    Kernel::ChannelAffine { affine: affine.clone(), epilogue: identity }
                }
                _ => continue,
            };
            let pre = Step { path: step.path.clone(), kernel, inputs: step.inputs.clone(), output: step.output };
            let c = m.tensors[info.weight].numel();
            at_step[k] = Some(layers.len());
            layers.push(Layer {
                info: info.clone(),
                step: k,
                pre,
                act: ep.act,
                adapter: step.kernel.adapter().copied(),
                sum_mean: vec![0.0; c],
                sum_var: vec![0.0; c],
                batch_mean: vec![0.0; c],
                batch_var: vec![0.0; c],
            });
        }
        // Every BatchNorm the plan folded (its running mean went into a step) must be
        // recorded; a plan from before BnInfo existed records none.
        let recorded: HashSet<&str> = layers.iter().map(|l| l.info.name.as_str()).collect();
        let folded: Vec<&str> = m
            .params
            .iter()
            .filter(|p| p.stored_as.starts_with("folded into"))
            .filter_map(|p| p.name.strip_suffix(".running_mean"))
            .collect();
        let missing: Vec<String> = folded.iter().filter(|n| !recorded.contains(*n)).map(|n| n.to_string()).collect();
        if !missing.is_empty() {
            return Err(CalibrateError::NotRecorded { missing });
        }
        if layers.is_empty() {
            return Err(CalibrateError::NoBatchNorm { model: m.model.clone() });
        }
        let session = Session::with_options(plan, options)?;
        Ok(BnCalibrator { session, layers, at_step, batches: 0, samples: 0 })
    }

    /// The BatchNorm layers' names, in schedule order.
    pub fn layers(&self) -> impl ExactSizeIterator<Item = &str> {
        self.layers.iter().map(|l| l.info.name.as_str())
    }

    /// Batches calibrated so far.
    pub fn batches(&self) -> usize {
        self.batches
    }

    /// Samples calibrated so far: the sum of the batches' sizes (axis 0 of the first input).
    pub fn samples(&self) -> usize {
        self.samples
    }

    pub fn threads(&self) -> usize {
        self.session.threads()
    }

    /// Runs the base model on one batch (inputs as for [`Session::run`]) and adds its
    /// statistics. A failed batch adds nothing.
    pub fn add_batch(&mut self, inputs: &[Input<'_>]) -> Result<(), CalibrateError> {
        let BnCalibrator { session, layers, at_step, .. } = self;
        session.run_custom(inputs, |run, bound, threads| Ok(execute(run, bound, threads, layers, at_step)))??;
        for l in layers.iter_mut() {
            for (s, b) in l.sum_mean.iter_mut().zip(&l.batch_mean) {
                *s += b;
            }
            for (s, b) in l.sum_var.iter_mut().zip(&l.batch_var) {
                *s += b;
            }
        }
        self.batches += 1;
        self.samples += inputs.first().and_then(|i| i.shape.first()).copied().unwrap_or(1);
        Ok(())
    }

    /// The running statistics over the batches so far, one entry per BatchNorm in
    /// schedule order.
    pub fn statistics(&self) -> Result<Vec<BnStats>, CalibrateError> {
        if self.batches == 0 {
            return Err(CalibrateError::NoBatches);
        }
        let k = self.batches as f64;
        let average = |name: &str, what: &str, sums: &[f64]| -> Result<Vec<f32>, CalibrateError> {
            let out: Vec<f32> = sums.iter().map(|s| (s / k) as f32).collect();
            match out.iter().position(|x| !x.is_finite()) {
                None => Ok(out),
                Some(i) => Err(CalibrateError::Derived {
                    tensor: format!("{name}.{what}"),
                    index: i,
                    value: out[i],
                    cause: format!(
                        "the average over {} batches of the batch statistic of channel {i}, {:e}, overflows f32",
                        self.batches,
                        sums[i] / k
                    ),
                }),
            }
        };
        self.layers
            .iter()
            .map(|l| {
                Ok(BnStats {
                    name: l.info.name.clone(),
                    running_mean: average(&l.info.name, "running_mean", &l.sum_mean)?,
                    running_var: average(&l.info.name, "running_var", &l.sum_var)?,
                })
            })
            .collect()
    }
}

/// The schedule with every BatchNorm in train mode; see the module docs. Buffers taken
/// out are always put back, so the session stays usable after an error.
fn execute(
    run: &Run<'_>,
    bound: &mut Bound,
    threads: usize,
    layers: &mut [Layer],
    at_step: &[Option<usize>],
) -> Result<(), CalibrateError> {
    let m = &run.plan.manifest;
    // Checked first, so that a batch fails before it changes anything.
    for l in layers.iter() {
        let shape = &bound.shapes[m.steps[l.step].output];
        let numel: usize = shape.iter().product();
        let c = shape.get(1).copied().unwrap_or(0);
        if shape.len() < 2 || c == 0 || c != l.sum_mean.len() {
            return Err(RunError::BadPlan {
                step: m.steps[l.step].path.clone(),
                detail: format!("BatchNorm `{}` of {} channels on shape {shape:?}", l.info.name, l.sum_mean.len()),
            }
            .into());
        }
        if numel / c < 2 {
            return Err(CalibrateError::OneValue { layer: l.info.name.clone(), shape: shape.clone() });
        }
    }
    for (k, step) in m.steps.iter().enumerate() {
        let Storage::Slot(out_slot) = m.values[step.output].storage else {
            return Err(crate::exec::bad(&step.path, "output is not an activation buffer").into());
        };
        if step.is_view(&m.values) {
            continue;
        }
        let mut out_buf = std::mem::take(&mut bound.slots[out_slot]);
        let out_len: usize = bound.shapes[step.output].iter().product();
        let mut scratch = std::mem::take(&mut bound.scratch);
        let result = {
            let b: &Bound = bound;
            let out = &mut out_buf[..out_len];
            match at_step[k].map(|i| &mut layers[i]) {
                None => run_step(run, b, k, step, out, &mut scratch, threads).map_err(|d| step_error(step, d)),
                Some(layer) => run_step(run, b, k, &layer.pre, out, &mut scratch, threads)
                    .map_err(|d| step_error(step, d))
                    .and_then(|()| {
                        let shape = &b.shapes[step.output];
                        // The base's: no variant replaces these.
                        let gamma = run.plan.tensor(layer.info.weight);
                        let beta = run.plan.tensor(layer.info.bias);
                        let adapted = layer.adapter.zip(b.convs[k].as_ref());
                        // A residual conv adds its second input after the BatchNorm (and
                        // the adapter), before the activation.
                        let res = matches!(step.kernel, Kernel::Conv2d { residual: true, .. })
                            .then(|| crate::exec::value_slice(run, b, step.inputs[1]));
                        let act_now = adapted.is_none() && res.is_none();
                        train_mode_batchnorm(layer, act_now, out, shape[0], shape[1], gamma, beta).map(|()| {
                            if let Some((a, (s, _))) = adapted {
                                let ad = crate::exec::adapter_of(run, &a);
                                let act = layer.act.filter(|_| res.is_none());
                                crate::kernels::conv::adapter_after(s, &ad, out, act, &mut scratch, threads);
                            }
                            if let Some(r) = res {
                                crate::kernels::elementwise::add_in_place(out, r, layer.act);
                            }
                        })
                    }),
            }
        };
        bound.scratch = scratch;
        bound.slots[out_slot] = out_buf;
        result?;
    }
    Ok(())
}

/// A step that refused its data, as the calibration's error.
fn step_error(step: &Step, detail: String) -> CalibrateError {
    RunError::Step { step: step.path.clone(), detail }.into()
}

/// Elements per parallel task, roughly.
const CHUNK: usize = 1 << 14;

/// Computes the batch statistics of `x` (`[n, c, inner]`) into the layer's batch
/// accumulators and normalises `x` with them in place: `y = (x - mean) / sqrt(var + eps)
/// * gamma + beta` with the biased variance, then the step's fused activation if `act`.
///
/// `act` is false for a step whose fused adapter or residual input comes between the two.
fn train_mode_batchnorm(
    layer: &mut Layer,
    act: bool,
    x: &mut [f32],
    n: usize,
    c: usize,
    gamma: &[f32],
    beta: &[f32],
) -> Result<(), CalibrateError> {
    let inner = x.len() / (n * c).max(1);
    let count = (n * inner) as f64;
    let xs: &[f32] = x;
    // Two passes per channel in f64: the mean, then the squared deviations.
    let stats: Vec<(f64, f64)> = (0..c)
        .into_par_iter()
        .with_min_len((CHUNK / (n * inner).max(1)).max(1))
        .map(|ch| {
            let rows = || (0..n).map(move |i| &xs[(i * c + ch) * inner..(i * c + ch + 1) * inner]);
            let mean = rows().flatten().map(|&v| v as f64).sum::<f64>() / count;
            let ss = rows().flatten().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>();
            (mean, ss / count)
        })
        .collect();
    let mut affine = Vec::with_capacity(c);
    for (ch, &(mean, var)) in stats.iter().enumerate() {
        let unbiased = var * count / (count - 1.0);
        if !(mean.is_finite() && unbiased.is_finite()) {
            return Err(CalibrateError::NotFinite { layer: layer.info.name.clone(), channel: ch });
        }
        layer.batch_mean[ch] = mean;
        layer.batch_var[ch] = unbiased;
        let (a, b) = batchnorm_channel(gamma[ch] as f64, beta[ch] as f64, mean, var, layer.info.eps);
        let (a, b) = (a as f32, b as f32);
        if !(a.is_finite() && b.is_finite()) {
            let name = &layer.info.name;
            let (what, value) = if a.is_finite() { ("shift", b) } else { ("scale", a) };
            return Err(CalibrateError::Derived {
                tensor: format!("{name}@{what} (train mode)"),
                index: ch,
                value,
                cause: format!(
                    "from `{name}.weight[{ch}]` = {:e}, `{name}.bias[{ch}]` = {:e}, batch mean {mean:e} and variance \
                     {var:e} with eps {:e}: gamma / sqrt(var + eps) overflows f32",
                    gamma[ch], beta[ch], layer.info.eps
                ),
            });
        }
        affine.push((a, b));
    }
    let relu = act && layer.act == Some(Activation::Relu);
    x.par_chunks_mut(inner.max(1)).with_min_len((CHUNK / inner.max(1)).max(1)).enumerate().for_each(|(row, xs)| {
        let (a, b) = affine[row % c];
        for v in xs {
            let y = *v * a + b;
            *v = if relu { crate::kernels::elementwise::relu(y) } else { y };
        }
    });
    if let Some(f) = layer.act.filter(|a| act && *a != Activation::Relu) {
        crate::kernels::elementwise::activation_in_place(f, x);
    }
    Ok(())
}
