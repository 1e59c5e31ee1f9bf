//! Hostile specs (issue 10): inputs a user could write that must give a clear error at
//! their span, in bounded time and memory, and never a panic.

mod common;

use common::compile_text;
use proptest::prelude::*;
use readi_compiler::select::Matcher;
use readi_grammar::ast::{Pattern, PatternSeg};
use readi_grammar::diag::{Diagnostic, SourceMap, Span};

/// An error and its `line:col`.
type Located = (Diagnostic, (usize, usize));

/// The errors of compiling `text`, rendered, with each error's `line:col`.
fn errors(text: &str) -> (String, Vec<Located>) {
    let (sources, out) = compile_text("hostile.readi", text, &[], None);
    let rendered = sources.render_all(&out.diagnostics, false);
    let errs = out
        .diagnostics
        .iter()
        .filter(|d| d.is_error())
        .map(|d| (d.clone(), sources.line_col(d.primary_span().expect("every error has a span"))))
        .collect();
    (rendered, errs)
}

/// `line:col` of the first occurrence of `needle` in `text` (1-based, as diagnostics print).
fn place_of(text: &str, needle: &str) -> (usize, usize) {
    let at = text.find(needle).unwrap_or_else(|| panic!("`{needle}` not in the spec"));
    let mut sources = SourceMap::new();
    let file = sources.add("x", text);
    sources.line_col(Span::new(file, at, at + needle.len()))
}

// --- selectors --------------------------------------------------------------------------

/// A 30-deep path: 30 nested blocks, the innermost holding `fc`.
fn deep_spec(selector: &str) -> String {
    let mut s = String::from("block B0(x: tensor) {\n  fc = linear(x, 4)\n  return fc\n}\n");
    for i in 1..30 {
        s += &format!("block B{i}(x: tensor) {{\n  s = B{}(x)\n  return s\n}}\n", i - 1);
    }
    s += "model m {\n  input x: f32[N, 4]\n  s = B29(x)\n  output y = s\n}\n";
    s += &format!("adapt {{\n  tune {selector}\n}}\n");
    s
}

#[test]
fn ten_double_stars_on_a_30_deep_path() {
    let stars = ["**"; 10].join(".");
    // Matches: the spec checks.
    let (rendered, errs) = errors(&deep_spec(&format!("{stars}.fc")));
    assert!(errs.is_empty(), "{rendered}");
    // As a scope of kinds, and as an exact path in a block instance.
    let (rendered, errs) = errors(&deep_spec(&format!("linear in {stars}.s")));
    assert!(errs.is_empty(), "{rendered}");
    let (rendered, errs) = errors(&deep_spec(&format!("linear in {stars}.q")));
    assert!(errs.len() == 1 && errs[0].0.message.contains("matches no layer"), "{rendered}");
    // Matches nothing: the ordinary error, at the selector, after a search of every split.
    let sel = format!("{stars}.x");
    let spec = deep_spec(&sel);
    let (rendered, errs) = errors(&spec);
    assert_eq!(errs.len(), 1, "{rendered}");
    assert!(errs[0].0.message.contains("matches no layer"), "{rendered}");
    assert_eq!(errs[0].1, place_of(&spec, &sel), "{rendered}");
}

#[test]
fn twenty_two_brace_groups() {
    let spec = |sel: &str| {
        format!(
            "model m {{\n  input x: f32[N, 4]\n  {name} = linear(x, 2)\n  output y = {name}\n}}\nadapt {{\n  tune {sel}\n}}\n",
            name = "ab".repeat(11)
        )
    };
    let groups = "{a,b}".repeat(22);
    let (rendered, errs) = errors(&spec(&groups));
    assert!(errs.is_empty(), "{rendered}");
    let near_miss = format!("{groups}c");
    let (rendered, errs) = errors(&spec(&near_miss));
    assert_eq!(errs.len(), 1, "{rendered}");
    assert!(errs[0].0.message.contains("matches no layer"), "{rendered}");
}

