//! Reference direct volume rendering (DVR) of the original data: `I(S_A, P_I) → Õ` in the
//! paper's notation (Alg. 1, line 15; Sec. 5.3).
//!
//! Front-to-back emission–absorption compositing of the [`Raycaster`]'s samples with opacity
//! correction, early ray termination and empty-space skipping, parallel over image tiles.

use crate::camera::{Camera, ViewFrame};
use crate::cancel::{Cancel, Cancelled};
use crate::image::Image;
use crate::raycast::{Coverage, FrontToBack, Raycaster};
use rayon::prelude::*;

/// Tile side in pixels for the parallel loop.
pub(crate) const TILE: u32 = 16;

/// Renders `camera`'s view at `width × height`; background black.
pub fn render(raycaster: &Raycaster, camera: &Camera, width: u32, height: u32) -> Image {
    raycaster.prepare(width as usize * height as usize);
    let frame = camera.frame(width, height);
    let pixels = tiles(&frame, marched(raycaster, &frame, |m| m.0));
    Image::from_pixels(width, height, pixels).unwrap_or_else(|| Image::new(width, height))
}

/// [`render`] with each pixel's accumulated opacity `A = 1 − T` beside it (`width · height`
/// values in [0, 1], row-major from the top): what front-to-back compositing of several
/// bricks' frames needs ([`crate::compose::compose_frames`]).
pub fn render_with_opacity(
    raycaster: &Raycaster,
    camera: &Camera,
    width: u32,
    height: u32,
) -> (Image, Vec<f32>) {
    raycaster.prepare(width as usize * height as usize);
    let frame = camera.frame(width, height);
    let pixels = tiles(&frame, marched(raycaster, &frame, |m| m));
    let (rgb, opacity): (Vec<[f32; 3]>, Vec<f32>) = pixels.into_iter().unzip();
    let image = Image::from_pixels(width, height, rgb).unwrap_or_else(|| Image::new(width, height));
    (image, opacity)
}

/// `(i, j) → pick(colour, opacity)` of pixel `(i, j)`, marched only where the visible macro
/// cells cover the view ([`Coverage`]): the other rays would composite nothing, so their
/// pixels are `pick(([0; 3], 0))` at once.
fn marched<'a, P>(
    raycaster: &'a Raycaster,
    frame: &'a ViewFrame,
    pick: impl Fn(([f32; 3], f32)) -> P + Sync + 'a,
) -> impl Fn(u32, u32) -> P + Sync + 'a {
    let coverage = Coverage::new(raycaster, frame);
    move |i, j| {
        if coverage.covers(i, j) {
            pick(march(raycaster, frame, i, j))
        } else {
            pick(([0.0; 3], 0.0))
        }
    }
}

/// Colour and opacity of pixel `(i, j)`: front-to-back compositing up to early termination.
#[inline]
fn march(raycaster: &Raycaster, frame: &ViewFrame, i: u32, j: u32) -> ([f32; 3], f32) {
    let acc = FrontToBack::new(raycaster.params().termination);
    raycaster
        .march_fold(&frame.pixel_ray(i, j), acc, |acc, s| acc.add(s))
        .finish()
}

/// Evaluates `shade(i, j)` for every pixel of `frame` and returns the pixels row-major from
/// the top. Parallel over bands of `TILE` rows, each walked in `TILE × TILE` tiles (neighbouring
/// rays, neighbouring voxels), written straight into the one output buffer: no per-tile
/// allocation, so a large image costs one buffer, which goes back to the system when dropped
/// (per-tile vectors spread over the worker threads' heaps would stay resident after large
/// renders). [`blocks`] with one pixel a block, written out: the DVR's per-pixel march
/// measures 10–15 % slower behind a block's buffer.
pub(crate) fn tiles<P: Copy + Default + Send>(
    frame: &ViewFrame,
    shade: impl Fn(u32, u32) -> P + Sync,
) -> Vec<P> {
    let (w, h) = (frame.width, frame.height);
    let mut pixels = vec![P::default(); w as usize * h as usize];
    if w == 0 {
        return pixels;
    }
    pixels
        .par_chunks_mut(w as usize * TILE as usize)
        .enumerate()
        .for_each(|(band, rows)| {
            let y0 = band as u32 * TILE;
            let y1 = (y0 + TILE).min(h);
            for x0 in (0..w).step_by(TILE as usize) {
                let x1 = (x0 + TILE).min(w);
                for j in y0..y1 {
                    let row = &mut rows[((j - y0) * w) as usize..][..w as usize];
                    for i in x0..x1 {
                        row[i as usize] = shade(i, j);
                    }
                }
            }
        });
    pixels
}

