//! Counts heap allocations: switching variants allocates nothing, and a run at a bound
//! batch size allocates only the outputs it returns. The counter is global, so this file
//! holds a single test (tests of one binary run on parallel threads).
//!
//! The plan uses only kernels that allocate nothing themselves, so the count is the
//! executor's. (At the time of writing the conv, linear, matmul, permute and mean kernels
//! allocate small work lists per call, a few to a few dozen, independent of the data.)
//!
//! A second plan, one `lss_bev_pool` step, runs under alternating calibrations: the
//! geometry it recomputes each time is written into buffers sized at bind time. A third,
//! the lidar front end (voxelizations and the depth map), hashes into tables sized at
//! bind time. A fourth, whose input's point count `P` changes every run, keeps its buffers
//! (counted in bytes).
//!
//! Sparse convs (`subm_conv3d`, `sparse_out_coords`, a strided `sparse_conv3d`,
//! `sparse_to_dense`) on changing coords: the hash tables and rulebooks rebuilt each run
//! are the buffers sized at bind time.

use std::alloc::System;
use std::sync::Arc;

use readi_plan::ops::{
    Activation, BinaryOp, ChannelAffine, Concat, GlobalAvgPool, LayerNorm, LidarDepthMap, LssBevPool, Pool2d, PoolKind,
    Pure, Reshape, Softmax, SparseConv3d, SparseOutCoords, SparseToDense, VoxelOutput, Voxelize, Window2, Window3,
};
use readi_plan::{Dim, VariantKey};
use readi_runtime::exec::{Input, Session};
use readi_runtime::kernels::conv::{self, Conv2dShape, ConvAlgo};
use readi_runtime::kernels::{merge, select};
use readi_runtime::plan::{
    EpilogueSpec, FORMAT_VERSION, InputSpec, Kernel, Manifest, OutputSpec, Plan, Replacement, Step, Storage,
    TensorData, TensorSpec, ValueSpec, VariantTable,
};
use readi_runtime::testdata::data;
use stats_alloc::{INSTRUMENTED_SYSTEM, Region, StatsAlloc};

#[global_allocator]
static GLOBAL: &StatsAlloc<System> = &INSTRUMENTED_SYSTEM;

fn shape(n: bool, rest: &[usize]) -> Vec<Dim> {
    let batch = n.then(|| Dim::symbol("N"));
    batch.into_iter().chain(rest.iter().map(|&d| Dim::from(d))).collect()
}

