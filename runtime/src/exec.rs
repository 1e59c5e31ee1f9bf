//! Executing a plan.
//!
//! A [`Session`] owns a thread pool and the activation buffers of one plan. The first run
//! (and any run with a new batch size) *binds* the plan: it evaluates every value's shape
//! from the inputs', checks each step against its kernel's requirements (a plan file is
//! untrusted), and allocates one buffer per slot of the plan's buffer plan plus the
//! kernels' scratch. Later runs at the same batch size allocate nothing in the executor
//! but the output tensors they return (`runtime/tests/allocations.rs` counts; some
//! kernels still allocate small per-call work lists: conv, the GEMM, matmul, permute,
//! mean and broadcasting binary ops); weights are read in place from the plan.
//!
//! An `optional` input that is not given is zero-filled.
//!
//! # Variants
//!
//! A session's active variant (see [`crate::plan`]) is an atomic index shared with every
//! [`VariantSwitch`] handle taken from it. Switching looks the key up and stores the
//! index: no weight is copied or rewritten and nothing is allocated, and it may happen
//! from any thread while a run is in progress. A run loads the index once, at its start,
//! and resolves every tensor access through that variant's map, so each run sees exactly
//! one variant.

use std::collections::HashMap;
use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use readi_plan::ops::Pure;

use crate::kernels::conv::{self, Conv2dShape, ConvAlgo};
use crate::kernels::pool::{self, Pool2dShape};
use crate::kernels::resize;
use crate::kernels::{Epilogue, elementwise, layout, linear, norm, reduce, softmax};
use crate::plan::{EpilogueSpec, Kernel, Plan, Step, Storage, VariantTensors, show_shape};

/// A dense f32 tensor returned by a run.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// An input given to a run: name, data, shape.
#[derive(Clone, Copy, Debug)]
pub struct Input<'a> {
    pub name: &'a str,
    pub data: &'a [f32],
    pub shape: &'a [usize],
}

/// Why a run failed.
#[derive(Clone, Debug, PartialEq)]
pub enum RunError {
    /// An input the model does not have.
    UnknownInput { name: String, known: Vec<String> },
    /// A required input that was not given.
    MissingInput { name: String },
    /// An input given twice.
    DuplicateInput { name: String },
    /// An input whose shape does not fit the declared one.
    InputShape { name: String, expected: String, got: Vec<usize>, detail: String },
    /// Data length and shape disagree.
    InputLength { name: String, len: usize, shape: Vec<usize> },
    /// A NaN or infinity in an input.
    NotFinite { name: String, index: usize, value: f32 },
    /// The plan is inconsistent (a corrupted or hand-edited file).
    BadPlan { step: String, detail: String },
    /// The thread pool could not be created.
    Threads(String),
    /// A variant key the plan does not have.
    UnknownVariant { key: String, known: Vec<String>, nearest: Option<String> },
    /// A variant index past the plan's variants.
    VariantIndex { index: usize, count: usize },
}

/// Most keys an [`RunError::UnknownVariant`] message lists.
const KEYS_SHOWN: usize = 24;