/// Evaluates the pixels of `frame` a block at a time: each `TILE × TILE` tile (corner
/// `(x0, y0)`) in blocks of `shape(x0, y0) = (bw, bh)` pixels (`bw` and `bh` divide [`TILE`]),
/// `shade(i0, j0, (bw, bh), out)` filling `out` (`bw·bh` pixels, row-major) for pixels
/// `i0..i0 + bw` × `j0..j0 + bh`, those outside the frame ignored; returns the pixels
/// row-major from the top. Parallel over bands of `TILE` rows, each written straight into the
/// one output buffer, as [`tiles`]. `cancel`, read before each tile, stops the work: the
/// pixels left are then the default, and the caller discards them.
pub(crate) fn blocks<P: Copy + Default + Send>(
    frame: &ViewFrame,
    shape: impl Fn(u32, u32) -> (u32, u32) + Sync,
    shade: impl Fn(u32, u32, (u32, u32), &mut [P]) + Sync,
    cancel: Option<&Cancel>,
) -> Vec<P> {
    let (w, h) = (frame.width, frame.height);
    let mut pixels = vec![P::default(); w as usize * h as usize];
    if w == 0 {
        return pixels;
    }
    pixels
        .par_chunks_mut(w as usize * TILE as usize)
        .enumerate()
        .for_each(|(band, rows)| {
            let y0 = band as u32 * TILE;
            let y1 = (y0 + TILE).min(h);
            let mut block = Vec::new();
            for x0 in (0..w).step_by(TILE as usize) {
                if cancel.is_some_and(Cancel::is_cancelled) {
                    return;
                }
                let x1 = (x0 + TILE).min(w);
                let (bw, bh) = shape(x0, y0);
                debug_assert!(bw > 0 && bh > 0 && TILE % bw == 0 && TILE % bh == 0);
                block.resize((bw * bh) as usize, P::default());
                for by in (y0..y1).step_by(bh as usize) {
                    for bx in (x0..x1).step_by(bw as usize) {
                        shade(bx, by, (bw, bh), &mut block);
                        for b in 0..bh.min(y1 - by) {
                            let row = &mut rows[((by + b - y0) * w) as usize..][..w as usize];
                            for a in 0..bw.min(x1 - bx) {
                                row[(bx + a) as usize] = block[(a + bw * b) as usize];
                            }
                        }
                    }
                }
            }
        });
    pixels
}

/// [`blocks`] of RGB pixels as an [`Image`].
#[cfg(test)]
pub(crate) fn render_blocks(
    frame: &ViewFrame,
    shape: impl Fn(u32, u32) -> (u32, u32) + Sync,
    shade: impl Fn(u32, u32, (u32, u32), &mut [[f32; 3]]) + Sync,
) -> Image {
    render_blocks_until(frame, shape, shade, None).unwrap_or_else(|_| Image::new(0, 0))
}

/// [`render_blocks`] stopped between tiles when `cancel` is set.
///
/// # Errors
/// [`Cancelled`] when it was.
pub(crate) fn render_blocks_until(
    frame: &ViewFrame,
    shape: impl Fn(u32, u32) -> (u32, u32) + Sync,
    shade: impl Fn(u32, u32, (u32, u32), &mut [[f32; 3]]) + Sync,
    cancel: Option<&Cancel>,
) -> Result<Image, Cancelled> {
    let pixels = blocks(frame, shape, shade, cancel);
    if cancel.is_some_and(Cancel::is_cancelled) {
        return Err(Cancelled);
    }
    Ok(Image::from_pixels(frame.width, frame.height, pixels)
        .unwrap_or_else(|| Image::new(frame.width, frame.height)))
}
