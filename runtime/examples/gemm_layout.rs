//! sgemm speed by B layout for ViT-S linear shapes: `cargo run --release -p readi-runtime --example gemm_layout`.
use readi_runtime::kernels::gemm::{MatMut, MatRef, sgemm};
fn main() {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().expect("pool");
    for (m, k, n) in [(196, 384, 1536), (196, 1536, 384), (196, 384, 384), (512, 512, 512)] {
        let a = vec![0.5f32; m * k];
        let b = vec![0.25f32; k * n];
        let mut c = vec![0.0f32; m * n];
        for (label, col_major) in [("B row-major", false), ("B col-major (PyTorch weight)", true)] {
            let bm = if col_major {
                MatRef { data: &b, rows: k, cols: n, row_stride: 1, col_stride: k }
            } else {
                MatRef::row_major(&b, k, n)
            };
            let mut best = f64::MAX;
            for _ in 0..20 {
                let t = std::time::Instant::now();
                pool.install(|| sgemm(MatRef::row_major(&a, m, k), bm, MatMut::row_major(&mut c, m, n), false, 2));
                best = best.min(t.elapsed().as_secs_f64());
            }
            println!("{m}x{k}x{n} {label}: {:.0} GFLOP/s", 2.0 * (m * k * n) as f64 / best / 1e9);
        }
    }
}
