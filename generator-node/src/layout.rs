//! The ranks' bricks of the worlds pushing to this node.
//!
//! **Checked** at the first step whose ranks have all arrived here: bricks that cannot tile
//! the grid (a real hole, or overlap) are named once per run, the steps they make are
//! counted, and later pushes of the same bricks are refused at their header, so a simulation
//! hears of its decomposition at its next push rather than at the end of the run.
//!
//! **Grown** where they tile the grid's points without sharing a plane (as one splits an
//! array, and as ADIOS2 writers lay out blocks; `insitu_core::volume::tiling`): each push
//! leaves its low faces here as it arrives, and before a rank's brick is made the worker
//! grows it by its neighbours' faces ([`Layouts::growth`]), so the bricks it ships share their
//! boundary planes and compose without seams. The first step of a world waits (at most the
//! host's `wait_secs`) for its ranks to show how they tile.
//!
//! **Exchanged** where a world's ranks do not all push here (known once its first step's
//! ranks have not all come within that wait) and a viz-node is configured: each of its bricks
//! is posted to the viz-node with its low faces ([`Layouts::posts`], sent by
//! [`crate::faces`]), the other nodes' bricks and faces come back ([`Layouts::remote`]), and a
//! brick that grows waits for them (at most twice the host's wait) as for a neighbour pushed
//! here. Without a viz-node, or past that wait, bricks are made as pushed (the viz-node names
//! the cells they leave out).
//!
//! Only a world whose ranks all push to this node is checked here before it is made; a world
//! spread over several nodes is checked by the viz-node when it composes
//! (docs/ranks-and-clients.md).

use crate::ingest::StepInfo;
use insitu_core::volume::bricks::{Brick, DecompositionError};
use insitu_core::volume::tiling::{self, Tiling};
use insitu_core::volume::{Volume, VolumeError};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tonic::Status;
use tracing::{info, warn};

/// Steps whose ranks are not all in or not all made, kept at most: a node that serves part of
/// a world never sees one whole, and forgets the oldest.
const MAX_PENDING: usize = 64;

/// How long a brick that grows waits for its neighbours' faces once the world is known to
/// push here whole, seconds: past it, the brick is made as pushed.
const FACES_WAIT_SECS: f64 = 60.0;

/// A world's bricks, by rank, on one grid.
#[derive(Clone, Debug, PartialEq)]
struct Layout {
    global: [usize; 3],
    bricks: BTreeMap<u32, Brick>,
}

impl Layout {
    /// The bricks as `tiling` takes them, in rank order.
    fn placed(&self) -> Vec<(u32, Brick)> {
        self.bricks.iter().map(|(r, b)| (*r, *b)).collect()
    }

    /// How rank `rank`'s brick is made under `tiling` (as pushed when not of this layout).
    fn made(&self, tiling: &Tiling, rank: u32) -> Option<Brick> {
        let i = self.bricks.keys().position(|&r| r == rank)?;
        Some(tiling.made(i, self.bricks[&rank]))
    }
}

/// A layout that cannot tile its grid.
#[derive(Debug)]
struct Bad {
    layout: Layout,
    /// The first step that showed it.
    step: u64,
    why: DecompositionError,
}

/// A step whose ranks are not all in, or not all made.
#[derive(Debug)]
struct Pending {
    world_size: u32,
    layout: Layout,
    /// Each rank's low faces, where its bricks may grow.
    faces: BTreeMap<u32, Arc<Vec<(Brick, Volume)>>>,
    /// How the bricks tile, once all are in (`None` after: they do not).
    tiling: Option<Option<Tiling>>,
    /// Ranks whose worker has asked for its growth, or that were dropped.
    done: usize,
    /// Ranks pushed to other nodes, known from the exchange (never made here).
    remote: usize,
}

