//! Sparse 3-D convolution (`subm_conv3d`, `sparse_conv3d`, `sparse_out_coords`,
//! `sparse_to_dense`) against PyTorch's dense conv3d: `tests/fixtures/sparse/sparse.readi`
//! and `make_sparse_fixtures.py` (the active sites scattered into a dense grid,
//! `F.conv3d`, gathered at the output sites; no spconv), and `subm_conv3d` against readi's
//! own dense `conv3d` on a grid with every site active. Also an empty input, and hostile
//! coords and attributes: a run-time error naming the step, a compile error with its
//! place.

mod common;

use std::sync::Arc;

use readi_compiler::backend::{self, CompileOptions, WeightSet};
use readi_plan::ops::Pure;
use readi_runtime::exec::{Input, RunError, Session};
use readi_runtime::plan::{Kernel, Plan};

const SPEC: &str = "tests/fixtures/sparse/sparse.readi";

fn fixture(name: &str) -> WeightSet {
    let path = common::root().join("tests/fixtures/sparse").join(name);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    WeightSet::from_safetensors(name, &bytes).expect("fixture")
}

fn compile_text(text: &str) -> Result<Plan, String> {
    compile_with(text, &fixture("sparse.weights.safetensors"))
}

/// Compiles `text` with `weights`; the rendered diagnostics on failure.
fn compile_with(text: &str, weights: &WeightSet) -> Result<Plan, String> {
    let (sources, out) = common::compile_text("sparse.readi", text, &[], None);
    if out.diagnostics.has_errors() {
        return Err(sources.render_all(&out.diagnostics, false));
    }
    let module = out.module.expect("module");
    backend::compile(&module, weights, "sparse.weights.safetensors", &CompileOptions::default())
        .map(|(plan, _)| plan)
        .map_err(|d| sources.render_all(&d, false))
}

fn plan() -> Plan {
    let text = std::fs::read_to_string(common::root().join(SPEC)).expect("spec");
    compile_text(&text).unwrap_or_else(|e| panic!("{e}"))
}

/// Runs the plan on `features` and `coords` at `threads` threads.
/// An output: its name, shape and data.
type Output = (String, Vec<usize>, Vec<f32>);

fn run(plan: &Arc<Plan>, features: &[f32], coords: &[f32], threads: usize) -> Result<Vec<Output>, RunError> {
    let (fs, cs) = ([64usize, 4], [64usize, 3]);
    let inputs =
        [Input { name: "features", data: features, shape: &fs }, Input { name: "coords", data: coords, shape: &cs }];
    let out = Session::new(plan.clone(), threads).expect("session").run(&inputs)?;
    Ok(out.into_iter().map(|(n, t)| (n.to_string(), t.shape.clone(), t.data.clone())).collect())
}

#[test]
fn sparse_convs_match_the_dense_conv3d_of_pytorch() {
    let plan = Arc::new(plan());
    let io = fixture("sparse.io.safetensors");
    let (_, features) = &io.tensors["input.features"];
    let (_, coords) = &io.tensors["input.coords"];
    let mut bits = Vec::new();
    for threads in [1, 2] {
        let outputs = run(&plan, features, coords, threads).expect("runs");
        assert_eq!(outputs.len(), 5);
        for (name, shape, got) in &outputs {
            let (want_shape, want) = &io.tensors[&format!("output.{name}")];
            assert_eq!(shape, want_shape, "shape of {name}");
            let mut worst = 0.0f32;
            for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
                if w.is_nan() {
                    // An inactive row after a BatchNorm: anything finite.
                    assert!(g.is_finite(), "{name}[{i}]: {g}");
                    continue;
                }
                let err = (g - w).abs() / w.abs().max(1.0);
                assert!(err <= 1e-4, "{name}[{i}]: {g}, torch {w} (error {err:e})");
                worst = worst.max(err);
            }
            eprintln!("{name}: max error vs torch {worst:e}");
        }
        bits.push(outputs.iter().flat_map(|o| o.2.iter().map(|v| v.to_bits())).collect::<Vec<_>>());
    }
    assert_eq!(bits[0], bits[1], "the bits differ between 1 and 2 threads");
}

/// The plan holds one step per sparse operator, its BatchNorms as channel affines over
/// `[V, C]` (BatchNorm1d), none folded into a sparse conv.
#[test]
fn sparse_steps_and_their_batchnorms() {
    let plan = plan();
    let steps = &plan.manifest.steps;
    let count = |f: &dyn Fn(&Kernel) -> bool| steps.iter().filter(|s| f(&s.kernel)).count();
    assert_eq!(count(&|k| matches!(k, Kernel::Pure(Pure::SparseConv3d(c)) if c.subm)), 3);
    assert_eq!(count(&|k| matches!(k, Kernel::Pure(Pure::SparseConv3d(c)) if !c.subm)), 2);
    assert_eq!(count(&|k| matches!(k, Kernel::Pure(Pure::SparseOutCoords(_)))), 2);
    assert_eq!(count(&|k| matches!(k, Kernel::Pure(Pure::SparseToDense(_)))), 1);
    assert_eq!(count(&|k| matches!(k, Kernel::ChannelAffine { .. })), 2, "{steps:#?}");
}

