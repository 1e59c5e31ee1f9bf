//! What an addition to a kernel costs, measured in alternating calls: the examples that
//! time a layer with and without a fused branch (`lora_cost`, `adapter_cost`) include this
//! file (`#[path]`), so both measure the same way.

use std::time::Instant;

/// Calls `layer(with)` 2000 times on a rayon pool of `threads` threads, `with` false and
/// true in turn, and returns the median over the pairs (after 100 warm-up pairs) of the
/// time added, in us, and of the ratio with / without.
pub fn with_and_without(threads: usize, mut layer: impl FnMut(bool) + Send) -> (f64, f64) {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
    let (mut base, mut with) = (Vec::new(), Vec::new());
    pool.install(|| {
        for i in 0..2000 {
            let on = i % 2 == 1;
            let t = Instant::now();
            layer(on);
            let us = t.elapsed().as_secs_f64() * 1e6;
            if i >= 200 {
                if on { with.push(us) } else { base.push(us) }
            }
        }
    });
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let added = median(with.iter().zip(&base).map(|(w, b)| w - b).collect());
    let ratio = median(with.iter().zip(&base).map(|(w, b)| w / b).collect());
    (added, ratio)
}