#[derive(Debug, Default)]
struct State {
    /// The steps in flight of worlds of several ranks.
    pending: BTreeMap<u64, Pending>,
    /// The last whole layout that tiled its grid, and how (not checked again).
    good: Option<(Layout, Tiling)>,
    /// The last whole layout that did not.
    bad: Option<Bad>,
    /// Steps whose whole layout did not tile the grid.
    bad_steps: u64,
    /// Pushes refused for their layout.
    refused: u64,
    /// The world size of the last step whose ranks all pushed here.
    whole: u32,
    /// A first step's ranks did not all arrive within the wait: the world pushes to several
    /// nodes, and no brick waits for a layout again until a whole one is seen (but for the
    /// exchange's answer, where there is one).
    apart: bool,
    /// Bricks to post to the viz-node for the exchange, one [`Post`] of one brick each.
    to_post: Vec<Post>,
    /// The (step, rank)s posted, the newest kept.
    posted: std::collections::BTreeSet<(u64, u32)>,
}

/// How a rank's brick is made ([`Layouts::growth`]).
#[derive(Debug)]
pub enum Growth {
    /// As pushed.
    AsPushed,
    /// Grown to `brick` from the neighbours' low faces `faces` (every rank's, its own passed over).
    Grow {
        /// The brick grown.
        brick: Brick,
        /// Every rank's low faces at this step.
        faces: Vec<Arc<Vec<(Brick, Volume)>>>,
        /// Whether some came from another node (the exchange).
        across: bool,
    },
}

impl Growth {
    /// The field of `info`'s brick grown, in the memory of `spare` where there is one (its
    /// info's brick made the grown one); `None` when there is nothing to grow.
    ///
    /// # Errors
    /// [`VolumeError`] when the faces do not fill the grown brick (cannot happen for faces
    /// of bricks that tile the points).
    pub fn apply(
        &self,
        info: &mut StepInfo,
        field: &Volume,
        spare: Option<Volume>,
    ) -> Result<Option<Volume>, VolumeError> {
        let Growth::Grow { brick, faces, .. } = self else {
            return Ok(None);
        };
        let own = Brick {
            offset: info.brick_offset,
            dims: info.brick_dims,
        };
        let pieces: Vec<(Brick, &Volume)> = faces
            .iter()
            .flat_map(|f| f.iter().map(|(b, v)| (*b, v)))
            .collect();
        let grown = tiling::grow(field, &own, brick, &pieces, spare)?;
        info.brick_dims = brick.dims;
        Ok(Some(grown))
    }
}

/// The layouts of the worlds pushing to this node.
#[derive(Debug, Default)]
pub struct Layouts {
    state: Mutex<State>,
    /// Rings when a step's ranks are all in.
    whole_step: Notify,
    /// Whether bricks of a world spread over nodes are exchanged through the viz-node.
    exchange: bool,
}

/// What a brick gives or takes across nodes ([`Layouts::posts`], [`Layouts::remote`]): its
/// rank, its points and its low faces.
pub type Placed = (u32, Brick, Arc<Vec<(Brick, Volume)>>);

/// One step's bricks to post for the exchange ([`Layouts::posts`]).
#[derive(Debug)]
pub struct Post {
    /// The step.
    pub step: u64,
    /// Its world's size.
    pub world_size: u32,
    /// The grid, points.
    pub global: [usize; 3],
    /// This node's bricks of the step not posted yet.
    pub bricks: Vec<Placed>,
    /// Whether a brick of this node at the step waits for the other nodes' bricks.
    pub waits: bool,
}

impl Post {
    /// `placed`, a brick of `step` of a world of `world_size` ranks on a grid of `global`
    /// points, waiting for the answer where it grows.
    fn one(world_size: u32, global: [usize; 3], step: u64, placed: Placed) -> Self {
        Self {
            step,
            world_size,
            global,
            waits: may_grow(&placed.1, global),
            bricks: vec![placed],
        }
    }
}

/// How much longer than the host's wait a brick of a world spread over nodes waits for the
/// exchange's answer.
const EXCHANGE_WAITS: u32 = 2;

