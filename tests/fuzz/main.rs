//! Property tests of the whole compiler, on random, edited and generated specs.
//!
//! Inputs: random text, random token sequences, the bundled models and language cases
//! with random edits (deleted ranges, inserted tokens, duplicated and swapped lines,
//! replaced numbers and words), and random well-formed models from a small generator
//! ([`generate`]), as they are and edited.
//!
//! | property | checks |
//! |---|---|
//! | `random_text_never_panics`, `token_soup_never_panics`, `edited_models_never_panic`, `edited_generated_models_never_panic` | no panic, no internal error, every module without errors verifies ([`exercise`]) |
//! | `generated_models_check` | the front end accepts every generated model |
//! | `canonical_printing_is_a_fixed_point` | print, parse, print: the same text |
//! | `printing_preserves_meaning` | a spec and its canonical print check alike, to the same graph |
//! | `checked_specs_run_alike_on_every_path` | in memory vs reloaded, 1/2/3 threads, reruns, variant switches, absent inputs ([`drive_backend`]) |
//! | `values_do_not_depend_on_what_else_is_computed` | extra outputs, cut models, adaptation zero in the base, batches ([`check_independence`]) |
//! | `variant_switches_in_any_order_reproduce_fresh_runs`, `variant_switching_reproduces_runs_*` | switching variants on one session reproduces runs bit for bit |
//!
//! An internal compiler error (`Code::Internal`, rendered `E0999`) is a bug whatever the
//! input, so every property fails on one, from the front end or the back end. Bugs found
//! so far are in [`regressions`].
//!
//! Case counts: the front-end properties run `PROPTEST_CASES` cases each (default 192; CI
//! sets 256), the back-end ones a quarter of that ([`backend_cases`]), since each of
//! their cases compiles and runs one to a dozen plans. Failures are persisted (see
//! [`config`]) and proptest prints the minimal failing input.

#[path = "../common/mod.rs"]
mod common;

use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;
use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions};
use readi_compiler::passes::{self, Options};
use readi_compiler::print;
use readi_compiler::verify::verify;
use readi_grammar::ast_print::to_source;
use readi_grammar::diag::{Code, Diagnostics, FileId, SourceMap};
use readi_runtime::exec::{Input, Session, Tensor};
use readi_runtime::plan::Plan;

const SEEDS: &[&str] = &[
    include_str!("../../models/resnet18.readi"),
    include_str!("../../models/vit_encoder.readi"),
    include_str!("../../models/pointpillars_bev.readi"),
    include_str!("../../models/bevfusion_tiny.readi"),
    include_str!("../cases/ok/all_ops.readi"),
    include_str!("../cases/ok/adapt_and_variants.readi"),
    include_str!("../cases/ok/conditionals.readi"),
    include_str!("../cases/ok/arithmetic.readi"),
];

/// Seeds small enough to compile and run per case (the bundled models take seconds).
const SMALL_SEEDS: &[&str] = &[
    include_str!("../cases/ok/all_ops.readi"),
    include_str!("../cases/ok/adapt_and_variants.readi"),
    include_str!("../cases/ok/arithmetic.readi"),
    include_str!("../cases/ok/conditionals.readi"),
    include_str!("../cases/ok/lists_and_comprehensions.readi"),
    include_str!("../cases/ok/namespaces_and_members.readi"),
    include_str!("../cases/ok/seq_for_and_names.readi"),
];

const TOKENS: &[&str] = &[
    "model",
    "block",
    "adapt",
    "variants",
    "input",
    "output",
    "let",
    "if",
    "then",
    "else",
    "for",
    "in",
    "return",
    "seq",
    "true",
    "false",
    "and",
    "or",
    "not",
    "tune",
    "lora",
    "adapter",
    "on",
    "before",
    "axis",
    "missing",
    "select",
    "by",
    "meld",
    "clear",
    "nearest",
    "meta",
    "optional",
    "{",
    "}",
    "(",
    ")",
    "[",
    "]",
    ",",
    ".",
    "..",
    "=",
    "==",
    "!=",
    "<",
    "<=",
    "+",
    "-",
    "*",
    "**",
    "/",
    "//",
    "%",
    "->",
    "@",
    ":",
    "#",
    "\"",
    "\n",
    "0",
    "1",
    "-1",
    "3",
    "64",
    "0.5",
    "1e-5",
    "1e308",
    "99999999999999999999",
    "x",
    "N",
    "conv2d",
    "batchnorm",
    "linear",
    "relu",
    "concat",
    "reshape",
    "dim",
    "seq",
    "f32",
    "i64",
    "tensor",
    "int",
    "BasicBlock",
    "layer1",
    "head.*",
    "**",
    "**.**.**.**.**.**.**.**.**.**.x",
    "{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}{a,b}",
    "camera",
    "lidar",
    "é",
    "\t",
];

