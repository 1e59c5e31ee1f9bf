//! Adaptation rules scoped to conditions (`adapt camera { ... }`): which variant owns
//! what, the errors of a variant file that gives a tensor outside its scope, the one
//! summary warning for variants that give part of what they own, and each variant's
//! budget in the plan, checked against element counts worked out by hand from
//! tests/cases/ok/adapt_scoped.readi:
//!
//! | parameter | elements | scope |
//! | --- | --- | --- |
//! | `head.{weight,bias}` | 4*8 + 4 = 36 | every variant |
//! | `cam.bn.{weight,bias,running_mean,running_var}` | 4*8 = 32 | camera |
//! | `cam.conv.lora_{A,B}` (rank 2, 3 -> 8, 3x3) | 2*3*9 + 8*2 = 70 added | camera |
//! | `lid.bn.*` | 32 | lidar, missing=lidar |
//! | `fuse.{weight,bias}` | 8*16 + 8 = 136 | lidar, missing=lidar (and `fuse.bias` fog) |

mod common;

use readi_compiler::Module;
use readi_compiler::backend::variants::owned_params;
use readi_compiler::backend::{self, CompileOptions, VariantSource, WeightSet};
use readi_grammar::diag::{Code, Diagnostics, SourceMap};
use readi_plan::VariantKey;

const CASE: &str = "tests/cases/ok/adapt_scoped.readi";

fn module() -> (SourceMap, Module) {
    let (sources, out) = common::compile(CASE, &[], None);
    assert!(out.diagnostics.is_empty(), "{}", sources.render_all(&out.diagnostics, false));
    (sources, out.module.expect("module"))
}

fn key(k: &str) -> VariantKey {
    VariantKey::parse(k).expect("a key")
}

/// The names a key owns, sorted.
fn owned_by(m: &Module, k: &str) -> Vec<String> {
    let k = key(k);
    owned_params(m).into_iter().filter(|(_, o)| o.is_owned_by(&k)).map(|(n, _)| n).collect()
}

fn names(list: &[&str]) -> Vec<String> {
    let mut v: Vec<String> = list.iter().map(|s| s.to_string()).collect();
    v.sort();
    v
}

const HEAD: &[&str] = &["head.bias", "head.weight"];
const CAM: &[&str] = &[
    "cam.bn.bias",
    "cam.bn.running_mean",
    "cam.bn.running_var",
    "cam.bn.weight",
    "cam.conv.lora_A.weight",
    "cam.conv.lora_B.weight",
];
const LIDAR: &[&str] =
    &["fuse.bias", "fuse.weight", "lid.bn.bias", "lid.bn.running_mean", "lid.bn.running_var", "lid.bn.weight"];

#[test]
fn each_variant_owns_its_scopes_and_the_unscoped_rules() {
    let (_, m) = module();
    assert_eq!(owned_by(&m, "gamma=0.5"), names(&[HEAD, CAM].concat()));
    assert_eq!(owned_by(&m, "gamma=2"), names(&[HEAD, CAM].concat()));
    assert_eq!(owned_by(&m, "fog=0.03"), names(&[HEAD, LIDAR].concat()));
    // `missing=lidar` is named by `adapt lidar, missing=lidar`, not by `adapt lidar` alone.
    assert_eq!(owned_by(&m, "missing=lidar"), names(&[HEAD, LIDAR].concat()));
    // A meld owns the union of its parts'.
    assert_eq!(owned_by(&m, "fog=0.03+gamma=0.5"), names(&[HEAD, CAM, LIDAR].concat()));
    assert!(owned_by(&m, "base").is_empty());
    // Two `tune` rules of different scopes on one parameter: both scopes own it.
    let owned = owned_params(&m);
    let labels: Vec<String> = owned["fuse.bias"].scopes.iter().map(|s| s.label()).collect();
    assert_eq!(labels, vec!["lidar, missing=lidar".to_string(), "fog".to_string()]);
    assert!(owned["head.weight"].scopes[0].is_all());
}

