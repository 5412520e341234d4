//! Receiving a time step: the header is validated before any payload is read, and the
//! payload is converted into the volume's own storage chunk by chunk as it arrives
//! ([`FieldAssembler`]: one pass, no copy of the received bytes kept, docs/conventions.md).

use glam::Vec3;
use insitu_core::volume::{Aabb, FieldAssembler, ScalarType};
use insitu_core::Volume;
use insitu_proto::convert::wire_enum;
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
    /// The step's named fields as pushed (empty: one unnamed field, or a step read back from
    /// the spool, which keeps only the field kept).
    pub fields: Vec<String>,
    /// The name of the field kept (`None`: unnamed, or not known).
    pub field_name: Option<String>,
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

/// Longest field name, bytes.
pub const MAX_FIELD_NAME: usize = 128;

/// A field's name as steps and configs may carry it: 1 to [`MAX_FIELD_NAME`] bytes, no control
/// characters.
///
/// # Errors
/// What is wrong with it, in words.
pub fn check_field_name(name: &str) -> Result<(), String> {
    if name.is_empty() || name.len() > MAX_FIELD_NAME || name.chars().any(char::is_control) {
        return Err(format!(
            "a field name is 1 to {MAX_FIELD_NAME} bytes without control characters, not {name:?}"
        ));
    }
    Ok(())
}

/// Where the field to render lies in a step's payload, and how far the stream has come: the
/// bytes of the other fields are skipped as they arrive.
#[derive(Clone, Copy, Debug)]
pub struct FieldWindow {
    at: u64,
    start: u64,
    end: u64,
}

impl FieldWindow {
    /// The part of the payload's next `bytes` that belongs to the field (possibly empty).
    pub fn take<'a>(&mut self, bytes: &'a [u8]) -> &'a [u8] {
        let from = self.at;
        let to = from + bytes.len() as u64;
        self.at = to;
        let a = self.start.clamp(from, to);
        let b = self.end.clamp(a, to);
        &bytes[(a - from) as usize..(b - from) as usize]
    }
}

/// Checks a step header: types, dims, brick inside the grid, rank, and that `total_bytes`
/// equals the fields' bytes. Returns the parsed geometry of the field to render.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the field; see [`check_step`].
pub fn check_header(h: &pb::StepHeader) -> Result<StepInfo, Status> {
    check_step(h, None).map(|(info, _)| info)
}

/// Checks a step header and finds the field to render: `wanted` by name, else the first. A
/// step without named fields holds one vertex field of `dtype`, whatever `wanted` says. An
/// element-associated field (one value per cell) is returned as the grid of its cells'
/// centres: one fewer sample per axis, half a cell in from the origin.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the header field or the step's field: dims out of range, a brick
/// outside the grid, a bad rank, `total_bytes` that is not the fields' bytes, a field name
/// empty, too long or given twice, an unknown type or association, `wanted` absent (listing
/// the fields there), element data from more than one rank or with an axis of one point, a
/// spacing or origin that is not finite.
pub fn check_step(
    h: &pb::StepHeader,
    wanted: Option<&str>,
) -> Result<(StepInfo, FieldWindow), Status> {
    let mut global_dims = dims(h.global_dims.as_ref(), "global_dims", 1)?;
    let brick_offset = dims(h.brick_offset.as_ref(), "brick_offset", 0)?;
    let mut brick_dims = dims(h.brick_dims.as_ref(), "brick_dims", 1)?;
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
    check_world(h.world_size, brick_dims, global_dims)?;
    let spacing = h
        .spacing
        .as_ref()
        .map_or(Vec3::ONE, |s| Vec3::new(s.x, s.y, s.z));
    if !(spacing.is_finite() && spacing.min_element() > 0.0) {
        return Err(Status::invalid_argument(format!(
            "spacing {spacing} must be finite and positive"
        )));
    }
    let mut origin = h
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
    let (chosen, window) = choose_field(h, brick_dims, wanted)?;
    if chosen.association == pb::Association::Element {
        if h.world_size > 1 {
            return Err(Status::invalid_argument(format!(
                "field {:?} is element-associated: cell data is taken from a single rank (the \
                 bricks of cells of several ranks do not abut without ghost cells); push it \
                 from one rank, or as vertex data",
                chosen.name
            )));
        }
        global_dims = global_dims.map(|d| d - 1);
        brick_dims = brick_dims.map(|d| d - 1);
        origin += spacing * 0.5;
    }
    Ok((
        StepInfo {
            step: h.step,
            sim_time: h.sim_time,
            rank: h.rank,
            world_size: h.world_size,
            dtype: chosen.dtype,
            global_dims,
            brick_offset,
            brick_dims,
            spacing,
            origin,
        },
        window,
    ))
}

