//! Steering (docs/steering.md): what an operator may change while the run goes on — the
//! transfer function, the rendered field, the generation camera (the *scene*) and the
//! tuner's utility — checked here, before anything changes.
//!
//! A scene change is versioned as `P_M` is: the engine gives it the next scene version and
//! pushes it in a decision of its own (the `P_M` in force, `PmDecision.scene`), so it applies
//! from that decision's `from_step` on every node and rank alike, survives restarts of every
//! daemon (the tuner's state keeps it; every later decision carries it), and each stored step
//! names the scene it was made with. The scene is cumulative: a part never steered stays each
//! node's own (its config, or the default the world agreed).

use insitu_core::volume::Aabb;
use insitu_core::{Camera, TransferFunction};
use insitu_proto::convert::tf_field;
use insitu_proto::pb;
use serde::{Deserialize, Deserializer, Serialize};

/// A generation camera as persisted: eye, target and up (world units) and the vertical field
/// of view (degrees).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraSpec {
    /// Eye position.
    pub eye: [f32; 3],
    /// Point looked at.
    pub target: [f32; 3],
    /// Up hint.
    pub up: [f32; 3],
    /// Vertical field of view, degrees.
    pub fov_y_deg: f32,
}

impl CameraSpec {
    fn of(c: &insitu_core::Camera) -> Self {
        Self {
            eye: c.eye.to_array(),
            target: c.target.to_array(),
            up: c.up.to_array(),
            fov_y_deg: c.fov_y_deg,
        }
    }

    fn camera(&self) -> insitu_core::Camera {
        insitu_core::Camera {
            eye: self.eye.into(),
            target: self.target.into(),
            up: self.up.into(),
            fov_y_deg: self.fov_y_deg,
        }
    }
}

/// The steered scene, cumulative over the run (`pb::Scene`): `None` parts are each node's own.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneState {
    /// Version (0: never steered, the configured scene).
    pub version: u64,
    /// Transfer function (a JSON object in the state file; read from `tf_json`, JSON text,
    /// in state files written before it was typed).
    #[serde(default, alias = "tf_json", deserialize_with = "tf_or_text")]
    pub tf: Option<TransferFunction>,
    /// Its name in VDI metadata.
    pub tf_name: Option<String>,
    /// The field rendered, by name.
    pub field: Option<String>,
    /// The generation camera.
    pub camera: Option<CameraSpec>,
    /// The ray-casting sample distance, world units (read as `step` too, the key of older
    /// state files).
    #[serde(default, alias = "step")]
    pub sample_distance: Option<f32>,
    /// Gradient shading on.
    #[serde(default)]
    pub shading: Option<bool>,
}

impl SceneState {
    /// As carried by decisions and the status.
    pub fn to_pb(&self) -> pb::Scene {
        pb::Scene {
            version: self.version,
            tf: self.tf.as_ref().map(pb::TransferFunction::from),
            legacy_tf_json: None,
            tf_name: self.tf_name.clone(),
            field: self.field.clone(),
            camera: self.camera.as_ref().map(|c| pb::Camera::from(&c.camera())),
            sample_distance: self.sample_distance,
            shading: self.shading,
        }
    }
}

/// A persisted transfer function: a JSON object, or the JSON text of older state files; either
/// checked as a file's is.
fn tf_or_text<'de, D: Deserializer<'de>>(d: D) -> Result<Option<TransferFunction>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Persisted {
        Object(TransferFunction),
        Text(String),
    }
    let tf = match Option::<Persisted>::deserialize(d)? {
        None => return Ok(None),
        Some(Persisted::Object(tf)) => tf,
        Some(Persisted::Text(json)) => {
            TransferFunction::from_json(&json, "tf_json").map_err(serde::de::Error::custom)?
        }
    };
    tf.validate("tf").map_err(serde::de::Error::custom)?;
    Ok(Some(tf))
}

/// Where a steering change stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Standing {
    /// Decided; no step made with it yet.
    Pending,
    /// A production step was made with it (a utility change: in force at once).
    Applied,
    /// A later change came before any step was made with it: never applied.
    Superseded,
}

