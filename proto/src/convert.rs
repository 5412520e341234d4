//! Wire messages ↔ `insitu-core` types. Every conversion from the wire validates and says what
//! was wrong, as a gRPC status the caller can return as is.

use crate::pb;
use glam::Vec3;
use insitu_core::backend::TimeSource;
use insitu_core::compose::{frame_from_le_bytes, frame_to_le_bytes};
use insitu_core::tf::TfError;
use insitu_core::vdi::codec::Codec;
use insitu_core::volume::{Aabb, ScalarType};
use insitu_core::{Camera, Image, TransferFunction};
use tonic::Status;

/// The largest preview side, pixels (a brick's window of f32 RGBA stays within a gRPC message
/// once compressed).
pub const PREVIEW_MAX_SIZE: u32 = 512;

/// The preview side when a request leaves it unset (0), pixels.
pub const PREVIEW_DEFAULT_SIZE: u32 = 256;

/// A preview's side from `PreviewRequest.size`: 0 → [`PREVIEW_DEFAULT_SIZE`].
///
/// # Errors
/// A message naming a side outside 16..=[`PREVIEW_MAX_SIZE`].
pub fn preview_size(size: u32) -> Result<u32, String> {
    match size {
        0 => Ok(PREVIEW_DEFAULT_SIZE),
        s if (16..=PREVIEW_MAX_SIZE).contains(&s) => Ok(s),
        s => Err(format!("size {s} is not in 16..={PREVIEW_MAX_SIZE}")),
    }
}

/// A brick's window of a preview frame on the wire (`origin`, colour and opacity, as
/// [`insitu_core::compose::frame_window`] cuts it): its RGBA as little-endian f32
/// ([`frame_to_le_bytes`]), zstd-compressed, with the brick's world box and the camera it was
/// rendered from. Ids, step, rank and timing are the caller's to set.
///
/// # Errors
/// A message when the window does not compress.
pub fn preview_frame_to_pb(
    (origin, image, opacity): &([u32; 2], Image, Vec<f32>),
    world_box: Aabb,
    camera: &Camera,
) -> Result<pb::PreviewFrame, String> {
    let raw: Vec<u8> = frame_to_le_bytes(image, opacity).collect();
    let rgba_zstd =
        zstd::bulk::compress(&raw, 1).map_err(|e| format!("the frame did not compress: {e}"))?;
    Ok(pb::PreviewFrame {
        box_min: Some(world_box.min.into()),
        box_max: Some(world_box.max.into()),
        origin_x: origin[0],
        origin_y: origin[1],
        width: image.width(),
        height: image.height(),
        rgba_zstd: rgba_zstd.into(),
        camera: Some(camera.into()),
        ..Default::default()
    })
}

/// A preview frame's window back from the wire: `(origin, image, opacity, world box)`, read
/// only up to `size × size` pixels.
///
/// # Errors
/// A message naming the rank whose frame does not decompress, does not hold its window's
/// pixels, or lacks its box.
pub fn preview_window_from_pb(
    f: &pb::PreviewFrame,
    size: u32,
) -> Result<([u32; 2], Image, Vec<f32>, Aabb), String> {
    let rank = f.rank;
    let limit = size as usize * size as usize * 16;
    let raw = zstd::bulk::decompress(&f.rgba_zstd, limit)
        .map_err(|e| format!("rank {rank}: the frame does not decompress: {e}"))?;
    let (image, opacity) = frame_from_le_bytes(&raw, (f.width, f.height)).ok_or_else(|| {
        format!(
            "rank {rank}: {} bytes are not a {}×{} window",
            raw.len(),
            f.width,
            f.height
        )
    })?;
    let (Some(min), Some(max)) = (
        f.box_min.as_ref().map(Vec3::from),
        f.box_max.as_ref().map(Vec3::from),
    ) else {
        return Err(format!("rank {rank}: no box"));
    };
    Ok(([f.origin_x, f.origin_y], image, opacity, Aabb { min, max }))
}

