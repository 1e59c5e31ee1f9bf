//! A compiled plan as text: what `readi inspect` and `readi bench --profile` print, as
//! functions that return the text instead of printing it, so that other code (snapshot
//! tests, a listing of the lowered schedule) shows a plan exactly as the CLI does.
//!
//! Every function returns whole lines, each ending in `\n`; [`plan`] is `readi inspect`'s
//! output, the others its sections. The ones that need only the manifest take a
//! [`Manifest`], so they also serve a schedule that is not yet a stored plan.

use std::collections::HashSet;
use std::fmt::{self, Write};
use std::path::Path;

use readi_compiler::print;
use readi_runtime::plan::{Kernel, Manifest, Plan, Step, Storage, escaped, show_shape};

/// Runs a writer into a new string.
fn render(f: impl FnOnce(&mut String) -> fmt::Result) -> String {
    let mut out = String::new();
    // Writing to a `String` cannot fail.
    let _ = f(&mut out);
    out
}

/// `readi inspect`: the [`header`], the [`budget`] table, with `verbose` every
/// [`parameter`](params), the [`schedule`] (with `verbose`, every step) and the [`buffers`].
/// `path` is the file the plan was loaded from (and its checksum checked).
pub fn plan(plan: &Plan, path: &Path, verbose: bool) -> String {
    let m = &plan.manifest;
    let mut out = header(plan, path);
    out += &budget(plan, spec_parameters(m), verbose);
    if verbose {
        out += &params(m);
    }
    out += &schedule(m, verbose);
    out += &buffers(m);
    out += &footprint(m);
    out
}

/// The parameters the spec declares (trainable, not added by adaptation): the base model's
/// size, which the variants' budgets are shares of.
pub fn spec_parameters(m: &Manifest) -> u64 {
    // Saturating: a hand-edited plan may declare any shape.
    m.params
        .iter()
        .filter(|p| p.trainable && !p.added)
        .map(|p| p.shape.iter().fold(1u64, |a, &d| a.saturating_mul(d as u64)))
        .fold(0u64, u64::saturating_add)
}

/// The plan file, the model and its parameter values, the inputs and outputs with their
/// shapes, and the parameter count and stored bytes.
pub fn header(plan: &Plan, path: &Path) -> String {
    render(|out| {
        let m = &plan.manifest;
        let params: Vec<String> =
            m.model_params.iter().map(|(k, v)| format!("{} = {}", escaped(k), escaped(v))).collect();
        writeln!(out, "plan {} (format version {}, checksum ok)", path.display(), m.format_version)?;
        writeln!(out, "model {}({})", escaped(&m.model), params.join(", "))?;
        writeln!(out, "inputs:")?;
        for i in &m.inputs {
            let modality = i.modality.as_deref().map(|m| format!(" @{}", escaped(m))).unwrap_or_default();
            let opt = if i.optional { " optional" } else { "" };
            writeln!(out, "  {}: f32{}{modality}{opt}", escaped(&i.name), show_shape(&i.shape))?;
        }
        writeln!(out, "outputs:")?;
        for o in &m.outputs {
            let (name, shape) = (escaped(&o.name), show_shape(&m.values[o.value].shape));
            writeln!(out, "  {name}: {}{shape}", o.dtype.as_str())?;
        }
        writeln!(
            out,
            "parameters: {} in the spec; stored: {} tensors, {}",
            print::thousands(spec_parameters(m)),
            m.tensors.len(),
            print::bytes(plan.tensor_bytes() as u64)
        )
    })
}

/// Every parameter the spec declares: name, shape, how the plan stores it and, when
/// variants own it, which (`owned by every variant`, `owned by camera, missing=lidar`).
pub fn params(m: &Manifest) -> String {
    render(|out| {
        for p in &m.params {
            let owners = match &p.owned_by {
                None => String::new(),
                Some(s) if s.is_empty() => "; owned by every variant".to_string(),
                Some(s) => {
                    let names: Vec<String> = s.iter().map(|n| escaped(n).into_owned()).collect();
                    format!("; owned by {}", names.join(", "))
                }
            };
            writeln!(out, "  {:<40} {:?} {}{owners}", escaped(&p.name), p.shape, escaped(&p.stored_as))?;
        }
        Ok(())
    })
}

