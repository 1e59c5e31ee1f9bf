//! Variant switching and the cost of adaptation, on bevfusion_tiny with 12 variants and on
//! ResNet-18 (224x224), with seeded weights. Prints one table; every ratio is measured in
//! this run against its baseline in this run.
//!
//!     cargo bench --bench variants            (add `-- --quick` for fewer runs)
//!
//! * switch latency: `VariantSwitch::set` by key, median over many switches, and the tail
//!   (p99) of single switches;
//! * the first run after a switch against a steady run of the same variant;
//! * choosing the variant from a frame (`Plan::select`) against a run;
//! * adapted-plan latency against the base plan (no adaptation), LoRA merged and as a
//!   branch, and without the adapter rules (tuning and merged LoRA fold into the base
//!   schedule; adapters add layers);
//! * plan size against the base plus the sum of the variants' deltas;
//! * a melded variant's latency against its parts';
//! * the ResNet-18 case: LoRA r = 4 on the 3x3 convs of layer3 and layer4, tuned
//!   BatchNorm and fc: bytes per variant and latency against the base, merged and as a branch;
//! * merge on switch under `--lora auto --memory-budget 3` (the default switch budget), on both
//!   models: bytes per variant, latency against the base, the re-merge of a switch timed
//!   directly (every layer merged on switch, `kernels::merge::switch_pack`, p50/p99), and
//!   the first run after a switch minus a steady run (p50/p99);
//! * reloading a full model copy from disk (read + checksum), for comparison.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Instant;

#[path = "common.rs"]
mod common;

use common::inputs;
use readi::rounds::Rounds;
use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions, LoraMode};
use readi_compiler::passes::{self, Options};
use readi_grammar::diag::FileId;
use readi_runtime::conditions;
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::Plan;

fn module(src: &str, overrides: &[(&str, &str)]) -> Module {
    let opts = Options::with_overrides(overrides);
    passes::run(FileId(0), src, &opts).module.expect("the model checks")
}

fn plan(m: &Module, variants: usize, lora: LoraMode) -> Arc<Plan> {
    let weights = backend::seeded_weights(&m.graph, 1);
    let keys = m.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    let keys: Vec<String> =
        round_robin(keys.into_iter().map(|k| k.to_string()).collect()).into_iter().take(variants).collect();
    assert_eq!(keys.len(), variants, "the spec declares enough variants");
    let sources = backend::seeded_variants(m, &keys, 10);
    let opts = CompileOptions { lora, ..Default::default() };
    Arc::new(backend::compile_variants(m, &weights, "seeded", &sources, &opts).expect("compiles").0)
}

/// The keys taken one axis at a time (`fog=0.01`, `snow=0.5`, `gamma=0.25`, ...), so that
/// the first few cover every axis and both modalities' scoped rules.
fn round_robin(keys: Vec<String>) -> Vec<String> {
    let mut axes: Vec<(String, std::collections::VecDeque<String>)> = Vec::new();
    for k in keys {
        let axis = k.split('=').next().unwrap_or("").to_string();
        match axes.iter_mut().find(|(a, _)| *a == axis) {
            Some((_, q)) => q.push_back(k),
            None => axes.push((axis, std::collections::VecDeque::from([k]))),
        }
    }
    let mut out = Vec::new();
    while axes.iter().any(|(_, q)| !q.is_empty()) {
        for (_, q) in &mut axes {
            out.extend(q.pop_front());
        }
    }
    out
}

/// The spec without its `adapter` rules: tuning and LoRA only, which fold away.
fn without_adapters(src: &str) -> String {
    src.lines().filter(|l| !l.trim_start().starts_with("adapter ")).collect::<Vec<_>>().join("\n")
}

/// ResNet-18 with the adaptation the issue measured: LoRA on the 3x3 convs of the last two
/// stages, BatchNorm and fc tuned, no adapters.
fn lora_resnet18() -> String {
    let src = include_str!("../models/resnet18.readi");
    let start = src.find("adapt {").expect("resnet18.readi has an adapt section");
    let end = start + src[start..].find("\n}").expect("the section ends") + 2;
    let rules = "adapt {\n  tune batchnorm\n  tune fc\n  lora rank=4 alpha=8 on layer3.*.{conv1,conv2}, layer4.*.{conv1,conv2}\n}";
    format!("{}{rules}{}", &src[..start], &src[end..])
}

