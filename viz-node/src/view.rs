//! Any stored step from any camera (paper Sec. 3.1: a VDI is explored later from
//! other viewpoints): which VDI shows a step (one rank's, or for a world of ranks the step's
//! composed VDI), the camera of a view (an orbit about the generation camera's target), the
//! checks on a request, and the encoding of the frame. Shared by the web viewer
//! ([`crate::http`]), the `Render` call and `insitu view --recording`.

use insitu_core::cancel::Cancel;
use insitu_core::vdi::Vdi;
use insitu_core::{Backend, Camera, Image};
use insitu_recording::decoded::Expected;
use insitu_recording::store::{Entry, StepEntry};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Instant;

/// Largest side of a rendered image, pixels.
pub const MAX_SIDE: u32 = 8192;
/// Zoom range (eye–target distance over the generation camera's).
pub const ZOOM_RANGE: (f32, f32) = (0.05, 20.0);

/// The part of the image's half extents a fitted view's box fills ([`View::fit_zoom`]).
pub const FIT_MARGIN: f32 = 0.9;

/// Why a view cannot be served. The HTTP layer maps the kinds to 404, 400, 413 and 500.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ViewError {
    /// The step, rank or file is not in the recording (yet).
    #[error("{0}")]
    NotFound(String),
    /// A parameter is out of range or not a number.
    #[error("{0}")]
    BadRequest(String),
    /// The image is larger than the server allows.
    #[error("{0}")]
    TooLarge(String),
    /// Too many frames wait to render: try again shortly (503 with `Retry-After`).
    #[error("{0}")]
    Busy(String),
    /// A stored file cannot be read or decoded, or rendering failed.
    #[error("{0}")]
    Failed(String),
    /// The render was stopped: its client went away ([`Cancel`]).
    #[error("the render was cancelled (its client went away)")]
    Cancelled,
}

/// A camera about a stored VDI and an image size: the generation camera orbited by
/// `angle_deg` about +y and `elevation_deg` up, its distance scaled by `zoom`
/// ([`Camera::orbit`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct View {
    /// Degrees about +y (any finite value).
    pub angle_deg: f32,
    /// Degrees up, in [−89, 89].
    pub elevation_deg: f32,
    /// Distance over the generation camera's, in [`ZOOM_RANGE`].
    pub zoom: f32,
    /// Image width, pixels, 1..=[`MAX_SIDE`].
    pub width: u32,
    /// Image height, pixels, 1..=[`MAX_SIDE`].
    pub height: u32,
}

impl Default for View {
    fn default() -> Self {
        Self {
            angle_deg: 0.0,
            elevation_deg: 0.0,
            zoom: 1.0,
            width: 512,
            height: 512,
        }
    }
}

impl View {
    /// Checks every field; `max_pixels` bounds `width × height`.
    ///
    /// # Errors
    /// [`ViewError::BadRequest`] naming the field, [`ViewError::TooLarge`] over `max_pixels`.
    pub fn check(&self, max_pixels: u64) -> Result<(), ViewError> {
        let bad = |what: String| Err(ViewError::BadRequest(what));
        if !self.angle_deg.is_finite() {
            return bad(format!(
                "angle {} is not a finite number of degrees",
                self.angle_deg
            ));
        }
        if !(self.elevation_deg.is_finite() && self.elevation_deg.abs() <= 89.0) {
            return bad(format!(
                "elevation {} must be degrees in [-89, 89]",
                self.elevation_deg
            ));
        }
        if !(self.zoom >= ZOOM_RANGE.0 && self.zoom <= ZOOM_RANGE.1) {
            return bad(format!(
                "zoom {} must be in [{}, {}]",
                self.zoom, ZOOM_RANGE.0, ZOOM_RANGE.1
            ));
        }
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if !(1..=MAX_SIDE).contains(&v) {
                return bad(format!("{name} {v} must be in 1..={MAX_SIDE} pixels"));
            }
        }
        let pixels = u64::from(self.width) * u64::from(self.height);
        if pixels > max_pixels {
            return Err(ViewError::TooLarge(format!(
                "image of {}×{} = {pixels} pixels exceeds the server's limit of {max_pixels}",
                self.width, self.height
            )));
        }
        Ok(())
    }

    /// The camera of this view about `generation` (the VDI's own camera).
    pub fn camera(&self, generation: &Camera) -> Camera {
        generation.orbit(self.angle_deg, self.elevation_deg, self.zoom)
    }

    /// The zoom at which this view's direction about `generation` frames `volume_box`, the
    /// box filling [`FIT_MARGIN`] of the image's half extents ([`Camera::fit_zoom`]), within
    /// [`ZOOM_RANGE`]: the viewer's default.
    pub fn fit_zoom(&self, generation: &Camera, volume_box: &insitu_core::volume::Aabb) -> f32 {
        let unzoomed = Self { zoom: 1.0, ..*self }.camera(generation);
        unzoomed
            .fit_zoom(volume_box, self.width, self.height, FIT_MARGIN)
            .clamp(ZOOM_RANGE.0, ZOOM_RANGE.1)
    }
}

