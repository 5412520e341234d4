//! Where in a run a VDI file comes from: the step, the rank and its brick, the world and the
//! `P_M` version. A VDI file of format version 3 carries it uncompressed at the start
//! of its body (under the file's checksum), so that a recording's index can be rebuilt from its
//! files alone and a file can be checked against the row that names it without decoding it
//! (docs/guarantees.md, "The recording").
//!
//! ```text
//! offset  size  field (little-endian)
//!  0       8    step (u64)
//!  8       4    rank (u32)
//! 12       4    world size (u32)
//! 16       8    P_M version (u64; 0: not from a tuner)
//! 24       8    simulation time (f64)
//! 32       1    1 when a placement follows, else 0
//! 33      72    global dims, brick offset, brick dims (3 × u64 each)
//! 105      4    n: ranks the VDI holds when a host composed several (u32; 0: the rank alone)
//! 109     4n    those ranks, ascending, the first being `rank` (u32 each)
//! 109+4n  8     the steered scene version (u64; 0: the configured scene; absent: 0)
//! ```
//!
//! A block of a host's composed part ([`Provenance::covers`]) names every rank it holds, and
//! its placement is the union of their bricks, itself a box (docs/scale.md). A block that ends
//! at byte 105 (written before hosts composed) holds its rank alone; a longer one is read up
//! to the end of the ranks (a later version may append fields); a shorter one is refused. Everything in it is fixed by the step and the run, so a VDI made
//! again for the same step (a generator-node restarted from its spool) has the same bytes and
//! is stored once; τ, a measurement that differs each time, stays in the index.

use super::codec::format::{CodecError, Reader};
use crate::volume::bricks::Brick;

/// Bytes of the block's fixed part (a block holding one rank is this long plus 4).
pub const LEN: usize = 105;

/// Where a VDI file comes from.
#[derive(Clone, Debug, PartialEq)]
pub struct Provenance {
    /// The simulation step.
    pub step: u64,
    /// The rank whose brick the VDI shows.
    pub rank: u32,
    /// Ranks in the step's world (≥ 1).
    pub world_size: u32,
    /// The tuner's `P_M` version the VDI was made with (0: not from a tuner).
    pub pm_version: u64,
    /// Simulation time of the step.
    pub sim_time: f64,
    /// The whole grid's dims and the rank's brick in it, voxels (none when not said).
    pub placement: Option<([usize; 3], Brick)>,
    /// The ranks the VDI holds when a generator-node composed several of its ranks into one
    /// part (ascending, `rank` first); empty: `rank` alone.
    pub covers: Vec<u32>,
    /// The steered scene version the VDI was made with (docs/steering.md; 0: the scene the
    /// nodes were configured with).
    pub scene_version: u64,
}

/// Whether `covers` may name the ranks of a part whose first rank is `rank` in a world of
/// `world_size`: empty (the rank alone), or strictly ascending from `rank`, each inside the
/// world.
pub fn covers_valid(rank: u32, world_size: u32, covers: &[u32]) -> bool {
    covers.is_empty()
        || (covers[0] == rank
            && covers.windows(2).all(|w| w[0] < w[1])
            && covers.iter().all(|&r| r < world_size))
}

impl Provenance {
    /// The ranks the VDI holds: [`Self::covers`], or `rank` alone.
    pub fn ranks(&self) -> Vec<u32> {
        if self.covers.is_empty() {
            vec![self.rank]
        } else {
            self.covers.clone()
        }
    }

