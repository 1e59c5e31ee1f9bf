//! Melded variants against PyTorch: the paper's rule (layers one part tunes taken whole,
//! overlapping layers interpolated with the lambdas renormalised over their owners, LoRA
//! melded on its updates), on tests/fixtures/meld/meld.readi with the weights, variants
//! and reference outputs tests/fixtures/meld/make_meld_fixtures.py wrote. The script
//! computes the meld itself, from the layer ownership it writes out, not through readi.

mod common;

use std::sync::Arc;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, LoraMode, VariantSource, WeightSet};
use readi_compiler::passes::{self, BackendInputs, Pass};
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::Plan;

const SPEC: &str = "tests/fixtures/meld/meld.readi";
const VARIANTS: [&str; 3] = ["gamma=0.5", "fog=0.06", "blur=5"];
const MELDS: [&str; 3] = ["fog=0.06+gamma=0.5", "blur=5+fog=0.06+gamma=0.5", "blur=5+gamma=0.5"];

struct Fixture {
    all: WeightSet,
    module: Module,
}

fn fixture() -> Fixture {
    let path = common::root().join("tests/fixtures/meld/meld.safetensors");
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let all = WeightSet::from_safetensors("meld.safetensors", &bytes).expect("fixture");
    let (sources, out) = common::compile(SPEC, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    Fixture { all, module: out.module.expect("module") }
}

/// The tensors stored under `<prefix>.`, with the prefix removed.
fn with_prefix(all: &WeightSet, prefix: &str) -> WeightSet {
    let mut set = WeightSet::default();
    for (k, v) in &all.tensors {
        if let Some(name) = k.strip_prefix(&format!("{prefix}.")) {
            set.tensors.insert(name.to_string(), v.clone());
        }
    }
    set
}

fn sources(fx: &Fixture) -> Vec<VariantSource> {
    VARIANTS
        .iter()
        .map(|k| VariantSource { key: k.to_string(), weights: with_prefix(&fx.all, k), origin: format!("{k} files") })
        .collect()
}

fn compile(fx: &Fixture, lora: LoraMode) -> Plan {
    let opts = CompileOptions { lora, melds: MELDS.iter().map(|m| m.to_string()).collect(), ..Default::default() };
    let base = with_prefix(&fx.all, "base");
    backend::compile_variants(&fx.module, &base, "base", &sources(fx), &opts)
        .unwrap_or_else(|d| panic!("{:?}", d.0.iter().map(|d| &d.message).collect::<Vec<_>>()))
        .0
}

#[test]
fn melded_variants_match_the_papers_rule_in_pytorch() {
    let fx = fixture();
    let input = |n: &str| &fx.all.tensors[&format!("input.{n}")];
    let (img, bev) = (input("img"), input("bev"));
    for lora in [LoraMode::Merge, LoraMode::Branch] {
        let plan = Arc::new(compile(&fx, lora));
        assert_eq!(plan.manifest.variants.len(), VARIANTS.len() + MELDS.len());
        let mut session = Session::new(plan, 1).expect("session");
        for key in std::iter::once("base").chain(VARIANTS).chain(MELDS) {
            session.set_variant(key).expect("known key");
            let inputs = [
                Input { name: "img", data: &img.1, shape: &img.0 },
                Input { name: "bev", data: &bev.1, shape: &bev.0 },
            ];
            let out = session.run(&inputs).expect("run");
            let want = &fx.all.tensors[&format!("out.{key}.y")].1;
            let got = &out[0].1.data;
            let scale = want.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            let err = got.iter().zip(want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            eprintln!("{key} (LoRA {}): max abs error {err:e} (outputs up to {scale:.3})", lora.name());
            assert!(err <= 1e-4 * scale.max(1.0), "{key} (LoRA {}): differs from PyTorch by {err:e}", lora.name());
        }
    }
}

/// Read after the `meld` pass: what each melded variant holds, tensor by tensor.
#[test]
fn the_meld_takes_exclusive_layers_whole_and_serves_a_melded_lora_as_a_weight() {
    let fx = fixture();
    let base = with_prefix(&fx.all, "base");
    let opts = CompileOptions { melds: MELDS.iter().map(|m| m.to_string()).collect(), ..Default::default() };
    let srcs = sources(&fx);
    let inputs = BackendInputs { base: &base, base_name: "base", variants: &srcs, opts: &opts };
    let mut m = fx.module.clone();
    passes::run_backend(&mut m, &inputs, Some(Pass::Meld)).expect("melds");
    let table = m.tensors.expect("table");
    let index = |key: &str| 1 + table.variants.iter().position(|v| v.key.to_string() == key).expect("variant");
    let bits =
        |name: &str, v: usize| table.value(name, v).expect("bound").iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let (gamma, blur, fog_gamma, all3, blur_gamma) =
        (index("gamma=0.5"), index("blur=5"), index(MELDS[0]), index(MELDS[1]), index(MELDS[2]));
    // (b) head.fc is gamma's alone in fog+gamma: bit for bit.
    assert_eq!(bits("head.fc.weight", fog_gamma), bits("head.fc.weight", gamma));
    // b2 is blur's alone in the three-part meld; nobody's in fog+gamma.
    assert_eq!(bits("b2.running_var", all3), bits("b2.running_var", blur));
    assert_eq!(bits("b2.running_var", fog_gamma), bits("b2.running_var", 0));
    // (a) c2 is owned by gamma (LoRA) and fog (bias): the update is in the weight, A and B
    // are the base's zeros.
    assert_ne!(bits("c2.weight", fog_gamma), bits("c2.weight", 0));
    assert!(table.value("c2.lora_B.weight", fog_gamma).expect("B").iter().all(|x| *x == 0.0));
    // blur does not own c2: gamma's LoRA comes whole, the weight stays the base's.
    assert_eq!(bits("c2.lora_A.weight", blur_gamma), bits("c2.lora_A.weight", gamma));
    assert_eq!(bits("c2.weight", blur_gamma), bits("c2.weight", 0));
    // (d) BatchNorm statistics interpolate: 0.5, 0.3, 0.2 over b1's three owners.
    let mean = |k: &str| with_prefix(&fx.all, k).tensors["b1.running_mean"].1.clone();
    let (g, b, f) = (mean("gamma=0.5"), mean("blur=5"), mean("fog=0.06"));
    for (i, x) in table.value("b1.running_mean", all3).expect("b1").iter().enumerate() {
        let want = 0.5 * g[i] as f64 + 0.3 * b[i] as f64 + 0.2 * f[i] as f64;
        assert!((*x as f64 - want).abs() < 1e-6, "b1.running_mean[{i}]: {x} vs {want}");
    }
    let origin = &table.variants[all3 - 1].origin;
    assert!(origin.contains("1 layer taken whole from one part, 3 layers interpolated"), "{origin}");
}

/// The meld's layers on ResNet-18: an adapter's down and up convs are one layer, a LoRA's
/// A and B belong to the layer they adapt, a BatchNorm's four tensors are one layer.
#[test]
fn layers_group_injected_tensors_with_what_they_adapt() {
    let (sources, out) = common::compile("models/resnet18.readi", &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let base = backend::seeded_weights(&m.graph, 1);
    let opts = CompileOptions::default();
    let inputs = BackendInputs { base: &base, base_name: "seeded", variants: &[], opts: &opts };
    let mut bound = m.clone();
    passes::run_backend(&mut bound, &inputs, Some(Pass::BindWeights)).expect("binds");
    let table = bound.tensors.as_ref().expect("table");
    let layers = passes::meld::layers(&bound, table);
    let find = |name: &str| layers.iter().find(|l| l.name == name).unwrap_or_else(|| panic!("no layer `{name}`"));
    let adapter = find("layer1.0.bn2.adapter");
    let mut t = adapter.tensors.clone();
    t.sort();
    assert_eq!(
        t,
        [
            "layer1.0.bn2.adapter.down.bias",
            "layer1.0.bn2.adapter.down.weight",
            "layer1.0.bn2.adapter.up.bias",
            "layer1.0.bn2.adapter.up.weight"
        ]
    );
    let lora = find("layer4.0.downsample.0");
    let l = lora.lora.as_ref().expect("a LoRA layer");
    assert_eq!((l.weight.as_str(), l.rank, l.scale), ("layer4.0.downsample.0.weight", 4, 2.0));
    assert_eq!(lora.tensors.len(), 2, "{:?}", lora.tensors);
    assert_eq!(find("bn1").tensors.len(), 4);
    // Every owned tensor is in exactly one layer.
    let n: usize = layers.iter().map(|l| l.tensors.len()).sum();
    assert_eq!(n, table.owned.len());
}