/// The VDI file (relative to the recording) that shows `step`: rank `rank`'s when one is
/// asked for (the part holding it when its host composed it with others); else, for a single rank, its VDI, and for a world of ranks the step's composed
/// VDI (all ranks in one picture). `ranks` are the step's stored ranks, `composed` its
/// composed entry if any.
///
/// # Errors
/// [`ViewError::NotFound`] saying what is missing (the step, the rank, or the composition).
pub fn vdi_file(
    step: u64,
    rank: Option<u32>,
    ranks: &[Entry],
    composed: Option<&StepEntry>,
) -> Result<VdiFile, ViewError> {
    let missing = |what: String| ViewError::NotFound(what);
    if ranks.is_empty() && composed.is_none() {
        return Err(missing(format!("step {step} is not in the recording")));
    }
    let mut stored: Vec<u32> = ranks.iter().flat_map(Entry::ranks).collect();
    stored.sort_unstable();
    // A rank is shown by its own VDI, or by the part its host composed it into.
    let of_rank = |r: u32| {
        let own = ranks.iter().find(|e| e.rank == r);
        let e = own
            .or_else(|| ranks.iter().find(|e| e.holds(r)))
            .ok_or_else(|| {
                missing(format!(
                    "step {step} has no rank {r} (stored ranks: {stored:?})"
                ))
            })?;
        let name = e.vdi.clone();
        name.map(|name| VdiFile {
            name,
            expected: e.into(),
        })
        .ok_or_else(|| missing(format!("step {step} rank {r} has no VDI yet")))
    };
    if let Some(r) = rank {
        return of_rank(r);
    }
    let world = world_size(ranks);
    if world <= 1 {
        return of_rank(stored.first().copied().unwrap_or(0));
    }
    composed
        .and_then(|c| {
            c.vdi.clone().map(|name| VdiFile {
                name,
                expected: c.into(),
            })
        })
        .ok_or_else(|| match composed.and_then(|c| c.error.as_deref()) {
            // A step whose ranks cannot compose says why, not that it will later.
            Some(why) => missing(format!(
                "step {step} of {world} ranks cannot be composed: {why} (stored ranks: {stored:?}); ask for one rank"
            )),
            None => missing(format!(
                "step {step} of {world} ranks is not composed yet (stored ranks: {stored:?}); ask for one rank"
            )),
        })
}

/// A VDI file of the recording and what its index row says of it.
#[derive(Clone, Debug, PartialEq)]
pub struct VdiFile {
    /// The file name, relative to the recording.
    pub name: String,
    /// What the row says of it (checked when it is read).
    pub expected: Expected,
}

/// Ranks of the world `ranks` (a step's stored entries) belong to; 1 when none is stored.
pub fn world_size(ranks: &[Entry]) -> u32 {
    ranks.iter().map(|e| e.world_size).max().unwrap_or(1)
}

/// Reads and decodes the VDI file `file` of the recording in `dir`, checked against its row.
///
/// # Errors
/// [`ViewError::Failed`] naming the file (also when it is not the VDI its row describes).
pub fn load_vdi(dir: &Path, file: &VdiFile) -> Result<Vdi, ViewError> {
    insitu_recording::decoded::read_vdi(dir, &file.name, file.expected)
        .map_err(|e| ViewError::Failed(e.to_string()))
}

/// What a frame of `view` is rendered from: with `lod`, the coarsest level of `vdi` still as
/// wide as the frame ([`Vdi::level_for`]; built on first use and kept with `vdi`), else `vdi`.
pub fn level<'a>(vdi: &'a Vdi, view: &View, lod: bool) -> &'a Vdi {
    if lod {
        vdi.level_for(view.width.max(view.height))
    } else {
        vdi
    }
}

