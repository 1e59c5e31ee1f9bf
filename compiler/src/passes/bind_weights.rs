//! `bind_weights`: binds the base weights (a safetensors file, PyTorch names) to the
//! graph's parameter slots: the tensor table's first column.
//!
//! Checks, each an error naming the tensor and showing the layer's source line: a slot
//! without a tensor, a tensor of the wrong shape or dtype, a NaN or infinity. A tensor no
//! slot claims is an error too, or a warning when unused tensors are allowed. f16 and bf16
//! tensors are converted to f32 when the file is read. `num_batches_tracked` (a counter
//! PyTorch keeps for every BatchNorm) is understood: it may be present or absent and is
//! not used. An int64 `buffer` (an index table) binds an int64 tensor of the file, kept as
//! exact f32 values; an int64 tensor for a float slot, or a float one for an int64
//! buffer, is an error. The slots an adaptation rule added (LoRA matrices, adapter convs) are zero in
//! the base model; a base file that gives one is an error.
//!
//! Produces: the tensor table ([`TensorTable`]) with every f32 slot's base value, the
//! parameters the variants own (from the adaptation plan) and the spec's parameter list.
//! No variants yet (`bind_variants`). Changes nothing in the graph. Assumes the front end
//! ran.

use std::collections::HashMap;

use readi_grammar::ast::DType;
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, suggest};

use super::{BackendInputs, Output};
use crate::ir::{Graph, NodeId, Op, ParamSlot, SlotKind};
use crate::module::Module;
use crate::weights::WeightSet;
use crate::weights::tensors::{Data, SpecParam, Tensor, TensorTable};
use crate::weights::variants::owned_params;

pub fn run(module: &Module, inputs: &BackendInputs<'_>, warnings: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let g = &module.graph;
    let (bound, w) = bind(g, inputs.base, inputs.base_name, inputs.opts.allow_unused)?;
    warnings.extend(w);
    let owned = owned_params(module);
    let mut table = TensorTable::default();
    for (name, id, slot) in g.param_table() {
        if !binds(g, id, slot) {
            continue;
        }
        let shape: Vec<usize> = slot.shape.iter().map(|&d| d.max(0) as usize).collect();
        let data: Data = match bound.get(&name) {
            Some(d) => Data::from(*d),
            // An added slot: zero in the base model.
            None => Data::from(vec![0.0; shape.iter().product()]),
        };
        table.insert(name.clone(), Tensor::param(&name, shape, data, 0));
    }
    table.params = g
        .param_table()
        .into_iter()
        .map(|(name, _, slot)| SpecParam {
            shape: slot.shape.iter().map(|&d| d.max(0) as usize).collect(),
            trainable: slot.kind != SlotKind::Buffer,
            added: slot.kind == SlotKind::Added,
            name,
        })
        .collect();
    table.owned = owned;
    Ok(Output::Tensors(Box::new(table)))
}

