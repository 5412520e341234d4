//! Where trials run: a thread pool of their own, beside the production pool, so that what the
//! tuner costs a node is counted where it is spent (docs/performance.md, "The tuner's cost"):
//! the CPU time of the pool's threads is the trials' CPU time (size probes, full trials, their
//! reference frames), with no difference of two runs that differ in more than the trials.
//! Trials and production still take turns on the node's compute lane
//! ([`crate::tuner_link`]), so the two pools never contend for the cores. A node without a
//! tuner has no trial pool.

use cpu_time::{ProcessTime, ThreadTime};

/// The trial pool.
pub struct TrialPool {
    pool: rayon::ThreadPool,
}

impl TrialPool {
    /// A pool of `threads` threads (0: one per core, as the production pool).
    ///
    /// # Errors
    /// The threads could not be started.
    pub fn new(threads: usize) -> Result<Self, rayon::ThreadPoolBuildError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("trial-{i}"))
            .build()?;
        Ok(Self { pool })
    }

    /// Runs `f` on the pool (every rayon loop inside uses its threads) and returns its result
    /// and the CPU seconds the pool's threads spent meanwhile (its own work: trials run one at
    /// a time).
    pub fn run<R: Send>(&self, f: impl FnOnce() -> R + Send) -> (R, f64) {
        let before = self.threads_cpu_secs();
        let out = self.pool.install(f);
        let spent = self.threads_cpu_secs() - before;
        (out, spent.max(0.0))
    }

    /// CPU seconds of the pool's threads since they started, summed.
    fn threads_cpu_secs(&self) -> f64 {
        self.pool
            .broadcast(|_| ThreadTime::now().as_duration().as_secs_f64())
            .iter()
            .sum()
    }
}

/// CPU seconds of this process since it started, all threads.
pub fn process_cpu_secs() -> f64 {
    ProcessTime::now().as_duration().as_secs_f64()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// The CPU time a pool reports is the work run on it: a parallel loop on the pool is
    /// counted (against the CPU time each of its jobs measured on its own thread), and work
    /// off the pool, on the calling thread, is not (other tests run beside this one, so the
    /// process's CPU time is no reference).
    #[test]
    fn the_pool_counts_the_cpu_time_of_its_own_work() {
        let pool = TrialPool::new(2).unwrap();
        let spin = |n: u64| (0..n).fold(0u64, |a, i| a.wrapping_mul(31).wrapping_add(i ^ a));
        let (jobs, on_pool) = pool.run(|| {
            (0..64u64)
                .into_par_iter()
                .map(|k| {
                    let t = ThreadTime::now();
                    std::hint::black_box(spin(300_000 + k));
                    t.elapsed().as_secs_f64()
                })
                .sum::<f64>()
        });
        assert!(
            on_pool >= 0.95 * jobs && on_pool <= 1.5 * jobs + 0.05,
            "{on_pool} s counted for {jobs} s of jobs"
        );
        let t = ThreadTime::now();
        let off = std::hint::black_box(spin(20_000_000));
        let off_secs = t.elapsed().as_secs_f64();
        let (_, idle) = pool.run(|| off);
        assert!(
            idle < 0.5 * off_secs + 0.005,
            "{idle} s counted for work off the pool ({off_secs} s)"
        );
    }
}
