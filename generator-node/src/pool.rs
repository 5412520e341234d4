//! The node's worker threads: generation, reference frames, host composition and trials run
//! on one rayon pool of `threads` (0: one per core), optionally at a lower CPU priority than
//! the simulation beside it (`nice`, docs/performance.md, "The simulation's share"). A node
//! on the simulation's cores then takes the time the simulation leaves idle; the price is the
//! VDIs' latency, and τ's waits, while the simulation keeps every core busy. The threads that
//! receive steps (the simulation waits on them) keep the process's priority.

use std::sync::Arc;

/// The worker pool: `threads` threads (0: rayon's default, one per core), each at nice level
/// `nice` (0–19, Linux; higher is lower priority) or the process's own when that is higher
/// already. Elsewhere `nice` is ignored, with a warning.
///
/// # Errors
/// The threads could not be started.
pub fn worker_pool(
    threads: usize,
    nice: i32,
) -> Result<Arc<rayon::ThreadPool>, rayon::ThreadPoolBuildError> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("generate-{i}"))
        .start_handler(move |i| {
            if nice > 0 {
                if let Err(problem) = lower_priority(nice) {
                    tracing::warn!(thread = i, nice, %problem, "worker thread keeps the process's priority");
                }
            }
        })
        .build()
        .map(Arc::new)
}

/// Sets the calling thread's nice level to `nice` unless it is at that level or lower
/// priority already (raising priority would need privileges the node does not ask for).
///
/// # Errors
/// The kernel refused, or threads' priorities cannot be set apart on this system.
pub fn lower_priority(nice: i32) -> std::io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        if thread_nice()? < nice {
            // On Linux a thread id addresses that thread alone (setpriority(2), "BUGS").
            rustix::process::setpriority_process(Some(rustix::thread::gettid()), nice)?;
        }
        Ok(())
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = nice;
        Err(std::io::Error::new(
            std::io::ErrorKind::Unsupported,
            "per-thread priorities are set on Linux only",
        ))
    }
}

/// The calling thread's nice level (Linux).
///
/// # Errors
/// The kernel's answer, when `getpriority` fails.
#[cfg(target_os = "linux")]
pub fn thread_nice() -> std::io::Result<i32> {
    Ok(rustix::process::getpriority_process(Some(
        rustix::thread::gettid(),
    ))?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn work_runs_on_the_configured_threads() {
        let one = worker_pool(1, 0).unwrap();
        assert_eq!(one.install(rayon::current_num_threads), 1);
        let three = worker_pool(3, 0).unwrap();
        assert_eq!(three.install(rayon::current_num_threads), 3);
        let default = worker_pool(0, 0).unwrap();
        // rayon's default, as its global pool has it (one per core, or RAYON_NUM_THREADS).
        assert_eq!(
            default.install(rayon::current_num_threads),
            rayon::current_num_threads()
        );
    }

    /// Every worker runs at the pool's nice level (or the process's, when that is lower
    /// priority already); the thread that built the pool keeps its own.
    #[cfg(target_os = "linux")]
    #[test]
    fn workers_run_at_lower_priority_and_the_caller_keeps_its_own() {
        let own = thread_nice().unwrap();
        let pool = worker_pool(3, 7).unwrap();
        let levels = pool.broadcast(|_| thread_nice().unwrap());
        assert_eq!(levels, vec![own.max(7); 3]);
        assert_eq!(thread_nice().unwrap(), own);
        // A level at or below the thread's own changes nothing (and needs no privilege).
        let same = worker_pool(2, 0).unwrap();
        assert_eq!(same.broadcast(|_| thread_nice().unwrap()), vec![own; 2]);
    }
}