/// Grid dims or a voxel offset, `[x, y, z]`, on the wire (each < 2³², as every grid the
/// nodes accept).
impl From<[usize; 3]> for pb::Dims3 {
    fn from(d: [usize; 3]) -> Self {
        Self {
            x: d[0] as u32,
            y: d[1] as u32,
            z: d[2] as u32,
        }
    }
}

/// Dims or an offset from the wire, unchecked (what a field means and which values it may
/// take is for its reader to check).
impl From<&pb::Dims3> for [usize; 3] {
    fn from(d: &pb::Dims3) -> Self {
        [d.x, d.y, d.z].map(|x| x as usize)
    }
}

/// A world-space vector.
impl From<Vec3> for pb::Vec3 {
    fn from(v: Vec3) -> Self {
        Self {
            x: v.x,
            y: v.y,
            z: v.z,
        }
    }
}

/// A world-space vector from the wire.
impl From<&pb::Vec3> for Vec3 {
    fn from(v: &pb::Vec3) -> Self {
        Vec3::new(v.x, v.y, v.z)
    }
}

/// A camera for the wire.
impl From<&Camera> for pb::Camera {
    fn from(c: &Camera) -> Self {
        Self {
            eye: Some(c.eye.into()),
            target: Some(c.target.into()),
            up: Some(c.up.into()),
            fov_y_deg: c.fov_y_deg,
        }
    }
}

/// A camera from the wire.
///
/// # Errors
/// `INVALID_ARGUMENT` when a vector is missing or the camera is degenerate (see
/// [`Camera::is_valid`]).
impl TryFrom<&pb::Camera> for Camera {
    type Error = Status;

    fn try_from(c: &pb::Camera) -> Result<Self, Status> {
        let field = |v: Option<&pb::Vec3>, name: &str| {
            v.map(Vec3::from)
                .ok_or_else(|| Status::invalid_argument(format!("camera.{name} is missing")))
        };
        let cam = Camera {
            eye: field(c.eye.as_ref(), "eye")?,
            target: field(c.target.as_ref(), "target")?,
            up: field(c.up.as_ref(), "up")?,
            fov_y_deg: c.fov_y_deg,
        };
        if cam.is_valid() {
            Ok(cam)
        } else {
            Err(Status::invalid_argument(format!(
                "camera {cam:?} is degenerate (non-finite, eye = target, up parallel to the view, or fov outside (0, 180))"
            )))
        }
    }
}

/// Most control points a transfer function may have on the wire.
pub const MAX_TF_POINTS: usize = 16_384;

/// A transfer function for the wire.
impl From<&TransferFunction> for pb::TransferFunction {
    fn from(tf: &TransferFunction) -> Self {
        Self {
            domain_lo: tf.domain[0],
            domain_hi: tf.domain[1],
            points: tf
                .points
                .iter()
                .map(|&[x, r, g, b, a]| pb::ControlPoint { x, r, g, b, a })
                .collect(),
        }
    }
}

/// A transfer function from the wire, checked as a file's is
/// ([`TransferFunction::validate`]).
///
/// # Errors
/// [`TfError::Invalid`] (named "on the wire") for more than [`MAX_TF_POINTS`] points or a
/// broken rule: an empty point list, a domain that is not finite with lo < hi, x not strictly
/// increasing in [0, 1], a colour or opacity outside [0, 1].
impl TryFrom<&pb::TransferFunction> for TransferFunction {
    type Error = TfError;

    fn try_from(m: &pb::TransferFunction) -> Result<Self, TfError> {
        const SOURCE: &str = "on the wire";
        if m.points.len() > MAX_TF_POINTS {
            return Err(TfError::Invalid {
                source_name: SOURCE.into(),
                problem: format!("{} points, more than {MAX_TF_POINTS}", m.points.len()),
            });
        }
        let tf = TransferFunction {
            domain: [m.domain_lo, m.domain_hi],
            points: m.points.iter().map(|p| [p.x, p.r, p.g, p.b, p.a]).collect(),
        };
        tf.validate(SOURCE)?;
        Ok(tf)
    }
}

