//! A structure-aware fuzzer for plan files: hostile plans are refused, never crash.
//!
//! Each case takes a plan compiled from a small spec (with variants, conditions, LoRA
//! merged and as a branch, every conv algorithm), applies up to six mutations to its
//! manifest, as JSON but knowing what the fields mean, writes the file with a correct
//! checksum (a checksum guards against accidents, not against someone who rewrites the
//! manifest), and loads, inspects, binds and runs it under a memory budget, for the base
//! and its variants. Loading or binding may refuse the plan; nothing may panic, abort or
//! hang ([`HANG`]).
//!
//! Mutations ([`Mutation`]): set a number to a boundary value or near its old value, graft
//! another node of the manifest with the same field name in its place (indices, shapes,
//! kernels, keys, variant tables), edit an array (drop, duplicate, swap, clear), replace a
//! string (another name of the plan, a kernel or algorithm name, control characters),
//! change a conv's algorithm, poison a tensor's data (NaN, infinity, huge), grow an axis
//! of an input (to reach the memory budget once the shapes behind it are repaired), or
//! change a tensor's element type (f16 on a base tensor or a value, a type the plan format
//! has no tensors of, f32 for an f16 replacement); the file stores each tensor as its
//! manifest entry says (f16 as f16), except the types it cannot hold, stored f32. Half of the
//! cases are then *repaired* ([`repair`]): value shapes re-inferred by the operators'
//! rules, tensor sizes made to fit their kernels, so that the mutation reaches the checks
//! behind the manifest validation (kernel preconditions, the memory budget) instead of
//! being refused by the first shape comparison.
//!
//! Case count: `PLAN_FUZZ_CASES` (default 1024: about 20 s in a debug build). The long run is described in
//! `docs/security.md`. A failure is persisted by proptest and printed as the minimal
//! mutation list; the plan file of the failing case is kept in the temporary directory.

#[path = "common/mod.rs"]
mod common;

use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use proptest::prelude::*;
use proptest::test_runner::FileFailurePersistence;
use readi_compiler::backend::{self, CompileOptions, LoraMode};
use readi_plan::format::{Kernel, Manifest, Storage};
use readi_plan::ops::{self, ConvAlgo};
use readi_plan::{Dim, TensorType};
use readi_runtime::exec::{Input, Session, SessionOptions};
use readi_runtime::plan::Plan;
use serde_json::Value;

/// A case that takes longer than this is a hang.
const HANG: Duration = Duration::from_secs(30);

/// The memory budget plans are bound under.
const BUDGET: usize = 256 << 20;

/// A plan to mutate: its manifest as JSON and its stored tensors by name.
struct Seed {
    name: &'static str,
    manifest: Value,
    tensors: HashMap<String, Vec<f32>>,
}

/// The specs the seeds are compiled from, with the LoRA mode and the variants to seed.
const SPECS: &[(&str, LoraMode, usize)] = &[
    ("tests/cases/ok/adapt_and_variants.readi", LoraMode::Merge, 3),
    ("tests/cases/ok/adapt_and_variants.readi", LoraMode::Branch, 2),
    ("tests/cases/ok/all_ops.readi", LoraMode::Merge, 0),
    ("conv_algorithms", LoraMode::Merge, 0),
    ("conv_algorithms_lora", LoraMode::Branch, 1),
    ("conv_algorithms_switch", LoraMode::Auto, 1),
    ("conv_algorithms_adapters", LoraMode::Merge, 1),
    ("conv_algorithms_f16", LoraMode::Branch, 1),
];

/// A spec with a conv of every algorithm the compiler chooses (Winograd F(4x4) and
/// F(2x2), 1x1 GEMM, depthwise, im2col), so that the cases can give each one's layer to
/// another.
const CONV_ALGORITHMS: &str = "\
model convs {
  input x: f32[N, 32, 24, 24] @camera
  w4 = conv2d(x, 32, kernel=3, padding=1)
  small = maxpool(relu(w4), kernel=2)
  w2 = conv2d(small, 32, kernel=3, padding=1)
  pw = conv2d(w2, 16, kernel=1)
  dw = conv2d(pw, 16, kernel=3, padding=1, groups=16)
  s2 = conv2d(dw, 8, kernel=3, stride=2, padding=1)
  head = linear(flatten(global_avgpool(s2), start=1), 4)
  output y = head
}
";

