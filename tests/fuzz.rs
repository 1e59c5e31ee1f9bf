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
    include_str!("../models/resnet18.readi"),
    include_str!("../models/vit_encoder.readi"),
    include_str!("../models/pointpillars_bev.readi"),
    include_str!("../models/bevfusion_tiny.readi"),
    include_str!("cases/ok/all_ops.readi"),
    include_str!("cases/ok/adapt_and_variants.readi"),
    include_str!("cases/ok/conditionals.readi"),
    include_str!("cases/ok/arithmetic.readi"),
];

/// Seeds small enough to compile and run per case (the bundled models take seconds).
const SMALL_SEEDS: &[&str] = &[
    include_str!("cases/ok/all_ops.readi"),
    include_str!("cases/ok/adapt_and_variants.readi"),
    include_str!("cases/ok/arithmetic.readi"),
    include_str!("cases/ok/conditionals.readi"),
    include_str!("cases/ok/lists_and_comprehensions.readi"),
    include_str!("cases/ok/namespaces_and_members.readi"),
    include_str!("cases/ok/seq_for_and_names.readi"),
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
    "camera",
    "lidar",
    "é",
    "\t",
];

fn cases() -> u32 {
    std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(192)
}

/// `PROPTEST_CASES` cases (default 192). Failures are persisted as proptest does by
/// default, next to this file (`tests/fuzz.proptest-regressions`, replayed first on the
/// next run; commit it with the fix). The default `SourceParallel` looks for a `lib.rs`
/// or `main.rs` above `tests/`, finds none and falls back to exactly this, with a warning.
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

#[derive(Clone, Debug)]
enum Edit {
    Delete {
        at: usize,
        len: usize,
    },
    Insert {
        at: usize,
        token: &'static str,
    },
    DuplicateLine {
        line: usize,
    },
    SwapLines {
        a: usize,
        b: usize,
    },
    ReplaceNumber {
        nth: usize,
        with: &'static str,
    },
    /// The `nth` word of [`WORDS`] becomes the `pick`-th word of its group.
    ReplaceWord {
        nth: usize,
        pick: usize,
    },
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), 1usize..40).prop_map(|(at, len)| Edit::Delete { at, len }),
        (any::<usize>(), prop::sample::select(TOKENS)).prop_map(|(at, token)| Edit::Insert { at, token }),
        any::<usize>().prop_map(|line| Edit::DuplicateLine { line }),
        (any::<usize>(), any::<usize>()).prop_map(|(a, b)| Edit::SwapLines { a, b }),
        (any::<usize>(), prop::sample::select(TOKENS)).prop_map(|(nth, with)| Edit::ReplaceNumber { nth, with }),
        (any::<usize>(), any::<usize>()).prop_map(|(nth, pick)| Edit::ReplaceWord { nth, pick }),
    ]
}

/// Sizes and factors an edit may put in place of a number and still often have a spec
/// that checks.
const NUMBERS: &[&str] = &["0", "1", "2", "3", "4", "5", "8", "16", "0.5", "2.0"];

/// Words an edit may swap for another of their group: ops that take and give the same
/// kinds of tensors, arguments that take the same values.
const WORDS: &[&[&str]] = &[
    &["relu", "sigmoid", "tanh", "silu", "gelu"],
    &["maxpool", "avgpool"],
    &["batchnorm", "layernorm"],
    &["stride", "padding", "dilation"],
    &["true", "false"],
    &["x", "y"],
];

/// Edits that keep the text a spec, and often one that checks: for the back end, which
/// sees only the specs that check.
fn mild_edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        3 => (any::<usize>(), prop::sample::select(NUMBERS)).prop_map(|(nth, with)| Edit::ReplaceNumber { nth, with }),
        3 => (any::<usize>(), any::<usize>()).prop_map(|(nth, pick)| Edit::ReplaceWord { nth, pick }),
        1 => (any::<usize>(), any::<usize>()).prop_map(|(a, b)| Edit::SwapLines { a, b }),
    ]
}

/// Applies an edit at char boundaries.
fn apply(src: &str, e: &Edit) -> String {
    let boundary = |at: usize| {
        let mut i = at % (src.len() + 1);
        while !src.is_char_boundary(i) {
            i -= 1;
        }
        i
    };
    match e {
        Edit::Delete { at, len } => {
            let a = boundary(*at);
            let b = boundary(a + len);
            format!("{}{}", &src[..a], &src[b.max(a)..])
        }
        Edit::Insert { at, token } => {
            let a = boundary(*at);
            format!("{} {token} {}", &src[..a], &src[a..])
        }
        Edit::DuplicateLine { line } => {
            let mut lines: Vec<&str> = src.lines().collect();
            if !lines.is_empty() {
                let i = line % lines.len();
                lines.insert(i, lines[i]);
            }
            lines.join("\n")
        }
        Edit::SwapLines { a, b } => {
            let mut lines: Vec<&str> = src.lines().collect();
            if !lines.is_empty() {
                let (i, j) = (a % lines.len(), b % lines.len());
                lines.swap(i, j);
            }
            lines.join("\n")
        }
        Edit::ReplaceNumber { nth, with } => {
            let starts: Vec<usize> = src
                .char_indices()
                .filter(|&(i, c)| c.is_ascii_digit() && !src[..i].ends_with(|p: char| p.is_alphanumeric() || p == '_'))
                .map(|(i, _)| i)
                .collect();
            if starts.is_empty() {
                return src.to_string();
            }
            let a = starts[nth % starts.len()];
            let b = src[a..].find(|c: char| !(c.is_ascii_digit() || c == '.')).map_or(src.len(), |k| a + k);
            format!("{}{with}{}", &src[..a], &src[b..])
        }
        Edit::ReplaceWord { nth, pick } => {
            let word = |c: char| c.is_ascii_alphanumeric() || c == '_';
            let mut found = Vec::new();
            let mut i = 0;
            while let Some(k) = src[i..].find(|c: char| c.is_ascii_alphabetic() || c == '_') {
                let a = i + k;
                let b = src[a..].find(|c: char| !word(c)).map_or(src.len(), |k| a + k);
                if let Some(group) = WORDS.iter().find(|g| g.contains(&&src[a..b]))
                    && !src[..a].ends_with(word)
                {
                    found.push((a, b, group[pick % group.len()]));
                }
                i = b;
            }
            match found.get(nth % found.len().max(1)) {
                Some(&(a, b, with)) => format!("{}{with}{}", &src[..a], &src[b..]),
                None => src.to_string(),
            }
        }
    }
}

