//! `readi bench`: a plan's latency on seeded inputs, and with `--profile` where the time goes.

use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;

use readi::rounds::{Rounds, median};
use readi_compiler::print::thousands;
use readi_runtime::exec::{Input, Session, SessionOptions};
use readi_runtime::plan::{BASE_VARIANT, Plan, escaped};

use super::load_plan;

/// Seeded inputs for every input of a plan at the given batch size.
fn synthetic_inputs(plan: &Plan, batch: usize, seed: u64) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let mut uniform = super::uniform(seed);
    plan.manifest
        .input_shapes(batch)
        .into_iter()
        .map(|(name, shape)| {
            let n = shape.iter().product();
            let data = (0..n).map(|_| uniform() * 2.0 - 1.0).collect();
            (name.to_string(), shape, data)
        })
        .collect()
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// How `readi bench` times a plan.
pub struct Timing {
    /// Timed runs.
    pub runs: usize,
    /// Untimed runs first.
    pub warmup: usize,
    /// The batch size bound to the symbolic batch dimension.
    pub batch: usize,
    /// Whether to print the per-step profile.
    pub profile: bool,
    /// How many of the slowest steps the profile lists (0: all).
    pub steps: usize,
    /// Whether to measure the machine's peak and print the run's fraction of it.
    pub peak: bool,
    /// Variants to switch to and back from after the timed runs ([`switching`]).
    pub switch: Vec<String>,
    /// A variant (or the base) to time in alternating runs with the timed one ([`against`]).
    pub against: Option<String>,
}

/// Times `plan_path` under `variant` (or the base) on seeded inputs, except those `inputs`
/// names (`NAME=FILE`, read as `readi run` reads them): a model whose work depends on its
/// data (a point cloud's voxels and sparse sites) is timed on real data that way.
pub fn run(
    plan_path: &Path,
    options: SessionOptions,
    timing: &Timing,
    variant: Option<&str>,
    inputs: &[(String, String)],
) -> Result<(), ExitCode> {
    let Timing { runs, warmup, batch, profile, steps, peak, ref switch, ref against } = *timing;
    let plan = load_plan(plan_path)?;
    let fail = |msg: String| {
        eprintln!("error: {msg}");
        ExitCode::FAILURE
    };
    let threads = options.threads;
    let max_memory = options.max_memory;
    let mut session = Session::with_options(plan.clone(), options).map_err(|e| fail(e.to_string()))?;
    // Every key is looked up before anything runs: a typo fails at once. The timed
    // variant is set last.
    for key in switch.iter().map(String::as_str).chain([variant.unwrap_or(BASE_VARIANT)]) {
        session.set_variant(key).map_err(|e| fail(e.to_string()))?;
    }
    // The second session of `--against`, its variant set and its batch bound with the first's.
    let mut other = match against {
        Some(key) => {
            let s = Session::with_options(plan.clone(), options).map_err(|e| fail(e.to_string()))?;
            s.set_variant(key).map_err(|e| fail(e.to_string()))?;
            Some(s)
        }
        None => None,
    };
    // Bound first: a batch too large for the memory limit (or for the address space) is
    // refused before the inputs are made.
    for s in std::iter::once(&mut session).chain(other.as_mut()) {
        s.bind_batch(batch).map_err(|e| fail(format!("{}: batch {batch}: {e}", plan_path.display())))?;
    }
    let mut data = synthetic_inputs(&plan, batch, 42);
    for (name, (shape, d)) in super::run::load_inputs(&plan.manifest, inputs, max_memory).map_err(fail)? {
        match data.iter_mut().find(|(n, _, _)| *n == name) {
            Some(slot) => *slot = (name, shape, d),
            None => return Err(fail(format!("the plan has no input `{}`", escaped(&name)))),
        }
    }
    let given: Vec<Input<'_>> = data.iter().map(|(name, shape, d)| Input { name, data: d, shape }).collect();
    let shown = plan_path.display();
    for _ in 0..warmup {
        session.run(&given).map_err(|e| fail(format!("{shown}: {e}")))?;
    }
    if profile {
        session.enable_profiling();
    }
    let mut times = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        session.run(&given).map_err(|e| fail(format!("{shown}: {e}")))?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    println!(
        "{} ({}): batch {}, {} threads, {} runs: median {:.2} ms, p90 {:.2} ms, min {:.2} ms",
        escaped(&plan.manifest.model),
        session.variant(),
        batch,
        threads,
        times.len(),
        percentile(&times, 0.5),
        percentile(&times, 0.9),
        times.first().copied().unwrap_or(0.0)
    );
    work(
        session.multiply_adds().unwrap_or(0),
        percentile(&times, 0.5),
        peak.then(|| readi_runtime::peak::measure(threads)),
    );
    if let Some(kib) = peak_resident_kib() {
        println!("peak resident memory: {:.1} MiB (the process's, so far)", kib as f64 / 1024.0);
    }
    if let Some(p) = session.profile() {
        print!("{}", readi::inspect::profile(&plan.manifest, p, times.len(), steps));
    }
    if let Some(other) = other.as_mut() {
        // The timed session goes on profiling its steps: the other pays the same timers.
        if profile {
            other.enable_profiling();
        }
        alternating(&mut session, other, &given, warmup, runs).map_err(|e| fail(format!("{shown}: {e}")))?;
    }
    if !switch.is_empty() {
        switching(&mut session, &given, switch, runs).map_err(|e| fail(format!("{shown}: {e}")))?;
    }
    Ok(())
}