fn cases() -> u32 {
    std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(192)
}

/// `PROPTEST_CASES` cases (default 192). Failures are persisted next to the source file
/// of the property (`tests/fuzz/main.proptest-regressions`), replayed first on the next
/// run; commit it with the fix.
fn config() -> ProptestConfig {
    with_cases(cases())
}

/// A quarter of [`config`]'s cases (at least 8), for the back-end properties: a case
/// compiles one to a dozen plans and runs them several times, a few milliseconds in debug.
fn backend_cases() -> u32 {
    (cases() / 4).max(8)
}

/// Runs a back-end property as `proptest!` would (environment overrides such as
/// `PROPTEST_RNG_SEED`, failures persisted and replayed, shrinking), but with
/// [`backend_cases`] cases: the macro lets `PROPTEST_CASES` override any case count.
fn check_backend<S: Strategy>(name: &'static str, strategy: S, test: impl Fn(S::Value)) {
    let mut config = proptest::test_runner::contextualize_config(with_cases(backend_cases()));
    config.cases = backend_cases();
    config.source_file = Some(file!());
    config.test_name = Some(name);
    let mut runner = proptest::test_runner::TestRunner::new(config);
    if let Err(e) = runner.run(&strategy, |v| {
        test(v);
        Ok(())
    }) {
        panic!("{e}");
    }
}

fn with_cases(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        max_global_rejects: cases * 10,
        failure_persistence: Some(Box::new(FileFailurePersistence::WithSource("proptest-regressions"))),
        ..ProptestConfig::default()
    }
}

/// Fails on an internal compiler error among `diags`: whatever the input, one is a bug.
fn assert_no_ice(diags: &Diagnostics, sources: &SourceMap, stage: &str, src: &str) {
    if diags.iter().any(|d| d.code == Code::Internal) {
        panic!(
            "internal compiler error ({}) in {stage}:\n{}\n--- source ---\n{src}",
            Code::Internal.as_str(),
            sources.render_all(diags, false)
        );
    }
}

/// Runs everything a user can run on a source: the pipeline, the renderer for every
/// diagnostic, the printers on a module. Fails on an internal error, and on a module the
/// pipeline returns without errors that the verifier rejects (the driver verifies after
/// every pass, so this is a cheap second look). Returns the outcome.
fn exercise(src: &str) -> (SourceMap, passes::Outcome) {
    let mut sources = SourceMap::new();
    let file = sources.add("fuzz.readi", src);
    let out = passes::run(file, src, &Options::default());
    let _ = sources.render_all(&out.diagnostics, false);
    assert_no_ice(&out.diagnostics, &sources, "the front end", src);
    let _ = to_source(&out.ast);
    if let Some(m) = &out.module {
        let _ = print::to_text(m);
        let _ = print::to_dot(&m.graph);
        let _ = print::param_table(m, true);
        if !out.diagnostics.has_errors()
            && let Err(problems) = verify(m)
        {
            panic!("a module without errors fails verification: {problems:?}\n--- source ---\n{src}");
        }
    }
    (sources, out)
}

mod drive;
mod edit;
mod generate;

use drive::*;
use edit::*;
use generate::*;

/// A small seed or a generated model, with up to two mild edits.
fn small_spec() -> impl Strategy<Value = String> {
    let base = prop_oneof![
        (0..SMALL_SEEDS.len()).prop_map(|i| SMALL_SEEDS[i].to_string()),
        gen_spec().prop_map(|g| generate(&g))
    ];
    (base, prop::collection::vec(mild_edit(), 0..3))
        .prop_map(|(src, edits)| edits.iter().fold(src, |s, e| apply(&s, e)))
}

