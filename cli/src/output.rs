//! Output files written atomically: a temporary file in the target's folder, renamed into
//! place only when complete, so a failure never leaves a partial file behind.

use anyhow::{Context, Result};
use insitu_core::Image;
use std::path::Path;

/// Writes `bytes` to `path` atomically and durably ([`insitu_core::file::write_atomic`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    insitu_core::file::write_atomic(path, bytes, insitu_core::file::Durability::PowerLoss)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Encodes `image` as an 8-bit RGB PNG and writes it atomically.
pub fn write_png(path: &Path, image: &Image) -> Result<()> {
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(
            &image.to_rgb8(),
            image.width(),
            image.height(),
            image::ExtendedColorType::Rgb8,
        )
        .with_context(|| format!("cannot encode PNG for {}", path.display()))?;
    write_atomic(path, &bytes)
}

use image::ImageEncoder as _;