/// The per-variant budget table: parameters each variant owns (the paper's exist and
/// add budgets, as a share of `base_params`, the base model's parameters) and the bytes it
/// stores. With `verbose`, also each variant's replaced tensors. Empty without variants.
pub fn budget(plan: &Plan, base_params: u64, verbose: bool) -> String {
    render(|out| {
        let m = &plan.manifest;
        if m.variants.is_empty() {
            return Ok(());
        }
        let replacement: HashSet<usize> = m.variants.iter().flat_map(|v| v.replaces.iter().map(|r| r.with)).collect();
        let bytes_of = |t: usize| m.tensors[t].numel() as u64 * 4;
        let base_bytes: u64 = (0..m.tensors.len()).filter(|t| !replacement.contains(t)).map(bytes_of).sum();
        let pct = |a: u64, b: u64| 100.0 * a as f64 / b.max(1) as f64;
        writeln!(
            out,
            "variants: {} (base {} stored once; the variants add {}, shared tensors stored once)",
            m.variants.len(),
            print::bytes(base_bytes),
            print::bytes(plan.tensor_bytes() as u64 - base_bytes)
        )?;
        let width = m.variants.iter().map(|v| v.key.to_string().len()).max().unwrap_or(0).max(7);
        // With scoped `adapt` sections, which scopes each variant owns (`-`: only the
        // unscoped rules).
        let scoped = m.variants.iter().any(|v| !v.scopes.is_empty());
        let scope_of = |v: &readi_runtime::plan::VariantTable| {
            if !scoped {
                String::new()
            } else if v.scopes.is_empty() {
                "  -".to_string()
            } else {
                format!("  {}", v.scopes.iter().map(|s| escaped(s)).collect::<Vec<_>>().join(" + "))
            }
        };
        let sw = m.variants.iter().map(|v| scope_of(v).len()).max().unwrap_or(0).max(if scoped { 7 } else { 0 });
        writeln!(
            out,
            "  {:<width$}{:<sw$}  {:>20}  {:>20}  {:>30}",
            "variant",
            if scoped { "  scope" } else { "" },
            "exist budget (tuned)",
            "add budget (new)",
            "stored: tuned + added = % base"
        )?;
        for v in &m.variants {
            let (mut tuned, mut added) = (0u64, 0u64);
            for r in &v.replaces {
                *(if r.added { &mut added } else { &mut tuned }) += bytes_of(r.with);
            }
            let fallback =
                if v.fallback.is_empty() { String::new() } else { format!("  ({} at base value)", v.fallback.len()) };
            writeln!(
                out,
                "  {:<width$}{:<sw$}  {:>10} {:>8.2}%  {:>10} {:>8.2}%  {:>9} + {:>9} = {:>5.2}%{fallback}",
                v.key,
                scope_of(v),
                print::thousands(v.tuned_elements),
                pct(v.tuned_elements, base_params),
                print::thousands(v.added_elements),
                pct(v.added_elements, base_params),
                print::bytes(tuned),
                print::bytes(added),
                pct(tuned + added, base_bytes),
            )?;
            if verbose {
                for r in &v.replaces {
                    let shared =
                        if m.variants.iter().filter(|o| o.replaces.iter().any(|x| x.with == r.with)).count() > 1 {
                            " (shared)"
                        } else {
                            ""
                        };
                    let (base, with) = (escaped(&m.tensors[r.base].name), escaped(&m.tensors[r.with].name));
                    writeln!(out, "      {base} -> {with}{shared}")?;
                }
            }
        }
        Ok(())
    })
}

