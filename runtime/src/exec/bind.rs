//! Binding a plan to one set of symbol values: the symbols read from the inputs' shapes,
//! every value's shape, the activation buffers and scratch, and each conv step's
//! parameters at those shapes. Done at a session's first run and whenever a run's symbol
//! values (its batch size) differ from the last binding's.

use std::collections::HashMap;
use std::sync::Mutex;

use crate::kernels::bev_pool;
use crate::kernels::conv::{self, Conv2dShape, ConvAlgo};
use crate::kernels::conv_transpose;
use crate::kernels::conv3d;
use crate::kernels::sparse;
use crate::kernels::voxel;
use crate::kernels::{
    self, elementwise, index, layout as layout_k, linear, merge, movement, norm, pool, reduce, resize, select, softmax,
};
use readi_plan::ops::{Operator, Pure};

use crate::plan::{EpilogueSpec, Kernel, LoraSpec, Manifest, Plan, Step, Storage, VariantTensors, show_shape};

use super::arena::Buffer;
use super::{Input, RunError, bad};

/// Everything that depends on the bound symbol values.
pub(crate) struct Bound {
    /// The symbol values the buffers were made for, in `manifest.symbols` order.
    pub(super) symbols: Vec<usize>,
    pub(crate) shapes: Vec<Vec<usize>>,
    /// The activation slots and the scratch, on huge pages where they are large enough.
    pub(crate) slots: Vec<Buffer>,
    pub(crate) scratch: Buffer,
    /// Per step, the conv parameters (for conv steps).
    pub(crate) convs: Vec<Option<(Conv2dShape, ConvAlgo)>>,
    /// Zero-filled buffers for absent optional inputs, by input index.
    pub(super) zeros: Vec<Vec<f32>>,
    /// Per step, the packed LoRA `A` of a conv whose plan stores it raw
    /// ([`LoraSpec::a_raw`]), empty for the others; packed for the variant
    /// `lora_variant` (`None`: not yet) by [`Bound::pack_lora`].
    pub(crate) lora_a: Vec<Vec<f32>>,
    /// Per step, the working copy of a conv merged on switch (`Kernel::Conv2d::switch`):
    /// its raw weight, with its LoRA update merged in, packed for its algorithm under the
    /// variant `lora_variant`; empty for the others. One per session, whatever the
    /// number of variants.
    pub(crate) working: Vec<Vec<f32>>,
    /// The raw merged weight of the largest Winograd layer merged on switch with a LoRA
    /// update, before packing (`kernels::merge::switch_tmp_len`).
    pub(super) switch_tmp: Vec<f32>,
    pub(super) lora_variant: Option<usize>,
    /// What this binding takes.
    pub(super) footprint: Footprint,
    /// Per step, the geometry an `lss_bev_pool` step computed from the calibration of the
    /// last run (recomputed when a run's calibration differs), `None` for the others.
    /// Behind a lock because a step gets the binding shared; only the running step takes
    /// it.
    pub(crate) bev: Vec<Option<Mutex<bev_pool::Geometry>>>,
    /// Per step, the hash table of a voxelization step (sized from its `max_voxels`),
    /// `None` for the others. Behind a lock as `bev`.
    pub(crate) voxel: Vec<Option<Mutex<voxel::Table>>>,
    /// Per step, the hash table and rulebook of a sparse conv step (or the candidate
    /// sites of a `sparse_out_coords` one), rebuilt by every run; `None` for the others.
    pub(crate) sparse: Vec<Option<Mutex<sparse::Scratch>>>,
}