/// A message's transfer function: its `tf` field checked ([`TransferFunction::try_from`]),
/// `None` when unset. `legacy` is the message's `legacy_tf_json`, set only by peers older than
/// the typed field: JSON text is refused by name, never ignored.
///
/// # Errors
/// A message starting `tf: ` for a transfer function that breaks a rule, or `tf_json: ` for
/// JSON text.
pub fn tf_field(
    tf: Option<&pb::TransferFunction>,
    legacy: Option<&str>,
) -> Result<Option<TransferFunction>, String> {
    if legacy.is_some_and(|j| !j.is_empty()) {
        return Err("tf_json: a transfer function as JSON text is no longer taken; send `tf` (a TransferFunction message): the sender is older than this node".into());
    }
    tf.map(TransferFunction::try_from)
        .transpose()
        .map_err(|e| format!("tf: {e}"))
}

/// The transfer function a preview asks for ([`tf_field`] of `req`): a preview without one is
/// refused.
///
/// # Errors
/// As [`tf_field`], and `tf: no transfer function to preview` when it is unset.
pub fn preview_tf(req: &pb::PreviewRequest) -> Result<TransferFunction, String> {
    tf_field(req.tf.as_ref(), Some(&req.legacy_tf_json))?
        .ok_or_else(|| "tf: no transfer function to preview".to_owned())
}

/// A wire enum from the `i32` prost stores, `field` naming it in the error.
///
/// # Errors
/// `INVALID_ARGUMENT` for a value the enum does not have.
pub fn wire_enum<E: TryFrom<i32>>(v: i32, field: &str) -> Result<E, Status> {
    E::try_from(v).map_err(|_| Status::invalid_argument(format!("unknown {field} {v}")))
}

/// A codec for the wire.
impl From<Codec> for pb::Codec {
    fn from(c: Codec) -> Self {
        match c {
            Codec::None => pb::Codec::None,
            Codec::Bzip2 => pb::Codec::Bzip2,
            Codec::Zstd => pb::Codec::Zstd,
        }
    }
}

/// A codec from the wire; `None` for "unspecified".
impl From<pb::Codec> for Option<Codec> {
    fn from(c: pb::Codec) -> Self {
        match c {
            pb::Codec::Unspecified => None,
            pb::Codec::None => Some(Codec::None),
            pb::Codec::Bzip2 => Some(Codec::Bzip2),
            pb::Codec::Zstd => Some(Codec::Zstd),
        }
    }
}

/// Where a τ comes from, for the wire.
impl From<TimeSource> for pb::TauSource {
    fn from(t: TimeSource) -> Self {
        match t {
            TimeSource::WallClock => pb::TauSource::WallClock,
            TimeSource::GpuTimestamps => pb::TauSource::GpuTimestamps,
        }
    }
}

/// Where a τ comes from, from the wire; unspecified (a node that does not say) is the wall
/// clock.
impl From<pb::TauSource> for TimeSource {
    fn from(t: pb::TauSource) -> Self {
        match t {
            pb::TauSource::Unspecified | pb::TauSource::WallClock => TimeSource::WallClock,
            pb::TauSource::GpuTimestamps => TimeSource::GpuTimestamps,
        }
    }
}

/// A scalar type for the wire.
impl From<ScalarType> for pb::ScalarType {
    fn from(t: ScalarType) -> Self {
        match t {
            ScalarType::U8 => pb::ScalarType::U8,
            ScalarType::U16 => pb::ScalarType::U16,
            ScalarType::I16 => pb::ScalarType::I16,
            ScalarType::F32 => pb::ScalarType::F32,
            ScalarType::F64 => pb::ScalarType::F64,
        }
    }
}

/// A scalar type from the wire.
///
/// # Errors
/// `INVALID_ARGUMENT` for "unspecified".
impl TryFrom<pb::ScalarType> for ScalarType {
    type Error = Status;

