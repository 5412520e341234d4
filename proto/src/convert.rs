//! Wire messages ↔ `insitu-core` types. Every conversion from the wire validates and says what
//! was wrong, as a gRPC status the caller can return as is.

use crate::pb;
use glam::Vec3;
use insitu_core::backend::TimeSource;
use insitu_core::compose::{frame_from_le_bytes, frame_to_le_bytes};
use insitu_core::vdi::codec::Codec;
use insitu_core::volume::{Aabb, ScalarType};
use insitu_core::{Camera, Image, TransferFunction};
use tonic::Status;

/// Largest transfer function taken over the wire (`GenerationConfig.tf_json`, a steered
/// `Scene`'s, `SteerRequest.tf_json`), bytes.
pub const MAX_TF_JSON: usize = 1 << 20;

/// A transfer function from the wire: at most [`MAX_TF_JSON`] bytes of JSON
/// (docs/conventions.md format), named `name`.
///
/// # Errors
/// A message saying it is too long, or why it does not parse or is invalid.
pub fn tf_from_json(json: &str, name: &str) -> Result<TransferFunction, String> {
    if json.len() > MAX_TF_JSON {
        return Err(format!(
            "{} bytes exceeds the limit of {MAX_TF_JSON}",
            json.len()
        ));
    }
    TransferFunction::from_json(json, name).map_err(|e| e.to_string())
}

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
        box_min: Some(vec3_to_pb(world_box.min)),
        box_max: Some(vec3_to_pb(world_box.max)),
        origin_x: origin[0],
        origin_y: origin[1],
        width: image.width(),
        height: image.height(),
        rgba_zstd: rgba_zstd.into(),
        camera: Some(camera_to_pb(camera)),
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
        vec3_from_pb(f.box_min.as_ref()),
        vec3_from_pb(f.box_max.as_ref()),
    ) else {
        return Err(format!("rank {rank}: no box"));
    };
    Ok(([f.origin_x, f.origin_y], image, opacity, Aabb { min, max }))
}

/// Grid dims or a voxel offset, `[x, y, z]`, on the wire (each < 2³², as every grid the
/// nodes accept).
pub fn dims_to_pb(d: [usize; 3]) -> pb::Dims3 {
    pb::Dims3 {
        x: d[0] as u32,
        y: d[1] as u32,
        z: d[2] as u32,
    }
}

/// Dims or an offset from the wire, unchecked; an unset field is `None` (what a field means
/// and which values it may take is for its reader to check).
pub fn dims_from_pb(d: Option<&pb::Dims3>) -> Option<[usize; 3]> {
    d.map(|d| [d.x, d.y, d.z].map(|x| x as usize))
}

