//! The panel-packed product ([`panel::gemm`]) against `sgemm` on a row-major `[in, out]`
//! weight, on the linear shapes of Swin-T, ViT-B/16 and ConvNeXt-T at batch 1, one
//! thread: `cargo run --release -p readi-runtime --example panel_gemm`. Prints the median
//! of each, and their ratio of medians and of the fastest runs, rounds alternating.
use std::hint::black_box;
use std::time::Instant;

use readi_runtime::kernels::gemm::{MatMut, MatRef, sgemm};
use readi_runtime::kernels::panel;
use readi_runtime::testdata::data;

fn main() {
    let shapes = [
        ("swin stage 4 fc1", 49, 768, 3072),
        ("swin stage 4 fc2", 49, 3072, 768),
        ("swin stage 4 qkv", 49, 768, 2304),
        ("swin stage 3 fc1", 196, 384, 1536),
        ("swin stage 1 fc1", 3136, 96, 384),
        ("vit-b fc1", 197, 768, 3072),
        ("vit-b fc2", 197, 3072, 768),
    ];
    for (name, m, k, n) in shapes {
        let x = data(m * k, 1);
        let w = data(n * k, 2);
        let mut wt = vec![0.0; k * n];
        for j in 0..n {
            for i in 0..k {
                wt[i * n + j] = w[j * k + i];
            }
        }
        let mut p = vec![0.0; panel::packed_len(k, n)];
        panel::pack(&w, k, n, &mut p);
        let mut out = vec![0.0; m * n];
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for _ in 0..31 {
            let t = Instant::now();
            sgemm(
                MatRef::row_major(&x, m, k),
                MatRef::row_major(&wt, k, n),
                MatMut::row_major(&mut out, m, n),
                false,
                1,
            );
            a.push(t.elapsed().as_secs_f64());
            black_box(&out);
            let t = Instant::now();
            panel::gemm(&x, m, k, &p, n, &mut out);
            b.push(t.elapsed().as_secs_f64());
            black_box(&out);
        }
        a.sort_by(f64::total_cmp);
        b.sort_by(f64::total_cmp);
        let (ta, tb) = (a[a.len() / 2], b[b.len() / 2]);
        let gf = |t: f64| 2.0 * (m * k * n) as f64 / t / 1e9;
        println!(
            "{name:18} {m}x{k}x{n}: sgemm {:7.1} us ({:5.1} GFLOP/s), panel {:7.1} us ({:5.1} GFLOP/s), \
             panel/sgemm median {:.2}, fastest {:.2}",
            ta * 1e6,
            gf(ta),
            tb * 1e6,
            gf(tb),
            tb / ta,
            b[0] / a[0]
        );
    }
}
