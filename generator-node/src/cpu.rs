//! CPU time, counted where it is spent (docs/performance.md, "The tuner's cost"): the
//! trials' CPU time is what the compute pool's threads spend while a trial holds the node's
//! compute lane ([`crate::tuner_link`]), when production does not run, read from each
//! thread's own clock; no difference of two runs that differ in more than the trials.

use cpu_time::{ProcessTime, ThreadTime};

/// CPU seconds, summed, that the threads of `pool` have spent since they started.
pub fn pool_cpu_secs(pool: &rayon::ThreadPool) -> f64 {
    pool.broadcast(|_| ThreadTime::now().as_duration().as_secs_f64())
        .iter()
        .sum()
}

/// Runs `f` on `pool` (`f` itself and its parallel loops) and returns its result and the CPU
/// seconds the pool's threads spent meanwhile: `f`'s CPU time when nothing else runs on the
/// pool (anything that does is counted with it).
pub fn on_pool_counted<R: Send>(
    pool: &rayon::ThreadPool,
    f: impl FnOnce() -> R + Send,
) -> (R, f64) {
    let before = pool_cpu_secs(pool);
    let out = pool.install(f);
    let spent = pool_cpu_secs(pool) - before;
    (out, spent.max(0.0))
}

/// CPU seconds of this process since it started, all threads.
pub fn process_cpu_secs() -> f64 {
    ProcessTime::now().as_duration().as_secs_f64()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// The CPU time counted on a pool is the work run on it: a parallel loop on the pool is
    /// counted (against the CPU time each of its jobs measured on its own thread), so is `f`'s
    /// serial work (which runs on one of the pool's threads), and work before and after, on
    /// the calling thread, is not (other tests run beside this one, so the
    /// process's CPU time is no reference).
    #[test]
    fn a_pool_counts_the_cpu_time_of_its_own_work() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let spin = |n: u64| (0..n).fold(0u64, |a, i| a.wrapping_mul(31).wrapping_add(i ^ a));
        let (jobs, on_pool) = on_pool_counted(&pool, || {
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
        // `f` itself runs on one of the pool's threads: its serial work counts too.
        let (serial, counted) = on_pool_counted(&pool, || {
            let t = ThreadTime::now();
            std::hint::black_box(spin(10_000_000));
            t.elapsed().as_secs_f64()
        });
        assert!(
            counted >= 0.95 * serial,
            "{counted} s counted for {serial} s of serial work in `f`"
        );
        let t = ThreadTime::now();
        let off = std::hint::black_box(spin(20_000_000));
        let off_secs = t.elapsed().as_secs_f64();
        let (_, idle) = on_pool_counted(&pool, || off);
        assert!(
            idle < 0.5 * off_secs + 0.005,
            "{idle} s counted for work off the pool ({off_secs} s)"
        );
    }
}
