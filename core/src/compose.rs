//! Many ranks, one picture: the sub-VDIs and the reference frames of a step's bricks
//! composed into those of the whole domain (docs/conventions.md, "A world of ranks").
//!
//! All ranks of a step share the generation camera, and their bricks are boxes whose
//! interiors are disjoint (neighbours share at most their boundary plane). A ray meets
//! disjoint convex boxes in disjoint parameter intervals, so along one generation ray the
//! ranks' supersegment lists occupy disjoint depth ranges, and their merge, ordered by depth,
//! is the list the whole domain would have had (up to where the samples fall). Where two
//! bricks share a plane, the front brick's last supersegment and the back brick's first may
//! touch: both are kept, and a start that rounding puts before the previous end is moved to
//! that end (the codec's invariant `z_start ≥ previous z_end`), so nothing is composited twice.
//!
//! Reference frames are composited per pixel front to back, `C += T·Cᵢ`, `T ·= 1 − Aᵢ`, with
//! the bricks ordered by where the pixel's ray enters each brick's box. For disjoint convex
//! boxes that order is exact for every camera, perspective included, and it needs no global
//! visibility sort (a perspective camera can see axis-aligned bricks in an order that no
//! single per-axis rule gives when the eye is inside the grid's extent on some axis).

use crate::camera::Camera;
use crate::image::Image;
use crate::raycast::FrontToBack;
use crate::vdi::window::VdiWindow;
use crate::vdi::{Supersegment, Vdi, VdiMeta};
use crate::volume::Aabb;
use rayon::prelude::*;

/// Why sub-VDIs or frames cannot be composed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ComposeError {
    /// Nothing to compose.
    #[error("nothing to compose")]
    Empty,
    /// A part was made differently from the first part.
    #[error("part {part} differs from part 0 in {what}")]
    Mismatch {
        /// Index of the part in the input.
        part: usize,
        /// What differs (camera, P_M, step, …).
        what: &'static str,
    },
    /// The composed VDI would hold more than `u32::MAX` supersegments.
    #[error("{0} supersegments in all: more than one VDI holds")]
    TooLarge(u64),
    /// Frames of different sizes, or opacity planes that do not match their frames.
    #[error("frame {part}: {problem}")]
    Frame {
        /// Index of the frame.
        part: usize,
        /// What is wrong.
        problem: String,
    },
}

/// What must agree between the parts of one step's VDI (the transfer function's name may
/// differ only if its identity agrees, so it is not compared).
fn mismatch(a: &VdiMeta, b: &VdiMeta) -> Option<&'static str> {
    if a.camera != b.camera {
        Some("generation camera")
    } else if a.params != b.params {
        Some("P_M (r, γ)")
    } else if a.tf_hash != b.tf_hash {
        Some("transfer function")
    } else if a.sample_distance.to_bits() != b.sample_distance.to_bits() {
        Some("ray-casting step")
    } else if a.termination.to_bits() != b.termination.to_bits() {
        Some("termination")
    } else if a.shaded != b.shaded {
        Some("shading")
    } else {
        None
    }
}

/// The smallest box holding all `boxes` (the first when there is one).
pub fn union_box(boxes: impl IntoIterator<Item = Aabb>) -> Option<Aabb> {
    boxes.into_iter().reduce(|a, b| Aabb {
        min: a.min.min(b.min),
        max: a.max.max(b.max),
    })
}

/// What composing reads of a sub-VDI: its metadata and the list of each pixel. A [`Vdi`]
/// and a [`VdiWindow`] (a sub-VDI cropped to its footprint) give the same lists, so they
/// compose to the same VDI bit for bit.
pub trait PixelLists: Sync {
    /// Generation metadata.
    fn meta(&self) -> &VdiMeta;
    /// Supersegments in all.
    fn supersegment_count(&self) -> usize;
    /// Whether row `j` (from the top) holds no supersegment.
    fn row_is_empty(&self, j: usize) -> bool;
    /// The depth-ordered list of pixel `(i, j)`.
    fn list(&self, i: usize, j: usize) -> &[Supersegment];
}

impl PixelLists for Vdi {
    fn meta(&self) -> &VdiMeta {
        Vdi::meta(self)
    }
    fn supersegment_count(&self) -> usize {
        self.supersegments().len()
    }
    fn row_is_empty(&self, j: usize) -> bool {
        let r = self.resolution() as usize;
        self.offsets()[(j + 1) * r] == self.offsets()[j * r]
    }
    #[inline]
    fn list(&self, i: usize, j: usize) -> &[Supersegment] {
        self.pixel(i as u32, j as u32)
    }
}

