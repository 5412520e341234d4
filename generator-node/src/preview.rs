//! A transfer function previewed on a held step before it is steered (docs/steering.md): each
//! rank of the step this node holds is rendered by reference DVR with the asked transfer
//! function from the asked camera, cut to the window its brick covers and compressed, for the
//! tuner to compose front to back with the other nodes' ranks
//! ([`insitu_core::compose::compose_frames`]). Nothing held changes.

use crate::hold::Holds;
use insitu_core::compose::window_of;
use insitu_core::{dvr, Camera, Raycaster};
use insitu_proto::convert::{preview_frame_to_pb, preview_size, preview_tf};
use insitu_proto::pb;
use std::time::Instant;

/// The frames of `req.step`'s ranks held here, one per rank; one frame with `error` set
/// when the request is bad or no rank of the step is held here, or per rank when its
/// rendering fails.
pub fn render(holds: &Holds, req: &pb::PreviewRequest) -> Vec<pb::PreviewFrame> {
    let refused = |rank: u32, error: String| pb::PreviewFrame {
        preview_id: req.preview_id,
        step: req.step.unwrap_or_default(),
        rank,
        error,
        ..Default::default()
    };
    let Some(step) = req.step else {
        return vec![refused(0, "no step named".into())];
    };
    let size = match preview_size(req.size) {
        Ok(s) => s,
        Err(e) => return vec![refused(0, e)],
    };
    let tf = match preview_tf(req) {
        Ok(tf) => tf,
        Err(e) => return vec![refused(0, e)],
    };
    let asked = match req.camera.as_ref().map(Camera::try_from).transpose() {
        Ok(c) => c,
        Err(e) => return vec![refused(0, format!("camera: {}", e.message()))],
    };
    let ranks = holds.ranks(step);
    if ranks.is_empty() {
        return vec![refused(0, format!("step {step} is not held here"))];
    }
    ranks
        .into_iter()
        .map(|(rank, held)| {
            let t0 = Instant::now();
            let camera = asked.unwrap_or(held.camera);
            let rc = match Raycaster::new(&held.volume, &tf, held.raycast) {
                Ok(rc) => rc,
                Err(e) => return refused(rank, e.to_string()),
            };
            let (image, opacity) = dvr::render_with_opacity(&rc, &camera, size, size);
            let window = window_of(&image, &opacity);
            match preview_frame_to_pb(&window, held.volume.world_box(), &camera) {
                Ok(f) => pb::PreviewFrame {
                    preview_id: req.preview_id,
                    step,
                    rank,
                    render_secs: t0.elapsed().as_secs_f64(),
                    ..f
                },
                Err(e) => refused(rank, e),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hold::HeldStep;
    use insitu_core::raycast::RaycastParams;
    use insitu_core::vdi::codec::Codec;
    use insitu_core::{Camera, NamedTf, TransferFunction, Volume};
    use std::collections::BTreeMap;
    use std::sync::Arc;

    const TF: &str = r#"{"domain":[0,1],"points":[[0,1,0,0,0],[1,1,0,0,0.9]]}"#;

    fn held() -> Holds {
        let n = 8;
        let data: Vec<f32> = (0..n * n * n).map(|i| (i % n) as f32 / 7.0).collect();
        let volume = Volume::new([n; 3], glam::Vec3::ONE, data).unwrap();
        let camera = Camera::default_for_box(&volume.world_box());
        let holds = Holds::new(1 << 20);
        let tf = TransferFunction::from_json(TF, "own").unwrap();
        let step = HeldStep {
            volume: Arc::new(volume),
            tf: Arc::new(NamedTf::new(tf, "own")),
            camera,
            raycast: RaycastParams::default(),
            codec: Codec::None,
            precision: insitu_core::Precision::Float32,
            view_angles_deg: vec![0.0],
            reference_size: 0,
            references: BTreeMap::new(),
            sizes: BTreeMap::new(),
        };
        assert!(holds.offer((4, 0), step));
        holds
    }

    fn req(tf_json: &str, size: u32) -> pb::PreviewRequest {
        let tf = TransferFunction::from_json(tf_json, "test").unwrap();
        pb::PreviewRequest {
            preview_id: 7,
            step: Some(4),
            tf: Some(pb::TransferFunction::from(&tf)),
            size,
            ..Default::default()
        }
    }

    #[test]
    fn a_held_rank_is_rendered_with_the_asked_tf_as_the_reference_dvr() {
        let holds = held();
        let frames = render(&holds, &req(TF, 32));
        assert_eq!(frames.len(), 1);
        let f = &frames[0];
        assert!(f.error.is_empty(), "{}", f.error);
        assert_eq!((f.preview_id, f.step, f.rank), (7, 4, 0));
        let ([ox, oy], window, alpha, _) =
            insitu_proto::convert::preview_window_from_pb(f, 32).unwrap();
        // The same as rendering the held field with that TF here, pixel for pixel.
        let ranks = holds.ranks(4);
        let held = &ranks[0].1;
        let tf = TransferFunction::from_json(TF, "x").unwrap();
        let rc = Raycaster::new(&held.volume, &tf, held.raycast).unwrap();
        let (image, opacity) = dvr::render_with_opacity(&rc, &held.camera, 32, 32);
        let (ox, oy) = (ox as usize, oy as usize);
        for j in 0..f.height as usize {
            for i in 0..f.width as usize {
                let p = (oy + j) * 32 + ox + i;
                let w = j * f.width as usize + i;
                assert_eq!(window.pixels()[w], image.pixels()[p]);
                assert_eq!(alpha[w], opacity[p]);
            }
        }
        assert!(opacity.iter().any(|&a| a > 0.5), "the TF is dense at 1");
        // A red ramp: no green or blue anywhere.
        assert!(window.pixels().iter().all(|c| c[1] == 0.0 && c[2] == 0.0));
    }

    #[test]
    fn bad_requests_and_steps_not_held_are_answered_with_why() {
        let holds = held();
        let one = |r: pb::PreviewRequest| {
            let f = render(&holds, &r);
            assert_eq!(f.len(), 1);
            f[0].error.clone()
        };
        let mut bad = req(TF, 32);
        bad.tf.as_mut().unwrap().domain_lo = f64::INFINITY;
        assert!(one(bad).starts_with("tf: transfer function on the wire: domain"));
        let mut none = req(TF, 32);
        none.tf = None;
        assert_eq!(one(none), "tf: no transfer function to preview");
        let mut old = req(TF, 32);
        old.legacy_tf_json = TF.into();
        assert!(one(old).starts_with("tf_json:"));
        assert!(one(req(TF, 8)).contains("not in 16..=512"));
        assert!(one(req(TF, 4096)).contains("not in 16..=512"));
        let mut other = req(TF, 32);
        other.step = Some(5);
        assert_eq!(one(other), "step 5 is not held here");
        let mut degenerate = req(TF, 32);
        degenerate.camera = Some(pb::Camera::default());
        assert!(one(degenerate).starts_with("camera:"));
    }
}