impl Layouts {
    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Layouts whose worlds spread over nodes exchange their bricks' faces (`exchange`: a
    /// viz-node is configured).
    pub fn new(exchange: bool) -> Self {
        Self {
            exchange,
            ..Self::default()
        }
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

    /// Records a received step's brick, and its low faces (`field`'s) where it may give a
    /// neighbour's growth; once its step's ranks are all in, checks how their bricks tile the
    /// grid. Returns the fault the first time a layout shows it (logged).
    pub fn record(&self, info: &StepInfo, field: &Volume) -> Option<DecompositionError> {
        if info.world_size < 2 {
            return None;
        }
        let brick = brick_of(info);
        let mut s = self.state();
        // A layout known to share its planes needs no faces.
        let shared = s.good.as_ref().is_some_and(|(l, t)| {
            *t == Tiling::Shared
                && l.global == info.global_dims
                && l.bricks.get(&info.rank) == Some(&brick)
        });
        // Nor does a world that pushes to several nodes, as far as this node knows, unless
        // its bricks are exchanged; those are posted as they come.
        let apart = s.apart && s.good.is_none() && !self.exchange;
        let faces = if shared || apart || !brick.offset.iter().any(|&o| o > 0) {
            None
        } else {
            tiling::low_faces(field, &brick).ok().map(Arc::new)
        };
        if s.apart && self.exchange && !shared {
            let placed = (info.rank, brick, faces.clone().unwrap_or_default());
            s.to_post.push(Post::one(
                info.world_size,
                info.global_dims,
                info.step,
                placed,
            ));
        }
        let entry = s.pending.entry(info.step).or_insert_with(|| Pending {
            world_size: info.world_size,
            layout: Layout {
                global: info.global_dims,
                bricks: BTreeMap::new(),
            },
            faces: BTreeMap::new(),
            tiling: None,
            done: 0,
            remote: 0,
        });
        entry.layout.bricks.insert(info.rank, brick);
        if let Some(f) = faces {
            entry.faces.insert(info.rank, f);
        }
        let all_in = entry.layout.bricks.len() >= info.world_size as usize;
        if !all_in || entry.tiling.is_some() {
            drop(s);
            self.trim();
            return None;
        }
        let layout = entry.layout.clone();
        let remote = entry.remote > 0;
        let (tiling, fault) = self.judge(&mut s, info.step, layout, remote);
        if let Some(p) = s.pending.get_mut(&info.step) {
            p.tiling = Some(tiling);
        }
        if !remote {
            s.whole = info.world_size;
        }
        drop(s);
        self.whole_step.notify_waiters();
        self.trim();
        fault
    }

    /// How a whole step's `layout` tiles its grid, from the last one judged when it is the
    /// same; a new fault is logged and returned.
    fn judge(
        &self,
        s: &mut State,
        step: u64,
        layout: Layout,
        remote: bool,
    ) -> (Option<Tiling>, Option<DecompositionError>) {
        if let Some((good, tiling)) = &s.good {
            if *good == layout {
                return (Some(tiling.clone()), None);
            }
        }
        if s.bad.as_ref().is_some_and(|b| b.layout == layout) {
            s.bad_steps += 1;
            return (None, None);
        }
        match tiling::tiling(layout.global, &layout.placed()) {
            Ok(tiling) => {
                // A layout completed by the exchange is still spread over nodes.
                s.apart &= remote;
                s.good = Some((layout, tiling.clone()));
                (Some(tiling), None)
            }
            Err(why) => {
                warn!(step, error = %why, "the ranks' bricks cannot be composed; later pushes of these bricks are refused");
                s.bad_steps += 1;
                s.bad = Some(Bad {
                    layout,
                    step,
                    why: why.clone(),
                });
                (None, Some(why))
            }
        }
    }

    /// Keeps at most [`MAX_PENDING`] steps in flight, the oldest forgotten.
    fn trim(&self) {
        let mut s = self.state();
        while s.pending.len() > MAX_PENDING {
            s.pending.pop_first();
        }
    }

    /// How `info`'s brick is made: grown when its step's bricks tile the grid's points
    /// without sharing a plane. `Err(deadline)` while its step's other ranks are still to
    /// come and it must wait for them (asked again when [`Layouts::changed`] rings or at the
    /// deadline): at most `first_wait` after `since` (when it was first asked) on a world's
    /// first step, [`FACES_WAIT_SECS`] once its bricks are known to grow. A brick made as
    /// pushed where it should have grown is logged; the viz-node names the cells it leaves
    /// out. Each rank is counted made once it gets its answer.
    ///
    /// # Errors
    /// The instant to ask again by, as above.
    pub fn decide(
        &self,
        info: &StepInfo,
        first_wait: Duration,
        since: Instant,
    ) -> Result<Growth, Instant> {
        let growth = self.decision(info, first_wait, since)?;
        self.made(info.step);
        Ok(growth)
    }

    fn decision(
        &self,
        info: &StepInfo,
        first_wait: Duration,
        since: Instant,
    ) -> Result<Growth, Instant> {
        let brick = brick_of(info);
        let grows = may_grow(&brick, info.global_dims);
        // A brick that gives faces learns on the first step, as one that grows does, whether
        // its neighbours push here, and posts its faces where they do not.
        let gives = self.exchange && brick.offset.iter().any(|&o| o > 0);
        if info.world_size < 2 || !(grows || gives) {
            return Ok(Growth::AsPushed);
        }
        let mut s = self.state();
        if let Some(t) = s.pending.get(&info.step).and_then(|p| p.tiling.as_ref()) {
            return Ok(grown(&s, info, t.as_ref()));
        }
        // Not all in yet: what the last whole layout says of this brick.
        let known = s.good.as_ref().filter(|(l, _)| {
            l.global == info.global_dims
                && l.bricks.len() == info.world_size as usize
                && l.bricks.get(&info.rank) == Some(&brick)
        });
        let exchanged = since + first_wait * EXCHANGE_WAITS;
        let deadline = match known {
            Some((l, t)) if l.made(t, info.rank) == Some(brick) => return Ok(Growth::AsPushed),
            Some(_) if s.apart => exchanged,
            Some(_) => since + Duration::from_secs_f64(FACES_WAIT_SECS),
            None if s.apart && self.exchange && grows => exchanged,
            None if s.apart => return Ok(Growth::AsPushed),
            None => since + first_wait,
        };
        if Instant::now() < deadline {
            return Err(deadline);
        }
        if known.is_some() || s.apart {
            warn!(step = info.step, rank = info.rank, "a neighbour's faces did not arrive: the brick is made as pushed, and the cells between it and that neighbour are left out");
            return Ok(Growth::AsPushed);
        }
        s.apart = true;
        if !self.exchange {
            warn!(step = info.step, rank = info.rank, world_size = info.world_size, "the world's ranks did not all push here within the host's wait: its bricks are made as pushed (bricks laid out without a shared plane are grown only where one node receives them all, or with a viz-node to exchange their faces through)");
            return Ok(Growth::AsPushed);
        }
        info!(step = info.step, world_size = info.world_size, "the world's ranks do not all push here: their bricks' faces are exchanged through the viz-node");
        // Every brick received so far is posted; the steps after this one were received
        // before the world was known to be apart, and kept their faces.
        let due: Vec<Post> = s
            .pending
            .iter()
            .flat_map(|(&step, p)| {
                p.layout.bricks.iter().map(move |(&rank, &b)| {
                    let faces = p.faces.get(&rank).cloned().unwrap_or_default();
                    Post::one(p.world_size, p.layout.global, step, (rank, b, faces))
                })
            })
            .collect();
        s.to_post.extend(due);
        if grows {
            return Err(Instant::now() + first_wait * EXCHANGE_WAITS);
        }
        Ok(Growth::AsPushed)
    }

    /// The bricks to post to the viz-node for the exchange, by step; each (step, rank) once.
    pub fn posts(&self) -> Vec<Post> {
        let mut s = self.state();
        let due = std::mem::take(&mut s.to_post);
        let mut out: BTreeMap<u64, Post> = BTreeMap::new();
        for post in due {
            let fresh: Vec<Placed> = post
                .bricks
                .into_iter()
                .filter(|(rank, _, _)| s.posted.insert((post.step, *rank)))
                .collect();
            if fresh.is_empty() {
                continue;
            }
            let e = out.entry(post.step).or_insert(Post {
                bricks: Vec::new(),
                waits: false,
                ..post
            });
            e.bricks.extend(fresh);
            e.waits |= post.waits;
        }
        while s.posted.len() > 4 * MAX_PENDING {
            s.posted.pop_first();
        }
        out.into_values().collect()
    }

    /// The bricks of `step` posted by every node (`bricks`, this node's among them): those of
    /// ranks not received here join the step's layout, and once every rank is in its tiling
    /// is judged and the bricks waiting for it are decided.
    pub fn remote(&self, step: u64, bricks: Vec<Placed>) {
        let mut s = self.state();
        let Some(p) = s.pending.get_mut(&step) else {
            return;
        };
        if p.tiling.is_some() {
            return;
        }
        for (rank, brick, faces) in bricks {
            if p.layout.bricks.contains_key(&rank) {
                continue;
            }
            p.layout.bricks.insert(rank, brick);
            if !faces.is_empty() {
                p.faces.insert(rank, faces);
            }
            p.remote += 1;
        }
        if p.layout.bricks.len() < p.world_size as usize {
            return;
        }
        let layout = p.layout.clone();
        let (tiling, _) = self.judge(&mut s, step, layout, true);
        if let Some(p) = s.pending.get_mut(&step) {
            p.tiling = Some(tiling);
        }
        drop(s);
        self.whole_step.notify_waiters();
    }

    /// Rings when a step's ranks are all in (a brick that waits for them may be decided).
    pub fn changed(&self) -> tokio::sync::futures::Notified<'_> {
        self.whole_step.notified()
    }

