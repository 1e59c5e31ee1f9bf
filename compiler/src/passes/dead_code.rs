//! `dead_code`: removes nodes that no graph output depends on.
//!
//! Changes: deletes every non-input node from which no output is reachable. Layers with
//! parameters among them are reported (a warning): their weights would be loaded for
//! nothing, which usually means a forgotten `output` or a typo in a name. Unused inputs
//! are kept (they are the model's interface) and reported.
//!
//! Assumes: a verified graph. Returns `None` when there is nothing to remove, so the
//! driver's fixed-point loop ends after one round.

use std::collections::HashSet;

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};

use super::Patch;
use crate::ir::{Graph, NodeId, Op};

pub fn run(graph: &Graph, diags: &mut Diagnostics) -> Option<Patch> {
    let mut live: HashSet<NodeId> = HashSet::new();
    let mut stack: Vec<NodeId> = graph.outputs.iter().map(|o| o.value.node).collect();
    while let Some(n) = stack.pop() {
        if live.insert(n) {
            stack.extend(graph.inputs(n).into_iter().map(|v| v.node));
        }
    }
    let mut remove = Vec::new();
    for id in graph.node_ids() {
        if live.contains(&id) {
            continue;
        }
        let node = graph.node(id);
        if let Op::Input(attrs) = &node.op {
            diags.push(
                Diagnostic::warning(Code::Unused, format!("input `{}` is not used by any output", attrs.name))
                    .with_primary(node.span, "unused input"),
            );
            continue;
        }
        if node.op.has_params() {
            diags.push(
                Diagnostic::warning(
                    Code::Unused,
                    format!("layer `{}` does not contribute to any output; it is removed", node.path),
                )
                .with_primary(node.span, "unused layer with parameters"),
            );
        }
        remove.push(id);
    }
    (!remove.is_empty()).then_some(Patch { remove, ..Patch::new("dead_code.unreachable") })
}
