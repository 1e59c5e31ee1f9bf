//! `readi demo`: the whole story on the embedded BEVFusion-tiny model, with nothing to
//! download. The spec is checked and compiled with seeded weights and a dozen seeded
//! variants (fog levels, under-exposure, a lost lidar, and a melded fog + dark variant);
//! then a simulated drive runs frame by frame while conditions change — clear, fog rising,
//! dusk on top of fog, a dark camera, the lidar lost, clear again — and each frame's
//! variant is chosen from the sensor data and the weather metadata by the spec's selectors.
//! `readi demo --model bevfusion` does the same with the paper's network ([`bevfusion`]).

use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use readi_compiler::Module;
use readi_compiler::backend::{self, CompileOptions};
use readi_compiler::passes::{self, Options};
use readi_compiler::print;
use readi_runtime::conditions;
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::Plan;

use super::frontend::Frontend;

mod bevfusion;
mod scene;

/// Which model `readi demo` drives.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DemoModel {
    /// models/bevfusion_tiny.readi: small, a frame in milliseconds.
    #[default]
    Tiny,
    /// models/bevfusion.readi at a demo size: a sweep and six views to boxes.
    Bevfusion,
}

/// The embedded model.
pub const MODEL: (&str, &str) = ("models/bevfusion_tiny.readi", include_str!("../../../models/bevfusion_tiny.readi"));

/// The variants the demo compiles: every fog level, two exposures, the lost lidar.
const VARIANTS: &[&str] = &[
    "fog=0.01",
    "fog=0.02",
    "fog=0.03",
    "fog=0.06",
    "fog=0.1",
    "fog=0.12",
    "fog=0.15",
    "gamma=0.25",
    "gamma=0.5",
    "missing=lidar",
];
/// Combined conditions, melded by the spec's rule (camera 0.8, lidar 0.2).
const MELDS: &[&str] = &["fog=0.12+gamma=0.5"];

/// One stretch of the drive.
struct Scene {
    what: &'static str,
    /// The weather service's fog density (the `fog` selector reads it).
    fog: f64,
    /// Camera exposure gamma (below 1 under-exposed), applied by `readi simulate`'s camera
    /// model: pixel `v` becomes `v^(1/gamma)`.
    gamma: f32,
    lidar: bool,
}

const DRIVE: &[Scene] = &[
    Scene { what: "clear", fog: 0.0, gamma: 1.0, lidar: true },
    Scene { what: "light fog", fog: 0.02, gamma: 1.0, lidar: true },
    Scene { what: "fog rising", fog: 0.065, gamma: 1.0, lidar: true },
    Scene { what: "dense fog", fog: 0.12, gamma: 1.0, lidar: true },
    Scene { what: "dusk in dense fog", fog: 0.12, gamma: 0.5, lidar: true },
    Scene { what: "fog lifts, tunnel: dark", fog: 0.0, gamma: 0.25, lidar: true },
    Scene { what: "lidar lost", fog: 0.0, gamma: 1.0, lidar: false },
    Scene { what: "clear again", fog: 0.0, gamma: 1.0, lidar: true },
];

/// A camera frame: six views of a seeded, textured scene in [0, 1] seen with `gamma`, and a
/// lidar BEV grid with about 1% of its cells occupied.
fn sensors(plan: &Plan, frame: u64, gamma: f32) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let mut uniform = super::uniform(0x9E37_79B9_7F4A_7C15u64 ^ frame);
    let m = &plan.manifest;
    m.input_shapes(1)
        .into_iter()
        .zip(&m.inputs)
        .map(|((name, shape), i)| {
            let n: usize = shape.iter().product();
            let data: Vec<f32> = if i.modality.as_deref() == Some("camera") {
                let scene: Vec<f32> = (0..n).map(|_| 0.3 + 0.4 * uniform()).collect();
                // The simulator's exposure model; gamma is one of the paper's levels.
                readi::simulate::camera::gamma(&scene, gamma as f64).unwrap_or(scene)
            } else {
                (0..n).map(|_| if uniform() < 0.01 { 0.2 + 0.8 * uniform() } else { 0.0 }).collect()
            };
            (name.to_string(), shape, data)
        })
        .collect()
}

fn describe_model(m: &Module, name: &str, check_ms: f64) {
    let g = &m.graph;
    println!("readi demo: {} ({name}), checked in {check_ms:.1} ms", g.name);
    let inputs: Vec<_> = g
        .input_nodes()
        .into_iter()
        .filter_map(|n| match &g.node(n).op {
            readi_compiler::ir::Op::Input(a) => Some((a, &g.node(n).outputs[0])),
            _ => None,
        })
        .collect();
    let width =
        inputs.iter().map(|(a, _)| a.name.len()).chain(g.outputs.iter().map(|o| o.name.len())).max().unwrap_or(0);
    for (a, ty) in &inputs {
        let m = a.modality.as_deref().map(|m| format!(" @{m}")).unwrap_or_default();
        let opt = if a.optional { " (optional)" } else { "" };
        println!("  input  {:<width$}  {ty}{m}{opt}", a.name);
    }
    for o in &g.outputs {
        println!("  output {:<width$}  {}", o.name, g.value_type(o.value).map(|t| t.to_string()).unwrap_or_default());
    }
    println!("  {} nodes, {} parameters", g.node_count(), print::thousands(g.parameter_count()));
    if let Some(plan) = &m.adapt {
        let p = g.parameter_count().max(1) as f64;
        // Each variant owns its scopes' rules and the shared ones (`adapt camera { ... }`).
        let groups = if plan.is_scoped() {
            print::params::variant_groups(m).into_iter().map(|(u, t, a)| (format!(" {u}"), t, a)).collect()
        } else {
            vec![(String::new(), plan.tuned_elements(g), plan.added_elements())]
        };
        for (units, tuned, added) in groups {
            println!(
                "  per variant{units}: exist budget {:.2}% ({} elements), add budget {:.2}% ({} elements)",
                100.0 * tuned as f64 / p,
                print::thousands(tuned),
                100.0 * added as f64 / p,
                print::thousands(added)
            );
        }
    }
    if let Some(v) = &m.variants {
        let keys: Vec<String> = v.keys().iter().map(|k| k.to_string()).collect();
        println!("  {} variants declared: {}", keys.len(), keys.join(" "));
    }
}