/// A spec for the back end: a generated model (`strict`), or a generated model or small
/// seed with random edits.
fn backend_case() -> impl Strategy<Value = (String, bool)> {
    prop_oneof![
        2 => gen_spec().prop_map(|g| (generate(&g), true)),
        1 => (gen_spec(), prop::collection::vec(mild_edit(), 1..4))
            .prop_map(|(g, edits)| (edits.iter().fold(generate(&g), |s, e| apply(&s, e)), false)),
        1 => (0..SMALL_SEEDS.len(), prop::collection::vec(mild_edit(), 1..4))
            .prop_map(|(i, edits)| (edits.iter().fold(SMALL_SEEDS[i].to_string(), |s, e| apply(&s, e)), false)),
    ]
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn random_text_never_panics(src in "\\PC{0,300}") {
        exercise(&src);
    }

    #[test]
    fn token_soup_never_panics(tokens in prop::collection::vec(0..TOKENS.len(), 0..120)) {
        let src: Vec<&str> = tokens.iter().map(|&t| TOKENS[t]).collect();
        exercise(&src.join(" "));
    }

    #[test]
    fn edited_models_never_panic(seed in 0..SEEDS.len(), edits in prop::collection::vec(edit(), 1..5)) {
        let src = edits.iter().fold(SEEDS[seed].to_string(), |s, e| apply(&s, e));
        exercise(&src);
    }

    #[test]
    fn edited_generated_models_never_panic(g in gen_spec(), edits in prop::collection::vec(edit(), 1..5)) {
        exercise(&edits.iter().fold(generate(&g), |s, e| apply(&s, e)));
    }

    /// The generator's models are well formed, so the front end accepts every one.
    #[test]
    fn generated_models_check(g in gen_spec()) {
        let src = generate(&g);
        let (sources, out) = exercise(&src);
        prop_assert!(
            !out.diagnostics.has_errors(),
            "{}\n--- source ---\n{}", sources.render_all(&out.diagnostics, false), src
        );
    }

    #[test]
    fn canonical_printing_is_a_fixed_point(seed in 0..SEEDS.len(), edits in prop::collection::vec(edit(), 0..3)) {
        let src = edits.iter().fold(SEEDS[seed].to_string(), |s, e| apply(&s, e));
        let first = readi_grammar::parse(FileId(0), &src);
        prop_assert!(!first.diagnostics.iter().any(|d| d.code == Code::Internal), "{:?}", first.diagnostics);
        prop_assume!(!first.diagnostics.has_errors());
        let printed = to_source(&first.file);
        let second = readi_grammar::parse(FileId(0), &printed);
        prop_assert!(!second.diagnostics.has_errors(), "printed source does not parse:\n{}", printed);
        prop_assert_eq!(to_source(&second.file), printed);
    }

    /// On the language case with variants: any sequence of variant switches, on 1 or 2
    /// threads, gives each run exactly the outputs of a fresh session of that variant.
    #[test]
    fn variant_switches_in_any_order_reproduce_fresh_runs(
        order in prop::collection::vec(0usize..4, 1..10),
        threads in 1usize..=2,
    ) {
        let (plan, data, fresh) = switching_fixture(threads);
        let keys: Vec<&str> = plan.variant_keys().collect();
        let mut s = Session::new(Arc::clone(plan), threads).expect("session");
        let src = "tests/cases/ok/adapt_and_variants.readi";
        for &i in &order {
            let k = keys[i % keys.len()];
            let out = run_as(&mut s, k, data, None, src);
            assert_bit_identical(&fresh[i % keys.len()], &out, &format!("after the switches {order:?}, `{k}`"), src);
        }
    }

    /// A file means the same after canonical printing: it checks (or not) alike, to the
    /// same graph. On the small seeds and generated models, lightly edited (the bundled
    /// models take too long to elaborate twice per case).
    #[test]
    fn printing_preserves_meaning(src in small_spec()) {
        let first = readi_grammar::parse(FileId(0), &src);
        prop_assume!(!first.diagnostics.has_errors());
        let printed = to_source(&first.file);
        let (_, a) = exercise(&src);
        let (_, b) = exercise(&printed);
        prop_assert_eq!(a.diagnostics.has_errors(), b.diagnostics.has_errors(), "printed:\n{}", printed);
        if let (false, Some(ma), Some(mb)) = (a.diagnostics.has_errors(), &a.module, &b.module) {
            prop_assert_eq!(print::to_text(ma), print::to_text(mb), "printed:\n{}", printed);
        }
    }
}

/// See [`drive_backend`].
#[test]
fn checked_specs_run_alike_on_every_path() {
    check_backend("checked_specs_run_alike_on_every_path", (backend_case(), 0u64..1000), |((src, strict), seed)| {
        drive_backend(&src, strict, seed);
    });
}

