//! The ranks' bricks, checked at the first step whose ranks have all arrived here: bricks that
//! cannot tile the grid (two disjoint halves leave the cells between them in no brick) are
//! named once per run with their fix, the steps they make are counted, and later pushes of
//! the same bricks are refused at their header, so a simulation hears of its decomposition at
//! its next push rather than at the end of the run.
//!
//! Only a world whose ranks all push to this node can be checked here; a world spread over
//! several nodes is checked by the viz-node when it composes (docs/ranks-and-clients.md).

use crate::ingest::StepInfo;
use insitu_core::volume::bricks::{self, Brick, DecompositionError};
use std::collections::BTreeMap;
use std::sync::Mutex;
use tonic::Status;
use tracing::warn;

/// Steps whose ranks are not all in, kept at most: a node that serves part of a world never
/// sees one whole, and forgets the oldest.
const MAX_PENDING: usize = 64;

/// A world's bricks, by rank, on one grid.
#[derive(Clone, Debug, PartialEq)]
struct Layout {
    global: [usize; 3],
    bricks: BTreeMap<u32, Brick>,
}

/// A layout that cannot tile its grid.
#[derive(Debug)]
struct Bad {
    layout: Layout,
    /// The first step that showed it.
    step: u64,
    why: DecompositionError,
}

#[derive(Debug, Default)]
struct State {
    /// Bricks of the steps whose ranks are not all in yet.
    pending: BTreeMap<u64, Layout>,
    /// The last whole layout that tiled its grid (not checked again).
    good: Option<Layout>,
    /// The last whole layout that did not.
    bad: Option<Bad>,
    /// Steps whose whole layout did not tile the grid.
    bad_steps: u64,
    /// Pushes refused for their layout.
    refused: u64,
    /// The world size of the last step whose ranks all pushed here.
    whole: u32,
}

/// The layouts of the worlds pushing to this node.
#[derive(Debug, Default)]
pub struct Layouts(Mutex<State>);

impl Layouts {
    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Refuses a push whose brick belongs to a layout already found not to tile its grid.
    ///
    /// # Errors
    /// `FAILED_PRECONDITION` naming the gap (or overlap), its fix, and the step that showed it.
    pub fn admit(&self, info: &StepInfo) -> Result<(), Status> {
        let mut s = self.state();
        let Some(bad) = &s.bad else {
            return Ok(());
        };
        let same = bad.layout.global == info.global_dims
            && bad.layout.bricks.len() == info.world_size as usize
            && bad.layout.bricks.get(&info.rank) == Some(&brick_of(info));
        if !same {
            return Ok(());
        }
        let message = format!(
            "step {} rank {}: not taken, the ranks' bricks cannot be composed (found when step {} had all its ranks): {}",
            info.step, info.rank, bad.step, bad.why
        );
        s.refused += 1;
        Err(Status::failed_precondition(message))
    }

    /// Records a received step's brick; once its step's ranks are all in, checks that their
    /// bricks tile the grid. Returns the fault the first time a layout shows it (logged).
    pub fn record(&self, info: &StepInfo) -> Option<DecompositionError> {
        if info.world_size < 2 {
            return None;
        }
        let mut s = self.state();
        let entry = s.pending.entry(info.step).or_insert_with(|| Layout {
            global: info.global_dims,
            bricks: BTreeMap::new(),
        });
        entry.bricks.insert(info.rank, brick_of(info));
        if entry.bricks.len() < info.world_size as usize {
            while s.pending.len() > MAX_PENDING {
                s.pending.pop_first();
            }
            return None;
        }
        let layout = s.pending.remove(&info.step)?;
        s.whole = info.world_size;
        if s.good.as_ref() == Some(&layout) {
            return None;
        }
        if s.bad.as_ref().is_some_and(|b| b.layout == layout) {
            s.bad_steps += 1;
            return None;
        }
        let placed: Vec<(u32, Brick)> = layout.bricks.iter().map(|(r, b)| (*r, *b)).collect();
        match bricks::check(layout.global, &placed, true) {
            Ok(()) => {
                s.good = Some(layout);
                None
            }
            Err(why) => {
                warn!(step = info.step, error = %why, "the ranks' bricks cannot be composed; later pushes of these bricks are refused");
                s.bad_steps += 1;
                s.bad = Some(Bad {
                    layout,
                    step: info.step,
                    why: why.clone(),
                });
                Some(why)
            }
        }
    }

