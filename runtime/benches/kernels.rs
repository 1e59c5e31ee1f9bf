//! Criterion benchmarks of the GEMM-based kernels at 2 threads: sgemm 512³, conv2d on
//! ResNet-18's layer shapes (batch 1) with the algorithm `conv::choose` picks, and a
//! transformer-sized linear; and the polynomial unary kernels against naive libm loops. Throughput is reported in FLOP/s (criterion's "elem/s").
//!
//! `cargo bench -p readi-runtime --bench kernels` runs all; a filter such as `conv2d`
//! selects. With `READI_BENCH_ALL_ALGOS=1` every other algorithm that supports a conv
//! layer is measured too, as `alt-<algo>`. `runtime/benches/ort_kernels.py` runs this and
//! ONNX Runtime and prints both side by side.

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use readi_runtime::kernels::Epilogue;
use readi_runtime::kernels::conv::{self, Conv2dShape, ConvAlgo};
use readi_runtime::kernels::gemm::{MatMut, MatRef, sgemm};
use readi_runtime::kernels::linear::{WeightLayout, linear};
use readi_runtime::testdata::data;

const THREADS: usize = 2;

fn pool() -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new().num_threads(THREADS).build().expect("rayon pool")
}

/// ResNet-18's conv layers at 224x224, batch 1 (name, cin, h·w, cout, k, stride, pad).
const RESNET18: [(&str, usize, usize, usize, usize, usize, usize); 11] = [
    ("conv1_7x7s2_3_64", 3, 224, 64, 7, 2, 3),
    ("l1_3x3_64", 64, 56, 64, 3, 1, 1),
    ("l2_3x3s2_64_128", 64, 56, 128, 3, 2, 1),
    ("l2_3x3_128", 128, 28, 128, 3, 1, 1),
    ("l3_3x3s2_128_256", 128, 28, 256, 3, 2, 1),
    ("l3_3x3_256", 256, 14, 256, 3, 1, 1),
    ("l4_3x3s2_256_512", 256, 14, 512, 3, 2, 1),
    ("l4_3x3_512", 512, 7, 512, 3, 1, 1),
    ("ds_1x1s2_64_128", 64, 56, 128, 1, 2, 0),
    ("ds_1x1s2_128_256", 128, 28, 256, 1, 2, 0),
    ("ds_1x1s2_256_512", 256, 14, 512, 1, 2, 0),
];

fn bench_sgemm(c: &mut Criterion) {
    let pool = pool();
    let n = 512;
    let (a, b) = (data(n * n, 1), data(n * n, 2));
    let mut out = vec![0.0; n * n];
    let mut g = c.benchmark_group("sgemm");
    g.throughput(Throughput::Elements(2 * (n * n * n) as u64));
    g.bench_function("512x512x512", |bench| {
        pool.install(|| {
            bench.iter(|| {
                sgemm(
                    MatRef::row_major(&a, n, n),
                    MatRef::row_major(&b, n, n),
                    MatMut::row_major(&mut out, n, n),
                    false,
                    THREADS,
                );
                black_box(&out);
            })
        })
    });
    g.finish();
}

fn bench_conv(c: &mut Criterion) {
    let pool = pool();
    let all = std::env::var_os("READI_BENCH_ALL_ALGOS").is_some();
    let mut g = c.benchmark_group("conv2d");
    g.sample_size(30).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(2));
    for (name, cin, hw, cout, k, stride, pad) in RESNET18 {
        let s = Conv2dShape::square(1, cin, hw, cout, k, stride, pad, 1);
        let o = s.oh;
        let x = data(cin * hw * hw, 3);
        let w = data(cout * cin * k * k, 4);
        let scale: Vec<f32> = data(cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(cout, 6);
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(readi_plan::ops::Activation::Relu) };
        let mut out = vec![0.0; cout * o * o];
        g.throughput(Throughput::Elements(2 * (cout * o * o * cin * k * k) as u64));
        let chosen = conv::choose(&s);
        let others = ConvAlgo::ALL.into_iter().filter(|&a| all && a != chosen && a.supports(&s));
        for (algo, id) in
            std::iter::once((chosen, chosen.name().to_string())).chain(others.map(|a| (a, format!("alt-{}", a.name()))))
        {
            let mut packed = vec![0.0; conv::packed_weight_len(&s, algo)];
            conv::pack_weight(&s, algo, &w, &mut packed);
            let mut scratch = vec![0.0; conv::scratch_len(&s, algo, THREADS)];
            g.bench_function(BenchmarkId::new(name, id), |bench| {
                pool.install(|| {
                    bench.iter(|| {
                        conv::conv2d(&s, algo, &packed, &ep, &x, &mut out, &mut scratch, THREADS);
                        black_box(&out);
                    })
                })
            });
        }
    }
    g.finish();
}