/// The schedule: its step count by kernel kind, in order of first use; with `verbose`,
/// then one line per step: index, output value, kernel (with a conv's algorithm and the
/// epilogue it fuses), input values, output shape and the spec path of the nodes it
/// computes.
pub fn schedule(m: &Manifest, verbose: bool) -> String {
    render(|out| {
        let mut kinds: Vec<(&str, usize)> = Vec::new();
        for st in &m.steps {
            match kinds.iter_mut().find(|(k, _)| *k == st.kernel.name()) {
                Some(e) => e.1 += 1,
                None => kinds.push((st.kernel.name(), 1)),
            }
        }
        let kinds: Vec<String> = kinds.iter().map(|(k, n)| format!("{n} {k}")).collect();
        writeln!(out, "schedule: {} steps ({})", m.steps.len(), kinds.join(", "))?;
        if verbose {
            for (k, st) in m.steps.iter().enumerate() {
                let ins: Vec<String> = st.inputs.iter().map(|i| format!("%{i}")).collect();
                let buffer = match m.values[st.output].storage {
                    Storage::Slot(s) if st.is_view(&m.values) => format!(" (view of buffer {s})"),
                    Storage::Slot(s) => format!(" (buffer {s})"),
                    _ => String::new(),
                };
                writeln!(
                    out,
                    "  {k:>4} %{}{buffer} = {}{}({}) {}  {}",
                    st.output,
                    st.kernel.name(),
                    kernel_detail(&st.kernel),
                    ins.join(", "),
                    show_shape(&m.values[st.output].shape),
                    escaped(&st.path)
                )?;
            }
        }
        Ok(())
    })
}

/// The variant tables: per variant, the stored tensors it replaces (by base tensor name)
/// and how many bytes it stores that the base does not share.
pub fn variant_tables(m: &Manifest) -> String {
    render(|out| {
        for v in &m.variants {
            let names: Vec<String> = v.replaces.iter().map(|r| escaped(&m.tensors[r.base].name).into_owned()).collect();
            let own: HashSet<usize> = v.replaces.iter().map(|r| r.with).collect();
            let bytes: usize = own.iter().map(|&t| m.tensors[t].numel() * 4).sum();
            writeln!(out, "variant {}: replaces {} ({})", v.key, names.join(", "), print::bytes(bytes as u64))?;
        }
        Ok(())
    })
}

/// A kernel's choices for listings, in the order it applies them: `[winograd4 scale shift
/// relu]` for a conv (its algorithm and what its epilogue applies), `[shift relu]` for a
/// linear or channel affine; nothing for other kernels. A conv that scales its input's
/// channels (its last input) starts with `channel_scale`. A fused LoRA branch shows as
/// `lora(rank=4)` (added before the epilogue), a fused residual adapter as
/// `adapter(mid=16, act=relu)` (between the shift and the activation), a residual input
/// (the step's second) as `+residual` (after those, before the activation). A conv merged on
/// switch (its variant's weight packed into a working copy when the variant changes) says
/// `switch` after its algorithm, `switch(lora_rank=4)` when the copy merges a LoRA update
/// (then there is no branch at run time).
pub fn kernel_detail(k: &Kernel) -> String {
    let Some(ep) = k.epilogue() else { return String::new() };
    let mut parts: Vec<String> = Vec::new();
    let mut switch = false;
    if let Kernel::Conv2d { algo, switch: s, channel_scale, .. } = k {
        if *channel_scale {
            parts.push("channel_scale".into());
        }
        parts.push(algo.to_string());
        switch = *s;
    }
    match (switch, k.lora()) {
        (true, Some(l)) => parts.push(format!("switch(lora_rank={})", l.rank)),
        (true, None) => parts.push("switch".into()),
        (false, Some(l)) => parts.push(format!("lora(rank={})", l.rank)),
        (false, None) => {}
    }
    for (on, name) in [(ep.scale.is_some(), "scale"), (ep.shift.is_some(), "shift")] {
        if on {
            parts.push(name.into());
        }
    }
    parts.extend(k.adapter().map(|a| format!("adapter(mid={}, act={})", a.mid, a.act.label())));
    if let Kernel::Conv2d { residual: true, .. } = k {
        parts.push("+residual".into());
    }
    parts.extend(ep.act.map(|a| a.label()));
    format!("[{}]", parts.join(" "))
}

