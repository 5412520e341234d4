//! Volumetric Depth Images (Sec. 3.2, Fig. 2; docs/conventions.md, "VDI").
//!
//! A [`Vdi`] holds, for an `r × r` grid of rays from the generation camera, a depth-ordered
//! list of [`Supersegment`]s per pixel, laid out as prefix offsets (`r² + 1` entries) into
//! one flat array: cheap to build, to traverse and to serialise.
//!
//! - [`generate`]: `R(S_A, P_A, P_M) → M`, the merge of ray samples into supersegments.
//! - [`render`]: `I(M, P_I) → O`, compositing the frusta along rays of a new camera.
//! - [`codec`]: the versioned, compressed, validated file format whose size is σ.
//! - [`window`]: a sub-VDI cropped to its footprint, as a host holds it until it composes.

pub mod codec;
pub mod generate;
pub mod lod;
pub mod provenance;
pub mod render;
pub mod window;

use crate::camera::Camera;
use crate::volume::Aabb;
use std::sync::OnceLock;

/// One supersegment: a frustum of a pixel's pyramid with constant colour and opacity.
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Supersegment {
    /// Eye-space depth (along the generation camera's view direction) where it starts.
    pub z_start: f32,
    /// Eye-space depth where it ends (`> z_start`).
    pub z_end: f32,
    /// Colour `ĉ`: accumulated premultiplied colour over accumulated opacity, in [0, 1].
    pub color: [f32; 3],
    /// Opacity per unit length `â = 1 − (1 − A)^(1/L)`, `L` its world length on the
    /// generating ray, in [0, 1].
    pub alpha: f32,
}

impl Supersegment {
    /// Extinction per unit length `κ = −ln(1 − â)` (`∞` for `â = 1`): what the walk's
    /// `α' = 1 − e^(−ℓ·κ)` takes, and what a coarser level averages ([`lod`]).
    #[inline]
    pub fn extinction(&self) -> f32 {
        -(-self.alpha).ln_1p()
    }
}

/// Generation parameters `P_M = (r, γ, precision)`: the paper's two (Sec. 5.2) and the
/// precision its file stores the supersegments at ([`codec`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VdiParams {
    /// Resolution: `r × r` rays.
    pub resolution: u32,
    /// Interrupt threshold γ on `‖â·ĉ − a·c‖₂`.
    pub gamma: f32,
    /// How the file stores the supersegments' numbers; generation ignores it.
    pub precision: Precision,
}

/// How a VDI file stores its supersegments' depths, colours and opacities: the third
/// parameter of `P_M`, trading σ for error bounds stated in world and colour units
/// ([`codec`], docs/conventions.md "The VDI file").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Precision {
    /// 32-bit floats, lossless (format version 3): the paper's σ.
    #[default]
    Float32,
    /// Colour and opacity to `bits` bits (an error of at most `0.5 / (2^bits − 1)` colour
    /// units), depths to a power-of-two fraction of the ray-casting step (format version 4;
    /// [`codec::quantized`]). `bits` in [`Precision::MIN_BITS`]`..=`[`Precision::MAX_BITS`].
    Bits(u8),
}

impl Precision {
    /// Fewest colour bits.
    pub const MIN_BITS: u8 = 4;
    /// Most colour bits.
    pub const MAX_BITS: u8 = 16;

    /// Lower-case name: `f32`, or the bit count (`10`).
    pub fn name(self) -> String {
        match self {
            Self::Float32 => "f32".to_owned(),
            Self::Bits(b) => b.to_string(),
        }
    }

    /// The largest error a stored colour or opacity may have, colour units (0 for `Float32`).
    pub fn color_bound(self) -> f32 {
        match self {
            Self::Float32 => 0.0,
            Self::Bits(b) => 0.5 / ((1u32 << b) - 1) as f32,
        }
    }

    /// The bit count on the wire and in configs: 0 for `Float32`.
    pub fn bits(self) -> u32 {
        match self {
            Self::Float32 => 0,
            Self::Bits(b) => u32::from(b),
        }
    }