fn bench_linear(c: &mut Criterion) {
    let pool = pool();
    let (rows, fin, fout) = (196, 384, 1536);
    let (x, w, bias) = (data(rows * fin, 7), data(fout * fin, 8), data(fout, 9));
    let ep = Epilogue { scale: None, shift: Some(&bias), act: None };
    let mut out = vec![0.0; rows * fout];
    let mut g = c.benchmark_group("linear");
    g.throughput(Throughput::Elements(2 * (rows * fin * fout) as u64));
    g.bench_function("196x384x1536", |bench| {
        pool.install(|| {
            bench.iter(|| {
                linear(&x, rows, fin, &w, WeightLayout::InOut, fout, &ep, &mut out, THREADS);
                black_box(&out);
            })
        })
    });
    g.finish();
}

/// The polynomial unary kernels against a naive loop calling libm on the same data (one
/// thread, 16384 elements, below the size that goes parallel): "no new operator slower
/// than a naive loop". `cargo bench -p readi-runtime --bench kernels unary`.
fn bench_unary(c: &mut Criterion) {
    use readi_runtime::kernels::elementwise::{activation, scalar};
    use readi_runtime::kernels::{Activation, BinaryOp};
    let n = 1 << 14;
    let x: Vec<f32> = data(n, 10).iter().map(|v| v * 8.0).collect();
    let pos: Vec<f32> = x.iter().map(|v| v.abs() + 1e-3).collect();
    let mut out = vec![0.0; n];
    let mut g = c.benchmark_group("unary");
    g.throughput(Throughput::Elements(n as u64));
    type Naive = fn(f32) -> f32;
    let cases: [(&str, Activation, Naive, &[f32]); 6] = [
        ("exp", Activation::Exp, f32::exp, &x),
        ("log", Activation::Log, f32::ln, &pos),
        ("erf", Activation::Erf, libm::erff, &x),
        ("tanh", Activation::Tanh, f32::tanh, &x),
        ("elu", Activation::Elu { alpha: 1.0 }, |v| if v > 0.0 { v } else { v.exp_m1() }, &x),
        ("hardswish", Activation::Hardswish, |v| v * (v + 3.0).clamp(0.0, 6.0) / 6.0, &x),
    ];
    for (name, act, naive, input) in cases {
        g.bench_function(BenchmarkId::new("readi", name), |bench| {
            bench.iter(|| {
                activation(act, black_box(input), &mut out);
                black_box(&out);
            })
        });
        g.bench_function(BenchmarkId::new("naive", name), |bench| {
            bench.iter(|| {
                for (o, &v) in out.iter_mut().zip(black_box(input)) {
                    *o = naive(v);
                }
                black_box(&out);
            })
        });
    }
    g.bench_function(BenchmarkId::new("readi", "pow1.5"), |bench| {
        bench.iter(|| {
            scalar(BinaryOp::Pow, black_box(&pos), 1.5, false, &mut out);
            black_box(&out);
        })
    });
    g.bench_function(BenchmarkId::new("naive", "pow1.5"), |bench| {
        bench.iter(|| {
            // The exponent a run-time value, as the kernel gets it.
            let e = black_box(1.5f32);
            for (o, &v) in out.iter_mut().zip(black_box(&pos)) {
                *o = v.powf(e);
            }
            black_box(&out);
        })
    });
    g.finish();
}

criterion_group!(benches, bench_sgemm, bench_conv, bench_linear, bench_unary);
criterion_main!(benches);