impl fmt::Display for RunError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RunError::UnknownInput { name, known } => {
                write!(f, "the model has no input `{name}` (its inputs: {})", known.join(", "))
            }
            RunError::MissingInput { name } => write!(f, "input `{name}` is required but was not given"),
            RunError::DuplicateInput { name } => write!(f, "input `{name}` is given twice"),
            RunError::InputShape { name, expected, got, detail } => {
                write!(f, "input `{name}` has shape {got:?}, but the model expects {expected}: {detail}")
            }
            RunError::InputLength { name, len, shape } => {
                write!(f, "input `{name}`: {len} values do not fill shape {shape:?}")
            }
            RunError::NotFinite { name, index, value } => {
                write!(f, "input `{name}` holds {value} at flat index {index}; inputs must be finite")
            }
            RunError::BadPlan { step, detail } => write!(f, "invalid plan at {step}: {detail}"),
            RunError::Threads(e) => write!(f, "cannot start the thread pool: {e}"),
            RunError::UnknownVariant { key, known, nearest } => {
                write!(f, "the plan has no variant `{key}`")?;
                if let Some(near) = nearest {
                    write!(f, "; did you mean `{near}`?")?;
                }
                let shown: Vec<&str> = known.iter().take(KEYS_SHOWN).map(String::as_str).collect();
                write!(f, " (its variants: {}", shown.join(", "))?;
                if known.len() > KEYS_SHOWN {
                    write!(f, " and {} more", known.len() - KEYS_SHOWN)?;
                }
                f.write_str(")")
            }
            RunError::VariantIndex { index, count } => {
                write!(f, "variant index {index} is out of range: the plan has {count} variants (0 is the base)")
            }
        }
    }
}

impl std::error::Error for RunError {}

/// Runs one plan; reuses its buffers across runs.
pub struct Session {
    plan: Arc<Plan>,
    pool: rayon::ThreadPool,
    threads: usize,
    /// The active variant's index, shared with every [`VariantSwitch`]; always a valid
    /// index (stores are checked).
    active: Arc<AtomicUsize>,
    /// The variant the last successful run used.
    last_variant: Option<usize>,
    bound: Option<Bound>,
    /// Per plan input, the position in the caller's list of the input of that name.
    /// Refilled by every run; kept so that a run does not allocate it.
    given: Vec<Option<usize>>,
    /// The symbol values of the current run in `manifest.symbols` order (0: not bound
    /// yet). Refilled by every run.
    symbols: Vec<usize>,
    /// Accumulated seconds per step, when profiling.
    profile: Option<Vec<f64>>,
}

/// Everything that depends on the bound symbol values.
pub(crate) struct Bound {
    /// The symbol values the buffers were made for, in `manifest.symbols` order.
    symbols: Vec<usize>,
    pub(crate) shapes: Vec<Vec<usize>>,
    pub(crate) slots: Vec<Vec<f32>>,
    pub(crate) scratch: Vec<f32>,
    /// Per step, the conv parameters (for conv steps).
    pub(crate) convs: Vec<Option<(Conv2dShape, ConvAlgo)>>,
    /// Zero-filled buffers for absent optional inputs, by input index.
    zeros: Vec<Vec<f32>>,
}

/// What one run reads besides its buffers: the stored tensors under the run's variant
/// and the caller's inputs.
#[derive(Clone, Copy)]
pub(crate) struct Run<'a> {
    pub(crate) plan: &'a Plan,
    weights: VariantTensors<'a>,
    inputs: &'a [Input<'a>],
    /// [`Session::given`].
    given: &'a [Option<usize>],
}

pub(crate) fn bad(step: &str, detail: impl Into<String>) -> RunError {
    RunError::BadPlan { step: step.to_string(), detail: detail.into() }
}