impl Standing {
    fn word(self) -> &'static str {
        match self {
            Self::Pending => "pending",
            Self::Applied => "applied",
            Self::Superseded => "superseded",
        }
    }
}

/// One steering change, as recorded in the tuner's state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SteerRecord {
    /// The scene version it made (0: a utility change).
    pub scene_version: u64,
    /// The decision that carried it (0: a utility change).
    pub pm_version: u64,
    /// The first step made with it (0: a utility change).
    pub from_step: u64,
    /// Where it stands.
    pub standing: Standing,
    /// What changed, in words.
    pub change: String,
    /// Who asked.
    pub who: String,
    /// When, seconds since the Unix epoch.
    pub at_unix_secs: f64,
}

impl SteerRecord {
    /// As in the status.
    pub fn to_pb(&self) -> pb::SteeringRecord {
        pb::SteeringRecord {
            scene_version: self.scene_version,
            pm_version: self.pm_version,
            from_step: self.from_step,
            state: self.standing.word().into(),
            change: self.change.clone(),
            who: self.who.clone(),
            at_unix_secs: self.at_unix_secs,
        }
    }
}

/// What the newest summarised step says about the domain: its named fields and its box
/// (what a steered field and camera are checked against).
#[derive(Clone, Debug, Default)]
pub struct Domain {
    /// Whether a step was seen at all.
    pub seen: bool,
    /// The step's named fields (empty: one unnamed field).
    pub fields: Vec<String>,
    /// The whole domain's box, when the nodes report it.
    pub bounds: Option<Aabb>,
    /// Ranks of the newest step (what a preview waits for).
    pub world_size: u32,
    /// The newest step whose ranks were all summarised (what the viewer's editor draws
    /// under the curve).
    pub histogram: Option<StepHistogram>,
}

/// One step's bin counts, summed over its ranks, and the value range they cover (the
/// transfer function's domain it was made with).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StepHistogram {
    /// Step index.
    pub step: u64,
    /// Counts per equal-width bin.
    pub counts: Vec<u64>,
    /// The range's ends.
    pub lo: f64,
    /// Upper end.
    pub hi: f64,
}

impl Domain {
    /// Learns from a step summary.
    pub fn saw(&mut self, s: &pb::StepSummary) {
        self.seen = true;
        self.world_size = s.world_size.max(1);
        self.fields.clone_from(&s.fields);
        if let (Some(min), Some(max)) = (
            s.box_min.as_ref().map(glam::Vec3::from),
            s.box_max.as_ref().map(glam::Vec3::from),
        ) {
            if min.is_finite() && max.is_finite() && min.cmple(max).all() {
                self.bounds = Some(Aabb { min, max });
            }
        }
    }
}

/// The most samples a steered sample distance may take along the domain's diagonal (a
/// guard against a typo that would stall every node: 65 536 samples per ray).
pub const MAX_SAMPLES_PER_RAY: f32 = 65_536.0;

/// A checked steering request.
#[derive(Clone, Debug, PartialEq)]
pub struct Change {
    /// The scene after it (version not yet given), when the scene changes.
    pub scene: Option<SceneState>,
    /// The new utility, when it changes.
    pub utility: Option<String>,
    /// What changes, in words (e.g. `transfer function "warm"; field "v"`).
    pub words: String,
}

