//! `fold_constants`: computes at compile time every pure node whose inputs are all stored
//! tensors no variant changes, so the plan stores its value instead of a step computing
//! it on every run.
//!
//! * rule `fold_constant`: a pure node (a `transpose` of a weight, an index selected from
//!   a table, a mask built from `arange`) whose every input is a parameter, a buffer or a
//!   constant folded before, none owned by a variant, becomes a constant reading the
//!   derived tensor `<path>@const`. The value is computed by the runtime's own kernel
//!   (`readi_runtime::exec::run_pure`, after its shape check `check_pure`), never by a
//!   second implementation, so it is exactly what the step would have computed. The
//!   parameter table is unchanged: the tensor derives from the parameters (`readi
//!   inspect` lists it as `constant-folded into ...`), it is not a new parameter.
//! * rule `fold_index`: an `index_select` (or `embedding`) of a stored table at a stored
//!   index (Swin's `relative_position_bias_table` at `relative_position_index`) becomes a
//!   constant the same way, computed by the runtime's `index_select` kernel;
//! * rule `bake_index`: an `index_select` of a computed tensor at a stored index becomes
//!   the plan's `index_select` step with the index's values in its attributes (checked
//!   against the axis when the plan loads). An index out of range is an error at the call;
//!   an index computed from the model's inputs is refused by `lower`;
//! * rule `drop_folded_input`: a parameter, buffer or constant nothing reads any more
//!   (every reader was folded) leaves the graph, so the plan does not store it.
//!
//! Guards: a node some variant's tensor flows into is not folded (see [`stored`]); nor a
//! graph output (a plan's outputs are computed values); nor a node with a symbolic shape;
//! nor one whose value is much larger than its inputs (an `expand` to a large shape), which
//! would trade a cheap step for plan bytes: at most [`MIN_FOLD_ELEMENTS`] elements or the
//! inputs' total.
//!
//! Does nothing when no pure node reads only stored tensors. Assumes the weights and
//! every variant are bound (and melded and pruned: the values are final).

use readi_grammar::diag::Diagnostics;
use readi_runtime::exec::{check_pure, run_pure};

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch, internal, rebind};
use readi_grammar::diag::{Code, Diagnostic};
use readi_plan::ops::IndexSelect;

use crate::ir::{Dim, Graph, NodeId, Op, Pure, TensorType, ValueRef};
use crate::module::Module;
use crate::ops::ConstantOp;
use crate::weights::tensors::TensorTable;

/// A folded value may always have this many elements (4 MiB); above it, no more than its
/// inputs together.
pub const MIN_FOLD_ELEMENTS: usize = 1 << 20;

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let mut patches = Vec::new();
    for id in g.node_ids() {
        match &g.node(id).op {
            Op::Pure(p) => patches.extend(fold(g, table, id, p)?),
            Op::IndexSelect(s) => patches.extend(index(g, table, id, s.axis)?),
            Op::Parameter(_) | Op::Buffer(_) | Op::Constant(_) if g.uses(id) == 0 => {
                let mut p = Patch::new("drop_folded_input");
                p.remove.push(id);
                patches.push(p);
            }
            _ => {}
        }
    }
    Ok(Output::Patches(patches))
}

/// The name of the stored tensor that is node `id`'s value, if it is one no variant
/// changes: a parameter, a buffer or a constant folded before.
///
/// Variant-owned tensors are not folded: a variant replaces them at run time (switching
/// is an index store), so a value computed from one would have to be derived and stored
/// once per variant; the step computes it from whichever variant is live instead.
fn stored(g: &Graph, table: &TensorTable, id: NodeId) -> Option<String> {
    let node = g.node(id);
    if !matches!(node.op, Op::Parameter(_) | Op::Buffer(_) | Op::Constant(_)) {
        return None;
    }
    let name = node.param_name(node.params.first()?);
    if table.owned.contains_key(&name) || table.get(&name)?.varies() {
        return None;
    }
    Some(name)
}