/// `x: [N, 4, 8, 8]` and an optional `z: [N, 2, 8, 8]` through a three-way concat (of
/// both inputs, one twice), a channel affine, max pooling, global average pooling, a
/// reshape, a layernorm, a residual addition, a GELU and a softmax; two outputs. Twelve
/// variants each replace the affine's shift and the layernorm's weight and bias, the odd
/// ones by f16 tensors (which a session decodes at a switch).
fn plan() -> Plan {
    let mut specs: Vec<TensorSpec> = Vec::new();
    let mut tensors: Vec<TensorData> = Vec::new();
    let mut add = |name: String, shape: Vec<usize>, seed: u64| {
        let d = data(shape.iter().product(), seed);
        let mut spec = TensorSpec::f32(name, shape);
        if seed >= 10 && seed % 2 == 1 {
            spec.dtype = readi_plan::DType::F16;
            tensors.push(d.iter().map(|&x| half::f16::from_f32(x)).collect::<Vec<_>>().into());
        } else {
            tensors.push(d.into());
        }
        specs.push(spec);
        specs.len() - 1
    };
    let aff_s = add("bn@scale".into(), vec![10], 3);
    let aff_t = add("bn@shift".into(), vec![10], 4);
    let ln_w = add("ln.weight".into(), vec![10], 5);
    let ln_b = add("ln.bias".into(), vec![10], 6);
    let mut variants = Vec::new();
    for v in 0..12u64 {
        let key = VariantKey::level("fog", v as f64);
        let t = add(format!("bn@shift~{key}"), vec![10], 10 + v);
        let w = add(format!("ln.weight~{key}"), vec![10], 30 + v);
        let b = add(format!("ln.bias~{key}"), vec![10], 50 + v);
        let replaces = [(aff_t, t), (ln_w, w), (ln_b, b)];
        variants.push(VariantTable {
            key,
            replaces: replaces.iter().map(|&(base, with)| Replacement { base, with, added: false }).collect(),
            tuned_elements: 0,
            added_elements: 0,
            fallback: Vec::new(),
            scopes: Vec::new(),
        });
    }
    let values = vec![
        ValueSpec { shape: shape(true, &[4, 8, 8]), storage: Storage::Input(0) },
        ValueSpec { shape: shape(true, &[2, 8, 8]), storage: Storage::Input(1) },
        ValueSpec { shape: shape(true, &[10, 8, 8]), storage: Storage::Slot(0) },
        ValueSpec { shape: shape(true, &[10, 8, 8]), storage: Storage::Slot(1) },
        ValueSpec { shape: shape(true, &[10, 4, 4]), storage: Storage::Slot(0) },
        ValueSpec { shape: shape(true, &[10, 1, 1]), storage: Storage::Slot(1) },
        ValueSpec { shape: shape(true, &[10]), storage: Storage::Slot(0) },
        ValueSpec { shape: shape(true, &[10]), storage: Storage::Slot(1) },
        ValueSpec { shape: shape(true, &[10]), storage: Storage::Slot(2) },
        ValueSpec { shape: shape(true, &[10]), storage: Storage::Slot(3) },
        ValueSpec { shape: shape(true, &[10]), storage: Storage::Slot(0) },
    ];
    let step = |path: &str, kernel, inputs: Vec<usize>, output| Step { path: path.into(), kernel, inputs, output };
    let steps = vec![
        step("cat", Kernel::Pure(Pure::Concat(Concat { axis: 1 })), vec![0, 1, 0], 2),
        step(
            "bn",
            Kernel::ChannelAffine {
                affine: ChannelAffine { channels: 10 },
                epilogue: EpilogueSpec { scale: Some(aff_s), shift: Some(aff_t), act: None, bn: None },
            },
            vec![2],
            3,
        ),
        step(
            "pool",
            Kernel::Pure(Pure::Pool(Pool2d {
                kind: PoolKind::Max,
                window: Window2 { kernel: [2, 2], stride: [2, 2], padding: [0, 0], dilation: [1, 1] },
                ceil_mode: false,
                count_include_pad: false,
            })),
            vec![3],
            4,
        ),
        step("gap", Kernel::Pure(Pure::GlobalAvgPool(GlobalAvgPool)), vec![4], 5),
        step("flat", Kernel::Pure(Pure::Reshape(Reshape { shape: shape(true, &[10]) })), vec![5], 6),
        step(
            "ln",
            Kernel::LayerNorm {
                norm: LayerNorm { features: 10, eps: 1e-5, affine: true },
                weight: Some(ln_w),
                bias: Some(ln_b),
            },
            vec![6],
            7,
        ),
        step("add", Kernel::Pure(Pure::Binary(BinaryOp::Add)), vec![7, 6], 8),
        step("act", Kernel::Pure(Pure::Activation(Activation::Gelu)), vec![8], 9),
        step("softmax", Kernel::Pure(Pure::Softmax(Softmax { axis: 1 })), vec![9], 10),
    ];
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "allocations".into(),
        model_params: Vec::new(),
        symbols: vec!["N".into()],
        inputs: vec![
            InputSpec { name: "x".into(), shape: shape(true, &[4, 8, 8]), modality: None, optional: false, value: 0 },
            InputSpec { name: "z".into(), shape: shape(true, &[2, 8, 8]), modality: None, optional: true, value: 1 },
        ],
        outputs: vec![OutputSpec::f32("probs", 10), OutputSpec::f32("act", 9)],
        values,
        steps,
        slots: 4,
        tensors: specs,
        params: Vec::new(),
        variants,
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, tensors).expect("a valid plan")
}