/// The plan's tensor bytes: the base's, and what the variants store beyond it.
fn plan_size(name: &str, p: &Plan) {
    let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
    let mf = &p.manifest;
    let with: std::collections::HashSet<usize> =
        mf.variants.iter().flat_map(|v| v.replaces.iter().map(|r| r.with)).collect();
    let base_bytes: usize = (0..mf.tensors.len()).filter(|t| !with.contains(t)).map(|t| mf.tensors[t].bytes()).sum();
    let deltas: usize = mf.variants.iter().flat_map(|v| v.replaces.iter().map(|r| mf.tensors[r.with].bytes())).sum();
    let n = mf.variants.len().max(1);
    println!(
        "plan size ({name}): {:.2} MiB = base {:.2} MiB + {:.2} MiB stored for {} variants (sum of deltas {:.2} MiB; one variant {:.1}% of the base)",
        mib(p.tensor_bytes()),
        mib(base_bytes),
        mib(p.tensor_bytes() - base_bytes),
        mf.variants.len(),
        mib(deltas),
        100.0 * deltas as f64 / n as f64 / base_bytes as f64
    );
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

struct Runner {
    session: Session,
    data: Vec<(String, Vec<usize>, Vec<f32>)>,
}

impl Runner {
    fn new(plan: Arc<Plan>) -> Runner {
        let data = inputs(&plan);
        Runner { session: Session::new(plan, 2).expect("session"), data }
    }
    fn run(&mut self) -> f64 {
        let given: Vec<Input<'_>> = self.data.iter().map(|(n, s, d)| Input { name: n, data: d, shape: s }).collect();
        let t = Instant::now();
        self.session.run(&given).expect("run");
        t.elapsed().as_secs_f64() * 1e3
    }
}

/// Several plans timed in alternating rounds ([`Rounds`]) after three warm-up runs each.
fn alternating(runners: &mut [(&str, Runner)], rounds: usize) -> Rounds {
    for (_, r) in runners.iter_mut() {
        for _ in 0..3 {
            r.run();
        }
    }
    let mut timers: Vec<_> = runners.iter_mut().map(|(_, r)| move || Ok::<_, Infallible>(r.run())).collect();
    let mut timers: Vec<&mut dyn FnMut() -> Result<f64, Infallible>> = timers.iter_mut().map(|t| t as _).collect();
    let Ok(rounds) = Rounds::run(&mut timers, rounds);
    rounds
}

/// Latency of a variant against the base plan: LoRA merged, as a branch, and without the
/// spec's adapter rules (tuning and merged LoRA only), in alternating rounds ([`Rounds`]).
fn adaptation_cost(
    src: &str,
    base: &Arc<Plan>,
    merged: &Arc<Plan>,
    branch: &Arc<Plan>,
    variants: usize,
    rounds: usize,
) {
    let key = merged.variant_key(1).to_string();
    let folded = plan(&module(&without_adapters(src), &[]), variants, LoraMode::Merge);
    let mut runners = vec![
        ("base plan (no adaptation)", Runner::new(base.clone())),
        ("variant, LoRA merged", Runner::new(merged.clone())),
        ("variant, LoRA branch", Runner::new(branch.clone())),
        ("variant, tune + LoRA merged", Runner::new(folded)),
    ];
    for (_, r) in &mut runners[1..] {
        r.session.set_variant(&key).expect("key");
    }
    let t = alternating(&mut runners, rounds);
    for (i, (name, _)) in runners.iter().enumerate() {
        println!("{name:<28} {:7.2} ms  {:+6.1}% vs base", t.median(i), 100.0 * (t.ratio(|r| r[i] / r[0]) - 1.0));
    }
}

/// A percentile of `v` (0..=100).
fn percentile(mut v: Vec<f64>, p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p / 100.0).round() as usize]
}

