//! The IR as stable, readable text.
//!
//! Nodes are renumbered `%0, %1, ...` in topological order (creation order wherever
//! dependencies allow), so the text depends only on the graph's meaning, not on the
//! history of node ids. Each node is one line, `%k path = op(inputs) {attrs} : type`,
//! followed by an indented line of its parameter slots. The adaptation plan and the
//! variant spec, when present, follow the nodes.
//!
//! In the back end a node may show the nodes fused into it (`%3 conv1 (+bn1) = ...`), a
//! slot the tensor a pass bound it to (`scale f32[64] = bn1@scale`) and the variants whose
//! value of that tensor differs from the base's (`{fog=0.03, gamma=4}`); a `tensors` line
//! sums up the tensor table.

use std::collections::HashMap;
use std::fmt::Write;

use super::thousands;
use crate::adapt::RuleKind;
use crate::ir::{Graph, NodeId, Op, SlotKind, ValueRef};
use crate::module::Module;
use crate::passes::check_variants::{KeySource, MissingPolicy, fmt_level};
use crate::weights::tensors::TensorTable;

/// The module as text.
pub fn to_text(module: &Module) -> String {
    let g = &module.graph;
    let mut out = String::new();
    let params: Vec<String> = g.model_params.iter().map(|(k, v)| format!("{k} = {v}")).collect();
    if params.is_empty() {
        let _ = writeln!(out, "model {}", g.name);
    } else {
        let _ = writeln!(out, "model {}({})", g.name, params.join(", "));
    }
    let order = g.topo_order().unwrap_or_else(|| g.node_ids().collect());
    let number: HashMap<NodeId, usize> = order.iter().enumerate().map(|(i, n)| (*n, i)).collect();
    let val = |v: ValueRef| -> String {
        let k = number.get(&v.node).copied().unwrap_or(usize::MAX);
        if v.port == 0 { format!("%{k}") } else { format!("%{k}.{}", v.port) }
    };
    for &id in &order {
        let node = g.node(id);
        let k = number[&id];
        let types: Vec<String> = node.outputs.iter().map(|t| t.to_string()).collect();
        if let Op::Input(a) = &node.op {
            let mut line = format!("  %{k} = input {}", a.name);
            if let Some(m) = &a.modality {
                let _ = write!(line, " @{m}");
            }
            if a.optional {
                line.push_str(" optional");
            }
            let _ = writeln!(out, "{line} : {}", types.join(", "));
            continue;
        }
        let inputs: Vec<String> = g.inputs(id).into_iter().map(val).collect();
        let attrs: Vec<String> = node.op.attrs().into_iter().map(|(k, v)| format!("{k}={v}")).collect();
        let attrs = if attrs.is_empty() { String::new() } else { format!(" {{{}}}", attrs.join(", ")) };
        let _ = writeln!(
            out,
            "  %{k} {} = {}({}){attrs} : {}",
            node.display_path(),
            node.op.kind_name(),
            inputs.join(", "),
            types.join(", ")
        );
        if !node.params.is_empty() {
            let list = |kind: SlotKind| -> Vec<String> {
                node.params
                    .iter()
                    .filter(|s| s.kind == kind)
                    .map(|s| {
                        let dims: Vec<String> = s.shape.iter().map(|d| d.to_string()).collect();
                        let name = if s.name.is_empty() { "(value)" } else { s.name };
                        let bound = s.tensor.as_ref().map(|t| format!(" = {t}")).unwrap_or_default();
                        let varies =
                            module.tensors.as_ref().map(|t| varies(t, &node.param_name(s))).unwrap_or_default();
                        format!("{name} {}[{}]{bound}{varies}", s.dtype.as_str(), dims.join(", "))
                    })
                    .collect()
            };
            let groups = [(SlotKind::Param, "params"), (SlotKind::Buffer, "buffers"), (SlotKind::Added, "added")];
            let parts: Vec<String> = groups
                .iter()
                .map(|&(kind, label)| (label, list(kind)))
                .filter(|(_, l)| !l.is_empty())
                .map(|(label, l)| format!("{label} {}", l.join(", ")))
                .collect();
            let _ = writeln!(out, "      {}", parts.join("; "));
        }
    }
    for o in &g.outputs {
        let _ = writeln!(out, "  output {} = {}", o.name, val(o.value));
    }
    if let Some(t) = &module.tensors {
        let elements: usize = t.iter().map(|(_, x)| x.numel()).sum();
        let keys: Vec<String> = t.variants.iter().map(|v| v.key.to_string()).collect();
        let variants =
            if keys.is_empty() { "no variants".to_string() } else { format!("variants {}", keys.join(", ")) };
        let _ = writeln!(out, "tensors: {} ({} elements); {variants}", t.len(), thousands(elements as u64));
    }
    if let Some(t) = &module.tensors {
        // Once bound, the table says what the variants own; the rules' targets are gone
        // with the nodes the back end folded away.
        let count = |added: bool| {
            t.owned.values().filter(|o| o.added == added).map(|o| o.shape.iter().product::<usize>() as u64).sum::<u64>()
        };
        let scoped = t.owned.values().any(|o| o.scopes.iter().any(|s| !s.is_all()));
        if !scoped {
            let _ = writeln!(
                out,
                "  per variant: {} existing elements tuned, {} added",
                thousands(count(false)),
                thousands(count(true))
            );
        } else {
            // Each variant owns its scopes' parameters.
            for v in &t.variants {
                let (mut tuned, mut added) = (0u64, 0u64);
                for (_, o) in t.owned_by(&v.key) {
                    *(if o.added { &mut added } else { &mut tuned }) += o.shape.iter().product::<usize>() as u64;
                }
                let _ = writeln!(
                    out,
                    "  variant {}: {} existing elements tuned, {} added",
                    v.key,
                    thousands(tuned),
                    thousands(added)
                );
            }
        }
        if let Some((layers, total, zero)) = crate::passes::prune::zeros(module, t) {
            let _ = writeln!(
                out,
                "  prune: {} of {} values zero in the {layers} shared weights the rules select",
                thousands(zero),
                thousands(total)
            );
        }
    } else if let Some(plan) = &module.adapt {
        let _ = writeln!(out, "adapt");
        for (i, r) in plan.rules.iter().enumerate() {
            let what = match &r.kind {
                RuleKind::Tune => "tunes",
                RuleKind::Lora { .. } => "adds LoRA to",
                RuleKind::Adapter { .. } => "adds adapters before",
                RuleKind::Prune { .. } => "prunes the shared weights of",
            };
            let tuned: u64 = r.targets.iter().map(|t| t.tuned).sum();
            let added: u64 = r.targets.iter().map(|t| t.added).sum();
            let mut detail = String::new();
            if let Some(scale) = r.kind.lora_scale() {
                let _ = write!(detail, ", scale {scale}");
            }
            let scope = if r.scope.is_all() { String::new() } else { format!("  (scope {})", r.scope.label()) };
            let _ = writeln!(out, "  #{} {}{scope}", i + 1, r.text);
            let _ = writeln!(
                out,
                "     {what} {} layer{}: {} elements tuned, {} added{detail}",
                r.targets.len(),
                if r.targets.len() == 1 { "" } else { "s" },
                thousands(tuned),
                thousands(added)
            );
            let names: Vec<String> = r
                .targets
                .iter()
                .map(|t| {
                    let path = g.node(t.node).path.clone();
                    let all = g.node(t.node).params.len() == t.slots.len();
                    if t.slots.is_empty() || all { path } else { format!("{path}.{{{}}}", t.slots.join(",")) }
                })
                .collect();
            wrap(&mut out, "       ", &names, 100);
        }
        if !plan.is_scoped() {
            let _ = writeln!(
                out,
                "  per variant: {} existing elements tuned, {} added",
                thousands(plan.tuned_elements(g)),
                thousands(plan.added_elements())
            );
        } else {
            for line in super::params::scope_lines(module) {
                let _ = writeln!(out, "  {line}");
            }
            for (units, tuned, added) in super::params::variant_groups(module) {
                let _ = writeln!(
                    out,
                    "  per variant {units}: {} existing elements tuned, {} added",
                    thousands(tuned),
                    thousands(added)
                );
            }
        }
    }
    if let Some(v) = &module.variants {
        let _ = writeln!(out, "variants");
        for a in &v.axes {
            let levels: Vec<String> = a.levels.iter().map(|l| fmt_level(*l)).collect();
            let clear = a.clear.map(|c| format!(" clear {}", fmt_level(c))).unwrap_or_default();
            let _ = writeln!(out, "  axis {} on {}: {}{clear}", a.name, a.modality, levels.join(", "));
        }
        for (m, p) in &v.missing {
            let p = match p {
                MissingPolicy::ZeroFill => "zero_fill",
                MissingPolicy::Variant => "variant",
            };
            let _ = writeln!(out, "  missing {m}: {p}");
        }
        for s in &v.selectors {
            let src = match &s.source {
                KeySource::Meta(k) => format!("meta(\"{k}\")"),
                KeySource::Stat { stat, input } => format!("{}({input})", stat.name()),
            };
            let arms: Vec<String> = s
                .arms
                .iter()
                .map(|arm| {
                    let l = arm.level.map(fmt_level).unwrap_or_else(|| "clear".into());
                    match arm.below {
                        Some((t, incl)) => format!("{} {} -> {l}", if incl { "<=" } else { "<" }, fmt_level(t)),
                        None => format!("else -> {l}"),
                    }
                })
                .collect();
            let map = if arms.is_empty() { "nearest".to_string() } else { arms.join(", ") };
            let _ = writeln!(out, "  select {} by {src}: {map}", s.axis);
        }
        if let Some(meld) = &v.meld {
            let w: Vec<String> = meld.weights.iter().map(|(m, l)| format!("{m} = {l}")).collect();
            let _ = writeln!(out, "  meld {}", w.join(", "));
        }
        let keys = v.keys();
        let _ = writeln!(out, "  {} variants:", keys.len());
        let keys: Vec<String> = keys.iter().map(|k| k.to_string()).collect();
        wrap(&mut out, "    ", &keys, 100);
    }
    out
}

