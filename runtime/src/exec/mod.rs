//! Executing a plan.
//!
//! A [`Session`] owns a thread pool and the activation buffers of one plan. The first run
//! (and any run with a new batch size) *binds* the plan: it evaluates every value's shape
//! from the inputs' (the plan's load checked every step's shapes against its operator's
//! rule for any batch size, so binding only bounds the sizes and builds each conv's
//! parameters), and allocates one buffer per slot of the plan's buffer plan plus the
//! kernels' scratch. A run whose symbol values differ but need buffers of the same
//! lengths (a symbol only an input carries, such as a lidar sweep's point count) takes
//! the new shapes in the buffers it has. Later runs at the same batch size allocate
//! nothing in the executor but the output tensors they return
//! (`runtime/tests/allocations.rs` counts; some
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
//! one variant. A conv whose LoRA `A` the plan stores raw (a Winograd layer's) reads it
//! from a session-owned buffer, packed for its algorithm at the start of a run whose
//! variant differs from the one the buffer holds (`Bound::pack_lora`; microseconds for a
//! few small `A`s, nothing allocated). A variant's replacement stored as f16 is read the
//! same way, from a session-owned f32 copy (one per replaced tensor, allocated by the
//! first run) decoded at the start of a run whose variant differs from the copy's.
//!
//! An `lss_bev_pool` step (BEVFusion's view transform) keeps, per session, where its
//! frustum points land in the BEV grid (`Bound::bev`, sized at bind time): computed from
//! its calibration inputs by the first run, recomputed in place only by a run whose
//! calibration differs bit for bit from the last.
//!
//! # Where things are
//!
//! * this file: the types a caller sees ([`Tensor`], [`Input`], [`RunError`]) and
//!   [`Session`], which matches inputs, binds and runs;
//! * `bind.rs`: binding symbols, shapes, buffers and conv parameters (`Bound`);
//! * `run.rs`: executing the steps of a bound plan (`Run`, `run_step`);
//! * `awake.rs`: the other workers spinning through a run ([`SessionOptions::spin`]);
//! * `switch.rs`: [`VariantSwitch`] and the variant key lookup.

mod arena;
mod awake;
mod bind;
mod run;
mod switch;

use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use readi_plan::VariantKey;

use crate::plan::{Decoded, Plan, escaped};

pub(crate) use bind::Bound;
pub use bind::Footprint;
pub use bind::check_pure;
pub use run::run_pure;
pub(crate) use run::{Run, adapter_of, run_step, value_slice};
pub use switch::VariantSwitch;

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
    /// A step refused the data it was given (an index computed at run time out of range):
    /// checks only a run can make, of values rather than shapes.
    Step { step: String, detail: String },
    /// The thread pool could not be created.
    Threads(String),
    /// A variant key the plan does not have (`key` as given), or a text that is not a
    /// variant key at all (`malformed` says why).
    UnknownVariant { key: String, known: Vec<String>, nearest: Option<String>, malformed: Option<String> },
    /// A variant index past the plan's variants.
    VariantIndex { index: usize, count: usize },
    /// Binding at these shapes (`at`: `N = 4`) needs more memory than the session's
    /// limit; `largest` are the largest parts (description, bytes).
    OverBudget { needed: usize, limit: usize, at: String, largest: Vec<(String, usize)> },
    /// A size (of `what`) does not fit in the address space.
    TooLarge { what: String },
}

