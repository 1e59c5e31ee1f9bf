//! `prune below=T [in SEL]`: the pass zeroes exactly the shared weights' values below the
//! threshold (against a naive count), leaves owned, added and non-weight tensors alone,
//! scopes by its selector, and `prune_summary` reports the counts and how far the outputs
//! move.

mod common;

use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, VariantSource, WeightSet};
use readi_compiler::passes::{self, BackendInputs, Pass};
use readi_compiler::weights::tensors::TensorTable;

const MODEL: &str = "model m {
  input x: f32[N, 4, 8, 8] @lidar
  c1 = conv2d(x, 8, kernel=3, padding=1)
  bn = batchnorm(c1)
  c2 = conv2d(relu(bn), 8, kernel=1, bias=false)
  pool = global_avgpool(relu(c2))
  head {
    fc = linear(flatten(pool, start=1), 3)
  }
  out = linear(head.fc, 2)
  output y = out
}
variants {
  axis fog on lidar: 0.03 clear 0
}
";

fn module(adapt: &str) -> Module {
    let text = format!("{MODEL}adapt {{\n{adapt}\n}}\n");
    let (sources, out) = common::compile_text("m.readi", &text, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

fn errors(adapt: &str) -> String {
    let text = format!("{MODEL}adapt {{\n{adapt}\n}}\n");
    let (sources, out) = common::compile_text("m.readi", &text, &[], None);
    assert!(out.diagnostics.has_errors(), "expected errors for `{adapt}`");
    sources.render_all(&out.diagnostics, false)
}

struct Setup {
    base: WeightSet,
    variants: Vec<VariantSource>,
    opts: CompileOptions,
}

fn setup(m: &Module) -> Setup {
    Setup {
        base: backend::seeded_weights(&m.graph, 3),
        variants: backend::seeded_variants(m, &["fog=0.03".to_string()], 9),
        opts: CompileOptions::default(),
    }
}

/// The table after `stop` (and the warnings).
fn table_after(m: &Module, s: &Setup, stop: Pass) -> (TensorTable, String) {
    let inputs = BackendInputs { base: &s.base, base_name: "seeded", variants: &s.variants, opts: &s.opts };
    let mut m = m.clone();
    let run = passes::run_backend(&mut m, &inputs, Some(stop)).expect("compiles");
    let w: Vec<String> = run.warnings.iter().map(|d| d.message.clone()).collect();
    (m.tensors.expect("table"), w.join("\n"))
}

/// Checks that after `prune` exactly the `pruned` tensors lost their values below `t`
/// (naively: `|x| < t` in f64) and every other tensor is bit for bit as before; returns
/// the number of values zeroed.
fn check_pruned(m: &Module, pruned: &[&str], t: f64) -> u64 {
    let s = setup(m);
    let (before, _) = table_after(m, &s, Pass::Meld);
    let (after, _) = table_after(m, &s, Pass::Prune);
    let mut zeroed = 0;
    for (name, t0) in before.iter() {
        let t1 = after.get(name).expect("still bound");
        assert_eq!(t0.variants, t1.variants, "{name}: variant values untouched");
        if pruned.contains(&name.as_str()) {
            for (i, (x, y)) in t0.base.iter().zip(t1.base.iter()).enumerate() {
                let want = if ((x.abs()) as f64) < t { 0.0 } else { *x };
                assert_eq!(y.to_bits(), want.to_bits(), "{name}[{i}]: {x} pruned at {t}");
                zeroed += u64::from(*x != 0.0 && (x.abs() as f64) < t);
            }
        } else {
            assert_eq!(t0.base, t1.base, "{name} is not pruned");
        }
    }
    let report = passes::prune::report(m, &before);
    let counted: u64 = report.iter().map(|l| l.zeroed).sum();
    assert_eq!(counted, zeroed, "the report counts what the pass zeroes");
    let names: Vec<&str> = report.iter().map(|l| l.tensor.as_str()).collect();
    let mut want: Vec<&str> = pruned.to_vec();
    want.sort_unstable();
    let mut got = names.clone();
    got.sort_unstable();
    assert_eq!(got, want, "the report lists the pruned weights");
    zeroed
}

#[test]
fn prune_zeroes_exactly_the_small_values_of_shared_weights() {
    // c2 has a LoRA (its A and B are added, never pruned; its own weight stays shared),
    // head.fc is tuned, the BatchNorm too. Seeded weights are uniform in +-1/sqrt(fan_in):
    // 0.05 prunes a good share of c1 (fan_in 36, bound 0.17) and c2 (fan_in 8, 0.35).
    let m = module("  tune batchnorm, head.*\n  lora rank=2 alpha=4 on c2\n  prune below=0.05");
    let n = check_pruned(&m, &["c1.weight", "c2.weight", "out.weight"], 0.05);
    assert!(n > 20, "something is pruned: {n}");
}

#[test]
fn a_selector_scopes_the_rule() {
    let m = module("  tune batchnorm\n  prune below=0.05 in c1, head.*");
    check_pruned(&m, &["c1.weight", "head.fc.weight"], 0.05);
    // Op kinds in scopes, and two rules on one weight: the larger threshold wins.
    let m = module("  prune below=0.02 in linear in head\n  prune below=0.1 in head.fc");
    check_pruned(&m, &["head.fc.weight"], 0.1);
}

#[test]
fn a_rule_on_owned_weights_only_warns_and_bad_selectors_are_errors() {
    let m = module("  tune head.*\n  prune below=0.05 in head.fc");
    let s = setup(&m);
    let (_, warnings) = table_after(&m, &s, Pass::Prune);
    assert!(warnings.contains("selects only weights the variants own"), "{warnings}");
    assert_eq!(warnings.matches("selects only").count(), 1, "said once: {warnings}");
    check_pruned(&m, &[], 0.05);

    let msg = errors("  prune below=0.05 in nosuch");
    assert!(msg.contains("this selector matches no layer") && msg.contains("m.readi:"), "{msg}");
    let msg = errors("  prune below=0.05 in bn");
    assert!(msg.contains("`prune` selects no conv2d or linear weight"), "{msg}");
    let msg = errors("  prune below=-1");
    assert!(msg.contains("`below` must be a positive number"), "{msg}");
    let msg = errors("  prune above=1");
    assert!(msg.contains("unknown option `above`"), "{msg}");
}

#[test]
fn the_summary_counts_and_measures_the_output_difference() {
    let summary = |adapt: &str| {
        let m = module(adapt);
        let s = setup(&m);
        let (plan, _) = backend::compile_variants(&m, &s.base, "seeded", &s.variants, &s.opts).expect("compiles");
        backend::prune_summary(&m, &s.base, "seeded", &s.variants, &s.opts, Arc::new(plan))
            .expect("runs")
            .expect("the spec prunes")
    };
    let p = summary("  tune batchnorm\n  prune below=0.05");
    let (zeroed, total) = p.totals();
    // Independent count over the seeded weights.
    let m = module("  tune batchnorm\n  prune below=0.05");
    let base = backend::seeded_weights(&m.graph, 3);
    let names = ["c1.weight", "c2.weight", "head.fc.weight", "out.weight"];
    let count = |f: &dyn Fn(f32) -> bool| -> u64 {
        names.iter().map(|n| base.tensors[*n].1.iter().filter(|x| f(**x)).count() as u64).sum()
    };
    assert_eq!(zeroed, count(&|x| x != 0.0 && (x.abs() as f64) < 0.05));
    assert_eq!(total, count(&|_| true));
    assert_eq!(p.output_difference.len(), 1);
    assert!(p.output_difference[0].1 > 0.0, "pruning moves the outputs: {:?}", p.output_difference);
    // A threshold below every value prunes nothing: the plans agree exactly.
    let p = summary("  tune batchnorm\n  prune below=1e-30");
    assert_eq!(p.totals().0, 0);
    assert_eq!(p.output_difference[0].1, 0.0);
    // No prune rule: no summary.
    let m = module("  tune batchnorm");
    let s = setup(&m);
    let (plan, _) = backend::compile_variants(&m, &s.base, "seeded", &s.variants, &s.opts).expect("compiles");
    assert!(backend::prune_summary(&m, &s.base, "seeded", &s.variants, &s.opts, Arc::new(plan)).expect("ok").is_none());
}

/// The bundled ResNet-18 with seeded weights (no trained weights are available offline):
/// prints how much the paper's 1e-3 prunes, and checks the count.
#[test]
fn resnet18_at_the_papers_threshold() {
    // The spec as bundled, plus the paper's rule.
    let text = std::fs::read_to_string(common::root().join("models/resnet18.readi")).expect("read");
    let text = text.replacen("adapt {", "adapt {\n  prune below=1e-3", 1);
    let (sources, out) = common::compile_text("resnet18.readi", &text, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let base = backend::seeded_weights(&m.graph, 1);
    let inputs = BackendInputs { base: &base, base_name: "seeded", variants: &[], opts: &CompileOptions::default() };
    let mut melded = m.clone();
    passes::run_backend(&mut melded, &inputs, Some(Pass::Meld)).expect("binds");
    let report = passes::prune::report(&melded, melded.tensors.as_ref().expect("table"));
    let zeroed: u64 = report.iter().map(|l| l.zeroed).sum();
    let total: u64 = report.iter().map(|l| l.total).sum();
    eprintln!(
        "resnet18, seeded weights, prune below=1e-3: {zeroed} of {total} shared weights ({:.2}%) in {} layers",
        100.0 * zeroed as f64 / total as f64,
        report.len()
    );
    // Every conv and linear weight not owned: the 20 convs, the downsample convs' LoRA
    // layer included (its weight is shared), and fc is tuned.
    assert_eq!(report.len(), 20);
    let naive: u64 = report
        .iter()
        .map(|l| base.tensors[&l.tensor].1.iter().filter(|x| (x.abs() as f64) < 1e-3 && **x != 0.0).count() as u64)
        .sum();
    assert_eq!(zeroed, naive);
}