    /// The block as the file holds it ([`LEN`] + 4 + 4 · covered ranks + 8 bytes).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(LEN + 12 + 4 * self.covers.len());
        out.extend_from_slice(&self.step.to_le_bytes());
        out.extend_from_slice(&self.rank.to_le_bytes());
        out.extend_from_slice(&self.world_size.to_le_bytes());
        out.extend_from_slice(&self.pm_version.to_le_bytes());
        out.extend_from_slice(&self.sim_time.to_le_bytes());
        let (global, brick) = self.placement.unwrap_or((
            [0; 3],
            Brick {
                offset: [0; 3],
                dims: [0; 3],
            },
        ));
        out.push(u8::from(self.placement.is_some()));
        for v in global.iter().chain(&brick.offset).chain(&brick.dims) {
            out.extend_from_slice(&(*v as u64).to_le_bytes());
        }
        out.extend_from_slice(&(self.covers.len() as u32).to_le_bytes());
        for r in &self.covers {
            out.extend_from_slice(&r.to_le_bytes());
        }
        out.extend_from_slice(&self.scene_version.to_le_bytes());
        out
    }

    /// Reads a block.
    ///
    /// # Errors
    /// [`CodecError::Truncated`] for a block shorter than [`LEN`];
    /// [`CodecError::Invalid`] for a world of 0 ranks, a rank outside it, a non-finite time, an
    /// unknown flag, a brick that is empty or leaves the grid, or covered ranks that are not
    /// ascending from `rank` inside the world.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, CodecError> {
        let mut rd = Reader::new(bytes);
        let step = rd.u64("provenance step")?;
        let rank = rd.u32("provenance rank")?;
        let world_size = rd.u32("provenance world size")?;
        let pm_version = rd.u64("provenance P_M version")?;
        let sim_time = f64::from_le_bytes(rd.array("provenance simulation time")?);
        let placed = rd.u8("provenance placement flag")?;
        let mut dims = [[0usize; 3]; 3];
        for d in dims.iter_mut().flatten() {
            *d = usize::try_from(rd.u64("provenance placement")?).unwrap_or(usize::MAX);
        }
        let invalid = |what: String| Err(CodecError::Invalid(format!("provenance: {what}")));
        if world_size == 0 || rank >= world_size {
            return invalid(format!("rank {rank} of a world of {world_size}"));
        }
        if !sim_time.is_finite() {
            return invalid(format!("simulation time {sim_time}"));
        }
        let placement = match placed {
            0 => None,
            1 => {
                let [global, offset, size] = dims;
                let inside = (0..3).all(|a| {
                    size[a] >= 1
                        && offset[a]
                            .checked_add(size[a])
                            .is_some_and(|end| end <= global[a])
                });
                if !inside {
                    return invalid(format!(
                        "brick at {offset:?} of {size:?} voxels is not inside a grid of {global:?}"
                    ));
                }
                Some((global, Brick { offset, dims: size }))
            }
            other => return invalid(format!("placement flag {other} is not 0 or 1")),
        };
        let mut covers = Vec::new();
        let mut scene_version = 0;
        if rd.remaining() > 0 {
            let n = rd.u32("provenance covered ranks")?;
            if n > world_size {
                return invalid(format!("{n} covered ranks in a world of {world_size}"));
            }
            for _ in 0..n {
                covers.push(rd.u32("provenance covered rank")?);
            }
            if !covers_valid(rank, world_size, &covers) {
                return invalid(format!(
                    "covered ranks {covers:?} must ascend from rank {rank} inside a world of {world_size}"
                ));
            }
            if rd.remaining() > 0 {
                scene_version = rd.u64("provenance scene version")?;
            }
        }
        Ok(Self {
            step,
            rank,
            world_size,
            pm_version,
            sim_time,
            placement,
            covers,
            scene_version,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Provenance {
        Provenance {
            step: 1 << 40,
            rank: 3,
            world_size: 8,
            pm_version: 7,
            sim_time: 12.5,
            placement: Some((
                [64, 64, 128],
                Brick {
                    offset: [0, 32, 63],
                    dims: [33, 32, 65],
                },
            )),
            covers: vec![3, 5],
            scene_version: 2,
        }
    }

    #[test]
    fn a_block_reads_back_as_written_and_may_grow() {
        let p = sample();
        let bytes = p.to_bytes();
        assert_eq!(bytes.len(), LEN + 4 + 8 + 8);
        assert_eq!(Provenance::from_bytes(&bytes).unwrap(), p);
        assert_eq!(p.ranks(), [3, 5]);
        let mut longer = bytes.clone();
        longer.extend_from_slice(&[9; 16]);
        assert_eq!(Provenance::from_bytes(&longer).unwrap(), p);
        // A block written before hosts composed: its rank alone.
        let alone = Provenance::from_bytes(&bytes[..LEN]).unwrap();
        assert_eq!((alone.covers.len(), alone.ranks()), (0, vec![3]));
        // One written before scenes were steered: the configured scene.
        let unsteered = Provenance::from_bytes(&bytes[..LEN + 4 + 8]).unwrap();
        assert_eq!(unsteered.scene_version, 0);
        assert_eq!(unsteered.covers, p.covers);
        let unplaced = Provenance {
            placement: None,
            ..p.clone()
        };
        assert_eq!(
            Provenance::from_bytes(&unplaced.to_bytes()).unwrap(),
            unplaced
        );
    }

    #[test]
    fn impossible_blocks_are_refused_with_the_reason() {
        let bytes = sample().to_bytes();
        for cut in [LEN - 1, LEN + 2, LEN + 6, LEN + 4 + 8 + 3] {
            assert!(matches!(
                Provenance::from_bytes(&bytes[..cut]),
                Err(CodecError::Truncated { .. })
            ));
        }
        let with = |f: fn(&mut Provenance)| {
            let mut p = sample();
            f(&mut p);
            Provenance::from_bytes(&p.to_bytes())
                .unwrap_err()
                .to_string()
        };
        assert!(with(|p| p.rank = 8).contains("rank 8 of a world of 8"));
        assert!(with(|p| p.world_size = 0).contains("world of 0"));
        assert!(with(|p| p.sim_time = f64::NAN).contains("simulation time NaN"));
        assert!(with(|p| {
            if let Some((_, b)) = &mut p.placement {
                b.offset[2] = 64;
            }
        })
        .contains("not inside"));
        assert!(with(|p| p.covers = vec![2, 3]).contains("ascend from rank 3"));
        assert!(with(|p| p.covers = vec![3, 3]).contains("ascend from rank 3"));
        assert!(with(|p| p.covers = vec![3, 8]).contains("inside a world of 8"));
        assert!(with(|p| p.covers = (3..12).collect()).contains("9 covered ranks"));
        let mut flag = bytes.clone();
        flag[32] = 2;
        assert!(Provenance::from_bytes(&flag)
            .unwrap_err()
            .to_string()
            .contains("placement flag 2"));
    }
}
