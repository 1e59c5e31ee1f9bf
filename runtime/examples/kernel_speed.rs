//! Median times of the memory-bound and transform kernels on ResNet-18 / ViT-S shapes, at
//! 1 and 2 threads: `cargo run --release -p readi-runtime --example kernel_speed [filter]`.
//! Conv layers run with the algorithm `conv::choose` picks.
use std::hint::black_box;
use std::time::Instant;

use readi_plan::ops::Activation;
use readi_runtime::kernels::conv::{self, Conv2dShape};
use readi_runtime::kernels::pool::{Pool2dShape, PoolKind, pool2d};
use readi_runtime::kernels::resize::{ResizeMode, upsample};
use readi_runtime::kernels::{BinaryOp, Epilogue, elementwise, layout, norm, reduce, softmax};
use readi_runtime::testdata::data;

fn time(name: &str, filter: &str, mut f: impl FnMut(usize) + Send) {
    if !name.contains(filter) {
        return;
    }
    let mut line = format!("{name:40}");
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
        let mut ts = Vec::new();
        pool.install(|| {
            for _ in 0..5 {
                f(threads);
            }
            let start = Instant::now();
            // At least 40 runs and 0.3 s.
            while ts.len() < 40 || start.elapsed().as_secs_f64() < 0.3 {
                let t = Instant::now();
                f(threads);
                ts.push(t.elapsed().as_secs_f64());
            }
        });
        ts.sort_by(f64::total_cmp);
        line += &format!("  {threads}T {:8.1} us", ts[ts.len() / 2] * 1e6);
    }
    println!("{line}");
}

