//! The IR verifier.
//!
//! Invariants of a valid [`Module`], checked after every pass:
//!
//! 1. The graph is acyclic.
//! 2. Each node's incoming edges use input ports `0..n` exactly once, and `n` is the op's
//!    arity (at least one for variadic ops); every edge leaves from an existing output port.
//! 3. Input nodes ([`Op::Input`]) have no incoming edges, exactly one output, and unique
//!    names; graph outputs have unique names and refer to existing node outputs.
//! 4. Every node's stored output types equal shape inference run again on its inputs'
//!    types (shapes agree along every edge).
//! 5. Every node's parameter slots equal the slots its op derives (names, shapes, dtypes);
//!    a trainable slot may be marked added ([`SlotKind::Added`]).
//! 6. Node paths are unique, so every parameter's full name (`path.slot`) is bound once.
//! 7. Every node's scope exists, and every scope's parent precedes it.
//! 8. The adaptation plan, when present, refers only to existing nodes; until the weights
//!    are bound, each `tune` target's slots exist on its node (every variant parameter has
//!    a base slot) and exactly the slots of nodes the plan's injections added are marked
//!    added.
//! 9. Once weights are bound (the tensor table exists): every f32 slot reads a tensor of
//!    the table with the slot's shape; every tensor has one value row per variant, each
//!    value of the tensor's length; a conv's algorithm computes it, and a packed conv has
//!    one.
//! 10. Once lowered: the manifest passes the plan checks the runtime makes at load
//!     (`readi_plan::validate`), and there is one data vector of the right length per
//!     stored tensor.
//!
//! A violation is a compiler bug, never a user error. Each is reported with the node it
//! concerns, so the driver can point at the node's source.

use std::collections::{HashMap, HashSet};

use crate::ir::{DType, NodeId, Op, SlotKind, TensorType};
use crate::module::Module;

/// A broken invariant: what, and at which node (`None` for the graph as a whole).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VerifyError {
    pub node: Option<NodeId>,
    pub message: String,
}

impl std::fmt::Display for VerifyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

/// Checks every invariant; returns the violations found.
pub fn verify(module: &Module) -> Result<(), Vec<VerifyError>> {
    let mut problems = Vec::new();
    graph(module, &mut problems);
    if problems.is_empty() {
        tensors(module, &mut problems);
        lowered(module, &mut problems);
    }
    if problems.is_empty() { Ok(()) } else { Err(problems) }
}