/// Checks `weights` against the graph's slots and returns the value of every base slot by
/// full name, borrowed from the set. `weights_name` names the file in messages.
fn bind<'w>(
    graph: &Graph,
    weights: &'w WeightSet,
    weights_name: &str,
    allow_unused: bool,
) -> Result<(HashMap<String, &'w [f32]>, Diagnostics), Diagnostics> {
    let mut diags = Diagnostics::default();
    let mut bound = HashMap::new();
    let table = graph.param_table();
    let expected: std::collections::HashSet<String> =
        table.iter().filter(|(_, _, s)| s.kind != SlotKind::Added).map(|(name, _, _)| name.clone()).collect();
    let added: std::collections::HashSet<&str> =
        table.iter().filter(|(_, _, s)| s.kind == SlotKind::Added).map(|(name, _, _)| name.as_str()).collect();
    // Tensors no slot claims: the likely intended names when a slot's tensor is missing.
    let unclaimed: Vec<&str> = weights.tensors.keys().filter(|k| !expected.contains(*k)).map(String::as_str).collect();
    let missing = expected.iter().filter(|n| !weights.tensors.contains_key(*n) && !n.ends_with("num_batches_tracked"));
    if let Some((prefix, n)) = name_prefix(&expected, &unclaimed).filter(|&(_, n)| 2 * n >= missing.count().max(1)) {
        // One error for the whole file instead of one per tensor.
        let d = Diagnostic::error(
            Code::Weights,
            format!(
                "`{weights_name}` names its tensors with a prefix the model's parameters do not have: \
                 {n} of its {} tensors are the model's once `{prefix}` is dropped",
                weights.tensors.len()
            ),
        )
        .with_note(format!("pass --strip-prefix {prefix} to drop it (training wrappers such as DataParallel add one)"));
        return Err(Diagnostics(vec![d]));
    }
    let order: Vec<NodeId> = graph.topo_order().unwrap_or_else(|| graph.node_ids().collect());
    for id in order {
        let node = graph.node(id);
        for slot in &node.params {
            let name = node.param_name(slot);
            if !binds(graph, id, slot) || slot.kind == SlotKind::Added {
                // num_batches_tracked: bookkeeping of PyTorch's training, not used here.
                // Added slots (LoRA, adapters) are zero in the base; variants provide them.
                continue;
            }
            let layer = format!("{} `{}`", node.op.kind_name(), node.path);
            let Some((shape, data)) = weights.tensors.get(&name) else {
                let mut d = Diagnostic::error(Code::Weights, format!("`{weights_name}` has no tensor `{name}`"))
                    .with_primary(node.span, format!("{layer} needs `{name}` of shape {:?}", slot.shape));
                if let Some(s) = suggest(&name, unclaimed.iter().copied()) {
                    d = d.with_note(format!("the file has `{s}`, which the model does not use"));
                }
                diags.push(d);
                continue;
            };
            let want: Vec<usize> = slot.shape.iter().map(|&d| d as usize).collect();
            let integer = weights.integer.contains(&name);
            if integer != (slot.dtype == DType::I64) {
                let (has, needs) = if integer { ("int64", "f32") } else { ("float", "int64") };
                diags.push(
                    Diagnostic::error(
                        Code::Weights,
                        format!("tensor `{name}` in `{weights_name}` is {has}, but {layer} needs {needs}"),
                    )
                    .with_primary(node.span, format!("expects {needs} {want:?}")),
                );
                continue;
            }
            if *shape != want {
                diags.push(
                    Diagnostic::error(
                        Code::Weights,
                        format!("tensor `{name}` in `{weights_name}` has shape {shape:?}, but {layer} needs {want:?}"),
                    )
                    .with_primary(node.span, format!("expects {want:?}")),
                );
                continue;
            }
            if let Some(i) = data.iter().position(|v| !v.is_finite()) {
                diags.push(
                    Diagnostic::error(
                        Code::Weights,
                        format!("tensor `{name}` in `{weights_name}` holds {} at flat index {i}", data[i]),
                    )
                    .with_primary(node.span, "weights must be finite"),
                );
                continue;
            }
            bound.insert(name, data.as_slice());
        }
    }
    for name in weights.tensors.keys() {
        if expected.contains(name) {
            continue;
        }
        if added.contains(name.as_str()) {
            diags.push(
                Diagnostic::error(
                    Code::Weights,
                    format!("tensor `{name}` in `{weights_name}` belongs to the variants, not to the base model"),
                )
                .with_note("an adaptation rule adds it; the base model's value is zero")
                .with_note("give it in a variant's parameter file or PEFT adapter instead"),
            );
            continue;
        }
        let message = format!("tensor `{name}` in `{weights_name}` is not a parameter of the model");
        let d = if allow_unused {
            Diagnostic::warning(Code::Weights, message)
        } else {
            Diagnostic::error(Code::Weights, message)
                .with_note("pass --allow-unused to ignore tensors the spec does not use")
        };
        let d = match suggest(name, expected.iter().map(String::as_str)) {
            Some(s) => d.with_note(format!("did you mean the model's `{s}`?")),
            None => d,
        };
        diags.push(d);
    }
    if diags.has_errors() { Err(diags) } else { Ok((bound, diags)) }
}

/// Whether a slot reads a tensor of the weights file: every f32 slot, and an integer
/// `buffer`'s (not BatchNorm's `num_batches_tracked`, which is not used).
fn binds(g: &Graph, id: NodeId, slot: &ParamSlot) -> bool {
    slot.dtype == DType::F32 || (slot.dtype == DType::I64 && matches!(g.node(id).op, Op::Buffer(_)))
}

/// The dotted prefix (`module.`, `model.backbone.`) that, dropped from the most names
/// the model does not use, leaves names it does, with how many it explains.
fn name_prefix(expected: &std::collections::HashSet<String>, unclaimed: &[&str]) -> Option<(String, usize)> {
    let mut counts: HashMap<&str, usize> = HashMap::new();
    for name in unclaimed {
        for (i, _) in name.match_indices('.') {
            if expected.contains(&name[i + 1..]) {
                *counts.entry(&name[..=i]).or_default() += 1;
            }
        }
    }
    // The most names explained; of equals, the shortest prefix, so the answer is stable.
    counts.into_iter().max_by(|a, b| a.1.cmp(&b.1).then(b.0.len().cmp(&a.0.len()))).map(|(p, n)| (p.to_string(), n))
}
