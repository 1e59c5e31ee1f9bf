//! Executing a plan.
//!
//! A [`Session`] owns a thread pool and the activation buffers of one plan. The first run
//! (and any run with a new batch size) *binds* the plan: it evaluates every value's shape
//! from the inputs', checks each step against its kernel's requirements (a plan file is
//! untrusted), and allocates one buffer per slot of the plan's buffer plan plus the
//! kernels' scratch. Later runs at the same batch size allocate nothing but the output
//! tensors they return; weights are read in place from the plan.
//!
//! An `optional` input that is not given is zero-filled.

use std::collections::HashMap;
use std::fmt;
use std::sync::Arc;

use crate::kernels::conv::{self, Conv2dShape, ConvAlgo};
use crate::kernels::pool::{self, Pool2dShape, PoolKind};
use crate::kernels::resize::{self, ResizeMode};
use crate::kernels::{Epilogue, elementwise, layout, linear, norm, reduce, softmax};
use crate::plan::{EpilogueSpec, Kernel, Plan, Storage, show_shape};

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
}

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
        }
    }
}

impl std::error::Error for RunError {}

/// Runs one plan; reuses its buffers across runs.
pub struct Session {
    plan: Arc<Plan>,
    pool: rayon::ThreadPool,
    threads: usize,
    bound: Option<Bound>,
    /// Accumulated seconds per step, when profiling.
    profile: Option<Vec<f64>>,
}

/// Everything that depends on the bound symbol values.
struct Bound {
    bindings: HashMap<String, usize>,
    shapes: Vec<Vec<usize>>,
    slots: Vec<Vec<f32>>,
    scratch: Vec<f32>,
    /// Per step, the conv parameters (for conv steps).
    convs: Vec<Option<(Conv2dShape, ConvAlgo)>>,
    /// Zero-filled buffers for absent optional inputs, by input index.
    zeros: Vec<Vec<f32>>,
}

fn bad(step: &str, detail: impl Into<String>) -> RunError {
    RunError::BadPlan { step: step.to_string(), detail: detail.into() }
}

impl Session {
    /// A session running `plan` on `threads` threads (at least 1).
    pub fn new(plan: Arc<Plan>, threads: usize) -> Result<Session, RunError> {
        let threads = threads.max(1);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("readi-{i}"))
            .build()
            .map_err(|e| RunError::Threads(e.to_string()))?;
        Ok(Session { plan, pool, threads, bound: None, profile: None })
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