impl Session {
    /// A session running `plan` on `threads` threads (at least 1), under the base
    /// variant.
    pub fn new(plan: Arc<Plan>, threads: usize) -> Result<Session, RunError> {
        let threads = threads.max(1);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("readi-{i}"))
            .build()
            .map_err(|e| RunError::Threads(e.to_string()))?;
        let given = Vec::with_capacity(plan.manifest.inputs.len());
        let symbols = vec![0; plan.manifest.symbols.len()];
        Ok(Session {
            plan,
            pool,
            threads,
            active: Arc::new(AtomicUsize::new(0)),
            last_variant: None,
            bound: None,
            given,
            symbols,
            profile: None,
        })
    }

    /// Starts (or restarts) accumulating the time each step takes across runs.
    pub fn enable_profiling(&mut self) {
        self.profile = Some(vec![0.0; self.plan.manifest.steps.len()]);
    }

    /// Seconds spent in each step since profiling was enabled, in schedule order.
    pub fn profile(&self) -> Option<&[f64]> {
        self.profile.as_deref()
    }

    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Makes variant `key` ([`BASE_VARIANT`](crate::plan::BASE_VARIANT) for the base)
    /// active for the runs that start from now on. A run in progress keeps its variant.
    /// Copies no weights and allocates nothing (except for the error of an unknown key).
    pub fn set_variant(&self, key: &str) -> Result<(), RunError> {
        select(&self.plan, &self.active, key)
    }

    /// The active variant's key: the one the next run will use, unless it is switched
    /// before.
    pub fn variant(&self) -> &str {
        self.plan.variant_key(self.active.load(Ordering::Acquire))
    }

    /// A handle that switches this session's variant, for another thread (or many).
    pub fn switch_handle(&self) -> VariantSwitch {
        VariantSwitch { plan: Arc::clone(&self.plan), active: Arc::clone(&self.active) }
    }

    /// The index of the variant the last successful run used (its key:
    /// [`Plan::variant_key`]), or `None` before the first.
    pub fn last_variant(&self) -> Option<usize> {
        self.last_variant
    }

    /// Runs the plan under the active variant. Inputs are matched by name; absent
    /// `optional` inputs are zeros. Returns the outputs in the plan's order, with their
    /// names.
    pub fn run(&mut self, inputs: &[Input<'_>]) -> Result<Vec<(String, Tensor)>, RunError> {
        // The run's only read of the active variant: every tensor access below resolves
        // through this variant's map, whatever switches happen meanwhile.
        let variant = self.active.load(Ordering::Acquire);
        let plan = Arc::clone(&self.plan);
        let m = &plan.manifest;
        let weights = plan
            .variant_tensors(variant)
            .ok_or(RunError::VariantIndex { index: variant, count: plan.variant_count() })?;
        self.prepare(&plan, inputs)?;
        let Some(bound) = self.bound.as_mut() else { return Err(bad("bind", "no buffers")) };
        let run = Run { plan: &plan, weights, inputs, given: &self.given };
        let threads = self.threads;
        let profile = self.profile.as_deref_mut();
        self.pool.install(|| execute(&run, bound, threads, profile))?;
        let bound: &Bound = bound;
        let mut out = Vec::with_capacity(m.outputs.len());
        for o in &m.outputs {
            let data = value_slice(&run, bound, o.value).to_vec();
            out.push((o.name.clone(), Tensor { shape: bound.shapes[o.value].clone(), data }));
        }
        self.last_variant = Some(variant);
        Ok(out)
    }

    /// Runs `exec` on the session's thread pool in place of the normal executor, under the
    /// base model, with the inputs matched, checked and the buffers bound as for a run.
    /// For calibration ([`crate::calibrate`]), which needs to see inside the steps.
    pub(crate) fn run_custom<T>(
        &mut self,
        inputs: &[Input<'_>],
        exec: impl FnOnce(&Run<'_>, &mut Bound, usize) -> Result<T, RunError> + Send,
    ) -> Result<T, RunError>
    where
        T: Send,
    {
        let plan = Arc::clone(&self.plan);
        self.prepare(&plan, inputs)?;
        let Some(bound) = self.bound.as_mut() else { return Err(bad("bind", "no buffers")) };
        let run = Run { plan: &plan, weights: plan.base_tensors(), inputs, given: &self.given };
        let threads = self.threads;
        self.pool.install(|| exec(&run, bound, threads))
    }

    /// Matches the inputs to the plan's by name, binds the symbols, checks the inputs and
    /// (re)binds the buffers when the symbol values changed.
    fn prepare(&mut self, plan: &Plan, inputs: &[Input<'_>]) -> Result<(), RunError> {
        let m = &plan.manifest;
        // Match inputs to the plan's.
        self.given.clear();
        self.given.resize(m.inputs.len(), None);
        for (pos, inp) in inputs.iter().enumerate() {
            match m.inputs.iter().position(|s| s.name == inp.name) {
                Some(i) if self.given[i].is_some() => return Err(RunError::DuplicateInput { name: inp.name.into() }),
                Some(i) => self.given[i] = Some(pos),
                None => {
                    return Err(RunError::UnknownInput {
                        name: inp.name.into(),
                        known: m.inputs.iter().map(|s| s.name.clone()).collect(),
                    });
                }
            }
        }
        self.bind_symbols(inputs)?;
        for (spec, g) in m.inputs.iter().zip(&self.given) {
            if let Some(pos) = *g
                && let Some(index) = inputs[pos].data.iter().position(|v| !v.is_finite())
            {
                return Err(RunError::NotFinite { name: spec.name.clone(), index, value: inputs[pos].data[index] });
            }
        }
        if self.bound.as_ref().is_none_or(|b| b.symbols != self.symbols) {
            self.bound = Some(bind(plan, &self.symbols, self.threads)?);
        }
        Ok(())
    }

    /// Binds the symbols from the given inputs' shapes into `self.symbols` and checks every
    /// given input (`self.given`). Allocates nothing unless it fails.
    fn bind_symbols(&mut self, inputs: &[Input<'_>]) -> Result<(), RunError> {
        let m = &self.plan.manifest;
        let symbols = &mut self.symbols;
        symbols.fill(0);
        for (spec, g) in m.inputs.iter().zip(&self.given) {
            let Some(inp) = g.map(|pos| &inputs[pos]) else {
                if !spec.optional {
                    return Err(RunError::MissingInput { name: spec.name.clone() });
                }
                continue;
            };
            let shape_err = |detail: String| RunError::InputShape {
                name: spec.name.clone(),
                expected: show_shape(&spec.shape),
                got: inp.shape.to_vec(),
                detail,
            };
            if inp.shape.len() != spec.shape.len() {
                return Err(shape_err(format!("{} axes instead of {}", inp.shape.len(), spec.shape.len())));
            }
            let numel = inp.shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
            if numel != Some(inp.data.len()) {
                return Err(RunError::InputLength {
                    name: spec.name.clone(),
                    len: inp.data.len(),
                    shape: inp.shape.to_vec(),
                });
            }
            for (axis, (d, &got)) in spec.shape.iter().zip(inp.shape).enumerate() {
                match d.symbols() {
                    [] => {
                        if d.coef() as usize != got {
                            return Err(shape_err(format!("axis {axis} must be {}", d.coef())));
                        }
                    }
                    [s] => {
                        let c = d.coef().max(1) as usize;
                        if got == 0 || got % c != 0 {
                            return Err(shape_err(format!("axis {axis} must be a positive multiple of {c}")));
                        }
                        let v = got / c;
                        // Validation: every symbol of an input's shape is one of the plan's.
                        let Some(k) = m.symbols.iter().position(|x| x == s) else {
                            return Err(bad(&format!("input `{}`", spec.name), format!("unknown symbol `{s}`")));
                        };
                        match symbols[k] {
                            0 => symbols[k] = v,
                            prev if prev != v => {
                                return Err(shape_err(format!(
                                    "axis {axis} gives {s} = {v}, another input gave {prev}"
                                )));
                            }
                            _ => {}
                        }
                    }
                    _ => {
                        return Err(shape_err(format!(
                            "axis {axis} has a product of symbols, which inputs cannot bind"
                        )));
                    }
                }
            }
        }
        for v in symbols.iter_mut().filter(|v| **v == 0) {
            // Every input that carries this symbol is absent: a batch of one.
            *v = 1;
        }
        Ok(())
    }
}

/// Switches the variant of the session it was taken from ([`Session::switch_handle`]),
/// from any thread, while that session runs or not. Cheap to clone; every clone switches
/// the same session.
#[derive(Clone)]
pub struct VariantSwitch {
    plan: Arc<Plan>,
    active: Arc<AtomicUsize>,
}

impl VariantSwitch {
    /// Makes variant `key` active for the runs that start from now on: a lookup that
    /// allocates nothing and an atomic store. A run in progress keeps its variant.
    pub fn set(&self, key: &str) -> Result<(), RunError> {
        select(&self.plan, &self.active, key)
    }

    /// As [`set`](VariantSwitch::set), by index (0 is the base).
    pub fn set_index(&self, index: usize) -> Result<(), RunError> {
        let count = self.plan.variant_count();
        if index >= count {
            return Err(RunError::VariantIndex { index, count });
        }
        self.active.store(index, Ordering::Release);
        Ok(())
    }

    /// The active variant's index.
    pub fn index(&self) -> usize {
        self.active.load(Ordering::Acquire)
    }

    /// The active variant's key.
    pub fn key(&self) -> &str {
        self.plan.variant_key(self.index())
    }
}

impl fmt::Debug for VariantSwitch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VariantSwitch").field("active", &self.key()).finish()
    }
}

/// Looks `key` up and stores its index; the lookup is a binary search over the plan's
/// keys, so nothing is allocated unless the key is unknown.
fn select(plan: &Plan, active: &AtomicUsize, key: &str) -> Result<(), RunError> {
    let Some(i) = plan.variant_index(key) else {
        let known: Vec<String> = plan.variant_keys().map(str::to_string).collect();
        let nearest = nearest_key(key, &known).map(str::to_string);
        return Err(RunError::UnknownVariant { key: key.to_string(), known, nearest });
    };
    active.store(i, Ordering::Release);
    Ok(())
}

/// The known key closest to `key` by edit distance (ignoring case), if it is close: at
/// most a third of the key's length, and at least 1, edits away.
fn nearest_key<'a>(key: &str, known: &'a [String]) -> Option<&'a str> {
    let key = key.to_lowercase();
    let limit = (key.chars().count() / 3).max(1);
    known
        .iter()
        .map(|k| (edit_distance(&key, &k.to_lowercase()), k.as_str()))
        .filter(|&(d, _)| d <= limit)
        .min_by_key(|&(d, _)| d)
        .map(|(_, k)| k)
}

