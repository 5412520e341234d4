//! The CPU side of the render lanes ([`super::lanes`]): interactive frames and large renders
//! (stills over [`super::lanes::LARGE_PIXELS`], movie frames) run on two thread pools of
//! their own, each as wide as the machine. A render is split into bands of tiles that its
//! pool's workers take in turn; on one shared pool a small frame's bands queued behind every
//! band of a 4096² still (1.8 s for a 64² frame). On two pools the operating system shares
//! the cores between them, so a small frame costs about twice its idle time while a large
//! one runs, and the large one loses only what the small ones take. Work that is not a
//! viewer's render (composing, scoring) keeps rayon's global pool.

use rayon::{ThreadPool, ThreadPoolBuilder};

/// The two pools; either may be missing when its threads could not be started (then that
/// lane renders on the global pool, as before, and the log says so).
pub struct Pools {
    interactive: Option<ThreadPool>,
    large: Option<ThreadPool>,
}

impl Pools {
    /// Two pools of `threads` workers each (0: one per core).
    pub fn new(threads: usize) -> Self {
        let build = |name: &'static str| {
            ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(move |i| format!("render-{name}-{i}"))
                .build()
                .map_err(|e| {
                    tracing::warn!(pool = name, error = %e, "render pool not started: its frames render on the global pool");
                })
                .ok()
        };
        Self {
            interactive: build("interactive"),
            large: build("large"),
        }
    }

    /// Runs `render` on the large renders' pool when `large`, else on the interactive one.
    pub fn install<R: Send>(&self, large: bool, render: impl FnOnce() -> R + Send) -> R {
        let pool = if large {
            &self.large
        } else {
            &self.interactive
        };
        match pool {
            Some(p) => p.install(render),
            None => render(),
        }
    }
}
