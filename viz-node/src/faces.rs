//! Where bricks that split the grid's points without sharing a plane meet across
//! generator-nodes (`ExchangeFaces`; docs/ranks-and-clients.md, "Bricks"): each node posts, per
//! step, the bricks of the ranks it received with their low faces (the first plane on each axis
//! where a brick does not start at 0), and waits until every rank of the step has been posted;
//! each then grows its bricks by its neighbours' faces as a node holding the whole world does.
//! The viz-node only relays: it checks what it keeps, and forgets the oldest steps.

use insitu_core::volume::ScalarType;
use insitu_proto::convert::wire_enum;
use insitu_proto::pb;
use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::Duration;
use tokio::sync::Notify;
use tonic::Status;

/// Steps whose posts are kept at most (the oldest forgotten).
pub const MAX_STEPS: usize = 64;

/// Bytes of faces kept at most, over every step.
pub const MAX_BYTES: u64 = 1 << 30;

/// The longest wait a post may ask for, seconds.
pub const MAX_WAIT_SECS: f64 = 60.0;

/// One step's posts.
#[derive(Debug)]
struct Posted {
    world_size: u32,
    global: [u32; 3],
    bricks: BTreeMap<u32, pb::BrickFaces>,
    bytes: u64,
}

#[derive(Debug, Default)]
struct State {
    steps: BTreeMap<u64, Posted>,
    bytes: u64,
}

/// The posts of the newest steps.
#[derive(Debug, Default)]
pub struct Faces {
    state: Mutex<State>,
    posted: Notify,
}

impl Faces {
    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps `offer`'s bricks (a rank posted again replaces its post) and waits until every
    /// rank of its step is posted, at most `offer.wait_secs` (at most [`MAX_WAIT_SECS`]);
    /// returns the step's posts in rank order.
    ///
    /// # Errors
    /// `INVALID_ARGUMENT` naming what is wrong with the offer ([`check`]), or a world size or
    /// grid other than the step's first post's; `RESOURCE_EXHAUSTED` when keeping it would pass
    /// [`MAX_BYTES`] after the older steps are forgotten.
    pub async fn exchange(&self, offer: pb::FacesOffer) -> Result<Vec<pb::BrickFaces>, Status> {
        let global = check(&offer)?;
        let wait = if offer.wait_secs.is_finite() && offer.wait_secs > 0.0 {
            offer.wait_secs.min(MAX_WAIT_SECS)
        } else {
            0.0
        };
        let step = offer.step;
        self.keep(offer, global)?;
        self.posted.notify_waiters();
        let deadline = tokio::time::Instant::now() + Duration::from_secs_f64(wait);
        loop {
            let posted = self.posted.notified();
            tokio::pin!(posted);
            posted.as_mut().enable();
            if let Some(all) = self.all(step, true) {
                return Ok(all);
            }
            if tokio::time::timeout_at(deadline, posted).await.is_err() {
                return Ok(self.all(step, false).unwrap_or_default());
            }
        }
    }

    fn keep(&self, offer: pb::FacesOffer, global: [u32; 3]) -> Result<(), Status> {
        let bytes: u64 = offer.bricks.iter().map(faces_bytes).sum();
        let mut s = self.state();
        let entry = s.steps.entry(offer.step).or_insert_with(|| Posted {
            world_size: offer.world_size,
            global,
            bricks: BTreeMap::new(),
            bytes: 0,
        });
        if entry.world_size != offer.world_size || entry.global != global {
            return Err(Status::invalid_argument(format!(
                "step {}: a world of {} ranks on a grid of {global:?} points, where its first post said {} ranks on {:?}",
                offer.step, offer.world_size, entry.world_size, entry.global
            )));
        }
        let mut freed = 0;
        for b in offer.bricks {
            if let Some(old) = entry.bricks.insert(b.rank, b) {
                freed += faces_bytes(&old);
            }
        }
        entry.bytes = entry.bytes + bytes - freed;
        s.bytes = s.bytes + bytes - freed;
        while s.steps.len() > MAX_STEPS || s.bytes > MAX_BYTES {
            let Some((&oldest, _)) = s.steps.first_key_value() else {
                break;
            };
            if oldest == offer.step {
                let gone = s.steps.remove(&oldest).map_or(0, |p| p.bytes);
                s.bytes -= gone;
                return Err(Status::resource_exhausted(format!(
                    "step {}: {bytes} bytes of faces would pass the viz-node's {MAX_BYTES} bytes for them",
                    offer.step
                )));
            }
            if let Some((_, p)) = s.steps.pop_first() {
                s.bytes -= p.bytes;
            }
        }
        Ok(())
    }

