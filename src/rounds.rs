//! Timing in alternating rounds: one run of each contender a round, the order reversed
//! every round, so that a drift of the machine within a round hits them alike. On a
//! shared host whose speed moves by 2x within minutes, the median of the rounds' ratios
//! is steadier than the ratio of the medians: a round's runs are milliseconds apart.
//! `readi bench --against` and `cargo bench --bench variants` measure this way.

/// Each round's times (ms), one per contender, in the contenders' order.
pub struct Rounds(Vec<Vec<f64>>);

impl Rounds {
    /// `rounds` rounds of one call of each of `timers` (each runs once and returns the
    /// run's time in ms); the first error ends it.
    pub fn run<E>(timers: &mut [&mut dyn FnMut() -> Result<f64, E>], rounds: usize) -> Result<Rounds, E> {
        let mut order: Vec<usize> = (0..timers.len()).collect();
        let mut all = Vec::with_capacity(rounds);
        for _ in 0..rounds {
            let mut t = vec![0.0; timers.len()];
            for &i in &order {
                t[i] = timers[i]()?;
            }
            order.reverse();
            all.push(t);
        }
        Ok(Rounds(all))
    }

    /// Contender `i`'s median time, ms.
    pub fn median(&self, i: usize) -> f64 {
        median(&self.sorted(|t| t[i]))
    }

    /// `f` of each round's times, sorted.
    pub fn sorted(&self, f: impl Fn(&[f64]) -> f64) -> Vec<f64> {
        let mut v: Vec<f64> = self.0.iter().map(|t| f(t)).collect();
        v.sort_by(f64::total_cmp);
        v
    }

    /// The median over the rounds of `f` of a round's times (a ratio of two contenders).
    pub fn ratio(&self, f: impl Fn(&[f64]) -> f64) -> f64 {
        median(&self.sorted(f))
    }
}

/// The middle value of sorted `v` (the upper one of an even count); 0 for none.
pub fn median(v: &[f64]) -> f64 {
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounds_alternate_and_take_the_median_ratio() {
        // Two contenders; the log shows the order reversing every round.
        let log = std::cell::RefCell::new(Vec::new());
        let mut times_a = [1.0, 2.0, 4.0].into_iter();
        let mut times_b = [2.0, 2.0, 2.0].into_iter();
        let mut a = || -> Result<f64, ()> {
            log.borrow_mut().push('a');
            Ok(times_a.next().unwrap_or(0.0))
        };
        let mut b = || -> Result<f64, ()> {
            log.borrow_mut().push('b');
            Ok(times_b.next().unwrap_or(0.0))
        };
        let r = Rounds::run(&mut [&mut a, &mut b], 3).expect("runs");
        assert_eq!(log.borrow().iter().collect::<String>(), "abbaab");
        // Ratios a / b: 0.5, 1, 2; median 1. Medians: a 2, b 2.
        assert_eq!(r.ratio(|t| t[0] / t[1]), 1.0);
        assert_eq!(r.sorted(|t| t[0] / t[1]), [0.5, 1.0, 2.0]);
        assert_eq!((r.median(0), r.median(1)), (2.0, 2.0));
        // An error ends the rounds.
        let mut fail = || -> Result<f64, &str> { Err("no") };
        assert_eq!(Rounds::run(&mut [&mut fail], 2).err(), Some("no"));
    }
}
