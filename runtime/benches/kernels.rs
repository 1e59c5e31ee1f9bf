//! Criterion benchmarks of the GEMM-based kernels at 2 threads: sgemm 512³, conv2d on
//! ResNet-18's layer shapes (batch 1) with the algorithm `conv::choose` picks, and a
//! transformer-sized linear; conv_transpose2d on SECOND's FPN deblocks against the naive
//! scatter loop; conv3d on SECOND-style middle-encoder shapes against the naive loop; the polynomial unary kernels against naive libm loops; and pad, roll and
//! slice against naive index loops. Throughput is reported in FLOP/s (criterion's "elem/s").
//!
//! `cargo bench -p readi-runtime --bench kernels` runs all; a filter such as `conv2d`
//! selects. With `READI_BENCH_ALL_ALGOS=1` every other algorithm that supports a conv
//! layer is measured too, as `alt-<algo>`. `runtime/benches/ort_kernels.py` runs this and
//! ONNX Runtime and prints both side by side.
//!
//! Under `cargo bench`, after criterion's runs, a summary times each FLOP-bound kernel the
//! filter selects once more (median of nine calls) and prints its GFLOP/s as a fraction
//! of the machine's peak at the same thread count, measured by `readi_runtime::peak`.

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group};
use readi_runtime::kernels::Epilogue;
use readi_runtime::kernels::conv::{self, Conv2dShape, ConvAlgo};
use readi_runtime::kernels::gemm::{MatMut, MatRef, sgemm};
use readi_runtime::kernels::linear::{WeightLayout, linear};
use readi_runtime::peak;
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

/// Depthwise convs of ConvNeXt-T (7x7) and MobileNetV2 (3x3) at 224x224, batch 1 (name,
/// channels, h·w, k, stride; padding k / 2).
const DEPTHWISE: [(&str, usize, usize, usize, usize); 9] = [
    ("dw7x7_96_56", 96, 56, 7, 1),
    ("dw7x7_192_28", 192, 28, 7, 1),
    ("dw7x7_384_14", 384, 14, 7, 1),
    ("dw7x7_768_7", 768, 7, 7, 1),
    ("dw3x3s2_96_112", 96, 112, 3, 2),
    ("dw3x3_144_56", 144, 56, 3, 1),
    ("dw3x3_192_28", 192, 28, 3, 1),
    ("dw3x3_576_14", 576, 14, 3, 1),
    ("dw3x3_960_7", 960, 7, 3, 1),
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

/// The fused LoRA branch (rank 4, as in the ResNet-18 variants) on the Winograd layers of
/// ResNet-18's layer3 and layer4: `lora0` is the conv alone, `lora4` with the branch; the
/// ratio of the two is the branch's cost (`conv2d_lora` filters).
fn bench_conv_lora(c: &mut Criterion) {
    let pool = pool();
    let mut g = c.benchmark_group("conv2d_lora");
    g.sample_size(40).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(2));
    for (name, cin, hw, cout) in [("l3_3x3_256", 256, 14, 256), ("l4_3x3_512", 512, 7, 512)] {
        let s = Conv2dShape::square(1, cin, hw, cout, 3, 1, 1, 1);
        let algo = conv::choose(&s);
        let x = data(cin * hw * hw, 3);
        let w = data(cout * cin * 9, 4);
        let scale: Vec<f32> = data(cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(cout, 6);
        let ep =
            Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(readi_runtime::kernels::Activation::Relu) };
        let mut out = vec![0.0; cout * s.oh * s.ow];
        let mut packed = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &w, &mut packed);
        let rank = 4;
        let sa = conv::lora_a_shape(&s, rank);
        let mut packed_a = vec![0.0; conv::packed_weight_len(&sa, algo)];
        conv::pack_weight(&sa, algo, &data(rank * cin * 9, 7), &mut packed_a);
        let b = data(cout * rank, 8);
        let lora = conv::Lora { a: &packed_a, b: &b, rank };
        let mut scratch = vec![0.0; conv::lora_scratch_len(&s, algo, rank, THREADS)];
        for threads in [1, THREADS].into_iter().filter(|_| selected(&format!("conv2d_lora/{name}"))) {
            let run = |with: bool| {
                let l = with.then_some(&lora);
                conv::conv2d_lora(&s, algo, &packed, l, &ep, &x, &mut out, &mut scratch, threads);
                black_box(&out);
            };
            let ratio = pool.install(|| alternate(run));
            println!("conv2d_lora/{name}-{} at {threads} thread(s): with/without the branch {ratio}", algo.name());
        }
        for (id, l) in [("lora0", None), ("lora4", Some(&lora))] {
            let mut scratch = vec![0.0; conv::lora_scratch_len(&s, algo, l.map_or(0, |l| l.rank), THREADS)];
            g.bench_function(BenchmarkId::new(format!("{name}-{}", algo.name()), id), |bench| {
                pool.install(|| {
                    bench.iter(|| {
                        conv::conv2d_lora(&s, algo, &packed, l, &ep, &x, &mut out, &mut scratch, THREADS);
                        black_box(&out);
                    })
                })
            });
        }
    }
    g.finish();
}