/// Levenshtein distance over chars.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diag = row[0];
        row[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let next = (diag + usize::from(ca != cb)).min(row[j] + 1).min(row[j + 1] + 1);
            diag = row[j + 1];
            row[j + 1] = next;
        }
    }
    row[b.len()]
}

/// Evaluates shapes, checks the steps, and allocates buffers for one binding of the
/// symbols (values in `manifest.symbols` order).
///
/// The checks read the base's tensors. Every variant's replacement has exactly its base
/// tensor's shape (checked when the plan was built), so they hold under every variant
/// and a switch needs no new check.
fn bind(plan: &Plan, symbols: &[usize], threads: usize) -> Result<Bound, RunError> {
    let m = &plan.manifest;
    let base = plan.base_tensors();
    let bindings: HashMap<String, usize> = m.symbols.iter().cloned().zip(symbols.iter().copied()).collect();
    let mut shapes = Vec::with_capacity(m.values.len());
    for (i, v) in m.values.iter().enumerate() {
        let s: Option<Vec<usize>> = v.shape.iter().map(|d| d.eval(&bindings)).collect();
        let s = s.ok_or_else(|| bad(&format!("value {i}"), "a dimension cannot be evaluated"))?;
        if s.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).is_none_or(|n| n > (1usize << 36)) {
            return Err(bad(&format!("value {i}"), format!("shape {s:?} is too large")));
        }
        shapes.push(s);
    }
    let numel = |i: usize| shapes[i].iter().product::<usize>();
    let mut slot_len = vec![0usize; m.slots];
    for (i, v) in m.values.iter().enumerate() {
        match v.storage {
            Storage::Slot(s) => slot_len[s] = slot_len[s].max(numel(i)),
            Storage::Tensor(t) => {
                if base.get(t).len() != numel(i) {
                    return Err(bad(&format!("value {i}"), "stored tensor does not match the value's shape"));
                }
            }
            Storage::Input(_) => {}
        }
    }
    let mut convs = Vec::with_capacity(m.steps.len());
    let mut scratch = 0usize;
    for (k, step) in m.steps.iter().enumerate() {
        let at = format!("step {k} (`{}`)", step.path);
        let conv = conv_params(step, &shapes, &at)?;
        if let Some((s, algo)) = &conv {
            scratch = scratch.max(conv::scratch_len(s, *algo, threads));
        }
        convs.push(conv);
    }
    let zeros =
        m.inputs.iter().map(|spec| if spec.optional { vec![0.0; numel(spec.value)] } else { Vec::new() }).collect();
    Ok(Bound {
        symbols: symbols.to_vec(),
        shapes,
        slots: slot_len.into_iter().map(|n| vec![0.0; n]).collect(),
        scratch: vec![0.0; scratch],
        convs,
        zeros,
    })
}