impl PixelLists for VdiWindow {
    fn meta(&self) -> &VdiMeta {
        VdiWindow::meta(self)
    }
    fn supersegment_count(&self) -> usize {
        self.supersegments().len()
    }
    fn row_is_empty(&self, j: usize) -> bool {
        VdiWindow::row_is_empty(self, j)
    }
    #[inline]
    fn list(&self, i: usize, j: usize) -> &[Supersegment] {
        VdiWindow::list(self, i, j)
    }
}

/// Composes the sub-VDIs of one step (one per rank, any order; whole VDIs or windows,
/// [`PixelLists`]) into the VDI of the union of their boxes: per pixel, the ranks' lists
/// ordered by their first supersegment's depth and concatenated (see the module docs for
/// touching supersegments). The result's metadata is part 0's with the union box.
///
/// Time `O(r · parts + r · Σ_rows (parts with content in the row) + supersegments)`, rows in
/// parallel: a rank whose VDI is empty (a transparent brick) costs `r` comparisons, and a rank
/// costs per-pixel work only in the rows its brick covers with content.
///
/// # Errors
/// [`ComposeError::Empty`] for no parts; [`ComposeError::Mismatch`] when a part differs from
/// part 0 in camera, `P_M`, transfer function, step, termination or shading;
/// [`ComposeError::TooLarge`] past `u32::MAX` supersegments.
pub fn compose_vdis<L: PixelLists>(parts: &[&L]) -> Result<Vdi, ComposeError> {
    let first = parts.first().ok_or(ComposeError::Empty)?;
    for (part, v) in parts.iter().enumerate().skip(1) {
        if let Some(what) = mismatch(first.meta(), v.meta()) {
            return Err(ComposeError::Mismatch { part, what });
        }
    }
    let total: u64 = parts.iter().map(|v| v.supersegment_count() as u64).sum();
    if total > u64::from(u32::MAX) {
        return Err(ComposeError::TooLarge(total));
    }
    let r = first.meta().params.resolution as usize;
    // The parts with anything in row j: a rank's brick covers a part of the image, and an
    // empty brick none, so the per-pixel work follows the content, not the number of ranks.
    let row_parts: Vec<Vec<&L>> = (0..r)
        .map(|j| {
            parts
                .iter()
                .copied()
                .filter(|v| !v.row_is_empty(j))
                .collect()
        })
        .collect();
    let offsets = composed_offsets(&row_parts, r);
    let mut flat = vec![Supersegment::default(); total as usize];
    // Split the flat array into one slice per row, then fill rows in parallel.
    let mut rows: Vec<(usize, &mut [Supersegment])> = Vec::with_capacity(r);
    let mut rest = flat.as_mut_slice();
    for j in 0..r {
        let n = (offsets[(j + 1) * r] - offsets[j * r]) as usize;
        let (row, tail) = rest.split_at_mut(n);
        rows.push((j, row));
        rest = tail;
    }
    rows.into_par_iter()
        .filter(|(_, row)| !row.is_empty())
        .for_each_init(Vec::new, |order, (j, row)| {
            let mut at = 0;
            for i in 0..r {
                let p = i + r * j;
                if offsets[p] != offsets[p + 1] {
                    at += compose_pixel(&row_parts[j], i, j, order, &mut row[at..]);
                }
            }
        });
    let mut meta = first.meta().clone();
    meta.volume_box =
        union_box(parts.iter().map(|v| v.meta().volume_box)).unwrap_or(meta.volume_box);
    Vdi::from_parts(meta, offsets, flat).ok_or(ComposeError::Empty)
}

/// The composed VDI's list offsets (`r² + 1`, as [`Vdi::offsets`]): each pixel's list is
/// the sum of its lists in the parts with content in its row (`row_parts[j]` for row `j`).
/// The caller checked that the total fits a `u32`.
fn composed_offsets<L: PixelLists>(row_parts: &[Vec<&L>], r: usize) -> Vec<u32> {
    let mut offsets = Vec::with_capacity(r * r + 1);
    offsets.push(0u32);
    let mut sum = 0u32;
    for (j, active) in row_parts.iter().enumerate() {
        for i in 0..r {
            sum += active
                .iter()
                .map(|v| v.list(i, j).len() as u32)
                .sum::<u32>();
            offsets.push(sum);
        }
    }
    offsets
}

