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
//! ```
//!
//! A block longer than this is read up to here (a later version may append fields); a
//! shorter one is refused. Everything in it is fixed by the step and the run, so a VDI made
//! again for the same step (a generator-node restarted from its spool) has the same bytes and
//! is stored once; τ, a measurement that differs each time, stays in the index.

use super::codec::{CodecError, Reader};
use crate::volume::bricks::Brick;

/// Bytes of the block this version writes.
pub const LEN: usize = 105;

/// Where a VDI file comes from.
#[derive(Clone, Copy, Debug, PartialEq)]
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
}

impl Provenance {
    /// The block as the file holds it ([`LEN`] bytes).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(LEN);
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
        out
    }

    /// Reads a block.
    ///
    /// # Errors
    /// [`CodecError::Truncated`] for a block shorter than [`LEN`];
    /// [`CodecError::Invalid`] for a world of 0 ranks, a rank outside it, a non-finite time, an
    /// unknown flag, or a brick that is empty or leaves the grid.
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
        Ok(Self {
            step,
            rank,
            world_size,
            pm_version,
            sim_time,
            placement,
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
        }
    }

    #[test]
    fn a_block_reads_back_as_written_and_may_grow() {
        let p = sample();
        let bytes = p.to_bytes();
        assert_eq!(bytes.len(), LEN);
        assert_eq!(Provenance::from_bytes(&bytes).unwrap(), p);
        let mut longer = bytes.clone();
        longer.extend_from_slice(&[9; 16]);
        assert_eq!(Provenance::from_bytes(&longer).unwrap(), p);
        let unplaced = Provenance {
            placement: None,
            ..p
        };
        assert_eq!(
            Provenance::from_bytes(&unplaced.to_bytes()).unwrap(),
            unplaced
        );
    }

    #[test]
    fn impossible_blocks_are_refused_with_the_reason() {
        let bytes = sample().to_bytes();
        assert!(matches!(
            Provenance::from_bytes(&bytes[..LEN - 1]),
            Err(CodecError::Truncated { .. })
        ));
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
        let mut flag = bytes.clone();
        flag[32] = 2;
        assert!(Provenance::from_bytes(&flag)
            .unwrap_err()
            .to_string()
            .contains("placement flag 2"));
    }
}