/// Times `run(false)` (the base) and `run(true)` alternately, one call each, 400 times
/// (so that load from other processes hits both alike), and formats the ratio
/// `true / false` of their fastest tenths (the least disturbed calls; the code is
/// deterministic) and the median of the per-pair ratios.
fn alternate(mut run: impl FnMut(bool)) -> String {
    let mut time = |with: bool| {
        let t = std::time::Instant::now();
        run(with);
        t.elapsed().as_secs_f64()
    };
    let (mut base, mut new, mut pairs) = (vec![], vec![], vec![]);
    for i in 0..410 {
        let (b, w) = (time(false), time(true));
        if i >= 10 {
            base.push(b);
            new.push(w);
            pairs.push(w / b);
        }
    }
    for v in [&mut base, &mut new, &mut pairs] {
        v.sort_by(f64::total_cmp);
    }
    let fast = |v: &[f64]| v[..v.len() / 10].iter().sum::<f64>() / (v.len() / 10) as f64;
    let (b, w) = (fast(&base), fast(&new));
    format!(
        "{:.3}x fastest tenths ({:.1} vs {:.1} us), median pair {:.3}x",
        w / b,
        w * 1e6,
        b * 1e6,
        pairs[pairs.len() / 2]
    )
}

/// `conv_transpose2d` on SECOND's FPN deblock shapes (batch 1, bias and ReLU fused)
/// against the naive scatter loop (`conv_transpose::reference`, timed on its own: three
/// calls, the fastest printed with the ratio). `cargo bench -p readi-runtime --bench
/// kernels conv_transpose2d`.
fn bench_conv_transpose(c: &mut Criterion) {
    use readi_plan::ops::{ConvTranspose2d, Window2};
    use readi_runtime::kernels::conv_transpose;
    let pool = pool();
    let mut g = c.benchmark_group("conv_transpose2d");
    g.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    // (name, cin, cout, k = stride, h, w)
    let shapes = [("k2s2_128_128_124x108", 128, 128, 2, 124, 108), ("k4s4_256_256_50x44", 256, 256, 4, 50, 44)];
    for (name, cin, cout, k, h, w) in shapes {
        let window = Window2 { kernel: [k, k], stride: [k, k], padding: [0, 0], dilation: [1, 1] };
        let op = ConvTranspose2d { in_channels: cin, out_channels: cout, window, output_padding: [0, 0], groups: 1 };
        let s = op.shape(1, h, w);
        let x = data(s.cin * h * w, 3);
        let wt = data(s.weight_len(), 4);
        let bias = data(s.cout, 5);
        let ep = Epilogue { scale: None, shift: Some(&bias), act: Some(readi_plan::ops::Activation::Relu) };
        let mut out = vec![0.0; s.cout * s.oh * s.ow];
        let mut scratch = vec![0.0; conv_transpose::scratch_len(&s, THREADS).expect("fits")];
        g.throughput(Throughput::Elements(2 * (s.weight_len() * h * w) as u64));
        let mut fastest = f64::INFINITY;
        g.bench_function(name, |bench| {
            pool.install(|| {
                bench.iter(|| {
                    let t = std::time::Instant::now();
                    conv_transpose::conv_transpose2d(&s, &wt, &ep, &x, &mut out, &mut scratch, THREADS);
                    fastest = fastest.min(t.elapsed().as_secs_f64());
                    black_box(&out);
                })
            })
        });
        if !fastest.is_finite() {
            continue; // filtered out: criterion did not run it
        }
        let mut naive = f64::INFINITY;
        let mut want = vec![0.0; out.len()];
        for _ in 0..3 {
            let t = std::time::Instant::now();
            conv_transpose::reference(&s, &wt, &ep, &x, &mut want);
            naive = naive.min(t.elapsed().as_secs_f64());
            black_box(&want);
        }
        eprintln!(
            "conv_transpose2d/{name}: kernel {:.2} ms (fastest call, {THREADS} threads), naive loop {:.1} ms (1 thread): \
             {:.0}x",
            fastest * 1e3,
            naive * 1e3,
            naive / fastest
        );
    }
    g.finish();
}