/// `x: [1, 64, 14, 14]` through a 3x3 conv to 4 channels at Winograd F(4x4) merged on
/// switch (its weight raw, a rank-2 LoRA with raw `A`), two variants replacing `A` and `B`.
fn switch_plan() -> Plan {
    use readi_plan::ops::Conv2d;
    use readi_runtime::plan::LoraSpec;
    let mut specs = Vec::new();
    let mut tensors = Vec::new();
    let mut add = |name: String, shape: Vec<usize>, seed: u64| {
        tensors.push(data(shape.iter().product(), seed));
        specs.push(TensorSpec::f32(name, shape));
        specs.len() - 1
    };
    let w = add("conv.weight".into(), vec![4, 64, 3, 3], 1);
    let a = add("conv.lora_A.weight".into(), vec![2, 64, 3, 3], 2);
    let b = add("conv.lora_B.weight@scaled".into(), vec![4, 2], 3);
    let mut variants = Vec::new();
    for v in 1..=2u64 {
        let key = VariantKey::level("fog", v as f64);
        let (va, vb) =
            (add(format!("a~{key}"), vec![2, 64, 3, 3], 10 + v), add(format!("b~{key}"), vec![4, 2], 20 + v));
        variants.push(VariantTable {
            key,
            replaces: [(a, va), (b, vb)].iter().map(|&(base, with)| Replacement { base, with, added: false }).collect(),
            tuned_elements: 0,
            added_elements: 0,
            fallback: Vec::new(),
            scopes: Vec::new(),
        });
    }
    let window = Window2 { kernel: [3, 3], stride: [1, 1], padding: [1, 1], dilation: [1, 1] };
    let kernel = Kernel::Conv2d {
        conv: Conv2d { in_channels: 64, out_channels: 4, window, groups: 1 },
        algo: ConvAlgo::Winograd4,
        weight: w,
        epilogue: EpilogueSpec::default(),
        lora: Some(LoraSpec { a, b, rank: 2, a_raw: true }),
        switch: true,
        adapter: None,
        residual: false,
        channel_scale: false,
    };
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "switch".into(),
        model_params: Vec::new(),
        symbols: Vec::new(),
        inputs: vec![InputSpec {
            name: "x".into(),
            shape: shape(false, &[1, 64, 14, 14]),
            modality: None,
            optional: false,
            value: 0,
        }],
        outputs: vec![OutputSpec::f32("y", 1)],
        values: vec![
            ValueSpec { shape: shape(false, &[1, 64, 14, 14]), storage: Storage::Input(0) },
            ValueSpec { shape: shape(false, &[1, 4, 14, 14]), storage: Storage::Slot(0) },
        ],
        steps: vec![Step { path: "conv".into(), kernel, inputs: vec![0], output: 1 }],
        slots: 1,
        tensors: specs,
        params: Vec::new(),
        variants,
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, tensors).expect("a valid plan")
}

/// What some work allocated: the fewest allocations and the fewest bytes of [`TRIALS`].
struct Fewest {
    allocations: usize,
    bytes: usize,
}

/// The counter sees every thread, and the pool's threads allocate now and then on their
/// own (rayon's queues, crossbeam's epoch bookkeeping), more under CPU contention. So each
/// count is taken over several trials and the smallest kept: an allocation made by
/// switching or by the executor shows in every trial.
const TRIALS: usize = 5;

/// Runs `work` [`TRIALS`] times under the counter; allocations include reallocations.
fn fewest(mut work: impl FnMut()) -> Fewest {
    let mut f = Fewest { allocations: usize::MAX, bytes: usize::MAX };
    for _ in 0..TRIALS {
        let region = Region::new(GLOBAL);
        work();
        let c = region.change();
        f.allocations = f.allocations.min(c.allocations + c.reallocations);
        f.bytes = f.bytes.min(c.bytes_allocated);
    }
    f
}