// --- a generator of small well-formed models ---------------------------------------------

/// Small choices drawn from one number: `take(n)` is in `0..n`. Proptest shrinks the
/// number towards 0, which makes every choice its first option.
struct Draw(u64);

impl Draw {
    fn take(&mut self, n: u64) -> u64 {
        let v = self.0 % n;
        self.0 /= n;
        v
    }
    fn flag(&mut self) -> bool {
        self.take(2) == 1
    }
    fn range(&mut self, lo: i64, hi: i64) -> i64 {
        lo + self.take((hi - lo + 1) as u64) as i64
    }
    fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.take(xs.len() as u64) as usize]
    }
}

/// The numbers a generated model is made from; see [`generate`].
#[derive(Clone, Debug)]
struct GenSpec {
    input: u64,
    steps: Vec<u64>,
    head: u64,
    sections: u64,
}

fn gen_spec() -> impl Strategy<Value = GenSpec> {
    (any::<u64>(), prop::collection::vec(any::<u64>(), 1..10), any::<u64>(), any::<u64>())
        .prop_map(|(input, steps, head, sections)| GenSpec { input, steps, head, sections })
}

/// A 4-D value `[N, c, h, w]` of the trunk, by the name it has inside the trunk.
#[derive(Clone, Debug)]
struct Val {
    name: String,
    c: i64,
    h: i64,
    w: i64,
}

