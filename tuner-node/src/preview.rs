//! `Tuner.Preview` (docs/steering.md): a transfer function seen on a held step before it is
//! steered. The nodes that hold the step's ranks render their bricks by reference DVR with it
//! (`insitu_generator_node::preview`); here the windows are composed front to back in the
//! order each pixel's ray enters the bricks' boxes ([`compose_frames`]: exact for disjoint
//! boxes), the picture the whole field would give. Nothing is steered or kept.

use crate::engine::Engine;
use crate::hub::PreviewReply;
use insitu_core::compose::{compose_frames, BrickFrame};
use insitu_core::{Camera, Image};
use insitu_proto::convert::{preview_size, preview_tf, preview_window_from_pb};
use insitu_proto::pb;
use std::time::{Duration, Instant};
use tonic::Status;

/// How long the nodes get to answer.
pub const TIMEOUT: Duration = Duration::from_secs(30);

/// Checks `req`, asks the nodes holding its step (or the newest step held whole) for their
/// ranks' frames and composes them.
///
/// # Errors
/// `INVALID_ARGUMENT` naming a bad size, transfer function or camera; `FAILED_PRECONDITION`
/// before any step was summarised, when no step (or not the one named) is held whole by the
/// connected nodes, or when a node could not render its rank (its message); `DEADLINE_EXCEEDED`
/// after [`TIMEOUT`]; `INTERNAL` when the frames do not compose.
pub async fn preview(e: &Engine, mut req: pb::PreviewRequest) -> Result<pb::PreviewReply, Status> {
    let t0 = Instant::now();
    let size = preview_size(req.size).map_err(Status::invalid_argument)?;
    preview_tf(&req).map_err(Status::invalid_argument)?;
    if let Some(c) = &req.camera {
        Camera::try_from(c)
            .map_err(|e| Status::invalid_argument(format!("camera: {}", e.message())))?;
    }
    let world_size = e.domain().world_size;
    if world_size == 0 {
        return Err(Status::failed_precondition(
            "no step has been made yet: there is nothing to preview on",
        ));
    }
    let step = match req.step {
        Some(s) => s,
        None => e.hub.newest_whole(world_size).ok_or_else(|| {
            Status::failed_precondition(format!(
                "no step is held whole by the connected nodes (all {world_size} ranks)"
            ))
        })?,
    };
    req.step = Some(step);
    req.size = size;
    let (id, rx) = e
        .hub
        .request_preview(req, world_size)
        .map_err(|e| Status::failed_precondition(e.to_string()))?;
    let frames: PreviewReply = match tokio::time::timeout(TIMEOUT, rx).await {
        Ok(Ok(r)) => r,
        Ok(Err(_)) => return Err(Status::unavailable("the tuner is stopping")),
        Err(_) => {
            e.hub.abandon_preview(id);
            return Err(Status::deadline_exceeded(format!(
                "the nodes did not render step {step} within {} s",
                TIMEOUT.as_secs()
            )));
        }
    };
    let frames = frames.map_err(Status::failed_precondition)?;
    let image = compose(&frames, size).map_err(Status::internal)?;
    Ok(pb::PreviewReply {
        step,
        size,
        rgb: image.to_rgb8().into(),
        ranks: frames.len() as u32,
        render_secs: frames.iter().map(|f| f.render_secs).fold(0.0, f64::max),
        secs: t0.elapsed().as_secs_f64(),
    })
}