#[test]
fn switching_and_runs_allocate_only_outputs() {
    let plan = Arc::new(plan());
    assert_eq!(plan.variant_count(), 13);
    let keys: Vec<String> = plan.variant_keys().map(str::to_string).collect();
    let parsed: Vec<VariantKey> = keys.iter().map(|k| VariantKey::parse(k).expect("a key")).collect();
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    let handle = s.switch_handle();
    let x = data(3 * 4 * 64, 7);
    let z = data(3 * 2 * 64, 8);
    let with_z =
        [Input { name: "x", data: &x, shape: &[3, 4, 8, 8] }, Input { name: "z", data: &z, shape: &[3, 2, 8, 8] }];
    let without_z = &with_z[..1];
    // Bind, and let the thread pool and the GEMM's thread-local buffers settle.
    for _ in 0..20 {
        for inputs in [&with_z[..], without_z] {
            s.run(inputs).expect("runs");
        }
    }

    let switching = fewest(|| {
        for i in 0..10_000 {
            handle.set(&keys[i % keys.len()]).expect("known key");
            s.set_variant(&keys[(i + 5) % keys.len()]).expect("known key");
            handle.set_index(i % keys.len()).expect("in range");
            handle.set_key(&parsed[(i + 3) % keys.len()]).expect("known key");
            s.set_variant_key(&parsed[(i + 7) % keys.len()]).expect("known key");
        }
    })
    .allocations;
    assert_eq!(switching, 0, "50,000 switches allocated");

    // The first run after a switch packs the raw LoRA `A`s of the plan's Winograd convs
    // into the session's buffers (`Bound::pack_lora`, with the kernels' `pack_weight`):
    // nothing allocated either.
    let s3 = Conv2dShape {
        n: 1,
        cin: 64,
        h: 14,
        w: 14,
        cout: 4,
        kh: 3,
        kw: 3,
        stride_h: 1,
        stride_w: 1,
        pad_h: 1,
        pad_w: 1,
        dil_h: 1,
        dil_w: 1,
        groups: 1,
        oh: 14,
        ow: 14,
    };
    let raw = data(4 * 64 * 9, 9);
    let mut bufs: Vec<(ConvAlgo, Vec<f32>)> =
        [ConvAlgo::Winograd4, ConvAlgo::Winograd2].map(|a| (a, vec![0.0; conv::packed_weight_len(&s3, a)])).into();
    let packing = fewest(|| {
        for (algo, buf) in &mut bufs {
            conv::pack_weight(&s3, *algo, &raw, buf);
        }
    })
    .allocations;
    assert_eq!(packing, 0, "packing a raw LoRA A allocated");

    // A conv merged on switch: the re-merge (`kernels::merge::switch_pack`, W + B A
    // packed for Winograd into the working copy) allocates nothing, and in a session the
    // first run after a switch allocates what a steady run does.
    let (w, a, b) = (data(4 * 64 * 9, 11), data(2 * 64 * 9, 12), data(4 * 2, 13));
    let lora = readi_runtime::kernels::Lora { a: &a, b: &b, rank: 2 };
    let mut tmp = vec![0.0; merge::switch_tmp_len(&s3, ConvAlgo::Winograd4, true)];
    let mut working = vec![0.0; conv::packed_weight_len(&s3, ConvAlgo::Winograd4)];
    let merging = fewest(|| {
        merge::switch_pack(&s3, ConvAlgo::Winograd4, &w, Some(&lora), &mut tmp, &mut working);
        merge::switch_pack(&s3, ConvAlgo::Winograd2, &w, None, &mut tmp, &mut working[..4 * 64 * 16]);
    })
    .allocations;
    assert_eq!(merging, 0, "re-merging a layer allocated");

    // The run-time index kernels (a TransFusion head's top-k over its heatmap, the
    // gathers of the selected queries) work in their outputs.
    let heat = data(10 * 400, 15);
    let feats = data(8 * 400, 16);
    let (mut top, mut at) = (vec![0.0; 64], vec![0.0; 64]);
    let mut picked = vec![0.0; 8 * 64];
    let rows: Vec<f32> = (0..8 * 64).map(|j| (j * 37 % 400) as f32).collect();
    let mut gathered = vec![0.0; 8 * 64];
    let indexing = fewest(|| {
        select::topk(&heat, &[1, 4000], 64, 1, true, false, &mut top);
        select::topk(&heat, &[1, 4000], 64, 1, true, true, &mut at);
        for v in &mut at {
            *v %= 400.0;
        }
        select::index_select_at(&feats, &[8, 400], 1, &at, &mut picked).expect("in range");
        select::gather((&feats, &[8, 400]), (&rows, &[8, 64]), 1, &mut gathered, &[8, 64]).expect("in range");
    })
    .allocations;
    assert_eq!(indexing, 0, "the index kernels allocated");
    let switched = Arc::new(switch_plan());
    let mut sw = Session::new(Arc::clone(&switched), 1).expect("session");
    let xs = data(64 * 14 * 14, 14);
    let input = [Input { name: "x", data: &xs, shape: &[1, 64, 14, 14] }];
    for k in ["base", "fog=1", "fog=2", "base"] {
        sw.set_variant(k).expect("key");
        sw.run(&input).expect("runs");
    }
    let count = |sw: &mut Session, switch: bool| {
        fewest(|| {
            for i in 0..10 {
                if switch {
                    sw.set_variant(["fog=1", "fog=2"][i % 2]).expect("key");
                }
                sw.run(&input).expect("runs");
            }
        })
        .allocations
    };
    let (steady, switching) = (count(&mut sw, false), count(&mut sw, true));
    assert_eq!(switching, steady, "10 runs each after a switch allocated {switching}, 10 steady runs {steady}");

    // Each run returns a Vec of two (name, tensor) pairs: 1 + 2 * 3 allocations.
    let per_run = 7;
    let runs = 100;
    let running = fewest(|| {
        for i in 0..runs {
            handle.set_index(i % keys.len()).expect("in range");
            let out = s.run(if i % 2 == 0 { &with_z[..] } else { without_z }).expect("runs");
            assert_eq!(out.len(), 2);
        }
    })
    .allocations;
    // rayon's injector queue (every job handed to the pool from outside goes through it)
    // allocates a block per 63 jobs: one or two per trial.
    let slack = 2;
    assert!(
        (per_run * runs..=per_run * runs + slack).contains(&running),
        "{runs} runs made {running} allocations at least; their outputs need {}",
        per_run * runs
    );

    // An lss_bev_pool step: a run whose calibration differs from the last recomputes the
    // cached geometry in place, allocating nothing but the output (1 + 3 allocations).
    let mut bev = Session::new(Arc::new(bev_plan()), 2).expect("session");
    let (depth, context) = (data(2 * 4 * 24, 21), data(2 * 3 * 24, 22));
    let cal: Vec<[Vec<f32>; 4]> = [0.0f32, 0.3].iter().map(|&yaw| bev_calibration(yaw)).collect();
    fn bev_inputs<'a>(depth: &'a [f32], context: &'a [f32], c: &'a [Vec<f32>; 4]) -> Vec<Input<'a>> {
        vec![
            Input { name: "depth", data: depth, shape: &[1, 2, 4, 4, 6] },
            Input { name: "context", data: context, shape: &[1, 2, 3, 4, 6] },
            Input { name: "camera_intrinsics", data: &c[0], shape: &[1, 2, 4, 4] },
            Input { name: "camera2lidar", data: &c[1], shape: &[1, 2, 4, 4] },
            Input { name: "img_aug_matrix", data: &c[2], shape: &[1, 2, 4, 4] },
            Input { name: "lidar_aug_matrix", data: &c[3], shape: &[1, 4, 4] },
        ]
    }
    let both = [bev_inputs(&depth, &context, &cal[0]), bev_inputs(&depth, &context, &cal[1])];
    let first = bev.run(&both[0]).expect("runs");
    let second = bev.run(&both[1]).expect("runs");
    assert_ne!(first, second, "the calibrations give the same grid");
    let runs = 40;
    let recomputing = fewest(|| {
        for i in 0..runs {
            bev.run(&both[i % 2]).expect("runs");
        }
    })
    .allocations;
    assert!(
        (4 * runs..=4 * runs + slack).contains(&recomputing),
        "{runs} runs alternating two calibrations made {recomputing} allocations at least; their outputs need {}",
        4 * runs
    );

    // The lidar front end: hard and dynamic voxelization (their hash tables cleared and
    // refilled in place) and the depth map, allocating nothing but the five outputs.
    let mut vox = Session::new(Arc::new(voxel_plan()), 2).expect("session");
    let points: Vec<f32> = data(300 * 4, 23).iter().map(|v| v * 6.0).collect();
    let cal = bev_calibration(0.2);
    let vox_inputs = [
        Input { name: "points", data: &points, shape: &[300, 4] },
        Input { name: "camera_intrinsics", data: &cal[0], shape: &[1, 2, 4, 4] },
        Input { name: "camera2lidar", data: &cal[1], shape: &[1, 2, 4, 4] },
        Input { name: "img_aug_matrix", data: &cal[2], shape: &[1, 2, 4, 4] },
        Input { name: "lidar_aug_matrix", data: &cal[3], shape: &[1, 4, 4] },
    ];
    let out = vox.run(&vox_inputs).expect("runs");
    assert!(out[1].1.data.iter().filter(|&&n| n > 0.0).count() > 10, "too few voxels");
    assert!(out[4].1.data.iter().filter(|&&d| d > 0.0).count() > 10, "too few depths");
    let voxelizing = fewest(|| {
        for _ in 0..runs {
            vox.run(&vox_inputs).expect("runs");
        }
    })
    .allocations;
    let per_run = 1 + 3 * 5;
    assert!(
        (per_run * runs..=per_run * runs + slack).contains(&voxelizing),
        "{runs} voxelizing runs made {voxelizing} allocations at least; their outputs need {}",
        per_run * runs
    );

    // A symbol only an input carries (`P`, a lidar sweep's point count): a run at
    // another `P` keeps the buffers it has. Rebinding would allocate the 256 KiB buffer
    // of the sum at every run; what a run allocates is its output and the broadcasting
    // add's small work lists.
    let mut sweeps = Session::new(Arc::new(points_plan()), 2).expect("session");
    let frames: Vec<Vec<f32>> = [5usize, 9, 17].iter().map(|&p| data(4 * p, p as u64)).collect();
    let dims: Vec<[usize; 4]> = frames.iter().map(|f| [1, 4, f.len() / 4, 1]).collect();
    let frame = |i: usize| [Input { name: "points", data: &frames[i], shape: &dims[i] }];
    for i in 0..3 {
        let out = sweeps.run(&frame(i)).expect("runs");
        let p = dims[i][2];
        let means = (0..4).map(|c| frames[i][c * p..(c + 1) * p].iter().sum::<f32>() / p as f32);
        let expected: Vec<f32> = means.zip(sweep_offsets()).map(|(m, o)| m + o).collect();
        let close = out[0].1.data.iter().zip(&expected).all(|(a, b)| (a - b).abs() < 1e-5);
        assert!(close, "sweep {i}: {:?}, not {expected:?}", out[0].1.data);
    }
    let runs = 30;
    let bytes = fewest(|| {
        for i in 0..runs {
            sweeps.run(&frame(i % 3)).expect("runs");
        }
    })
    .bytes;
    assert!(
        bytes < runs * 16 * 1024,
        "{runs} runs of sweeps of 5, 9 and 17 points allocated {bytes} bytes: the buffers were made anew"
    );

    // Sparse convs on two sets of active sites: nothing but the outputs (1 + 2 * 3).
    let mut sp = Session::new(Arc::new(sparse_plan()), 2).expect("session");
    let features = data(64 * 4, 31);
    let coord_sets: Vec<Vec<f32>> = [(40usize, 7usize), (25, 11)]
        .iter()
        .map(|&(n, step)| {
            let mut c = vec![-1.0f32; 64 * 3];
            for r in 0..n {
                let l = (r * step) % (5 * 9 * 7);
                c[3 * r..3 * r + 3].copy_from_slice(&[(l / 63) as f32, (l / 7 % 9) as f32, (l % 7) as f32]);
            }
            c
        })
        .collect();
    let sp_inputs = |c: &[f32]| {
        let (f, c) = (features.clone(), c.to_vec());
        (f, c)
    };
    let sets: Vec<(Vec<f32>, Vec<f32>)> = coord_sets.iter().map(|c| sp_inputs(c)).collect();
    let inputs: Vec<[Input<'_>; 2]> = sets
        .iter()
        .map(|(f, c)| {
            [Input { name: "features", data: f, shape: &[64, 4] }, Input { name: "coords", data: c, shape: &[64, 3] }]
        })
        .collect();
    let a = sp.run(&inputs[0]).expect("runs");
    let b = sp.run(&inputs[1]).expect("runs");
    assert_ne!(a, b, "the two site sets give the same outputs");
    let sparse_runs = fewest(|| {
        for i in 0..runs {
            sp.run(&inputs[i % 2]).expect("runs");
        }
    })
    .allocations;
    assert!(
        (7 * runs..=7 * runs + slack).contains(&sparse_runs),
        "{runs} sparse runs made {sparse_runs} allocations at least; their outputs need {}",
        7 * runs
    );
}

