//! Plans built by hand for the variant tests: an MLP and a conv layer with variants,
//! references computed from their weights, and helpers to run and edit them.
#![allow(dead_code)]

use std::collections::HashMap;
use std::sync::Arc;

use readi_plan::ops::{BinaryOp, ChannelAffine, Conv2d, LayerNorm, Linear, Pure, Window2};
use readi_plan::{Dim, VariantKey};
use readi_runtime::exec::{Input, Session};
use readi_runtime::plan::{
    BASE_VARIANT, EpilogueSpec, FORMAT_VERSION, InputSpec, Kernel, Manifest, OutputSpec, Plan, PlanError, Replacement,
    Step, Storage, TensorSpec, ValueSpec, VariantTable,
};
use readi_runtime::testdata::data;

// The workspace's one scratch-directory helper (the root test crate's).
#[path = "../../../tests/common/scratch.rs"]
mod scratch;
#[allow(unused_imports)] // Not every test crate writes files.
pub use scratch::Scratch;

// ---------------------------------------------------------------------------------------
// Building plans by hand
// ---------------------------------------------------------------------------------------

/// Stored tensors under construction: specs and data in manifest order.
#[derive(Default)]
pub struct Store {
    pub specs: Vec<TensorSpec>,
    pub data: Vec<Vec<f32>>,
}

impl Store {
    fn add(&mut self, name: &str, shape: &[usize], data: Vec<f32>) -> usize {
        assert_eq!(data.len(), shape.iter().product::<usize>(), "{name}");
        self.specs.push(TensorSpec::f32(name, shape.to_vec()));
        self.data.push(data);
        self.specs.len() - 1
    }
}

pub fn n_dim() -> Dim {
    Dim::symbol("N")
}

pub fn dims(rest: &[usize]) -> Vec<Dim> {
    std::iter::once(n_dim()).chain(rest.iter().map(|&d| Dim::from(d))).collect()
}

pub fn key(text: &str) -> VariantKey {
    VariantKey::parse(text).expect("a valid key")
}

pub fn table(key: &str, replaces: &[(usize, usize)]) -> VariantTable {
    VariantTable {
        key: self::key(key),
        replaces: replaces.iter().map(|&(base, with)| Replacement { base, with, added: false }).collect(),
        tuned_elements: 0,
        added_elements: 0,
        fallback: Vec::new(),
        scopes: Vec::new(),
    }
}

pub fn manifest(
    inputs: Vec<InputSpec>,
    values: Vec<ValueSpec>,
    steps: Vec<Step>,
    slots: usize,
    output: usize,
    tensors: Vec<TensorSpec>,
    variants: Vec<VariantTable>,
) -> Manifest {
    Manifest {
        format_version: FORMAT_VERSION,
        model: "variants-test".into(),
        conditions: None,
        model_params: Vec::new(),
        symbols: vec!["N".into()],
        inputs,
        outputs: vec![OutputSpec::f32("y", output)],
        values,
        steps,
        slots,
        tensors,
        params: Vec::new(),
        variants,
        footprint: None,
    }
}

/// The weights of one variant of the MLP plan, as the reference sees them.
#[derive(Clone)]
pub struct MlpWeights {
    /// `[fin, fout]` (the runtime's linear layout: `y = x W`).
    pub w: Vec<f32>,
    pub bias: Vec<f32>,
    pub gamma: Vec<f32>,
    pub beta: Vec<f32>,
    /// `[1, fout]`, added to every row (a stored tensor used as a value).
    pub p: Vec<f32>,
}

/// `y = layernorm(relu(x W + bias)) * gamma + beta + p` over `x: [N, fin]`: three steps
/// (linear with epilogue, layernorm, add of a stored value) reading five base tensors, and
/// variants:
///
/// * `A`: W, gamma and p (one tensor in each step);
/// * `B`: W, bias, beta and p (again every step);
/// * `C`: W only, sharing A's stored W.
pub struct Mlp {
    pub plan: Plan,
    pub fin: usize,
    pub fout: usize,
    pub weights: HashMap<&'static str, MlpWeights>,
}

pub const LN_EPS: f32 = 1e-5;