/// `--lora auto --memory-budget 3` (the default switch budget; with `half`,
/// `--variant-f16`) on `m` with `variants` variants: what the strategy chose, bytes per
/// variant, latency against `base`, and the switch.
fn merge_on_switch(m: &Module, base: &Arc<Plan>, variants: usize, rounds: usize, quick: bool, half: bool) {
    use readi_runtime::kernels::{Lora, conv, merge};
    use readi_runtime::plan::Kernel;
    let weights = backend::seeded_weights(&m.graph, 1);
    let keys = m.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    let keys: Vec<String> =
        round_robin(keys.into_iter().map(|k| k.to_string()).collect()).into_iter().take(variants).collect();
    let sources = backend::seeded_variants(m, &keys, 10);
    let opts = CompileOptions {
        lora: LoraMode::Auto,
        memory_budget: Some(3.0),
        switch_budget: None,
        variant_f16: half,
        ..Default::default()
    };
    let (p, warnings, s) = backend::compile_explained(m, &weights, "seeded", &sources, &opts).expect("compiles");
    let p = Arc::new(p);
    let s = s.expect("a strategy");
    if let Some(h) = backend::half_summary(m, &weights, "seeded", &sources, &opts, p.clone(), Some(&s))
        .expect("compiles without f16")
    {
        println!("{}", h.line());
    }
    let count = |f: &dyn Fn(&readi_compiler::passes::choose_strategy::LayerChoice) -> bool| {
        s.layers.iter().filter(|l| f(l)).count()
    };
    println!(
        "strategy: {} layers merged on switch ({:.3} ms predicted per switch of a budget of {:.3} ms, working copies \
         {:.2} MiB per session), {} branch, {} merged; {:.2}% per variant{}",
        count(&|l| l.switch),
        s.switch_ms(),
        s.switch_budget_ms,
        s.working_bytes() as f64 / (1024.0 * 1024.0),
        count(&|l| !l.switch && l.lora == Some(LoraMode::Branch)),
        count(&|l| !l.switch && l.lora != Some(LoraMode::Branch)),
        s.max_pct(),
        if warnings.0.is_empty() { String::new() } else { format!(" ({})", warnings.0[0].message) }
    );
    plan_size("merge on switch", &p);
    let mut runners = vec![("base", Runner::new(base.clone())), ("variant", Runner::new(p.clone()))];
    runners[1].1.session.set_variant(p.variant_key(1)).expect("key");
    let t = alternating(&mut runners, rounds);
    let ratio = t.ratio(|r| r[1] / r[0]);
    println!("  variant {:.2} ms against the base plan {:.2} ms: ratio {ratio:.3}", t.median(1), t.median(0));

    // The re-merge a switch does, timed directly: every layer merged on switch, from the
    // plan's own raw tensors, into working copies like the session's.
    let mf = &p.manifest;
    type Layer = (conv::Conv2dShape, conv::ConvAlgo, usize, Option<(usize, usize, usize)>);
    let mut layers: Vec<Layer> = Vec::new();
    for step in &mf.steps {
        if let Kernel::Conv2d { conv: c, algo, weight, lora, switch: true, .. } = &step.kernel {
            let x = &mf.values[step.inputs[0]].shape;
            let known = |d: &readi_plan::Dim| d.as_known().map_or(1, |v| v as usize);
            let sh = c.shape(1, known(&x[2]), known(&x[3]));
            layers.push((sh, *algo, *weight, lora.map(|l| (l.a, l.b, l.rank))));
        }
    }
    let tmp_len = layers.iter().map(|(sh, a, _, l)| merge::switch_tmp_len(sh, *a, l.is_some())).max().unwrap_or(0);
    let mut tmp = vec![0.0f32; tmp_len];
    let mut working: Vec<Vec<f32>> =
        layers.iter().map(|(sh, a, _, _)| vec![0.0f32; conv::packed_weight_len(sh, *a)]).collect();
    // And the f16 tensors of variant 1 decoded into copies like the session's.
    use half::slice::HalfFloatSliceExt;
    let halves: Vec<usize> = mf.variants[0]
        .replaces
        .iter()
        .map(|r| r.with)
        .filter(|&t| mf.tensors[t].dtype == readi_plan::DType::F16)
        .collect();
    let mut decoded: Vec<Vec<f32>> = halves.iter().map(|&t| vec![0.0f32; mf.tensors[t].numel()]).collect();
    let n = if quick { 50 } else { 300 };
    let remerge: Vec<f64> = (0..n)
        .map(|_| {
            let t = Instant::now();
            for ((sh, a, w, l), out) in layers.iter().zip(&mut working) {
                let l = l.map(|(la, lb, rank)| Lora { a: p.tensor(la), b: p.tensor(lb), rank });
                merge::switch_pack(sh, *a, p.tensor(*w), l.as_ref(), &mut tmp, out);
            }
            for (&h, out) in halves.iter().zip(&mut decoded) {
                p.tensor_f16(h).expect("an f16 tensor").convert_to_f32_slice(out);
            }
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    println!(
        "  re-merge ({} layers) and f16 decode ({} tensors) per switch, timed directly: p50 {:.3} ms, p99 {:.3} ms",
        layers.len(),
        halves.len(),
        percentile(remerge.clone(), 50.0),
        percentile(remerge, 99.0)
    );
    // The first run after a switch against a steady run, alternating: switch, run, run.
    let mut r = Runner::new(p.clone());
    let (a, b) = (p.variant_key(1).to_string(), p.variant_key(2.min(p.variant_count() - 1)).to_string());
    for _ in 0..3 {
        r.run();
    }
    let (mut first, mut steady) = (Vec::new(), Vec::new());
    for i in 0..if quick { 20 } else { 100 } {
        r.session.set_variant(if i % 2 == 0 { &a } else { &b }).expect("key");
        first.push(r.run());
        steady.push(r.run());
    }
    let extra: Vec<f64> = first.iter().zip(&steady).map(|(f, s)| f - s).collect();
    println!(
        "  first run after a switch minus the steady run after it: p50 {:+.3} ms, p99 {:+.3} ms (steady p50 {:.2} ms, \
         first/steady {:.3})",
        percentile(extra.clone(), 50.0),
        percentile(extra, 99.0),
        percentile(steady.clone(), 50.0),
        percentile(first.clone(), 50.0) / percentile(steady, 50.0)
    );
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    // Alternating rounds of one run per plan.
    let rounds = if quick { 9 } else { 50 };
    let mib = |b: usize| b as f64 / (1024.0 * 1024.0);

    println!("== bevfusion_tiny, 12 variants, 2 threads ==");
    let m = module(include_str!("../models/bevfusion_tiny.readi"), &[]);
    let base = plan(&m, 0, LoraMode::Merge);
    let merged = plan(&m, 12, LoraMode::Merge);
    let branch = plan(&m, 12, LoraMode::Branch);
    let key = merged.variant_key(1).to_string();
    let other = merged.variant_key(2).to_string();

    // Switch latency: a handle, as another thread would hold it.
    let runner = Runner::new(merged.clone());
    let switch = runner.session.switch_handle();
    let keys: Vec<String> = (1..=12).map(|i| merged.variant_key(i).to_string()).collect();
    let mut lat = Vec::new();
    for round in 0..if quick { 20 } else { 200 } {
        let t = Instant::now();
        for i in 0..500 {
            switch.set(&keys[(round + i) % keys.len()]).expect("known key");
        }
        lat.push(t.elapsed().as_secs_f64() * 1e9 / 500.0);
    }
    println!("switch latency (set by key, median of batches of 500): {:.0} ns", median(lat));
    // One switch at a time, for the tail: each timed alone (the timer's own cost included).
    let mut one: Vec<f64> = (0..if quick { 2_000 } else { 20_000 })
        .map(|i| {
            let t = Instant::now();
            switch.set(&keys[i % keys.len()]).expect("known key");
            t.elapsed().as_secs_f64() * 1e9
        })
        .collect();
    one.sort_by(f64::total_cmp);
    println!(
        "switch latency, single switches: p50 {:.0} ns, p99 {:.0} ns, max {:.0} ns",
        one[one.len() / 2],
        one[one.len() * 99 / 100],
        one[one.len() - 1]
    );

    // The first run after a switch against a steady run.
    let mut r = runner;
    for _ in 0..3 {
        r.run();
    }
    let (mut first, mut steady) = (Vec::new(), Vec::new());
    for _ in 0..rounds {
        r.session.set_variant(&other).expect("key");
        r.run();
        r.session.set_variant(&key).expect("key");
        first.push(r.run());
        steady.push(r.run());
    }
    let (first, steady) = (median(first), median(steady));
    println!("first run after a switch {first:.2} ms, steady run {steady:.2} ms: ratio {:.3}", first / steady);

    // Choosing the variant from the frame: the spec's statistics (brightness and Laplacian
    // variance of the six camera views, density of the lidar grid) and metadata.
    // A lidar grid with 1% of its cells occupied (a clear-weather density), dense fog.
    let frame: Vec<(String, Vec<usize>, Vec<f32>)> = r
        .data
        .iter()
        .map(|(n, s, d)| {
            let sparse = n.starts_with("lidar");
            let d = d.iter().enumerate().map(|(i, &v)| if sparse && i % 100 != 0 { 0.0 } else { v }).collect();
            (n.clone(), s.clone(), d)
        })
        .collect();
    let given: Vec<Input<'_>> = frame.iter().map(|(n, s, d)| Input { name: n, data: d, shape: s }).collect();
    let meta = vec![("fog_density".to_string(), 0.05)];
    let mut sel = Vec::new();
    for _ in 0..if quick { 10 } else { 50 } {
        let t = Instant::now();
        std::hint::black_box(conditions::select(&merged, &given, &meta).expect("selects"));
        sel.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let sel = median(sel);
    println!(
        "variant selection from the frame (3 statistics + metadata): {:.3} ms = {:.2}% of a steady run",
        sel,
        100.0 * sel / steady
    );

    adaptation_cost(include_str!("../models/bevfusion_tiny.readi"), &base, &merged, &branch, 12, rounds);

    for (name, p) in [("merged", &merged), ("branch", &branch)] {
        plan_size(name, p);
    }
    println!("-- bevfusion_tiny, --lora auto --memory-budget 3, 12 variants --");
    merge_on_switch(&m, &base, 12, rounds, quick, false);

    // A melded variant against its parts: the meld stores its own values, never extra steps.
    let meld = "fog=0.06+gamma=0.5";
    let melded = {
        let weights = backend::seeded_weights(&m.graph, 1);
        let keys = ["fog=0.06".to_string(), "gamma=0.5".to_string()];
        let sources = backend::seeded_variants(&m, &keys, 10);
        let opts = CompileOptions { melds: vec![meld.to_string()], ..Default::default() };
        Arc::new(backend::compile_variants(&m, &weights, "seeded", &sources, &opts).expect("melds").0)
    };
    let mut runners: Vec<(&str, Runner)> =
        ["fog=0.06", "gamma=0.5", meld].iter().map(|k| (*k, Runner::new(melded.clone()))).collect();
    for (k, r) in &mut runners {
        r.session.set_variant(k).expect("key");
    }
    let t = alternating(&mut runners, rounds);
    println!(
        "melded variant {meld}: {:.2} ms against its parts {:.2} ms and {:.2} ms (ratio to the slower part {:.3})",
        t.median(2),
        t.median(0),
        t.median(1),
        t.ratio(|r| r[2] / r[0].max(r[1]))
    );

    println!("\n== resnet18 224x224, 4 variants, 2 threads ==");
    let m = module(include_str!("../models/resnet18.readi"), &[]);
    let base = plan(&m, 0, LoraMode::Merge);
    let merged = plan(&m, 4, LoraMode::Merge);
    let branch = plan(&m, 4, LoraMode::Branch);
    adaptation_cost(include_str!("../models/resnet18.readi"), &base, &merged, &branch, 4, rounds);

    // The measurement: PEFT-style LoRA (r = 4, alpha = 8) on every 3x3 conv of layer3
    // and layer4, tuned BatchNorm and fc, two variants.
    println!("\n== resnet18 224x224, LoRA r=4 on layer3/layer4 3x3 convs + tuned BN and fc, 2 variants ==");
    let src = lora_resnet18();
    let m = module(&src, &[]);
    let base = plan(&m, 0, LoraMode::Merge);
    for (name, lora) in [("merged", LoraMode::Merge), ("branch", LoraMode::Branch)] {
        let p = plan(&m, 2, lora);
        plan_size(name, &p);
        let mut runners = vec![("base", Runner::new(base.clone())), ("variant", Runner::new(p.clone()))];
        runners[1].1.session.set_variant(p.variant_key(1)).expect("key");
        let t = alternating(&mut runners, rounds);
        let ratio = t.ratio(|r| r[1] / r[0]);
        println!(
            "  variant ({name}) {:.2} ms against the base plan {:.2} ms: ratio {ratio:.3}",
            t.median(1),
            t.median(0)
        );
    }
    println!("-- --lora auto --memory-budget 3 --");
    merge_on_switch(&m, &base, 2, rounds, quick, false);
    println!("-- --lora auto --memory-budget 3 --variant-f16 --");
    merge_on_switch(&m, &base, 2, rounds, quick, true);

    // Reloading a whole model copy: what a system without variants does on a switch.
    let path = std::env::temp_dir().join(format!("readi-bench-{}.plan", std::process::id()));
    base.write(&path).expect("write");
    let mut reload = Vec::new();
    for _ in 0..if quick { 3 } else { 10 } {
        let t = Instant::now();
        let p = Plan::load(&path).expect("load");
        std::hint::black_box(&p);
        reload.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let _ = std::fs::remove_file(&path);
    println!(
        "reload of the {:.1} MiB base plan from disk (map + checksum of every byte, page cache warm): {:.1} ms",
        mib(base.tensor_bytes()),
        median(reload)
    );
}