/// Hard voxelization (voxels, num_points), dynamic voxelization (features) of `[300, 4]`
/// points and their depth map in two cameras, as a five-step plan.
fn voxel_plan() -> Plan {
    let voxelize = |output, max_points| Voxelize {
        voxel_size: [0.5, 0.5, 1.0],
        point_cloud_range: [-4.0, -4.0, -2.0, 4.0, 4.0, 2.0],
        max_points,
        max_voxels: 64,
        output,
    };
    let kernels = [
        Pure::Voxelize(voxelize(VoxelOutput::Voxels, Some(3))),
        Pure::Voxelize(voxelize(VoxelOutput::NumPoints, Some(3))),
        Pure::Voxelize(voxelize(VoxelOutput::Coords, Some(3))),
        Pure::Voxelize(voxelize(VoxelOutput::Mean, None)),
        Pure::LidarDepthMap(LidarDepthMap { image_size: [64, 96] }),
    ];
    let out_shapes: [&[usize]; 5] = [&[64, 3, 4], &[64], &[64, 3], &[64, 4], &[1, 2, 1, 64, 96]];
    let names = ["points", "camera_intrinsics", "camera2lidar", "img_aug_matrix", "lidar_aug_matrix"];
    let in_shapes: [&[usize]; 5] = [&[300, 4], &[1, 2, 4, 4], &[1, 2, 4, 4], &[1, 2, 4, 4], &[1, 4, 4]];
    let mut values: Vec<ValueSpec> =
        (0..5).map(|i| ValueSpec { shape: shape(false, in_shapes[i]), storage: Storage::Input(i) }).collect();
    for (k, s) in out_shapes.iter().enumerate() {
        values.push(ValueSpec { shape: shape(false, s), storage: Storage::Slot(k) });
    }
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "voxel".into(),
        model_params: Vec::new(),
        symbols: Vec::new(),
        inputs: (0..5)
            .map(|i| InputSpec {
                name: names[i].into(),
                shape: values[i].shape.clone(),
                modality: None,
                optional: false,
                value: i,
            })
            .collect(),
        outputs: ["voxels", "num_points", "coords", "features", "depth"]
            .iter()
            .enumerate()
            .map(|(k, n)| OutputSpec::f32(*n, 5 + k))
            .collect(),
        values,
        steps: kernels
            .into_iter()
            .enumerate()
            .map(|(k, op)| Step {
                path: format!("step{k}"),
                inputs: if k == 4 { (0..5).collect() } else { vec![0] },
                kernel: Kernel::Pure(op),
                output: 5 + k,
            })
            .collect(),
        slots: 5,
        tensors: Vec::new(),
        params: Vec::new(),
        variants: Vec::new(),
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, Vec::<Vec<f32>>::new()).expect("a valid plan")
}