#[test]
fn too_complex_a_selector_is_an_error_at_its_span() {
    let sel = "{a,b}".repeat(40);
    let spec = format!(
        "model m {{\n  input x: f32[N, 4]\n  fc = linear(x, 2)\n  output y = fc\n}}\nadapt {{\n  tune fc\n  tune {sel}\n}}\n"
    );
    let (rendered, errs) = errors(&spec);
    assert_eq!(errs.len(), 1, "{rendered}");
    assert!(errs[0].0.message.contains("too complex") && errs[0].0.message.contains("80"), "{rendered}");
    assert_eq!(errs[0].1, place_of(&spec, &sel), "{rendered}");
    let long = format!("{}.fc", ["**"; 100].join("."));
    let spec = deep_spec(&long);
    let (rendered, errs) = errors(&spec);
    assert_eq!(errs.len(), 1, "{rendered}");
    assert!(errs[0].0.message.contains("characters long"), "{rendered}");
    assert_eq!(errs[0].1, place_of(&spec, &long), "{rendered}");
}

/// A direct, backtracking reading of the selector definition (exponential, small cases only).
mod naive {
    fn glob(p: &[u8], s: &[u8]) -> bool {
        match p.split_first() {
            None => s.is_empty(),
            Some((b'*', rest)) => (0..=s.len()).any(|k| glob(rest, &s[k..])),
            Some((b'{', _)) => {
                let close = p.iter().position(|&c| c == b'}').expect("closed group");
                let rest = &p[close + 1..];
                p[1..close].split(|&c| c == b',').any(|alt| glob(&[alt, rest].concat(), s))
            }
            Some((c, rest)) => s.first() == Some(c) && glob(rest, &s[1..]),
        }
    }

    pub fn matches(p: &[&str], s: &[&str]) -> bool {
        match p.split_first() {
            None => s.is_empty(),
            Some((&"**", rest)) => (0..=s.len()).any(|k| matches(rest, &s[k..])),
            Some((w, rest)) => !s.is_empty() && glob(w.as_bytes(), s[0].as_bytes()) && matches(rest, &s[1..]),
        }
    }
}

fn pattern(text: &str) -> Pattern {
    let segments = text
        .split('.')
        .map(|s| if s == "**" { PatternSeg::AnyDepth } else { PatternSeg::Word(s.to_string()) })
        .collect();
    Pattern { segments, text: text.to_string(), span: Span::default() }
}

/// A segment glob over a two-letter alphabet, with `*` and `{a,b}` groups.
fn glob_strategy() -> impl Strategy<Value = String> {
    let piece = prop_oneof![
        Just("a".to_string()),
        Just("b".to_string()),
        Just("*".to_string()),
        prop::collection::vec(prop::collection::vec(prop_oneof![Just('a'), Just('b'), Just('*')], 1..3), 1..4)
            .prop_map(|alts| format!(
                "{{{}}}",
                alts.iter().map(|a| a.iter().collect::<String>()).collect::<Vec<_>>().join(",")
            )),
    ];
    prop::collection::vec(piece, 1..4).prop_map(|p| p.concat())
}

fn pattern_strategy() -> impl Strategy<Value = String> {
    let seg = prop_oneof![1 => Just("**".to_string()), 3 => glob_strategy()];
    prop::collection::vec(seg, 1..5).prop_map(|s| s.join("."))
}

fn path_strategy() -> impl Strategy<Value = String> {
    let seg = prop::collection::vec(prop_oneof![Just('a'), Just('b')], 1..4).prop_map(|c| c.into_iter().collect());
    prop::collection::vec(seg, 1..6).prop_map(|s: Vec<String>| s.join("."))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// The compiled matcher agrees with the backtracking definition, exactly and on prefixes.
    #[test]
    fn matcher_agrees_with_backtracking(p in pattern_strategy(), path in path_strategy()) {
        let m = Matcher::new(&pattern(&p)).expect("small patterns are within the limits");
        let ps: Vec<&str> = p.split('.').collect();
        let s: Vec<&str> = path.split('.').collect();
        prop_assert_eq!(m.matches_exactly(&path), naive::matches(&ps, &s), "{} on {}", p, path);
        let prefix = (1..=s.len()).any(|k| naive::matches(&ps, &s[..k]));
        prop_assert_eq!(m.selects(&path), prefix, "{} selects {}", p, path);
    }
}

