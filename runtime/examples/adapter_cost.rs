//! What a residual bottleneck adapter (squeeze 2, ReLU) adds to the conv it follows on
//! ResNet-18's adapted layers (each BasicBlock's conv2, with its residual and ReLU), at 1
//! and 2 threads: the layer with and without its adapter in alternating calls, the median
//! of the pairs' differences, and the adapter's multiply-adds per second at that median.
//! `cargo run --release -p readi-runtime --example adapter_cost [filter]`.
use std::hint::black_box;

use readi_plan::ops::Activation;
use readi_runtime::kernels::Epilogue;
use readi_runtime::kernels::conv::{self, Adapter, Conv2dShape, ConvAlgo};
use readi_runtime::testdata::data;

#[path = "common/paired.rs"]
mod paired;

/// A layer: name, its shape, and the algorithm the ResNet-18 plan gives it.
struct Layer(&'static str, Conv2dShape, ConvAlgo);

fn main() {
    let filter = std::env::args().nth(1).unwrap_or_default();
    let layers = [
        Layer("layer1 64 56x56", Conv2dShape::square(1, 64, 56, 64, 3, 1, 1, 1), ConvAlgo::Winograd4),
        Layer("layer2 128 28x28", Conv2dShape::square(1, 128, 28, 128, 3, 1, 1, 1), ConvAlgo::Winograd4),
        Layer("layer3 256 14x14", Conv2dShape::square(1, 256, 14, 256, 3, 1, 1, 1), ConvAlgo::Winograd2),
        Layer("layer4 512 7x7", Conv2dShape::square(1, 512, 7, 512, 3, 1, 1, 1), ConvAlgo::Panels),
    ];
    for Layer(name, s, algo) in layers {
        if !name.contains(&filter) {
            continue;
        }
        let mid = s.cout / 2;
        let x = data(s.cin * s.h * s.w, 3);
        let res = data(s.cout * s.oh * s.ow, 9);
        let scale: Vec<f32> = data(s.cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(s.cout, 6);
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) };
        let mut out = vec![0.0; s.cout * s.oh * s.ow];
        let mut w = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &data(s.cout * s.k(), 4), &mut w);
        let (down, up) = (data(mid * s.cout, 7), data(s.cout * mid, 8));
        let (bd, bu) = (data(mid, 10), data(s.cout, 11));
        let ad = Adapter { down: &down, down_bias: &bd, up: &up, up_bias: &bu, mid, act: Activation::Relu };
        let macs = 2.0 * (mid * s.cout * s.oh * s.ow) as f64;
        let mut line = format!("{name:18}");
        for threads in [1, 2] {
            let need = conv::adapter_scratch_len(&s, algo, 0, mid, threads).expect("a size");
            let mut scratch = vec![0.0; need];
            let (added, ratio) = paired::with_and_without(threads, |on| {
                let adapter = on.then_some(&ad);
                let res = Some(&res[..]);
                conv::conv2d_fused(&s, algo, &w, None, adapter, &ep, &x, res, &mut out, &mut scratch, threads);
                black_box(&out);
            });
            let gfma = macs / added * 1e-3;
            line += &format!("  {threads}T +{added:5.1} us ({ratio:.3}x, {gfma:4.1} GFMA/s)");
        }
        println!("{line}");
    }
}