/// The conv parameters of a conv step at the bound shapes. Every other requirement of a
/// step (its shapes against its operator's rule, its tensors' sizes, the conv's algorithm
/// and packed weight) was checked when the plan was built, on its symbolic shapes, so it
/// holds at every batch size.
fn conv_params(step: &Step, shapes: &[Vec<usize>], at: &str) -> Result<Option<(Conv2dShape, ConvAlgo)>, RunError> {
    let Kernel::Conv2d { conv, algo, .. } = &step.kernel else { return Ok(None) };
    let algo = *algo;
    let x = &shapes[step.inputs[0]];
    let s = conv::layer_shape(conv, x[0], x[2], x[3]);
    if shapes[step.output] != [s.n, s.cout, s.oh, s.ow] {
        return Err(bad(at, "conv2d output shape"));
    }
    Ok(Some((s, algo)))
}

/// The data of a value, stored tensors resolved under the run's variant.
fn value_slice<'a>(run: &Run<'a>, bound: &'a Bound, v: usize) -> &'a [f32] {
    let n: usize = bound.shapes[v].iter().product();
    match run.plan.manifest.values[v].storage {
        Storage::Input(i) => match run.given[i] {
            Some(pos) => run.inputs[pos].data,
            None => &bound.zeros[i],
        },
        Storage::Slot(s) => &bound.slots[s][..n],
        Storage::Tensor(t) => run.weights.get(t),
    }
}

