//! Two sessions step by step in one process: a plan at two thread counts (how each step
//! scales), or two plans of the same model (what a compile-time change does to each
//! step), their runs alternating so that the host's drift falls on both alike.
//!
//! ```text
//! cargo run --release -p readi-runtime --example step_compare -- A.plan[@THREADS] B.plan[@THREADS] [ROUNDS]
//! cargo run --release -p readi-runtime --example step_compare -- m.plan@1 m.plan@2 200
//! ```
//!
//! Each round runs A once and B once (the order swapped every round) on the same seeded
//! inputs, profiling every step. Prints the median of the rounds' whole-run ratios B / A,
//! then the steps whose medians differ most: for two thread counts, against perfect
//! scaling (B = A times A's threads over B's); for two plans (steps matched by their
//! place in the schedule), B - A. Thread counts default to 2; rounds to 200.
use std::sync::Arc;
use std::time::Instant;

use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::Plan;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        eprintln!("usage: step_compare A.plan[@THREADS] B.plan[@THREADS] [ROUNDS]");
        std::process::exit(2);
    }
    let parse = |arg: &str| match arg.rsplit_once('@') {
        Some((path, t)) => (path.to_string(), t.parse::<usize>().expect("a thread count after @")),
        None => (arg.to_string(), 2),
    };
    let ((path_a, ta), (path_b, tb)) = (parse(&args[0]), parse(&args[1]));
    let load = |path: &str| Arc::new(Plan::load(std::path::Path::new(path)).unwrap_or_else(|e| panic!("{path}: {e}")));
    // One plan at two thread counts is loaded once.
    let same = path_a == path_b;
    let plan = load(&path_a);
    let plan_b = if same { Arc::clone(&plan) } else { load(&path_b) };
    let session = |plan: &Arc<Plan>, threads: usize| {
        let mut s = Session::new(Arc::clone(plan), threads).expect("a session");
        s.bind_batch(1).expect("batch 1 binds");
        s
    };
    let (a, b) = (session(&plan, ta), session(&plan_b, tb));
    let rounds: usize = args.get(2).map_or(200, |r| r.parse().expect("a round count"));
    let steps = plan.manifest.steps.len();
    assert_eq!(steps, plan_b.manifest.steps.len(), "the plans have different schedules");
    let shapes = plan.manifest.input_shapes(1);
    let data: Vec<Vec<f32>> =
        shapes.iter().map(|(_, s)| readi_runtime::testdata::data(s.iter().product(), 7)).collect();
    let inputs: Vec<Input> =
        shapes.iter().zip(&data).map(|((name, shape), d)| Input { name, data: d, shape }).collect();
    let mut sessions = [a, b];
    for _ in 0..10 {
        for s in sessions.iter_mut() {
            s.run(&inputs).expect("a run");
        }
    }
    let mut per_step = [vec![Vec::new(); steps], vec![Vec::new(); steps]];
    let mut whole = [Vec::with_capacity(rounds), Vec::with_capacity(rounds)];
    for r in 0..rounds {
        let mut t = [0.0; 2];
        for i in if r % 2 == 0 { [0, 1] } else { [1, 0] } {
            let s = &mut sessions[i];
            s.enable_profiling();
            let start = Instant::now();
            s.run(&inputs).expect("a run");
            t[i] = start.elapsed().as_secs_f64() * 1e3;
            for (k, v) in s.profile().expect("profiling").iter().enumerate() {
                per_step[i][k].push(v * 1e3);
            }
        }
        whole[0].push(t[0]);
        whole[1].push(t[1]);
    }
    let median = |v: &[f64]| {
        let mut v = v.to_vec();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let ratios: Vec<f64> = whole[0].iter().zip(&whole[1]).map(|(a, b)| b / a).collect();
    println!(
        "A {:.3} ms ({ta} threads), B {:.3} ms ({tb} threads): B / A {:.3} (median of {rounds} rounds)",
        median(&whole[0]),
        median(&whole[1]),
        median(&ratios)
    );
    // Excess of B over what A predicts: perfect scaling for one plan, A itself for two.
    let expect = |x: f64| if same { x * ta as f64 / tb as f64 } else { x };
    let mut rows: Vec<(f64, f64, f64, &str)> = (0..steps)
        .map(|k| {
            let (x, y) = (median(&per_step[0][k]), median(&per_step[1][k]));
            (y - expect(x), x, y, plan.manifest.steps[k].path.as_str())
        })
        .collect();
    rows.sort_by(|p, q| q.0.total_cmp(&p.0));
    println!("{:>9} {:>9} {:>9}  step", if same { "excess" } else { "B - A" }, "A ms", "B ms");
    let n = rows.len();
    let shown: Vec<usize> =
        if same { (0..n.min(16)).collect() } else { (0..n.min(8)).chain(n.saturating_sub(8).max(8)..n).collect() };
    for k in shown {
        let (d, x, y, path) = rows[k];
        println!("{d:+9.4} {x:9.4} {y:9.4}  {path}");
    }
}