/// The activation buffers: how many, and their bytes at batch 1 with and without the
/// planned reuse. Sizes saturate (a hand-edited plan may declare any shape; binding
/// refuses what does not fit).
pub fn buffers(m: &Manifest) -> String {
    render(|out| {
        let ones = m.batch_bindings(1);
        let mut slot_len = vec![0u64; m.slots.min(m.values.len())];
        let mut total_values = 0u64;
        for v in &m.values {
            if let Storage::Slot(s) = v.storage {
                let n = v.shape.iter().map(|d| d.eval(&ones).unwrap_or(0) as u64).fold(1u64, u64::saturating_mul);
                if let Some(len) = slot_len.get_mut(s) {
                    *len = (*len).max(n);
                }
                total_values = total_values.saturating_add(n);
            }
        }
        let planned = slot_len.iter().fold(0u64, |a, &b| a.saturating_add(b));
        writeln!(
            out,
            "buffers: {} slots, {} at batch 1 ({} without reuse)",
            m.slots,
            print::bytes(planned.saturating_mul(4)),
            print::bytes(total_values.saturating_mul(4))
        )
    })
}

/// The footprint the plan records ([`Manifest::footprint`]): what a run takes at the
/// compiled batch size on one thread. Plans written before it was recorded say so.
pub fn footprint(m: &Manifest) -> String {
    render(|out| match &m.footprint {
        Some(f) => writeln!(
            out,
            "memory at batch {}: {} per run (buffers {}, scratch {} on one thread, the rest inputs and outputs)",
            f.batch,
            print::bytes(f.total),
            print::bytes(f.activations),
            print::bytes(f.scratch)
        ),
        None => writeln!(out, "memory: not recorded in the plan (compiled before footprints were)"),
    })
}

/// The memory limit line of `readi inspect`: the footprint at batch 1 on `threads`
/// threads, computed now, against `limit`, and the largest batch size within it.
pub fn memory_limit(plan: &Plan, threads: usize, limit: usize) -> String {
    use readi_runtime::exec::{self, show_bytes};
    render(|out| {
        let fits = |batch: usize| exec::footprint(plan, batch, threads).is_ok_and(|f| f.total <= limit);
        match exec::footprint(plan, 1, threads) {
            Err(e) => writeln!(out, "memory limit {}: the plan cannot be bound: {e}", show_bytes(limit)),
            Ok(f) if f.total > limit => writeln!(
                out,
                "memory limit {}: batch 1 on {threads} threads needs {}, over the limit",
                show_bytes(limit),
                show_bytes(f.total)
            ),
            Ok(_) if m_has_no_symbols(&plan.manifest) => {
                writeln!(out, "memory limit {}: the plan fits (its shapes are fixed)", show_bytes(limit))
            }
            Ok(_) => {
                // The largest batch that fits: the footprint grows with the batch.
                let (mut lo, mut hi) = (1usize, 1usize << 40);
                while lo < hi {
                    let mid = lo + (hi - lo).div_ceil(2);
                    if fits(mid) { lo = mid } else { hi = mid - 1 }
                }
                writeln!(out, "memory limit {}: batches up to {lo} fit on {threads} threads", show_bytes(limit))
            }
        }
    })
}

fn m_has_no_symbols(m: &Manifest) -> bool {
    m.symbols.is_empty()
}

/// The steps' `seconds` summed per `key` of a step, with the number of steps: the largest
/// total first, ties in order of first appearance.
fn totals(m: &Manifest, seconds: &[f64], key: impl Fn(&Step) -> String) -> Vec<(String, f64, usize)> {
    let mut groups: Vec<(String, f64, usize)> = Vec::new();
    for (st, &t) in m.steps.iter().zip(seconds) {
        let k = key(st);
        match groups.iter_mut().find(|(g, _, _)| *g == k) {
            Some(e) => {
                e.1 += t;
                e.2 += 1;
            }
            None => groups.push((k, t, 1)),
        }
    }
    groups.sort_by(|a, b| b.1.total_cmp(&a.1));
    groups
}

