//! The graph as Graphviz DOT, with block instances and sequences as nested clusters.

use std::collections::HashMap;
use std::fmt::Write;

use crate::ir::{Graph, NodeId, Op, ScopeId, ScopeKind};

/// DOT text for `dot -Tsvg`.
pub fn to_dot(g: &Graph) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "digraph \"{}\" {{", esc(&g.name));
    let _ = writeln!(out, "  rankdir=TB;");
    let _ = writeln!(
        out,
        "  node [shape=box, style=\"rounded,filled\", fillcolor=\"#f4f4f4\", fontname=\"Helvetica\", fontsize=10];"
    );
    let _ = writeln!(out, "  edge [fontname=\"Helvetica\", fontsize=8, color=\"#666666\"];");
    let order = g.topo_order().unwrap_or_else(|| g.node_ids().collect());

    // Children of each scope, and the nodes directly in it.
    let mut child_scopes: HashMap<ScopeId, Vec<ScopeId>> = HashMap::new();
    for (i, s) in g.scopes.iter().enumerate() {
        if let Some(p) = s.parent {
            child_scopes.entry(p).or_default().push(ScopeId(i as u32));
        }
    }
    let mut nodes_in: HashMap<ScopeId, Vec<NodeId>> = HashMap::new();
    for &n in &order {
        nodes_in.entry(g.node(n).scope).or_default().push(n);
    }
    write_scope(&mut out, g, g.root_scope(), &child_scopes, &nodes_in, 1);

    for &n in &order {
        for (port, v) in g.incoming(n) {
            let label = g.value_type(v).map(|t| t.to_string()).unwrap_or_default();
            let _ = writeln!(
                out,
                "  n{} -> n{} [label=\"{}\"{}];",
                v.node.index(),
                n.index(),
                esc(&label),
                if port > 0 { format!(", headlabel=\"{port}\"") } else { String::new() }
            );
        }
    }
    for o in &g.outputs {
        let _ =
            writeln!(out, "  out_{} [label=\"{}\", shape=oval, fillcolor=\"#d9ead3\"];", ident(&o.name), esc(&o.name));
        let _ = writeln!(out, "  n{} -> out_{};", o.value.node.index(), ident(&o.name));
    }
    out.push_str("}\n");
    out
}

fn write_scope(
    out: &mut String,
    g: &Graph,
    scope: ScopeId,
    children: &HashMap<ScopeId, Vec<ScopeId>>,
    nodes_in: &HashMap<ScopeId, Vec<NodeId>>,
    depth: usize,
) {
    let pad = "  ".repeat(depth);
    for &n in nodes_in.get(&scope).map(Vec::as_slice).unwrap_or(&[]) {
        let node = g.node(n);
        let (label, color) = match &node.op {
            Op::Input(a) => {
                let m = a.modality.as_deref().map(|m| format!(" @{m}")).unwrap_or_default();
                (format!("{}{m}\\n{}", a.name, node.outputs[0]), "#cfe2f3")
            }
            op => {
                let short = node.path.rsplit('.').next().unwrap_or(&node.path);
                let color = if op.has_params() { "#fff2cc" } else { "#f4f4f4" };
                (format!("{}\\n{}", esc(short), op.kind_name()), color)
            }
        };
        let _ = writeln!(
            out,
            "{pad}n{} [label=\"{label}\", fillcolor=\"{color}\", tooltip=\"{}\"];",
            n.index(),
            esc(&node.path)
        );
    }
    for &c in children.get(&scope).map(Vec::as_slice).unwrap_or(&[]) {
        let info = g.scope(c);
        let kind = match &info.kind {
            ScopeKind::Block(b) => format!(" : {b}"),
            ScopeKind::Seq => " (seq)".to_string(),
            ScopeKind::List => " (list)".to_string(),
            _ => String::new(),
        };
        let _ = writeln!(out, "{pad}subgraph cluster_{} {{", c.0);
        let _ = writeln!(
            out,
            "{pad}  label=\"{}{}\"; style=rounded; color=\"#999999\"; fontname=\"Helvetica\"; fontsize=10;",
            esc(&info.path),
            esc(&kind)
        );
        write_scope(out, g, c, children, nodes_in, depth + 1);
        let _ = writeln!(out, "{pad}}}");
    }
}

fn esc(s: &str) -> String {
    s.replace('\\', "\\\\").replace('"', "\\\"")
}

fn ident(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect()
}