    /// Counts one of `step`'s ranks as made (or dropped); the step is forgotten once all are.
    pub fn made(&self, step: u64) {
        let mut s = self.state();
        let apart = s.apart;
        let Some(p) = s.pending.get_mut(&step) else {
            return;
        };
        p.done += 1;
        // Once every rank received here is made, a step whose world is spread over nodes
        // needs nothing more here (what it posts was taken when it was due).
        let local_made = p.done + p.remote >= p.layout.bricks.len();
        if local_made && (p.tiling.is_some() || apart) {
            s.pending.remove(&step);
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

/// The growth of `info`'s brick under its step's `tiling` (`None`: it does not tile).
fn grown(s: &State, info: &StepInfo, tiling: Option<&Tiling>) -> Growth {
    let Some(p) = s.pending.get(&info.step) else {
        return Growth::AsPushed;
    };
    let made = tiling.and_then(|t| p.layout.made(t, info.rank));
    match made {
        Some(brick) if brick != brick_of(info) => Growth::Grow {
            brick,
            faces: p.faces.values().cloned().collect(),
            across: p.remote > 0,
        },
        _ => Growth::AsPushed,
    }
}

/// Whether `brick` may grow (it ends short of `global` on some axis, where a neighbour may
/// start one point past its end).
fn may_grow(brick: &Brick, global: [usize; 3]) -> bool {
    (0..3).any(|a| brick.offset[a] + brick.dims[a] < global[a])
}

fn brick_of(info: &StepInfo) -> Brick {
    Brick {
        offset: info.brick_offset,
        dims: info.brick_dims,
    }
}

#[cfg(test)]
mod tests;