    /// From [`Precision::bits`]: 0 is `Float32`.
    ///
    /// # Errors
    /// [`VdiParamError::Precision`] for a count outside the range.
    pub fn from_bits(bits: u32) -> Result<Self, VdiParamError> {
        match bits {
            0 => Ok(Self::Float32),
            b if (u32::from(Self::MIN_BITS)..=u32::from(Self::MAX_BITS)).contains(&b) => {
                Ok(Self::Bits(b as u8))
            }
            b => Err(VdiParamError::Precision(b.to_string())),
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Float32 => f.write_str("f32"),
            Self::Bits(b) => write!(f, "{b}-bit"),
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = VdiParamError;
    /// `f32` (or `float`), or a bit count in 4..=16 (`10`, `10-bit`).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let t = s.trim().to_ascii_lowercase();
        if t == "f32" || t == "float" || t == "float32" {
            return Ok(Self::Float32);
        }
        t.trim_end_matches("-bit")
            .trim_end_matches("bit")
            .parse::<u32>()
            .ok()
            .filter(|&b| b != 0)
            .map_or_else(
                || Err(VdiParamError::Precision(s.to_owned())),
                Self::from_bits,
            )
            .map_err(|_| VdiParamError::Precision(s.to_owned()))
    }
}

impl serde::Serialize for Precision {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.name())
    }
}

impl<'de> serde::Deserialize<'de> for Precision {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Bits(u32),
            Name(String),
        }
        match Raw::deserialize(d)? {
            Raw::Bits(b) => Precision::from_bits(b),
            Raw::Name(n) => n.parse(),
        }
        .map_err(serde::de::Error::custom)
    }
}

/// Largest accepted resolution `r`.
pub const MAX_RESOLUTION: u32 = 16384;

/// Errors for VDI parameters.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum VdiParamError {
    /// r outside 1..=16384.
    #[error("VDI resolution r = {0} must be in 1..={MAX_RESOLUTION}")]
    Resolution(u32),
    /// γ negative or not finite.
    #[error("interrupt threshold gamma = {0} must be finite and >= 0")]
    Gamma(f32),
    /// The generation camera is degenerate.
    #[error("generation camera is degenerate: {0:?}")]
    Camera(Camera),
    /// A precision that is neither `f32` nor a bit count in 4..=16.
    #[error("precision {0:?} must be f32 or a bit count in 4..=16")]
    Precision(String),
}

impl VdiParams {
    /// Checks ranges.
    ///
    /// # Errors
    /// [`VdiParamError`] naming the bad value.
    pub fn validate(&self) -> Result<(), VdiParamError> {
        if !(1..=MAX_RESOLUTION).contains(&self.resolution) {
            return Err(VdiParamError::Resolution(self.resolution));
        }
        if !(self.gamma.is_finite() && self.gamma >= 0.0) {
            return Err(VdiParamError::Gamma(self.gamma));
        }
        if let Precision::Bits(b) = self.precision {
            Precision::from_bits(u32::from(b))?;
        }
        Ok(())
    }
}

/// What a VDI was made from: enough to tell whether two VDIs are comparable.
#[derive(Clone, Debug, PartialEq)]
pub struct VdiMeta {
    /// Generation camera (square `r × r` image).
    pub camera: Camera,
    /// `P_M`.
    pub params: VdiParams,
    /// Ray-casting sample distance used, world units.
    pub sample_distance: f32,
    /// Early-termination threshold used.
    pub termination: f32,
    /// Whether samples were shaded.
    pub shaded: bool,
    /// The volume's world box.
    pub volume_box: Aabb,
    /// [`crate::tf::TransferFunction::identity_hash`] of the transfer function.
    pub tf_hash: u64,
    /// Human-readable transfer-function name (e.g. its file name), at most 1024 bytes.
    pub tf_name: String,
}

/// A Volumetric Depth Image.
#[derive(Clone, Debug, PartialEq)]
pub struct Vdi {
    meta: VdiMeta,
    offsets: Vec<u32>,
    supersegments: Vec<Supersegment>,
    derived: Derived,
}

/// What rendering derives from a VDI, built on first use and kept with it (a viewer renders
/// one VDI from many cameras): the walk's tables and the next coarser level. Not part of the
/// VDI's value (equality ignores it); cleared whenever the lists change.
#[derive(Clone, Default)]
struct Derived {
    walk: OnceLock<render::WalkTables>,
    half: OnceLock<Option<Box<Vdi>>>,
}

impl PartialEq for Derived {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for Derived {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Derived")
            .field("walk", &self.walk.get().is_some())
            .field("half", &self.half.get().is_some())
            .finish()
    }
}