/// Writes pixel `(i, j)`'s composed list to the start of `out` and returns its length: the
/// lists of `parts` there, ordered by their first supersegment's depth (`order` is scratch)
/// and concatenated, each supersegment that starts before the previous one's end moved to
/// start there (see the module docs).
fn compose_pixel<'v, L: PixelLists>(
    parts: &[&'v L],
    i: usize,
    j: usize,
    order: &mut Vec<&'v [Supersegment]>,
    out: &mut [Supersegment],
) -> usize {
    order.clear();
    order.extend(parts.iter().map(|v| v.list(i, j)).filter(|l| !l.is_empty()));
    order.sort_unstable_by(|a, b| a[0].z_start.total_cmp(&b[0].z_start));
    let mut prev_end = f32::NEG_INFINITY;
    let segments = order.iter().flat_map(|list| list.iter());
    for (out, s) in out.iter_mut().zip(segments) {
        let mut s = *s;
        if s.z_start < prev_end {
            s.z_start = prev_end;
            s.z_end = s.z_end.max(prev_end);
        }
        prev_end = s.z_end;
        *out = s;
    }
    order.iter().map(|list| list.len()).sum()
}

/// One brick's frame at one view: colour (premultiplied, black background) and accumulated
/// opacity per pixel (`image`'s `width · height`, row-major from the top) of the window of
/// the frame whose top-left pixel is `origin` (the whole frame at `[0, 0]`; pixels outside
/// the window are transparent), and the brick's world box.
#[derive(Clone, Copy, Debug)]
pub struct BrickFrame<'a> {
    /// The brick's rendering, or the window of it that holds every pixel it covers.
    pub image: &'a Image,
    /// Its accumulated opacity per pixel, in [0, 1].
    pub opacity: &'a [f32],
    /// The window's top-left pixel in the frame, `[column, row]`.
    pub origin: [u32; 2],
    /// The brick's world box.
    pub world_box: Aabb,
}

impl<'a> From<&'a (Image, Vec<f32>, Aabb)> for BrickFrame<'a> {
    /// A brick's whole frame from its rendering with opacity
    /// ([`crate::dvr::render_with_opacity`]) and its world box.
    fn from((image, opacity, world_box): &'a (Image, Vec<f32>, Aabb)) -> Self {
        Self {
            image,
            opacity,
            origin: [0, 0],
            world_box: *world_box,
        }
    }
}

/// The window of a frame (`rgba`: `width · height` pixels of colour and opacity) that holds
/// every pixel with a value whose bits are not all zero, `(origin, image, opacity)`; an empty
/// window at `[0, 0]` when there is none. Outside the window every value is `+0.0`, so the
/// frame can be rebuilt from the window byte for byte, and compositing the window is
/// compositing the frame, bit for bit (a pixel of colour 0 and opacity 0 leaves the
/// front-to-back sum as it was).
pub fn frame_window(
    (width, height): (u32, u32),
    rgba: impl Fn(usize) -> [f32; 4],
) -> ([u32; 2], Image, Vec<f32>) {
    let (w, h) = (width as usize, height as usize);
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for j in 0..h {
        for i in 0..w {
            if rgba(i + w * j).iter().any(|&c| c.to_bits() != 0) {
                (x0, x1) = (x0.min(i), x1.max(i + 1));
                (y0, y1) = (y0.min(j), y1.max(j + 1));
            }
        }
    }
    if x1 <= x0 || y1 <= y0 {
        return ([0, 0], Image::new(0, 0), Vec::new());
    }
    let (ww, wh) = (x1 - x0, y1 - y0);
    let mut rgb = Vec::with_capacity(ww * wh);
    let mut opacity = Vec::with_capacity(ww * wh);
    for j in y0..y1 {
        for i in x0..x1 {
            let [r, g, b, a] = rgba(i + w * j);
            rgb.push([r, g, b]);
            opacity.push(a);
        }
    }
    let image = Image::from_pixels(ww as u32, wh as u32, rgb).unwrap_or_else(|| Image::new(0, 0));
    ([x0 as u32, y0 as u32], image, opacity)
}

/// [`frame_window`] of a frame rendered with its opacity ([`crate::dvr::render_with_opacity`]).
pub fn window_of(image: &Image, opacity: &[f32]) -> ([u32; 2], Image, Vec<f32>) {
    frame_window((image.width(), image.height()), |p| {
        let [r, g, b] = image.pixels()[p];
        [r, g, b, opacity[p]]
    })
}