/// The per-channel means of the stored offsets, `[1, 4, 128, 128]`.
fn sweep_offsets() -> Vec<f32> {
    let t = data(4 * 128 * 128, 40);
    t.chunks(128 * 128).map(|c| c.iter().sum::<f32>() / c.len() as f32).collect()
}

/// `points: [1, 4, P, 1]` to its per-channel means, broadcast-added to stored offsets
/// `[1, 4, 128, 128]` and averaged again (the means plus the offsets' means): no buffer
/// depends on `P`.
fn points_plan() -> Plan {
    let p = vec![Dim::from(1usize), Dim::from(4usize), Dim::symbol("P"), Dim::from(1usize)];
    let values = vec![
        ValueSpec { shape: p.clone(), storage: Storage::Input(0) },
        ValueSpec { shape: shape(false, &[1, 4, 1, 1]), storage: Storage::Slot(0) },
        ValueSpec { shape: shape(false, &[1, 4, 128, 128]), storage: Storage::Tensor(0) },
        ValueSpec { shape: shape(false, &[1, 4, 128, 128]), storage: Storage::Slot(1) },
        ValueSpec { shape: shape(false, &[1, 4, 1, 1]), storage: Storage::Slot(0) },
    ];
    let step = |path: &str, kernel, inputs, output| Step { path: path.into(), kernel, inputs, output };
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "sweep".into(),
        model_params: Vec::new(),
        symbols: vec!["P".into()],
        inputs: vec![InputSpec { name: "points".into(), shape: p, modality: None, optional: false, value: 0 }],
        outputs: vec![OutputSpec::f32("means", 4)],
        values,
        steps: vec![
            step("mean", Kernel::Pure(Pure::GlobalAvgPool(GlobalAvgPool)), vec![0], 1),
            step("offset", Kernel::Pure(Pure::Binary(BinaryOp::Add)), vec![1, 2], 3),
            step("mean2", Kernel::Pure(Pure::GlobalAvgPool(GlobalAvgPool)), vec![3], 4),
        ],
        slots: 2,
        tensors: vec![TensorSpec::f32("offsets", vec![1, 4, 128, 128])],
        params: Vec::new(),
        variants: Vec::new(),
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, vec![data(4 * 128 * 128, 40)]).expect("a valid plan")
}