/// Invariants 1 to 8.
fn graph(module: &Module, problems: &mut Vec<VerifyError>) {
    let g = &module.graph;
    let at_node = |n: NodeId, m: String| VerifyError { node: Some(n), message: m };
    let whole = |m: String| VerifyError { node: None, message: m };

    // 1.
    let Some(order) = g.topo_order() else {
        problems.push(whole("the graph has a cycle".into()));
        return;
    };

    let mut paths: HashSet<&str> = HashSet::new();
    let mut input_names: HashSet<&str> = HashSet::new();
    for &id in &order {
        let node = g.node(id);
        let at = format!("node `{}` ({})", node.path, node.op.kind_name());
        let mut push = |m: String| problems.push(at_node(id, m));

        // 2.
        let mut incoming = g.incoming(id);
        incoming.sort_by_key(|(p, _)| *p);
        for (i, (port, _)) in incoming.iter().enumerate() {
            if *port as usize != i {
                push(format!("{at}: input ports are not 0..{} (found port {port})", incoming.len()));
                break;
            }
        }
        match node.op.arity() {
            Some(n) if n != incoming.len() => push(format!("{at}: has {} inputs, its op takes {n}", incoming.len())),
            None if incoming.is_empty() => push(format!("{at}: variadic op without inputs")),
            _ => {}
        }
        let mut types: Vec<&TensorType> = Vec::new();
        for (_, v) in &incoming {
            match g.value_type(*v) {
                Some(t) => types.push(t),
                None => push(format!("{at}: reads output {} of a node that has no such output", v.port)),
            }
        }

        // 3.
        if let Op::Input(attrs) = &node.op {
            if node.outputs.len() != 1 {
                push(format!("{at}: an input must have one output"));
            }
            if !input_names.insert(&attrs.name) {
                push(format!("{at}: input name `{}` is not unique", attrs.name));
            }
        } else if types.len() == incoming.len() {
            // 4.
            match node.op.infer(&types) {
                Ok(out) if out == node.outputs => {}
                Ok(out) => push(format!(
                    "{at}: stored output types {} differ from inferred {}",
                    show(&node.outputs),
                    show(&out)
                )),
                Err(e) => push(format!("{at}: its inputs no longer fit: {}", e.message)),
            }
        }

        // 5.
        let derived = node.op.param_slots();
        let same = node.params.len() == derived.len()
            && node.params.iter().zip(&derived).all(|(p, d)| {
                let kind_ok = p.kind == d.kind || (p.kind == SlotKind::Added && d.kind == SlotKind::Param);
                p.name == d.name && p.shape == d.shape && p.dtype == d.dtype && kind_ok
            });
        if !same {
            push(format!("{at}: parameter slots differ from those its op derives"));
        }

        // 6.
        if !paths.insert(&node.path) {
            push(format!("{at}: path `{}` is not unique", node.path));
        }

        // 7.
        if node.scope.0 as usize >= g.scopes.len() {
            push(format!("{at}: scope {} does not exist", node.scope.0));
        }
    }

    let mut output_names: HashMap<&str, ()> = HashMap::new();
    for o in &g.outputs {
        if output_names.insert(&o.name, ()).is_some() {
            problems.push(whole(format!("output `{}` is declared twice", o.name)));
        }
        if g.value_type(o.value).is_none() {
            problems.push(whole(format!("output `{}` refers to a missing value", o.name)));
        }
    }
    for (i, s) in g.scopes.iter().enumerate() {
        if let Some(p) = s.parent
            && p.0 as usize >= i
        {
            problems.push(whole(format!("scope `{}` has a parent that does not precede it", s.path)));
        }
    }

    // 8.
    if let Some(plan) = &module.adapt {
        for r in &plan.rules {
            for t in &r.targets {
                if !g.contains(t.node) {
                    problems.push(whole(format!("rule `{}` targets a removed node", r.text)));
                    continue;
                }
                let node = g.node(t.node);
                // Once the weights are bound, ownership is the tensor table's, and the
                // back end may give a tuned slot another role (a bias becomes a shift).
                for s in t.slots.iter().filter(|_| module.tensors.is_none()) {
                    if !node.params.iter().any(|p| p.name == *s && p.kind != SlotKind::Added) {
                        let m = format!("rule `{}` tunes `{}.{s}`, which has no base slot", r.text, node.path);
                        problems.push(at_node(t.node, m));
                    }
                }
            }
        }
        let mut injected: HashSet<NodeId> = HashSet::new();
        for inj in &plan.injections {
            for n in inj.nodes().into_iter().chain([inj.anchor()]) {
                if !g.contains(n) {
                    problems.push(whole(format!("an injection refers to removed node {}", n.index())));
                }
            }
            injected.extend(inj.nodes());
        }
        for id in g.node_ids().filter(|_| module.tensors.is_none()) {
            let node = g.node(id);
            let added = node.params.iter().any(|p| p.kind == SlotKind::Added);
            let all_added = node.params.iter().all(|p| p.kind == SlotKind::Added);
            if added != injected.contains(&id) && !node.params.is_empty() || (added && !all_added) {
                problems.push(at_node(id, format!("node `{}`: added slots do not match the injections", node.path)));
            }
        }
    } else if module.tensors.is_none()
        && g.node_ids().any(|id| g.node(id).params.iter().any(|p| p.kind == SlotKind::Added))
    {
        problems.push(whole("added parameter slots without an adaptation plan".into()));
    }
}

/// Invariant 9.
fn tensors(module: &Module, problems: &mut Vec<VerifyError>) {
    let Some(table) = &module.tensors else { return };
    let g = &module.graph;
    for id in g.node_ids() {
        let node = g.node(id);
        for slot in node.params.iter().filter(|s| s.dtype == DType::F32) {
            let name = node.param_name(slot);
            let want: Vec<usize> = slot.shape.iter().map(|&d| d.max(0) as usize).collect();
            match table.get(&name) {
                None => problems.push(VerifyError {
                    node: Some(id),
                    message: format!("node `{}`: slot `{}` reads `{name}`, which is not bound", node.path, slot.name),
                }),
                Some(t) if t.shape != want => problems.push(VerifyError {
                    node: Some(id),
                    message: format!(
                        "node `{}`: slot `{}` has shape {want:?}, its tensor `{name}` {:?}",
                        node.path, slot.name, t.shape
                    ),
                }),
                Some(_) => {}
            }
        }
        if let Op::Conv2d(c) = &node.op {
            // What an algorithm supports does not depend on the spatial size.
            let fits = c.algo.map(|a| a.supports(&c.conv.shape(1, 0, 0)));
            if fits == Some(false) || (c.packed && fits.is_none()) {
                let m = format!(
                    "node `{}`: packed without an algorithm, or an algorithm that cannot compute it",
                    node.path
                );
                problems.push(VerifyError { node: Some(id), message: m });
            }
        }
    }
    let n = table.variant_count();
    for (name, t) in table.iter() {
        let len = t.numel();
        if t.base.len() != len || t.variants.len() != n || t.variants.iter().flatten().any(|v| v.len() != len) {
            problems.push(VerifyError {
                node: None,
                message: format!("tensor `{name}` does not have one value of {len} elements per variant"),
            });
        }
    }
}