impl Vdi {
    /// Assembles a VDI from its parts. `offsets` has `r² + 1` non-decreasing entries starting
    /// at 0 and ending at `supersegments.len()`; pixel `(i, j)` (row `j` from the top) owns
    /// `supersegments[offsets[i + r·j] .. offsets[i + r·j + 1]]`.
    ///
    /// Returns `None` when the offsets do not fit that shape.
    pub fn from_parts(
        meta: VdiMeta,
        offsets: Vec<u32>,
        supersegments: Vec<Supersegment>,
    ) -> Option<Self> {
        if !offsets.windows(2).all(|w| w[0] <= w[1]) {
            return None;
        }
        Self::from_sorted_parts(meta, offsets, supersegments)
    }

    /// [`Self::from_parts`] for offsets the caller has already found non-decreasing (the GPU
    /// path checks them as it reads them back); the other checks are made.
    pub(crate) fn from_sorted_parts(
        meta: VdiMeta,
        offsets: Vec<u32>,
        supersegments: Vec<Supersegment>,
    ) -> Option<Self> {
        let r = meta.params.resolution as usize;
        let ok = offsets.len() == r * r + 1
            && offsets.first() == Some(&0)
            && offsets.last().map(|&l| l as usize) == Some(supersegments.len());
        ok.then_some(Self {
            meta,
            offsets,
            supersegments,
            derived: Derived::default(),
        })
    }

    /// Generation metadata.
    pub fn meta(&self) -> &VdiMeta {
        &self.meta
    }

    /// Resolution `r`.
    pub fn resolution(&self) -> u32 {
        self.meta.params.resolution
    }

    /// Prefix offsets, `r² + 1` entries.
    pub fn offsets(&self) -> &[u32] {
        &self.offsets
    }

    /// All supersegments, pixel after pixel.
    pub fn supersegments(&self) -> &[Supersegment] {
        &self.supersegments
    }

    /// The depth-ordered list of pixel `(i, j)`.
    #[inline]
    pub fn pixel(&self, i: u32, j: u32) -> &[Supersegment] {
        let p = i as usize + self.resolution() as usize * j as usize;
        &self.supersegments[self.offsets[p] as usize..self.offsets[p + 1] as usize]
    }

    /// Supersegment count of pixel index `p = i + r·j`.
    pub fn count(&self, p: usize) -> u32 {
        self.offsets[p + 1] - self.offsets[p]
    }

    /// Sets the precision its file is written at (the lists are unchanged: rendering does not
    /// depend on it).
    pub fn set_precision(&mut self, precision: Precision) {
        self.meta.params.precision = precision;
    }

    /// Bytes held in memory by the lists (what the renderer reads).
    pub fn memory_bytes(&self) -> usize {
        self.offsets.len() * 4 + self.supersegments.len() * std::mem::size_of::<Supersegment>()
    }

    /// The walk's tables ([`render::Walker`]), built on first use.
    pub(crate) fn walk_tables(&self) -> &render::WalkTables {
        self.derived
            .walk
            .get_or_init(|| render::WalkTables::new(self))
    }

    /// The VDI at `r / 2` ([`lod::halve`]), built on first use and kept; `None` for odd `r`.
    pub fn half(&self) -> Option<&Vdi> {
        self.derived
            .half
            .get_or_init(|| lod::halve(self).map(Box::new))
            .as_deref()
    }

    /// The coarsest level (this VDI or one made by halving it, [`Vdi::half`]) whose
    /// resolution is still at least `side` pixels: what a frame `side` pixels across can show.
    /// Levels are built on first use (the teapot at r = 768: about 0.11 s for r = 384, on two
    /// cores) and kept.
    pub fn level_for(&self, side: u32) -> &Vdi {
        let mut v = self;
        while v.resolution() / 2 >= side.max(1) {
            match v.half() {
                Some(h) => v = h,
                None => break,
            }
        }
        v
    }

    /// Every pixel's list emptied (memory kept), at the metadata's resolution.
    fn empty_lists(&mut self) {
        self.offsets.clear();
        self.offsets
            .resize((self.resolution() as usize).pow(2) + 1, 0);
        self.supersegments.clear();
        self.lists_changed();
    }

    /// Forgets what was derived from the lists (after they change).
    fn lists_changed(&mut self) {
        self.derived = Derived::default();
    }
}