// --- derived tensors --------------------------------------------------------------------

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, VariantSource, WeightSet};

const BN_SPEC: &str = "model m {
  input x: f32[N, 4, 4, 4]
  conv1 = conv2d(x, 4, kernel=1, bias=false)
  bn1 = batchnorm(conv1)
  output y = bn1
}
";

const LORA_SPEC: &str = "model m {
  input x: f32[N, 8] @camera
  fc = linear(x, 4)
  output y = fc
}
adapt {
  lora rank=2 alpha=2 on fc
}
variants {
  axis fog on camera: 0.01, 0.02 clear 0
}
";

fn module_of(text: &str) -> Module {
    let (sources, out) = compile_text("hostile.readi", text, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    out.module.expect("module")
}

/// The back end's errors for `text` with seeded weights edited by `edit_base` and seeded
/// variants `keys` edited by `edit_variants`, each with its `line:col`.
fn backend_errors(
    text: &str,
    edit_base: impl Fn(&mut WeightSet),
    keys: &[&str],
    edit_variants: impl Fn(&mut Vec<VariantSource>),
) -> Vec<Located> {
    let m = module_of(text);
    let mut w = backend::seeded_weights(&m.graph, 7);
    edit_base(&mut w);
    let keys: Vec<String> = keys.iter().map(|k| k.to_string()).collect();
    let mut vs = backend::seeded_variants(&m, &keys, 8);
    edit_variants(&mut vs);
    let Err(diags) = backend::compile_variants(&m, &w, "base.safetensors", &vs, &CompileOptions::default()) else {
        panic!("the back end should refuse");
    };
    let mut sources = SourceMap::new();
    sources.add("hostile.readi", text);
    diags.iter().map(|d| (d.clone(), sources.line_col(d.primary_span().expect("a span")))).collect()
}

fn set(w: &mut WeightSet, name: &str, i: usize, x: f32) {
    let names: Vec<String> = w.tensors.keys().cloned().collect();
    w.tensors.get_mut(name).unwrap_or_else(|| panic!("no `{name}` in {names:?}")).1[i] = x;
}

#[test]
fn negative_running_var_is_named_as_the_cause() {
    let errs = backend_errors(BN_SPEC, |w| set(w, "bn1.running_var", 3, -1.0), &[], |_| {});
    assert_eq!(errs.len(), 1, "{errs:?}");
    let m = &errs[0].0.message;
    assert!(m.contains("bn1.running_var[3] = -1 is negative"), "{m}");
    assert!(m.contains("BatchNorm `bn1` cannot be folded"), "{m}");
    assert!(!m.contains("internal"), "{m}");
    assert_eq!(errs[0].1, place_of(BN_SPEC, "batchnorm(conv1)"), "{m}");
}

#[test]
fn overflowing_fold_names_the_derived_tensor_and_its_sources() {
    // A finite but huge gamma over a zero variance: the folded scale overflows f32.
    let edit = |w: &mut WeightSet| {
        set(w, "bn1.weight", 2, 3e38);
        set(w, "bn1.running_var", 2, 0.0);
    };
    let errs = backend_errors(BN_SPEC, edit, &[], |_| {});
    assert_eq!(errs.len(), 2, "the scale and the shift: {errs:?}");
    assert!(errs[1].0.message.contains("derived tensor `bn1@shift` is -inf"), "{errs:?}");
    assert_eq!(errs[0].1, place_of(BN_SPEC, "batchnorm(conv1)"), "{errs:?}");
    let m = &errs[0].0.message;
    assert!(m.contains("derived tensor `bn1@scale` is inf at flat index 2"), "{m}");
    assert!(m.contains("overflows f32") && m.contains("`bn1.weight[2]` = 3e38"), "{m}");
    assert!(m.contains("`bn1.weight`, `bn1.running_var`"), "{m}");
}

#[test]
fn overflowing_lora_merge_names_the_lora_tensors() {
    let errs = backend_errors(
        LORA_SPEC,
        |_| {},
        &["fog=0.01"],
        |vs| {
            for (name, (_, data)) in vs[0].weights.tensors.iter_mut() {
                if name.contains("lora_") {
                    data.fill(1e30);
                }
            }
        },
    );
    assert_eq!(errs.len(), 1, "{errs:?}");
    let m = &errs[0].0.message;
    assert!(m.contains("derived tensor `fc.weight` in variant `fog=0.01` is inf"), "{m}");
    assert!(m.contains("`fc.lora_A.weight`") && m.contains("`fc.lora_B.weight`"), "{m}");
    assert!(m.contains("overflows f32"), "{m}");
    assert_eq!(errs[0].1, place_of(LORA_SPEC, "linear(x, 4)"), "{m}");
}

#[test]
fn adabn_statistics_that_overflow_f32_are_refused() {
    use readi_runtime::calibrate::{BnCalibrator, CalibrateError};
    use readi_runtime::exec::Input;
    let m = module_of(BN_SPEC);
    let w = backend::seeded_weights(&m.graph, 7);
    let (plan, _) = backend::compile(&m, &w, "seeded", &CompileOptions::default()).expect("compiles");
    let mut cal = BnCalibrator::new(std::sync::Arc::new(plan), 1).expect("calibrator");
    // Finite inputs whose variance (~1e40) is finite in f64 but not in f32.
    let x: Vec<f32> = (0..2 * 4 * 16).map(|i| if i % 2 == 0 { 1e20 } else { -1e20 }).collect();
    cal.add_batch(&[Input { name: "x", data: &x, shape: &[2, 4, 4, 4] }]).expect("the batch is finite in f64");
    let e = cal.statistics().expect_err("running_var overflows f32");
    assert!(matches!(&e, CalibrateError::Derived { tensor, .. } if tensor == "bn1.running_var"), "{e}");
    assert!(e.to_string().contains("overflows f32"), "{e}");
}

// --- arithmetic and sizes ---------------------------------------------------------------

/// Compiles `text` expecting exactly one error containing `message`, at `needle`.
fn one_error_at(text: &str, message: &str, needle: &str) {
    let (rendered, errs) = errors(text);
    assert_eq!(errs.len(), 1, "{rendered}");
    assert!(errs[0].0.message.contains(message), "wanted `{message}` in\n{rendered}");
    assert!(!rendered.contains("internal compiler error"), "{rendered}");
    assert_eq!(errs[0].1, place_of(text, needle), "{rendered}");
}

#[test]
fn infinite_arithmetic_is_an_error_at_its_span() {
    let text = "model m {\n  input x: f32[N, 4]\n  output y = x * (0 ** -1)\n}\n";
    one_error_at(text, "`0 ** -1` gives inf", "0 ** -1");
    let text = "model m {\n  input x: f32[N, 4]\n  output y = x * (1e300 * 1e300)\n}\n";
    one_error_at(text, "gives inf", "1e300 * 1e300");
}

#[test]
fn huge_parameters_are_refused_not_wrapped() {
    let text = "model m {\n  input x: f32[N, 65536]\n  fc = linear(x, 65537)\n  output y = fc\n}\n";
    one_error_at(text, "parameter `fc.weight` of shape [65537, 65536] has 4295032832 elements", "linear(x, 65537)");
}

#[test]
fn a_concat_of_65537_inputs_is_a_limit_not_an_internal_error() {
    let xs = vec!["x"; 65_537].join(", ");
    let text = format!("model m {{\n  input x: f32[N, 1]\n  output y = concat([{xs}], axis=1)\n}}\n");
    one_error_at(&text, "`concat` has 65537 inputs, over the limit of 65535", "concat(");
    // One fewer is the limit itself.
    let xs = vec!["x"; 65_535].join(", ");
    let text = format!("model m {{\n  input x: f32[N, 1]\n  output y = concat([{xs}], axis=1)\n}}\n");
    let (rendered, errs) = errors(&text);
    assert!(errs.is_empty(), "{}", &rendered[..rendered.len().min(2000)]);
}

#[test]
fn huge_inputs_are_refused_at_their_declaration() {
    let text = "model m {\n  input x: f32[99999999999, 4]\n  output y = relu(x)\n}\n";
    one_error_at(text, "1490.1 GiB at batch size 1, over the activation limit of 4.0 GiB", "input x");
    let text = "model m {\n  input x: f32[N, 99999999999, 99999999999, 99999999999]\n  output y = relu(x)\n}\n";
    one_error_at(text, "its size in bytes overflows", "input x");
}

#[test]
fn upsample_to_65536_squared_is_refused_at_compile_time() {
    let text = "model m {\n  input x: f32[N, 3, 8, 8]\n  output y = upsample(x, size=[65536, 65536])\n}\n";
    one_error_at(text, "48.0 GiB at batch size 1", "upsample(");
}

#[test]
fn the_activation_peak_is_checked_against_the_limit() {
    use readi_compiler::passes::{self, Options};
    let text = "model m {\n  input x: f32[N, 1024, 1024]\n  a = relu(x)\n  b = relu(x)\n  c = relu(x)\n  \
                output y = a + b + c\n}\n";
    let run = |limit: u64| {
        let mut sources = SourceMap::new();
        let file = sources.add("peak.readi", text);
        let mut opts = Options::default();
        opts.elab.max_activation_bytes = Some(limit);
        let out = passes::run(file, text, &opts);
        (sources.render_all(&out.diagnostics, false), out.diagnostics.error_count())
    };
    // Four 4 MiB values are alive when `c` runs.
    let (rendered, n) = run(12 << 20);
    assert_eq!(n, 1, "{rendered}");
    assert!(rendered.contains("peak at 16.0 MiB (4 values alive together at `c`)"), "{rendered}");
    assert!(rendered.contains("peak.readi:2:3"), "{rendered}");
    assert_eq!(run(16 << 20).1, 0);
    // A single value over the limit is refused where it is made.
    let (rendered, n) = run(2 << 20);
    assert!(n >= 1 && rendered.contains("4.0 MiB at batch size 1, over the activation limit of 2.0 MiB"), "{rendered}");
}

#[test]
fn max_activation_memory_flag() {
    let dir = common::Scratch::new("hostile");
    let spec = dir.join("up.readi");
    std::fs::write(&spec, "model m {\n  input x: f32[N, 3, 8, 8]\n  output y = upsample(x, size=[65536, 65536])\n}\n")
        .expect("write");
    let spec = spec.to_str().expect("utf-8");
    let out = common::readi(&["check", spec]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("over the activation limit of 4.0 GiB"), "{err}");
    let out = common::readi(&["check", spec, "--max-activation-memory", "64G"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // One size syntax with --max-memory: fractions of a unit too.
    let out = common::readi(&["check", spec, "--max-activation-memory", "1.5G"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.code() == Some(1) && err.contains("over the activation limit of 1.5 GiB"), "{err}");
    for bad in ["0", "2X", "99999999999T"] {
        let out = common::readi(&["check", spec, "--max-activation-memory", bad]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: {err}");
        assert!(err.contains("--max-activation-memory"), "{err}");
    }
}

// --- variant files ----------------------------------------------------------------------

const TUNE_SPEC: &str = "model m {
  input x: f32[N, 8] @camera
  fc = linear(x, 4)
  output y = fc
}
adapt {
  tune fc
}
variants {
  axis fog on camera: 0.01, 0.02 clear 0
}
";

/// A fresh directory with the spec, seeded base weights and variant files holding the
/// named tensors of a seeded variant.
fn variant_dir(tag: &str, files: &[(&str, &[&str])]) -> common::Scratch {
    let dir = common::Scratch::new(&format!("hostile-{tag}"));
    std::fs::write(dir.join("m.readi"), TUNE_SPEC).expect("write spec");
    let m = module_of(TUNE_SPEC);
    let base = backend::seeded_weights(&m.graph, 7);
    std::fs::write(dir.join("base.safetensors"), base.to_safetensors().expect("serialises")).expect("write");
    let seeded = backend::seeded_variants(&m, &["fog=0.01".to_string()], 8).remove(0).weights;
    for (file, names) in files {
        let mut w = WeightSet::default();
        for n in *names {
            w.tensors.insert(n.to_string(), seeded.tensors[*n].clone());
        }
        std::fs::write(dir.join(file), w.to_safetensors().expect("serialises")).expect("write");
    }
    dir
}

fn run_in(dir: &std::path::Path, args: &[&str]) -> (bool, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_readi"))
        .args(args)
        .current_dir(dir)
        .env("NO_COLOR", "1")
        .output()
        .expect("run readi");
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

#[test]
fn a_variant_key_given_twice_merges_disjoint_files() {
    let dir = variant_dir("merge", &[("a.safetensors", &["fc.weight"]), ("b.safetensors", &["fc.bias"])]);
    let compile = ["compile", "m.readi", "--weights", "base.safetensors", "-o", "m.plan", "--strict"];
    // One file alone is missing a tensor the variant owns: with --strict, an error.
    let (ok, out) = run_in(&dir, &[&compile[..], &["--variant", "fog=0.01=a.safetensors"]].concat());
    assert!(!ok && out.contains("fc.bias"), "{out}");
    // Both files: their tensors merge (before, `a` was silently dropped).
    let both = ["--variant", "fog=0.01=a.safetensors", "--variant", "fog=0.01=b.safetensors"];
    let (ok, out) = run_in(&dir, &[&compile[..], &both].concat());
    assert!(ok, "{out}");
    // Keys match by value: `fog=0.010` is `fog=0.01`.
    let respelt = ["--variant", "fog=0.01=a.safetensors", "--variant", "fog=0.010=b.safetensors"];
    let (ok, out) = run_in(&dir, &[&compile[..], &respelt].concat());
    assert!(ok, "{out}");
    // The same rule in a deployment manifest that lists the key twice.
    let yaml = "spec: m.readi\nweights: base.safetensors\nvariants:\n  - key: fog=0.01\n    params: a.safetensors\n  \
                - key: fog=0.01\n    params: b.safetensors\n";
    std::fs::write(dir.join("deploy.yaml"), yaml).expect("write");
    let (ok, out) = run_in(&dir, &["compile", "--deploy", "deploy.yaml", "-o", "d.plan", "--strict"]);
    assert!(ok, "{out}");
}

#[test]
fn a_variant_key_given_twice_with_overlapping_files_is_an_error() {
    let dir = variant_dir("overlap", &[("a.safetensors", &["fc.weight", "fc.bias"]), ("b.safetensors", &["fc.bias"])]);
    let args = ["compile", "m.readi", "--weights", "base.safetensors", "-o", "m.plan"];
    let both = ["--variant", "fog=0.01=a.safetensors", "--variant", "fog=0.01=b.safetensors"];
    let (ok, out) = run_in(&dir, &[&args[..], &both].concat());
    assert!(!ok, "{out}");
    assert!(
        out.contains("variant `fog=0.01`: tensor `fc.bias` is given by both a.safetensors and b.safetensors"),
        "{out}"
    );
    let yaml = "spec: m.readi\nweights: base.safetensors\nvariants:\n  - key: fog=0.01\n    params: a.safetensors\n  \
                - key: fog=0.01\n    params: b.safetensors\n";
    std::fs::write(dir.join("deploy.yaml"), yaml).expect("write");
    let (ok, out) = run_in(&dir, &["compile", "--deploy", "deploy.yaml", "-o", "d.plan"]);
    assert!(!ok && out.contains("tensor `fc.bias` is given by both"), "{out}");
}

#[test]
fn weight_files_must_be_regular_files() {
    let dir = variant_dir("devzero", &[]);
    let (ok, out) = run_in(&dir, &["compile", "m.readi", "--weights", "/dev/zero", "-o", "m.plan"]);
    assert!(!ok && out.contains("cannot read /dev/zero: it is not a regular file"), "{out}");
    let variant = ["compile", "m.readi", "--weights", "base.safetensors", "-o", "m.plan"];
    let (ok, out) = run_in(&dir, &[&variant[..], &["--variant", "fog=0.01=/dev/zero"]].concat());
    assert!(!ok && out.contains("cannot read /dev/zero: it is not a regular file"), "{out}");
    let (ok, out) = run_in(&dir, &["check", "/dev/zero"]);
    assert!(!ok && out.contains("not a regular file"), "{out}");
    // A PEFT directory whose weights are a device.
    let peft = dir.join("adapter");
    std::fs::create_dir_all(&peft).expect("dir");
    std::fs::write(peft.join("adapter_config.json"), "{}").expect("write");
    std::os::unix::fs::symlink("/dev/zero", peft.join("adapter_model.safetensors")).expect("symlink");
    let (ok, out) = run_in(&dir, &[&variant[..], &["--variant", "fog=0.01=adapter"]].concat());
    assert!(!ok && out.contains("adapter_model.safetensors: it is not a regular file"), "{out}");
    // A spec that is a device, for the other front-end commands too.
    let (ok, out) = run_in(&dir, &["ir", "/dev/zero"]);
    assert!(!ok && out.contains("not a regular file"), "{out}");
}

#[test]
fn read_bounded_refuses_files_over_the_limit() {
    let dir = variant_dir("limit", &[]);
    let big = dir.join("big.readi");
    std::fs::write(&big, vec![b' '; (4 << 20) + 1]).expect("write");
    let (ok, out) = run_in(&dir, &["check", "big.readi"]);
    assert!(!ok && out.contains("big.readi is 4194305 bytes, over the limit of 4194304 bytes"), "{out}");
}

#[test]
fn an_adapter_too_large_for_the_parameter_limit_is_refused_at_its_rule() {
    let text = "block B(x: tensor) {\n  bn2 = batchnorm(x)\n  return bn2\n}\nmodel m {\n  \
                input x: f32[N, 1048576, 1, 1]\n  b = B(x)\n  output y = b\n}\nadapt {\n  \
                adapter squeeze=2 in B before bn2\n}\n";
    one_error_at(
        text,
        "parameter `b.bn2.adapter.down.weight` of shape [524288, 1048576, 1, 1] has 549755813888 elements",
        "adapter squeeze=2",
    );
}

#[test]
fn adabn_train_mode_scales_that_overflow_f32_are_refused() {
    use readi_runtime::calibrate::{BnCalibrator, CalibrateError};
    use readi_runtime::exec::Input;
    let m = module_of(BN_SPEC);
    let mut w = backend::seeded_weights(&m.graph, 7);
    // Finite when folded with the running variance (about 1), infinite over a batch
    // variance of 0: gamma / sqrt(0 + 1e-5).
    set(&mut w, "bn1.weight", 1, 3e38);
    let (plan, _) = backend::compile(&m, &w, "seeded", &CompileOptions::default()).expect("compiles");
    let mut cal = BnCalibrator::new(std::sync::Arc::new(plan), 1).expect("calibrator");
    let x = vec![0.5f32; 2 * 4 * 16];
    let e = cal.add_batch(&[Input { name: "x", data: &x, shape: &[2, 4, 4, 4] }]).expect_err("the scale overflows");
    assert!(
        matches!(&e, CalibrateError::Derived { tensor, index: 1, .. } if tensor == "bn1@scale (train mode)"),
        "{e}"
    );
    assert!(e.to_string().contains("`bn1.weight[1]` = 3e38"), "{e}");
    assert_eq!(cal.batches(), 0, "a failed batch adds nothing");
}

#[test]
fn adabn_samples_must_be_regular_files() {
    let dir = variant_dir("adabn-samples", &[]);
    let m = module_of(BN_SPEC);
    let w = backend::seeded_weights(&m.graph, 7);
    let (plan, _) = backend::compile(&m, &w, "seeded", &CompileOptions::default()).expect("compiles");
    plan.write(&dir.join("bn.plan")).expect("write the plan");
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero.safetensors")).expect("symlink");
    let args = ["adapt-bn", "bn.plan", "--variant", "fog=0.01", "--samples", "zero.safetensors", "-o", "s.safetensors"];
    let (ok, out) = run_in(&dir, &args);
    assert!(!ok && out.contains("cannot read zero.safetensors: it is not a regular file"), "{out}");
}