fn epilogue<'a>(w: VariantTensors<'a>, e: &EpilogueSpec) -> Epilogue<'a> {
    Epilogue { scale: e.scale.map(|t| w.get(t)), shift: e.shift.map(|t| w.get(t)), relu: e.relu }
}

/// Runs every step in order. Allocates nothing: inputs are fetched by each kernel as
/// it needs them.
fn execute(run: &Run<'_>, bound: &mut Bound, threads: usize, mut profile: Option<&mut [f64]>) -> Result<(), RunError> {
    let m = &run.plan.manifest;
    for (k, step) in m.steps.iter().enumerate() {
        let start = profile.is_some().then(std::time::Instant::now);
        let Storage::Slot(out_slot) = m.values[step.output].storage else {
            return Err(bad(&step.path, "output is not an activation buffer"));
        };
        // Take the output buffer out so inputs can be borrowed alongside it; `bind`
        // checked that no step reads the slot it writes.
        let mut out_buf = std::mem::take(&mut bound.slots[out_slot]);
        let out_len: usize = bound.shapes[step.output].iter().product();
        let mut scratch = std::mem::take(&mut bound.scratch);
        {
            let b: &Bound = bound;
            let out = &mut out_buf[..out_len];
            run_step(run, b, step, b.convs[k].as_ref(), out, &mut scratch, threads);
        }
        bound.scratch = scratch;
        bound.slots[out_slot] = out_buf;
        if let (Some(p), Some(t)) = (profile.as_deref_mut(), start) {
            p[k] += t.elapsed().as_secs_f64();
        }
    }
    Ok(())
}