/// Most ranks a step's world may have.
pub const MAX_WORLD_SIZE: u32 = 1 << 20;

/// Refuses a world that cannot be: over [`MAX_WORLD_SIZE`] ranks, or more ranks than the grid
/// has room for beside this rank's brick (bricks do not overlap and each holds a voxel), so
/// a step is never held waiting for ranks that cannot exist.
///
/// # Errors
/// `INVALID_ARGUMENT` naming `world_size`, the limit or the grid.
fn check_world(world_size: u32, brick: [usize; 3], grid: [usize; 3]) -> Result<(), Status> {
    if world_size > MAX_WORLD_SIZE {
        return Err(Status::invalid_argument(format!(
            "world_size {world_size} is over the limit of {MAX_WORLD_SIZE} ranks"
        )));
    }
    let voxels = |d: [usize; 3]| d.iter().map(|&n| n as u64).product::<u64>();
    let room = voxels(grid) - voxels(brick);
    if u64::from(world_size - 1) > room {
        return Err(Status::invalid_argument(format!(
            "world_size {world_size}: this rank's brick {brick:?} leaves {room} voxel(s) of the grid {grid:?} for the other {} ranks, and bricks do not overlap",
            world_size - 1
        )));
    }
    Ok(())
}

/// The field [`check_step`] chose.
struct Chosen<'a> {
    name: &'a str,
    association: pb::Association,
    dtype: ScalarType,
}