    /// Runs the plan. Inputs are matched by name; absent `optional` inputs are zeros.
    /// Returns the outputs in the plan's order, with their names.
    pub fn run(&mut self, inputs: &[Input<'_>]) -> Result<Vec<(String, Tensor)>, RunError> {
        let plan = Arc::clone(&self.plan);
        let m = &plan.manifest;
        // Match inputs to the plan's.
        let mut given: Vec<Option<&Input<'_>>> = vec![None; m.inputs.len()];
        for inp in inputs {
            match m.inputs.iter().position(|s| s.name == inp.name) {
                Some(i) if given[i].is_some() => return Err(RunError::DuplicateInput { name: inp.name.into() }),
                Some(i) => given[i] = Some(inp),
                None => {
                    return Err(RunError::UnknownInput {
                        name: inp.name.into(),
                        known: m.inputs.iter().map(|s| s.name.clone()).collect(),
                    });
                }
            }
        }
        let bindings = self.bind_symbols(&given)?;
        for (spec, g) in m.inputs.iter().zip(&given) {
            if let Some(inp) = g
                && let Some(index) = inp.data.iter().position(|v| !v.is_finite())
            {
                return Err(RunError::NotFinite { name: spec.name.clone(), index, value: inp.data[index] });
            }
        }
        if self.bound.as_ref().is_none_or(|b| b.bindings != bindings) {
            self.bound = Some(bind(&plan, bindings, self.threads)?);
        }
        let Some(bound) = self.bound.as_mut() else { return Err(bad("bind", "no buffers")) };
        let threads = self.threads;
        let given_data: Vec<Option<&[f32]>> = given.iter().map(|g| g.map(|i| i.data)).collect();
        let profile = self.profile.as_deref_mut();
        self.pool.install(|| execute(&plan, bound, &given_data, threads, profile))?;
        let bound = self.bound.as_ref().ok_or_else(|| bad("run", "no buffers"))?;
        let mut out = Vec::with_capacity(m.outputs.len());
        for o in &m.outputs {
            let data = value_slice(&plan, bound, &given_data, o.value).to_vec();
            out.push((o.name.clone(), Tensor { shape: bound.shapes[o.value].clone(), data }));
        }
        Ok(out)
    }

    /// Binds the symbols from the given inputs' shapes and checks every given input.
    fn bind_symbols(&self, given: &[Option<&Input<'_>>]) -> Result<HashMap<String, usize>, RunError> {
        let m = &self.plan.manifest;
        let mut bindings: HashMap<String, usize> = HashMap::new();
        for (spec, g) in m.inputs.iter().zip(given) {
            let Some(inp) = g else {
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
                match d.syms.as_slice() {
                    [] => {
                        if d.coef as usize != got {
                            return Err(shape_err(format!("axis {axis} must be {}", d.coef)));
                        }
                    }
                    [s] => {
                        let c = d.coef.max(1) as usize;
                        if got == 0 || got % c != 0 {
                            return Err(shape_err(format!("axis {axis} must be a positive multiple of {c}")));
                        }
                        let v = got / c;
                        match bindings.get(s) {
                            Some(&prev) if prev != v => {
                                return Err(shape_err(format!(
                                    "axis {axis} gives {s} = {v}, another input gave {prev}"
                                )));
                            }
                            _ => {
                                bindings.insert(s.clone(), v);
                            }
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
        for s in &m.symbols {
            if !bindings.contains_key(s) {
                // Every input that carries this symbol is absent: a batch of one.
                bindings.insert(s.clone(), 1);
            }
        }
        Ok(bindings)
    }
}

/// Evaluates shapes, checks the steps, and allocates buffers for one binding.
fn bind(plan: &Plan, bindings: HashMap<String, usize>, threads: usize) -> Result<Bound, RunError> {
    let m = &plan.manifest;
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
                if plan.tensor(t).len() != numel(i) {
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
        let conv = check_step(plan, &shapes, step, &at)?;
        if let Some((s, algo)) = &conv {
            scratch = scratch.max(conv::scratch_len(s, *algo, threads));
        }
        convs.push(conv);
    }
    let zeros =
        m.inputs.iter().map(|spec| if spec.optional { vec![0.0; numel(spec.value)] } else { Vec::new() }).collect();
    Ok(Bound {
        bindings,
        shapes,
        slots: slot_len.into_iter().map(|n| vec![0.0; n]).collect(),
        scratch: vec![0.0; scratch],
        convs,
        zeros,
    })
}

fn tensor_len(plan: &Plan, t: Option<usize>) -> Option<usize> {
    t.map(|t| plan.tensor(t).len())
}

fn check_epilogue(plan: &Plan, ep: &EpilogueSpec, channels: usize, at: &str) -> Result<(), RunError> {
    for len in [tensor_len(plan, ep.scale), tensor_len(plan, ep.shift)].into_iter().flatten() {
        if len != channels {
            return Err(bad(at, format!("epilogue has {len} values for {channels} channels")));
        }
    }
    Ok(())
}

/// [`window_out`](crate::kernels::window_out) on sizes from the plan; `None` (rejected)
/// for values that do not fit.
fn window_out(len: usize, k: usize, s: usize, p: usize, d: usize, ceil: bool) -> Option<usize> {
    let i = |v: usize| i64::try_from(v).ok();
    let out = crate::kernels::window_out(i(len)?, i(k)?, i(s)?, i(p)?, i(d)?, ceil)?;
    usize::try_from(out).ok()
}

/// Checks a step's inputs and output against what its kernel needs, so kernels never see
/// inconsistent sizes. Returns the conv parameters for conv steps.
fn check_step(
    plan: &Plan,
    shapes: &[Vec<usize>],
    step: &crate::plan::Step,
    at: &str,
) -> Result<Option<(Conv2dShape, ConvAlgo)>, RunError> {
    let ins: Vec<&Vec<usize>> = step.inputs.iter().map(|&i| &shapes[i]).collect();
    let out = &shapes[step.output];
    let arity = |n: usize| {
        if ins.len() == n { Ok(()) } else { Err(bad(at, format!("{} inputs, the kernel takes {n}", ins.len()))) }
    };
    let numel = |s: &[usize]| s.iter().product::<usize>();
    let same = |a: &[usize], b: &[usize], what: &str| {
        if a == b { Ok(()) } else { Err(bad(at, format!("{what}: {a:?} vs {b:?}"))) }
    };
    match &step.kernel {
        Kernel::Conv2d { cout, kernel, stride, padding, dilation, groups, algo, weight, epilogue } => {
            arity(1)?;
            let x = ins[0];
            if x.len() != 4 || out.len() != 4 {
                return Err(bad(at, "conv2d needs 4-D input and output"));
            }
            let algo = ConvAlgo::from_name(algo).ok_or_else(|| bad(at, format!("unknown conv algorithm `{algo}`")))?;
            let s = Conv2dShape {
                n: x[0],
                cin: x[1],
                h: x[2],
                w: x[3],
                cout: *cout,
                kh: kernel[0],
                kw: kernel[1],
                stride_h: stride[0],
                stride_w: stride[1],
                pad_h: padding[0],
                pad_w: padding[1],
                dil_h: dilation[0],
                dil_w: dilation[1],
                groups: *groups,
                oh: out[2],
                ow: out[3],
            };
            let oh = window_out(s.h, s.kh, s.stride_h, s.pad_h, s.dil_h, false);
            let ow = window_out(s.w, s.kw, s.stride_w, s.pad_w, s.dil_w, false);
            if *groups == 0 || !s.cin.is_multiple_of(*groups) || !s.cout.is_multiple_of(*groups) {
                return Err(bad(at, "groups must divide both channel counts"));
            }
            same(out, &[s.n, s.cout, oh.unwrap_or(0), ow.unwrap_or(0)], "conv2d output shape")?;
            if plan.tensor(*weight).len() != conv::packed_weight_len(&s, algo) {
                return Err(bad(at, "conv2d weight has the wrong size"));
            }
            check_epilogue(plan, epilogue, s.cout, at)?;
            return Ok(Some((s, algo)));
        }
        Kernel::Linear { out_features, weight, epilogue } => {
            arity(1)?;
            let x = ins[0];
            let Some((&fin, lead)) = x.split_last() else { return Err(bad(at, "linear of a scalar")) };
            let mut want = lead.to_vec();
            want.push(*out_features);
            same(out, &want, "linear output shape")?;
            if plan.tensor(*weight).len() != fin * out_features {
                return Err(bad(at, "linear weight has the wrong size"));
            }
            check_epilogue(plan, epilogue, *out_features, at)?;
        }
        Kernel::MatMul => {
            arity(2)?;
            let (a, b) = (ins[0], ins[1]);
            if a.len() < 2 || b.len() < 2 || a[a.len() - 1] != b[b.len() - 2] {
                return Err(bad(at, format!("matmul of {a:?} and {b:?}")));
            }
            let mut want = broadcast(&a[..a.len() - 2], &b[..b.len() - 2]).ok_or_else(|| bad(at, "batch axes"))?;
            want.push(a[a.len() - 2]);
            want.push(b[b.len() - 1]);
            same(out, &want, "matmul output shape")?;
        }
        Kernel::Binary { .. } => {
            arity(2)?;
            let want = broadcast(ins[0], ins[1]).ok_or_else(|| bad(at, "operands do not broadcast"))?;
            same(out, &want, "broadcast shape")?;
        }
        Kernel::Scalar { .. } | Kernel::Activation { .. } => {
            arity(1)?;
            same(out, ins[0], "element-wise shape")?;
        }
        Kernel::ChannelAffine { epilogue } => {
            arity(1)?;
            same(out, ins[0], "channel affine shape")?;
            if ins[0].len() < 2 {
                return Err(bad(at, "channel affine needs a channel axis"));
            }
            check_epilogue(plan, epilogue, ins[0][1], at)?;
        }
        Kernel::LayerNorm { weight, bias, .. } => {
            arity(1)?;
            same(out, ins[0], "layernorm shape")?;
            let f = ins[0].last().copied().unwrap_or(0);
            for len in [tensor_len(plan, *weight), tensor_len(plan, *bias)].into_iter().flatten() {
                if len != f {
                    return Err(bad(at, "layernorm parameters have the wrong size"));
                }
            }
        }
        Kernel::Softmax { axis } => {
            arity(1)?;
            same(out, ins[0], "softmax shape")?;
            if *axis >= ins[0].len() {
                return Err(bad(at, "softmax axis out of range"));
            }
        }
        Kernel::Concat { axis } => {
            if ins.is_empty() {
                return Err(bad(at, "concat without inputs"));
            }
            let mut want = ins[0].clone();
            if *axis >= want.len() {
                return Err(bad(at, "concat axis out of range"));
            }
            want[*axis] = 0;
            for x in &ins {
                if x.len() != want.len() || x.iter().enumerate().any(|(i, &d)| i != *axis && d != want[i]) {
                    return Err(bad(at, "concat inputs differ off the axis"));
                }
                want[*axis] += x[*axis];
            }
            same(out, &want, "concat output shape")?;
        }
        Kernel::Reshape => {
            arity(1)?;
            if numel(out) != numel(ins[0]) {
                return Err(bad(at, "reshape changes the element count"));
            }
        }
        Kernel::Permute { perm } => {
            arity(1)?;
            let mut seen = vec![false; ins[0].len()];
            if perm.len() != seen.len()
                || perm.iter().any(|&p| p >= seen.len() || std::mem::replace(&mut seen[p], true))
            {
                return Err(bad(at, "not a permutation"));
            }
            let want: Vec<usize> = perm.iter().map(|&p| ins[0][p]).collect();
            same(out, &want, "permute output shape")?;
        }
        Kernel::Pool { kernel, stride, padding, ceil_mode, .. } => {
            arity(1)?;
            let x = ins[0];
            if x.len() != 4 {
                return Err(bad(at, "pooling needs a 4-D input"));
            }
            if padding[0] * 2 > kernel[0] || padding[1] * 2 > kernel[1] {
                return Err(bad(at, "pool padding exceeds half the kernel"));
            }
            let oh = window_out(x[2], kernel[0], stride[0], padding[0], 1, *ceil_mode).unwrap_or(0);
            let ow = window_out(x[3], kernel[1], stride[1], padding[1], 1, *ceil_mode).unwrap_or(0);
            same(out, &[x[0], x[1], oh, ow], "pool output shape")?;
        }
        Kernel::GlobalAvgPool => {
            arity(1)?;
            let x = ins[0];
            if x.len() != 4 {
                return Err(bad(at, "global_avgpool needs a 4-D input"));
            }
            same(out, &[x[0], x[1], 1, 1], "global_avgpool output shape")?;
        }
        Kernel::Upsample { scale, .. } => {
            arity(1)?;
            let x = ins[0];
            if x.len() != 4 || out.len() != 4 || out[0] != x[0] || out[1] != x[1] || out[2] == 0 || out[3] == 0 {
                return Err(bad(at, "upsample needs 4-D input and output with equal N and C"));
            }
            if scale.is_some_and(|s| !(s[0] > 0.0 && s[1] > 0.0 && s[0].is_finite() && s[1].is_finite())) {
                return Err(bad(at, "upsample scale must be positive"));
            }
        }
        Kernel::Mean { axes } => {
            arity(1)?;
            let x = ins[0];
            if axes.windows(2).any(|w| w[0] >= w[1]) || axes.iter().any(|&a| a >= x.len()) {
                return Err(bad(at, "mean axes must be sorted, distinct and in range"));
            }
            let want: Vec<usize> = x.iter().enumerate().filter(|(i, _)| !axes.contains(i)).map(|(_, &d)| d).collect();
            if numel(out) != numel(&want) {
                return Err(bad(at, "mean output size"));
            }
        }
    }
    Ok(None)
}

/// NumPy broadcasting of two concrete shapes.
fn broadcast(a: &[usize], b: &[usize]) -> Option<Vec<usize>> {
    let n = a.len().max(b.len());
    (0..n)
        .map(|i| {
            let da = if i + a.len() >= n { a[i + a.len() - n] } else { 1 };
            let db = if i + b.len() >= n { b[i + b.len() - n] } else { 1 };
            match (da, db) {
                (x, y) if x == y => Some(x),
                (1, y) => Some(y),
                (x, 1) => Some(x),
                _ => None,
            }
        })
        .collect()
}

/// The data of a value.
fn value_slice<'a>(plan: &'a Plan, bound: &'a Bound, given: &[Option<&'a [f32]>], v: usize) -> &'a [f32] {
    let n: usize = bound.shapes[v].iter().product();
    match plan.manifest.values[v].storage {
        Storage::Input(i) => given[i].unwrap_or(&bound.zeros[i]),
        Storage::Slot(s) => &bound.slots[s][..n],
        Storage::Tensor(t) => plan.tensor(t),
    }
}

fn epilogue<'a>(plan: &'a Plan, e: &EpilogueSpec) -> Epilogue<'a> {
    Epilogue { scale: e.scale.map(|t| plan.tensor(t)), shift: e.shift.map(|t| plan.tensor(t)), relu: e.relu }
}

/// Runs every step in order.
fn execute(
    plan: &Plan,
    bound: &mut Bound,
    given: &[Option<&[f32]>],
    threads: usize,
    mut profile: Option<&mut [f64]>,
) -> Result<(), RunError> {
    let m = &plan.manifest;
    for (k, step) in m.steps.iter().enumerate() {
        let start = profile.is_some().then(std::time::Instant::now);
        let Storage::Slot(out_slot) = m.values[step.output].storage else {
            return Err(bad(&step.path, "output is not an activation buffer"));
        };
        // Take the output buffer out so inputs can be borrowed alongside it; the buffer
        // plan never gives a step's output the slot of one of its inputs.
        let mut out_buf = std::mem::take(&mut bound.slots[out_slot]);
        let out_len: usize = bound.shapes[step.output].iter().product();
        let mut scratch = std::mem::take(&mut bound.scratch);
        {
            let b: &Bound = bound;
            let ins: Vec<&[f32]> = step.inputs.iter().map(|&i| value_slice(plan, b, given, i)).collect();
            let in_shapes: Vec<&[usize]> = step.inputs.iter().map(|&i| b.shapes[i].as_slice()).collect();
            let out = &mut out_buf[..out_len];
            let out_shape = &b.shapes[step.output];
            run_step(plan, &step.kernel, b.convs[k].as_ref(), &ins, &in_shapes, out, out_shape, &mut scratch, threads);
        }
        bound.scratch = scratch;
        bound.slots[out_slot] = out_buf;
        if let (Some(p), Some(t)) = (profile.as_deref_mut(), start) {
            p[k] += t.elapsed().as_secs_f64();
        }
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn run_step(
    plan: &Plan,
    kernel: &Kernel,
    conv_params: Option<&(Conv2dShape, ConvAlgo)>,
    ins: &[&[f32]],
    in_shapes: &[&[usize]],
    out: &mut [f32],
    out_shape: &[usize],
    scratch: &mut [f32],
    threads: usize,
) {
    let x = ins[0];
    let xs = in_shapes[0];
    match kernel {
        Kernel::Conv2d { weight, epilogue: ep, .. } => {
            if let Some((s, algo)) = conv_params {
                conv::conv2d(s, *algo, plan.tensor(*weight), &epilogue(plan, ep), x, out, scratch, threads);
            }
        }
        Kernel::Linear { out_features, weight, epilogue: ep } => {
            let fin = xs.last().copied().unwrap_or(1);
            let rows = x.len() / fin.max(1);
            let (w, layout) = (plan.tensor(*weight), linear::WeightLayout::InOut);
            linear::linear(x, rows, fin, w, layout, *out_features, &epilogue(plan, ep), out, threads);
        }
        Kernel::MatMul => linear::matmul(x, xs, ins[1], in_shapes[1], out, out_shape, threads),
        Kernel::Binary { op } => elementwise::binary((*op).into(), x, xs, ins[1], in_shapes[1], out, out_shape),
        Kernel::Scalar { op, value, scalar_first } => elementwise::scalar((*op).into(), x, *value, *scalar_first, out),
        Kernel::Activation { act } => elementwise::activation((*act).into(), x, out),
        Kernel::ChannelAffine { epilogue: ep } => {
            let (n, c) = (xs[0], xs[1]);
            let inner = x.len() / (n * c).max(1);
            let e = epilogue(plan, ep);
            norm::channel_affine(x, n, c, inner, e.scale, e.shift, e.relu, out);
        }
        Kernel::LayerNorm { weight, bias, eps } => {
            let f = xs.last().copied().unwrap_or(1);
            let rows = x.len() / f.max(1);
            norm::layernorm(x, rows, f, weight.map(|t| plan.tensor(t)), bias.map(|t| plan.tensor(t)), *eps, out);
        }
        Kernel::Softmax { axis } => {
            let outer: usize = xs[..*axis].iter().product();
            let inner: usize = xs[*axis + 1..].iter().product();
            softmax::softmax(x, outer, xs[*axis], inner, out);
        }
        Kernel::Concat { axis } => {
            let parts: Vec<(&[f32], &[usize])> = ins.iter().copied().zip(in_shapes.iter().copied()).collect();
            layout::concat(&parts, *axis, out);
        }
        Kernel::Reshape => out.copy_from_slice(x),
        Kernel::Permute { perm } => layout::permute(x, xs, perm, out),
        Kernel::Pool { max, kernel, stride, padding, ceil_mode, count_include_pad } => {
            let s = Pool2dShape {
                nc: xs[0] * xs[1],
                h: xs[2],
                w: xs[3],
                kh: kernel[0],
                kw: kernel[1],
                stride_h: stride[0],
                stride_w: stride[1],
                pad_h: padding[0],
                pad_w: padding[1],
                oh: out_shape[2],
                ow: out_shape[3],
                ceil_mode: *ceil_mode,
                count_include_pad: *count_include_pad,
            };
            pool::pool2d(if *max { PoolKind::Max } else { PoolKind::Avg }, &s, x, out);
        }
        Kernel::GlobalAvgPool => pool::global_avgpool(x, xs[0] * xs[1], xs[2] * xs[3], out),
        Kernel::Upsample { bilinear, align_corners, scale } => {
            let mode = if *bilinear { ResizeMode::Bilinear } else { ResizeMode::Nearest };
            let scale = scale.map(|s| (s[0], s[1]));
            resize::upsample(
                mode,
                *align_corners,
                scale,
                x,
                xs[0] * xs[1],
                xs[2],
                xs[3],
                out,
                out_shape[2],
                out_shape[3],
            );
        }
        Kernel::Mean { axes } => reduce::mean(x, xs, axes, out),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_out_matches_the_compiler() {
        assert_eq!(window_out(224, 7, 2, 3, 1, false), Some(112));
        assert_eq!(window_out(1, 2, 2, 0, 1, true), Some(1));
        assert_eq!(window_out(3, 5, 1, 0, 1, false), None);
    }

    #[test]
    fn broadcast_follows_numpy() {
        assert_eq!(broadcast(&[4, 1, 3], &[5, 1]), Some(vec![4, 5, 3]));
        assert_eq!(broadcast(&[2], &[3]), None);
    }
}
