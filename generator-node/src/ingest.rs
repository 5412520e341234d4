//! Receiving a time step: the header is validated before any payload is read, and the
//! payload is converted into the volume's own storage chunk by chunk as it arrives
//! ([`FieldAssembler`]: one pass, no copy of the received bytes kept, docs/conventions.md).

use glam::Vec3;
use insitu_core::volume::{Aabb, FieldAssembler, ScalarType};
use insitu_core::Volume;
use insitu_proto::convert::dtype_from_pb;
use insitu_proto::pb;
use tonic::Status;

/// Largest grid side accepted, voxels.
pub const MAX_DIM: u32 = 65536;

/// What a step's header says: which step and rank, and the brick's place in the grid.
#[derive(Clone, Copy, Debug)]
pub struct StepInfo {
    /// Step index.
    pub step: u64,
    /// Simulation time.
    pub sim_time: f64,
    /// Rank and number of ranks.
    pub rank: u32,
    /// Number of ranks.
    pub world_size: u32,
    /// Scalar type on the wire.
    pub dtype: ScalarType,
    /// The whole grid, voxels.
    pub global_dims: [usize; 3],
    /// First voxel of the brick in the whole grid.
    pub brick_offset: [usize; 3],
    /// Brick size, voxels.
    pub brick_dims: [usize; 3],
    /// Voxel spacing, world units.
    pub spacing: Vec3,
    /// World position of the whole grid's first voxel.
    pub origin: Vec3,
}

/// One rank's brick of one time step, as received.
#[derive(Debug)]
pub struct RawStep {
    /// Its header.
    pub info: StepInfo,
    /// The brick, placed at its world origin, in its own type (u8, u16; others as f32).
    pub field: Volume,
    /// Its file in the spool, when the node has one (removed once the step is settled).
    pub spool: Option<String>,
}

fn dims(d: Option<&pb::Dims3>, name: &str, min: u32) -> Result<[usize; 3], Status> {
    let d = d.ok_or_else(|| Status::invalid_argument(format!("{name} is missing")))?;
    let v = [d.x, d.y, d.z];
    if v.iter().any(|&x| x < min || x > MAX_DIM) {
        return Err(Status::invalid_argument(format!(
            "{name} {v:?}: each component must be in {min}..={MAX_DIM}"
        )));
    }
    Ok(v.map(|x| x as usize))
}

/// Checks a step header: types, dims, brick inside the grid, rank, and that `total_bytes`
/// equals the brick's voxels times the type's size. Returns the parsed geometry.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the field.
pub fn check_header(h: &pb::StepHeader) -> Result<StepInfo, Status> {
    let dtype = dtype_from_pb(h.dtype)?;
    let global_dims = dims(h.global_dims.as_ref(), "global_dims", 1)?;
    let brick_offset = dims(h.brick_offset.as_ref(), "brick_offset", 0)?;
    let brick_dims = dims(h.brick_dims.as_ref(), "brick_dims", 1)?;
    for a in 0..3 {
        if brick_offset[a] + brick_dims[a] > global_dims[a] {
            return Err(Status::invalid_argument(format!(
                "brick at {brick_offset:?} of size {brick_dims:?} does not fit in the grid {global_dims:?}"
            )));
        }
    }
    if h.world_size == 0 || h.rank >= h.world_size {
        return Err(Status::invalid_argument(format!(
            "rank {} with world_size {}: need 0 ≤ rank < world_size",
            h.rank, h.world_size
        )));
    }
    let voxels: u64 = brick_dims.iter().map(|&d| d as u64).product();
    let expected = voxels * dtype.size_bytes() as u64;
    if h.total_bytes != expected {
        return Err(Status::invalid_argument(format!(
            "total_bytes {} does not match brick_dims {brick_dims:?} of {} ({expected} bytes)",
            h.total_bytes,
            dtype.name()
        )));
    }
    let spacing = h
        .spacing
        .as_ref()
        .map_or(Vec3::ONE, |s| Vec3::new(s.x, s.y, s.z));
    if !(spacing.is_finite() && spacing.min_element() > 0.0) {
        return Err(Status::invalid_argument(format!(
            "spacing {spacing} must be finite and positive"
        )));
    }
    let origin = h
        .origin
        .as_ref()
        .map_or(Vec3::ZERO, |o| Vec3::new(o.x, o.y, o.z));
    if !origin.is_finite() {
        return Err(Status::invalid_argument(format!(
            "origin {origin} must be finite"
        )));
    }
    if !h.sim_time.is_finite() {
        return Err(Status::invalid_argument("sim_time must be finite"));
    }
    Ok(StepInfo {
        step: h.step,
        sim_time: h.sim_time,
        rank: h.rank,
        world_size: h.world_size,
        dtype,
        global_dims,
        brick_offset,
        brick_dims,
        spacing,
        origin,
    })
}

impl StepInfo {
    /// An empty brick to push the payload into, in `spare`'s memory when given
    /// ([`FieldAssembler::reusing`]).
    pub fn assembler(&self, spare: Option<Volume>) -> FieldAssembler {
        FieldAssembler::reusing(self.dtype, self.brick_dims.iter().product(), spare)
    }