/// Matches `inputs` to the plan's by name: `given[i]` is the position in `inputs` of the
/// plan's input `i`, if given. A name given twice, or one the plan lacks, is an error.
pub(super) fn match_inputs(m: &Manifest, inputs: &[Input<'_>], given: &mut Vec<Option<usize>>) -> Result<(), RunError> {
    given.clear();
    given.resize(m.inputs.len(), None);
    for (pos, inp) in inputs.iter().enumerate() {
        match m.inputs.iter().position(|s| s.name == inp.name) {
            Some(i) if given[i].is_some() => return Err(RunError::DuplicateInput { name: inp.name.into() }),
            Some(i) => given[i] = Some(pos),
            None => {
                return Err(RunError::UnknownInput {
                    name: inp.name.into(),
                    known: m.inputs.iter().map(|s| s.name.clone()).collect(),
                });
            }
        }
    }
    Ok(())
}

/// Binds the symbols from the given inputs' shapes into `symbols` (in `m.symbols` order)
/// and checks every given input; `given` holds, per plan input, the position in `inputs`
/// of the input of that name. Allocates nothing unless it fails.
pub(super) fn bind_symbols(
    m: &Manifest,
    given: &[Option<usize>],
    inputs: &[Input<'_>],
    symbols: &mut [usize],
) -> Result<(), RunError> {
    symbols.fill(0);
    for (spec, g) in m.inputs.iter().zip(given) {
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
                            return Err(shape_err(format!("axis {axis} gives {s} = {v}, another input gave {prev}")));
                        }
                        _ => {}
                    }
                }
                _ => {
                    return Err(shape_err(format!("axis {axis} has a product of symbols, which inputs cannot bind")));
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

/// Values shown by name in a [`RunError::OverBudget`] message.
const LARGEST_SHOWN: usize = 3;

/// The memory a run at one binding of the symbols takes, in bytes, by part: what
/// [`rebind`] allocates (activation buffers, conv scratch, zeros for absent optional
/// inputs) and what the caller holds or receives (the given inputs, the returned
/// outputs). Computed with checked arithmetic before anything is allocated.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Footprint {
    /// The activation buffers (one per slot of the buffer plan, each as large as the
    /// largest value a step writes into it).
    pub activations: usize,
    /// The conv kernels' scratch, for every worker thread.
    pub scratch: usize,
    /// Zero-filled stand-ins for absent optional inputs that a step or an output reads.
    pub zeros: usize,
    /// The LoRA `A`s the session packs for a conv's algorithm (stored raw in the plan).
    pub lora: usize,
    /// The working copies of the convs merged on switch (each packed for its algorithm)
    /// and the raw buffer a merge packs from, and the f32 copies of the variants' f16
    /// replacements (one per replaced tensor).
    pub working: usize,
    /// The inputs at these shapes (the caller's memory).
    pub inputs: usize,
    /// The outputs a run returns.
    pub outputs: usize,
    /// The geometry caches of the `lss_bev_pool` steps (each frustum point's place in the
    /// BEV grid), and the hash tables and rulebooks of the sparse conv steps.
    pub geometry: usize,
    /// The hash tables of the voxelization steps.
    pub voxel_tables: usize,
    /// Everything above.
    pub total: usize,
    /// The largest parts, largest first: a description (`buffer 3, written by step 7
    /// (`conv1`) as [1, 64, 112, 112]`) and its bytes. Names as the plan has them.
    pub largest: Vec<(String, usize)>,
}

/// The layout of one binding: shapes, buffer sizes and conv parameters, and its
/// [`Footprint`]. Allocates nothing proportional to the shapes.
pub(super) struct Layout {
    shapes: Vec<Vec<usize>>,
    slot_len: Vec<usize>,
    scratch_len: usize,
    convs: Vec<Option<(Conv2dShape, ConvAlgo)>>,
    /// Per input, the zeros an absent optional input needs (0 for the others).
    zeros_len: Vec<usize>,
    /// Per step, the floats of its packed LoRA `A` buffer (0: none).
    lora_len: Vec<usize>,
    /// Per step, the floats of its working copy (0: not merged on switch), and the raw
    /// buffer's.
    working_len: Vec<usize>,
    switch_tmp_len: usize,
    pub(super) footprint: Footprint,
    /// Per step, the sizes of an `lss_bev_pool` step (`None` for the others).
    bev: Vec<Option<bev_pool::Dims>>,
    /// Per step, the `max_voxels` of a voxelization step (`None` for the others).
    voxel: Vec<Option<usize>>,
    /// Per step, the sizes of a sparse conv or `sparse_out_coords` step (`true`: a conv).
    sparse: Vec<Option<(bool, sparse::Dims)>>,
    threads: usize,
}

fn overflow(what: String) -> RunError {
    RunError::TooLarge { what }
}

/// Floats to bytes, checked.
fn bytes_of(floats: usize, what: impl FnOnce() -> String) -> Result<usize, RunError> {
    floats.checked_mul(size_of::<f32>()).ok_or_else(|| overflow(what()))
}

/// Evaluates every value's shape for one binding of the symbols (values in
/// `manifest.symbols` order), checks every step against its kernel's preconditions, and
/// sizes the buffers, all with checked arithmetic. Only values a step writes get a
/// buffer; an optional input gets zeros only when something reads it.
pub(super) fn layout(plan: &Plan, symbols: &[usize], threads: usize) -> Result<Layout, RunError> {
    let m = &plan.manifest;
    let base = plan.base_tensors();
    let bindings: HashMap<String, usize> = m.symbols.iter().cloned().zip(symbols.iter().copied()).collect();
    let mut shapes = Vec::with_capacity(m.values.len());
    let mut numels = Vec::with_capacity(m.values.len());
    let read = read_values(m);
    let mut writer = vec![None; m.values.len()];
    for (k, step) in m.steps.iter().enumerate() {
        if let Some(w) = writer.get_mut(step.output) {
            *w = Some(k);
        }
    }
    for (i, v) in m.values.iter().enumerate() {
        // A value nothing reads or writes (validation saw to it that no step reads a value
        // before it is written) is never touched: no size, no buffer.
        let written = matches!(v.storage, Storage::Input(_) | Storage::Tensor(_)) || writer[i].is_some();
        if !read[i] && !written {
            shapes.push(Vec::new());
            numels.push(0);
            continue;
        }
        let s: Option<Vec<usize>> = v.shape.iter().map(|d| d.eval(&bindings)).collect();
        let what = || format!("{} at {}", value_name(m, writer[i], i), show_bindings(m, symbols));
        let s = s.ok_or_else(|| overflow(format!("a dimension of {}", what())))?;
        // The product of the axes other than 0 must fit too: the kernels multiply any
        // run of axes (an empty tensor `[0, 2^40, 2^40]` has 0 elements but 2^80 in its
        // inner axes).
        let nonzero = s.iter().try_fold(1usize, |a, &d| a.checked_mul(d.max(1)));
        let n = if s.contains(&0) { 0 } else { nonzero.unwrap_or(0) };
        if nonzero.is_none() {
            return Err(overflow(what()));
        }
        bytes_of(n, what)?;
        shapes.push(s);
        numels.push(n);
    }
    // Per slot, its floats and the value that sets them.
    let mut slot_len = vec![0usize; m.slots.min(m.values.len())];
    let mut slot_by: Vec<Option<usize>> = vec![None; slot_len.len()];
    for step in &m.steps {
        let i = step.output;
        if let Some(Storage::Slot(s)) = m.values.get(i).map(|v| v.storage)
            && let Some(len) = slot_len.get_mut(s)
            && numels[i] > *len
        {
            *len = numels[i];
            slot_by[s] = Some(i);
        }
    }
    for (i, v) in m.values.iter().enumerate() {
        if let Storage::Tensor(t) = v.storage
            && base.get(t).len() != numels[i]
        {
            return Err(bad(&format!("value {i}"), "stored tensor does not match the value's shape"));
        }
    }
    let mut convs = Vec::with_capacity(m.steps.len());
    let mut lora_len = vec![0usize; m.steps.len()];
    let (mut scratch_len, mut scratch_by) = (0usize, None);
    let mut lora_floats = 0usize;
    let mut working_len = vec![0usize; m.steps.len()];
    let (mut working_floats, mut switch_tmp_len) = (0usize, 0usize);
    let mut bev = vec![None; m.steps.len()];
    let mut sparse_dims = vec![None; m.steps.len()];
    let mut geometry = 0usize;
    let mut voxel_v = vec![None; m.steps.len()];
    let mut voxel_tables = 0usize;
    for (k, step) in m.steps.iter().enumerate() {
        let at = format!("step {k} (`{}`)", step.path);
        check_step(plan, step, &shapes).map_err(|e| bad(&at, e))?;
        let conv = conv_params(step, &shapes, &at)?;
        if let Some((s, algo)) = &conv {
            let switch = matches!(step.kernel, Kernel::Conv2d { switch: true, .. });
            // Merged on switch, the kernel runs the working copy without a branch.
            let lora = step.kernel.lora().filter(|_| !switch);
            let rank = lora.map_or(0, |l| l.rank);
            if switch {
                // `check_step` checked the raw lengths, so these are in range.
                working_len[k] = conv::packed_weight_len(s, *algo);
                working_floats = sum([working_floats, working_len[k]], "the working copies")?;
                switch_tmp_len = switch_tmp_len.max(merge::switch_tmp_len(s, *algo, step.kernel.lora().is_some()));
            }
            let mid = step.kernel.adapter().map_or(0, |a| a.mid);
            let need = if matches!(step.kernel, Kernel::Conv2d { channel_scale: true, .. }) {
                conv::scaled_scratch_len(s, *algo, mid, threads)
            } else {
                conv::adapter_scratch_len(s, *algo, rank, mid, threads)
            }
            .ok_or_else(|| overflow(format!("the scratch of {at}")))?;
            if need > scratch_len {
                (scratch_len, scratch_by) = (need, Some(k));
            }
            // `check_step` checked the raw length, so the packed one is in range.
            if lora.is_some_and(|l| l.a_raw) {
                lora_len[k] = conv::lora_a_len(s, *algo, rank);
                lora_floats = sum([lora_floats, lora_len[k]], "the packed LoRA A buffers")?;
            }
        }
        if let Kernel::ConvTranspose2d { conv: c, .. } = &step.kernel {
            // `check_step` checked the layer, so its sizes are in range.
            let x = &shapes[step.inputs[0]];
            let need = conv_transpose::scratch_len(&c.shape(x[0], x[2], x[3]), threads)
                .ok_or_else(|| overflow(format!("the scratch of {at}")))?;
            if need > scratch_len {
                (scratch_len, scratch_by) = (need, Some(k));
            }
        }
        if let Kernel::Conv3d { conv: c, .. } = &step.kernel {
            // `check_step` checked the layer, so its sizes are in range.
            let x = &shapes[step.inputs[0]];
            let need = conv3d::scratch_len(&c.shape(x[0], x[2], x[3], x[4]), threads)
                .ok_or_else(|| overflow(format!("the scratch of {at}")))?;
            if need > scratch_len {
                (scratch_len, scratch_by) = (need, Some(k));
            }
        }
        if let Kernel::Pure(Pure::LssBevPool(op)) = &step.kernel {
            // `check_step` checked the step, so this succeeds.
            let parts: Vec<&[usize]> = step.inputs.iter().map(|&v| shapes[v].as_slice()).collect();
            let dims = bev_pool::check(op, &parts, &shapes[step.output]).map_err(|e| bad(&at, e))?;
            let b = bev_pool::geometry_bytes(&dims).ok_or_else(|| overflow(format!("the geometry of {at}")))?;
            geometry = sum([geometry, b], "the bev_pool geometry caches")?;
            bev[k] = Some(dims);
        }
        if let Kernel::Pure(Pure::Voxelize(op)) = &step.kernel {
            let b = voxel::Table::bytes(op.max_voxels).ok_or_else(|| overflow(format!("the hash table of {at}")))?;
            voxel_tables = sum([voxel_tables, b], "the voxelization hash tables")?;
            voxel_v[k] = Some(op.max_voxels);
        }
        if let Kernel::Pure(op @ (Pure::SparseConv3d(_) | Pure::SparseOutCoords(_))) = &step.kernel {
            // `check_step` checked the step, so this succeeds.
            let parts: Vec<&[usize]> = step.inputs.iter().map(|&v| shapes[v].as_slice()).collect();
            let out = &shapes[step.output];
            let (conv, dims, b) = match op {
                Pure::SparseConv3d(c) => {
                    let d = sparse::check_conv(c, &parts, out).map_err(|e| bad(&at, e))?;
                    (true, d, sparse::Scratch::conv_bytes(&d, threads))
                }
                Pure::SparseOutCoords(c) => {
                    let d = sparse::check_out_coords(c, &parts, out).map_err(|e| bad(&at, e))?;
                    (false, d, sparse::Scratch::out_coords_bytes(&d))
                }
                _ => unreachable!("matched above"),
            };
            let b = b.ok_or_else(|| overflow(format!("the rulebook of {at}")))?;
            geometry = sum([geometry, b], "the sparse conv rulebooks")?;
            sparse_dims[k] = Some((conv, dims));
        }
        convs.push(conv);
    }
    let zeros_len: Vec<usize> =
        m.inputs.iter().map(|spec| if spec.optional && read[spec.value] { numels[spec.value] } else { 0 }).collect();

    // The footprint, part by part, each with a description for the message.
    let mut parts: Vec<(String, usize)> = Vec::new();
    let shape_of = |i: usize| format!("{:?}", shapes[i]);
    for (s, (&len, by)) in slot_len.iter().zip(&slot_by).enumerate() {
        if let Some(i) = *by {
            let what = format!("buffer {s} for {} {}", value_name(m, writer[i], i), shape_of(i));
            let b = bytes_of(len, || what.clone())?;
            parts.push((what, b));
        }
    }
    let activations = sum(parts.iter().map(|p| p.1), "the activation buffers")?;
    let scratch = bytes_of(scratch_len, || "the conv scratch".into())?;
    if let Some(k) = scratch_by {
        parts.push((format!("conv scratch of step {k} (`{}`) on {threads} threads", m.steps[k].path), scratch));
    }
    let lora = bytes_of(lora_floats, || "the packed LoRA A buffers".into())?;
    if lora > 0 {
        parts.push(("the packed LoRA A buffers".into(), lora));
    }
    let working = bytes_of(sum([working_floats, switch_tmp_len], "the working copies")?, || {
        "the working copies of the convs merged on switch".into()
    })?;
    if working > 0 {
        parts.push(("the working copies of the convs merged on switch".into(), working));
    }
    let decoded = crate::plan::Decoded::bytes(plan);
    if decoded > 0 {
        parts.push(("the decoded copies of the variants' f16 tensors".into(), decoded));
    }
    let working = sum([working, decoded], "the working copies")?;
    if geometry > 0 {
        parts.push(("the geometry caches of the lss_bev_pool steps and the sparse conv rulebooks".into(), geometry));
    }
    if voxel_tables > 0 {
        parts.push(("the hash tables of the voxelization steps".into(), voxel_tables));
    }
    let mut zeros = 0usize;
    let mut inputs = 0usize;
    for (spec, &z) in m.inputs.iter().zip(&zeros_len) {
        let b = bytes_of(numels[spec.value], || format!("input `{}`", spec.name))?;
        inputs = sum([inputs, b], "the inputs")?;
        if z > 0 {
            zeros = sum([zeros, b], "the zeros of absent optional inputs")?;
            parts.push((format!("zeros for optional input `{}` {}", spec.name, shape_of(spec.value)), b));
        }
        parts.push((format!("input `{}` {}", spec.name, shape_of(spec.value)), b));
    }
    let mut outputs = 0usize;
    for o in &m.outputs {
        let b = bytes_of(numels[o.value], || format!("output `{}`", o.name))?;
        outputs = sum([outputs, b], "the outputs")?;
        parts.push((format!("output `{}` {}", o.name, shape_of(o.value)), b));
    }
    let total = sum(
        [activations, scratch, lora, working, zeros, inputs, outputs, geometry, voxel_tables],
        "the memory footprint",
    )?;
    parts.sort_by_key(|p| std::cmp::Reverse(p.1));
    parts.truncate(LARGEST_SHOWN);
    let footprint = Footprint {
        activations,
        scratch,
        lora,
        working,
        zeros,
        inputs,
        outputs,
        geometry,
        voxel_tables,
        total,
        largest: parts,
    };
    Ok(Layout {
        shapes,
        slot_len,
        scratch_len,
        convs,
        zeros_len,
        lora_len,
        working_len,
        switch_tmp_len,
        footprint,
        bev,
        voxel: voxel_v,
        sparse: sparse_dims,
        threads,
    })
}

fn sum(parts: impl IntoIterator<Item = usize>, what: &str) -> Result<usize, RunError> {
    parts.into_iter().try_fold(0usize, |a, b| a.checked_add(b)).ok_or_else(|| overflow(what.to_string()))
}

/// Which values something reads: a step, or the outputs.
fn read_values(m: &Manifest) -> Vec<bool> {
    let mut read = vec![false; m.values.len()];
    for i in m.steps.iter().flat_map(|s| s.inputs.iter()).chain(m.outputs.iter().map(|o| &o.value)) {
        if let Some(r) = read.get_mut(*i) {
            *r = true;
        }
    }
    read
}

/// A value as messages name it: its index, and the step that writes it or the input it is.
fn value_name(m: &Manifest, writer: Option<usize>, i: usize) -> String {
    if let Some(k) = writer {
        return format!("value {i} (the output of step {k} `{}`)", m.steps[k].path);
    }
    if let Some(Storage::Input(k)) = m.values.get(i).map(|v| v.storage)
        && let Some(spec) = m.inputs.get(k)
    {
        return format!("value {i} (input `{}`)", spec.name);
    }
    format!("value {i}")
}

/// `N = 4` (every symbol and its value), for messages.
pub(super) fn show_bindings(m: &Manifest, symbols: &[usize]) -> String {
    let b: Vec<String> = m.symbols.iter().zip(symbols).map(|(s, v)| format!("{s} = {v}")).collect();
    if b.is_empty() { "the plan's shapes".into() } else { b.join(", ") }
}

/// Refuses a footprint over `limit` bytes at this binding of the symbols.
pub(super) fn within(f: &Footprint, limit: usize, m: &Manifest, symbols: &[usize]) -> Result<(), RunError> {
    if f.total <= limit {
        return Ok(());
    }
    Err(RunError::OverBudget { needed: f.total, limit, at: show_bindings(m, symbols), largest: f.largest.clone() })
}

/// Binds `bound` to new symbol values, refusing a layout whose footprint exceeds `limit`
/// bytes: in place when the buffers keep their lengths ([`Bound::rebind_in_place`]), else
/// afresh, the old buffers freed first so that the new binding alone must fit. On an error
/// `bound` is left as it was.
///
/// The checks read the base's tensors. Every variant's replacement has exactly its base
/// tensor's shape (checked when the plan was built), so they hold under every variant
/// and a switch needs no new check.
pub(super) fn rebind(
    bound: &mut Option<Bound>,
    plan: &Plan,
    symbols: &[usize],
    threads: usize,
    limit: usize,
) -> Result<(), RunError> {
    let layout = layout(plan, symbols, threads)?;
    within(&layout.footprint, limit, &plan.manifest, symbols)?;
    let layout = match bound.as_mut() {
        Some(b) => match b.rebind_in_place(symbols, layout) {
            Ok(()) => return Ok(()),
            Err(layout) => *layout,
        },
        None => layout,
    };
    *bound = None;
    *bound = Some(allocate(symbols, layout));
    Ok(())
}

/// Allocates the buffers of `layout`.
fn allocate(symbols: &[usize], layout: Layout) -> Bound {
    Bound {
        symbols: symbols.to_vec(),
        shapes: layout.shapes,
        slots: layout.slot_len.into_iter().map(Buffer::zeroed).collect(),
        scratch: Buffer::zeroed(layout.scratch_len),
        convs: layout.convs,
        zeros: layout.zeros_len.into_iter().map(|n| vec![0.0; n]).collect(),
        lora_a: layout.lora_len.into_iter().map(|n| vec![0.0; n]).collect(),
        working: layout.working_len.into_iter().map(|n| vec![0.0; n]).collect(),
        switch_tmp: vec![0.0; layout.switch_tmp_len],
        lora_variant: None,
        footprint: layout.footprint,
        bev: layout.bev.into_iter().map(|d| d.map(|d| Mutex::new(bev_pool::Geometry::new(d)))).collect(),
        voxel: layout.voxel.into_iter().map(|v| v.map(|v| Mutex::new(voxel::Table::new(v)))).collect(),
        sparse: layout
            .sparse
            .into_iter()
            .map(|d| {
                d.map(|(conv, d)| {
                    Mutex::new(if conv {
                        sparse::Scratch::conv(&d, layout.threads)
                    } else {
                        sparse::Scratch::out_coords(&d)
                    })
                })
            })
            .collect(),
    }
}

impl Bound {
    /// Takes `layout` (of new symbol values) in place when every buffer it needs has the
    /// length this binding's has, as when the symbol that changed is carried only by an
    /// input the steps read in place (a lidar sweep's point count `P`, different every
    /// frame): the shapes change, no buffer is allocated and the caches (packed LoRA,
    /// working copies, geometry) stay valid. Otherwise hands `layout` back, for a fresh
    /// binding.
    fn rebind_in_place(&mut self, symbols: &[usize], layout: Layout) -> Result<(), Box<Layout>> {
        fn same<B: std::ops::Deref<Target = [f32]>>(bufs: &[B], lens: &[usize]) -> bool {
            bufs.len() == lens.len() && bufs.iter().zip(lens).all(|(b, &n)| b.len() == n)
        }
        let same_geometry = self.bev.len() == layout.bev.len()
            && self.bev.iter().zip(&layout.bev).all(|(g, d)| match (g, d) {
                (None, None) => true,
                (Some(g), Some(d)) => g.lock().is_ok_and(|g| g.dims() == *d),
                _ => false,
            });
        let fits = same(&self.slots, &layout.slot_len)
            && self.scratch.len() == layout.scratch_len
            && same(&self.zeros, &layout.zeros_len)
            && same(&self.lora_a, &layout.lora_len)
            && same(&self.working, &layout.working_len)
            && self.switch_tmp.len() == layout.switch_tmp_len
            && self.convs == layout.convs
            && same_geometry;
        if !fits {
            return Err(Box::new(layout));
        }
        // The voxelization tables are sized by the plan's `max_voxels` alone.
        self.symbols.clear();
        self.symbols.extend_from_slice(symbols);
        self.shapes = layout.shapes;
        self.footprint = layout.footprint;
        Ok(())
    }

    /// Prepares the session's buffers for the variant of `weights`, unless they hold it
    /// already: packs every raw LoRA `A` ([`LoraSpec::a_raw`]) of a branch the variant
    /// gives for its conv's algorithm,
    /// and writes every working copy of a conv merged on switch
    /// (`Kernel::Conv2d::switch`): `pack(W + B A)` from the variant's raw tensors
    /// (`kernels::merge::switch_pack`). Reads the stored tensors, never writes them;
    /// allocates nothing (the lengths were checked at bind time). The caller runs it on
    /// the running thread before any step, so no step sees a half-written copy.
    pub(crate) fn pack_lora(&mut self, plan: &Plan, weights: VariantTensors<'_>) {
        let variant = weights.index();
        if self.lora_variant == Some(variant) {
            return;
        }
        for (k, step) in plan.manifest.steps.iter().enumerate() {
            let Some((s, algo)) = &self.convs[k] else { continue };
            if let Kernel::Conv2d { weight, lora, switch: true, .. } = &step.kernel {
                let l = lora.map(|l| kernels::Lora { a: weights.get(l.a), b: weights.get(l.b), rank: l.rank });
                let (tmp, out) = (&mut self.switch_tmp, &mut self.working[k]);
                merge::switch_pack(s, *algo, weights.get(*weight), l.as_ref(), tmp, out);
            } else if let Some(l) = step.kernel.lora()
                && l.a_raw
                && !weights.reads_zero(l.b)
            {
                // A branch the variant does not give is skipped (`run_step`): nothing
                // reads its `A`, and the next variant that gives it packs again.
                conv::pack_lora_a(s, *algo, l.rank, weights.get(l.a), &mut self.lora_a[k]);
            }
        }
        self.lora_variant = Some(variant);
    }
}

/// The conv parameters of a conv step at the bound shapes (its preconditions checked
/// by [`check_step`]).
fn conv_params(step: &Step, shapes: &[Vec<usize>], at: &str) -> Result<Option<(Conv2dShape, ConvAlgo)>, RunError> {
    let Kernel::Conv2d { conv, algo, .. } = &step.kernel else { return Ok(None) };
    let algo = *algo;
    let x = &shapes[step.inputs[0]];
    let [n, _, h, w] = x[..] else { return Err(bad(at, "conv2d input is not 4-D")) };
    let s = conv::layer_shape(conv, n, h, w);
    if shapes[step.output] != [s.n, s.cout, s.oh, s.ow] {
        return Err(bad(at, "conv2d output shape"));
    }
    Ok(Some((s, algo)))
}

/// Checks a step at the bound shapes against its kernel's preconditions (each kernel
/// module's `check`, which the kernel also asserts in debug builds), so that no input of
/// the declared shapes can make it panic.
fn check_step(plan: &Plan, step: &Step, shapes: &[Vec<usize>]) -> Result<(), String> {
    let base = plan.base_tensors();
    let len = |t: usize| base.get(t).len();
    let ep = |e: &EpilogueSpec| [e.scale.map(len), e.shift.map(len)];
    let lora = |l: &Option<LoraSpec>| l.map(|l| (l.rank, len(l.a), len(l.b)));
    let arity = match &step.kernel {
        Kernel::Pure(Pure::MatMul(_) | Pure::Binary(_)) => Some(2),
        Kernel::Pure(Pure::Where(_)) => Some(3),
        Kernel::Pure(Pure::LssBevPool(_)) => Some(6),
        Kernel::Pure(Pure::Gather(_) | Pure::IndexSelectAt(_)) => Some(2),
        Kernel::Pure(Pure::WhereScalar(w)) => w.arity(),
        Kernel::Pure(Pure::SparseConv3d(c)) => c.arity(),
        Kernel::Pure(Pure::SparseToDense(_)) => Some(2),
        Kernel::Pure(Pure::Concat(_)) => None,
        Kernel::Pure(Pure::LidarDepthMap(_)) => Some(5),
        Kernel::Conv2d { residual, channel_scale, .. } => {
            Some(1 + usize::from(*residual) + usize::from(*channel_scale))
        }
        _ => Some(1),
    };
    if step.inputs.is_empty() || arity.is_some_and(|n| step.inputs.len() != n) {
        return Err(format!("{} inputs for a `{}` kernel", step.inputs.len(), step.kernel.name()));
    }
    let x = shapes[step.inputs[0]].as_slice();
    let input = |j: usize| shapes[step.inputs[j]].as_slice();
    let out = shapes[step.output].as_slice();
    let u = |v: i64| usize::try_from(v).map_err(|_| format!("a negative size {v}"));
    match &step.kernel {
        Kernel::Conv2d { conv: c, algo, weight, epilogue, lora: l, switch, adapter, residual, channel_scale } => {
            let [n, cin, h, w] = x[..] else { return Err(format!("conv2d of a value of shape {x:?}, not 4-D")) };
            if *residual && input(1) != out {
                return Err(format!("conv2d residual of shape {:?}, its output is {out:?}", input(1)));
            }
            if *channel_scale {
                let sc = input(step.inputs.len() - 1);
                if sc != [n, cin, 1, 1] {
                    return Err(format!("conv2d channel scale of shape {sc:?}, its input is {x:?}"));
                }
                if !algo.packs_as_is() || l.is_some() {
                    return Err(format!(
                        "conv2d channel scale on a {} weight{}: only with a weight stored as PyTorch's and no LoRA branch",
                        algo.name(),
                        if l.is_some() { " with a LoRA branch" } else { "" }
                    ));
                }
            }
            if cin != u(c.in_channels)? {
                return Err(format!("conv2d expects {} input channels, its input is {x:?}", c.in_channels));
            }
            let s = conv::layer_shape(c, n, h, w);
            let (xl, ol) = (numel(x).ok_or("conv2d input too large")?, numel(out).ok_or("conv2d output too large")?);
            let mut branch = lora(l);
            if let (Some(spec), Some((rank, a_len, _))) = (l, branch.as_mut())
                && spec.a_raw
            {
                // A raw `A` is PyTorch's layout, the im2col packing; the kernel gets it
                // packed for `algo` (`Bound::pack_lora`).
                let raw = conv::ConvAlgo::Im2col.packed_len(&conv::lora_a_shape(&s, *rank));
                if *a_len != raw {
                    return Err(format!(
                        "LoRA A `{}` has {a_len} values, raw at rank {rank} it needs {raw}",
                        plan.manifest.tensors[spec.a].name
                    ));
                }
                *a_len = conv::lora_a_len(&s, *algo, *rank);
            }
            let mut w_len = len(*weight);
            if *switch {
                // A raw weight, packed for `algo` into the working copy the kernel reads.
                let raw = s.cout.saturating_mul(s.k());
                if w_len != raw {
                    return Err(format!(
                        "conv2d weight `{}` merged on switch has {w_len} values, raw it needs {raw}",
                        plan.manifest.tensors[*weight].name
                    ));
                }
                if l.is_some_and(|l| !l.a_raw) {
                    return Err("a conv merged on switch needs its LoRA A raw".into());
                }
                w_len = conv::packed_weight_len(&s, *algo);
            }
            conv::check(&s, *algo, w_len, xl, ol, ep(epilogue), branch)?;
            if let Some(a) = adapter {
                super::run::conv_adapter(base, a).check(s.cout)?;
            }
            Ok(())
        }
        Kernel::ConvTranspose2d { conv: c, weight, epilogue } => {
            let [n, cin, h, w] = x[..] else {
                return Err(format!("conv_transpose2d of a value of shape {x:?}, not 4-D"));
            };
            if cin != u(c.in_channels)? {
                return Err(format!("conv_transpose2d expects {} input channels, its input is {x:?}", c.in_channels));
            }
            let s = c.shape(n, h, w);
            if [s.oh, s.ow] != out.get(2..).unwrap_or_default() {
                return Err(format!("conv_transpose2d of {x:?} gives {}x{}, its output is {out:?}", s.oh, s.ow));
            }
            let xl = numel(x).ok_or("conv_transpose2d input too large")?;
            let ol = numel(out).ok_or("conv_transpose2d output too large")?;
            conv_transpose::check(&s, len(*weight), xl, ol, ep(epilogue))
        }
        Kernel::Conv3d { conv: c, weight, epilogue } => {
            let [n, cin, d, h, w] = x[..] else {
                return Err(format!("conv3d of a value of shape {x:?}, not 5-D"));
            };
            if cin != u(c.in_channels)? {
                return Err(format!("conv3d expects {} input channels, its input is {x:?}", c.in_channels));
            }
            let s = c.shape(n, d, h, w);
            if s.out != out.get(2..).unwrap_or_default() {
                return Err(format!("conv3d of {x:?} gives {:?}, its output is {out:?}", s.out));
            }
            let xl = numel(x).ok_or("conv3d input too large")?;
            let ol = numel(out).ok_or("conv3d output too large")?;
            conv3d::check(&s, len(*weight), xl, ol, ep(epilogue))
        }
        Kernel::Linear { linear: l, weight, epilogue, lora: r, panels } => {
            let layout = if *panels { linear::WeightLayout::Panels } else { linear::WeightLayout::InOut };
            linear::check(x, u(l.in_features)?, u(l.out_features)?, layout, len(*weight), out, ep(epilogue), lora(r))
        }
        Kernel::ChannelAffine { affine, epilogue } => {
            norm::check_channel_affine(x, u(affine.channels)?, ep(epilogue), out)
        }
        Kernel::LayerNorm { norm: ln, weight, bias } => {
            norm::check_layernorm(x, u(ln.features)?, [weight.map(len), bias.map(len)], out)
        }
        Kernel::GroupNorm { norm: gn, weight, bias } => {
            let (c, g) = (u(gn.num_channels)?, u(gn.num_groups)?);
            norm::check_groupnorm(x, c, g, [weight.map(len), bias.map(len)], out)
        }
        Kernel::Pure(op) => {
            let parts: Vec<&[usize]> = (0..step.inputs.len()).map(input).collect();
            check_pure(op, &parts, out)
        }
    }
}

/// Checks the pure operator `op` on inputs and an output of these shapes against its
/// kernel's preconditions: what [`run_pure`](super::run_pure) needs, for a plan's step at
/// bind time and for the compiler before it folds a constant.
pub fn check_pure(op: &Pure, inputs: &[&[usize]], out: &[usize]) -> Result<(), String> {
    let arity = match op {
        Pure::MatMul(_) | Pure::Binary(_) => Some(2),
        Pure::Where(_) => Some(3),
        Pure::Fill(_) => Some(0),
        Pure::LssBevPool(_) => Some(6),
        Pure::Gather(_) | Pure::IndexSelectAt(_) => Some(2),
        Pure::WhereScalar(w) => w.arity(),
        Pure::SparseConv3d(c) => c.arity(),
        Pure::SparseToDense(_) => Some(2),
        Pure::Concat(_) => None,
        Pure::LidarDepthMap(_) => Some(5),
        _ => Some(1),
    };
    if (arity.is_none() && inputs.is_empty()) || arity.is_some_and(|n| inputs.len() != n) {
        return Err(format!("{} inputs for a `{}` kernel", inputs.len(), op.op().kind_name()));
    }
    if let Pure::Fill(f) = op {
        let n: i64 = f.shape.iter().product();
        return if usize::try_from(n).ok() == numel(out) { Ok(()) } else { Err(format!("a fill of {n} into {out:?}")) };
    }
    let x = inputs[0];
    let u = |v: i64| usize::try_from(v).map_err(|_| format!("a negative size {v}"));
    match op {
        Pure::MatMul(_) => linear::check_matmul(x, inputs[1], out),
        Pure::Binary(_) => elementwise::check_binary(x, inputs[1], out),
        Pure::Scalar(_) | Pure::Activation(_) | Pure::Reshape(_) => elementwise::check_same_length(x, out),
        Pure::Softmax(sm) => softmax::check(x, sm.axis, out),
        Pure::Concat(c) => layout_k::check_concat(inputs, c.axis, out),
        Pure::Permute(p) => layout_k::check_permute(x, &p.perm, out),
        Pure::Pool(p) => pool::check(p, x, out),
        Pure::GlobalAvgPool(_) => pool::check_global_avgpool(x, out),
        Pure::Upsample(_) => resize::check(x, out),
        Pure::Reduce(r) => reduce::check_reduce(r.kind, x, &r.axes, out),
        Pure::AdaptivePool(_) => pool::check_adaptive(x, out),
        Pure::PixelShuffle(p) => resize::check_pixel_shuffle(p.inverse, u(p.factor)?, x, out),
        Pure::Pad(p) => movement::check_pad(p, x, out),
        Pure::Roll(r) => movement::check_roll(r, x, out),
        Pure::Slice(s) => movement::check_slice(s, x, out),
        Pure::Expand(_) => movement::check_expand(x, out),
        Pure::IndexSelect(s) => index::check_index_select(x, s.axis, &s.index, &s.index_shape, out),
        Pure::Where(_) => index::check_where(x, inputs[1], inputs[2], out),
        Pure::Cast(_) => elementwise::check_same_length(x, out),
        Pure::Fill(_) => Ok(()),
        Pure::LssBevPool(op) => bev_pool::check(op, inputs, out).map(|_| ()),
        Pure::ArgReduce(a) => select::check_arg_reduce(x, a.axis, out),
        Pure::TopK(t) => select::check_topk(x, t.k, t.axis, out),
        Pure::Gather(g) => select::check_gather(x, inputs[1], g.axis, g.broadcast, out),
        Pure::IndexSelectAt(s) => select::check_index_select_at(x, inputs[1], s.axis, out),
        Pure::OneHot(h) => select::check_one_hot(x, h.num_classes, out),
        Pure::SparseOutCoords(o) => sparse::check_out_coords(o, inputs, out).map(|_| ()),
        Pure::SparseConv3d(c) => sparse::check_conv(c, inputs, out).map(|_| ()),
        Pure::SparseToDense(o) => sparse::check_to_dense(o, inputs, out),
        Pure::WhereScalar(w) => {
            if w.input.into_iter().chain(w.other).any(|v| !v.is_finite()) {
                return Err("a where with a number that is not finite".into());
            }
            // The tensor branches follow the condition; a number is a tensor of shape [].
            let mut next = 1;
            let mut branch = |v: Option<f64>| match v {
                Some(_) => &[][..],
                None => {
                    next += 1;
                    inputs[next - 1]
                }
            };
            let (a, b) = (branch(w.input), branch(w.other));
            index::check_where(x, a, b, out)
        }
        Pure::Voxelize(v) => voxel::check(v, x, out).map(|_| ()),
        Pure::LidarDepthMap(d) => voxel::check_depth_map(d, inputs, out).map(|_| ()),
    }
}

fn numel(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d))
}
