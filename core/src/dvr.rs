//! Reference direct volume rendering (DVR) of the original data: `I(S_A, P_I) → Õ` in the
//! paper's notation (Alg. 1, line 15; Sec. 5.3).
//!
//! Front-to-back emission–absorption compositing of the [`Raycaster`]'s samples with opacity
//! correction, early ray termination and empty-space skipping, parallel over image tiles.

use crate::camera::{Camera, ViewFrame};
use crate::image::Image;
use crate::raycast::{Raycaster, Sample};
use rayon::prelude::*;
use std::ops::ControlFlow;

/// Tile side in pixels for the parallel loop.
pub(crate) const TILE: u32 = 16;

/// Renders `camera`'s view at `width × height`; background black.
pub fn render(raycaster: &Raycaster, camera: &Camera, width: u32, height: u32) -> Image {
    let frame = camera.frame(width, height);
    let termination = raycaster.params().termination;
    render_tiles(&frame, |i, j| {
        let ray = frame.pixel_ray(i, j);
        let mut color = [0.0f32; 3];
        let mut transmittance = 1.0f32;
        raycaster.march(&ray, |s: &Sample| {
            let w = transmittance * s.alpha;
            for (c, s) in color.iter_mut().zip(s.rgb) {
                *c += w * s;
            }
            transmittance *= 1.0 - s.alpha;
            if 1.0 - transmittance >= termination {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        });
        color.map(|c| c.clamp(0.0, 1.0))
    })
}

/// Evaluates `shade(i, j)` for every pixel of `frame`, tiles in parallel.
pub(crate) fn render_tiles(
    frame: &ViewFrame,
    shade: impl Fn(u32, u32) -> [f32; 3] + Sync,
) -> Image {
    let (w, h) = (frame.width, frame.height);
    let tiles_x = w.div_ceil(TILE);
    let tiles = tiles_x * h.div_ceil(TILE);
    let results: Vec<(u32, u32, Vec<[f32; 3]>)> = (0..tiles)
        .into_par_iter()
        .map(|t| {
            let (x0, y0) = ((t % tiles_x) * TILE, (t / tiles_x) * TILE);
            let (x1, y1) = ((x0 + TILE).min(w), (y0 + TILE).min(h));
            let mut px = Vec::with_capacity(((x1 - x0) * (y1 - y0)) as usize);
            for j in y0..y1 {
                for i in x0..x1 {
                    px.push(shade(i, j));
                }
            }
            (x0, y0, px)
        })
        .collect();
    let mut image = Image::new(w, h);
    let pixels = image.pixels_mut();
    for (x0, y0, px) in results {
        let tw = ((x0 + TILE).min(w) - x0) as usize;
        for (row, chunk) in px.chunks(tw).enumerate() {
            let dst = x0 as usize + w as usize * (y0 as usize + row);
            pixels[dst..dst + tw].copy_from_slice(chunk);
        }
    }
    image
}
