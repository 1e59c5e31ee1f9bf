//! The machine's peak f32 FLOP/s, measured: the yardstick a kernel's or a model's
//! GFLOP/s is read against (`cargo bench -p readi-runtime --bench kernels`, `readi bench
//! --peak`).
//!
//! The nominal figure, cores x FMA units x SIMD lanes x 2 x clock, needs the FMA unit
//! count and the clock under vector load, which neither `cpuid` nor the OS reports
//! reliably (AVX-512 lowers the clock on many Xeons; a VM's cores may share a physical
//! core). So it is measured instead: each thread runs [`CHAINS`] independent FMA chains on
//! vectors of the widest SIMD `pulp` finds, enough chains to cover the FMA latency
//! (4 cycles) on two FMA units, and nothing else: no loads, no stores. The best of a few
//! repetitions is taken (the least disturbed by other processes). About 0.1 s in all.

use std::hint::black_box;
use std::time::Instant;

use pulp::Simd;

/// Independent accumulators per thread: FMA latency (4 cycles) x 2 FMA units, plus
/// margin; more would spill on SIMD with 16 registers.
pub const CHAINS: usize = 12;

/// FMA steps per chain in one timed repetition (about 10 ms per thread at 2 x 16 lanes
/// and 3 GHz).
const STEPS: usize = 1 << 21;

/// Timed repetitions; the fastest counts.
const REPEATS: usize = 5;

/// A measured peak.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Peak {
    /// f32 lanes of the SIMD the loop ran on (16: AVX-512, 8: AVX2, 4: SSE or NEON).
    pub lanes: usize,
    /// The threads that ran the loop at once.
    pub threads: usize,
    /// FLOP/s of all of them together (an FMA counts as two).
    pub flops: f64,
}

impl Peak {
    /// GFLOP/s.
    pub fn gflops(&self) -> f64 {
        self.flops * 1e-9
    }

    /// `flops` FLOP/s as a fraction of this peak.
    pub fn fraction(&self, flops: f64) -> f64 {
        flops / self.flops
    }
}

/// Measures the peak of `threads` threads (at least 1) running the FMA loop at once, on
/// a rayon pool of its own.
pub fn measure(threads: usize) -> Peak {
    let threads = threads.max(1);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("rayon pool for the peak loop");
    // One untimed repetition first: the pool's threads start, the clock ramps up.
    let run = || pool.broadcast(|_| pulp::Arch::new().dispatch(Chains { steps: STEPS }));
    black_box(run());
    let mut best = f64::INFINITY;
    let mut lanes = 0;
    for _ in 0..REPEATS {
        let t = Instant::now();
        let out = run();
        best = best.min(t.elapsed().as_secs_f64());
        lanes = out[0].0;
        black_box(out);
    }
    let flops = (2 * lanes * CHAINS * STEPS * threads) as f64 / best;
    Peak { lanes, threads, flops }
}

/// The FMA loop for one thread: its SIMD's lanes and the sum of the chains (so that the
/// compiler keeps them).
struct Chains {
    steps: usize,
}

impl pulp::WithSimd for Chains {
    type Output = (usize, f32);

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) -> (usize, f32) {
        // acc <- acc * m + c converges to c / (1 - m) = 1: no overflow, no subnormals.
        let m = simd.splat_f32s(black_box(0.5));
        let c = simd.splat_f32s(black_box(0.5));
        let mut acc = [simd.splat_f32s(black_box(0.25)); CHAINS];
        for _ in 0..self.steps {
            for a in &mut acc {
                *a = simd.mul_add_f32s(*a, m, c);
            }
        }
        let sum = acc.iter().fold(simd.splat_f32s(0.0), |s, &a| simd.add_f32s(s, a));
        (size_of::<S::f32s>() / size_of::<f32>(), simd.reduce_sum_f32s(sum))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chains_converge_as_a_scalar_loop_does() {
        // The same recurrence in scalar code: every lane of every chain ends at it.
        let mut want = 0.25f32;
        for _ in 0..64 {
            want = want * 0.5 + 0.5;
        }
        let (lanes, sum) = pulp::Arch::new().dispatch(Chains { steps: 64 });
        assert!(lanes >= 1);
        assert_eq!(sum, want * (lanes * CHAINS) as f32);
    }

    #[test]
    fn a_measured_peak_counts_every_thread_and_lane() {
        let two = measure(2);
        assert!(two.flops.is_finite() && two.flops > 0.0, "{two:?}");
        assert_eq!(two.threads, 2);
        assert_eq!(two.lanes, pulp::Arch::new().dispatch(Chains { steps: 1 }).0);
        assert!((two.fraction(two.flops) - 1.0).abs() < 1e-12);
        assert!((two.fraction(0.5 * two.flops) - 0.5).abs() < 1e-12);
    }
}