/// [`CONV_ALGORITHMS`] with a LoRA branch fused into the conv of each algorithm but the
/// depthwise one and into the linear head.
const LORA_RULES: &str = "\
adapt {
  lora rank=2 alpha=4 on w4
  lora rank=2 alpha=4 on w2
  lora rank=2 alpha=4 on pw
  lora rank=2 alpha=4 on s2
  lora rank=2 alpha=4 on head
}
variants {
  axis fog on camera: 0.03 clear 0
}
";

/// A conv, BatchNorm and ReLU block for each algorithm but Winograd F(2x2) (F(4x4),
/// 1x1 GEMM, depthwise, im2col at stride 2), each with an adapter fused into its conv.
const ADAPTERS: &str = "\
block CB(x: tensor, c: int, k: int, s: int, p: int, g: int) {
  conv = conv2d(x, c, kernel=k, stride=s, padding=p, groups=g, bias=false)
  bn = batchnorm(conv)
  return relu(bn)
}
model convs {
  input x: f32[N, 32, 24, 24] @camera
  w4 = CB(x, 32, 3, 1, 1, 1)
  pw = CB(w4, 16, 1, 1, 0, 1)
  dw = CB(pw, 16, 3, 1, 1, 16)
  s2 = CB(dw, 8, 3, 2, 1, 1)
  head = linear(flatten(global_avgpool(s2), start=1), 4)
  output y = head
}
adapt {
  adapter squeeze=2 act=relu in CB before bn
}
variants {
  axis fog on camera: 0.03 clear 0
}
";

/// [`CONV_ALGORITHMS`] with its head tuned and a LoRA branch, compiled with
/// `--variant-f16`: the variant's head weight is stored f16.
const F16_RULES: &str = "\
adapt {
  tune head
  lora rank=2 alpha=4 on w4
}
variants {
  axis fog on camera: 0.03 clear 0
}
";

fn seeds() -> &'static [Seed] {
    static SEEDS: OnceLock<Vec<Seed>> = OnceLock::new();
    SEEDS.get_or_init(|| SPECS.iter().map(|&(rel, lora, n)| compile_seed(rel, lora, n)).collect())
}

