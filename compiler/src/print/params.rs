//! The parameter table of `readi params`: name, shape, count, total.

use std::fmt::Write;

use super::{bytes, thousands};
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
        let tuned = plan.tuned_elements(g);
        let added = plan.added_elements();
        let pct = |n: u64| if params == 0 { 0.0 } else { 100.0 * n as f64 / params as f64 };
        let _ = writeln!(
            out,
            "per variant: {} existing elements tuned ({:.2}% of parameters), {} added ({:.2}%)",
            thousands(tuned),
            pct(tuned),
            thousands(added),
            pct(added)
        );
    }
    out
}