/// Checks that a run of `plan` on `inputs` fits `options.max_memory`, as the first run
/// of a session with these options would, without allocating: the inputs are matched and
/// their shapes bind the symbols, then the footprint is computed.
pub fn check_fits(plan: &Plan, inputs: &[Input<'_>], options: &SessionOptions) -> Result<Footprint, RunError> {
    let m = &plan.manifest;
    let mut given = Vec::new();
    bind::match_inputs(m, inputs, &mut given)?;
    let mut symbols = vec![0; m.symbols.len()];
    bind::bind_symbols(m, &given, inputs, &mut symbols)?;
    let footprint = bind::layout(plan, &symbols, options.threads.max(1))?.footprint;
    bind::within(&footprint, options.max_memory, m, &symbols)?;
    Ok(footprint)
}

/// The footprint of `plan` with every symbol bound to `batch`, on `threads` threads,
/// computed without allocating (see [`Footprint`]).
pub fn footprint(plan: &Plan, batch: usize, threads: usize) -> Result<Footprint, RunError> {
    let symbols = vec![batch; plan.manifest.symbols.len()];
    Ok(bind::layout(plan, &symbols, threads.max(1))?.footprint)
}

/// The footprint [`Plan::new`] records: every symbol bound to 1, one thread; `None`
/// when a shape overflows or a step fails its kernel's preconditions.
pub(crate) fn compiled_footprint(plan: &Plan) -> Option<readi_plan::format::PlanFootprint> {
    let symbols = vec![1; plan.manifest.symbols.len()];
    let f = bind::layout(plan, &symbols, 1).ok()?.footprint;
    let u = |n: usize| n as u64;
    Some(readi_plan::format::PlanFootprint {
        batch: 1,
        activations: u(f.activations),
        scratch: u(f.scratch),
        total: u(f.total),
    })
}

/// `1.5 GiB (1610612736 bytes)`.
pub fn show_bytes(n: usize) -> String {
    const UNITS: [&str; 5] = ["KiB", "MiB", "GiB", "TiB", "PiB"];
    if n < 1024 {
        return format!("{n} bytes");
    }
    let (mut v, mut unit) = (n as f64 / 1024.0, 0);
    while v >= 1024.0 && unit + 1 < UNITS.len() {
        v /= 1024.0;
        unit += 1;
    }
    format!("{v:.1} {} ({n} bytes)", UNITS[unit])
}

/// Most keys an [`RunError::UnknownVariant`] message lists.
const KEYS_SHOWN: usize = 24;

impl fmt::Display for RunError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Names come from the plan (or the caller): printed escaped.
        let e = |name: &str| escaped(name).into_owned();
        match self {
            RunError::UnknownInput { name, known } => {
                let known: Vec<String> = known.iter().map(|k| e(k)).collect();
                write!(f, "the model has no input `{}` (its inputs: {})", e(name), known.join(", "))
            }
            RunError::MissingInput { name } => write!(f, "input `{}` is required but was not given", e(name)),
            RunError::DuplicateInput { name } => write!(f, "input `{}` is given twice", e(name)),
            RunError::InputShape { name, expected, got, detail } => {
                write!(f, "input `{}` has shape {got:?}, but the model expects {expected}: {detail}", e(name))
            }
            RunError::InputLength { name, len, shape } => {
                write!(f, "input `{}`: {len} values do not fill shape {shape:?}", e(name))
            }
            RunError::NotFinite { name, index, value } => {
                write!(f, "input `{}` holds {value} at flat index {index}; inputs must be finite", e(name))
            }
            RunError::BadPlan { step, detail } => write!(f, "invalid plan at {}: {}", e(step), e(detail)),
            RunError::Step { step, detail } => write!(f, "{} cannot run on its inputs: {}", e(step), e(detail)),
            RunError::Threads(e) => write!(f, "cannot start the thread pool: {e}"),
            RunError::UnknownVariant { key, known, nearest, malformed } => {
                match malformed {
                    None => write!(f, "the plan has no variant `{}`", e(key))?,
                    Some(why) => write!(f, "`{}` is not a variant key: {}", e(key), e(why))?,
                }
                if let Some(near) = nearest {
                    write!(f, "; did you mean `{near}`?")?;
                }
                let shown: Vec<&str> = known.iter().take(KEYS_SHOWN).map(String::as_str).collect();
                let whose = if malformed.is_some() { "the plan's" } else { "its" };
                write!(f, " ({whose} variants: {}", shown.join(", "))?;
                if known.len() > KEYS_SHOWN {
                    write!(f, " and {} more", known.len() - KEYS_SHOWN)?;
                }
                f.write_str(")")
            }
            RunError::VariantIndex { index, count } => {
                write!(f, "variant index {index} is out of range: the plan has {count} variants (0 is the base)")
            }
            RunError::OverBudget { needed, limit, at, largest } => {
                write!(
                    f,
                    "the plan needs {} of memory at {}, over the limit of {} (raise it with --max-memory); largest: ",
                    show_bytes(*needed),
                    e(at),
                    show_bytes(*limit)
                )?;
                let parts: Vec<String> =
                    largest.iter().map(|(what, b)| format!("{} {}", e(what), show_bytes(*b))).collect();
                f.write_str(&parts.join(", "))
            }
            RunError::TooLarge { what } => {
                write!(f, "the size of {} does not fit in memory (it overflows a 64-bit byte count)", e(what))
            }
        }
    }
}

impl std::error::Error for RunError {}

/// Memory limit when the physical memory is unknown: 4 GiB.
const FALLBACK_MAX_MEMORY: usize = 4 << 30;