fn compile_seed(rel: &'static str, lora: LoraMode, variants: usize) -> Seed {
    let (sources, out) = if rel == "conv_algorithms" {
        common::compile_text(rel, CONV_ALGORITHMS, &[], None)
    } else if rel == "conv_algorithms_lora" || rel == "conv_algorithms_switch" {
        common::compile_text(rel, &format!("{CONV_ALGORITHMS}{LORA_RULES}"), &[], None)
    } else if rel == "conv_algorithms_adapters" {
        common::compile_text(rel, ADAPTERS, &[], None)
    } else if rel == "conv_algorithms_f16" {
        common::compile_text(rel, &format!("{CONV_ALGORITHMS}{F16_RULES}"), &[], None)
    } else {
        common::compile(rel, &[], None)
    };
    assert!(!out.diagnostics.has_errors(), "{rel}: {}", sources.render_all(&out.diagnostics, false));
    let module = out.module.expect("a module without errors");
    let keys: Vec<String> = module
        .variants
        .as_ref()
        .map(|v| v.keys())
        .unwrap_or_default()
        .iter()
        .take(variants)
        .map(|k| k.to_string())
        .collect();
    let weights = backend::seeded_weights(&module.graph, 1);
    let sources_v = backend::seeded_variants(&module, &keys, 2);
    let mut opts = CompileOptions { lora, variant_f16: rel == "conv_algorithms_f16", ..CompileOptions::default() };
    if rel == "conv_algorithms_switch" {
        // Every LoRA conv merged on switch: an unreachable budget keeps the free savings,
        // fixed costs make it deterministic.
        fn ms(s: &ops::Conv2dShape, _: ConvAlgo) -> f64 {
            (s.cout * s.k() * s.oh * s.ow) as f64 * 1e-6
        }
        fn switch(_: &ops::Conv2dShape, _: ConvAlgo, _: usize) -> f64 {
            0.01
        }
        opts.memory_budget = Some(0.0);
        opts.switch_budget = Some(1.0);
        opts.timing = readi_compiler::passes::choose_strategy::Timing::FixedSwitch(ms, switch);
    }
    let (plan, _) = backend::compile_variants(&module, &weights, "seeded", &sources_v, &opts)
        .unwrap_or_else(|d| panic!("{rel}: {}", sources.render_all(&d, false)));
    if rel == "conv_algorithms_lora" {
        assert_eq!(plan.manifest.steps.iter().filter(|s| s.kernel.lora().is_some()).count(), 5, "fused branches");
    }
    if rel == "conv_algorithms_switch" {
        let switched = plan.manifest.steps.iter().filter(|s| matches!(s.kernel, Kernel::Conv2d { switch: true, .. }));
        assert_eq!(switched.count(), 4, "convs merged on switch");
    }
    if rel == "conv_algorithms_f16" {
        let half = plan.manifest.tensors.iter().filter(|t| t.dtype == readi_plan::ops::DType::F16).count();
        assert!(half >= 1, "an f16 variant tensor");
    }
    if rel == "conv_algorithms_adapters" {
        let fused: Vec<&str> = plan
            .manifest
            .steps
            .iter()
            .filter(|s| s.kernel.adapter().is_some())
            .filter_map(|s| match &s.kernel {
                readi_runtime::plan::Kernel::Conv2d { algo, .. } => Some(algo.name()),
                _ => None,
            })
            .collect();
        assert_eq!(fused, ["winograd4", "gemm1x1", "depthwise", "im2col"], "fused adapters");
    }
    // Values as f32 (an f16 tensor's decoded: `plan_file` encodes them again).
    let value = |i: usize| match plan.tensor_f16(i) {
        Some(h) => h.iter().map(|v| v.to_f32()).collect(),
        None => plan.tensor(i).to_vec(),
    };
    let tensors = plan.manifest.tensors.iter().enumerate().map(|(i, t)| (t.name.clone(), value(i))).collect();
    Seed { name: rel, manifest: serde_json::to_value(&plan.manifest).expect("a manifest is JSON"), tensors }
}

/// One edit of a plan: `at` picks the node (or tensor), `arg` the edit's details.
#[derive(Clone, Debug)]
enum Mutation {
    Number { at: usize, arg: u64 },
    Graft { at: usize, arg: usize },
    Array { at: usize, arg: u64 },
    Text { at: usize, arg: usize },
    Algorithm { at: usize, arg: usize },
    Poison { at: usize, arg: u64 },
    Grow { at: usize, arg: u64 },
    Dtype { at: usize, arg: usize },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let at = any::<usize>();
    prop_oneof![
        4 => (at, any::<u64>()).prop_map(|(at, arg)| Mutation::Number { at, arg }),
        3 => (at, any::<usize>()).prop_map(|(at, arg)| Mutation::Graft { at, arg }),
        2 => (at, any::<u64>()).prop_map(|(at, arg)| Mutation::Array { at, arg }),
        2 => (at, any::<usize>()).prop_map(|(at, arg)| Mutation::Text { at, arg }),
        2 => (at, any::<usize>()).prop_map(|(at, arg)| Mutation::Algorithm { at, arg }),
        1 => (at, any::<u64>()).prop_map(|(at, arg)| Mutation::Poison { at, arg }),
        2 => (at, any::<u64>()).prop_map(|(at, arg)| Mutation::Grow { at, arg }),
        2 => (at, any::<usize>()).prop_map(|(at, arg)| Mutation::Dtype { at, arg }),
    ]
}

/// A JSON node's place: the path from the root, and the name of the field it sits in
/// (for an array element, the array's field and `[]`).
#[derive(Clone)]
struct Place {
    path: Vec<Step>,
    field: String,
}

#[derive(Clone)]
enum Step {
    Key(String),
    Index(usize),
}