/// Runs one step, its shapes checked at bind time.
pub(crate) fn run_step(
    run: &Run<'_>,
    b: &Bound,
    step: &Step,
    conv_params: Option<&(Conv2dShape, ConvAlgo)>,
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) {
    let w = run.weights;
    let input = |j: usize| {
        let v = step.inputs[j];
        (value_slice(run, b, v), b.shapes[v].as_slice())
    };
    let out_shape = b.shapes[step.output].as_slice();
    // Every kernel takes at least one input (checked at bind time).
    let (x, xs) = input(0);
    match &step.kernel {
        Kernel::Conv2d { weight, epilogue: ep, .. } => {
            if let Some((s, algo)) = conv_params {
                conv::conv2d(s, *algo, w.get(*weight), &epilogue(w, ep), x, out, scratch, threads);
            }
        }
        Kernel::Linear { linear: l, weight, epilogue: ep } => {
            let fin = xs.last().copied().unwrap_or(1);
            let rows = x.len() / fin.max(1);
            let layout = linear::WeightLayout::InOut;
            let fout = l.out_features as usize;
            linear::linear(x, rows, fin, w.get(*weight), layout, fout, &epilogue(w, ep), out, threads);
        }
        Kernel::ChannelAffine { epilogue: ep, .. } => {
            let (n, c) = (xs[0], xs[1]);
            let inner = x.len() / (n * c).max(1);
            let e = epilogue(w, ep);
            norm::channel_affine(x, n, c, inner, e.scale, e.shift, e.relu, out);
        }
        Kernel::LayerNorm { norm: ln, weight, bias } => {
            let f = xs.last().copied().unwrap_or(1);
            let rows = x.len() / f.max(1);
            norm::layernorm(x, rows, f, weight.map(|t| w.get(t)), bias.map(|t| w.get(t)), ln.eps as f32, out);
        }
        Kernel::Pure(op) => match op {
            Pure::MatMul(_) => {
                let (y, ys) = input(1);
                linear::matmul(x, xs, y, ys, out, out_shape, threads);
            }
            Pure::Binary(op) => {
                let (y, ys) = input(1);
                elementwise::binary(*op, x, xs, y, ys, out, out_shape);
            }
            Pure::Scalar(s) => elementwise::scalar(s.op, x, s.value as f32, s.scalar_first, out),
            Pure::Activation(act) => elementwise::activation(*act, x, out),
            Pure::Softmax(s) => {
                let outer: usize = xs[..s.axis].iter().product();
                let inner: usize = xs[s.axis + 1..].iter().product();
                softmax::softmax(x, outer, xs[s.axis], inner, out);
            }
            Pure::Concat(c) => concat(step.inputs.len(), input, c.axis, out, out_shape),
            Pure::Reshape(_) => out.copy_from_slice(x),
            Pure::Permute(p) => layout::permute(x, xs, &p.perm, out),
            Pure::Pool(p) => {
                let s = Pool2dShape::of(p, xs[0] * xs[1], xs[2], xs[3]);
                pool::pool2d(p.kind, &s, x, out);
            }
            Pure::GlobalAvgPool(_) => pool::global_avgpool(x, xs[0] * xs[1], xs[2] * xs[3], out),
            Pure::Upsample(u) => {
                let scale = u.scale.map(|s| (s[0], s[1]));
                let (nc, h, wd) = (xs[0] * xs[1], xs[2], xs[3]);
                resize::upsample(u.mode, u.align_corners, scale, x, nc, h, wd, out, out_shape[2], out_shape[3]);
            }
            Pure::Mean(m) => reduce::mean(x, xs, &m.axes, out),
        },
    }
}

/// Outputs at least this long are copied in parallel.
const CONCAT_PAR_MIN: usize = 1 << 15;
/// Elements per parallel task.
const CONCAT_CHUNK: usize = 1 << 14;