/// The default memory limit of a session: half the physical memory (`MemTotal` in
/// `/proc/meminfo`), or 4 GiB where that cannot be read.
pub fn default_max_memory() -> usize {
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|text| {
        let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
        let kib: usize = line.split_whitespace().nth(1)?.parse().ok()?;
        kib.checked_mul(1024)
    });
    total.map_or(FALLBACK_MAX_MEMORY, |t| t / 2)
}

/// How a [`Session`] runs: its thread count, its memory limit and whether its workers spin.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SessionOptions {
    /// Worker threads (at least 1).
    pub threads: usize,
    /// Most bytes a binding may take ([`Footprint::total`]: activation buffers, scratch,
    /// zeros, inputs and outputs); a binding over it is refused before anything is
    /// allocated.
    pub max_memory: usize,
    /// Whether the workers other than the one running a run spin through it, taking each
    /// step's parallel work at once, rather than sleeping between steps (default: yes;
    /// `exec/awake.rs`). Off, they sleep whenever idle for a few microseconds: less CPU
    /// burnt in serial stretches, more latency on small steps.
    pub spin: bool,
}

impl Default for SessionOptions {
    /// One thread per core, [`default_max_memory`].
    fn default() -> SessionOptions {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        SessionOptions { threads, max_memory: default_max_memory(), spin: true }
    }
}

impl SessionOptions {
    pub fn threads(self, threads: usize) -> SessionOptions {
        SessionOptions { threads, ..self }
    }

    pub fn max_memory(self, bytes: usize) -> SessionOptions {
        SessionOptions { max_memory: bytes, ..self }
    }

    pub fn spin(self, spin: bool) -> SessionOptions {
        SessionOptions { spin, ..self }
    }
}

/// Runs one plan; reuses its buffers across runs.
pub struct Session {
    plan: Arc<Plan>,
    pool: rayon::ThreadPool,
    threads: usize,
    /// [`SessionOptions::max_memory`].
    max_memory: usize,
    /// [`SessionOptions::spin`].
    spin: bool,
    /// The active variant's index, shared with every [`VariantSwitch`]; always a valid
    /// index (stores are checked).
    active: Arc<AtomicUsize>,
    /// The variant the last successful run used.
    last_variant: Option<usize>,
    bound: Option<Bound>,
    /// The f32 copies of the active variant's f16 replacements.
    decoded: Decoded,
    /// Per plan input, the position in the caller's list of the input of that name.
    /// Refilled by every run; kept so that a run does not allocate it.
    given: Vec<Option<usize>>,
    /// The symbol values of the current run in `manifest.symbols` order (0: not bound
    /// yet). Refilled by every run.
    symbols: Vec<usize>,
    /// Accumulated seconds per step, when profiling.
    profile: Option<Vec<f64>>,
}

/// A [`RunError::BadPlan`] at `step` (`step 3 (`conv1`)`, names as the plan has them:
/// the message escapes them).
pub(crate) fn bad(step: &str, detail: impl Into<String>) -> RunError {
    RunError::BadPlan { step: step.to_string(), detail: detail.into() }
}

impl Session {
    /// A session running `plan` on `threads` threads (at least 1), under the base
    /// variant, with the default memory limit ([`default_max_memory`]).
    pub fn new(plan: Arc<Plan>, threads: usize) -> Result<Session, RunError> {
        Session::with_options(plan, SessionOptions::default().threads(threads))
    }