    /// The step with the brick `field` assembled, placed at its world origin.
    ///
    /// # Errors
    /// `INVALID_ARGUMENT` when the payload does not match the header's brick (cannot happen
    /// after [`check_header`] and a complete stream, but the check is cheap).
    pub fn with_field(self, field: FieldAssembler) -> Result<RawStep, Status> {
        let origin = self.origin + Vec3::from(self.brick_offset.map(|o| o as f32)) * self.spacing;
        let field = field
            .finish(self.brick_dims, self.spacing)
            .and_then(|v| v.with_origin(origin))
            .map_err(|e| Status::invalid_argument(format!("step {}: {e}", self.step)))?;
        Ok(RawStep {
            info: self,
            field,
            spool: None,
        })
    }

    /// The world box of the whole grid, `origin + [0, (n − 1)·s]` (what the default camera
    /// frames, so that all ranks share one camera).
    pub fn global_box(&self) -> Aabb {
        let [nx, ny, nz] = self.global_dims;
        Aabb {
            min: self.origin,
            max: self.origin
                + Vec3::new((nx - 1) as f32, (ny - 1) as f32, (nz - 1) as f32) * self.spacing,
        }
    }
}

impl RawStep {
    /// Bytes the field holds in memory (what the queue and the spool count).
    pub fn bytes(&self) -> u64 {
        self.field.storage_bytes() as u64
    }

    /// Its spool file and the bytes counted for it there (what
    /// [`crate::shared::Shared::unspool`] releases once the step is settled).
    pub fn spooled(&self) -> Option<(String, u64)> {
        self.spool.clone().map(|n| (n, self.bytes()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> pb::StepHeader {
        let d = |x, y, z| Some(pb::Dims3 { x, y, z });
        pb::StepHeader {
            step: 7,
            sim_time: 1.5,
            dtype: pb::ScalarType::F32 as i32,
            global_dims: d(8, 6, 10),
            brick_offset: d(0, 0, 5),
            brick_dims: d(8, 6, 5),
            rank: 1,
            world_size: 2,
            total_bytes: 8 * 6 * 5 * 4,
            spacing: None,
            origin: None,
        }
    }

    #[test]
    fn a_good_header_gives_the_brick_at_its_origin() {
        let info = check_header(&header()).unwrap();
        let mut field = info.assembler(None);
        let bytes: Vec<u8> = (0..240u32).flat_map(|i| (i as f32).to_le_bytes()).collect();
        // Chunks that split samples, as a client with its own chunk size may send.
        for c in bytes.chunks(7) {
            field.push(c);
        }
        let s = info.with_field(field).unwrap();
        let v = &s.field;
        assert_eq!(v.dims(), [8, 6, 5]);
        assert_eq!(v.world_box().min, Vec3::new(0.0, 0.0, 5.0));
        assert_eq!(v.data()[239], 239.0);
        assert_eq!(s.info.global_box().max, Vec3::new(7.0, 5.0, 9.0));
        assert_eq!(s.bytes(), 960);
    }

    /// The grid's origin moves every brick and the box the default camera frames; a
    /// non-finite one is refused by name.
    #[test]
    fn the_grid_s_origin_places_the_brick_and_the_box() {
        let h = pb::StepHeader {
            origin: Some(pb::Vec3 {
                x: 10.0,
                y: -2.0,
                z: 3.0,
            }),
            spacing: Some(pb::Vec3 {
                x: 2.0,
                y: 1.0,
                z: 0.5,
            }),
            ..header()
        };
        let info = check_header(&h).unwrap();
        let mut field = info.assembler(None);
        field.push(&vec![0u8; 960]);
        let s = info.with_field(field).unwrap();
        // Offset (0, 0, 5) at spacing (2, 1, 0.5) from (10, −2, 3).
        assert_eq!(s.field.world_box().min, Vec3::new(10.0, -2.0, 5.5));
        let whole = s.info.global_box();
        assert_eq!(
            (whole.min, whole.max),
            (Vec3::new(10.0, -2.0, 3.0), Vec3::new(24.0, 3.0, 7.5))
        );
        let bad = pb::StepHeader {
            origin: Some(pb::Vec3 {
                x: f32::NAN,
                y: 0.0,
                z: 0.0,
            }),
            ..header()
        };
        let e = check_header(&bad).unwrap_err();
        assert!(
            e.message().contains("origin [NaN, 0, 0] must be finite"),
            "{}",
            e.message()
        );
    }

    #[test]
    fn bad_headers_name_the_field() {
        let msg = |f: &dyn Fn(&mut pb::StepHeader)| {
            let mut h = header();
            f(&mut h);
            let e = check_header(&h).unwrap_err();
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            e.message().to_owned()
        };
        assert!(msg(&|h| h.total_bytes += 1).contains("total_bytes"));
        assert!(msg(&|h| h.dtype = 17).contains("dtype"));
        assert!(msg(&|h| h.dtype = 0).contains("dtype"));
        assert!(
            msg(&|h| h.brick_offset = Some(pb::Dims3 { x: 0, y: 0, z: 6 }))
                .contains("does not fit")
        );
        assert!(msg(&|h| h.global_dims = None).contains("global_dims"));
        assert!(
            msg(&|h| h.brick_dims = Some(pb::Dims3 { x: 0, y: 6, z: 5 })).contains("brick_dims")
        );
        assert!(msg(&|h| h.rank = 2).contains("rank"));
        assert!(msg(&|h| h.world_size = 0).contains("world_size"));
        assert!(msg(&|h| h.spacing = Some(pb::Vec3 {
            x: 1.0,
            y: 0.0,
            z: 1.0
        }))
        .contains("spacing"));
        assert!(msg(&|h| h.sim_time = f64::NAN).contains("sim_time"));
    }
}