impl Val {
    /// The name outside the `trunk` namespace.
    fn outside(&self) -> String {
        if self.name.starts_with('l') { format!("trunk.{}", self.name) } else { self.name.clone() }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum LayerKind {
    Conv { fan_in: i64, out: i64, grouped: bool },
    BatchNorm,
    Linear { fan_in: i64, out: i64 },
    Parameter,
}

/// A layer with parameters, for the adaptation rules.
#[derive(Clone, Debug)]
struct Layer {
    /// The full path, `trunk.l3.0`.
    path: String,
    kind: LayerKind,
    /// Channels of its input when that is 4-D (adapter targets in the trunk).
    in_c: Option<i64>,
}

/// PyTorch's sliding-window output length, written here again so that the generator does
/// not depend on the compiler's own formula (`pooling_output_shape` with dilation; convs
/// use it without ceil mode).
fn window(len: i64, k: i64, s: i64, p: i64, d: i64, ceil: bool) -> Option<i64> {
    let num = len + 2 * p - d * (k - 1) - 1 + if ceil { s - 1 } else { 0 };
    if num < 0 {
        return None;
    }
    let mut out = num / s + 1;
    if ceil && (out - 1) * s >= len + p {
        out -= 1;
    }
    (1..=16).contains(&out).then_some(out)
}

fn pair(v: [i64; 2]) -> String {
    if v[0] == v[1] { v[0].to_string() } else { format!("[{}, {}]", v[0], v[1]) }
}

fn divisors(n: i64) -> Vec<i64> {
    (1..=n).filter(|d| n % d == 0).collect()
}

fn gcd(a: i64, b: i64) -> i64 {
    if b == 0 { a } else { gcd(b, a % b) }
}

struct Gen {
    trunk: Vec<String>,
    vals: Vec<Val>,
    layers: Vec<Layer>,
    uses_unit: bool,
}

impl Gen {
    fn cur(&self) -> Val {
        self.vals.last().cloned().expect("the input")
    }

    fn push(&mut self, name: String, rhs: String, c: i64, h: i64, w: i64) {
        self.trunk.push(format!("    {name} = {rhs}"));
        self.vals.push(Val { name, c, h, w });
    }

    fn layer(&mut self, path: String, kind: LayerKind, in_c: Option<i64>) {
        self.layers.push(Layer { path, kind, in_c });
    }

    /// An earlier value with this shape, other than `cur`.
    fn same_shape(&self, cur: &Val, d: &mut Draw, fits: impl Fn(&Val) -> bool) -> Option<Val> {
        let found: Vec<&Val> = self.vals.iter().filter(|v| v.name != cur.name && fits(v)).collect();
        (!found.is_empty()).then(|| (*d.pick(&found)).clone())
    }

    fn step(&mut self, i: usize, r: u64) {
        let mut d = Draw(r);
        let x = self.cur();
        let name = format!("l{i}");
        let (c, h, w) = (x.c, x.h, x.w);
        let xn = &x.name;
        match d.take(20) {
            0 | 13 => self.conv(&name, &x, &mut d),
            1 => {
                let eps = *d.pick(&["", ", eps=1e-3", ", eps=1e-5, momentum=0.01"]);
                self.layer(format!("trunk.{name}"), LayerKind::BatchNorm, Some(c));
                self.push(name, format!("batchnorm({xn}{eps})"), c, h, w);
            }
            2 => {
                let act = *d.pick(&["relu", "sigmoid", "tanh", "silu", "gelu"]);
                let rhs = match act {
                    "gelu" if d.flag() => format!("gelu({xn}, approximate=\"tanh\")"),
                    a => format!("{a}({xn})"),
                };
                self.push(name, rhs, c, h, w);
            }
            3 => self.pool(&name, &x, &mut d),
            4 => {
                let op = *d.pick(&["+", "-", "*"]);
                let rhs = match self.same_shape(&x, &mut d, |v| (v.c, v.h, v.w) == (c, h, w)) {
                    Some(o) => format!("{xn} {op} {}", o.name),
                    None => format!("{} {op} {xn}", *d.pick(&["relu(XX)", "sigmoid(XX)", "XX"])).replace("XX", xn),
                };
                self.push(name, rhs, c, h, w);
            }
            5 => match self.same_shape(&x, &mut d, |v| (v.h, v.w) == (h, w) && v.c + c <= 16) {
                Some(o) => {
                    let (a, b) = if d.flag() { (xn.clone(), o.name) } else { (o.name, xn.clone()) };
                    self.push(name, format!("concat([{a}, {b}], axis=1)"), c + o.c, h, w);
                }
                None if 2 * c <= 16 => self.push(name, format!("concat([{xn}, {xn}], axis=1)"), 2 * c, h, w),
                None => self.push(name, format!("relu({xn})"), c, h, w),
            },
            6 => {
                let mode = if d.flag() {
                    let align = if d.flag() { ", align_corners=true" } else { "" };
                    format!(", mode=\"bilinear\"{align}")
                } else {
                    String::new()
                };
                let (oh, ow, how) = match d.take(3) {
                    0 if 2 * h <= 16 && 2 * w <= 16 => (2 * h, 2 * w, "scale=2".to_string()),
                    1 if h >= 2 && w >= 2 => (h / 2, w / 2, "scale=0.5".to_string()),
                    _ => {
                        let (oh, ow) = (d.range(1, 16), d.range(1, 16));
                        (oh, ow, format!("size=[{oh}, {ow}]"))
                    }
                };
                self.push(name, format!("upsample({xn}, {how}{mode})"), c, oh, ow);
            }
            7 => match d.take(5) {
                0 => self.push(name, format!("permute({xn}, [0, 1, 3, 2])"), c, w, h),
                1 => self.push(name, format!("transpose({xn}, 3, 2)"), c, w, h),
                2 => self.push(name, format!("reshape({xn}, [dim({xn}, 0), {c}, {w}, {h}])"), c, w, h),
                3 if h <= 16 => self.push(name, format!("permute({xn}, [0, 2, 1, 3])"), h, c, w),
                _ => self.push(name, format!("reshape(flatten({xn}, start=1), [-1, {c}, {h}, {w}])"), c, h, w),
            },
            8 => {
                let rhs = match d.take(5) {
                    0 => format!("{xn} * 0.5 + 0.25"),
                    1 => format!("1 - {xn}"),
                    2 => format!("-{xn}"),
                    3 => format!("{xn} / 2.0"),
                    _ => format!("{xn} * {xn}"),
                };
                self.push(name, rhs, c, h, w);
            }
            9 => {
                // Not a smaller eps than the default: see `differs`.
                let args = *d.pick(&["", ", eps=1e-3", ", affine=false"]);
                self.push(name, format!("layernorm({xn}{args})"), c, h, w);
            }
            10 => {
                let axis = *d.pick(&["", ", axis=1", ", axis=2", ", axis=-1"]);
                self.push(name, format!("softmax({xn}{axis})"), c, h, w);
            }
            11 => {
                let rhs = match d.take(3) {
                    0 => format!("{xn} * sigmoid(mean({xn}, axes=[2, 3], keepdim=true))"),
                    1 => format!("{xn} + global_avgpool({xn})"),
                    _ => format!("upsample(global_avgpool({xn}), size=[{h}, {w}])"),
                };
                self.push(name, rhs, c, h, w);
            }
            15 => {
                // A learned tensor used as a value (stored in the plan, not an input).
                let (pc, ph, pw) = *d.pick(&[(c, h, w), (1, h, w), (c, 1, 1), (1, 1, 1)]);
                let p = format!("p{i}");
                self.trunk.push(format!("    {p} = parameter([1, {pc}, {ph}, {pw}])"));
                self.layer(format!("trunk.{p}"), LayerKind::Parameter, None);
                let op = *d.pick(&["+", "*"]);
                self.push(name, format!("{xn} {op} {p}"), c, h, w);
            }
            16 => {
                self.push(name, format!("matmul({xn}, transpose({xn}, 2, 3))"), c, h, h);
            }
            17 => match self.same_shape(&x, &mut d, |v| v.c == c && v.h == h && v.w + w <= 16) {
                Some(o) => self.push(name, format!("concat([{xn}, {}], axis=3)", o.name), c, h, w + o.w),
                None if 2 * h <= 16 => self.push(name, format!("concat([{xn}, {xn}], axis=-2)"), c, 2 * h, w),
                None => self.push(name, format!("{xn} / (sigmoid({xn}) + 1)"), c, h, w),
            },
            18 => {
                let k = d.range(1, 16);
                let bias = if d.flag() { "" } else { ", bias=false" };
                self.layer(format!("trunk.{name}"), LayerKind::Linear { fan_in: w, out: k }, Some(c));
                self.push(name, format!("linear({xn}, {k}{bias})"), c, h, k);
            }
            12 => {
                self.uses_unit = true;
                self.layer(
                    format!("trunk.{name}.conv"),
                    LayerKind::Conv { fan_in: c * 9, out: c, grouped: false },
                    Some(c),
                );
                self.layer(format!("trunk.{name}.bn"), LayerKind::BatchNorm, Some(c));
                self.push(name, format!("Unit({xn}, {c})"), c, h, w);
            }
            _ => {
                let out = d.range(1, 16);
                let bias = if d.flag() { "" } else { ", bias=false" };
                self.layer(format!("trunk.{name}.0"), LayerKind::Conv { fan_in: c * 9, out, grouped: false }, Some(c));
                self.layer(format!("trunk.{name}.1"), LayerKind::BatchNorm, Some(out));
                let act = *d.pick(&["relu", "silu", "sigmoid"]);
                self.trunk.push(format!(
                    "    {name} = seq({xn}) {{\n      conv2d({out}, kernel=3, padding=1{bias})\n      batchnorm\n      {act}\n    }}"
                ));
                self.vals.push(Val { name, c: out, h, w });
            }
        }
    }

    fn conv(&mut self, name: &str, x: &Val, d: &mut Draw) {
        let out = d.range(1, 16);
        let mut k = [d.range(1, 3), 0];
        k[1] = if d.flag() { k[0] } else { d.range(1, 3) };
        let mut s = [d.range(1, 2), 0];
        s[1] = if d.flag() { s[0] } else { d.range(1, 2) };
        let mut p = [d.range(0, 2), 0];
        p[1] = if d.flag() { p[0] } else { d.range(0, 2) };
        let mut dil = [if d.take(4) == 0 { 2 } else { 1 }, 1];
        dil[1] = dil[0];
        let mut o = [0; 2];
        for (a, len) in [x.h, x.w].into_iter().enumerate() {
            o[a] = match window(len, k[a], s[a], p[a], dil[a], false) {
                Some(v) => v,
                None => {
                    (k[a], s[a], p[a], dil[a]) = (1, 1, 0, 1);
                    len
                }
            };
        }
        let groups = *d.pick(&divisors(gcd(x.c, out)));
        let mut args = format!("{}, {out}, kernel={}", x.name, pair(k));
        if s != [1, 1] || d.flag() {
            args += &format!(", stride={}", pair(s));
        }
        if p != [0, 0] {
            args += &format!(", padding={}", pair(p));
        }
        if dil != [1, 1] {
            args += &format!(", dilation={}", pair(dil));
        }
        if groups > 1 {
            args += &format!(", groups={groups}");
        }
        if d.flag() {
            args += ", bias=false";
        }
        let kind = LayerKind::Conv { fan_in: x.c / groups * k[0] * k[1], out, grouped: groups > 1 };
        self.layer(format!("trunk.{name}"), kind, Some(x.c));
        self.push(name.to_string(), format!("conv2d({args})"), out, o[0], o[1]);
    }

    fn pool(&mut self, name: &str, x: &Val, d: &mut Draw) {
        let avg = d.flag();
        let k = [d.range(1, 3), d.range(1, 3)];
        let s = if d.flag() { None } else { Some([d.range(1, 3), d.range(1, 3)]) };
        let p = [d.range(0, k[0] / 2), d.range(0, k[1] / 2)];
        let ceil = d.flag();
        let stride = s.unwrap_or(k);
        let (mut oh, mut ow) =
            (window(x.h, k[0], stride[0], p[0], 1, ceil), window(x.w, k[1], stride[1], p[1], 1, ceil));
        let mut args = format!("{}, kernel={}", x.name, pair(k));
        if oh.is_none() || ow.is_none() {
            args = format!("{}, kernel=1", x.name);
            (oh, ow) = (Some(x.h), Some(x.w));
        } else {
            if let Some(s) = s {
                args += &format!(", stride={}", pair(s));
            }
            if p != [0, 0] {
                args += &format!(", padding={}", pair(p));
            }
            if ceil {
                args += ", ceil_mode=true";
            }
            if avg && d.flag() {
                args += ", count_include_pad=false";
            }
        }
        let op = if avg { "avgpool" } else { "maxpool" };
        self.push(name.to_string(), format!("{op}({args})"), x.c, oh.unwrap_or(1), ow.unwrap_or(1));
    }
}

/// A random model that should check: an input `x` (and maybe a second, `y`, of the same
/// shape), a chain of 4-D layers in namespace `trunk` whose channel counts and window
/// geometry fit (channels and spatial sizes at most 16), a head (nothing, a classifier, or
/// attention over the spatial positions), maybe an `adapt` section with rules that fit
/// the layers, and maybe a `variants` section.
fn generate(g: &GenSpec) -> String {
    generate_with(g, false)
}

/// [`generate`], with every value of the trunk also an output (`v_l3 = trunk.l3`) when
/// `all_outputs`.
fn generate_with(g: &GenSpec, all_outputs: bool) -> String {
    let mut d = Draw(g.input);
    let (c, h, w) = (d.range(1, 8), d.range(1, 16), d.range(1, 16));
    let x_optional = d.flag();
    let with_y = d.flag();
    let mut model =
        vec![format!("  input x: f32[N, {c}, {h}, {w}] @camera{}", if x_optional { " optional" } else { "" })];
    let mut st = Gen { trunk: vec![], vals: vec![Val { name: "x".into(), c, h, w }], layers: vec![], uses_unit: false };
    if with_y {
        model.push(format!("  input y: f32[N, {c}, {h}, {w}] @lidar optional"));
        st.vals.push(Val { name: "y".into(), c, h, w });
        // Steps that look for a value of `x`'s shape may pick `y`.
        st.vals.swap(0, 1);
    }
    for (i, &r) in g.steps.iter().enumerate() {
        st.step(i, r);
    }
    let last = st.cur();
    model.push("  trunk {".into());
    model.append(&mut st.trunk);
    model.push("  }".into());
    let mut outputs = vec![format!("  output features = {}", last.outside())];

    let mut d = Draw(g.head);
    match d.take(4) {
        1 => {
            let k = d.range(1, 16);
            model.push(format!("  head {{\n    pooled = flatten(global_avgpool({}), start=1)", last.outside()));
            model.push(format!("    fc = linear(pooled, {k})"));
            st.layer("head.fc".into(), LayerKind::Linear { fan_in: last.c, out: k }, None);
            if d.flag() {
                let k2 = d.range(1, 16);
                model.push(format!("    fc2 = linear(relu(fc), {k2}{})", if d.flag() { ", bias=false" } else { "" }));
                st.layer("head.fc2".into(), LayerKind::Linear { fan_in: k, out: k2 }, None);
                outputs.push("  output logits = head.fc2".into());
            } else {
                outputs.push("  output logits = head.fc".into());
            }
            model.push("  }".into());
        }
        2 => {
            let (cc, hd) = (last.c, d.range(1, 8));
            model.push(format!("  head {{\n    tokens = transpose(flatten({}, start=2), 1, 2)", last.outside()));
            model.push("    norm = layernorm(tokens)".into());
            for p in ["q", "k", "v"] {
                model.push(format!("    {p} = linear(norm, {hd})"));
                st.layer(format!("head.{p}"), LayerKind::Linear { fan_in: cc, out: hd }, None);
            }
            let scale = 1.0 / (hd as f64).sqrt();
            model.push(format!("    attn = softmax(matmul(q, transpose(k, 1, 2)) * {scale:.4}, axis=-1)"));
            model.push(format!("    proj = linear(matmul(attn, v), {cc})"));
            st.layer("head.proj".into(), LayerKind::Linear { fan_in: hd, out: cc }, None);
            model.push("    mixed = tokens + proj\n  }".into());
            outputs.push(format!("  output summary = mean(head.mixed, axes={})", d.pick(&["1", "[1, 2]", "-1"])));
        }
        3 => {
            let k = d.range(1, 16);
            model.push(format!("  head {{\n    fc = linear(flatten({}, start=1), {k})\n  }}", last.outside()));
            st.layer("head.fc".into(), LayerKind::Linear { fan_in: last.c * last.h * last.w, out: k }, None);
            outputs.push("  output logits = head.fc".into());
        }
        _ => {}
    }
    if d.take(4) == 0 {
        let v = d.pick(&st.vals).clone();
        outputs.push(format!("  output early = {}", v.outside()));
    }
    if all_outputs {
        outputs.extend(
            st.vals
                .iter()
                .filter(|v| v.name.starts_with('l'))
                .map(|v| format!("  output v_{} = {}", v.name, v.outside())),
        );
    }
    model.append(&mut outputs);

    let mut text = String::new();
    if st.uses_unit {
        text.push_str(
            "block Unit(x: tensor, planes: int) {\n  conv = conv2d(x, planes, kernel=3, padding=1, bias=false)\n  \
             bn = batchnorm(conv)\n  return relu(bn + x)\n}\n",
        );
    }
    text.push_str("model g {\n");
    text.push_str(&model.join("\n"));
    text.push_str("\n}\n");

    let mut d = Draw(g.sections);
    let rules = if d.flag() { adapt_rules(&st.layers, &mut d) } else { vec![] };
    if !rules.is_empty() {
        text.push_str(&format!("adapt {{\n  {}\n}}\n", rules.join("\n  ")));
    }
    if d.flag() {
        let mut decls =
            vec![d.pick(&["axis fog on camera: 0.1, 0.2 clear 0", "axis gamma on camera: 0.5, 2 clear 1"]).to_string()];
        if with_y && d.flag() {
            decls.push("missing lidar: variant".into());
        }
        if x_optional && d.flag() {
            decls.push("missing camera: zero_fill".into());
        }
        text.push_str(&format!("variants {{\n  {}\n}}\n", decls.join("\n  ")));
    }
    text
}

/// Rules that fit the layers: tune some, LoRA on one that is not tuned, an adapter before
/// one whose input is 4-D with a squeeze ratio that divides its channels.
fn adapt_rules(layers: &[Layer], d: &mut Draw) -> Vec<String> {
    let mut rules = Vec::new();
    let mut tuned: Vec<&str> = Vec::new();
    if d.flag() {
        if layers.iter().any(|l| l.kind == LayerKind::BatchNorm) && d.flag() {
            rules.push("tune batchnorm".to_string());
            tuned.extend(layers.iter().filter(|l| l.kind == LayerKind::BatchNorm).map(|l| l.path.as_str()));
        } else if !layers.is_empty() {
            let l = d.pick(layers);
            rules.push(format!("tune {}", l.path));
            tuned.push(&l.path);
        }
    }
    let lora: Vec<(&Layer, i64)> = layers
        .iter()
        .filter(|l| !tuned.contains(&l.path.as_str()))
        .filter_map(|l| match l.kind {
            LayerKind::Conv { fan_in, out, grouped: false } | LayerKind::Linear { fan_in, out } => {
                Some((l, fan_in.min(out)))
            }
            _ => None,
        })
        .collect();
    if !lora.is_empty() && d.flag() {
        let (l, max) = *d.pick(&lora);
        let rank = d.range(1, max.min(4));
        let extra = *d.pick(&["", " alpha=4", " alpha=2 rslora"]);
        rules.push(format!("lora rank={rank}{extra} on {}", l.path));
    }
    let adapters: Vec<(&Layer, i64)> = layers.iter().filter_map(|l| Some((l, l.in_c?))).collect();
    if !adapters.is_empty() && d.flag() {
        let (l, c) = *d.pick(&adapters);
        let squeeze = *d.pick(&divisors(c));
        let act = *d.pick(&["relu", "gelu", "sigmoid"]);
        let rel = l.path.strip_prefix("trunk.").unwrap_or(&l.path);
        rules.push(format!("adapter squeeze={squeeze} act={act} in trunk before {rel}"));
    }
    rules
}

// --- driving the back end -------------------------------------------------------------------

/// The inputs of a run: name, shape, data.
type Data = Vec<(String, Vec<usize>, Vec<f32>)>;

/// Seeded finite inputs in [-1, 1) for every input of the plan, at batch size 1, a
/// function of the seed and each input's name.
fn seeded_inputs(plan: &Plan, seed: u64) -> Data {
    plan.manifest
        .input_shapes(1)
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let data = (0..n as u64).map(|k| unit(seed ^ fnv1a64(name) ^ k)).collect();
            (name.to_string(), shape, data)
        })
        .collect()
}