    fn try_from(t: pb::ScalarType) -> Result<Self, Status> {
        match t {
            pb::ScalarType::U8 => Ok(ScalarType::U8),
            pb::ScalarType::U16 => Ok(ScalarType::U16),
            pb::ScalarType::I16 => Ok(ScalarType::I16),
            pb::ScalarType::F32 => Ok(ScalarType::F32),
            pb::ScalarType::F64 => Ok(ScalarType::F64),
            pb::ScalarType::Unspecified => Err(Status::invalid_argument("dtype is unspecified")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects() {
        let cam = Camera {
            eye: Vec3::new(1.0, 2.0, 30.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_deg: 40.0,
        };
        assert_eq!(Camera::try_from(&pb::Camera::from(&cam)).unwrap(), cam);
        let mut bad = pb::Camera::from(&cam);
        bad.target = bad.eye;
        assert_eq!(
            Camera::try_from(&bad).unwrap_err().code(),
            tonic::Code::InvalidArgument
        );
        bad.eye = None;
        assert!(Camera::try_from(&bad)
            .unwrap_err()
            .message()
            .contains("eye"));
        let codec = |v: i32| wire_enum::<pb::Codec>(v, "codec").map(Option::<Codec>::from);
        for c in Codec::ALL {
            assert_eq!(codec(pb::Codec::from(c) as i32).unwrap(), Some(c));
        }
        assert_eq!(codec(0).unwrap(), None);
        assert!(codec(99).unwrap_err().message().contains("codec 99"));
        let dtype = |v: i32| ScalarType::try_from(wire_enum::<pb::ScalarType>(v, "dtype")?);
        for t in [
            ScalarType::U8,
            ScalarType::U16,
            ScalarType::I16,
            ScalarType::F32,
            ScalarType::F64,
        ] {
            assert_eq!(dtype(pb::ScalarType::from(t) as i32).unwrap(), t);
        }
        assert!(dtype(0).is_err());
        assert!(dtype(42).is_err());
        for t in [TimeSource::WallClock, TimeSource::GpuTimestamps] {
            assert_eq!(TimeSource::from(pb::TauSource::from(t)), t);
        }
        assert_eq!(
            <[usize; 3]>::from(&pb::Dims3::from([3, 70_000, 1])),
            [3, 70_000, 1]
        );
    }

    /// A transfer function comes back from the wire bit for bit (its identity hash too), and
    /// one that breaks a rule, or has too many points, is refused naming the rule.
    #[test]
    fn transfer_functions_round_trip_and_bad_ones_are_refused() {
        let tf = TransferFunction {
            domain: [-3.5, 1e30],
            points: vec![
                [0.0, 0.1, 0.2, 0.3, 0.0],
                [0.25, 1.0, 0.5, 0.0, 0.9],
                [1.0, 0.0, 0.0, 1.0, 1.0],
            ],
        };
        let back = TransferFunction::try_from(&pb::TransferFunction::from(&tf)).unwrap();
        assert_eq!(back, tf);
        assert_eq!(back.identity_hash(), tf.identity_hash());
        let mut m = pb::TransferFunction::from(&tf);
        m.points[1].x = 0.0;
        let e = TransferFunction::try_from(&m).unwrap_err().to_string();
        assert!(
            e.contains("on the wire") && e.contains("x must increase"),
            "{e}"
        );
        let mut m = pb::TransferFunction::from(&tf);
        m.domain_hi = f64::NAN;
        assert!(TransferFunction::try_from(&m)
            .unwrap_err()
            .to_string()
            .contains("domain"));
        let e = TransferFunction::try_from(&pb::TransferFunction::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("domain"), "{e}");
        let mut m = pb::TransferFunction::from(&tf);
        m.points = (0..=MAX_TF_POINTS)
            .map(|i| pb::ControlPoint {
                x: i as f64 / MAX_TF_POINTS as f64,
                ..Default::default()
            })
            .collect();
        let e = TransferFunction::try_from(&m).unwrap_err().to_string();
        assert!(e.contains("more than 16384"), "{e}");
        let e = tf_field(Some(&m), None).unwrap_err();
        assert!(e.starts_with("tf: transfer function on the wire"), "{e}");
        let e = tf_field(None, Some("{}")).unwrap_err();
        assert!(e.starts_with("tf_json:") && e.contains("send `tf`"), "{e}");
        assert_eq!(tf_field(None, Some("")), Ok(None));
        let ok = pb::TransferFunction::from(&tf);
        assert_eq!(tf_field(Some(&ok), None), Ok(Some(tf)));
    }
}