    /// `step`'s posts in rank order: when every rank is in, or (`complete` false) whatever is.
    fn all(&self, step: u64, complete: bool) -> Option<Vec<pb::BrickFaces>> {
        let s = self.state();
        let p = s.steps.get(&step)?;
        (!complete || p.bricks.len() >= p.world_size as usize)
            .then(|| p.bricks.values().cloned().collect())
    }
}

fn faces_bytes(b: &pb::BrickFaces) -> u64 {
    b.faces.iter().map(|f| f.values.len() as u64).sum()
}

/// The grid of `offer`, once what it posts is checked: a world of at least 2 ranks on a grid
/// of points, each brick a rank of it inside the grid, each face inside the grid and its bytes
/// exactly its points' samples of its type.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the step, the rank and the problem.
pub fn check(offer: &pb::FacesOffer) -> Result<[u32; 3], Status> {
    let bad = |what: String| Status::invalid_argument(format!("step {}: {what}", offer.step));
    let global = offer
        .global_dims
        .map(|d| [d.x, d.y, d.z])
        .ok_or_else(|| bad("no global_dims".into()))?;
    if offer.world_size < 2 || global.contains(&0) {
        return Err(bad(format!(
            "faces are exchanged for a world of 2 ranks or more on a grid of points, not {} on {global:?}",
            offer.world_size
        )));
    }
    let inside = |what: &str, o: Option<pb::Dims3>, d: Option<pb::Dims3>| {
        let (o, d) = o
            .zip(d)
            .ok_or_else(|| bad(format!("{what} without offset or dims")))?;
        let (o, d) = ([o.x, o.y, o.z], [d.x, d.y, d.z]);
        let fits =
            (0..3).all(|a| d[a] > 0 && u64::from(o[a]) + u64::from(d[a]) <= u64::from(global[a]));
        if !fits {
            return Err(bad(format!(
                "{what}: {d:?} points at {o:?} do not lie in the grid of {global:?}"
            )));
        }
        Ok(d.iter().map(|&n| u64::from(n)).product::<u64>())
    };
    for b in &offer.bricks {
        if b.rank >= offer.world_size {
            return Err(bad(format!(
                "rank {} of a world of {}",
                b.rank, offer.world_size
            )));
        }
        inside(&format!("rank {}'s brick", b.rank), b.offset, b.dims)?;
        for f in &b.faces {
            let what = format!("rank {}'s face", b.rank);
            let points = inside(&what, f.offset, f.dims)?;
            let dtype = wire_enum::<pb::ScalarType>(f.dtype, "dtype")
                .and_then(ScalarType::try_from)
                .map_err(|e| bad(format!("{what}: {}", e.message())))?;
            // A field is stored in 8, 16 or 32 bits (f64 is converted on receipt).
            if dtype == ScalarType::F64 {
                return Err(bad(format!("{what}: samples of {dtype:?} are not kept")));
            }
            if points.checked_mul(dtype.size_bytes() as u64) != Some(f.values.len() as u64) {
                return Err(bad(format!(
                    "{what}: {} bytes for {points} samples of {dtype:?}",
                    f.values.len()
                )));
            }
        }
    }
    Ok(global)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dims(x: u32, y: u32, z: u32) -> Option<pb::Dims3> {
        Some(pb::Dims3 { x, y, z })
    }

    /// Rank `rank` of the z-halves of a 4×4×8 grid (points 0–3 and 4–7), the upper half with
    /// its low z-face.
    fn half(rank: u32) -> pb::BrickFaces {
        let faces = if rank == 1 {
            vec![pb::Face {
                offset: dims(0, 0, 4),
                dims: dims(4, 4, 1),
                dtype: pb::ScalarType::F32 as i32,
                values: vec![0u8; 64].into(),
            }]
        } else {
            Vec::new()
        };
        pb::BrickFaces {
            rank,
            offset: dims(0, 0, 4 * rank),
            dims: dims(4, 4, 4),
            faces,
        }
    }

    fn offer(step: u64, bricks: Vec<pb::BrickFaces>, wait_secs: f64) -> pb::FacesOffer {
        pb::FacesOffer {
            step,
            world_size: 2,
            global_dims: dims(4, 4, 8),
            bricks,
            wait_secs,
        }
    }

    #[tokio::test]
    async fn each_node_gets_every_rank_once_all_are_posted() {
        let f = std::sync::Arc::new(Faces::default());
        let g = f.clone();
        let lower = tokio::spawn(async move { g.exchange(offer(3, vec![half(0)], 10.0)).await });
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(!lower.is_finished(), "rank 1 has not been posted");
        let upper = f.exchange(offer(3, vec![half(1)], 10.0)).await.unwrap();
        let lower = lower.await.unwrap().unwrap();
        assert_eq!(lower, upper);
        assert_eq!(lower.iter().map(|b| b.rank).collect::<Vec<_>>(), [0, 1]);
        assert_eq!(lower[1].faces[0].values.len(), 64);
        // Without the other rank the wait ends with what is there.
        let alone = f.exchange(offer(4, vec![half(0)], 0.05)).await.unwrap();
        assert_eq!(alone.len(), 1);
    }

    #[tokio::test]
    async fn bad_offers_are_refused_by_name_and_old_steps_forgotten() {
        let f = Faces::default();
        let refused = |o: pb::FacesOffer| {
            let f = &f;
            async move { f.exchange(o).await.unwrap_err().message().to_owned() }
        };
        let mut b = half(1);
        b.faces[0].values = b.faces[0].values.slice(1..);
        assert!(refused(offer(0, vec![b], 0.0))
            .await
            .contains("63 bytes for 16 samples of F32"));
        let mut b = half(1);
        b.rank = 2;
        assert!(refused(offer(0, vec![b], 0.0))
            .await
            .contains("rank 2 of a world of 2"));
        let mut b = half(1);
        b.offset = dims(0, 0, 5);
        assert!(refused(offer(0, vec![b], 0.0))
            .await
            .contains("do not lie in the grid"));
        let mut b = half(1);
        b.faces[0].dtype = pb::ScalarType::F64 as i32;
        assert!(refused(offer(0, vec![b], 0.0)).await.contains("not kept"));
        let mut o = offer(0, vec![half(0)], 0.0);
        o.world_size = 1;
        assert!(refused(o).await.contains("2 ranks or more"));
        // A second world size for a step is refused.
        f.exchange(offer(1, vec![half(0)], 0.0)).await.unwrap();
        let mut o = offer(1, vec![half(1)], 0.0);
        o.world_size = 3;
        assert!(refused(o).await.contains("its first post said 2 ranks"));
        // Only the newest steps are kept.
        for step in 10..10 + MAX_STEPS as u64 {
            f.exchange(offer(step, vec![half(1)], 0.0)).await.unwrap();
        }
        assert!(f.all(1, false).is_none());
        assert_eq!(f.state().steps.len(), MAX_STEPS);
        assert_eq!(f.state().bytes, 64 * MAX_STEPS as u64);
    }
}