/// FNV-1a: inputs are seeded by name, so that an input gets the same values in every
/// plan that has it.
fn fnv1a64(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// SplitMix64 of `x`, as a float uniform in [-1, 1).
fn unit(x: u64) -> f32 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    ((z >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
}

/// Runs under variant `key`, with the inputs not in `absent`.
fn run_as(s: &mut Session, key: &str, data: &Data, absent: Option<usize>, src: &str) -> Vec<(String, Tensor)> {
    s.set_variant(key).unwrap_or_else(|e| panic!("variant `{key}` of the plan: {e}\n--- source ---\n{src}"));
    let given: Vec<Input<'_>> = data
        .iter()
        .enumerate()
        .filter(|(i, _)| Some(*i) != absent)
        .map(|(_, (name, shape, data))| Input { name, data, shape })
        .collect();
    s.run(&given).unwrap_or_else(|e| {
        panic!("a compiled plan fails to run (variant `{key}`, {} threads): {e}\n--- source ---\n{src}", s.threads())
    })
}

fn bits(outs: &[(String, Tensor)]) -> Vec<(&str, &[usize], Vec<u32>)> {
    outs.iter().map(|(n, t)| (n.as_str(), &t.shape[..], t.data.iter().map(|v| v.to_bits()).collect())).collect()
}

fn assert_bit_identical(a: &[(String, Tensor)], b: &[(String, Tensor)], what: &str, src: &str) {
    if bits(a) != bits(b) {
        let names: Vec<&str> = a.iter().zip(b).filter(|(x, y)| x != y).map(|(x, _)| x.0.as_str()).collect();
        panic!("{what}: outputs {names:?} are not bit-identical\n--- source ---\n{src}");
    }
}

/// Why two computations of one value differ by more than rounding, if they do: the
/// largest difference must be at most `1e-4 * max(m, 1)`, where `m` is the value's
/// largest magnitude.
///
/// Relative to `m` for values of magnitude 1 or more; absolute below, because rounding
/// noise can make up a small value. A `layernorm` over a row whose values are equal up to
/// rounding (after `upsample` from width 1, say) divides the noise by `sqrt(eps)`,
/// amplifying a 1-ulp difference in its input ~316 times, and its output is then only its
/// bias plus that noise: a 2e-5 difference on an output of magnitude 0.1 is rounding
/// there. A wrong result (a lost partial sum, a misplaced tile) differs by about the
/// values themselves.
fn differs(x: &[f32], y: &[f32]) -> Option<String> {
    let scale = x.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let err = x.iter().zip(y).fold(0.0f32, |m, (p, q)| m.max((p - q).abs()));
    (err > 1e-4 * scale.max(1.0)).then(|| format!("differs by {err:e} (largest magnitude {scale:e})"))
}

/// The same outputs, equal up to rounding ([`differs`]): thread counts change the order
/// of floating-point sums, nothing else.
fn assert_close(a: &[(String, Tensor)], b: &[(String, Tensor)], what: &str, src: &str) {
    assert_eq!(a.len(), b.len(), "{what}: output count\n--- source ---\n{src}");
    for ((name, x), (_, y)) in a.iter().zip(b) {
        assert_eq!(x.shape, y.shape, "{what}: shape of `{name}`\n--- source ---\n{src}");
        if let Some(why) = differs(&x.data, &y.data) {
            panic!("{what}: `{name}` {why}\n--- source ---\n{src}");
        }
    }
}

fn finite(outs: &[(String, Tensor)]) -> bool {
    outs.iter().all(|(_, t)| t.data.iter().all(|v| v.is_finite()))
}

/// A plan written with `to_bytes`, stored in a temporary file and loaded (memory-mapped).
fn reload(plan: &Plan, src: &str) -> Plan {
    static COUNT: AtomicUsize = AtomicUsize::new(0);
    let bytes = plan.to_bytes().unwrap_or_else(|e| panic!("serialise: {e}\n--- source ---\n{src}"));
    let n = COUNT.fetch_add(1, Ordering::Relaxed);
    let path = std::env::temp_dir().join(format!("readi-fuzz-{}-{n}.plan", std::process::id()));
    std::fs::write(&path, bytes).expect("write the plan");
    let loaded = Plan::load(&path);
    // The mapping outlives the file's name.
    let _ = std::fs::remove_file(&path);
    loaded.unwrap_or_else(|e| panic!("a written plan does not load: {e}\n--- source ---\n{src}"))
}

/// Checks and compiles a spec with seeded weights, and seeded parameters for up to three
/// of its variants when it has an `adapt` section (without one, variant files are a user
/// error). Fails on an internal error or a panic; a user error, or a spec too large to run
/// in a few milliseconds, is `Err` with the reason and the rendered diagnostics.
fn compile_spec(src: &str, seed: u64) -> Result<Plan, String> {
    let (sources, out) = exercise(src);
    let context =
        |why: &str, d: &Diagnostics| format!("{why}:\n{}\n--- source ---\n{src}", sources.render_all(d, false));
    if out.diagnostics.has_errors() {
        return Err(context("does not check", &out.diagnostics));
    }
    let module: Module = out.module.expect("a module without errors");
    let params: u64 = module.graph.param_table().iter().map(|(_, _, s)| s.numel()).sum();
    if params > MAX_ELEMENTS {
        return Err(format!("has {params} parameters"));
    }
    let weights = backend::seeded_weights(&module.graph, seed);
    let keys = if module.adapt.is_some() { variant_keys(&module, 3) } else { vec![] };
    let variants = backend::seeded_variants(&module, &keys, seed + 1);
    let plan = match backend::compile_variants(&module, &weights, "seeded", &variants, &CompileOptions::default()) {
        Ok((plan, warnings)) => {
            assert_no_ice(&warnings, &sources, "the back end", src);
            plan
        }
        Err(diags) => {
            assert_no_ice(&diags, &sources, "the back end", src);
            return Err(context("does not compile", &diags));
        }
    };
    let b = plan.manifest.batch_bindings(1);
    let elements: u64 = plan
        .manifest
        .values
        .iter()
        .map(|v| v.shape.iter().map(|d| d.eval(&b).unwrap_or(1) as u64).product::<u64>())
        .sum();
    if elements > MAX_ELEMENTS {
        return Err(format!("has {elements} activation elements"));
    }
    Ok(plan)
}

/// What [`drive_backend`] did with a case.
#[derive(Debug, PartialEq)]
enum Outcome {
    Ran,
    Skipped(&'static str),
}

/// Most parameters and activation elements a case may have, so that an edit that makes a
/// layer wide (`conv2d(x, 1616, ...)`) does not make a case take seconds.
const MAX_ELEMENTS: u64 = 1 << 20;

/// Compiles a spec with seeded weights (and seeded parameters for up to three of its
/// variants), and runs the plan on seeded inputs on every path, for the base and every
/// variant:
///
/// * in memory on 1 thread, and written, reloaded and run on 1 thread: bit-identical;
/// * the same on 2 threads: bit-identical; 1, 2 and 3 threads agree within
///   [`assert_close`];
/// * a second run of a session reproduces its first bit for bit (buffers are reused), and
///   switching back to the base after every variant reproduces the first base run;
/// * an absent `optional` input is the same as zeros;
/// * every output is finite.
///
/// `strict` (generated models): the spec must check and compile. Otherwise a spec with
/// user errors, from the front end or the back end, is skipped. An internal error, a
/// panic, or a compiled plan that fails to load or run fails in both cases.
fn drive_backend(src: &str, strict: bool, seed: u64) -> Outcome {
    let plan = match compile_spec(src, seed) {
        Ok(plan) => plan,
        Err(why) => {
            assert!(!strict, "a generated model {why}");
            return Outcome::Skipped("user error");
        }
    };
    let data = seeded_inputs(&plan, seed);
    let keys: Vec<String> = plan.variant_keys().map(str::to_string).collect();
    let mem = Arc::new(plan);
    let loaded = Arc::new(reload(&mem, src));
    let session = |p: &Arc<Plan>, threads| {
        Session::new(Arc::clone(p), threads).unwrap_or_else(|e| panic!("session: {e}\n--- source ---\n{src}"))
    };
    let (mut mem1, mut mem2, mut load1, mut load2) =
        (session(&mem, 1), session(&mem, 2), session(&loaded, 1), session(&loaded, 2));
    // More threads than this machine may have cores, and an uneven split of the work.
    let mut mem3 = session(&mem, 3);
    let mut first_base = None;
    for key in &keys {
        let a1 = run_as(&mut mem1, key, &data, None, src);
        let b1 = run_as(&mut load1, key, &data, None, src);
        let a2 = run_as(&mut mem2, key, &data, None, src);
        let b2 = run_as(&mut load2, key, &data, None, src);
        assert_bit_identical(&a1, &b1, &format!("variant `{key}`, 1 thread: in memory vs reloaded"), src);
        assert_bit_identical(&a2, &b2, &format!("variant `{key}`, 2 threads: in memory vs reloaded"), src);
        let again = run_as(&mut mem1, key, &data, None, src);
        assert_bit_identical(&a1, &again, &format!("variant `{key}`: a second run of one session"), src);
        if !finite(&a1) || !finite(&a2) {
            // Inputs are finite and weights are seeded in PyTorch's init ranges, so a
            // non-finite output from a generated model is a bug. An edited spec can
            // overflow legitimately (`a / (a + 2.0)` in `all_ops` with the 2.0 edited to
            // 0 divides by zero where `a` is 0): such a case says nothing about the
            // paths and is skipped, rather than comparing non-finite values loosely.
            assert!(!strict, "variant `{key}`: an output is not finite\n--- source ---\n{src}");
            return Outcome::Skipped("non-finite output");
        }
        assert_close(&a1, &a2, &format!("variant `{key}`: 1 vs 2 threads"), src);
        let a3 = run_as(&mut mem3, key, &data, None, src);
        assert_close(&a1, &a3, &format!("variant `{key}`: 1 vs 3 threads"), src);
        first_base.get_or_insert(a1);
    }
    let first_base = first_base.expect("the base variant");
    let base = &keys[0];
    let back = run_as(&mut mem1, base, &data, None, src);
    assert_bit_identical(&first_base, &back, "back to the base after every variant", src);
    for (i, spec) in mem.manifest.inputs.iter().enumerate() {
        if spec.optional {
            let absent = run_as(&mut mem1, base, &data, Some(i), src);
            let mut zeros = data.clone();
            zeros[i].2.fill(0.0);
            let given = run_as(&mut mem1, base, &zeros, None, src);
            assert_bit_identical(&absent, &given, &format!("optional input `{}` absent vs zeros", spec.name), src);
        }
    }
    Outcome::Ran
}

/// The base variant's outputs by name, on 1 thread, for seeded inputs; all finite.
fn run_base(src: &str, seed: u64) -> HashMap<String, Tensor> {
    let plan = compile_spec(src, seed).unwrap_or_else(|why| panic!("a generated model {why}"));
    let data = seeded_inputs(&plan, seed);
    let out = run_as(&mut Session::new(Arc::new(plan), 1).expect("session"), "base", &data, None, src);
    assert!(finite(&out), "an output is not finite\n--- source ---\n{src}");
    out.into_iter().collect()
}

/// Output `a` of spec `sa` and output `b` of spec `sb` are one value, computed by plans
/// that fuse differently (so round differently): equal up to rounding ([`differs`]).
fn assert_same_value(a: (&str, &HashMap<String, Tensor>, &str), b: (&str, &HashMap<String, Tensor>, &str)) {
    let (x, y) = (&a.1[a.0], &b.1[b.0]);
    let srcs = format!("--- source ---\n{}\n--- and ---\n{}", a.2, b.2);
    assert_eq!(x.shape, y.shape, "the shapes of `{}` and `{}`\n{srcs}", a.0, b.0);
    if let Some(why) = differs(&x.data, &y.data) {
        panic!("`{}` and `{}`: {why}\n{srcs}", a.0, b.0);
    }
}

/// A value does not depend on what else the model computes: for a generated model,
/// * every output is the same when every trunk value is an output too (fusing a layer
///   into its consumer must not change what another consumer sees);
/// * trunk value `l<k>` is the output of the model cut after layer `k`;
/// * the base of a spec with `adapt` and `variants` sections is the spec without them
///   (LoRA branches and adapters are zero in the base, wherever they were moved);
/// * a batch of two is two batches of one (no op of the generator mixes batch items, and
///   every input and output has the batch axis first).
fn check_independence(g: &GenSpec, seed: u64) {
    let src = generate(g);
    check_batch(&src, seed);
    let full = run_base(&src, seed);
    let all_src = generate_with(g, true);
    let all = run_base(&all_src, seed);
    for name in full.keys() {
        assert_same_value((name, &full, &src), (name, &all, &all_src));
    }
    let plain_src = generate(&GenSpec { sections: 0, ..g.clone() });
    if plain_src != src {
        let plain = run_base(&plain_src, seed);
        for name in full.keys() {
            assert_same_value((name, &full, &src), (name, &plain, &plain_src));
        }
    }
    for k in 0..g.steps.len() {
        let cut_src = generate(&GenSpec { steps: g.steps[..=k].to_vec(), head: 0, sections: 0, input: g.input });
        let cut = run_base(&cut_src, seed);
        assert_same_value(("features", &cut, &cut_src), (&format!("v_l{k}"), &all, &all_src));
    }
}

/// Runs a generated model on input batches `a`, `[a, b]` and `b`, on one session (which
/// rebinds its buffers at each change of batch size): the batch of two holds the two
/// batches of one.
fn check_batch(src: &str, seed: u64) {
    let plan = compile_spec(src, seed).unwrap_or_else(|why| panic!("a generated model {why}"));
    let (a, b) = (seeded_inputs(&plan, seed), seeded_inputs(&plan, seed + 1));
    let two: Data = a
        .iter()
        .zip(&b)
        .map(|((name, shape, x), (_, _, y))| {
            let mut shape = shape.clone();
            shape[0] *= 2;
            (name.clone(), shape, [&x[..], &y[..]].concat())
        })
        .collect();
    let mut s = Session::new(Arc::new(plan), 2).expect("session");
    let one_a = run_as(&mut s, "base", &a, None, src);
    let both = run_as(&mut s, "base", &two, None, src);
    let one_b = run_as(&mut s, "base", &b, None, src);
    for (((name, x), (_, y)), (_, xy)) in one_a.iter().zip(&one_b).zip(&both) {
        let mut shape = x.shape.clone();
        shape[0] *= 2;
        assert_eq!(xy.shape, shape, "the shape of `{name}` at batch size 2\n--- source ---\n{src}");
        let (first, second) = xy.data.split_at(x.data.len());
        let halves = |d: &[f32]| vec![(name.clone(), Tensor { shape: x.shape.clone(), data: d.to_vec() })];
        let what = format!("`{name}`: batch of two vs one");
        assert_close(&halves(&x.data), &halves(first), &what, src);
        assert_close(&halves(&y.data), &halves(second), &what, src);
    }
}

/// The keys of the variants a spec declares, at most `n`.
fn variant_keys(m: &Module, n: usize) -> Vec<String> {
    m.variants.as_ref().map(|v| v.keys()).unwrap_or_default().iter().take(n).map(|k| k.to_string()).collect()
}

/// Compiles a bundled spec with seeded variants; runs the base and every variant on one
/// session, then the first variant and the base again: each second visit reproduces the
/// first bit for bit, and every variant differs from the base.
fn check_switching(rel: &str, variants: usize, seed: u64) {
    let src = std::fs::read_to_string(common::root().join(rel)).expect("read the spec");
    let (sources, out) = common::compile_text(rel, &src, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = variant_keys(&m, variants);
    assert_eq!(keys.len(), variants, "{rel} declares enough variants");
    let sources_v = backend::seeded_variants(&m, &keys, seed + 1);
    let weights = backend::seeded_weights(&m.graph, seed);
    let (plan, _) = backend::compile_variants(&m, &weights, "seeded", &sources_v, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{rel}: {}", sources.render_all(&d, false)));
    let data = seeded_inputs(&plan, seed);
    let mut s = Session::new(Arc::new(plan), 2).expect("session");
    let order: Vec<&str> = std::iter::once("base").chain(keys.iter().map(String::as_str)).collect();
    let first: Vec<_> = order.iter().map(|k| run_as(&mut s, k, &data, None, &src)).collect();
    for (k, out) in order.iter().zip(&first).skip(1) {
        assert_ne!(bits(out), bits(&first[0]), "{rel}: variant `{k}` equals the base");
    }
    for (k, want) in [(order[1], &first[1]), ("base", &first[0])] {
        let again = run_as(&mut s, k, &data, None, &src);
        assert_bit_identical(want, &again, &format!("{rel}: switching back to `{k}`"), &src);
    }
}

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
