//! Cost of the selector statistics on bevfusion_tiny-sized inputs (six 3x128x352 camera
//! views, a 64x128x128 lidar grid): `cargo run --release -p readi-runtime --example select_cost`.

use std::time::Instant;

use readi_runtime::conditions::{Statistic, statistic};

fn main() {
    let cam: Vec<f32> = (0..6 * 3 * 128 * 352).map(|i| ((i * 7919) % 1000) as f32 / 1000.0).collect();
    let lidar: Vec<f32> = (0..64 * 128 * 128).map(|i| if i % 97 == 0 { 0.5 } else { 0.0 }).collect();
    for (stat, data, shape) in [
        (Statistic::Brightness, &cam, vec![18, 128, 352]),
        (Statistic::LaplacianVar, &cam, vec![18, 128, 352]),
        (Statistic::Density, &lidar, vec![64, 128, 128]),
    ] {
        let mut t = Vec::new();
        for _ in 0..50 {
            let s = Instant::now();
            std::hint::black_box(statistic(stat, data, &shape));
            t.push(s.elapsed().as_secs_f64() * 1e6);
        }
        t.sort_by(f64::total_cmp);
        println!("{:<14} {:>8.1} us  ({} floats)", stat.name(), t[t.len() / 2], data.len());
    }
}
