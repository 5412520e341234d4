//! The generator-node's side of the exchange of faces (docs/ranks-and-clients.md, "Bricks"):
//! for a world whose ranks push to several nodes and whose bricks share no plane, the bricks
//! [`crate::layout::Layouts::posts`] names go to the viz-node (`ExchangeFaces`, the shard the
//! step ships to, so that every node of the world meets at one), and the bricks and faces of
//! the other nodes' ranks that come back join the step's layout
//! ([`crate::layout::Layouts::remote`]). The viz-node only relays.

use crate::layout::Placed;
use crate::shared::Shared;
use glam::Vec3;
use insitu_core::volume::bricks::Brick;
use insitu_core::volume::{ScalarType, Volume};
use insitu_proto::convert::wire_enum;
use insitu_proto::pb;
use std::sync::Arc;
use tracing::warn;

/// Posts what the layouts name, each step's bricks in one call on a task of its own; where a
/// brick of this node waits for the other nodes' bricks, the answer (waited for at most twice
/// the host's wait) joins the step's layout. A failed call is logged; the bricks that waited
/// are then made as pushed when their wait ends.
pub fn send(shared: &Arc<Shared>) {
    if shared.viz_shards.is_empty() {
        return;
    }
    for crate::layout::Post {
        step,
        world_size,
        global,
        bricks,
        waits,
    } in shared.layout.posts()
    {
        let wait = if waits {
            shared.host.wait() * 2
        } else {
            std::time::Duration::ZERO
        };
        let offer = pb::FacesOffer {
            step,
            world_size,
            global_dims: Some(global.into()),
            bricks: bricks.iter().map(brick_faces).collect(),
            wait_secs: wait.as_secs_f64(),
        };
        let sent = faces_bytes(&offer.bricks);
        shared.stats.update(|c| c.faces_sent_bytes += sent);
        let shard = shared.shard_of(step);
        let shared = shared.clone();
        tokio::spawn(async move {
            let reply = async {
                let peer = &shared.viz_shards[shard];
                let client = shared.faces_clients[shard]
                    .get_or_try_init(|| crate::viz_link::connect(peer))
                    .await?;
                let reply = client.clone().exchange_faces(offer).await?;
                Ok::<_, tonic::Status>(reply.into_inner())
            };
            match reply.await {
                Ok(r) if waits => {
                    let received = faces_bytes(&r.bricks);
                    shared.stats.update(|c| c.faces_received_bytes += received);
                    match r.bricks.iter().map(placed).collect::<Result<Vec<_>, _>>() {
                        Ok(bricks) => shared.layout.remote(step, bricks),
                        Err(e) => {
                            warn!(step, error = %e, "the viz-node's answer to the exchange of faces is not usable: bricks that grow by them are made as pushed")
                        }
                    }
                }
                Ok(_) => {}
                Err(e) => {
                    warn!(step, code = ?e.code(), error = %e.message(), "the exchange of faces through the viz-node failed: bricks that grow by them are made as pushed")
                }
            }
        });
    }
}

/// Bytes of samples in `bricks`' faces.
fn faces_bytes(bricks: &[pb::BrickFaces]) -> u64 {
    bricks
        .iter()
        .flat_map(|b| &b.faces)
        .map(|f| f.values.len() as u64)
        .sum()
}

/// A brick and its faces as the wire carries them.
fn brick_faces((rank, brick, faces): &Placed) -> pb::BrickFaces {
    pb::BrickFaces {
        rank: *rank,
        offset: Some(brick.offset.into()),
        dims: Some(brick.dims.into()),
        faces: faces
            .iter()
            .map(|(b, v)| {
                let voxels = v.voxels();
                pb::Face {
                    offset: Some(b.offset.into()),
                    dims: Some(b.dims.into()),
                    dtype: pb::ScalarType::from(voxels.scalar_type()) as i32,
                    values: voxels.to_le_bytes().into_owned().into(),
                }
            })
            .collect(),
    }
}

/// A brick and its faces from the wire.
///
/// # Errors
/// Naming the rank and what is missing or does not fill its face.
fn placed(b: &pb::BrickFaces) -> Result<Placed, String> {
    let dims3 = |d: Option<pb::Dims3>, what: &str| {
        d.as_ref()
            .map(<[usize; 3]>::from)
            .ok_or_else(|| format!("rank {}: no {what}", b.rank))
    };
    let brick = Brick {
        offset: dims3(b.offset, "offset")?,
        dims: dims3(b.dims, "dims")?,
    };
    let faces = b
        .faces
        .iter()
        .map(|f| {
            let piece = Brick {
                offset: dims3(f.offset, "face offset")?,
                dims: dims3(f.dims, "face dims")?,
            };
            let scalar = wire_enum::<pb::ScalarType>(f.dtype, "dtype")
                .and_then(ScalarType::try_from)
                .map_err(|e| format!("rank {}: {}", b.rank, e.message()))?;
            let v = Volume::from_le_bytes(piece.dims, Vec3::ONE, scalar, f.values.to_vec())
                .map_err(|e| format!("rank {}'s face: {e}", b.rank))?;
            Ok((piece, v))
        })
        .collect::<Result<Vec<_>, String>>()?;
    Ok((b.rank, brick, Arc::new(faces)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_brick_and_its_faces_cross_the_wire_unchanged() {
        let field = Volume::new([4, 4, 4], Vec3::ONE, (0..64).map(|i| i as f32).collect()).unwrap();
        let brick = Brick {
            offset: [0, 0, 4],
            dims: [4, 4, 4],
        };
        let faces = insitu_core::volume::tiling::low_faces(&field, &brick).unwrap();
        let sent: Placed = (1, brick, Arc::new(faces));
        let (rank, b, f) = placed(&brick_faces(&sent)).unwrap();
        assert_eq!((rank, b), (1, brick));
        assert_eq!(f.len(), sent.2.len());
        for ((b0, v0), (b1, v1)) in f.iter().zip(sent.2.iter()) {
            assert_eq!(b0, b1);
            assert_eq!(v0.voxels().to_le_bytes(), v1.voxels().to_le_bytes());
        }
        // A face whose bytes do not fill it is refused, naming the rank.
        let mut wire = brick_faces(&sent);
        wire.faces[0].values = wire.faces[0].values.slice(4..);
        assert!(placed(&wire).unwrap_err().contains("rank 1's face"));
    }
}