/// The ranks' frames (`size × size`, each a window of its brick) composed into one picture
/// over black.
///
/// # Errors
/// A message naming the rank whose frame does not decompress, does not hold its window's
/// pixels, lacks its box or camera, or does not lie inside the picture.
pub fn compose(frames: &[pb::PreviewFrame], size: u32) -> Result<Image, String> {
    let camera = frames
        .first()
        .and_then(|f| f.camera.as_ref())
        .ok_or("no frame carries the camera")?;
    let camera: Camera = Camera::try_from(camera).map_err(|e| e.message().to_owned())?;
    let windows = frames
        .iter()
        .map(|f| preview_window_from_pb(f, size))
        .collect::<Result<Vec<_>, _>>()?;
    let bricks: Vec<BrickFrame> = windows
        .iter()
        .map(|(origin, image, opacity, world_box)| BrickFrame {
            image,
            opacity,
            origin: *origin,
            world_box: *world_box,
        })
        .collect();
    compose_frames(&camera, (size, size), &bricks)
        .map(|(image, _)| image)
        .map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::compose::window_of;
    use insitu_core::raycast::RaycastParams;
    use insitu_core::volume::bricks::grid_bricks;
    use insitu_core::{dvr, Raycaster, TransferFunction, Volume};
    use insitu_proto::convert::preview_frame_to_pb;

    const TF: &str = r#"{"domain":[0,1],"points":[[0,0,0,1,0],[0.5,0,1,0,0.3],[1,1,0,0,0.9]]}"#;

    /// A 17³ field, whole and as 2 × 1 × 2 bricks sharing their faces.
    fn field() -> (Volume, Vec<Volume>) {
        let n = 17;
        let value = |x: usize, y: usize, z: usize| {
            let d = [x as f32 - 6.0, y as f32 - 9.0, z as f32 - 10.0];
            (-(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / 30.0).exp()
        };
        let whole: Vec<f32> = (0..n * n * n)
            .map(|i| value(i % n, (i / n) % n, i / (n * n)))
            .collect();
        let whole = Volume::new([n; 3], glam::Vec3::ONE, whole).unwrap();
        let bricks = grid_bricks([n; 3], [2, 1, 2])
            .unwrap()
            .into_iter()
            .map(|b| {
                let mut data = Vec::new();
                for z in 0..b.dims[2] {
                    for y in 0..b.dims[1] {
                        for x in 0..b.dims[0] {
                            data.push(value(b.offset[0] + x, b.offset[1] + y, b.offset[2] + z));
                        }
                    }
                }
                let origin =
                    glam::Vec3::new(b.offset[0] as f32, b.offset[1] as f32, b.offset[2] as f32);
                Volume::new(b.dims, glam::Vec3::ONE, data)
                    .unwrap()
                    .with_origin(origin)
                    .unwrap()
            })
            .collect();
        (whole, bricks)
    }

    /// Rank `rank`'s frame as a node sends it.
    fn frame(rank: u32, v: &Volume, camera: &Camera, size: u32) -> pb::PreviewFrame {
        let tf = TransferFunction::from_json(TF, "t").unwrap();
        let rc = Raycaster::new(v, &tf, RaycastParams::default()).unwrap();
        let (image, opacity) = dvr::render_with_opacity(&rc, camera, size, size);
        pb::PreviewFrame {
            rank,
            ..preview_frame_to_pb(&window_of(&image, &opacity), v.world_box(), camera).unwrap()
        }
    }

    #[test]
    fn the_ranks_frames_compose_to_the_whole_field_s_dvr() {
        let (whole, bricks) = field();
        let tf = TransferFunction::from_json(TF, "t").unwrap();
        let rc = Raycaster::new(&whole, &tf, RaycastParams::default()).unwrap();
        for angle in [0.0, 40.0, 135.0, 250.0] {
            let camera = Camera::default_for_box(&whole.world_box()).orbit(angle, 20.0, 1.0);
            let frames: Vec<_> = bricks
                .iter()
                .enumerate()
                .map(|(k, b)| frame(k as u32, b, &camera, 48))
                .collect();
            let composed = compose(&frames, 48).unwrap();
            let reference = dvr::render(&rc, &camera, 48, 48);
            let q = insitu_core::metrics::psnr(&composed, &reference).unwrap();
            assert!(q >= 40.0, "{angle}°: {q:.1} dB");
        }
    }

    #[test]
    fn frames_that_do_not_hold_their_window_are_named() {
        let (_, bricks) = field();
        let camera = Camera::default_for_box(&bricks[0].world_box());
        let mut f = frame(3, &bricks[0], &camera, 32);
        f.width += 1;
        let e = compose(&[f.clone()], 32).unwrap_err();
        assert!(e.starts_with("rank 3:") && e.contains("window"), "{e}");
        f.width -= 1;
        f.rgba_zstd = vec![1, 2, 3].into();
        assert!(compose(&[f.clone()], 32)
            .unwrap_err()
            .contains("does not decompress"));
        let mut f = frame(3, &bricks[0], &camera, 32);
        f.box_min = None;
        assert_eq!(compose(&[f], 32).unwrap_err(), "rank 3: no box");
        assert!(compose(&[], 32).is_err());
    }
}
