//! The generation settings as they travel: a `GenerationConfig` pushed by an operator or
//! recorded in the spool, read into [`Generation`] (all or nothing) and written back.

use crate::config::Generation;
use insitu_core::raycast::{RaycastParams, Shading};
use insitu_core::vdi::codec::Codec;
use insitu_core::{Camera, NamedTf, Precision, VdiParams};
use insitu_proto::convert::{tf_field, wire_enum};
use insitu_proto::pb;
use tonic::Status;

/// The settings as a `GenerationConfig` (what [`apply_config`] reads back).
pub fn to_pb(g: &Generation) -> pb::GenerationConfig {
    pb::GenerationConfig {
        resolution: g.params.resolution,
        gamma: g.params.gamma,
        sample_distance: Some(g.raycast.sample_distance),
        termination: Some(g.raycast.termination),
        codec: pb::Codec::from(g.codec) as i32,
        precision_bits: Some(g.params.precision.bits()),
        tf: g.tf.as_ref().map(|t| pb::TransferFunction::from(&t.tf)),
        legacy_tf_json: None,
        tf_name: g.tf.as_ref().map(|t| t.name.clone()),
        camera: g.camera.as_ref().map(pb::Camera::from),
        view_angles_deg: g.view_angles_deg.clone(),
        reference_every: u32::try_from(g.reference_every).ok(),
        reference_size: Some(g.reference_size),
        field: Some(g.field.clone().unwrap_or_default()),
        scene_version: Some(g.scene_version),
        shading: Some(g.raycast.shading.is_some()),
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
    let precision = match c.precision_bits {
        Some(bits) => Precision::from_bits(bits).map_err(|e| bad("precision_bits", &e))?,
        None => g.params.precision,
    };
    next.params = VdiParams {
        resolution: c.resolution,
        gamma: c.gamma,
        precision,
    };
    next.params
        .validate()
        .map_err(|e| bad("resolution/gamma", &e))?;
    next.raycast = RaycastParams {
        sample_distance: c.sample_distance.unwrap_or(g.raycast.sample_distance),
        termination: c.termination.unwrap_or(g.raycast.termination),
        shading: shading(c.shading, g.raycast.shading),
        ..g.raycast
    };
    next.raycast
        .validate()
        .map_err(|e| bad("sample_distance/termination", &e))?;
    if let Some(codec) = Option::<Codec>::from(wire_enum::<pb::Codec>(c.codec, "codec")?) {
        next.codec = codec;
    }
    if let Some(tf) =
        tf_field(c.tf.as_ref(), c.legacy_tf_json.as_deref()).map_err(Status::invalid_argument)?
    {
        let name = c.tf_name.clone().unwrap_or_else(|| "pushed".into());
        next.tf = Some(NamedTf::new(tf, name));
    }
    if let Some(cam) = &c.camera {
        next.camera = Some(Camera::try_from(cam)?);
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

/// The settings after a tuner's decision `d`, given the first step no rank of which the node
/// has begun (`begun`): `P_M` and version from `d`, and the steered scene it carries when its
/// version differs from `g`'s (its parts replace `g`'s; the rest stay). They apply from
/// `d.from_step` or `begun`, whichever is later; the settings before stay for the steps
/// before (`Generation::previous`), unless an earlier decision is not in force yet, whose
/// settings-before then stay until this one.
///
/// # Errors
/// A message naming the problem: not newer than the version applied, a bad `P_M`, or a
/// scene whose transfer function, field name or camera is bad; `g` is left as it was.
pub fn decided(g: &Generation, d: &pb::PmDecision, begun: u64) -> Result<Generation, String> {
    if d.pm_version <= g.pm_version {
        return Err(format!(
            "decision version {} is not newer than the applied version {}",
            d.pm_version, g.pm_version
        ));
    }
    // A decision without a precision leaves the node's.
    let precision = match d.precision_bits {
        Some(bits) => Precision::from_bits(bits)
            .map_err(|e| format!("decision version {}: {e}", d.pm_version))?,
        None => g.params.precision,
    };
    let params = VdiParams {
        resolution: d.resolution,
        gamma: d.gamma,
        precision,
    };
    params
        .validate()
        .map_err(|e| format!("decision version {}: {e}", d.pm_version))?;
    let mut next = match d.scene.as_ref().filter(|s| s.version != g.scene_version) {
        Some(s) => steered(g, s).map_err(|e| format!("decision version {}: {e}", d.pm_version))?,
        None => g.clone(),
    };
    switch_at(g, &mut next, d.from_step.max(begun), begun);
    next.params = params;
    next.pm_version = d.pm_version;
    Ok(next)
}

/// Makes `next` the settings from `from_step` on, `g` (the settings now) those of the steps
/// before it, with `begun` the first step no rank of which has begun: every rank of a step
/// keeps the settings its first rank was made with.
pub fn switch_at(g: &Generation, next: &mut Generation, from_step: u64, begun: u64) {
    if g.previous.is_some() && begun < g.from_step {
        // An earlier change not yet in force: the settings before it stay until this one.
        next.from_step = g.from_step.max(from_step);
    } else {
        let mut before = g.clone();
        before.previous = None;
        next.previous = Some(Box::new(before));
        next.from_step = from_step;
    }
}

/// `g` under the steered scene `s`.
///
/// # Errors
/// A transfer function that does not parse, a bad field name or a degenerate camera, named.
fn steered(g: &Generation, s: &pb::Scene) -> Result<Generation, String> {
    let mut next = g.clone();
    next.scene_version = s.version;
    if let Some(tf) = tf_field(s.tf.as_ref(), s.legacy_tf_json.as_deref())
        .map_err(|e| format!("scene {}: {e}", s.version))?
    {
        let name = s.tf_name.clone().unwrap_or_else(|| "steered".into());
        next.tf = Some(NamedTf::new(tf, name));
    }
    if let Some(f) = &s.field {
        crate::ingest::check_field_name(f)
            .map_err(|e| format!("scene {}: field: {e}", s.version))?;
        next.field = Some(f.clone());
    }
    if let Some(c) = &s.camera {
        next.camera = Some(
            Camera::try_from(c)
                .map_err(|e| format!("scene {}: camera: {}", s.version, e.message()))?,
        );
    }
    next.raycast = RaycastParams {
        sample_distance: s.sample_distance.unwrap_or(g.raycast.sample_distance),
        shading: shading(s.shading, g.raycast.shading),
        ..g.raycast
    };
    next.raycast
        .validate()
        .map_err(|e| format!("scene {}: sample distance: {e}", s.version))?;
    Ok(next)
}

/// Shading as asked (`Some(on)`), else as it was.
fn shading(asked: Option<bool>, was: Option<Shading>) -> Option<Shading> {
    match asked {
        Some(true) => Some(was.unwrap_or_default()),
        Some(false) => None,
        None => was,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::GenerationConfig;
    use insitu_core::{NamedTf, TransferFunction};

    const TF: &str = r#"{"domain":[0,1],"points":[[0,0,0,0,0],[1,1,0.5,0,0.8]]}"#;

    fn configured() -> Generation {
        let mut g = GenerationConfig {
            field: Some("u".into()),
            ..Default::default()
        }
        .resolve()
        .unwrap();
        g.tf = Some(NamedTf::new(
            TransferFunction::from_json(TF, "own").unwrap(),
            "own",
        ));
        g
    }

    fn decision(version: u64, from_step: u64, scene: Option<pb::Scene>) -> pb::PmDecision {
        pb::PmDecision {
            pm_version: version,
            resolution: 128,
            gamma: 0.02,
            from_step,
            scene,
            ..Default::default()
        }
    }

    fn scene(version: u64, field: &str) -> pb::Scene {
        pb::Scene {
            version,
            tf: Some(pb::TransferFunction::from(
                &TransferFunction::from_json(&TF.replace("0.8]", "0.2]"), "steered").unwrap(),
            )),
            tf_name: Some("steered".into()),
            field: Some(field.into()),
            ..Default::default()
        }
    }

    #[test]
    fn a_steered_scene_applies_from_its_step_and_the_steps_before_keep_the_old_one() {
        let g = configured();
        let next = decided(&g, &decision(1, 10, Some(scene(1, "v"))), 4).unwrap();
        let before = next.clone().for_step(9);
        let after = next.clone().for_step(10);
        assert_eq!((before.scene_version, before.pm_version), (0, 0));
        assert_eq!(before.field.as_deref(), Some("u"));
        assert_eq!(before.tf.as_ref().unwrap().name, "own");
        assert_eq!((after.scene_version, after.pm_version), (1, 1));
        assert_eq!(after.field.as_deref(), Some("v"));
        assert_eq!(after.tf.as_ref().unwrap().name, "steered");
        assert_eq!(
            after.camera, g.camera,
            "a part not steered stays the node's own"
        );
        assert_eq!(next.field_for(9), Some("u"));
        assert_eq!(next.field_for(10), Some("v"));
        // A step begun already: from the first one not begun.
        let late = decided(&g, &decision(1, 10, Some(scene(1, "v"))), 12).unwrap();
        assert_eq!(late.from_step, 12);
        // The same scene again (a P_M correction, or a restarted node's record): P_M only.
        let corrected = decided(&after, &decision(2, 20, Some(scene(1, "u"))), 15).unwrap();
        assert_eq!(
            corrected.field.as_deref(),
            Some("v"),
            "scene 1 is in force already"
        );
        assert_eq!(corrected.params.resolution, 128);
    }

    #[test]
    fn a_step_that_holds_the_old_field_is_made_with_the_scene_it_was_received_under() {
        let next = decided(&configured(), &decision(1, 10, Some(scene(1, "v"))), 4).unwrap();
        let held_old = next.clone().for_step_holding(11, Some("u"));
        assert_eq!(
            (held_old.scene_version, held_old.field.as_deref()),
            (0, Some("u"))
        );
        let held_new = next.clone().for_step_holding(11, Some("v"));
        assert_eq!(held_new.scene_version, 1);
        // Unnamed or unknown (read back from the spool): the scene in force for the step.
        assert_eq!(next.for_step_holding(11, None).scene_version, 1);
    }

    #[test]
    fn a_steered_sample_distance_and_shading_apply_from_the_switch_and_survive_the_spool() {
        let g = configured();
        assert!(
            g.raycast.shading.is_none(),
            "emission–absorption by default"
        );
        let mut s = scene(1, "u");
        s.sample_distance = Some(0.25);
        s.shading = Some(true);
        let next = decided(&g, &decision(1, 10, Some(s)), 0).unwrap();
        let before = next.clone().for_step(9);
        let after = next.clone().for_step(10);
        assert_eq!(before.raycast, g.raycast);
        assert_eq!(after.raycast.sample_distance, 0.25);
        assert!(after.raycast.shading.is_some());
        assert_eq!(after.raycast.termination, g.raycast.termination);
        let back = apply_config(&configured(), &to_pb(&after)).unwrap();
        assert_eq!(back.raycast, after.raycast);
        // Shading off again; the step kept.
        let mut off = scene(2, "u");
        off.shading = Some(false);
        let later = decided(&after, &decision(2, 20, Some(off)), 0)
            .unwrap()
            .for_step(20);
        assert!(later.raycast.shading.is_none());
        assert_eq!(later.raycast.sample_distance, 0.25);
        let mut bad = scene(3, "u");
        bad.sample_distance = Some(-1.0);
        let e = decided(&later, &decision(3, 30, Some(bad)), 0).unwrap_err();
        assert!(e.contains("scene 3: sample distance"), "{e}");
    }

    #[test]
    fn a_bad_scene_is_refused_and_nothing_changes() {
        let g = configured();
        let mut bad = scene(1, "v");
        bad.tf.as_mut().unwrap().points[1].x = -1.0;
        let e = decided(&g, &decision(1, 0, Some(bad)), 0).unwrap_err();
        assert!(
            e.contains("scene 1: tf: transfer function on the wire"),
            "{e}"
        );
        // JSON text from an older tuner is refused by name, not ignored.
        let mut old = scene(1, "v");
        old.tf = None;
        old.legacy_tf_json = Some(TF.into());
        let e = decided(&g, &decision(1, 0, Some(old)), 0).unwrap_err();
        assert!(
            e.contains("scene 1: tf_json") && e.contains("send `tf`"),
            "{e}"
        );
        let mut pushed = to_pb(&g);
        pushed.legacy_tf_json = Some(TF.into());
        let e = apply_config(&g, &pushed).unwrap_err();
        assert!(e.message().contains("no longer taken"), "{}", e.message());
        let e = decided(&g, &decision(1, 0, Some(scene(1, "a\nb"))), 0).unwrap_err();
        assert!(e.contains("scene 1: field"), "{e}");
        let old = decided(&g, &decision(3, 0, None), 0).unwrap();
        let e = decided(&old, &decision(3, 0, None), 0).unwrap_err();
        assert!(e.contains("not newer"), "{e}");
    }

    #[test]
    fn the_scene_version_survives_the_spool_s_record() {
        let next = decided(&configured(), &decision(1, 0, Some(scene(1, "v"))), 0)
            .unwrap()
            .for_step(0);
        let back = apply_config(&configured(), &to_pb(&next)).unwrap();
        assert_eq!(back.scene_version, 1);
        assert_eq!(back.field.as_deref(), Some("v"));
        assert_eq!(back.tf.as_ref().unwrap().name, "steered");
        // An operator's config carries none: the configured scene.
        let mut operator = to_pb(&next);
        operator.scene_version = None;
        assert_eq!(apply_config(&next, &operator).unwrap().scene_version, 0);
    }

    /// A decision's precision applies with its r and γ; one without keeps the node's; a bit
    /// count outside 4–16 is refused with the version named, and nothing changes.
    #[test]
    fn a_decision_carries_the_precision_or_keeps_the_nodes() {
        use insitu_core::Precision;
        let g = configured();
        assert_eq!(g.params.precision, Precision::Bits(8), "the default");
        let kept = decided(&g, &decision(1, 0, None), 0).unwrap();
        assert_eq!(kept.params.precision, Precision::Bits(8));
        let mut d = decision(2, 0, None);
        d.precision_bits = Some(6);
        let six = decided(&kept, &d, 0).unwrap();
        assert_eq!(
            (six.params.resolution, six.params.precision),
            (128, Precision::Bits(6))
        );
        d.pm_version = 3;
        d.precision_bits = Some(0);
        assert_eq!(
            decided(&six, &d, 0).unwrap().params.precision,
            Precision::Float32
        );
        d.precision_bits = Some(17);
        let err = decided(&six, &d, 0).unwrap_err();
        assert!(err.contains("version 3") && err.contains("17"), "{err}");
    }
}