/// `features [64, 4]` and `coords [64, 3]` in a `[5, 9, 7]` grid through a submanifold
/// 3x3x3 conv (output `subm`) and, at the sites `sparse_out_coords` finds, a strided one
/// (stride 2, padding 1) made dense (output `dense`).
fn sparse_plan() -> Plan {
    let grid = [5, 9, 7];
    let win =
        |stride, padding| Window3 { kernel: [3; 3], stride: [stride; 3], padding: [padding; 3], dilation: [1; 3] };
    let v = |s: &[usize], storage| ValueSpec { shape: shape(false, s), storage };
    let values = vec![
        v(&[64, 4], Storage::Input(0)),
        v(&[64, 3], Storage::Input(1)),
        v(&[3, 3, 3, 4, 8], Storage::Tensor(0)),
        v(&[64, 8], Storage::Slot(0)),
        v(&[64, 3], Storage::Slot(1)),
        v(&[3, 3, 3, 4, 6], Storage::Tensor(1)),
        v(&[64, 6], Storage::Slot(2)),
        v(&[1, 6, 3, 5, 4], Storage::Slot(3)),
    ];
    let step = |path: &str, kernel: Pure, inputs: Vec<usize>, output| Step {
        path: path.into(),
        kernel: Kernel::Pure(kernel),
        inputs,
        output,
    };
    let subm = SparseConv3d { spatial_shape: grid, window: win(1, 1), subm: true, bias: false };
    let down = SparseConv3d { spatial_shape: grid, window: win(2, 1), subm: false, bias: false };
    let coords = SparseOutCoords { spatial_shape: grid, window: win(2, 1), max_out: None };
    let steps = vec![
        step("subm", Pure::SparseConv3d(subm), vec![0, 1, 1, 2], 3),
        step("down_coords", Pure::SparseOutCoords(coords), vec![1], 4),
        step("down", Pure::SparseConv3d(down), vec![0, 1, 4, 5], 6),
        step("dense", Pure::SparseToDense(SparseToDense { spatial_shape: [3, 5, 4] }), vec![6, 4], 7),
    ];
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "sparse".into(),
        model_params: Vec::new(),
        symbols: Vec::new(),
        inputs: ["features", "coords"]
            .iter()
            .enumerate()
            .map(|(i, n)| InputSpec {
                name: (*n).into(),
                shape: values[i].shape.clone(),
                modality: None,
                optional: false,
                value: i,
            })
            .collect(),
        outputs: vec![OutputSpec::f32("subm", 3), OutputSpec::f32("dense", 7)],
        values,
        steps,
        slots: 4,
        tensors: vec![
            TensorSpec::f32("subm.weight", vec![3, 3, 3, 4, 8]),
            TensorSpec::f32("down.weight", vec![3, 3, 3, 4, 6]),
        ],
        params: Vec::new(),
        variants: Vec::new(),
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, vec![data(27 * 4 * 8, 41), data(27 * 4 * 6, 42)]).expect("a valid plan")
}