pub fn mlp(fin: usize, fout: usize) -> Mlp {
    let mut s = Store::default();
    // Offsets keep every variant's tensors different from the base's everywhere.
    let base = MlpWeights {
        w: data(fin * fout, 1),
        bias: data(fout, 2),
        gamma: data(fout, 3).iter().map(|v| 1.0 + 0.5 * v).collect(),
        beta: data(fout, 4),
        p: data(fout, 5),
    };
    let w = s.add("fc.weight@t", &[fin, fout], base.w.clone());
    let bias = s.add("fc.bias", &[fout], base.bias.clone());
    let gamma = s.add("ln.weight", &[fout], base.gamma.clone());
    let beta = s.add("ln.bias", &[fout], base.beta.clone());
    let p = s.add("p", &[1, fout], base.p.clone());

    let a = MlpWeights {
        w: data(fin * fout, 11),
        gamma: data(fout, 13).iter().map(|v| 2.0 + 0.5 * v).collect(),
        p: data(fout, 15).iter().map(|v| v + 3.0).collect(),
        ..base.clone()
    };
    let w_a = s.add("fc.weight@t~A", &[fin, fout], a.w.clone());
    let gamma_a = s.add("ln.weight~A", &[fout], a.gamma.clone());
    let p_a = s.add("p~A", &[1, fout], a.p.clone());

    let b = MlpWeights {
        w: data(fin * fout, 21),
        bias: data(fout, 22).iter().map(|v| v - 3.0).collect(),
        beta: data(fout, 24).iter().map(|v| v + 5.0).collect(),
        p: data(fout, 25).iter().map(|v| v - 7.0).collect(),
        ..base.clone()
    };
    let w_b = s.add("fc.weight@t~B", &[fin, fout], b.w.clone());
    let bias_b = s.add("fc.bias~B", &[fout], b.bias.clone());
    let beta_b = s.add("ln.bias~B", &[fout], b.beta.clone());
    let p_b = s.add("p~B", &[1, fout], b.p.clone());

    let c = MlpWeights { w: a.w.clone(), ..base.clone() };

    let values = vec![
        ValueSpec { shape: dims(&[fin]), storage: Storage::Input(0) },
        ValueSpec { shape: dims(&[fout]), storage: Storage::Slot(0) },
        ValueSpec { shape: dims(&[fout]), storage: Storage::Slot(1) },
        ValueSpec { shape: vec![Dim::known(1), Dim::from(fout)], storage: Storage::Tensor(p) },
        ValueSpec { shape: dims(&[fout]), storage: Storage::Slot(0) },
    ];
    let steps = vec![
        Step {
            path: "fc".into(),
            kernel: Kernel::Linear {
                linear: Linear { in_features: fin as i64, out_features: fout as i64 },
                weight: w,
                epilogue: EpilogueSpec {
                    scale: None,
                    shift: Some(bias),
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
                norm: LayerNorm { features: fout as i64, eps: f64::from(LN_EPS), affine: true },
                weight: Some(gamma),
                bias: Some(beta),
            },
            inputs: vec![1],
            output: 2,
        },
        Step { path: "add".into(), kernel: Kernel::Pure(Pure::Binary(BinaryOp::Add)), inputs: vec![2, 3], output: 4 },
    ];
    let inputs = vec![InputSpec { name: "x".into(), shape: dims(&[fin]), modality: None, optional: false, value: 0 }];
    let variants = vec![
        table("fog=1", &[(w, w_a), (gamma, gamma_a), (p, p_a)]),
        table("fog=2", &[(w, w_b), (bias, bias_b), (beta, beta_b), (p, p_b)]),
        table("fog=3", &[(w, w_a)]),
    ];
    let m = manifest(inputs, values, steps, 2, 4, s.specs, variants);
    let plan = Plan::new(m, s.data).expect("a valid plan");
    let weights = HashMap::from([(BASE_VARIANT, base), ("fog=1", a), ("fog=2", b), ("fog=3", c)]);
    Mlp { plan, fin, fout, weights }
}

/// The MLP computed naively in f64.
pub fn mlp_reference(x: &[f32], fin: usize, fout: usize, w: &MlpWeights) -> Vec<f64> {
    let mut y = Vec::with_capacity(x.len() / fin * fout);
    for row in x.chunks(fin) {
        let h: Vec<f64> = (0..fout)
            .map(|o| {
                let acc: f64 = (0..fin).map(|i| f64::from(row[i]) * f64::from(w.w[i * fout + o])).sum();
                (acc + f64::from(w.bias[o])).max(0.0)
            })
            .collect();
        let mean = h.iter().sum::<f64>() / fout as f64;
        let var = h.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / fout as f64;
        let inv = 1.0 / (var + f64::from(LN_EPS)).sqrt();
        for (o, &h) in h.iter().enumerate() {
            let ln = (h - mean) * inv * f64::from(w.gamma[o]) + f64::from(w.beta[o]);
            y.push(ln + f64::from(w.p[o]));
        }
    }
    y
}

/// The weights of one variant of the conv plan.
#[derive(Clone)]
pub struct ConvWeights {
    /// PyTorch layout `[cout, cin, 3, 3]` (im2col's packing).
    pub w: Vec<f32>,
    pub scale1: Vec<f32>,
    pub shift1: Vec<f32>,
    pub scale2: Vec<f32>,
    pub shift2: Vec<f32>,
}

/// `y = affine2(relu(affine1(conv3x3(x))))` over `x: [N, cin, hw, hw]`, padding 1, with
/// variants `fog=0.05` (the folded BatchNorm's scale and shift and the second affine's
/// scale: BitFit-style tuning) and `gamma=2` (the conv weight, as a merged LoRA would
/// change it, and the second affine's shift).
pub struct ConvPlan {
    pub plan: Plan,
    pub cin: usize,
    pub cout: usize,
    pub hw: usize,
    pub weights: HashMap<&'static str, ConvWeights>,
}

pub fn conv_plan(cin: usize, cout: usize, hw: usize) -> ConvPlan {
    let mut s = Store::default();
    let pos = |len, seed| data(len, seed).iter().map(|v| 1.0 + 0.5 * v).collect::<Vec<f32>>();
    let base = ConvWeights {
        w: data(cout * cin * 9, 31),
        scale1: pos(cout, 32),
        shift1: data(cout, 33),
        scale2: pos(cout, 34),
        shift2: data(cout, 35),
    };
    let w = s.add("conv.weight", &[cout, cin, 3, 3], base.w.clone());
    let scale1 = s.add("bn1@scale", &[cout], base.scale1.clone());
    let shift1 = s.add("bn1@shift", &[cout], base.shift1.clone());
    let scale2 = s.add("bn2@scale", &[cout], base.scale2.clone());
    let shift2 = s.add("bn2@shift", &[cout], base.shift2.clone());
    let fog = ConvWeights { scale1: pos(cout, 42), shift1: data(cout, 43), scale2: pos(cout, 44), ..base.clone() };
    let fog_s1 = s.add("bn1@scale~fog", &[cout], fog.scale1.clone());
    let fog_t1 = s.add("bn1@shift~fog", &[cout], fog.shift1.clone());
    let fog_s2 = s.add("bn2@scale~fog", &[cout], fog.scale2.clone());
    let gamma = ConvWeights { w: data(cout * cin * 9, 51), shift2: data(cout, 55), ..base.clone() };
    let gamma_w = s.add("conv.weight~gamma", &[cout, cin, 3, 3], gamma.w.clone());
    let gamma_t2 = s.add("bn2@shift~gamma", &[cout], gamma.shift2.clone());

    let values = vec![
        ValueSpec { shape: dims(&[cin, hw, hw]), storage: Storage::Input(0) },
        ValueSpec { shape: dims(&[cout, hw, hw]), storage: Storage::Slot(0) },
        ValueSpec { shape: dims(&[cout, hw, hw]), storage: Storage::Slot(1) },
    ];
    let steps = vec![
        Step {
            path: "conv".into(),
            kernel: Kernel::Conv2d {
                conv: Conv2d {
                    in_channels: cin as i64,
                    out_channels: cout as i64,
                    window: Window2 { kernel: [3, 3], stride: [1, 1], padding: [1, 1], dilation: [1, 1] },
                    groups: 1,
                },
                algo: readi_plan::ops::ConvAlgo::Im2col,
                weight: w,
                epilogue: EpilogueSpec {
                    scale: Some(scale1),
                    shift: Some(shift1),
                    act: Some(readi_plan::ops::Activation::Relu),
                    bn: None,
                },
                lora: None,
                switch: false,
                adapter: None,
                residual: false,
                channel_scale: false,
            },
            inputs: vec![0],
            output: 1,
        },
        Step {
            path: "bn2".into(),
            kernel: Kernel::ChannelAffine {
                affine: ChannelAffine { channels: cout as i64 },
                epilogue: EpilogueSpec { scale: Some(scale2), shift: Some(shift2), act: None, bn: None },
            },
            inputs: vec![1],
            output: 2,
        },
    ];
    let inputs =
        vec![InputSpec { name: "x".into(), shape: dims(&[cin, hw, hw]), modality: None, optional: false, value: 0 }];
    let variants = vec![
        table("fog=0.05", &[(scale1, fog_s1), (shift1, fog_t1), (scale2, fog_s2)]),
        table("gamma=2", &[(w, gamma_w), (shift2, gamma_t2)]),
    ];
    let m = manifest(inputs, values, steps, 2, 2, s.specs, variants);
    let plan = Plan::new(m, s.data).expect("a valid plan");
    let weights = HashMap::from([(BASE_VARIANT, base), ("fog=0.05", fog), ("gamma=2", gamma)]);
    ConvPlan { plan, cin, cout, hw, weights }
}

/// The conv plan computed naively in f64.
pub fn conv_reference(x: &[f32], p: &ConvPlan, w: &ConvWeights) -> Vec<f64> {
    let (cin, cout, hw) = (p.cin, p.cout, p.hw);
    let n = x.len() / (cin * hw * hw);
    let mut y = Vec::with_capacity(n * cout * hw * hw);
    for b in 0..n {
        for o in 0..cout {
            for i in 0..hw {
                for j in 0..hw {
                    let mut acc = 0.0f64;
                    for c in 0..cin {
                        for ki in 0..3 {
                            for kj in 0..3 {
                                let (ii, jj) = ((i + ki) as isize - 1, (j + kj) as isize - 1);
                                if ii < 0 || jj < 0 || ii >= hw as isize || jj >= hw as isize {
                                    continue;
                                }
                                let xv = x[((b * cin + c) * hw + ii as usize) * hw + jj as usize];
                                let wv = w.w[((o * cin + c) * 3 + ki) * 3 + kj];
                                acc += f64::from(xv) * f64::from(wv);
                            }
                        }
                    }
                    let h = (acc * f64::from(w.scale1[o]) + f64::from(w.shift1[o])).max(0.0);
                    y.push(h * f64::from(w.scale2[o]) + f64::from(w.shift2[o]));
                }
            }
        }
    }
    y
}

pub fn assert_close(got: &[f32], want: &[f64], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
        assert!((f64::from(g) - w).abs() <= 1e-4 * (1.0 + w.abs()), "{what}: element {i} is {g}, expected {w}");
    }
}