/// Concatenation along `axis` of `count` inputs given by `part`, each copied into its
/// place in turn, so no list of inputs is built (the result is
/// [`layout::concat`]'s). Shapes were checked at bind time.
fn concat<'a>(
    count: usize,
    part: impl Fn(usize) -> (&'a [f32], &'a [usize]),
    axis: usize,
    out: &mut [f32],
    out_shape: &[usize],
) {
    let inner: usize = out_shape[axis + 1..].iter().product();
    let row = out_shape[axis] * inner;
    if row == 0 || out.is_empty() {
        return;
    }
    let outer = out.len() / row;
    let mut at = 0;
    for j in 0..count {
        let (d, s) = part(j);
        let n = s[axis] * inner;
        if n == 0 {
            continue;
        }
        let copy = |dst: &mut [f32], src: &[f32]| dst[at..at + n].copy_from_slice(src);
        if out.len() < CONCAT_PAR_MIN {
            out.chunks_mut(row).zip(d.chunks(n)).for_each(|(dst, src)| copy(dst, src));
        } else if outer > 1 {
            let min_rows = (CONCAT_CHUNK / row).max(1);
            out.par_chunks_mut(row).zip(d.par_chunks(n)).with_min_len(min_rows).for_each(|(dst, src)| copy(dst, src));
        } else {
            // One block per input: split the copy instead.
            out[at..at + n]
                .par_chunks_mut(CONCAT_CHUNK)
                .zip(d.par_chunks(CONCAT_CHUNK))
                .for_each(|(dst, src)| dst.copy_from_slice(src));
        }
        at += n;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn concat_by_parts_matches_the_kernel() {
        use crate::testdata::data;
        // (shapes of the parts, axis): small, empty parts, one big block per part and
        // many rows (both parallel paths).
        let cases: [(&[&[usize]], usize); 5] = [
            (&[&[2, 3, 4], &[2, 1, 4], &[2, 2, 4]], 1),
            (&[&[2, 0, 4], &[2, 3, 4], &[2, 0, 4]], 1),
            (&[&[3, 5], &[4, 5]], 0),
            (&[&[1, 40_000], &[1, 30_000]], 1),
            (&[&[600, 40, 2], &[600, 7, 2], &[600, 1, 2]], 1),
        ];
        for (k, (shapes, axis)) in cases.into_iter().enumerate() {
            let datas: Vec<Vec<f32>> =
                shapes.iter().enumerate().map(|(i, s)| data(s.iter().product(), (10 * k + i) as u64)).collect();
            let parts: Vec<(&[f32], &[usize])> = datas.iter().map(Vec::as_slice).zip(shapes.iter().copied()).collect();
            let mut out_shape = shapes[0].to_vec();
            out_shape[axis] = shapes.iter().map(|s| s[axis]).sum();
            let len = out_shape.iter().product();
            let mut want = vec![f32::NAN; len];
            layout::concat(&parts, axis, &mut want);
            let mut got = vec![f32::NAN; len];
            concat(parts.len(), |j| parts[j], axis, &mut got, &out_shape);
            assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "case {k}");
        }
    }

    #[test]
    fn near_keys_are_suggested() {
        assert_eq!(edit_distance("fog=0.05", "fog=0.5"), 1);
        assert_eq!(edit_distance("", "abc"), 3);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        let known: Vec<String> = ["base", "fog=0.05", "fog=0.1", "gamma=0.25"].map(String::from).to_vec();
        assert_eq!(nearest_key("fog=0.11", &known), Some("fog=0.1"));
        assert_eq!(nearest_key("Gamma=0.25", &known), Some("gamma=0.25"));
        assert_eq!(nearest_key("bas", &known), Some("base"));
        assert_eq!(nearest_key("snow=1", &known), None);
        assert_eq!(nearest_key("", &known), None);
    }
}
