//! What a fused LoRA branch (rank 4) adds to a conv on ResNet-18's LoRA layers (layer3,
//! layer4: the 3x3 convs issue 11 puts branches on), at 1 and 2 threads: the layer with
//! and without its branch in alternating calls, the median of the pairs' differences.
//! `cargo run --release -p readi-runtime --example lora_cost [filter]`.
use std::hint::black_box;

use readi_runtime::kernels::conv::{self, Conv2dShape, ConvAlgo};
use readi_runtime::kernels::{Epilogue, Lora};
use readi_runtime::testdata::data;

#[path = "common/paired.rs"]
mod paired;

/// A layer: name, its shape, and the algorithm the ResNet-18 plan gives it.
struct Layer(&'static str, Conv2dShape, ConvAlgo);

fn main() {
    let filter = std::env::args().nth(1).unwrap_or_default();
    let layers = [
        Layer("layer3 3x3 256 14x14", Conv2dShape::square(1, 256, 14, 256, 3, 1, 1, 1), ConvAlgo::Winograd2),
        Layer("layer3.0 3x3/2 128->256", Conv2dShape::square(1, 128, 28, 256, 3, 2, 1, 1), ConvAlgo::Im2col),
        Layer("layer4 3x3 512 7x7", Conv2dShape::square(1, 512, 7, 512, 3, 1, 1, 1), ConvAlgo::Im2col),
        Layer("layer4.0 3x3/2 256->512", Conv2dShape::square(1, 256, 14, 512, 3, 2, 1, 1), ConvAlgo::Im2col),
    ];
    let rank = 4;
    for Layer(name, s, algo) in layers {
        if !name.contains(&filter) {
            continue;
        }
        let x = data(s.cin * s.h * s.w, 3);
        let scale: Vec<f32> = data(s.cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(s.cout, 6);
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(readi_plan::ops::Activation::Relu) };
        let mut out = vec![0.0; s.cout * s.oh * s.ow];
        let mut w = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &data(s.cout * s.k(), 4), &mut w);
        let sa = conv::lora_a_shape(&s, rank);
        let mut a = vec![0.0; conv::packed_weight_len(&sa, algo)];
        conv::pack_weight(&sa, algo, &data(rank * s.k(), 7), &mut a);
        let b = data(s.cout * rank, 8);
        let lora = Lora { a: &a, b: &b, rank };
        let mut scratch = vec![0.0; conv::lora_scratch_len(&s, algo, rank, 2)];
        let mut line = format!("{name:26}");
        for threads in [1, 2] {
            let (added, ratio) = paired::with_and_without(threads, |on| {
                let branch = on.then_some(&lora);
                conv::conv2d_lora(&s, algo, &w, branch, &ep, &x, &mut out, &mut scratch, threads);
                black_box(&out);
            });
            line += &format!("  {threads}T +{added:5.1} us ({ratio:.3}x)");
        }
        println!("{line}");
    }
}