/// See [`check_independence`].
#[test]
fn values_do_not_depend_on_what_else_is_computed() {
    check_backend("values_do_not_depend_on_what_else_is_computed", (gen_spec(), 0u64..1000), |(g, seed)| {
        check_independence(&g, seed);
    });
}

type Fixture = (Arc<Plan>, Data, Vec<Vec<(String, Tensor)>>);

/// The language case with variants compiled with three seeded variants, its inputs, and
/// per variant the outputs of a fresh session on `threads` threads.
fn switching_fixture(threads: usize) -> &'static Fixture {
    static FIXTURES: [OnceLock<Fixture>; 2] = [OnceLock::new(), OnceLock::new()];
    FIXTURES[threads - 1].get_or_init(|| {
        let rel = "tests/cases/ok/adapt_and_variants.readi";
        let (sources, out) = common::compile(rel, &[], None);
        assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
        let m = out.module.expect("module");
        let variants = backend::seeded_variants(&m, &variant_keys(&m, 3), 5);
        let weights = backend::seeded_weights(&m.graph, 4);
        let plan = backend::compile_variants(&m, &weights, "seeded", &variants, &CompileOptions::default())
            .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)))
            .0;
        let plan = Arc::new(plan);
        let data = seeded_inputs(&plan, 4);
        let fresh = plan
            .variant_keys()
            .map(|k| run_as(&mut Session::new(Arc::clone(&plan), threads).expect("session"), k, &data, None, rel))
            .collect();
        (plan, data, fresh)
    })
}

#[test]
fn variant_switching_reproduces_runs_adapt_and_variants() {
    check_switching("tests/cases/ok/adapt_and_variants.readi", 4, 11);
}

#[test]
fn variant_switching_reproduces_runs_bevfusion_tiny() {
    check_switching("models/bevfusion_tiny.readi", 3, 12);
}

/// The elaborator's recursion is bounded by the parser's limits; the worst case allowed
/// must run on the 2 MiB stack of a test thread.
#[test]
fn limits_hold_on_a_small_stack() {
    let deep_expr = format!("{}1{}", "(".repeat(30), ")".repeat(30));
    let mut blocks = String::new();
    for i in 0..40 {
        blocks.push_str(&format!(
            "block B{i}(x: tensor) {{\n  let k = {deep_expr}\n  b = B{}(x)\n  return b\n}}\n",
            i + 1
        ));
    }
    blocks.push_str("block B40(x: tensor) {\n  return relu(x)\n}\n");
    let src = format!("{blocks}model m {{\n  input x: f32[N, 4]\n  b = B0(x)\n  output y = b\n}}\n");
    let handle = std::thread::Builder::new()
        .stack_size(2 << 20)
        .spawn(move || {
            let mut sources = SourceMap::new();
            let file = sources.add("deep.readi", src.as_str());
            let out = passes::run(file, &src, &Options::default());
            assert_no_ice(&out.diagnostics, &sources, "the front end", &src);
            sources.render_all(&out.diagnostics, false)
        })
        .expect("spawn");
    let rendered = handle.join().expect("no stack overflow");
    assert!(rendered.contains("nested more than"), "{rendered}");
}

/// Bugs the properties found, each reduced to a minimal spec, kept as regression tests
/// (the properties that found them still run too).
mod regressions {
    use super::exercise;

    /// An adapter before a layer whose input has a symbolic spatial axis (`H` in
    /// `f32[N, 4, H, 4]` is a symbol, as `N` is) was an internal error in `inject_adapt`
    /// (its 1x1 convs need known spatial sizes) and, with another rule injected first, a
    /// verifier failure. `resolve_adapt` now refuses the target at the rule. Found by
    /// `edited_generated_models_never_panic`, from an edit that put a word in place of an
    /// input's height.
    #[test]
    fn adapter_before_a_layer_with_a_symbolic_spatial_axis() {
        let (sources, out) = exercise(
            "model m {\n  input x: f32[N, 4, H, 4]\n  body {\n    bn = batchnorm(x)\n  }\n  output y = body.bn\n}\n\
             adapt {\n  lora rank=1 on body.bn\n  adapter in body before bn\n}\n",
        );
        let rendered = sources.render_all(&out.diagnostics, false);
        assert!(
            rendered.contains("an adapter needs an NCHW input with known channels and spatial sizes"),
            "{rendered}"
        );
    }
}