fn places(v: &Value) -> Vec<Place> {
    fn walk(v: &Value, path: &mut Vec<Step>, field: &str, out: &mut Vec<Place>) {
        out.push(Place { path: path.clone(), field: field.to_string() });
        match v {
            Value::Object(m) => {
                for (k, c) in m {
                    path.push(Step::Key(k.clone()));
                    walk(c, path, k, out);
                    path.pop();
                }
            }
            Value::Array(a) => {
                let element = format!("{field}[]");
                for (i, c) in a.iter().enumerate() {
                    path.push(Step::Index(i));
                    walk(c, path, &element, out);
                    path.pop();
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(v, &mut Vec::new(), "", &mut out);
    out
}

fn node<'a>(v: &'a mut Value, path: &[Step]) -> Option<&'a mut Value> {
    path.iter().try_fold(v, |v, s| match s {
        Step::Key(k) => v.get_mut(k),
        Step::Index(i) => v.get_mut(*i),
    })
}

fn get<'a>(v: &'a Value, path: &[Step]) -> Option<&'a Value> {
    path.iter().try_fold(v, |v, s| match s {
        Step::Key(k) => v.get(k),
        Step::Index(i) => v.get(*i),
    })
}

/// Counts, sizes and indices at the edges of what they can be.
const COUNTS: &[u64] = &[
    0,
    1,
    2,
    3,
    7,
    65_535,
    65_536,
    2_147_483_647,
    4_294_967_295,
    4_294_967_296,
    1 << 36,
    1 << 53,
    i64::MAX as u64,
    u64::MAX,
];

/// Real numbers (thresholds, levels, eps, scales) at the edges.
const REALS: &[f64] = &[0.0, -1.0, 1.0, 0.5, -1e-300, 1e-30, 1e30, 1e300, -1e300];

/// Strings a hostile plan may hold where a name or a kind is expected.
const WORDS: &[&str] = &[
    "",
    "base",
    "\u{1b}]0;owned\u{7}\u{1b}[2J",
    "a\nb",
    "conv2d",
    "gemm1x1",
    "im2col",
    "winograd2",
    "winograd4",
    "depthwise",
    "Conv2d",
    "Linear",
    "Pure",
    "fog=0.03",
    "gamma=0.25+fog=0.03",
    "fog=nan",
    "fog=1e999",
    "brightness",
    "../../etc/passwd",
];

const ALGOS: [ConvAlgo; 5] =
    [ConvAlgo::Gemm1x1, ConvAlgo::Im2col, ConvAlgo::Winograd2, ConvAlgo::Winograd4, ConvAlgo::Depthwise];

/// A new number for a node holding `old`: of the same kind (a count stays a count, so
/// that the manifest still deserialises and the mutation reaches the checks behind it).
fn mutate_number(old: &serde_json::Number, arg: u64) -> Value {
    let pick = (arg / 4) as usize;
    if let Some(n) = old.as_u64() {
        let new = match arg % 4 {
            0 | 1 => COUNTS[pick % COUNTS.len()],
            2 => [n.wrapping_sub(1), n + 1, n.saturating_mul(2), n / 2][pick % 4],
            _ => [n.saturating_mul(1 << 20), n ^ 1, n.saturating_add(1 << 32), 0][pick % 4],
        };
        Value::from(new)
    } else if let Some(n) = old.as_i64() {
        Value::from([n.saturating_sub(1), n.saturating_add(1), i64::MIN, 0][pick % 4])
    } else {
        let x = old.as_f64().unwrap_or(0.0);
        let new = match arg % 3 {
            0 | 1 => REALS[pick % REALS.len()],
            _ => [x * 2.0, -x, x * 1e30, x + 1.0][pick % 4],
        };
        serde_json::Number::from_f64(new).map_or(Value::Null, Value::Number)
    }
}

