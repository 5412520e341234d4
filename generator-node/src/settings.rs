//! The generation settings as they travel: a `GenerationConfig` pushed by an operator or
//! recorded in the spool, read into [`Generation`] (all or nothing) and written back.

use crate::config::Generation;
use insitu_core::raycast::RaycastParams;
use insitu_core::{TransferFunction, VdiParams};
use insitu_proto::convert::{camera_from_pb, codec_from_pb};
use insitu_proto::pb;
use tonic::Status;

/// Largest transfer function accepted over the wire, bytes.
pub const MAX_TF_JSON: usize = 1 << 20;

/// The settings as a `GenerationConfig` (what [`apply_config`] reads back).
pub fn to_pb(g: &Generation) -> pb::GenerationConfig {
    pb::GenerationConfig {
        resolution: g.params.resolution,
        gamma: g.params.gamma,
        step: Some(g.raycast.step),
        termination: Some(g.raycast.termination),
        codec: insitu_proto::convert::codec_to_pb(g.codec) as i32,
        tf_json: g
            .tf
            .as_ref()
            .and_then(|(tf, _)| serde_json::to_string(tf).ok()),
        tf_name: g.tf.as_ref().map(|(_, n)| n.clone()),
        camera: g.camera.as_ref().map(insitu_proto::convert::camera_to_pb),
        view_angles_deg: g.view_angles_deg.clone(),
        reference_every: u32::try_from(g.reference_every).ok(),
        reference_size: Some(g.reference_size),
        field: Some(g.field.clone().unwrap_or_default()),
        scene_version: Some(g.scene_version),
    }
}

/// Applies a pushed config to `g`; nothing changes unless all of it is valid.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the field.
pub fn apply_config(g: &Generation, c: &pb::GenerationConfig) -> Result<Generation, Status> {
    let bad =
        |field: &str, e: &dyn std::fmt::Display| Status::invalid_argument(format!("{field}: {e}"));
    let mut next = g.clone();
    // An operator's P_M is not a tuner's decision, and applies from the next step; an
    // operator's scene is not a steered one (a node's own record of its run says which).
    next.pm_version = 0;
    next.scene_version = c.scene_version.unwrap_or(0);
    next.previous = None;
    next.params = VdiParams {
        resolution: c.resolution,
        gamma: c.gamma,
    };
    next.params
        .validate()
        .map_err(|e| bad("resolution/gamma", &e))?;
    next.raycast = RaycastParams {
        step: c.step.unwrap_or(g.raycast.step),
        termination: c.termination.unwrap_or(g.raycast.termination),
        ..g.raycast
    };
    next.raycast
        .validate()
        .map_err(|e| bad("step/termination", &e))?;
    if let Some(codec) = codec_from_pb(c.codec)? {
        next.codec = codec;
    }
    if let Some(json) = &c.tf_json {
        if json.len() > MAX_TF_JSON {
            return Err(bad(
                "tf_json",
                &format!("{} bytes exceeds {MAX_TF_JSON}", json.len()),
            ));
        }
        let name = c.tf_name.clone().unwrap_or_else(|| "pushed".into());
        let tf = TransferFunction::from_json(json, &name).map_err(|e| bad("tf_json", &e))?;
        next.tf = Some((tf, name));
    }
    if let Some(cam) = &c.camera {
        next.camera = Some(camera_from_pb(cam)?);
    }
    if !c.view_angles_deg.is_empty() {
        if c.view_angles_deg.iter().any(|a| !a.is_finite()) {
            return Err(bad("view_angles_deg", &"angles must be finite"));
        }
        next.view_angles_deg = c.view_angles_deg.clone();
    }
    if let Some(k) = c.reference_every {
        next.reference_every = u64::from(k);
    }
    if let Some(s) = c.reference_size {
        if s > insitu_core::vdi::MAX_RESOLUTION {
            return Err(bad("reference_size", &format!("{s} is too large")));
        }
        next.reference_size = s;
    }
    if let Some(f) = &c.field {
        next.field = if f.is_empty() {
            None
        } else {
            crate::ingest::check_field_name(f).map_err(|e| bad("field", &e))?;
            Some(f.clone())
        };
    }
    Ok(next)
}