fn main() {
    let filter = std::env::args().nth(1).unwrap_or_default();
    let f = filter.as_str();

    // Softmax: ViT attention rows [6, 196, 196], and a middle axis.
    let x = data(6 * 196 * 196, 1);
    let mut out = vec![0.0; x.len()];
    time("softmax [1176,196] last axis", f, |_| softmax::softmax(&x, 1176, 196, 1, &mut out));
    time("softmax [56,4096] last axis", f, |_| softmax::softmax(&x[..56 * 4096], 56, 4096, 1, &mut out[..56 * 4096]));
    let xs = data(8 * 64 * 196, 1);
    let mut os = vec![0.0; xs.len()];
    time("softmax [8,64,196] middle axis", f, |_| softmax::softmax(&xs, 8, 64, 196, &mut os));

    // LayerNorm [196, 384].
    let x = data(196 * 384, 2);
    let (w, b) = (data(384, 3), data(384, 4));
    let mut out = vec![0.0; x.len()];
    time("layernorm [196,384]", f, |_| norm::layernorm(&x, 196, 384, Some(&w), Some(&b), 1e-6, &mut out));

    // Elementwise on ViT shapes.
    let a = data(196 * 384, 5);
    let b = data(196 * 384, 6);
    let mut out = vec![0.0; a.len()];
    time("binary add [196,384]", f, |_| {
        elementwise::binary(BinaryOp::Add, &a, &[1, 196, 384], &b, &[1, 196, 384], &mut out, &[1, 196, 384])
    });
    let a = data(64 * 56 * 56, 5);
    let b = data(64, 6);
    let mut out = vec![0.0; a.len()];
    time("binary mul [1,64,56,56]x[1,64,1,1]", f, |_| {
        elementwise::binary(BinaryOp::Mul, &a, &[1, 64, 56, 56], &b, &[1, 64, 1, 1], &mut out, &[1, 64, 56, 56])
    });
    // Activations over EfficientNet-B0's first expansion [96, 112, 112].
    let a = data(96 * 112 * 112, 7);
    let mut out = vec![0.0; a.len()];
    for act in [Activation::Silu, Activation::Sigmoid, Activation::Relu6] {
        time(&format!("{act:?} [96,112,112]"), f, |_| elementwise::activation(act, &a, &mut out));
    }
    let a = data(6 * 196 * 196, 7);
    let mut out = vec![0.0; a.len()];
    time("scalar mul [6,196,196]", f, |_| elementwise::scalar(BinaryOp::Mul, &a, 0.125, false, &mut out));
    time("scalar div [6,196,196]", f, |_| elementwise::scalar(BinaryOp::Div, &a, 3.0, true, &mut out));

    // Pooling: ResNet's maxpool, and a 2x2 average.
    let s = Pool2dShape {
        nc: 64,
        h: 112,
        w: 112,
        kh: 3,
        kw: 3,
        stride_h: 2,
        stride_w: 2,
        pad_h: 1,
        pad_w: 1,
        oh: 56,
        ow: 56,
        ceil_mode: false,
        count_include_pad: true,
    };
    let x = data(64 * 112 * 112, 8);
    let mut out = vec![0.0; 64 * 56 * 56];
    time("maxpool 3x3/2 [64,112,112]", f, |_| pool2d(PoolKind::Max, &s, &x, &mut out));
    let s2 = Pool2dShape { kh: 2, kw: 2, pad_h: 0, pad_w: 0, ..s };
    time("avgpool 2x2/2 [64,112,112]", f, |_| pool2d(PoolKind::Avg, &s2, &x, &mut out));

    // Permutes of ViT attention.
    let x = data(196 * 384, 9);
    let mut out = vec![0.0; x.len()];
    time("permute [1,196,6,64]->[0,2,1,3]", f, |_| layout::permute(&x, &[1, 196, 6, 64], &[0, 2, 1, 3], &mut out));
    time("permute [1,196,6,64]->[0,2,3,1]", f, |_| layout::permute(&x, &[1, 196, 6, 64], &[0, 2, 3, 1], &mut out));
    let x = data(64 * 56 * 56, 9);
    let mut out = vec![0.0; x.len()];
    time("permute NCHW->NHWC [1,64,56,56]", f, |_| layout::permute(&x, &[1, 64, 56, 56], &[0, 2, 3, 1], &mut out));
    time("permute [64,56,56]->[2,0,1]", f, |_| layout::permute(&x, &[64, 56, 56], &[2, 0, 1], &mut out));

    // Mean over tokens and over spatial axes.
    let x = data(196 * 384, 10);
    let mut out = vec![0.0; 384];
    time("mean [1,196,384] axis 1", f, |_| reduce::mean(&x, &[1, 196, 384], &[1], &mut out));
    let x = data(512 * 49, 10);
    let mut out = vec![0.0; 512];
    time("mean [1,512,7,7] axes 2,3", f, |_| reduce::mean(&x, &[1, 512, 7, 7], &[2, 3], &mut out));

    // Variance over channels, the last axis kept, against plain two-pass loops: one output
    // at a time, and one channel row at a time.
    let x = data(256 * 56 * 56, 10);
    let mut out = vec![0.0; 56 * 56];
    let var = reduce::ReduceKind::Var { correction: 1 };
    time("var [1,256,56,56] axis 1", f, |_| reduce::reduce(var, &x, &[1, 256, 56, 56], &[1], &mut out));
    time("var [1,256,56,56] axis 1, naive loop per output", f, |_| {
        for (o, v) in out.iter_mut().enumerate() {
            let mean = (0..256).map(|c| x[c * 3136 + o]).sum::<f32>() / 256.0;
            *v = (0..256).map(|c| (x[c * 3136 + o] - mean).powi(2)).sum::<f32>() / 255.0;
        }
        black_box(&out);
    });
    let mut mean = vec![0.0f32; 56 * 56];
    time("var [1,256,56,56] axis 1, naive row loop", f, |_| {
        mean.fill(0.0);
        out.fill(0.0);
        for row in x.chunks(3136) {
            mean.iter_mut().zip(row).for_each(|(m, &v)| *m += v / 256.0);
        }
        for row in x.chunks(3136) {
            out.iter_mut().zip(row).zip(&mean).for_each(|((o, &v), &m)| *o += (v - m) * (v - m) / 255.0);
        }
        black_box(&out);
    });

    // Upsampling x2 of [64, 56, 56].
    let x = data(64 * 56 * 56, 11);
    let mut out = vec![0.0; 64 * 112 * 112];
    for (name, mode) in [
        ("upsample nearest x2 [64,56,56]", ResizeMode::Nearest),
        ("upsample bilinear x2 [64,56,56]", ResizeMode::Bilinear),
    ] {
        time(name, f, |_| upsample(mode, false, Some((2.0, 2.0)), &x, 64, 56, 56, &mut out, 112, 112));
    }

    // Conv layers of ResNet-18 (224x224, batch 1) with the chosen algorithm.
    // Then MobileNetV2's and EfficientNet-B0's depthwise layers (strided, small planes).
    let layers: [(&str, usize, usize, usize, usize, usize, usize); 20] = [
        ("conv1_7x7s2_3_64", 3, 224, 64, 7, 2, 3),
        ("l1_3x3_64", 64, 56, 64, 3, 1, 1),
        ("l2_3x3s2_64_128", 64, 56, 128, 3, 2, 1),
        ("l2_3x3_128", 128, 28, 128, 3, 1, 1),
        ("l3_3x3_256", 256, 14, 256, 3, 1, 1),
        ("l4_3x3_512", 512, 7, 512, 3, 1, 1),
        ("ds_1x1s2_64_128", 64, 56, 128, 1, 2, 0),
        ("dw_3x3_64", 64, 56, 64, 3, 1, 1),
        ("dw_3x3s2_96@112", 96, 112, 96, 3, 2, 1),
        ("dw_3x3s2_144@56", 144, 56, 144, 3, 2, 1),
        ("dw_3x3s2_192@28", 192, 28, 192, 3, 2, 1),
        ("dw_3x3s2_576@14", 576, 14, 576, 3, 2, 1),
        ("dw_3x3_960@7", 960, 7, 960, 3, 1, 1),
        ("dw_5x5s2_144@56", 144, 56, 144, 5, 2, 2),
        ("dw_5x5s2_672@14", 672, 14, 672, 5, 2, 2),
        // EfficientNet-B0's stride-1 5x5 and 3x3 layers on small planes.
        ("dw_5x5_480@14", 480, 14, 480, 5, 1, 2),
        ("dw_5x5_1152@7", 1152, 7, 1152, 5, 1, 2),
        ("dw_3x3_1152@7", 1152, 7, 1152, 3, 1, 1),
        // MobileNetV3's squeeze-and-excitation convs: 1x1 on a 1x1 plane.
        ("se_fc1_960_240@1", 960, 1, 240, 1, 1, 0),
        ("se_fc2_240_960@1", 240, 1, 960, 1, 1, 0),
    ];
    for (name, cin, hw, cout, k, stride, pad) in layers {
        let groups = if name.starts_with("dw") { cin } else { 1 };
        let s = Conv2dShape::square(1, cin, hw, cout, k, stride, pad, groups);
        let o = s.oh;
        let algo = conv::choose(&s);
        let x = data(cin * hw * hw, 3);
        let w = data(cout * cin / groups * k * k, 4);
        let scale: Vec<f32> = data(cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(cout, 6);
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(readi_plan::ops::Activation::Relu) };
        let mut out = vec![0.0; cout * o * o];
        let mut packed = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &w, &mut packed);
        let mut scratch = vec![0.0; conv::scratch_len(&s, algo, 2)];
        time(&format!("conv {name} {}", algo.name()), f, |t| {
            conv::conv2d(&s, algo, &packed, &ep, &x, &mut out, &mut scratch, t);
            black_box(&out);
        });
    }

    // EfficientNet-B0's first expansion (1x1, 16 to 96 channels on 112x112) and a
    // depthwise layer, by activation: what each activation adds to the conv.
    let layers = [("expand_1x1_16_96@112", 16, 112, 96, 1, 1, 0, 1), ("dw_3x3_144@56", 144, 56, 144, 3, 1, 1, 144)];
    for (name, cin, hw, cout, k, stride, pad, groups) in layers {
        let s = Conv2dShape::square(1, cin, hw, cout, k, stride, pad, groups);
        let algo = conv::choose(&s);
        let x = data(cin * hw * hw, 3);
        let w = data(cout * cin / groups * k * k, 4);
        let scale: Vec<f32> = data(cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(cout, 6);
        let mut out = vec![0.0; cout * s.oh * s.ow];
        let mut packed = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &w, &mut packed);
        let mut scratch = vec![0.0; conv::scratch_len(&s, algo, 2)];
        for act in [None, Some(Activation::Relu), Some(Activation::Silu), Some(Activation::Hardswish)] {
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act };
            time(&format!("conv {name} {} {act:?}", algo.name()), f, |t| {
                conv::conv2d(&s, algo, &packed, &ep, &x, &mut out, &mut scratch, t);
                black_box(&out);
            });
        }
    }
}