/// The patch folding or baking the `index_select` node `id` along `axis`, if its index
/// is a stored tensor. An index out of range is the user's error, at the call.
fn index(g: &Graph, table: &TensorTable, id: NodeId, axis: usize) -> Result<Option<Patch>, Diagnostics> {
    let node = g.node(id);
    let inputs = g.inputs(id);
    let [data, idx] = inputs[..] else { return Err(internal(format!("`{}` has {} inputs", node.path, inputs.len()))) };
    let Some(index_name) = stored(g, table, idx.node) else { return Ok(None) };
    let (Some(xt), Some(it)) = (g.value_type(data), g.value_type(idx)) else { return Ok(None) };
    let Some(index_shape) = known(&it.shape) else { return Ok(None) };
    let values = table.get(&index_name).ok_or_else(|| internal("an index is not bound"))?;
    let index: Vec<i64> = values.base.iter().map(|&v| v as i64).collect();
    let op = Pure::IndexSelect(IndexSelect { axis, index, index_shape });
    if let Err(e) = readi_plan::ops::infer(op.op(), &[&TensorType::f32(xt.shape.clone())]) {
        let d = Diagnostic::error(Code::BadValue, format!("index_select `{}`: {e}", node.path))
            .with_primary(node.span, format!("the index `{index_name}` does not fit this tensor"));
        return Err(Diagnostics(vec![d]));
    }
    if stored(g, table, data.node).is_some() {
        // Both stored: the plain fold, by the runtime's kernel.
        let Some(mut p) = fold_reading(g, table, id, &op, &[data], Some(&index_name))? else { return Ok(None) };
        p.rule = "fold_index";
        return Ok(Some(p));
    }
    let mut p = Patch::new("bake_index");
    p.rewrite.push((id, Op::Pure(op), Vec::new()));
    p.detach.push(id);
    p.set_inputs.push((id, 0, data));
    Ok(Some(p))
}

/// Every axis as a known size.
fn known(shape: &[Dim]) -> Option<Vec<usize>> {
    shape.iter().map(|d| d.as_known().and_then(|v| usize::try_from(v).ok())).collect()
}

/// The patch folding pure node `id`, if every guard lets it.
fn fold(g: &Graph, table: &TensorTable, id: NodeId, p: &Pure) -> Result<Option<Patch>, Diagnostics> {
    fold_reading(g, table, id, p, &g.inputs(id), None)
}

/// The patch making node `id` the constant `p` computes from `inputs`, if every guard lets
/// it; `also` names a tensor the value derives from without being a kernel input (an
/// index baked into `p`), for the parameter table.
fn fold_reading(
    g: &Graph,
    table: &TensorTable,
    id: NodeId,
    p: &Pure,
    inputs: &[ValueRef],
    also: Option<&str>,
) -> Result<Option<Patch>, Diagnostics> {
    let node = g.node(id);
    // A constant generator (`arange`, `full`) has no inputs and is always folded: a plan
    // does not run one.
    if (inputs.is_empty() && !matches!(p, Pure::Fill(_))) || g.outputs.iter().any(|o| o.value.node == id) {
        return Ok(None);
    }
    let Some(names) = inputs.iter().map(|v| stored(g, table, v.node)).collect::<Option<Vec<String>>>() else {
        return Ok(None);
    };
    let shapes: Option<Vec<Vec<usize>>> =
        inputs.iter().map(|v| g.value_type(*v).and_then(|t| known(&t.shape))).collect();
    let (Some(shapes), Some(out_shape)) = (shapes, node.outputs.first().and_then(|t| known(&t.shape))) else {
        return Ok(None);
    };
    let out_len: usize = out_shape.iter().product();
    let in_len: usize = shapes.iter().map(|s| s.iter().product::<usize>()).sum();
    if out_len > in_len.max(MIN_FOLD_ELEMENTS) && !matches!(p, Pure::Fill(_)) {
        return Ok(None);
    }
    let parts: Vec<&[usize]> = shapes.iter().map(Vec::as_slice).collect();
    // Shape inference agreed to these shapes; a kernel refusing them is a compiler bug.
    check_pure(p, &parts, &out_shape).map_err(|e| internal(format!("`{}` cannot be folded: {e}", node.path)))?;
    let refs: Vec<&str> = names.iter().map(String::as_str).chain(also).collect();
    let refused = std::cell::RefCell::new(None);
    let folded = table
        .derive_one(&refs, "constant-folded into", out_shape.clone(), |v| {
            let mut out = vec![0.0f32; out_len];
            *refused.borrow_mut() = run_pure(p, parts.len(), |j| (v[j], parts[j]), &mut out, &out_shape, 1).err();
            out
        })
        .map_err(internal)?;
    if let Some(why) = refused.into_inner() {
        let d =
            Diagnostic::error(Code::BadValue, format!("{} `{}` of constants: {why}", p.op().kind_name(), node.path))
                .with_primary(node.span, "computed at compile time from these constants");
        return Err(Diagnostics(vec![d]));
    }
    let name = format!("{}@const", node.path);
    let shape = out_shape.iter().map(|&d| d as i64).collect();
    let dtype = node.outputs[0].dtype;
    let op = Op::Constant(ConstantOp { shape, dtype, from: p.op().kind_name() });
    let mut patch = Patch::new("fold_constant");
    patch.rewrite.push((id, op.clone(), rebind(&op, &[], &[("", name.clone())])));
    patch.detach.push(id);
    patch.tensors.push((name, folded));
    Ok(Some(patch))
}