/// A world-space vector.
pub fn vec3_to_pb(v: Vec3) -> pb::Vec3 {
    pb::Vec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

/// A world-space vector; an unset field is `None`.
pub fn vec3_from_pb(v: Option<&pb::Vec3>) -> Option<Vec3> {
    v.map(|v| Vec3::new(v.x, v.y, v.z))
}

/// A camera for the wire.
pub fn camera_to_pb(c: &Camera) -> pb::Camera {
    pb::Camera {
        eye: Some(vec3_to_pb(c.eye)),
        target: Some(vec3_to_pb(c.target)),
        up: Some(vec3_to_pb(c.up)),
        fov_y_deg: c.fov_y_deg,
    }
}

/// A camera from the wire.
///
/// # Errors
/// `INVALID_ARGUMENT` when a vector is missing or the camera is degenerate (see
/// [`Camera::is_valid`]).
pub fn camera_from_pb(c: &pb::Camera) -> Result<Camera, Status> {
    let field = |v: Option<&pb::Vec3>, name: &str| {
        vec3_from_pb(v).ok_or_else(|| Status::invalid_argument(format!("camera.{name} is missing")))
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

/// A codec for the wire.
pub fn codec_to_pb(c: Codec) -> pb::Codec {
    match c {
        Codec::None => pb::Codec::None,
        Codec::Bzip2 => pb::Codec::Bzip2,
        Codec::Zstd => pb::Codec::Zstd,
    }
}

/// A codec from the wire (`i32` as prost stores enums); `Ok(None)` for "unspecified".
///
/// # Errors
/// `INVALID_ARGUMENT` for an unknown value.
pub fn codec_from_pb(v: i32) -> Result<Option<Codec>, Status> {
    match pb::Codec::try_from(v) {
        Ok(pb::Codec::Unspecified) => Ok(None),
        Ok(pb::Codec::None) => Ok(Some(Codec::None)),
        Ok(pb::Codec::Bzip2) => Ok(Some(Codec::Bzip2)),
        Ok(pb::Codec::Zstd) => Ok(Some(Codec::Zstd)),
        Err(_) => Err(Status::invalid_argument(format!("unknown codec {v}"))),
    }
}

/// Where a τ comes from, for the wire.
pub fn tau_source_to_pb(t: TimeSource) -> pb::TauSource {
    match t {
        TimeSource::WallClock => pb::TauSource::WallClock,
        TimeSource::GpuTimestamps => pb::TauSource::GpuTimestamps,
    }
}

/// Where a τ comes from, from the wire; unspecified (a node that does not say) is the wall
/// clock.
///
/// # Errors
/// `INVALID_ARGUMENT` for an unknown value.
pub fn tau_source_from_pb(v: i32) -> Result<TimeSource, Status> {
    match pb::TauSource::try_from(v) {
        Ok(pb::TauSource::Unspecified | pb::TauSource::WallClock) => Ok(TimeSource::WallClock),
        Ok(pb::TauSource::GpuTimestamps) => Ok(TimeSource::GpuTimestamps),
        Err(_) => Err(Status::invalid_argument(format!("unknown tau_source {v}"))),
    }
}

/// A scalar type for the wire.
pub fn dtype_to_pb(t: ScalarType) -> pb::ScalarType {
    match t {
        ScalarType::U8 => pb::ScalarType::U8,
        ScalarType::U16 => pb::ScalarType::U16,
        ScalarType::I16 => pb::ScalarType::I16,
        ScalarType::F32 => pb::ScalarType::F32,
        ScalarType::F64 => pb::ScalarType::F64,
    }
}

/// A scalar type from the wire.
///
/// # Errors
/// `INVALID_ARGUMENT` for "unspecified" or an unknown value.
pub fn dtype_from_pb(v: i32) -> Result<ScalarType, Status> {
    match pb::ScalarType::try_from(v) {
        Ok(pb::ScalarType::U8) => Ok(ScalarType::U8),
        Ok(pb::ScalarType::U16) => Ok(ScalarType::U16),
        Ok(pb::ScalarType::I16) => Ok(ScalarType::I16),
        Ok(pb::ScalarType::F32) => Ok(ScalarType::F32),
        Ok(pb::ScalarType::F64) => Ok(ScalarType::F64),
        Ok(pb::ScalarType::Unspecified) => Err(Status::invalid_argument("dtype is unspecified")),
        Err(_) => Err(Status::invalid_argument(format!("unknown dtype {v}"))),
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
        assert_eq!(camera_from_pb(&camera_to_pb(&cam)).unwrap(), cam);
        let mut bad = camera_to_pb(&cam);
        bad.target = bad.eye;
        assert_eq!(
            camera_from_pb(&bad).unwrap_err().code(),
            tonic::Code::InvalidArgument
        );
        bad.eye = None;
        assert!(camera_from_pb(&bad).unwrap_err().message().contains("eye"));
        for c in Codec::ALL {
            assert_eq!(codec_from_pb(codec_to_pb(c) as i32).unwrap(), Some(c));
        }
        assert_eq!(codec_from_pb(0).unwrap(), None);
        assert!(codec_from_pb(99).is_err());
        for t in [
            ScalarType::U8,
            ScalarType::U16,
            ScalarType::I16,
            ScalarType::F32,
            ScalarType::F64,
        ] {
            assert_eq!(dtype_from_pb(dtype_to_pb(t) as i32).unwrap(), t);
        }
        assert!(dtype_from_pb(0).is_err());
        assert!(dtype_from_pb(42).is_err());
    }
}
