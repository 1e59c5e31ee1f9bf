//! The parameter table of `readi params`: name, shape, count, total, and what a variant
//! owns (per scope when the `adapt` sections are scoped).

use std::fmt::Write;

use super::{bytes, thousands};
use readi_plan::VariantKey;
use readi_plan::conditions::MissingPolicy;

use crate::adapt::Scope;
use crate::ir::SlotKind;
use crate::module::Module;

/// The table as text. Buffers (running statistics) are listed when `buffers` is set; the
/// total counts trainable parameters only, as PyTorch's `model.parameters()` does.
pub fn param_table(module: &Module, buffers: bool) -> String {
    let g = &module.graph;
    let rows: Vec<(String, String, String, &'static str)> = g
        .param_table()
        .into_iter()
        .filter(|(_, _, s)| buffers || s.kind == SlotKind::Param)
        .map(|(name, _, s)| {
            let dims: Vec<String> = s.shape.iter().map(|d| d.to_string()).collect();
            let kind = if s.kind == SlotKind::Buffer { " (buffer)" } else { "" };
            (name, format!("{}[{}]", s.dtype.as_str(), dims.join(", ")), thousands(s.numel()), kind)
        })
        .collect();
    let w0 = rows.iter().map(|r| r.0.len()).max().unwrap_or(4).max(4);
    let w1 = rows.iter().map(|r| r.1.len()).max().unwrap_or(5).max(5);
    let w2 = rows.iter().map(|r| r.2.len()).max().unwrap_or(5).max(5);
    let mut out = String::new();
    let _ = writeln!(out, "{:<w0$}  {:<w1$}  {:>w2$}", "name", "shape", "count");
    for (name, shape, count, kind) in &rows {
        let _ = writeln!(out, "{name:<w0$}  {shape:<w1$}  {count:>w2$}{kind}");
    }
    let table = g.param_table();
    let params: u64 = table.iter().filter(|(_, _, s)| s.kind == SlotKind::Param).map(|(_, _, s)| s.numel()).sum();
    let param_bytes: u64 = table
        .iter()
        .filter(|(_, _, s)| s.kind == SlotKind::Param)
        .map(|(_, _, s)| s.numel() * s.dtype.size_bytes())
        .sum();
    let buffer_count: u64 =
        table.iter().filter(|(_, _, s)| s.kind == SlotKind::Buffer).map(|(_, _, s)| s.numel()).sum();
    let tensors = table.iter().filter(|(_, _, s)| s.kind == SlotKind::Param).count();
    let _ = writeln!(
        out,
        "total: {} parameters in {tensors} tensors ({} as f32); {} buffer elements",
        thousands(params),
        bytes(param_bytes),
        thousands(buffer_count)
    );
    if let Some(plan) = &module.adapt {
        let pct = |n: u64| if params == 0 { 0.0 } else { 100.0 * n as f64 / params as f64 };
        if !plan.is_scoped() {
            let tuned = plan.tuned_elements(g);
            let added = plan.added_elements();
            let _ = writeln!(
                out,
                "per variant: {} existing elements tuned ({:.2}% of parameters), {} added ({:.2}%)",
                thousands(tuned),
                pct(tuned),
                thousands(added),
                pct(added)
            );
        } else {
            let _ = writeln!(out, "per scope (what its rules make per-variant):");
            for s in scope_lines(module) {
                let _ = writeln!(out, "  {s}");
            }
            let _ = writeln!(out, "per variant (its scopes and the unscoped rules together):");
            for (units, tuned, added) in variant_groups(module) {
                let _ = writeln!(
                    out,
                    "  {units}: {} existing elements tuned ({:.2}% of parameters), {} added ({:.2}%)",
                    thousands(tuned),
                    pct(tuned),
                    thousands(added),
                    pct(added)
                );
            }
        }
    }
    out
}

/// The variants a unit of the variants section stands for: `gamma=*` (every level of an
/// axis) or `missing=lidar`, with a key of it.
fn units(module: &Module) -> Vec<(String, VariantKey)> {
    let Some(v) = &module.variants else { return Vec::new() };
    let mut out: Vec<(String, VariantKey)> = Vec::new();
    for a in &v.axes {
        if let Some(&l) = a.levels.first() {
            out.push((format!("{}=*", a.name), VariantKey::level(&a.name, l)));
        }
    }
    for (m, p) in &v.missing {
        if *p == MissingPolicy::Variant {
            let k = VariantKey::missing(m);
            out.push((k.to_string(), k));
        }
    }
    out
}

/// One line per scope of the adaptation rules: `scope camera (variants gamma=*, blur=*):
/// 120,000 tuned, 4,096 added`, the unscoped rules first (`every variant`). Each
/// parameter counted once per scope.
pub fn scope_lines(module: &Module) -> Vec<String> {
    let (g, Some(plan)) = (&module.graph, &module.adapt) else { return Vec::new() };
    let mut scopes: Vec<&Scope> = Vec::new();
    for r in &plan.rules {
        if !scopes.iter().any(|s| s.label() == r.scope.label()) {
            scopes.push(&r.scope);
        }
    }
    scopes.sort_by_key(|s| !s.is_all());
    let units = units(module);
    scopes
        .iter()
        .map(|scope| {
            let same = |s: &Scope| s.label() == scope.label();
            let (tuned, added) = (plan.tuned_elements_where(g, same), plan.added_elements_where(same));
            let covered: Vec<&str> = units.iter().filter(|(_, k)| scope.covers(k)).map(|(u, _)| u.as_str()).collect();
            let who = match covered.as_slice() {
                [] => "no declared variant".to_string(),
                [one] if !one.ends_with('*') => format!("variant {one}"),
                many => format!("variants {}", many.join(", ")),
            };
            let name = if scope.is_all() { "unscoped".to_string() } else { format!("scope {}", scope.label()) };
            format!("{name} ({who}): {} tuned, {} added", thousands(tuned), thousands(added))
        })
        .collect()
}

/// The declared variants grouped by what they own (`gamma=*, blur=*`), with each group's
/// budget: existing elements tuned and elements added, each parameter once.
pub fn variant_groups(module: &Module) -> Vec<(String, u64, u64)> {
    let (g, Some(plan)) = (&module.graph, &module.adapt) else { return Vec::new() };
    let mut groups: Vec<(Vec<String>, Vec<&str>, VariantKey)> = Vec::new();
    let units = units(module);
    for (u, k) in &units {
        let mut own: Vec<String> = plan.rules.iter().filter(|r| r.scope.covers(k)).map(|r| r.scope.label()).collect();
        own.sort();
        own.dedup();
        match groups.iter_mut().find(|(o, _, _)| *o == own) {
            Some(group) => group.1.push(u),
            None => groups.push((own, vec![u], k.clone())),
        }
    }
    groups
        .into_iter()
        .map(|(_, units, key)| {
            let (tuned, added) = plan.budget(g, &key);
            (units.join(", "), tuned, added)
        })
        .collect()
}