/// Per-kernel-kind and per-step time from a profiled session (`seconds`, one per step,
/// summed over `runs`), as the mean per run: the kinds by total time, the layer scopes by
/// total time, then the `steps` slowest steps (every step when `steps` is 0).
pub fn profile(m: &Manifest, seconds: &[f64], runs: usize, steps: usize) -> String {
    let listed = if steps == 0 { usize::MAX } else { steps };
    render(|out| {
        let total: f64 = seconds.iter().sum();
        let ms = |s: f64| s * 1e3 / runs.max(1) as f64;
        let kinds = totals(m, seconds, |st| match &st.kernel {
            Kernel::Conv2d { algo, .. } => format!("conv2d/{algo}"),
            k => k.name().to_string(),
        });
        writeln!(out, "time per kernel kind (mean per run):")?;
        for (k, t, _) in &kinds {
            writeln!(out, "  {k:<20} {:8.3} ms  {:5.1}%", ms(*t), 100.0 * t / total.max(1e-12))?;
        }
        // Where in the network: each step under its layer path's first three segments, cut
        // before an index (`layer1.0.conv1` -> `layer1`, `encoders.camera.backbone.stages.0`
        // -> `encoders.camera.backbone`); a step of an unnamed value counts as `(unnamed)`.
        let scopes = totals(m, seconds, |st| {
            // After a space a step's path says what it absorbed (` (+relu#0)`) or how it
            // views its input (` [to N, C, L]`).
            let own = st.path.split(' ').next().unwrap_or_default();
            let segs: Vec<&str> = own
                .split('.')
                .take(3)
                .take_while(|s| !s.is_empty() && !s.starts_with(|c: char| c.is_ascii_digit()) && !s.contains('#'))
                .collect();
            if segs.is_empty() { "(unnamed)".to_string() } else { segs.join(".") }
        });
        writeln!(out, "time per layer scope (mean per run):")?;
        for (k, t, n) in &scopes {
            let k = escaped(k);
            writeln!(out, "  {k:<32} {:8.3} ms  {:5.1}%  {n} steps", ms(*t), 100.0 * t / total.max(1e-12))?;
        }
        let mut slowest: Vec<(usize, f64)> = seconds.iter().copied().enumerate().collect();
        slowest.sort_by(|a, b| b.1.total_cmp(&a.1));
        writeln!(out, "slowest steps:")?;
        for (k, t) in slowest.iter().take(listed) {
            let st = &m.steps[*k];
            writeln!(out, "  {:8.3} ms  {:<14} {}", ms(*t), st.kernel.name(), escaped(&st.path))?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use readi_compiler::backend::{self, CompileOptions};
    use readi_compiler::passes::{self, Options};
    use readi_grammar::diag::SourceMap;

    use super::*;

    const TWO_LAYERS: &str = "\
model two(hidden: int = 8) {
  input x: f32[N, 3, 8, 8] @camera
  conv = conv2d(x, hidden, kernel=3, padding=1)
  let a = relu(conv)
  pool = global_avgpool(a)
  fc = linear(flatten(pool, start=1), 4)
  output y = fc
}
";

    fn compile(text: &str) -> Plan {
        let mut sources = SourceMap::new();
        let file = sources.add("two.readi", text);
        let out = passes::run(file, text, &Options::default());
        assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
        let module = out.module.expect("a module");
        let weights = backend::seeded_weights(&module.graph, 3);
        backend::compile(&module, &weights, "seeded", &CompileOptions::default())
            .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)))
            .0
    }

    /// The listing names every step's kernel and spec path, in execution order, with the
    /// fused ReLU in the conv's path; without `verbose` only the summary line.
    #[test]
    fn schedule_lists_each_step_in_order() {
        let plan = compile(TWO_LAYERS);
        let listing = schedule(&plan.manifest, true);
        let mut lines = listing.lines();
        assert_eq!(
            lines.next(),
            Some("schedule: 4 steps (1 conv2d, 1 global_avgpool, 1 reshape, 1 linear)"),
            "{listing}"
        );
        let expected = [
            ("conv2d", "[N, 8, 8, 8]", "conv (+relu#0)"),
            ("global_avgpool", "[N, 8, 1, 1]", "pool"),
            ("reshape", "[N, 8]", "reshape#0"),
            ("linear", "[N, 4]", "fc"),
        ];
        let steps: Vec<&str> = lines.collect();
        assert_eq!(steps.len(), expected.len(), "{listing}");
        for (k, (line, (kernel, shape, path))) in steps.iter().zip(expected).enumerate() {
            // The reshape is a view of the pooled value's buffer.
            let buffer = if kernel == "reshape" { "view of buffer" } else { "buffer" };
            let head = format!("{k} %{} ({buffer} ", k + 1);
            assert!(line.trim_start().starts_with(&head), "step {k}: want `{head}`, got `{line}`");
            assert!(line.contains(&format!(" = {kernel}")), "step {k}: want kernel `{kernel}`, got `{line}`");
            assert!(line.contains(&format!("(%{k}) {shape}")), "step {k}: want `(%{k}) {shape}`, got `{line}`");
            assert!(line.ends_with(&format!("  {path}")), "step {k}: want path `{path}`, got `{line}`");
        }
        // The conv's algorithm and what its epilogue fuses.
        assert!(steps[0].contains("conv2d[im2col shift relu]"), "{listing}");
        assert!(listing.ends_with('\n'));
        assert_eq!(schedule(&plan.manifest, false), format!("{}\n", listing.lines().next().unwrap_or_default()));
    }

    /// Scopes sum their steps' times: the `conv` scope (its step absorbed a ReLU: `conv
    /// (+relu#0)`) has its one step's time and share, unnamed values count apart.
    #[test]
    fn profile_sums_steps_per_layer_scope() {
        let plan = compile(TWO_LAYERS);
        let m = &plan.manifest;
        let paths: Vec<&str> = m.steps.iter().map(|s| s.path.as_str()).collect();
        // One second for the conv's step, three for every other: the conv scope's share is
        // 1 / (1 + 3 (n - 1)).
        let conv = paths.iter().position(|p| p.starts_with("conv")).unwrap_or_else(|| panic!("{paths:?}"));
        let seconds: Vec<f64> = (0..paths.len()).map(|i| if i == conv { 1.0 } else { 3.0 }).collect();
        let text = profile(m, &seconds, 2, 12);
        let share = 100.0 / (1.0 + 3.0 * (paths.len() - 1) as f64);
        let line =
            text.lines().find(|l| l.trim_start().starts_with("conv ")).unwrap_or_else(|| panic!("{paths:?}\n{text}"));
        assert!(line.contains(&format!("{share:5.1}%")) && line.contains("500.000 ms"), "{line}\n{text}");
    }

    /// The listing takes the `steps` slowest, slowest first; 0 lists every step.
    #[test]
    fn profile_lists_as_many_steps_as_asked() {
        let plan = compile(TWO_LAYERS);
        let m = &plan.manifest;
        let n = m.steps.len();
        assert!(n >= 3, "{n} steps");
        // Step i takes i + 1 seconds: the slowest is the last.
        let seconds: Vec<f64> = (0..n).map(|i| (i + 1) as f64).collect();
        let listed = |steps: usize| -> Vec<String> {
            let text = profile(m, &seconds, 1, steps);
            let (_, tail) = text.split_once("slowest steps:\n").unwrap_or_else(|| panic!("{text}"));
            tail.lines().map(str::to_string).collect()
        };
        let two = listed(2);
        assert_eq!(two.len(), 2, "{two:?}");
        assert!(two[0].contains(&format!("{:.3} ms", n as f64 * 1e3)), "{two:?}");
        assert!(two[1].contains(&format!("{:.3} ms", (n - 1) as f64 * 1e3)), "{two:?}");
        assert_eq!(listed(0).len(), n);
        assert_eq!(listed(n + 5).len(), n);
    }
}