    /// A session running `plan` as `options` say, under the base variant.
    pub fn with_options(plan: Arc<Plan>, options: SessionOptions) -> Result<Session, RunError> {
        let threads = options.threads.max(1);
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
            max_memory: options.max_memory,
            spin: options.spin,
            active: Arc::new(AtomicUsize::new(0)),
            last_variant: None,
            bound: None,
            decoded: Decoded::default(),
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

    /// The memory limit ([`SessionOptions::max_memory`]).
    pub fn max_memory(&self) -> usize {
        self.max_memory
    }

    /// What a run with every symbol bound to `batch` would take on this session's
    /// threads, computed without allocating; the error of a shape that overflows or a
    /// step that fails its kernel's preconditions. Does not compare with the limit.
    pub fn footprint(&self, batch: usize) -> Result<Footprint, RunError> {
        footprint(&self.plan, batch, self.threads)
    }

    /// Binds the buffers for every symbol bound to `batch` now (as the first run at that
    /// batch size would), refusing a footprint over the limit; returns the footprint.
    pub fn bind_batch(&mut self, batch: usize) -> Result<&Footprint, RunError> {
        self.symbols.fill(batch);
        self.bind_current()
    }

    /// The multiply-adds of one run at the bound shapes ([`Kernel::multiply_adds`](crate::plan::Kernel::multiply_adds) over
    /// the steps; a data-dependent step, such as a sparse conv, counts none), or `None`
    /// before anything is bound ([`Session::bind_batch`] or a run).
    pub fn multiply_adds(&self) -> Option<u64> {
        let bound = self.bound.as_ref()?;
        let shape = |v: usize| bound.shapes.get(v).map_or(&[][..], Vec::as_slice);
        let steps = self.plan.manifest.steps.iter();
        Some(steps.fold(0u64, |sum, st| {
            let inputs: Vec<&[usize]> = st.inputs.iter().map(|&v| shape(v)).collect();
            sum.saturating_add(st.kernel.multiply_adds(&inputs, shape(st.output)))
        }))
    }

    fn bind_current(&mut self) -> Result<&Footprint, RunError> {
        if self.bound.as_ref().is_none_or(|b| b.symbols != self.symbols) {
            bind::rebind(&mut self.bound, &self.plan, &self.symbols, self.threads, self.max_memory)?;
        }
        match &self.bound {
            Some(b) => Ok(&b.footprint),
            None => Err(bad("bind", "no buffers")),
        }
    }

    /// Makes variant `key` ([`BASE_VARIANT`](crate::plan::BASE_VARIANT) for the base)
    /// active for the runs that start from now on. A run in progress keeps its variant.
    /// Copies no weights and allocates nothing (except for the error of an unknown key)
    /// when `key` is canonical, as the plan lists it; another spelling of a key
    /// (`fog=0.010` for `fog=0.01`, `gamma=0.5+blur=15` for `blur=15+gamma=0.5`) is read
    /// as a [`VariantKey`] and names the same variant.
    pub fn set_variant(&self, key: &str) -> Result<(), RunError> {
        self.active.store(switch::lookup(&self.plan, key)?, Ordering::Release);
        Ok(())
    }

    /// As [`set_variant`](Session::set_variant), by parsed key (a
    /// [`Selection`](crate::conditions::Selection)'s, say); allocates nothing (except for
    /// the error of an unknown key).
    pub fn set_variant_key(&self, key: &VariantKey) -> Result<(), RunError> {
        self.active.store(switch::lookup_key(&self.plan, key)?, Ordering::Release);
        Ok(())
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
        // Before any step, on this thread, and only when the variant differs from the
        // last: its f16 replacements decoded, then the raw LoRA `A`s packed for it and
        // the working copies of the layers merged on switch written.
        self.decoded.refresh(&plan, variant, &self.pool);
        let weights = weights.with_decoded(self.decoded.copies());
        let Some(bound) = self.bound.as_mut() else { return Err(bad("bind", "no buffers")) };
        bound.pack_lora(&plan, weights);
        let run = Run { plan: &plan, weights, inputs, given: &self.given };
        let threads = self.threads;
        let profile = self.profile.as_deref_mut();
        awake::install(&self.pool, threads, self.spin, || run::execute(&run, bound, threads, profile))?;
        let bound: &Bound = bound;
        let mut out = Vec::with_capacity(m.outputs.len());
        for o in &m.outputs {
            let data = run::value_slice(&run, bound, o.value).to_vec();
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
        bound.pack_lora(&plan, plan.base_tensors());
        let run = Run { plan: &plan, weights: plan.base_tensors(), inputs, given: &self.given };
        let threads = self.threads;
        self.pool.install(|| exec(&run, bound, threads))
    }

    /// Matches the inputs to the plan's by name, binds the symbols, checks the inputs and
    /// (re)binds the buffers when the symbol values changed.
    fn prepare(&mut self, plan: &Plan, inputs: &[Input<'_>]) -> Result<(), RunError> {
        let m = &plan.manifest;
        bind::match_inputs(m, inputs, &mut self.given)?;
        bind::bind_symbols(m, &self.given, inputs, &mut self.symbols)?;
        for (spec, g) in m.inputs.iter().zip(&self.given) {
            if let Some(pos) = *g
                && let Some(index) = inputs[pos].data.iter().position(|v| !v.is_finite())
            {
                return Err(RunError::NotFinite { name: spec.name.clone(), index, value: inputs[pos].data[index] });
            }
        }
        let _ = plan;
        self.bind_current()?;
        Ok(())
    }
}