/// Runs with input `x` of shape `shape` and returns output `y`.
pub fn run(s: &mut Session, x: &[f32], shape: &[usize]) -> Vec<f32> {
    let mut out = s.run(&[Input { name: "x", data: x, shape }]).expect("runs");
    assert_eq!(out.len(), 1);
    out.pop().expect("one output").1.data
}

/// Output of a fresh session under `key`.
pub fn fresh(plan: &Arc<Plan>, key: &str, threads: usize, x: &[f32], shape: &[usize]) -> Vec<f32> {
    let mut s = Session::new(Arc::clone(plan), threads).expect("session");
    s.set_variant(key).expect("known key");
    run(&mut s, x, shape)
}

// ---------------------------------------------------------------------------------------
// (e) Bad variant tables and keys
// ---------------------------------------------------------------------------------------

/// The MLP plan's manifest and tensors with its variant tables edited by `edit`.
pub fn edited(edit: impl FnOnce(&mut Vec<VariantTable>)) -> (Manifest, Vec<Vec<f32>>) {
    let p = mlp(4, 3).plan;
    let mut m = p.manifest.clone();
    let tensors = (0..m.tensors.len()).map(|i| p.tensor(i).to_vec()).collect();
    edit(&mut m.variants);
    (m, tensors)
}

pub fn refused(edit: impl FnOnce(&mut Vec<VariantTable>)) -> String {
    let (m, tensors) = edited(edit);
    match Plan::new(m, tensors) {
        Err(e @ PlanError::Manifest { .. }) => e.to_string(),
        Err(e) => panic!("expected a manifest error, got {e}"),
        Ok(_) => panic!("an invalid variant table was accepted"),
    }
}