/// Invariant 10.
fn lowered(module: &Module, problems: &mut Vec<VerifyError>) {
    let Some(l) = &module.lowered else { return };
    if let Err(e) = readi_plan::validate::manifest(&l.manifest) {
        problems.push(VerifyError { node: None, message: format!("the lowered plan is invalid: {e}") });
    }
    let m = &l.manifest;
    let lengths_ok = l.data.len() == m.tensors.len()
        && m.tensors.iter().zip(&l.data).all(|(t, d)| t.numel() == d.len() && t.dtype == d.dtype());
    if !lengths_ok {
        problems
            .push(VerifyError { node: None, message: "the lowered plan's tensor data do not fit its tensors".into() });
    }
}

fn show(types: &[TensorType]) -> String {
    types.iter().map(|t| t.to_string()).collect::<Vec<_>>().join(", ")
}

#[cfg(test)]
mod tests {
    use readi_grammar::ast::DType;
    use readi_grammar::diag::Span;

    use super::*;
    use crate::ir::*;

    fn tiny() -> Module {
        let mut g = Graph::new("m", Span::default());
        let t = TensorType::new(DType::F32, vec![Dim::symbol("N"), Dim::known(4)]);
        let x = g.add_node(
            Node::new(
                Op::Input(InputAttrs { name: "x".into(), modality: None, optional: false }),
                "x".into(),
                ScopeId(0),
                vec![],
                vec![t.clone()],
                Span::default(),
            ),
            &[],
        );
        let op = Op::Linear(crate::ops::LinearOp::new(crate::ir::Linear { in_features: 4, out_features: 2 }, true));
        let out = TensorType::new(DType::F32, vec![Dim::symbol("N"), Dim::known(2)]);
        let fc = g.add_node(
            Node::new(op.clone(), "fc".into(), ScopeId(0), op.param_slots(), vec![out], Span::default()),
            &[ValueRef { node: x, port: 0 }],
        );
        g.outputs.push(GraphOutput { name: "y".into(), value: ValueRef { node: fc, port: 0 }, span: Span::default() });
        Module::new(g)
    }

    #[test]
    fn a_well_formed_graph_passes() {
        assert_eq!(verify(&tiny()), Ok(()));
    }

    #[test]
    fn a_wrong_stored_shape_is_caught() {
        let mut m = tiny();
        let fc = m.graph.node_ids().nth(1).expect("fc");
        m.graph.node_mut(fc).outputs[0].shape[1] = Dim::known(3);
        let errs = verify(&m).expect_err("an error");
        assert!(errs[0].message.contains("differ from inferred"), "{errs:?}");
    }

    #[test]
    fn wrong_param_slots_are_caught() {
        let mut m = tiny();
        let fc = m.graph.node_ids().nth(1).expect("fc");
        m.graph.node_mut(fc).params.pop();
        let errs = verify(&m).expect_err("an error");
        assert!(errs.iter().any(|e| e.message.contains("parameter slots")), "{errs:?}");
    }

    #[test]
    fn duplicate_paths_are_caught() {
        let mut m = tiny();
        let fc = m.graph.node_ids().nth(1).expect("fc");
        m.graph.node_mut(fc).path = "x".into();
        let errs = verify(&m).expect_err("an error");
        assert!(errs.iter().any(|e| e.message.contains("not unique")), "{errs:?}");
    }

    #[test]
    fn missing_inputs_are_caught() {
        let mut m = tiny();
        let x = m.graph.node_ids().next().expect("x");
        let fc = m.graph.node_ids().nth(1).expect("fc");
        // Re-point fc's input at a port x does not have.
        m.graph.replace_uses(ValueRef { node: x, port: 0 }, ValueRef { node: x, port: 3 });
        let errs = verify(&m).expect_err("an error");
        assert!(errs.iter().any(|e| e.message.contains("no such output")), "{errs:?} {fc:?}");
    }
}