/// Checks a step's fields against its brick and `total_bytes`, and finds `wanted` (else the
/// first) and its bytes in the payload.
fn choose_field<'a>(
    h: &'a pb::StepHeader,
    brick_dims: [usize; 3],
    wanted: Option<&str>,
) -> Result<(Chosen<'a>, FieldWindow), Status> {
    let points: u64 = brick_dims.iter().map(|&d| d as u64).product();
    if h.fields.is_empty() {
        let dtype = wire_enum::<pb::ScalarType>(h.dtype, "dtype").and_then(ScalarType::try_from)?;
        let expected = points * dtype.size_bytes() as u64;
        if h.total_bytes != expected {
            return Err(Status::invalid_argument(format!(
                "total_bytes {} does not match brick_dims {brick_dims:?} of {} ({expected} bytes)",
                h.total_bytes,
                dtype.name()
            )));
        }
        let chosen = Chosen {
            name: "",
            association: pb::Association::Vertex,
            dtype,
        };
        let window = FieldWindow {
            at: 0,
            start: 0,
            end: expected,
        };
        return Ok((chosen, window));
    }
    let cells: u64 = brick_dims.iter().map(|&d| d as u64 - 1).product();
    let mut at = 0u64;
    let mut found = None;
    for (i, f) in h.fields.iter().enumerate() {
        check_field_name(&f.name)
            .map_err(|e| Status::invalid_argument(format!("fields[{i}]: {e}")))?;
        if h.fields[..i].iter().any(|g| g.name == f.name) {
            return Err(Status::invalid_argument(format!(
                "field {:?} is named twice",
                f.name
            )));
        }
        let dtype = wire_enum::<pb::ScalarType>(f.dtype, "dtype")
            .and_then(ScalarType::try_from)
            .map_err(|e| {
                Status::invalid_argument(format!("field {:?}: {}", f.name, e.message()))
            })?;
        let association = pb::Association::try_from(f.association).map_err(|_| {
            Status::invalid_argument(format!(
                "field {:?}: unknown association {}",
                f.name, f.association
            ))
        })?;
        let count = match association {
            pb::Association::Vertex => points,
            pb::Association::Element => {
                if brick_dims.contains(&1) {
                    return Err(Status::invalid_argument(format!(
                        "field {:?} is element-associated on a brick of {brick_dims:?} points: \
                         an axis of one point has no cell",
                        f.name
                    )));
                }
                cells
            }
        };
        let bytes = count * dtype.size_bytes() as u64;
        let is_wanted = wanted.map_or(i == 0, |w| w == f.name);
        if is_wanted {
            let chosen = Chosen {
                name: &f.name,
                association,
                dtype,
            };
            let window = FieldWindow {
                at: 0,
                start: at,
                end: at + bytes,
            };
            found = Some((chosen, window));
        }
        at += bytes;
    }
    if h.total_bytes != at {
        return Err(Status::invalid_argument(format!(
            "total_bytes {} does not match the {} bytes of the fields ({}) on a brick of {brick_dims:?} points",
            h.total_bytes,
            at,
            h.fields
                .iter()
                .map(|f| f.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    found.ok_or_else(|| {
        Status::invalid_argument(format!(
            "step {} has no field {:?}; fields here: {}",
            h.step,
            wanted.unwrap_or_default(),
            h.fields
                .iter()
                .map(|f| f.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))
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
            fields: Vec::new(),
            field_name: None,
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
    /// The step with the names of its header's fields, `wanted` the one kept (else the first).
    #[must_use]
    pub fn named(mut self, h: &pb::StepHeader, wanted: Option<&str>) -> Self {
        self.fields = h.fields.iter().map(|f| f.name.clone()).collect();
        self.field_name = wanted
            .map(str::to_owned)
            .or_else(|| self.fields.first().cloned());
        self
    }

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
            fields: Vec::new(),
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
        // The probe's world: four billion ranks, acknowledged and then waited for.
        assert!(msg(&|h| {
            h.rank = 0;
            h.world_size = u32::MAX;
        })
        .contains("over the limit of 1048576 ranks"));
        // More ranks than the grid has voxels beside this rank's brick.
        let m = msg(&|h| {
            h.rank = 0;
            h.world_size = 1 << 19;
        });
        assert!(
            m.contains("leaves") && m.contains("bricks do not overlap"),
            "{m}"
        );
        assert!(msg(&|h| h.spacing = Some(pb::Vec3 {
            x: 1.0,
            y: 0.0,
            z: 1.0
        }))
        .contains("spacing"));
        assert!(msg(&|h| h.sim_time = f64::NAN).contains("sim_time"));
    }

    /// A 4×3×2 single-rank step with named fields: `u` f32 on the points, `flag` u8 on the
    /// points, `p` f32 on the cells.
    fn named() -> pb::StepHeader {
        let d = |x, y, z| Some(pb::Dims3 { x, y, z });
        let field = |name: &str, association: pb::Association, dtype: pb::ScalarType| pb::Field {
            name: name.into(),
            association: association as i32,
            dtype: dtype as i32,
        };
        pb::StepHeader {
            step: 3,
            global_dims: d(4, 3, 2),
            brick_offset: d(0, 0, 0),
            brick_dims: d(4, 3, 2),
            world_size: 1,
            total_bytes: 24 * 4 + 24 + 6 * 4,
            spacing: Some(pb::Vec3 {
                x: 2.0,
                y: 1.0,
                z: 0.5,
            }),
            fields: vec![
                field("u", pb::Association::Vertex, pb::ScalarType::F32),
                field("flag", pb::Association::Vertex, pb::ScalarType::U8),
                field("p", pb::Association::Element, pb::ScalarType::F32),
            ],
            ..Default::default()
        }
    }

    /// The payload of [`named`]: u = 0..24, flag = 100..124, p = 1000..1006.
    fn named_payload() -> Vec<u8> {
        let mut b: Vec<u8> = (0..24u32).flat_map(|i| (i as f32).to_le_bytes()).collect();
        b.extend((100..124u8).collect::<Vec<_>>());
        b.extend((1000..1006u32).flat_map(|i| (i as f32).to_le_bytes()));
        b
    }

    /// The field `wanted` of the named step, its payload cut into chunks of `chunk` bytes.
    fn receive(wanted: Option<&str>, chunk: usize) -> RawStep {
        let (info, mut window) = check_step(&named(), wanted).unwrap();
        let mut field = info.assembler(None);
        for c in named_payload().chunks(chunk) {
            field.push(window.take(c));
        }
        info.with_field(field).unwrap()
    }

    #[test]
    fn the_scene_s_field_is_kept_and_the_others_skipped_whatever_the_chunks() {
        for chunk in [1, 5, 7, 96, 1000] {
            let u = receive(None, chunk);
            assert_eq!(u.field.dims(), [4, 3, 2]);
            assert_eq!(
                u.field.data().to_vec(),
                (0..24).map(|i| i as f32).collect::<Vec<_>>()
            );
            let flag = receive(Some("flag"), chunk);
            assert_eq!(flag.info.dtype, ScalarType::U8);
            assert_eq!(
                flag.field.data().to_vec(),
                (100..124).map(|i| i as f32).collect::<Vec<_>>()
            );
            // Cell data: its cells' centres, one fewer per axis, half a cell in.
            let p = receive(Some("p"), chunk);
            assert_eq!(p.field.dims(), [3, 2, 1]);
            assert_eq!(p.field.world_box().min, Vec3::new(1.0, 0.5, 0.25));
            assert_eq!(p.info.global_box().max, Vec3::new(5.0, 1.5, 0.25));
            assert_eq!(
                p.field.data().to_vec(),
                (1000..1006).map(|i| i as f32).collect::<Vec<_>>()
            );
        }
    }

    #[test]
    fn bad_field_descriptions_are_refused_by_name() {
        let msg = |h: &pb::StepHeader, wanted: Option<&str>| {
            check_step(h, wanted).unwrap_err().message().to_owned()
        };
        let e = msg(&named(), Some("rho"));
        assert!(
            e.contains("step 3 has no field \"rho\"; fields here: u, flag, p"),
            "{e}"
        );
        let mut h = named();
        h.total_bytes += 1;
        let e = msg(&h, None);
        assert!(
            e.contains("does not match the 144 bytes of the fields (u, flag, p)"),
            "{e}"
        );
        let mut h = named();
        h.fields[1].name = "u".into();
        assert!(msg(&h, None).contains("field \"u\" is named twice"));
        let mut h = named();
        h.fields[0].name = String::new();
        assert!(msg(&h, None).contains("fields[0]: a field name is 1 to 128 bytes"));
        let mut h = named();
        h.fields[2].dtype = 0;
        assert!(msg(&h, None).contains("field \"p\": dtype is unspecified"));
        let mut h = named();
        h.fields[2].association = 7;
        assert!(msg(&h, None).contains("field \"p\": unknown association 7"));
        // Cell data from one of several ranks, and on an axis of one point.
        let mut h = named();
        h.world_size = 2;
        // The other rank's brick beside this one.
        h.global_dims = Some(pb::Dims3 { x: 8, y: 3, z: 2 });
        assert!(msg(&h, Some("p")).contains("cell data is taken from a single rank"));
        assert!(
            check_step(&h, Some("u")).is_ok(),
            "vertex data from a rank is fine"
        );
        let mut h = named();
        h.global_dims = Some(pb::Dims3 { x: 4, y: 3, z: 1 });
        h.brick_dims = h.global_dims;
        h.total_bytes = 12 * 4 + 12;
        assert!(msg(&h, None)
            .contains("field \"p\" is element-associated on a brick of [4, 3, 1] points"));
    }

    #[test]
    fn a_step_without_named_fields_is_its_one_field_whatever_the_scene_names() {
        let (info, mut w) = check_step(&header(), Some("rho")).unwrap();
        assert_eq!((info.dtype, info.brick_dims), (ScalarType::F32, [8, 6, 5]));
        assert_eq!(w.take(&[0u8; 960]).len(), 960);
    }
}
