//! Throughput of the element-wise activations, one thread: `cargo run --release -p
//! readi-runtime --example act_speed`.
use readi_runtime::kernels::{Act, elementwise};
fn main() {
    let n = 3_600_000;
    let x: Vec<f32> = (0..n).map(|i| (i % 1000) as f32 / 250.0 - 2.0).collect();
    let mut out = vec![0.0; n];
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("pool");
    for act in [Act::Relu, Act::Gelu, Act::GeluTanh, Act::Sigmoid] {
        let mut best = f64::MAX;
        for _ in 0..5 {
            let t = std::time::Instant::now();
            pool.install(|| elementwise::activation(act, &x, &mut out));
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!("{act:?}: {:.3} ns/element", best * 1e9 / n as f64);
    }
}