/// Renders `vdi` at `view` on `backend` with early termination `termination`, stopped between
/// tiles when `cancel` is set; returns the image and the render's seconds (wall clock, or GPU
/// time on the GPU backend).
///
/// # Errors
/// [`ViewError::BadRequest`] for a bad view, [`ViewError::Failed`] when rendering fails.
pub fn render(
    backend: &Backend,
    vdi: &Vdi,
    view: &View,
    termination: f32,
    cancel: Option<&Cancel>,
) -> Result<(Image, f64), ViewError> {
    view.check(u64::MAX)?;
    let camera = view.camera(&vdi.meta().camera);
    let t = Instant::now();
    let out = backend
        .prepare_vdi(vdi)
        .and_then(|v| v.render_until(&camera, view.width, view.height, termination, cancel))
        .map_err(|e| match e {
            insitu_core::backend::BackendError::Cancelled(_) => ViewError::Cancelled,
            e => ViewError::Failed(format!("rendering: {e}")),
        })?;
    // Wall clock whatever the backend: what a viewer waits for.
    let secs = t.elapsed().as_secs_f64();
    Ok((out.value, secs))
}

/// An image encoding for frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// Lossless 8-bit RGB PNG.
    Png,
    /// Baseline JPEG at a quality in 1..=100.
    Jpeg,
}

impl Format {
    /// The MIME type.
    pub fn mime(self) -> &'static str {
        match self {
            Self::Png => "image/png",
            Self::Jpeg => "image/jpeg",
        }
    }
}