/// A row-major 4x4 from a 3x3 block and a translation.
fn mat4(r: [[f32; 3]; 3], t: [f32; 3]) -> Vec<f32> {
    let mut m = vec![0.0; 16];
    for i in 0..3 {
        m[i * 4..i * 4 + 3].copy_from_slice(&r[i]);
        m[i * 4 + 3] = t[i];
    }
    m[15] = 1.0;
    m
}

/// Two cameras (forward, backward) around a lidar turned by `yaw`.
fn bev_calibration(yaw: f32) -> [Vec<f32>; 4] {
    let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let k = mat4([[60.0, 0.0, 47.5], [0.0, 60.0, 31.5], [0.0, 0.0, 1.0]], [0.0; 3]);
    let front = mat4([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], [0.3, 0.1, 0.5]);
    let back = mat4([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], [-0.3, 0.1, 0.5]);
    let (c, s) = (yaw.cos(), yaw.sin());
    let lidar = mat4([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], [0.1, 0.0, 0.0]);
    [[k.clone(), k].concat(), [front, back].concat(), [mat4(id, [0.0; 3]), mat4(id, [0.0; 3])].concat(), lidar]
}

/// BEVFusion's view transform on two cameras (`lss_bev_pool`) as a one-step plan.
fn bev_plan() -> Plan {
    let op = LssBevPool {
        image_size: [64, 96],
        xbound: [-8.0, 8.0, 2.0],
        ybound: [-8.0, 8.0, 2.0],
        zbound: [-2.0, 2.0, 2.0],
        dbound: [2.0, 10.0, 2.0],
    };
    let shapes: [&[usize]; 6] = [&[2, 4, 4, 6], &[2, 3, 4, 6], &[2, 4, 4], &[2, 4, 4], &[2, 4, 4], &[4, 4]];
    let names = ["depth", "context", "camera_intrinsics", "camera2lidar", "img_aug_matrix", "lidar_aug_matrix"];
    let mut values: Vec<ValueSpec> = (0..6)
        .map(|i| ValueSpec { shape: shape(false, &[&[1], shapes[i]].concat()), storage: Storage::Input(i) })
        .collect();
    values.push(ValueSpec { shape: shape(false, &[1, 6, 8, 8]), storage: Storage::Slot(0) });
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: "bev".into(),
        model_params: Vec::new(),
        symbols: Vec::new(),
        inputs: (0..6)
            .map(|i| InputSpec {
                name: names[i].into(),
                shape: values[i].shape.clone(),
                modality: None,
                optional: false,
                value: i,
            })
            .collect(),
        outputs: vec![OutputSpec::f32("bev", 6)],
        values,
        steps: vec![Step {
            path: "bev".into(),
            kernel: Kernel::Pure(Pure::LssBevPool(op)),
            inputs: (0..6).collect(),
            output: 6,
        }],
        slots: 1,
        tensors: Vec::new(),
        params: Vec::new(),
        variants: Vec::new(),
        conditions: None,
        footprint: None,
    };
    Plan::new(manifest, Vec::<Vec<f32>>::new()).expect("a valid plan")
}