/// Checks `req` against the scene in force and what the steps say about the domain; nothing
/// changes here. The utility is only checked for presence: the engine resolves it (and
/// refuses it) with the rest of its configuration.
///
/// # Errors
/// A message naming the bad part and why: a transfer function that breaks a rule or has
/// more than [`insitu_proto::convert::MAX_TF_POINTS`] points (or comes as JSON text from an
/// older peer), a field the steps do not carry (or before any step named its fields), a
/// degenerate camera or one whose eye lies inside the domain's box, a sample distance not
/// finite and > 0, longer than the domain's diagonal or taking more than
/// [`MAX_SAMPLES_PER_RAY`] along it, an empty utility, or a request that changes nothing.
pub fn check(
    req: &pb::SteerRequest,
    scene: &SceneState,
    domain: &Domain,
) -> Result<Change, String> {
    let mut next = scene.clone();
    let mut words = Vec::new();
    if let Some(tf) = tf_field(req.tf.as_ref(), req.legacy_tf_json.as_deref())? {
        let name = req
            .tf_name
            .clone()
            .filter(|n| !n.trim().is_empty())
            .unwrap_or_else(|| "steered".into());
        words.push(format!("transfer function \"{name}\""));
        next.tf = Some(tf);
        next.tf_name = Some(name);
    } else if req.tf_name.is_some() {
        return Err("tf_name without tf: name the transfer function you send".into());
    }
    if let Some(field) = &req.field {
        check_field(field, domain)?;
        words.push(format!("field \"{field}\""));
        next.field = Some(field.clone());
    }
    if let Some(c) = &req.camera {
        let cam = Camera::try_from(c).map_err(|e| e.message().to_owned())?;
        if let Some(b) = domain.bounds {
            if cam.eye.cmpge(b.min).all() && cam.eye.cmple(b.max).all() {
                return Err(format!(
                    "camera: the eye {:?} lies inside the domain's box {:?}–{:?}; a generation camera sees the domain from outside",
                    cam.eye.to_array(),
                    b.min.to_array(),
                    b.max.to_array()
                ));
            }
        }
        words.push(format!(
            "generation camera at {:?} looking at {:?}",
            cam.eye.to_array(),
            cam.target.to_array()
        ));
        next.camera = Some(CameraSpec::of(&cam));
    }
    if let Some(d) = req.sample_distance {
        if !(d.is_finite() && d > 0.0) {
            return Err(format!("sample_distance: {d} is not a finite length > 0"));
        }
        if let Some(b) = domain.bounds {
            let diagonal = (b.max - b.min).length();
            if d > diagonal {
                return Err(format!(
                    "sample_distance: {d} is longer than the domain's diagonal {diagonal}; rays would take at most one sample"
                ));
            }
            if d * MAX_SAMPLES_PER_RAY < diagonal {
                return Err(format!(
                    "sample_distance: {d} would take more than {MAX_SAMPLES_PER_RAY} samples along the domain's diagonal {diagonal}"
                ));
            }
        }
        words.push(format!("sample distance {d}"));
        next.sample_distance = Some(d);
    }
    if let Some(on) = req.shading {
        words.push(format!("shading {}", if on { "on" } else { "off" }));
        next.shading = Some(on);
    }
    let utility = match &req.utility {
        Some(u) if u.trim().is_empty() => return Err("utility: empty".into()),
        Some(u) => {
            words.push(format!("utility {u}"));
            Some(u.trim().to_owned())
        }
        None => None,
    };
    if words.is_empty() {
        return Err(
            "nothing to change: give a transfer function, a field, a camera, a sample distance, shading or a utility".into(),
        );
    }
    let scene_changes = next != *scene;
    Ok(Change {
        scene: scene_changes.then_some(next),
        utility,
        words: words.join("; "),
    })
}