/// Applies one mutation to a manifest and the stored tensors.
fn apply(m: &Mutation, manifest: &mut Value, tensors: &mut HashMap<String, Vec<f32>>) {
    let all = places(manifest);
    let pick = |at: usize, want: &dyn Fn(&Value) -> bool| -> Option<Place> {
        let matching: Vec<&Place> = all.iter().filter(|p| get(manifest, &p.path).is_some_and(want)).collect();
        (!matching.is_empty()).then(|| matching[at % matching.len()].clone())
    };
    match *m {
        Mutation::Number { at, arg } => {
            let Some(p) = pick(at, &|v| v.is_number()) else { return };
            if let Some(n) = node(manifest, &p.path)
                && let Value::Number(old) = n
            {
                *n = mutate_number(old, arg);
            }
        }
        Mutation::Graft { at, arg } => {
            let Some(p) = pick(at, &|_| true) else { return };
            let donors: Vec<&Place> = all.iter().filter(|d| d.field == p.field && !d.path.is_empty()).collect();
            if donors.is_empty() {
                return;
            }
            let donor = get(manifest, &donors[arg % donors.len()].path).cloned();
            if let (Some(donor), Some(n)) = (donor, node(manifest, &p.path)) {
                *n = donor;
            }
        }
        Mutation::Array { at, arg } => {
            let Some(p) = pick(at, &|v| v.as_array().is_some_and(|a| !a.is_empty())) else { return };
            let Some(Value::Array(a)) = node(manifest, &p.path) else { return };
            let (i, j) = ((arg >> 8) as usize % a.len(), (arg >> 24) as usize % a.len());
            match arg % 5 {
                0 => {
                    a.remove(i);
                }
                1 => {
                    let x = a[i].clone();
                    a.insert(j, x);
                }
                2 => a.swap(i, j),
                3 => a.clear(),
                _ => a.truncate(i),
            }
        }
        Mutation::Text { at, arg } => {
            let Some(p) = pick(at, &|v| v.is_string()) else { return };
            let seen: Vec<String> =
                all.iter().filter_map(|q| get(manifest, &q.path).and_then(Value::as_str)).map(str::to_string).collect();
            let new = if arg % 2 == 0 {
                WORDS[arg / 2 % WORDS.len()].to_string()
            } else {
                seen[arg / 2 % seen.len()].clone()
            };
            if let Some(n) = node(manifest, &p.path) {
                *n = Value::String(new);
            }
        }
        Mutation::Algorithm { at, arg } => {
            let Some(p) = pick(at, &|v| v.get("algo").is_some()) else { return };
            if let Some(n) = node(manifest, &p.path) {
                n["algo"] = serde_json::to_value(ALGOS[arg % ALGOS.len()]).expect("an algorithm is JSON");
            }
        }
        Mutation::Grow { at, arg } => {
            // An axis of an input (and its value) grown to 2^8..2^39: once repaired, the
            // shapes behind it follow, and the memory budget is what refuses the plan.
            let Some(inputs) = manifest["inputs"].as_array() else { return };
            if inputs.is_empty() {
                return;
            }
            let i = at % inputs.len();
            let (Some(value), Some(rank)) = (inputs[i]["value"].as_u64(), inputs[i]["shape"].as_array().map(Vec::len))
            else {
                return;
            };
            if rank == 0 {
                return;
            }
            let j = (at / inputs.len()) % rank;
            let coef = Value::from(1u64 << (8 + arg % 32));
            // Earlier mutations may have made the axis something other than a dimension.
            if let Some(d) = manifest["inputs"][i]["shape"].get_mut(j).and_then(Value::as_object_mut) {
                d.insert("coef".into(), coef.clone());
            }
            if let Some(d) = manifest["values"]
                .get_mut(value as usize)
                .and_then(|v| v["shape"].get_mut(j))
                .and_then(Value::as_object_mut)
            {
                d.insert("coef".into(), coef);
            }
        }
        Mutation::Dtype { at, arg } => {
            // A stored tensor's (or, less often, a value's) element type: f16, f32 by
            // omission or by name, or one no plan tensor has.
            let Some(p) = pick(at, &|v| v.get("shape").is_some() && v.get("name").is_some()) else { return };
            if let Some(Value::Object(n)) = node(manifest, &p.path) {
                match arg % 4 {
                    0 => n.insert("dtype".into(), "F16".into()),
                    1 => n.remove("dtype"),
                    2 => n.insert("dtype".into(), "F32".into()),
                    _ => n.insert("dtype".into(), ["BF16", "I64", "Bool", "f16"][arg / 4 % 4].into()),
                };
            }
        }
        Mutation::Poison { at, arg } => {
            let mut names: Vec<&String> = tensors.keys().collect();
            names.sort();
            if names.is_empty() {
                return;
            }
            let name = names[at % names.len()].clone();
            let data = tensors.get_mut(&name).expect("a listed tensor");
            if !data.is_empty() {
                let i = (arg >> 4) as usize % data.len();
                data[i] = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::MAX, -1.0, 0.0][arg as usize % 6];
            }
        }
    }
}

