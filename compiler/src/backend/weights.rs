//! `bind_weights`: reads a safetensors file and binds its tensors to the graph's
//! parameter slots by PyTorch name.
//!
//! Checks, each an error naming the tensor and showing the layer's source line: a slot
//! without a tensor, a tensor of the wrong shape or dtype, a NaN or infinity. A tensor no
//! slot claims is an error too, or a warning when unused tensors are allowed. f16 and bf16
//! tensors are converted to f32. `num_batches_tracked` (a counter PyTorch keeps for every
//! BatchNorm) is understood: it may be present or absent and is not used.

use std::collections::{BTreeMap, HashMap};

use readi_grammar::ast::DType;
use readi_grammar::diag::{Code, Diagnostic, Diagnostics, suggest};
use safetensors::tensor::{Dtype, SafeTensors};

use crate::ir::{Graph, NodeId, SlotKind};

/// Tensors by name, as f32.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WeightSet {
    pub tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)>,
}

/// A problem with a weights file as a whole (not tied to one layer).
fn file_error(file: &str, message: String) -> Diagnostic {
    Diagnostic::error(Code::Weights, format!("{file}: {message}"))
}

impl WeightSet {
    /// Parses safetensors bytes. Tensors of float types become f32; integer tensors are
    /// kept only if they are `num_batches_tracked` counters (and then ignored).
    pub fn from_safetensors(file: &str, bytes: &[u8]) -> Result<WeightSet, Diagnostics> {
        let st = SafeTensors::deserialize(bytes).map_err(|e| {
            Diagnostics(vec![file_error(file, format!("not a valid safetensors file ({e}); is it truncated?"))])
        })?;
        let mut set = WeightSet::default();
        let mut diags = Diagnostics::default();
        let mut names: Vec<String> = st.names().into_iter().map(String::from).collect();
        names.sort();
        for name in names {
            let Ok(view) = st.tensor(&name) else { continue };
            let shape = view.shape().to_vec();
            let data = view.data();
            let values: Vec<f32> = match view.dtype() {
                Dtype::F32 => data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
                Dtype::F16 => data.chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                Dtype::BF16 => data.chunks_exact(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                Dtype::I64 if name.ends_with("num_batches_tracked") => continue,
                other => {
                    diags.push(file_error(
                        file,
                        format!("tensor `{name}` has dtype {other:?}; readi reads F32, F16 and BF16 weights"),
                    ));
                    continue;
                }
            };
            set.tensors.insert(name, (shape, values));
        }
        if diags.has_errors() { Err(diags) } else { Ok(set) }
    }

    /// The set as safetensors bytes (f32), as PyTorch's `save_file(state_dict)` writes.
    pub fn to_safetensors(&self) -> Result<Vec<u8>, String> {
        use safetensors::tensor::TensorView;
        let bytes: Vec<(&String, &Vec<usize>, Vec<u8>)> = self
            .tensors
            .iter()
            .map(|(name, (shape, data))| (name, shape, data.iter().flat_map(|v| v.to_le_bytes()).collect()))
            .collect();
        let mut views = Vec::with_capacity(bytes.len());
        for (name, shape, b) in &bytes {
            let view = TensorView::new(Dtype::F32, (*shape).clone(), b).map_err(|e| format!("tensor `{name}`: {e}"))?;
            views.push(((*name).clone(), view));
        }
        safetensors::serialize(views, None).map_err(|e| e.to_string())
    }
}

/// The value of every parameter slot of the graph, by full name, borrowed from the
/// weight set (weights are copied once, into the plan, by `lower`).
pub type Bound<'w> = HashMap<String, &'w [f32]>;

/// Binds `weights` to the graph's slots. `weights_name` names the file in messages.
pub fn bind<'w>(
    graph: &Graph,
    weights: &'w WeightSet,
    weights_name: &str,
    allow_unused: bool,
) -> Result<(Bound<'w>, Diagnostics), Diagnostics> {
    let mut diags = Diagnostics::default();
    let mut bound = Bound::new();
    let table = graph.param_table();
    let expected: std::collections::HashSet<String> =
        table.iter().filter(|(_, _, s)| s.kind != SlotKind::Added).map(|(name, _, _)| name.clone()).collect();
    let added: std::collections::HashSet<&str> =
        table.iter().filter(|(_, _, s)| s.kind == SlotKind::Added).map(|(name, _, _)| name.as_str()).collect();
    // Tensors no slot claims: the likely intended names when a slot's tensor is missing.
    let unclaimed: Vec<&str> = weights.tensors.keys().filter(|k| !expected.contains(*k)).map(String::as_str).collect();
    let order: Vec<NodeId> = graph.topo_order().unwrap_or_else(|| graph.node_ids().collect());
    for id in order {
        let node = graph.node(id);
        for slot in &node.params {
            let name = node.param_name(slot);
            if slot.dtype == DType::I64 || slot.kind == SlotKind::Added {
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