#[test]
fn budgets_per_variant_are_its_scopes() {
    let (_, m) = module();
    let plan = m.adapt.as_ref().expect("adapt");
    let g = &m.graph;
    assert_eq!(plan.budget(g, &key("gamma=0.5")), (36 + 32, 70));
    assert_eq!(plan.budget(g, &key("fog=0.06")), (36 + 32 + 136, 0));
    assert_eq!(plan.budget(g, &key("missing=lidar")), (36 + 32 + 136, 0));
    assert_eq!(plan.budget(g, &key("fog=0.03+gamma=0.5")), (36 + 32 + 32 + 136, 70));
    // Over every scope, each slot once.
    assert_eq!((plan.tuned_elements(g), plan.added_elements()), (36 + 32 + 32 + 136, 70));
}

fn base(m: &Module) -> WeightSet {
    backend::seeded_weights(&m.graph, 7)
}

fn compile(m: &Module, sources: &[VariantSource], opts: &CompileOptions) -> Result<Diagnostics, Diagnostics> {
    backend::compile_variants(m, &base(m), "base.safetensors", sources, opts).map(|(_, w)| w)
}

#[test]
fn plan_tables_carry_each_variants_budget_and_scopes() {
    let (_, m) = module();
    let keys: Vec<String> = ["gamma=0.5", "fog=0.03", "missing=lidar"].iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(&m, &keys, 11);
    let opts = CompileOptions { melds: vec!["fog=0.03+gamma=0.5".into()], ..Default::default() };
    let (plan, warnings) =
        backend::compile_variants(&m, &base(&m), "base.safetensors", &sources, &opts).expect("compiles");
    // Seeded variants give exactly what they own: no warning.
    assert!(warnings.is_empty(), "{warnings:?}");
    let got: Vec<(String, u64, u64, Vec<String>)> = plan
        .manifest
        .variants
        .iter()
        .map(|v| (v.key.to_string(), v.tuned_elements, v.added_elements, v.scopes.clone()))
        .collect();
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
    assert_eq!(
        got,
        vec![
            ("gamma=0.5".to_string(), 68, 70, s(&["camera"])),
            ("fog=0.03".to_string(), 204, 0, s(&["lidar, missing=lidar", "fog"])),
            ("missing=lidar".to_string(), 204, 0, s(&["lidar, missing=lidar"])),
            ("fog=0.03+gamma=0.5".to_string(), 236, 70, s(&["camera", "lidar, missing=lidar", "fog"])),
        ]
    );
    // The budget table of `readi inspect` shows each variant's scopes.
    let table = readi::inspect::budget(&plan, 452, false);
    let row = table.lines().find(|l| l.trim_start().starts_with("gamma=0.5")).expect("a gamma row");
    assert!(row.contains("  camera  "), "{table}");
    assert!(table.lines().nth(1).is_some_and(|h| h.contains("scope")), "{table}");
}

fn file(k: &str, origin: &str, tensors: &[(&str, Vec<usize>)]) -> VariantSource {
    let mut set = WeightSet::default();
    for (name, shape) in tensors {
        set.tensors.insert(name.to_string(), (shape.clone(), vec![0.5; shape.iter().product()]));
    }
    VariantSource { key: k.into(), weights: set, origin: origin.into() }
}

#[test]
fn a_tensor_outside_the_variants_scope_is_an_error_naming_both_scopes() {
    let (sources, m) = module();
    let v = file("gamma=0.5", "g05.safetensors", &[("head.bias", vec![4]), ("lid.bn.weight", vec![8])]);
    let err = compile(&m, &[v], &CompileOptions::default()).expect_err("out of scope");
    let msg = sources.render_all(&err, false);
    assert!(
        msg.contains(
            "g05.safetensors: tensor `lid.bn.weight` is outside the scope of variant `gamma=0.5`: it is owned by \
             scope `lidar, missing=lidar`, and `gamma=0.5` owns the unscoped rules and scope `camera`"
        ),
        "{msg}"
    );
    // Pointing at the layer.
    assert!(msg.contains("adapt_scoped.readi:12:"), "{msg}");
    // The same tensor given by a lidar variant binds.
    let v = file("fog=0.03", "f.safetensors", &[("lid.bn.weight", vec![8])]);
    assert!(compile(&m, &[v], &CompileOptions::default()).is_ok());
}

