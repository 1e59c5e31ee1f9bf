//! Latency of switching the active variant, on a plan with 12 variants.
//!
//! `cargo run --release -p readi-runtime --example switch_latency`
//!
//! Times 100,000 single switches (`VariantSwitch::set` by key, and `set_index`), each
//! between two clock reads, and prints the median with the clock's own cost (the median
//! of empty timings) subtracted; then the mean over a tight loop of switches; then `set`
//! again while another thread runs the session continuously.

use std::hint::black_box;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use readi_plan::ops::{LayerNorm, Linear};
use readi_plan::{Dim, VariantKey};
use readi_runtime::exec::{Input, Session, VariantSwitch};
use readi_runtime::plan::{
    EpilogueSpec, FORMAT_VERSION, InputSpec, Kernel, Manifest, OutputSpec, Plan, Replacement, Step, Storage,
    TensorSpec, ValueSpec, VariantTable,
};
use readi_runtime::testdata::data;

const SAMPLES: usize = 100_000;
const FIN: usize = 256;
const FOUT: usize = 256;

/// The keys of the t-READi conditions: fog densities, exposure gammas, missing sensors.
const KEYS: [&str; 12] = [
    "fog=0.01",
    "fog=0.03",
    "fog=0.05",
    "fog=0.1",
    "fog=0.15",
    "gamma=0.25",
    "gamma=0.5",
    "gamma=2",
    "gamma=4",
    "blur=5",
    "missing=camera",
    "missing=lidar",
];

/// `y = layernorm(relu(x W + b))` over `x: [N, 256]`; every variant replaces W, b and
/// the layernorm's weight and bias.
fn plan() -> Plan {
    let mut specs = Vec::new();
    let mut tensors = Vec::new();
    let mut add = |name: String, shape: Vec<usize>, seed: u64| {
        tensors.push(data(shape.iter().product(), seed));
        specs.push(TensorSpec::f32(name, shape));
        specs.len() - 1
    };
    let named =
        [("fc.weight@t", vec![FIN, FOUT]), ("fc.bias", vec![FOUT]), ("ln.weight", vec![FOUT]), ("ln.bias", vec![FOUT])];
    let base: Vec<usize> =
        named.iter().enumerate().map(|(i, (name, shape))| add(name.to_string(), shape.clone(), i as u64)).collect();
    let mut variants = Vec::new();
    for (v, key) in KEYS.iter().enumerate() {
        let mut replaces = Vec::new();
        for (i, (&b, (name, shape))) in base.iter().zip(&named).enumerate() {
            let with = add(format!("{name}~{key}"), shape.clone(), (100 + 10 * v + i) as u64);
            replaces.push(Replacement { base: b, with, added: false });
        }
        variants.push(VariantTable {
            key: VariantKey::parse(key).expect("a valid key"),
            replaces,
            tuned_elements: 0,
            added_elements: 0,
            fallback: Vec::new(),
            scopes: Vec::new(),
        });
    }
    let n = |d: usize| vec![Dim::symbol("N"), Dim::from(d)];
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "switch-latency".into(),
        model_params: Vec::new(),
        symbols: vec!["N".into()],
        inputs: vec![InputSpec { name: "x".into(), shape: n(FIN), modality: None, optional: false, value: 0 }],
        outputs: vec![OutputSpec::f32("y", 2)],
        values: vec![
            ValueSpec { shape: n(FIN), storage: Storage::Input(0) },
            ValueSpec { shape: n(FOUT), storage: Storage::Slot(0) },
            ValueSpec { shape: n(FOUT), storage: Storage::Slot(1) },
        ],
        steps: vec![
            Step {
                path: "fc".into(),
                kernel: Kernel::Linear {
                    linear: Linear { in_features: FIN as i64, out_features: FOUT as i64 },
                    weight: base[0],
                    epilogue: EpilogueSpec {
                        scale: None,
                        shift: Some(base[1]),
                        act: Some(readi_plan::ops::Activation::Relu),
                        bn: None,
                    },
                    lora: None,
                    panels: false,
                },
                inputs: vec![0],
                output: 1,
            },
            Step {
                path: "ln".into(),
                kernel: Kernel::LayerNorm {
                    norm: LayerNorm { features: FOUT as i64, eps: 1e-5, affine: true },
                    weight: Some(base[2]),
                    bias: Some(base[3]),
                },
                inputs: vec![1],
                output: 2,
            },
        ],
        slots: 2,
        tensors: specs,
        params: Vec::new(),
        variants,
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, tensors).expect("a valid plan")
}

fn median(mut v: Vec<u64>) -> u64 {
    v.sort_unstable();
    v[v.len() / 2]
}

/// Median and 99th percentile nanoseconds of `f` timed alone, less the clock's median
/// cost (also returned).
fn timed(mut f: impl FnMut(usize)) -> (u64, u64, u64) {
    let clock = median(
        (0..SAMPLES)
            .map(|_| {
                let t = Instant::now();
                black_box(());
                t.elapsed().as_nanos() as u64
            })
            .collect(),
    );
    let mut samples: Vec<u64> = (0..SAMPLES)
        .map(|i| {
            let t = Instant::now();
            f(i);
            (t.elapsed().as_nanos() as u64).saturating_sub(clock)
        })
        .collect();
    samples.sort_unstable();
    (samples[samples.len() / 2], samples[samples.len() * 99 / 100], clock)
}

/// Mean nanoseconds per call over a tight loop.
fn looped(mut f: impl FnMut(usize)) -> f64 {
    let t = Instant::now();
    for i in 0..SAMPLES {
        f(i);
    }
    t.elapsed().as_nanos() as f64 / SAMPLES as f64
}

fn report(what: &str, handle: &VariantSwitch) {
    let keys: Vec<&str> = KEYS.to_vec();
    let set_key = |i: usize| handle.set(black_box(keys[i % keys.len()])).expect("known key");
    let set_index = |i: usize| handle.set_index(black_box(1 + i % keys.len())).expect("in range");
    let (key_med, key_p99, clock) = timed(set_key);
    let (index_med, index_p99, _) = timed(set_index);
    let (key_mean, index_mean) = (looped(set_key), looped(set_index));
    println!("{what} (clock read: {clock} ns, subtracted):");
    println!("  set(key):   median {key_med} ns, p99 {key_p99} ns; mean in a loop {key_mean:.1} ns");
    println!("  set_index:  median {index_med} ns, p99 {index_p99} ns; mean in a loop {index_mean:.1} ns");
}

fn main() {
    let plan = Arc::new(plan());
    println!("plan: {} variants besides the base, {} switches per measurement", plan.variant_count() - 1, SAMPLES);
    let mut session = Session::new(Arc::clone(&plan), 2).expect("session");
    let handle = session.switch_handle();
    report("idle session", &handle);

    let stop = Arc::new(AtomicBool::new(false));
    let runner = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            let x = data(8 * FIN, 7);
            let mut runs = 0u64;
            let start = Instant::now();
            while !stop.load(Ordering::Relaxed) {
                session.run(&[Input { name: "x", data: &x, shape: &[8, FIN] }]).expect("runs");
                runs += 1;
            }
            (runs, start.elapsed())
        })
    };
    report("while another thread runs", &handle);
    stop.store(true, Ordering::Relaxed);
    let (runs, took) = runner.join().expect("runner");
    println!("(the runner made {runs} runs, {:.1} us each)", took.as_secs_f64() * 1e6 / runs as f64);
}