/// `conv3d` on SECOND-style middle-encoder shapes (batch 1, bias and ReLU fused): a
/// 3x3x3 block, its stride-2 downsampling, the depth downsampling (kernel (3, 1, 1),
/// stride (2, 1, 1)) and a depthwise 3x3x3, against the naive loop
/// (`conv3d::reference`, timed on its own: three calls, the fastest printed with the
/// ratio). `cargo bench -p readi-runtime --bench kernels conv3d`.
fn bench_conv3d(c: &mut Criterion) {
    use readi_plan::ops::{Conv3d, Window3};
    use readi_runtime::kernels::conv3d;
    let pool = pool();
    let mut g = c.benchmark_group("conv3d");
    g.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    // (name, cin, cout, kernel, stride, padding, groups, [d, h, w])
    let shapes = [
        ("k3p1_16_16_21x40x36", 16, 16, [3; 3], [1; 3], [1; 3], 1, [21, 40, 36]),
        ("k3s2p1_16_32_21x40x36", 16, 32, [3; 3], [2; 3], [1; 3], 1, [21, 40, 36]),
        ("k311s211_64_64_11x20x18", 64, 64, [3, 1, 1], [2, 1, 1], [0; 3], 1, [11, 20, 18]),
        ("dw_k3p1_32_21x40x36", 32, 32, [3; 3], [1; 3], [1; 3], 32, [21, 40, 36]),
    ];
    for (name, cin, cout, kernel, stride, padding, groups, [d, h, w]) in shapes {
        let window = Window3 { kernel, stride, padding, dilation: [1; 3] };
        let op = Conv3d { in_channels: cin, out_channels: cout, window, groups };
        let s = op.shape(1, d, h, w);
        let x = data(s.cin * s.in_plane(), 3);
        let wt = data(s.weight_len(), 4);
        let bias = data(s.cout, 5);
        let ep = Epilogue { scale: None, shift: Some(&bias), act: Some(readi_plan::ops::Activation::Relu) };
        let mut out = vec![0.0; s.cout * s.out_plane()];
        let mut scratch = vec![0.0; conv3d::scratch_len(&s, THREADS).expect("fits")];
        g.throughput(Throughput::Elements(2 * (s.weight_len() * s.out_plane()) as u64));
        let mut fastest = f64::INFINITY;
        g.bench_function(name, |bench| {
            pool.install(|| {
                bench.iter(|| {
                    let t = std::time::Instant::now();
                    conv3d::conv3d(&s, &wt, &ep, &x, &mut out, &mut scratch, THREADS);
                    fastest = fastest.min(t.elapsed().as_secs_f64());
                    black_box(&out);
                })
            })
        });
        if !fastest.is_finite() {
            continue; // filtered out: criterion did not run it
        }
        let mut naive = f64::INFINITY;
        let mut want = vec![0.0; out.len()];
        for _ in 0..3 {
            let t = std::time::Instant::now();
            conv3d::reference(&s, &wt, &ep, &x, &mut want);
            naive = naive.min(t.elapsed().as_secs_f64());
            black_box(&want);
        }
        eprintln!(
            "conv3d/{name}: kernel {:.2} ms (fastest call, {THREADS} threads), naive loop {:.1} ms (1 thread): {:.0}x",
            fastest * 1e3,
            naive * 1e3,
            naive / fastest
        );
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

/// The data-movement kernels on a 64x56x56 feature map (a ResNet stage) against naive
/// loops that compute each output element's source index.
fn bench_movement(c: &mut Criterion) {
    use readi_plan::ops::{Pad, PadMode, Roll, Slice, SliceAxis};
    use readi_runtime::kernels::movement::{pad, roll, slice};
    let (ch, h, w) = (64usize, 56usize, 56usize);
    let x = data(ch * h * w, 11);
    let mut g = c.benchmark_group("movement");
    g.throughput(Throughput::Elements(x.len() as u64));
    let p = Pad { pads: vec![1, 1, 1, 1], mode: PadMode::Reflect, value: 0.0 };
    let mut out = vec![0.0; ch * (h + 2) * (w + 2)];
    g.bench_function(BenchmarkId::new("readi", "pad_reflect"), |b| {
        b.iter(|| pad(&p, black_box(&x), &[1, ch, h, w], &mut out))
    });
    g.bench_function(BenchmarkId::new("naive", "pad_reflect"), |b| {
        b.iter(|| {
            let xb = black_box(&x);
            let refl = |i: i64, d: i64| if i < 0 { -i } else if i >= d { 2 * (d - 1) - i } else { i } as usize;
            let (oh, ow) = (h + 2, w + 2);
            for (o, v) in out.iter_mut().enumerate() {
                let (c0, r, q) = (o / (oh * ow), o / ow % oh, o % ow);
                let (sr, sq) = (refl(r as i64 - 1, h as i64), refl(q as i64 - 1, w as i64));
                *v = xb[(c0 * h + sr) * w + sq];
            }
        })
    });
    let r = Roll { shifts: vec![3, 3], axes: vec![2, 3] };
    let mut out = vec![0.0; x.len()];
    g.bench_function(BenchmarkId::new("readi", "roll_hw"), |b| {
        b.iter(|| roll(&r, black_box(&x), &[1, ch, h, w], &mut out))
    });
    g.bench_function(BenchmarkId::new("naive", "roll_hw"), |b| {
        b.iter(|| {
            let xb = black_box(&x);
            for (o, v) in out.iter_mut().enumerate() {
                let (c0, i, j) = (o / (h * w), o / w % h, o % w);
                *v = xb[(c0 * h + (i + h - 3) % h) * w + (j + w - 3) % w];
            }
        })
    });
    let full = SliceAxis::FULL;
    let cases = [
        ("slice_channels", vec![full, SliceAxis::Range { start: Some(0), stop: Some(32), step: 1 }, full, full]),
        (
            "slice_stride2",
            vec![
                full,
                full,
                SliceAxis::Range { start: None, stop: None, step: 2 },
                SliceAxis::Range { start: Some(1), stop: None, step: 2 },
            ],
        ),
    ];
    for (name, axes) in cases {
        let s = Slice { axes };
        let shape = [1, ch, h, w];
        let rs = s.resolve(&shape).expect("resolves");
        let mut out = vec![0.0; rs.iter().map(|r| r.len).product()];
        g.bench_function(BenchmarkId::new("readi", name), |b| b.iter(|| slice(&s, black_box(&x), &shape, &mut out)));
        g.bench_function(BenchmarkId::new("naive", name), |b| {
            b.iter(|| {
                let xb = black_box(&x);
                let (lh, lw) = (rs[2].len, rs[3].len);
                for (o, v) in out.iter_mut().enumerate() {
                    let (c0, i, j) = (o / (lh * lw), o / lw % lh, o % lw);
                    let (c0, i, j) =
                        (rs[1].start + c0 * rs[1].step, rs[2].start + i * rs[2].step, rs[3].start + j * rs[3].step);
                    *v = xb[(c0 * h + i) * w + j];
                }
            })
        });
    }
    g.finish();
}

criterion_group!(
    benches,
    bench_sgemm,
    bench_conv,
    bench_conv_lora,
    bench_conv_transpose,
    bench_conv3d,
    bench_linear,
    bench_unary,
    bench_movement
);

/// Criterion's runs, then (under `cargo bench`, not `cargo test`) the [`peak_summary`]
/// of the kernels the filter selects.
fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
    if std::env::args().any(|a| a == "--bench") {
        peak_summary(&filter());
    }
}

/// The name filter given to the bench (`cargo bench --bench kernels -- conv2d`), empty for
/// none: criterion's own runs match it as a regex, the summaries outside criterion as a
/// substring.
fn filter() -> String {
    std::env::args().skip(1).find(|a| !a.starts_with('-')).unwrap_or_default()
}

/// Whether a summary outside criterion's runs named `name` passes the [`filter`] (a
/// substring either way: `conv2d_lora` selects `conv2d_lora/l3_3x3_256`, and so does
/// `conv2d_lora/l3`).
fn selected(name: &str) -> bool {
    let f = filter();
    name.contains(&f) || f.contains(name)
}

/// A kernel call the summary times: its name, its FLOPs (multiply-adds x 2) and the call.
struct Case {
    name: String,
    flops: f64,
    run: Box<dyn FnMut() + Send>,
}

/// Each FLOP-bound kernel benchmarked above (the chosen conv algorithm only), timed again
/// outside criterion (two calls untimed, then the median of nine) on a pool of
/// [`THREADS`], against the machine's peak at [`THREADS`] threads measured by
/// [`readi_runtime::peak`]: `kernel | ms | GFLOP/s | % of peak`.
fn peak_summary(filter: &str) {
    let cases: Vec<Case> =
        flop_cases().into_iter().filter(|c| c.name.contains(filter) || filter.contains(&c.name)).collect();
    if cases.is_empty() {
        return;
    }
    let peak = peak::measure(THREADS);
    let one = peak::measure(1);
    println!(
        "\npeak f32 FMA throughput ({} lanes): {:.1} GFLOP/s on 1 thread, {:.1} GFLOP/s on {THREADS} threads",
        peak.lanes,
        one.gflops(),
        peak.gflops()
    );
    println!(
        "(FLOPs counted as a direct conv does them: a Winograd conv multiplies 2.25x to 4x less, so its figure is"
    );
    println!("the direct conv's equivalent, and can pass what the machine's multiplies alone would allow)");
    println!("{:<42} | {:>9} | {:>8} | {:>9}", "kernel", "ms", "GFLOP/s", "% of peak");
    let pool = pool();
    for mut case in cases {
        let median = pool.install(|| median_seconds(&mut case.run));
        let flops = case.flops / median;
        println!(
            "{:<42} | {:>9.3} | {:>8.1} | {:>8.1}%",
            case.name,
            median * 1e3,
            flops * 1e-9,
            100.0 * peak.fraction(flops)
        );
    }
}

/// The median time of nine calls after two untimed ones.
fn median_seconds(run: &mut (dyn FnMut() + Send)) -> f64 {
    run();
    run();
    let mut t: Vec<f64> = (0..9)
        .map(|_| {
            let t = std::time::Instant::now();
            run();
            t.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// The cases of [`peak_summary`], with the shapes and data of the criterion benches.
fn flop_cases() -> Vec<Case> {
    let mut cases = Vec::new();
    let n = 512;
    let (a, b, mut out) = (data(n * n, 1), data(n * n, 2), vec![0.0; n * n]);
    cases.push(Case {
        name: "sgemm/512x512x512".into(),
        flops: 2.0 * (n * n * n) as f64,
        run: Box::new(move || {
            let (a, b) = (MatRef::row_major(&a, n, n), MatRef::row_major(&b, n, n));
            sgemm(a, b, MatMut::row_major(&mut out, n, n), false, THREADS);
            black_box(&out);
        }),
    });
    for (name, cin, hw, cout, k, stride, pad) in RESNET18 {
        let s = Conv2dShape::square(1, cin, hw, cout, k, stride, pad, 1);
        let algo = conv::choose(&s);
        let x = data(cin * hw * hw, 3);
        let mut packed = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &data(cout * cin * k * k, 4), &mut packed);
        let scale: Vec<f32> = data(cout, 5).iter().map(|v| 1.0 + 0.5 * v).collect();
        let shift = data(cout, 6);
        let mut out = vec![0.0; cout * s.oh * s.ow];
        let mut scratch = vec![0.0; conv::scratch_len(&s, algo, THREADS)];
        cases.push(Case {
            name: format!("conv2d/{name}/{}", algo.name()),
            flops: 2.0 * (cout * s.oh * s.ow * cin * k * k) as f64,
            run: Box::new(move || {
                let act = Some(readi_plan::ops::Activation::Relu);
                let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act };
                conv::conv2d(&s, algo, &packed, &ep, &x, &mut out, &mut scratch, THREADS);
                black_box(&out);
            }),
        });
    }
    for (name, c, hw, k, stride) in DEPTHWISE {
        let s = Conv2dShape::square(1, c, hw, c, k, stride, k / 2, c);
        let algo = conv::choose(&s);
        let x = data(c * hw * hw, 3);
        let mut packed = vec![0.0; conv::packed_weight_len(&s, algo)];
        conv::pack_weight(&s, algo, &data(c * k * k, 4), &mut packed);
        let shift = data(c, 6);
        let mut out = vec![0.0; c * s.oh * s.ow];
        let mut scratch = vec![0.0; conv::scratch_len(&s, algo, THREADS)];
        cases.push(Case {
            name: format!("conv2d/{name}/{}", algo.name()),
            flops: 2.0 * (c * s.oh * s.ow * k * k) as f64,
            run: Box::new(move || {
                let ep = Epilogue { scale: None, shift: Some(&shift), act: None };
                conv::conv2d(&s, algo, &packed, &ep, &x, &mut out, &mut scratch, THREADS);
                black_box(&out);
            }),
        });
    }
    cases.extend(transposed_and_3d_cases());
    let (rows, fin, fout) = (196, 384, 1536);
    let (x, w, bias) = (data(rows * fin, 7), data(fout * fin, 8), data(fout, 9));
    let mut out = vec![0.0; rows * fout];
    cases.push(Case {
        name: format!("linear/{rows}x{fin}x{fout}"),
        flops: 2.0 * (rows * fin * fout) as f64,
        run: Box::new(move || {
            let ep = Epilogue { scale: None, shift: Some(&bias), act: None };
            linear(&x, rows, fin, &w, WeightLayout::InOut, fout, &ep, &mut out, THREADS);
            black_box(&out);
        }),
    });
    cases
}

/// [`flop_cases`]' `conv_transpose2d` and `conv3d` cases, the shapes of
/// [`bench_conv_transpose`] and [`bench_conv3d`].
fn transposed_and_3d_cases() -> Vec<Case> {
    use readi_plan::ops::{Conv3d, ConvTranspose2d, Window2, Window3};
    use readi_runtime::kernels::{conv_transpose, conv3d};
    let relu = Some(readi_plan::ops::Activation::Relu);
    let mut cases = Vec::new();
    for (name, c, k, h, w) in [("k2s2_128_128_124x108", 128, 2, 124, 108), ("k4s4_256_256_50x44", 256, 4, 50, 44)] {
        let window = Window2 { kernel: [k, k], stride: [k, k], padding: [0, 0], dilation: [1, 1] };
        let op = ConvTranspose2d { in_channels: c, out_channels: c, window, output_padding: [0, 0], groups: 1 };
        let s = op.shape(1, h, w);
        let (x, wt, bias) = (data(s.cin * h * w, 3), data(s.weight_len(), 4), data(s.cout, 5));
        let mut out = vec![0.0; s.cout * s.oh * s.ow];
        let mut scratch = vec![0.0; conv_transpose::scratch_len(&s, THREADS).expect("fits")];
        cases.push(Case {
            name: format!("conv_transpose2d/{name}"),
            flops: 2.0 * (s.weight_len() * h * w) as f64,
            run: Box::new(move || {
                let ep = Epilogue { scale: None, shift: Some(&bias), act: relu };
                conv_transpose::conv_transpose2d(&s, &wt, &ep, &x, &mut out, &mut scratch, THREADS);
                black_box(&out);
            }),
        });
    }
    let shapes = [
        ("k3p1_16_16_21x40x36", 16, 16, [3; 3], [1; 3], [1; 3], 1, [21, 40, 36]),
        ("k3s2p1_16_32_21x40x36", 16, 32, [3; 3], [2; 3], [1; 3], 1, [21, 40, 36]),
        ("k311s211_64_64_11x20x18", 64, 64, [3, 1, 1], [2, 1, 1], [0; 3], 1, [11, 20, 18]),
        ("dw_k3p1_32_21x40x36", 32, 32, [3; 3], [1; 3], [1; 3], 32, [21, 40, 36]),
    ];
    for (name, cin, cout, kernel, stride, padding, groups, [d, h, w]) in shapes {
        let window = Window3 { kernel, stride, padding, dilation: [1; 3] };
        let s = Conv3d { in_channels: cin, out_channels: cout, window, groups }.shape(1, d, h, w);
        let (x, wt, bias) = (data(s.cin * s.in_plane(), 3), data(s.weight_len(), 4), data(s.cout, 5));
        let mut out = vec![0.0; s.cout * s.out_plane()];
        let mut scratch = vec![0.0; conv3d::scratch_len(&s, THREADS).expect("fits")];
        cases.push(Case {
            name: format!("conv3d/{name}"),
            flops: 2.0 * (s.weight_len() * s.out_plane()) as f64,
            run: Box::new(move || {
                let ep = Epilogue { scale: None, shift: Some(&bias), act: relu };
                conv3d::conv3d(&s, &wt, &ep, &x, &mut out, &mut scratch, THREADS);
                black_box(&out);
            }),
        });
    }
    cases
}