#[test]
fn variants_that_give_part_of_what_they_own_are_one_warning() {
    let (sources, m) = module();
    let vs = vec![
        file("gamma=0.5", "a", &[("head.bias", vec![4])]),
        file("gamma=2", "b", &[("head.bias", vec![4]), ("cam.bn.weight", vec![8])]),
        file("fog=0.03", "c", &[("head.bias", vec![4])]),
    ];
    let warnings = compile(&m, &vs, &CompileOptions::default()).expect("compiles");
    assert_eq!(warnings.iter().filter(|d| d.code == Code::VariantWeights).count(), 1, "{warnings:?}");
    let text = sources.render_all(&warnings, false);
    assert_eq!(text.lines().filter(|l| l.contains("warning")).count(), 1, "{text}");
    assert!(
        text.contains(
            "3 variants give part of what they own (the rest keeps the base value): gamma=0.5 gives 1 of 8, \
             gamma=2 gives 2 of 8, fog=0.03 gives 1 of 8; --strict makes this an error"
        ),
        "{text}"
    );
    // `--strict`: one error per variant, each naming it.
    let err = compile(&m, &vs, &CompileOptions { strict: true, ..Default::default() }).expect_err("strict");
    let text = sources.render_all(&err, false);
    assert_eq!(err.iter().filter(|d| d.is_error()).count(), 3, "{text}");
    for k in ["gamma=0.5", "gamma=2", "fog=0.03"] {
        assert!(text.contains(&format!("variant `{k}` does not give")), "{text}");
    }
    assert!(text.contains("variant `gamma=0.5` does not give 7 of its 8 parameters"), "{text}");
}

#[test]
fn provided_and_fallback_are_within_the_scope() {
    let (_, m) = module();
    let mut module = m.clone();
    let vs = vec![file("gamma=0.5", "a", &[("head.bias", vec![4]), ("cam.bn.bias", vec![8])])];
    let opts = CompileOptions::default();
    let inputs = readi_compiler::passes::BackendInputs { base: &base(&m), base_name: "b", variants: &vs, opts: &opts };
    readi_compiler::passes::run_backend(&mut module, &inputs, Some(readi_compiler::passes::Pass::BindVariants))
        .expect("binds");
    let table = module.tensors.as_ref().expect("table");
    let info = &table.variants[0];
    assert_eq!(info.provided.iter().cloned().collect::<Vec<_>>(), names(&["cam.bn.bias", "head.bias"]));
    let mut fallback = info.fallback.clone();
    fallback.sort();
    assert_eq!(
        fallback,
        names(&[
            "cam.bn.running_mean",
            "cam.bn.running_var",
            "cam.bn.weight",
            "cam.conv.lora_A.weight",
            "cam.conv.lora_B.weight",
            "head.weight"
        ])
    );
    assert!(table.variant_owns(1, "cam.bn.weight") && !table.variant_owns(1, "lid.bn.weight"));
    assert!(!table.variant_owns(0, "head.bias"), "the base owns nothing");
    assert_eq!(table.owned_by(&info.key).count(), 8);
}

#[test]
fn readi_params_reports_per_scope() {
    let o = common::readi(&["params", CASE]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}");
    for line in [
        "  unscoped (variants gamma=*, fog=*, missing=lidar): 36 tuned, 0 added",
        "  scope camera (variants gamma=*): 32 tuned, 70 added",
        "  scope lidar, missing=lidar (variants fog=*, missing=lidar): 168 tuned, 0 added",
        "  scope fog (variants fog=*): 8 tuned, 0 added",
        "  gamma=*: 68 existing elements tuned (15.04% of parameters), 70 added (15.49%)",
        "  fog=*: 204 existing elements tuned (45.13% of parameters), 0 added (0.00%)",
        "  missing=lidar: 204 existing elements tuned (45.13% of parameters), 0 added (0.00%)",
    ] {
        assert!(out.lines().any(|l| l == line), "`{line}` missing from\n{out}");
    }
}