/// `--against`: `session` and `other` (the same plan under another variant) in `runs`
/// alternating rounds ([`Rounds`]); prints the median of the rounds' ratios and their
/// range.
fn alternating(
    session: &mut Session,
    other: &mut Session,
    given: &[Input<'_>],
    warmup: usize,
    runs: usize,
) -> Result<(), String> {
    for _ in 0..warmup {
        other.run(given).map_err(|e| e.to_string())?;
    }
    let timer = |s: &mut Session| -> Result<f64, String> {
        let t = Instant::now();
        s.run(given).map_err(|e| e.to_string())?;
        Ok(t.elapsed().as_secs_f64() * 1e3)
    };
    let (mut mine, mut theirs) = (|| timer(&mut *session), || timer(&mut *other));
    let rounds = Rounds::run(&mut [&mut mine, &mut theirs], runs)?;
    let ratios = rounds.sorted(|t| t[0] / t[1]);
    println!(
        "{} against {}, {runs} alternating rounds: median {:.2} ms against {:.2} ms, ratio {:.3} (the median of the rounds' ratios; rounds {:.3} to {:.3})",
        session.variant(),
        other.variant(),
        rounds.median(0),
        rounds.median(1),
        median(&ratios),
        ratios.first().copied().unwrap_or(0.0),
        ratios.last().copied().unwrap_or(0.0)
    );
    Ok(())
}

/// Prints a run's work, `macs` multiply-adds (of the convs, linears and matmuls, counted
/// as the direct algorithm does them), and the GFLOP/s of a run of `median_ms` (an FMA
/// counts as two FLOPs), with its fraction of `peak` when measured. Faster algorithms
/// (Winograd) do fewer multiplications than counted, so their GFLOP/s are effective ones.
fn work(macs: u64, median_ms: f64, peak: Option<readi_runtime::peak::Peak>) {
    if macs == 0 {
        return;
    }
    let flops = 2.0 * macs as f64 / (median_ms * 1e-3);
    print!("work: {} multiply-adds a run, {:.1} GFLOP/s at the median", thousands(macs), flops * 1e-9);
    match peak {
        Some(p) => println!(
            ", {:.1}% of this machine's peak ({:.1} GFLOP/s on {} thread{}, {} f32 lanes, measured now)",
            100.0 * p.fraction(flops),
            p.gflops(),
            p.threads,
            if p.threads == 1 { "" } else { "s" },
            p.lanes
        ),
        None => println!(),
    }
}

/// The process's peak resident memory in KiB, from `/proc/self/status` (`VmHWM`); `None`
/// where there is no such file (not Linux) or it says nothing readable.
fn peak_resident_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
    line.trim().strip_suffix("kB")?.trim().parse().ok()
}

/// Switches per key in [`switching`]'s timing of the switch alone.
const SWITCHES: usize = 2000;

/// Times switching between the session's variant (`home`) and each of `keys`: the switch
/// alone, [`SWITCHES`] times per key there and back (a key lookup and an atomic store, so
/// nanoseconds to microseconds); then `runs` switches, alternately to a key and home, each
/// followed by two runs: the first, which pays whatever a switch defers to the run (a
/// layer merged on switch is re-merged there), against the steady one after it.
fn switching(session: &mut Session, given: &[Input<'_>], keys: &[String], runs: usize) -> Result<(), String> {
    let home = session.variant().to_string();
    let mut switch_ns = Vec::with_capacity(2 * SWITCHES * keys.len());
    for _ in 0..SWITCHES {
        for key in keys.iter().flat_map(|k| [k.as_str(), home.as_str()]) {
            let t = Instant::now();
            session.set_variant(key).map_err(|e| e.to_string())?;
            switch_ns.push(t.elapsed().as_secs_f64() * 1e9);
        }
    }
    switch_ns.sort_by(f64::total_cmp);
    println!(
        "switch {} <-> {}: {} switches: p50 {:.0} ns, p99 {:.0} ns, max {:.0} ns",
        escaped(&home),
        keys.iter().map(|k| escaped(k).to_string()).collect::<Vec<_>>().join(", "),
        switch_ns.len(),
        percentile(&switch_ns, 0.5),
        percentile(&switch_ns, 0.99),
        switch_ns.last().copied().unwrap_or(0.0)
    );
    let timed = |session: &mut Session| -> Result<f64, String> {
        let t = Instant::now();
        session.run(given).map_err(|e| e.to_string())?;
        Ok(t.elapsed().as_secs_f64() * 1e3)
    };
    let (mut extra, mut ratio) = (Vec::with_capacity(runs), Vec::with_capacity(runs));
    for i in 0..runs {
        let to = if i % 2 == 0 { keys[(i / 2) % keys.len()].as_str() } else { home.as_str() };
        session.set_variant(to).map_err(|e| e.to_string())?;
        let (first, steady) = (timed(session)?, timed(session)?);
        extra.push(first - steady);
        ratio.push(first / steady);
    }
    session.set_variant(&home).map_err(|e| e.to_string())?;
    extra.sort_by(f64::total_cmp);
    ratio.sort_by(f64::total_cmp);
    println!(
        "first run after a switch, against the steady run after it ({runs} switches): {:+.3} ms p50, {:+.3} ms p99; \
         first / steady median {:.3} (range {:.3} to {:.3})",
        percentile(&extra, 0.5),
        percentile(&extra, 0.99),
        percentile(&ratio, 0.5),
        ratio.first().copied().unwrap_or(0.0),
        ratio.last().copied().unwrap_or(0.0)
    );
    Ok(())
}