/// No active site: every conv output zero, no output site, an empty dense grid.
#[test]
fn an_empty_input_gives_zeros() {
    let plan = Arc::new(plan());
    let features = vec![0.5f32; 64 * 4];
    let coords = vec![-1.0f32; 64 * 3];
    for (name, _, data) in run(&plan, &features, &coords, 2).expect("runs") {
        let want = if name == "down_coords" { -1.0 } else { 0.0 };
        if name == "block" {
            // Inactive rows after a BatchNorm: finite, ignored.
            assert!(data.iter().all(|v| v.is_finite()), "{name}");
            continue;
        }
        assert!(data.iter().all(|&v| v == want), "{name}: {data:?}");
    }
}

fn step_error(e: RunError) -> (String, String) {
    match e {
        RunError::Step { step, detail } => (step, detail),
        other => panic!("not a step error: {other}"),
    }
}

/// Coords outside the grid, after an inactive row, twice the same site, or more output
/// sites than `max_out`: a run-time error naming the step, never a panic.
#[test]
fn hostile_coords_are_refused_at_run_time() {
    let plan = Arc::new(plan());
    let io = fixture("sparse.io.safetensors");
    let features = &io.tensors["input.features"].1;
    let good = io.tensors["input.coords"].1.clone();
    let mut outside = good.clone();
    outside[1] = 9.0;
    let mut hole = good.clone();
    hole[3 * 50..3 * 51].copy_from_slice(&[0.0, 0.0, 0.0]);
    let mut twice = good.clone();
    let (a, b) = (twice[0..3].to_vec(), 3);
    twice[b..b + 3].copy_from_slice(&a);
    let mut fraction = good.clone();
    fraction[2] = 0.5;
    let cases = [
        (outside, "not a site of the grid"),
        (hole, "must be a prefix"),
        (twice, "are the same site"),
        (fraction, "not a site of the grid"),
    ];
    for (coords, want) in cases {
        let (step, detail) = step_error(run(&plan, features, &coords, 2).expect_err(want));
        assert!(detail.contains(want), "{step}: {detail}");
        assert!(!step.is_empty(), "{detail}");
    }
    // A dense input: every site active, more than max_out outputs.
    let text = std::fs::read_to_string(common::root().join(SPEC)).expect("spec");
    let small = compile_text(&text.replace("max_out=96", "max_out=20")).expect("compiles");
    let (step, detail) = step_error(run(&Arc::new(small), features, &good, 1).expect_err("over capacity"));
    assert!(detail.contains("47 active output sites, more than its capacity 20: raise max_out"), "{detail}");
    assert!(step.contains("down_coords"), "{step}");
}

/// Bad attributes and operands: compile errors at their place.
#[test]
fn bad_attributes_are_compile_errors() {
    let text = std::fs::read_to_string(common::root().join(SPEC)).expect("spec");
    let cases = [
        (
            "kernel=3, stride=2, padding=1, max_out=96",
            "kernel=3, stride=0, padding=1, max_out=96",
            "must be at least 1",
        ),
        ("max_out=96", "max_out=0", "max_out"),
        (
            "sparse_out_coords(coords, [5, 9, 7], kernel=3",
            "sparse_out_coords(coords, [5, 0, 7], kernel=3",
            "spatial_shape",
        ),
        (
            "kernel=[3, 1, 1], stride=[2, 1, 1], max_out=128",
            "kernel=[9, 1, 1], stride=[2, 1, 1], max_out=128",
            "does not fit",
        ),
        ("subm_w = parameter([3, 3, 3, 4, 8])", "subm_w = parameter([2, 3, 3, 4, 8])", "odd kernel"),
        ("subm_w = parameter([3, 3, 3, 4, 8])", "subm_w = parameter([8, 4, 3, 3, 3])", "weight"),
        ("subm_conv3d(features, coords, subm_w", "subm_conv3d(features, features, subm_w", "coords"),
    ];
    for (from, to, want) in cases {
        assert!(text.contains(from), "{from}");
        let e = compile_text(&text.replacen(from, to, 1)).expect_err(to);
        assert!(e.contains(want) && e.contains("sparse.readi:"), "{to}: {e}");
    }
}