/// Makes a mutated manifest consistent where it can: input and output shapes of every step
/// re-inferred in schedule order by the operators' rules, inputs declared as their values,
/// stored tensors sized for their kernels, replacements shaped as their base tensors. A
/// manifest that does not deserialise, or a step whose rule fails, is left as it is.
fn repair(manifest: &mut Value) {
    let Ok(mut m) = serde_json::from_value::<Manifest>(manifest.clone()) else { return };
    let nv = m.values.len();
    let nt = m.tensors.len();
    for inp in &mut m.inputs {
        if let Some(v) = m.values.get(inp.value) {
            inp.shape = v.shape.clone();
        }
    }
    let b = m.batch_bindings(1);
    for k in 0..m.steps.len() {
        let step = &m.steps[k];
        if step.output >= nv || step.inputs.iter().any(|&i| i >= nv) {
            return;
        }
        let inputs: Vec<TensorType> = step.inputs.iter().map(|&i| TensorType::f32(m.values[i].shape.clone())).collect();
        let refs: Vec<&TensorType> = inputs.iter().collect();
        let Ok(out) = ops::infer(step.kernel.op(), &refs) else { return };
        let known = |d: &Dim| d.eval(&b).unwrap_or(0);
        let mut sizes: Vec<(usize, usize)> = Vec::new();
        match &step.kernel {
            Kernel::Conv2d { conv, algo, weight, epilogue, lora, switch, adapter, .. } => {
                let x = &inputs[0].shape;
                let c = usize::try_from(conv.out_channels).unwrap_or(0);
                if x.len() == 4 {
                    let s = conv.shape(1, known(&x[2]), known(&x[3]));
                    // Merged on switch, the weight is raw (the im2col packing).
                    let w_algo = if *switch { ConvAlgo::Im2col } else { *algo };
                    sizes.push((*weight, w_algo.packed_len(&s)));
                    if let Some(l) = lora {
                        let a = readi_plan::ops::Conv2dShape { cout: l.rank, ..s };
                        // A raw `A` is PyTorch's layout, the im2col packing.
                        let stored = if l.a_raw { ConvAlgo::Im2col } else { *algo };
                        sizes.extend([(l.a, stored.packed_len(&a)), (l.b, c.saturating_mul(l.rank))]);
                    }
                }
                sizes.extend(epilogue.scale.into_iter().chain(epilogue.shift).map(|t| (t, c)));
                if let Some(a) = adapter {
                    let mc = a.mid.saturating_mul(c);
                    sizes.extend([(a.down, mc), (a.down_bias, a.mid), (a.up, mc), (a.up_bias, c)]);
                }
            }
            Kernel::Linear { linear, weight, epilogue, lora, panels } => {
                let (i, o) = (
                    usize::try_from(linear.in_features).unwrap_or(0),
                    usize::try_from(linear.out_features).unwrap_or(0),
                );
                sizes.push((*weight, if *panels { linear.panel_len().unwrap_or(0) } else { i.saturating_mul(o) }));
                if let Some(l) = lora {
                    sizes.extend([(l.a, i.saturating_mul(l.rank)), (l.b, o.saturating_mul(l.rank))]);
                }
                sizes.extend(epilogue.scale.into_iter().chain(epilogue.shift).map(|t| (t, o)));
            }
            _ => {}
        }
        let output = step.output;
        if matches!(m.values[output].storage, Storage::Slot(_)) {
            m.values[output].shape = out.shape;
        }
        for (t, n) in sizes {
            if t < nt && m.tensors[t].numel() != n {
                m.tensors[t].shape = vec![n];
            }
        }
    }
    for v in &mut m.variants {
        for r in &mut v.replaces {
            if r.base < nt && r.with < nt {
                m.tensors[r.with].shape = m.tensors[r.base].shape.clone();
            }
        }
    }
    if let Ok(v) = serde_json::to_value(&m) {
        *manifest = v;
    }
}

