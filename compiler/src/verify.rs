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
//! 8. The adaptation plan, when present, refers only to existing nodes, and each `tune`
//!    target's slots exist on its node (every variant parameter has a base slot). Exactly
//!    the slots of nodes the plan's injections added are marked added.
//!
//! A violation is a compiler bug, never a user error.

use std::collections::{HashMap, HashSet};

use crate::ir::{Op, SlotKind, TensorType};
use crate::passes::Module;

/// Checks every invariant; returns the violations found.
pub fn verify(module: &Module) -> Result<(), Vec<String>> {
    let g = &module.graph;
    let mut problems = Vec::new();

    // 1.
    let Some(order) = g.topo_order() else {
        return Err(vec!["the graph has a cycle".into()]);
    };

    let mut paths: HashSet<&str> = HashSet::new();
    let mut input_names: HashSet<&str> = HashSet::new();
    for &id in &order {
        let node = g.node(id);
        let at = format!("node `{}` ({})", node.path, node.op.kind_name());

        // 2.
        let mut incoming = g.incoming(id);
        incoming.sort_by_key(|(p, _)| *p);
        for (i, (port, _)) in incoming.iter().enumerate() {
            if *port as usize != i {
                problems.push(format!("{at}: input ports are not 0..{} (found port {port})", incoming.len()));
                break;
            }
        }
        match node.op.arity() {
            Some(n) if n != incoming.len() => {
                problems.push(format!("{at}: has {} inputs, its op takes {n}", incoming.len()));
            }
            None if incoming.is_empty() => problems.push(format!("{at}: variadic op without inputs")),
            _ => {}
        }
        let mut types: Vec<&TensorType> = Vec::new();
        for (_, v) in &incoming {
            match g.value_type(*v) {
                Some(t) => types.push(t),
                None => problems.push(format!("{at}: reads output {} of a node that has no such output", v.port)),
            }
        }

        // 3.
        if let Op::Input(attrs) = &node.op {
            if node.outputs.len() != 1 {
                problems.push(format!("{at}: an input must have one output"));
            }
            if !input_names.insert(&attrs.name) {
                problems.push(format!("{at}: input name `{}` is not unique", attrs.name));
            }
        } else if types.len() == incoming.len() {
            // 4.
            match node.op.infer(&types) {
                Ok(out) if out == node.outputs => {}
                Ok(out) => problems.push(format!(
                    "{at}: stored output types {} differ from inferred {}",
                    show(&node.outputs),
                    show(&out)
                )),
                Err(e) => problems.push(format!("{at}: its inputs no longer fit: {}", e.message)),
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
            problems.push(format!("{at}: parameter slots differ from those its op derives"));
        }

        // 6.
        if !paths.insert(&node.path) {
            problems.push(format!("{at}: path `{}` is not unique", node.path));
        }

        // 7.
        if node.scope.0 as usize >= g.scopes.len() {
            problems.push(format!("{at}: scope {} does not exist", node.scope.0));
        }
    }

    let mut output_names: HashMap<&str, ()> = HashMap::new();
    for o in &g.outputs {
        if output_names.insert(&o.name, ()).is_some() {
            problems.push(format!("output `{}` is declared twice", o.name));
        }
        if g.value_type(o.value).is_none() {
            problems.push(format!("output `{}` refers to a missing value", o.name));
        }
    }
    for (i, s) in g.scopes.iter().enumerate() {
        if let Some(p) = s.parent
            && p.0 as usize >= i
        {
            problems.push(format!("scope `{}` has a parent that does not precede it", s.path));
        }
    }

    // 8.
    if let Some(plan) = &module.adapt {
        for r in &plan.rules {
            for t in &r.targets {
                if !g.contains(t.node) {
                    problems.push(format!("rule `{}` targets a removed node", r.text));
                    continue;
                }
                let node = g.node(t.node);
                for s in &t.slots {
                    if !node.params.iter().any(|p| p.name == *s && p.kind != SlotKind::Added) {
                        problems.push(format!("rule `{}` tunes `{}.{s}`, which has no base slot", r.text, node.path));
                    }
                }
            }
        }
        let mut injected: HashSet<crate::ir::NodeId> = HashSet::new();
        for inj in &plan.injections {
            for n in inj.nodes() {
                if !g.contains(n) {
                    problems.push(format!("an injection refers to removed node {}", n.index()));
                }
                injected.insert(n);
            }
        }
        for id in g.node_ids() {
            let node = g.node(id);
            let added = node.params.iter().any(|p| p.kind == SlotKind::Added);
            let all_added = node.params.iter().all(|p| p.kind == SlotKind::Added);
            if added != injected.contains(&id) && !node.params.is_empty() || (added && !all_added) {
                problems.push(format!("node `{}`: added slots do not match the injections", node.path));
            }
        }
    } else if g.node_ids().any(|id| g.node(id).params.iter().any(|p| p.kind == SlotKind::Added)) {
        problems.push("added parameter slots without an adaptation plan".into());
    }

    if problems.is_empty() { Ok(()) } else { Err(problems) }
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
            Node {
                op: Op::Input(InputAttrs { name: "x".into(), modality: None, optional: false }),
                path: "x".into(),
                scope: ScopeId(0),
                params: vec![],
                outputs: vec![t.clone()],
                span: Span::default(),
            },
            &[],
        );
        let op = Op::Linear(crate::ops::LinearOp {
            linear: crate::ir::Linear { in_features: 4, out_features: 2 },
            bias: true,
        });
        let out = TensorType::new(DType::F32, vec![Dim::symbol("N"), Dim::known(2)]);
        let fc = g.add_node(
            Node {
                params: op.param_slots(),
                op,
                path: "fc".into(),
                scope: ScopeId(0),
                outputs: vec![out],
                span: Span::default(),
            },
            &[ValueRef { node: x, port: 0 }],
        );
        g.outputs.push(GraphOutput { name: "y".into(), value: ValueRef { node: fc, port: 0 }, span: Span::default() });
        Module { graph: g, adapt: None, variants: None }
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
        assert!(errs[0].contains("differ from inferred"), "{errs:?}");
    }

    #[test]
    fn wrong_param_slots_are_caught() {
        let mut m = tiny();
        let fc = m.graph.node_ids().nth(1).expect("fc");
        m.graph.node_mut(fc).params.pop();
        let errs = verify(&m).expect_err("an error");
        assert!(errs.iter().any(|e| e.contains("parameter slots")), "{errs:?}");
    }

    #[test]
    fn duplicate_paths_are_caught() {
        let mut m = tiny();
        let fc = m.graph.node_ids().nth(1).expect("fc");
        m.graph.node_mut(fc).path = "x".into();
        let errs = verify(&m).expect_err("an error");
        assert!(errs.iter().any(|e| e.contains("not unique")), "{errs:?}");
    }

    #[test]
    fn missing_inputs_are_caught() {
        let mut m = tiny();
        let x = m.graph.node_ids().next().expect("x");
        let fc = m.graph.node_ids().nth(1).expect("fc");
        // Re-point fc's input at a port x does not have.
        m.graph.replace_uses(ValueRef { node: x, port: 0 }, ValueRef { node: x, port: 3 });
        let errs = verify(&m).expect_err("an error");
        assert!(errs.iter().any(|e| e.contains("no such output")), "{errs:?} {fc:?}");
    }
}