    /// Whether every rank of a world of `world_size` pushed a step here (a world of one
    /// always does): this node then sees whole steps.
    pub fn whole_world_here(&self, world_size: u32) -> bool {
        world_size <= 1 || self.state().whole == world_size
    }

    /// For the node's summary: the steps whose bricks could not be composed, the pushes
    /// refused for it, and why (`None` when every whole step tiled its grid).
    pub fn summary(&self) -> Option<String> {
        let s = self.state();
        let bad = s.bad.as_ref()?;
        Some(format!(
            "{} step(s) whose ranks' bricks cannot be composed (first: step {}), {} later push(es) of them refused: {}",
            s.bad_steps, bad.step, s.refused, bad.why
        ))
    }
}

fn brick_of(info: &StepInfo) -> Brick {
    Brick {
        offset: info.brick_offset,
        dims: info.brick_dims,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use insitu_core::volume::ScalarType;

    fn info(step: u64, rank: u32, z0: usize, nz: usize) -> StepInfo {
        StepInfo {
            step,
            sim_time: 0.0,
            rank,
            world_size: 2,
            dtype: ScalarType::F32,
            global_dims: [8, 8, 8],
            brick_offset: [0, 0, z0],
            brick_dims: [8, 8, nz],
            spacing: Vec3::ONE,
            origin: Vec3::ZERO,
        }
    }

    #[test]
    fn disjoint_halves_are_named_once_and_their_later_pushes_refused() {
        let l = Layouts::default();
        l.admit(&info(0, 0, 0, 4)).unwrap();
        assert!(l.record(&info(0, 0, 0, 4)).is_none(), "rank 1 not in yet");
        let why = l.record(&info(0, 1, 4, 4)).unwrap();
        assert!(
            why.to_string()
                .contains("rank 0's brick must include z = 4 (nz 5, not 4)"),
            "{why}"
        );
        // Step 1's pushes of the same bricks are refused at their header, naming step 0.
        for rank in [0, 1] {
            let z0 = 4 * rank as usize;
            let refused = l.admit(&info(1, rank, z0, 4)).unwrap_err();
            assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
            assert!(
                refused.message().starts_with(&format!(
                    "step 1 rank {rank}: not taken, the ranks' bricks cannot be composed (found when step 0 had all its ranks)"
                )),
                "{}",
                refused.message()
            );
        }
        // The fixed bricks are taken, checked and found whole.
        l.admit(&info(2, 0, 0, 5)).unwrap();
        assert!(l.record(&info(2, 0, 0, 5)).is_none());
        assert!(l.record(&info(2, 1, 4, 4)).is_none());
        let summary = l.summary().unwrap();
        assert!(
            summary.starts_with("1 step(s) whose ranks' bricks cannot be composed (first: step 0), 2 later push(es) of them refused: "),
            "{summary}"
        );
    }

    #[test]
    fn bricks_that_tile_the_grid_pass_and_a_lone_rank_is_not_checked() {
        let l = Layouts::default();
        for step in 0..3 {
            l.admit(&info(step, 0, 0, 5)).unwrap();
            assert!(l.record(&info(step, 0, 0, 5)).is_none());
            assert!(l.record(&info(step, 1, 4, 4)).is_none());
        }
        assert!(l.summary().is_none());
        assert!(l.whole_world_here(2) && l.whole_world_here(1) && !l.whole_world_here(3));
        let mut lone = info(0, 0, 0, 4);
        lone.world_size = 1;
        assert!(l.record(&lone).is_none());
        // A node serving part of a world forgets the oldest of the steps it never sees whole.
        for step in 0..200 {
            assert!(l.record(&info(step, 0, 0, 5)).is_none());
        }
        assert!(l.state().pending.len() <= MAX_PENDING);
    }
}