/// The plan file of a (mutated) manifest: each manifest tensor stored under its name with
/// the manifest's shape (its data cut or repeated to fit) and, if the manifest says f16,
/// as f16 (any other type as f32), the checksum computed as the compiler computes it.
fn plan_file(manifest: &Value, tensors: &HashMap<String, Vec<f32>>) -> Vec<u8> {
    let json = manifest.to_string();
    let entries: Vec<(String, Vec<usize>, bool)> = manifest["tensors"]
        .as_array()
        .map(|ts| {
            ts.iter()
                .filter_map(|t| {
                    let name = t["name"].as_str()?.to_string();
                    let shape: Option<Vec<usize>> = t["shape"]
                        .as_array()?
                        .iter()
                        .map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()))
                        .collect();
                    Some((name, shape?, t["dtype"] == "F16"))
                })
                .collect()
        })
        .unwrap_or_default();
    let stored: Vec<_> = entries
        .into_iter()
        .filter_map(|(name, shape, half)| {
            let numel = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d)).filter(|&n| n <= 1 << 22)?;
            let source = tensors.get(&name).filter(|d| !d.is_empty()).map_or(&[0.5f32][..], Vec::as_slice);
            let values = source.iter().cycle().take(numel);
            let (dtype, bytes): (_, Vec<u8>) = if half {
                (safetensors::Dtype::F16, values.flat_map(|&v| half::f16::from_f32(v).to_le_bytes()).collect())
            } else {
                (safetensors::Dtype::F32, values.flat_map(|v| v.to_le_bytes()).collect())
            };
            Some((name, shape, dtype, bytes))
        })
        .collect();
    common::typed_plan_file_bytes(&readi_plan::format::FORMAT_VERSION.to_string(), json, &stored)
}

/// How far a case got.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Reached {
    /// Loading refused the plan.
    Refused,
    /// It loaded; binding or every run refused it.
    Failed,
    /// A run succeeded.
    Ran,
}

/// Fails the case if `text`, printed to a terminal, would carry control characters
/// (escape sequences) from the plan: names from plans are printed escaped.
fn printable(what: &str, text: &str) {
    if let Some(c) = text.chars().find(|&c| c.is_control() && c != '\n') {
        panic!("{what} holds the raw control character {c:?}: {text:?}");
    }
}

/// Loads, prints, binds and runs a plan file; a refusal is fine, a panic is not.
fn exercise(path: &std::path::Path) -> Reached {
    let plan = match Plan::load(path) {
        Ok(plan) => plan,
        Err(e) => {
            printable("the load error", &e.to_string());
            if std::env::var_os("PLAN_FUZZ_VERBOSE").is_some() {
                eprintln!("refused: {e}");
            }
            return Reached::Refused;
        }
    };
    printable("the inspect listing", &readi::inspect::plan(&plan, path, true));
    let keys: Vec<String> = plan.variant_keys().take(3).map(str::to_string).collect();
    let plan = Arc::new(plan);
    let Ok(mut session) = session(Arc::clone(&plan)) else { return Reached::Failed };
    // Bound first, under the budget (which counts the inputs): the inputs below are made
    // only for a plan whose footprint at batch 1 fits, as `readi bench` does.
    if let Err(e) = session.bind_batch(1) {
        printable("the bind error", &e.to_string());
        return Reached::Failed;
    }
    let inputs: Vec<(String, Vec<usize>, Vec<f32>)> = plan
        .manifest
        .input_shapes(1)
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            (name.to_string(), shape, (0..n).map(|k| ((k * 7919) % 255) as f32 / 127.0 - 1.0).collect())
        })
        .collect();
    let given: Vec<Input<'_>> = inputs.iter().map(|(name, shape, data)| Input { name, data, shape }).collect();
    let mut reached = Reached::Failed;
    for key in std::iter::once("base").chain(keys.iter().map(String::as_str)) {
        match session.set_variant(key).map_err(|e| e.to_string()) {
            Ok(_) => match session.run(&given) {
                Ok(_) => reached = Reached::Ran,
                Err(e) => printable("the run error", &e.to_string()),
            },
            Err(e) => printable("the switch error", &e),
        }
    }
    reached
}