fn check_field(field: &str, domain: &Domain) -> Result<(), String> {
    if !domain.seen {
        return Err(format!(
            "field \"{field}\": no step has been made yet, so the steps' fields are not known"
        ));
    }
    if domain.fields.is_empty() {
        return Err(format!(
            "field \"{field}\": the steps carry one unnamed field, there is none to choose"
        ));
    }
    if !domain.fields.iter().any(|f| f == field) {
        return Err(format!(
            "field \"{field}\" is not one of the steps' fields ({})",
            domain.fields.join(", ")
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    const TF: &str = r#"{"domain":[0,1],"points":[[0,0,0,0,0],[1,1,0.5,0,0.8]]}"#;

    fn wire_tf() -> pb::TransferFunction {
        pb::TransferFunction::from(&TransferFunction::from_json(TF, "t").unwrap())
    }

    fn domain() -> Domain {
        Domain {
            seen: true,
            fields: vec!["u".into(), "v".into()],
            bounds: Some(Aabb {
                min: Vec3::ZERO,
                max: Vec3::splat(10.0),
            }),
            world_size: 1,
            histogram: None,
        }
    }

    fn camera(eye: [f32; 3]) -> pb::Camera {
        let v = |a: [f32; 3]| {
            Some(pb::Vec3 {
                x: a[0],
                y: a[1],
                z: a[2],
            })
        };
        pb::Camera {
            eye: v(eye),
            target: v([5.0, 5.0, 5.0]),
            up: v([0.0, 1.0, 0.0]),
            fov_y_deg: 30.0,
        }
    }

    /// The state file keeps the transfer function as a JSON object and reads it back
    /// equal; a state file written when it was JSON text (`tf_json`) reads the same; a broken
    /// one is refused, not taken.
    #[test]
    fn the_persisted_transfer_function_reads_back_from_either_form() {
        let tf = TransferFunction::from_json(TF, "t").unwrap();
        let scene = SceneState {
            version: 2,
            tf: Some(tf.clone()),
            tf_name: Some("warm".into()),
            ..Default::default()
        };
        let text = serde_json::to_string(&scene).unwrap();
        assert!(text.contains(r#""tf":{"domain""#), "{text}");
        assert_eq!(serde_json::from_str::<SceneState>(&text).unwrap(), scene);
        let old = format!(
            r#"{{"version":2,"tf_json":{},"tf_name":"warm"}}"#,
            serde_json::to_string(TF).unwrap()
        );
        assert_eq!(serde_json::from_str::<SceneState>(&old).unwrap(), scene);
        let broken = r#"{"version":2,"tf":{"domain":[1,0],"points":[[0,0,0,0,0]]}}"#;
        let e = serde_json::from_str::<SceneState>(broken)
            .unwrap_err()
            .to_string();
        assert!(e.contains("domain"), "{e}");
        let none = serde_json::from_str::<SceneState>(r#"{"version":0}"#).unwrap();
        assert_eq!(none.tf, None);
    }

    #[test]
    fn each_part_changes_the_scene_it_names_and_keeps_the_rest() {
        let mut scene = SceneState {
            version: 3,
            field: Some("u".into()),
            ..SceneState::default()
        };
        let c = check(
            &pb::SteerRequest {
                tf: Some(wire_tf()),
                tf_name: Some("warm".into()),
                camera: Some(camera([5.0, 5.0, 40.0])),
                ..Default::default()
            },
            &scene,
            &domain(),
        )
        .unwrap();
        let next = c.scene.unwrap();
        assert_eq!(next.tf, Some(TransferFunction::from_json(TF, "t").unwrap()));
        assert_eq!(next.tf_name.as_deref(), Some("warm"));
        assert_eq!(next.field.as_deref(), Some("u"), "the field stays");
        assert_eq!(next.camera.unwrap().eye, [5.0, 5.0, 40.0]);
        assert_eq!(next.version, 3, "the engine gives the version");
        assert!(c.words.contains("\"warm\"") && c.words.contains("camera"));
        assert_eq!(c.utility, None);
        // The same field again changes nothing in the scene: a utility-only change is not a
        // scene change.
        scene.field = Some("v".into());
        let c = check(
            &pb::SteerRequest {
                field: Some("v".into()),
                utility: Some("size:1MB".into()),
                ..Default::default()
            },
            &scene,
            &domain(),
        )
        .unwrap();
        assert_eq!(c.scene, None);
        assert_eq!(c.utility.as_deref(), Some("size:1MB"));
    }

    #[test]
    fn sample_distance_and_shading_are_scene_parts() {
        let scene = SceneState {
            version: 2,
            shading: Some(false),
            ..SceneState::default()
        };
        let c = check(
            &pb::SteerRequest {
                sample_distance: Some(0.25),
                shading: Some(true),
                ..Default::default()
            },
            &scene,
            &domain(),
        )
        .unwrap();
        let next = c.scene.unwrap();
        assert_eq!(
            (next.sample_distance, next.shading),
            (Some(0.25), Some(true))
        );
        assert_eq!(c.words, "sample distance 0.25; shading on");
        let pb = next.to_pb();
        assert_eq!((pb.sample_distance, pb.shading), (Some(0.25), Some(true)));
        // Shading off again when it is off is no scene change.
        let c = check(
            &pb::SteerRequest {
                shading: Some(false),
                ..Default::default()
            },
            &scene,
            &domain(),
        )
        .unwrap();
        assert_eq!(c.scene, None);
    }

    #[test]
    fn bad_parts_are_refused_with_their_name() {
        let scene = SceneState::default();
        let refused = |req: pb::SteerRequest, d: &Domain| check(&req, &scene, d).unwrap_err();
        let d = domain();
        let e = refused(
            pb::SteerRequest {
                tf: Some(pb::TransferFunction::default()),
                ..Default::default()
            },
            &d,
        );
        assert!(e.starts_with("tf: transfer function on the wire"), "{e}");
        let e = refused(
            pb::SteerRequest {
                field: Some("w".into()),
                ..Default::default()
            },
            &d,
        );
        assert!(
            e.contains("\"w\" is not one of the steps' fields (u, v)"),
            "{e}"
        );
        let e = refused(
            pb::SteerRequest {
                field: Some("u".into()),
                ..Default::default()
            },
            &Domain::default(),
        );
        assert!(e.contains("no step has been made yet"), "{e}");
        let one = Domain {
            fields: Vec::new(),
            ..domain()
        };
        let e = refused(
            pb::SteerRequest {
                field: Some("u".into()),
                ..Default::default()
            },
            &one,
        );
        assert!(e.contains("one unnamed field"), "{e}");
        let e = refused(
            pb::SteerRequest {
                camera: Some(camera([5.0, 5.0, 9.0])),
                ..Default::default()
            },
            &d,
        );
        assert!(e.contains("inside the domain's box"), "{e}");
        let e = refused(
            pb::SteerRequest {
                camera: Some(camera([f32::NAN, 5.0, 40.0])),
                ..Default::default()
            },
            &d,
        );
        assert!(e.contains("degenerate"), "{e}");
        let e = refused(
            pb::SteerRequest {
                tf_name: Some("x".into()),
                ..Default::default()
            },
            &d,
        );
        assert!(e.contains("tf_name without tf"), "{e}");
        let e = refused(pb::SteerRequest::default(), &d);
        assert!(e.starts_with("nothing to change"), "{e}");
        // The box's diagonal is 10·√3 ≈ 17.3.
        for (step, why) in [
            (0.0, "not a finite length > 0"),
            (-1.0, "not a finite length > 0"),
            (f32::NAN, "not a finite length > 0"),
            (f32::INFINITY, "not a finite length > 0"),
            (18.0, "longer than the domain's diagonal"),
            (1e-4, "more than 65536 samples"),
        ] {
            let e = refused(
                pb::SteerRequest {
                    sample_distance: Some(step),
                    ..Default::default()
                },
                &d,
            );
            assert!(
                e.starts_with("sample_distance:") && e.contains(why),
                "{step}: {e}"
            );
        }
        let e = refused(
            pb::SteerRequest {
                utility: Some("  ".into()),
                ..Default::default()
            },
            &d,
        );
        assert_eq!(e, "utility: empty");
    }

    #[test]
    fn a_camera_on_the_box_s_surface_is_inside_and_one_just_outside_is_not() {
        let scene = SceneState::default();
        let req = |eye| pb::SteerRequest {
            camera: Some(camera(eye)),
            ..Default::default()
        };
        assert!(check(&req([10.0, 5.0, 5.0]), &scene, &domain()).is_err());
        assert!(check(&req([10.001, 5.0, 5.0]), &scene, &domain()).is_ok());
        // Without a box reported (older nodes), only the camera's own validity is checked.
        let no_box = Domain {
            bounds: None,
            ..domain()
        };
        assert!(check(&req([5.0, 5.0, 9.0]), &scene, &no_box).is_ok());
    }
}