/// Submanifold conv with every site of the grid active is the dense `conv3d` with
/// padding `dilation·(k - 1) / 2` (spconv's centring), the weight `[kD, kH, kW, Cin, Cout]`
/// read as `[Cout, Cin, kD, kH, kW]`: two independent kernels (the rulebook's
/// gather-GEMM-scatter and vol2col) cross-checked, on sites listed in shuffled order, a
/// cubic kernel with a bias and an anisotropic `[1, 1, 3]` one dilated by 2 without one.
#[test]
fn subm_conv3d_at_all_active_sites_is_the_dense_conv3d() {
    const SPEC: &str = "
model all_active {
  input features: f32[60, 4]
  input coords: i64[60, 3]
  cube_w = parameter([3, 3, 3, 4, 5])
  cube_b = parameter([5])
  output subm_cube = sparse_to_dense(subm_conv3d(features, coords, cube_w, [3, 4, 5], bias=cube_b), coords, [3, 4, 5])
  row_w = parameter([1, 1, 3, 4, 2])
  output subm_row = sparse_to_dense(subm_conv3d(features, coords, row_w, [3, 4, 5], dilation=2), coords, [3, 4, 5])
  grid = sparse_to_dense(features, coords, [3, 4, 5])
  cube = conv3d(grid, 5, kernel=3, padding=1)
  output dense_cube = cube
  row = conv3d(grid, 2, kernel=[1, 1, 3], padding=[0, 0, 2], dilation=2, bias=false)
  output dense_row = row
}";
    let (grid, cin) = ([3usize, 4, 5], 4usize);
    let sites = grid.iter().product::<usize>();
    // A fixed pseudo-random stream in [-1, 1).
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    };
    let mut weights = WeightSet::default();
    for (sparse, dense, kernel, cout) in
        [("cube_w", "cube.weight", [3usize, 3, 3], 5usize), ("row_w", "row.weight", [1, 1, 3], 2)]
    {
        let taps = kernel.iter().product::<usize>();
        let w: Vec<f32> = (0..taps * cin * cout).map(|_| next()).collect();
        // [kD, kH, kW, Cin, Cout] -> [Cout, Cin, kD, kH, kW]
        let mut torch = vec![0.0f32; w.len()];
        for t in 0..taps {
            for i in 0..cin {
                for o in 0..cout {
                    torch[(o * cin + i) * taps + t] = w[(t * cin + i) * cout + o];
                }
            }
        }
        let [kd, kh, kw] = kernel;
        weights.tensors.insert(sparse.into(), (vec![kd, kh, kw, cin, cout], w));
        weights.tensors.insert(dense.into(), (vec![cout, cin, kd, kh, kw], torch));
    }
    let bias: Vec<f32> = (0..5).map(|_| next()).collect();
    weights.tensors.insert("cube_b".into(), (vec![5], bias.clone()));
    weights.tensors.insert("cube.bias".into(), (vec![5], bias));
    let plan = Arc::new(compile_with(SPEC, &weights).unwrap_or_else(|e| panic!("{e}")));
    // Every site once, in an order that is not the grid's.
    let mut order: Vec<usize> = (0..sites).collect();
    for i in (1..sites).rev() {
        order.swap(i, ((next() + 1.0) * 0.5 * (i + 1) as f32) as usize % (i + 1));
    }
    let coords: Vec<f32> = order
        .iter()
        .flat_map(|&s| [s / (grid[1] * grid[2]), s / grid[2] % grid[1], s % grid[2]].map(|c| c as f32))
        .collect();
    let features: Vec<f32> = (0..sites * cin).map(|_| next()).collect();
    let (fs, cs) = ([sites, cin], [sites, 3]);
    let inputs =
        [Input { name: "features", data: &features, shape: &fs }, Input { name: "coords", data: &coords, shape: &cs }];
    for threads in [1, 2] {
        let out = Session::new(plan.clone(), threads).expect("session").run(&inputs).expect("runs");
        let get = |name: &str| &out.iter().find(|(n, _)| *n == name).unwrap_or_else(|| panic!("{name}")).1;
        for (subm, dense) in [("subm_cube", "dense_cube"), ("subm_row", "dense_row")] {
            let (s, d) = (get(subm), get(dense));
            assert_eq!(s.shape, d.shape, "{subm} and {dense}");
            let mut worst = 0.0f32;
            for (i, (&a, &b)) in s.data.iter().zip(&d.data).enumerate() {
                let err = (a - b).abs() / b.abs().max(1.0);
                assert!(err <= 1e-5, "{subm}[{i}] = {a}, {dense}[{i}] = {b} ({threads} threads)");
                worst = worst.max(err);
            }
            assert!(s.data.iter().any(|&v| v != 0.0), "{subm} is all zero");
            eprintln!("{subm} vs {dense}, {threads} threads: max error {worst:e}");
        }
    }
}