fn session(plan: Arc<Plan>) -> Result<Session, readi_runtime::exec::RunError> {
    Session::with_options(plan, SessionOptions::default().threads(1).max_memory(BUDGET))
}

/// Runs a case on its own thread and fails it when it takes longer than [`HANG`]; the
/// plan file of a failing case is kept.
fn exercise_in_time(path: std::path::PathBuf, seed: &str) -> Reached {
    let shown = path.display().to_string();
    let (tx, rx) = std::sync::mpsc::channel();
    let worker = std::thread::spawn(move || {
        let _ = tx.send(exercise(&path));
    });
    match rx.recv_timeout(HANG) {
        Ok(reached) => reached,
        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
            panic!("a mutant of {seed} did not finish in {HANG:?}; its plan: {shown}")
        }
        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => match worker.join() {
            Err(panic) => {
                eprintln!("a mutant of {seed} panicked; its plan: {shown}");
                std::panic::resume_unwind(panic)
            }
            Ok(()) => unreachable!("the worker sends before it ends"),
        },
    }
}

fn cases() -> u32 {
    std::env::var("PLAN_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(1024)
}

/// Builds a case's plan file and exercises it.
fn case(seed: usize, edits: &[Mutation], fix: bool) -> Reached {
    let s = &seeds()[seed];
    let (mut manifest, mut tensors) = (s.manifest.clone(), s.tensors.clone());
    for m in edits {
        apply(m, &mut manifest, &mut tensors);
    }
    if fix {
        repair(&mut manifest);
    }
    static N: AtomicUsize = AtomicUsize::new(0);
    let path = std::env::temp_dir().join(format!(
        "readi-plan-fuzz-{}-{}.plan",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::write(&path, plan_file(&manifest, &tensors)).expect("write the plan file");
    let reached = exercise_in_time(path.clone(), s.name);
    let _ = std::fs::remove_file(&path);
    reached
}

/// The unmutated seeds load, bind and run: otherwise every case would be refused and
/// the fuzzer would test nothing.
#[test]
fn seeds_run() {
    for (i, s) in seeds().iter().enumerate() {
        assert!(matches!(case(i, &[], false), Reached::Ran), "seed {} does not run", s.name);
        assert!(matches!(case(i, &[], true), Reached::Ran), "seed {} does not run once repaired", s.name);
    }
}

#[test]
fn mutated_plans_are_refused_or_run() {
    let config = ProptestConfig {
        cases: cases(),
        failure_persistence: Some(Box::new(FileFailurePersistence::Direct("tests/plan_fuzz.proptest-regressions"))),
        ..ProptestConfig::default()
    };
    let counts: [AtomicUsize; 3] = Default::default();
    let strategy = (0..SPECS.len(), prop::collection::vec(mutation(), 1..6), any::<bool>());
    let result = proptest::test_runner::TestRunner::new(config).run(&strategy, |(seed, edits, fix)| {
        counts[case(seed, &edits, fix) as usize].fetch_add(1, Ordering::Relaxed);
        Ok(())
    });
    if let Err(e) = result {
        panic!("{e}");
    }
    let [refused, failed, ran] = counts.map(|c| c.into_inner());
    eprintln!("plan fuzz: {refused} refused at load, {failed} refused at bind or run, {ran} ran");
    // The mutations are not all caught by the first check: a good part of the cases get
    // past loading (the repaired ones mostly), so the kernels and the budget are reached.
    let total = refused + failed + ran;
    assert!(ran * 10 >= total, "only {ran} of {total} cases ran: the mutations are too blunt to test the runtime");
}