/// Encodes `image` as `format` (`quality` for JPEG, 1..=100).
///
/// # Errors
/// [`ViewError::BadRequest`] for a quality outside 1..=100, [`ViewError::Failed`] when the
/// encoder fails.
pub fn encode(image: &Image, format: Format, quality: u8) -> Result<Vec<u8>, ViewError> {
    let (w, h) = (image.width(), image.height());
    match format {
        Format::Png => {
            let rgb = image::RgbImage::from_raw(w, h, image.to_rgb8())
                .ok_or_else(|| ViewError::Failed("image size mismatch".into()))?;
            let mut out = std::io::Cursor::new(Vec::new());
            rgb.write_to(&mut out, image::ImageFormat::Png)
                .map_err(|e| ViewError::Failed(format!("PNG encoding: {e}")))?;
            Ok(out.into_inner())
        }
        Format::Jpeg => {
            if !(1..=100).contains(&quality) {
                return Err(ViewError::BadRequest(format!(
                    "JPEG quality {quality} must be in 1..=100"
                )));
            }
            let (Ok(w16), Ok(h16)) = (u16::try_from(w), u16::try_from(h)) else {
                return Err(ViewError::BadRequest(format!(
                    "a JPEG frame is at most 65535 pixels a side, not {w}×{h}"
                )));
            };
            // Full-resolution chroma (4:4:4), as `image`'s encoder made them: the same
            // frames, 1.7× faster (3.3 → 1.9 ms for a 384² drag frame).
            let mut jpeg = Vec::new();
            let mut encoder = jpeg_encoder::Encoder::new(&mut jpeg, quality);
            encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::F_1_1);
            encoder
                .encode(&image.to_rgb8(), w16, h16, jpeg_encoder::ColorType::Rgb)
                .map_err(|e| ViewError::Failed(format!("JPEG encoding: {e}")))?;
            Ok(jpeg)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(step: u64, rank: u32, world: u32, vdi: Option<&str>) -> Entry {
        Entry {
            world_size: world,
            vdi: vdi.map(str::to_owned),
            ..Entry::empty(step, rank)
        }
    }

    #[test]
    fn a_view_is_checked_field_by_field() {
        let ok = View::default();
        assert_eq!(ok.check(1 << 20), Ok(()));
        let bad = |v: View| match v.check(1 << 20) {
            Err(ViewError::BadRequest(m)) => m,
            other => panic!("{other:?}"),
        };
        assert!(bad(View {
            angle_deg: f32::NAN,
            ..ok
        })
        .contains("angle"));
        assert!(bad(View {
            elevation_deg: 90.5,
            ..ok
        })
        .contains("elevation"));
        assert!(bad(View { zoom: 0.0, ..ok }).contains("zoom"));
        assert!(bad(View {
            zoom: f32::INFINITY,
            ..ok
        })
        .contains("zoom"));
        assert!(bad(View { width: 0, ..ok }).contains("width"));
        assert!(bad(View {
            height: MAX_SIDE + 1,
            ..ok
        })
        .contains("height"));
        assert!(matches!(
            View {
                width: 2048,
                height: 2048,
                ..ok
            }
            .check(1 << 20),
            Err(ViewError::TooLarge(_))
        ));
        // Zoom 1, no elevation: the generation camera orbited about +y, as the test views.
        let c = Camera::default_for_box(&insitu_core::volume::Aabb {
            min: glam::Vec3::ZERO,
            max: glam::Vec3::ONE,
        });
        let v = View {
            angle_deg: 30.0,
            ..ok
        };
        assert!((v.camera(&c).eye - c.orbit_y(30.0).eye).length() < 1e-5);
    }

    #[test]
    fn the_file_of_a_step_is_its_rank_or_its_composition() {
        let single = [entry(3, 0, 1, Some("s3r0.vdi"))];
        assert_eq!(vdi_file(3, None, &single, None).unwrap().name, "s3r0.vdi");
        assert_eq!(
            vdi_file(3, Some(0), &single, None).unwrap().name,
            "s3r0.vdi"
        );
        let e = vdi_file(3, Some(2), &single, None).unwrap_err();
        assert!(e.to_string().contains("no rank 2"), "{e}");
        let e = vdi_file(9, None, &[], None).unwrap_err();
        assert!(
            e.to_string().contains("step 9 is not in the recording"),
            "{e}"
        );
        let world = [entry(4, 0, 2, Some("r0.vdi")), entry(4, 1, 2, None)];
        let e = vdi_file(4, None, &world, None).unwrap_err();
        assert!(e.to_string().contains("not composed yet"), "{e}");
        let e = vdi_file(4, Some(1), &world, None).unwrap_err();
        assert!(e.to_string().contains("rank 1 has no VDI"), "{e}");
        let composed = StepEntry {
            vdi: Some("c4.vdi".into()),
            ..StepEntry::of_ranks(4, 2, &[], vec![])
        };
        assert_eq!(
            vdi_file(4, None, &world, Some(&composed)).unwrap().name,
            "c4.vdi"
        );
        assert_eq!(
            vdi_file(4, Some(0), &world, Some(&composed)).unwrap().name,
            "r0.vdi"
        );
        // A step that cannot compose says why, not that it will later.
        let failed = StepEntry {
            error: Some("bricks of ranks [0, 1] do not cover the grid".into()),
            ..StepEntry::of_ranks(4, 2, &[], vec![])
        };
        let e = vdi_file(4, None, &world, Some(&failed)).unwrap_err();
        assert!(
            e.to_string()
                .contains("cannot be composed: bricks of ranks [0, 1] do not cover the grid"),
            "{e}"
        );
    }

    #[test]
    fn frames_encode_as_png_and_jpeg_and_a_bad_quality_is_refused() {
        let img = Image::from_pixels(8, 4, vec![[0.25, 0.5, 1.0]; 32]).unwrap();
        let png = encode(&img, Format::Png, 0).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let jpeg = encode(&img, Format::Jpeg, 55).unwrap();
        assert_eq!(&jpeg[..2], &[0xFF, 0xD8]);
        let back = image::load_from_memory(&jpeg).unwrap().to_rgb8();
        assert_eq!(back.dimensions(), (8, 4));
        // The pixels come back, each channel in its place: a smooth gradient with different
        // values per channel, within a JPEG's error at quality 90.
        let gradient = Image::from_pixels(
            64,
            48,
            (0..64 * 48)
                .map(|k| {
                    let (x, y) = ((k % 64) as f32 / 63.0, (k / 64) as f32 / 47.0);
                    [x, y, 0.5 * (1.0 - x)]
                })
                .collect(),
        )
        .unwrap();
        let back = image::load_from_memory(&encode(&gradient, Format::Jpeg, 90).unwrap())
            .unwrap()
            .to_rgb8();
        let original = gradient.to_rgb8();
        let worst = back
            .as_raw()
            .iter()
            .zip(&original)
            .map(|(&a, &b)| a.abs_diff(b))
            .max()
            .unwrap();
        assert!(worst <= 8, "a channel off by {worst}/255");
        assert!(matches!(
            encode(&img, Format::Jpeg, 0),
            Err(ViewError::BadRequest(_))
        ));
    }
}