/// ` {a, b}`: the variants whose value of tensor `name` differs from the base's (all of
/// them listed up to four, else their count), or nothing.
fn varies(table: &TensorTable, name: &str) -> String {
    let Some(t) = table.get(name) else { return String::new() };
    let keys: Vec<String> = t
        .variants
        .iter()
        .zip(&table.variants)
        .filter(|(v, _)| v.is_some())
        .map(|(_, info)| info.key.to_string())
        .collect();
    match keys.len() {
        0 => String::new(),
        1..=4 => format!(" {{{}}}", keys.join(", ")),
        n => format!(" {{{n} variants}}"),
    }
}

/// Writes words separated by spaces, wrapped at `width` columns.
fn wrap(out: &mut String, indent: &str, words: &[String], width: usize) {
    let mut line = String::from(indent);
    for w in words {
        if line.len() > indent.len() && line.len() + 1 + w.len() > width {
            let _ = writeln!(out, "{line}");
            line = String::from(indent);
        }
        if line.len() > indent.len() {
            line.push(' ');
        }
        line.push_str(w);
    }
    if line.len() > indent.len() {
        let _ = writeln!(out, "{line}");
    }
}

/// The graph alone as text (no side tables).
pub fn graph_to_text(g: &Graph) -> String {
    to_text(&Module::new(g.clone()))
}
