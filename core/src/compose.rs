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
    } else if a.step.to_bits() != b.step.to_bits() {
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

/// Composes the sub-VDIs of one step (one per rank, any order) into the VDI of the union of
/// their boxes: per pixel, the ranks' lists ordered by their first supersegment's depth and
/// concatenated (see the module docs for touching supersegments). The result's metadata is
/// part 0's with the union box.
///
/// Time `O(r · parts + r · Σ_rows (parts with content in the row) + supersegments)`, rows in
/// parallel: a rank whose VDI is empty (a transparent brick) costs `r` comparisons, and a rank
/// costs per-pixel work only in the rows its brick covers with content.
///
/// # Errors
/// [`ComposeError::Empty`] for no parts; [`ComposeError::Mismatch`] when a part differs from
/// part 0 in camera, `P_M`, transfer function, step, termination or shading;
/// [`ComposeError::TooLarge`] past `u32::MAX` supersegments.
pub fn compose_vdis(parts: &[&Vdi]) -> Result<Vdi, ComposeError> {
    let first = parts.first().ok_or(ComposeError::Empty)?;
    for (part, v) in parts.iter().enumerate().skip(1) {
        if let Some(what) = mismatch(first.meta(), v.meta()) {
            return Err(ComposeError::Mismatch { part, what });
        }
    }
    let total: u64 = parts.iter().map(|v| v.supersegments().len() as u64).sum();
    if total > u64::from(u32::MAX) {
        return Err(ComposeError::TooLarge(total));
    }
    let r = first.resolution() as usize;
    // The parts with anything in row j: a rank's brick covers a part of the image, and an
    // empty brick none, so the per-pixel work follows the content, not the number of ranks.
    let row_parts: Vec<Vec<&Vdi>> = (0..r)
        .map(|j| {
            parts
                .iter()
                .copied()
                .filter(|v| v.offsets()[(j + 1) * r] > v.offsets()[j * r])
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
            for p in r * j..r * (j + 1) {
                if offsets[p] != offsets[p + 1] {
                    at += compose_pixel(&row_parts[j], p, order, &mut row[at..]);
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
fn composed_offsets(row_parts: &[Vec<&Vdi>], r: usize) -> Vec<u32> {
    let mut offsets = Vec::with_capacity(r * r + 1);
    offsets.push(0u32);
    let mut sum = 0u32;
    for (j, active) in row_parts.iter().enumerate() {
        for p in r * j..r * (j + 1) {
            sum += active.iter().map(|v| v.count(p)).sum::<u32>();
            offsets.push(sum);
        }
    }
    offsets
}

/// Writes pixel `p`'s composed list to the start of `out` and returns its length: the lists
/// of `parts` at `p`, ordered by their first supersegment's depth (`order` is scratch) and
/// concatenated, each supersegment that starts before the previous one's end moved to start
/// there (see the module docs).
fn compose_pixel<'v>(
    parts: &[&'v Vdi],
    p: usize,
    order: &mut Vec<&'v [Supersegment]>,
    out: &mut [Supersegment],
) -> usize {
    order.clear();
    order.extend(parts.iter().filter_map(|v| {
        let (a, b) = (v.offsets()[p] as usize, v.offsets()[p + 1] as usize);
        (a < b).then(|| &v.supersegments()[a..b])
    }));
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

/// One brick's frame at one view: colour (premultiplied, black background), accumulated
/// opacity per pixel (`width · height`, row-major from the top), and the brick's world box.
#[derive(Clone, Copy, Debug)]
pub struct BrickFrame<'a> {
    /// The brick's rendering.
    pub image: &'a Image,
    /// Its accumulated opacity per pixel, in [0, 1].
    pub opacity: &'a [f32],
    /// The brick's world box.
    pub world_box: Aabb,
}

impl<'a> From<&'a (Image, Vec<f32>, Aabb)> for BrickFrame<'a> {
    /// A brick's frame from its rendering with opacity ([`crate::dvr::render_with_opacity`])
    /// and its world box.
    fn from((image, opacity, world_box): &'a (Image, Vec<f32>, Aabb)) -> Self {
        Self {
            image,
            opacity,
            world_box: *world_box,
        }
    }
}

/// Composites the frames of a step's bricks, all rendered from `camera` at the same size,
/// into the frame of the whole domain and its opacity: per pixel, front to back in the order
/// in which the pixel's ray enters the bricks' boxes (exact for disjoint convex boxes; see
/// the module docs). Pixels whose ray misses a box take nothing from that brick.
///
/// # Errors
/// [`ComposeError::Empty`] for no frames; [`ComposeError::Frame`] when sizes differ or an
/// opacity plane does not have one value per pixel.
pub fn compose_frames(
    camera: &Camera,
    frames: &[BrickFrame],
) -> Result<(Image, Vec<f32>), ComposeError> {
    let first = frames.first().ok_or(ComposeError::Empty)?;
    let (w, h) = (first.image.width(), first.image.height());
    for (part, f) in frames.iter().enumerate() {
        if f.image.width() != w || f.image.height() != h {
            return Err(ComposeError::Frame {
                part,
                problem: format!("{}×{} beside {w}×{h}", f.image.width(), f.image.height()),
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
        let p = i as usize + w as usize * j as usize;
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
            acc.over(f.image.pixels()[p], f.opacity[p]);
        }
        acc.finish()
    });
    let (rgb, opacity): (Vec<[f32; 3]>, Vec<f32>) = pixels.into_iter().unzip();
    let image = Image::from_pixels(w, h, rgb).unwrap_or_else(|| Image::new(w, h));
    Ok((image, opacity))
}
