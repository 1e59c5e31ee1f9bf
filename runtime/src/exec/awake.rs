//! A run with the pool's other workers kept awake. Between two parallel steps, and while
//! one thread finishes a step's last part, rayon's idle workers yield a few dozen times
//! and then sleep on a futex; waking one takes longer than a small step's share of the
//! work on a virtual machine's cores. Through a run the other workers spin instead,
//! taking every job the run's thread offers (`rayon::yield_now`), and stop when it ends
//! (ONNX Runtime's pool spins the same way). [`SessionOptions::spin`] turns it off.
//!
//! The spinners are the second half of a `rayon::join` whose first half is the run:
//! nothing is allocated, and the join returns only once every spinner has seen the run's
//! end. A spinner that the run's own thread picks up (while it waits inside the run, no
//! other worker having taken it) returns at once, so the run never waits on itself.
//!
//! [`SessionOptions::spin`]: super::SessionOptions::spin

use std::sync::atomic::{AtomicBool, Ordering};

/// Runs `f` on `pool` (of `threads` workers), the other workers spinning until `f`
/// returns or unwinds when `spin`.
pub(super) fn install<T: Send>(
    pool: &rayon::ThreadPool,
    threads: usize,
    spin: bool,
    f: impl FnOnce() -> T + Send,
) -> T {
    if threads <= 1 || !spin {
        return pool.install(f);
    }
    pool.install(|| {
        let done = AtomicBool::new(false);
        let me = rayon::current_thread_index();
        let (out, ()) = rayon::join(
            || {
                let _stop = Stop(&done);
                f()
            },
            || spinners(threads - 1, &done, me),
        );
        out
    })
}

/// Sets `done` when dropped: when the run returns or unwinds.
struct Stop<'a>(&'a AtomicBool);

impl Drop for Stop<'_> {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Release);
    }
}

/// `n` spinners, each on whichever worker takes it.
fn spinners(n: usize, done: &AtomicBool, me: Option<usize>) {
    match n {
        0 => {}
        1 => spinner(done, me),
        _ => {
            rayon::join(|| spinner(done, me), || spinners(n - 1, done, me));
        }
    }
}

/// Runs other jobs, or waits, until `done`; at once on the run's own thread `me`.
fn spinner(done: &AtomicBool, me: Option<usize>) {
    if rayon::current_thread_index() == me {
        return;
    }
    while !done.load(Ordering::Acquire) {
        if rayon::yield_now() != Some(rayon::Yield::Executed) {
            std::hint::spin_loop();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// A run that panics ends the spinning: the join returns (else this test hangs), and
    /// the pool runs the next parallel work.
    #[test]
    fn a_panic_stops_the_spinners() {
        for threads in [2, 3] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                install(&pool, threads, true, || {
                    let v: Vec<u64> = (0..10_000u64).into_par_iter().map(|i| i * i).collect();
                    if v.len() == 10_000 {
                        panic!("a step failed");
                    }
                })
            }));
            assert!(r.is_err());
            let sum: u64 = install(&pool, threads, true, || (0..1000u64).into_par_iter().sum());
            assert_eq!(sum, 999 * 1000 / 2);
        }
    }

    /// The spinners take the run's parallel work: with one worker running the run and the
    /// others spinning, jobs run on more than one worker.
    #[test]
    fn the_spinners_take_the_runs_jobs() {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().expect("pool");
        let seen = install(&pool, 2, true, || {
            let me = rayon::current_thread_index();
            (0..64)
                .into_par_iter()
                .map(|_| {
                    std::thread::sleep(std::time::Duration::from_millis(1));
                    rayon::current_thread_index() != me
                })
                .filter(|&other| other)
                .count()
        });
        assert!(seen > 0, "no job ran on the other worker");
    }
}
