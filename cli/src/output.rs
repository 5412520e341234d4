//! Output files written atomically: a temporary file in the target's folder, renamed into
//! place only when complete, so a failure never leaves a partial file behind.

use anyhow::{Context, Result};
use insitu_core::Image;
use std::io::Write;
use std::path::Path;

/// Writes `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("cannot create a file in {}", dir.display()))?;
    tmp.write_all(bytes)
        .and_then(|()| tmp.as_file().sync_all())
        .with_context(|| format!("cannot write {}", path.display()))?;
    tmp.persist(path)
        .with_context(|| format!("cannot move the output into place at {}", path.display()))?;
    Ok(())
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