/// `m` compiled with seeded weights, seeded `variants` and the `melds` of them.
fn seeded_plan(s: &Frontend, m: &Module, variants: &[&str], melds: &[&str]) -> Result<Arc<Plan>, ExitCode> {
    let weights = backend::seeded_weights(&m.graph, 2024);
    let keys: Vec<String> = variants.iter().map(|k| k.to_string()).collect();
    let sources = backend::seeded_variants(m, &keys, 2025);
    let opts = CompileOptions { melds: melds.iter().map(|k| k.to_string()).collect(), ..Default::default() };
    match backend::compile_variants(m, &weights, "<seeded weights>", &sources, &opts) {
        Ok((plan, _)) => Ok(Arc::new(plan)),
        Err(d) => {
            s.report(&d);
            Err(ExitCode::FAILURE)
        }
    }
}

/// Why a frame's variant was chosen, but for the axes found clear.
fn print_reasons(selection: &conditions::Selection) {
    let why: Vec<&str> = selection.reasons.iter().map(String::as_str).filter(|r| !r.ends_with("-> clear")).collect();
    if !why.is_empty() {
        println!("        because {}", why.join("; "));
    }
}

/// Runs the demo on `model`; `frames` frames of the drive (it repeats when longer).
pub fn run(s: &mut Frontend, model: DemoModel, threads: usize, frames: usize) -> Result<(), ExitCode> {
    match model {
        DemoModel::Tiny => run_tiny(s, threads, frames),
        DemoModel::Bevfusion => bevfusion::run(s, threads, frames),
    }
}

fn run_tiny(s: &mut Frontend, threads: usize, frames: usize) -> Result<(), ExitCode> {
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let (name, text) = MODEL;
    let file = s.sources.add(name, text);
    let start = Instant::now();
    let out = passes::run(file, text, &Options::default());
    let check_ms = start.elapsed().as_secs_f64() * 1e3;
    s.report(&out.diagnostics);
    let Some(m) = out.module.filter(|_| !out.diagnostics.has_errors()) else {
        return Err(fail("the bundled model does not check".into()));
    };
    describe_model(&m, name, check_ms);

    let start = Instant::now();
    let plan = seeded_plan(s, &m, VARIANTS, MELDS)?;
    let mf = &plan.manifest;
    let variant_bytes: usize =
        mf.variants.iter().flat_map(|v| &v.replaces).map(|r| mf.tensors[r.with].numel() * 4).sum();
    println!(
        "\ncompiled with seeded weights and {} seeded variants in {:.0} ms: {} steps, {} of weights ({} of them \
         variant tensors)",
        mf.variants.len(),
        start.elapsed().as_secs_f64() * 1e3,
        mf.steps.len(),
        print::bytes(plan.tensor_bytes() as u64),
        print::bytes(variant_bytes as u64),
    );
    println!("  variants: {}", plan.variant_keys().skip(1).collect::<Vec<_>>().join(" "));

    let mut session = Session::new(plan.clone(), threads).map_err(|e| fail(e.to_string()))?;
    println!(
        "\na drive on {threads} threads; each frame's variant is chosen from its sensor data and weather metadata:"
    );
    println!(
        "  {:<5} {:<24} {:<20} {:>9} {:>9} {:>9}  outputs",
        "frame", "conditions", "variant", "select", "switch", "run"
    );
    for frame in 0..frames {
        let scene = &DRIVE[frame % DRIVE.len()];
        let mut data = sensors(&plan, frame as u64, scene.gamma);
        if !scene.lidar {
            data.retain(|(n, _, _)| {
                mf.inputs.iter().find(|i| &i.name == n).and_then(|i| i.modality.as_deref()) != Some("lidar")
            });
        }
        let given: Vec<Input<'_>> = data.iter().map(|(name, shape, d)| Input { name, data: d, shape }).collect();
        let meta = vec![("fog_density".to_string(), scene.fog)];
        let t = Instant::now();
        let selection = conditions::select(&plan, &given, &meta).map_err(|e| fail(e.to_string()))?;
        let select_us = t.elapsed().as_secs_f64() * 1e6;
        let t = Instant::now();
        session.set_variant_key(&selection.key).map_err(|e| fail(e.to_string()))?;
        let switch_us = t.elapsed().as_secs_f64() * 1e6;
        let t = Instant::now();
        let result = session.run(&given).map_err(|e| fail(e.to_string()))?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let summary: Vec<String> = result
            .iter()
            .map(|(n, t)| {
                let peak = t.data.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                format!("{n} max {peak:.3}")
            })
            .collect();
        println!(
            "  {frame:<5} {:<24} {:<20} {:>6.0} us {:>6.2} us {:>6.1} ms  {}",
            scene.what,
            selection.key,
            select_us,
            switch_us,
            ms,
            summary.join(", ")
        );
        print_reasons(&selection);
    }
    println!("\nnext: `readi ir {name}` for the graph, `readi params {name}` for every tensor");
    Ok(())
}