/// A frame's colour and opacity as little-endian f32 RGBA, row-major (16 bytes per pixel):
/// how brick frames travel between nodes ([`frame_from_le_bytes`] reads them back).
pub fn frame_to_le_bytes<'a>(
    image: &'a Image,
    opacity: &'a [f32],
) -> impl Iterator<Item = u8> + 'a {
    image
        .pixels()
        .iter()
        .zip(opacity)
        .flat_map(|(c, a)| [c[0], c[1], c[2], *a])
        .flat_map(f32::to_le_bytes)
}

/// A `w × h` frame of little-endian f32 RGBA ([`frame_to_le_bytes`]) as an image and its
/// opacity plane; `None` when the bytes are not that many pixels.
pub fn frame_from_le_bytes(bytes: &[u8], (w, h): (u32, u32)) -> Option<(Image, Vec<f32>)> {
    if bytes.len() != w as usize * h as usize * 16 {
        return None;
    }
    let (rgb, opacity) = bytes
        .chunks_exact(16)
        .map(|px| {
            let at = |k: usize| {
                f32::from_le_bytes([px[4 * k], px[4 * k + 1], px[4 * k + 2], px[4 * k + 3]])
            };
            ([at(0), at(1), at(2)], at(3))
        })
        .unzip();
    Some((Image::from_pixels(w, h, rgb)?, opacity))
}

/// Composites the frames of a step's bricks, all rendered from `camera` at `width × height`
/// (whole or as windows, [`BrickFrame::origin`]), into the frame of the whole domain and its
/// opacity: per pixel, front to back in the order in which the pixel's ray enters the
/// bricks' boxes (exact for disjoint convex boxes; see the module docs). Pixels whose ray
/// misses a box, or outside a brick's window, take nothing from that brick.
///
/// # Errors
/// [`ComposeError::Empty`] for no frames; [`ComposeError::Frame`] when a window does not lie
/// inside the frame or an opacity plane does not have one value per pixel.
pub fn compose_frames(
    camera: &Camera,
    (w, h): (u32, u32),
    frames: &[BrickFrame],
) -> Result<(Image, Vec<f32>), ComposeError> {
    if frames.is_empty() {
        return Err(ComposeError::Empty);
    }
    for (part, f) in frames.iter().enumerate() {
        let [ox, oy] = f.origin;
        let (fw, fh) = (f.image.width(), f.image.height());
        if u64::from(ox) + u64::from(fw) > u64::from(w)
            || u64::from(oy) + u64::from(fh) > u64::from(h)
        {
            return Err(ComposeError::Frame {
                part,
                problem: format!("{fw}×{fh} at ({ox}, {oy}) outside {w}×{h}"),
            });
        }
        if f.opacity.len() != f.image.pixels().len() {
            return Err(ComposeError::Frame {
                part,
                problem: format!(
                    "{} opacity values for {} pixels",
                    f.opacity.len(),
                    f.image.pixels().len()
                ),
            });
        }
    }
    let frame = camera.frame(w, h);
    let pixels = crate::dvr::tiles(&frame, |i, j| {
        let ray = frame.pixel_ray(i, j);
        let inv = ray.dir.recip();
        let mut order: Vec<(f32, usize)> = Vec::with_capacity(frames.len());
        for (k, f) in frames.iter().enumerate() {
            let (t0, t1) = f.world_box.intersect(ray.origin, inv);
            if t0 <= t1 && t1 >= 0.0 {
                order.push((t0.max(0.0), k));
            }
        }
        order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        // Every frame is composed: no termination.
        let mut acc = FrontToBack::new(1.0);
        for &(_, k) in &order {
            let f = &frames[k];
            let (x, y) = (i.wrapping_sub(f.origin[0]), j.wrapping_sub(f.origin[1]));
            if x < f.image.width() && y < f.image.height() {
                let p = x as usize + f.image.width() as usize * y as usize;
                acc.over(f.image.pixels()[p], f.opacity[p]);
            }
        }
        acc.finish()
    });
    let (rgb, opacity): (Vec<[f32; 3]>, Vec<f32>) = pixels.into_iter().unzip();
    let image = Image::from_pixels(w, h, rgb).unwrap_or_else(|| Image::new(w, h));
    Ok((image, opacity))
}
