//! Linear RGB images in [0, 1], row 0 at the top.

/// A `width × height` RGB image, linear, each channel in [0, 1], row-major from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    width: u32,
    height: u32,
    pixels: Vec<[f32; 3]>,
}

impl Image {
    /// A black image.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![[0.0; 3]; width as usize * height as usize],
        }
    }

    /// Wraps pixels; `None` if the length is not `width · height`.
    pub fn from_pixels(width: u32, height: u32, pixels: Vec<[f32; 3]>) -> Option<Self> {
        (pixels.len() == width as usize * height as usize).then_some(Self {
            width,
            height,
            pixels,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Pixels, row-major from the top.
    pub fn pixels(&self) -> &[[f32; 3]] {
        &self.pixels
    }

    /// Mutable pixels.
    pub fn pixels_mut(&mut self) -> &mut [[f32; 3]] {
        &mut self.pixels
    }

    /// Pixel at column `x`, row `y`.
    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        self.pixels[x as usize + self.width as usize * y as usize]
    }

    /// The pixels as little-endian f32 RGB, row-major (12 bytes per pixel): the wire and file
    /// layout of reference frames.
    pub fn to_f32_le(&self) -> Vec<u8> {
        self.pixels
            .iter()
            .flatten()
            .flat_map(|c| c.to_le_bytes())
            .collect()
    }

    /// The inverse of [`Image::to_f32_le`]; `None` unless `bytes` holds exactly
    /// `width · height` pixels, each channel finite and in [0, 1].
    pub fn from_f32_le(width: u32, height: u32, bytes: &[u8]) -> Option<Self> {
        if bytes.len() != width as usize * height as usize * 12 {
            return None;
        }
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if values.iter().any(|v| !(0.0..=1.0).contains(v)) {
            return None;
        }
        Self::from_pixels(
            width,
            height,
            values.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        )
    }

    /// 8-bit RGB bytes (value × 255, rounded, clamped), row-major: what a PNG stores.
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.pixels
            .iter()
            .flat_map(|p| p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8))
            .collect()
    }

    /// Whether every channel is finite and in [0, 1].
    pub fn is_valid(&self) -> bool {
        self.pixels
            .iter()
            .flatten()
            .all(|c| c.is_finite() && (0.0..=1.0).contains(c))
    }

    /// Stacks images into a grid of `rows` × `cols` (row-major); images must share a size.
    /// Returns `None` on a size mismatch or a wrong count.
    pub fn grid(images: &[&Image], cols: usize) -> Option<Image> {
        let first = images.first()?;
        let (w, h) = (first.width as usize, first.height as usize);
        if cols == 0
            || images
                .iter()
                .any(|i| i.width as usize != w || i.height as usize != h)
        {
            return None;
        }
        let rows = images.len().div_ceil(cols);
        let mut out = Image::new((w * cols) as u32, (h * rows) as u32);
        let out_w = w * cols;
        for (n, img) in images.iter().enumerate() {
            let (ox, oy) = ((n % cols) * w, (n / cols) * h);
            for y in 0..h {
                let dst = (oy + y) * out_w + ox;
                out.pixels[dst..dst + w].copy_from_slice(&img.pixels[y * w..(y + 1) * w]);
            }
        }
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f32_bytes_round_trip_and_refuse_bad_values() {
        let im = Image::from_pixels(2, 1, vec![[0.0, 0.5, 1.0], [0.25, 0.125, 1e-7]]).unwrap();
        let b = im.to_f32_le();
        assert_eq!(b.len(), 24);
        assert_eq!(Image::from_f32_le(2, 1, &b), Some(im));
        assert!(Image::from_f32_le(2, 1, &b[..20]).is_none());
        let mut nan = b.clone();
        nan[..4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(Image::from_f32_le(2, 1, &nan).is_none());
        nan[..4].copy_from_slice(&1.5f32.to_le_bytes());
        assert!(Image::from_f32_le(2, 1, &nan).is_none());
    }

    #[test]
    fn grid_places_tiles() {
        let mut a = Image::new(2, 1);
        a.pixels_mut()[1] = [1.0, 0.0, 0.0];
        let b = Image::new(2, 1);
        let g = Image::grid(&[&a, &b, &b, &a], 2).unwrap();
        assert_eq!((g.width(), g.height()), (4, 2));
        assert_eq!(g.get(1, 0), [1.0, 0.0, 0.0]);
        assert_eq!(g.get(3, 1), [1.0, 0.0, 0.0]);
        assert_eq!(g.get(1, 1), [0.0; 3]);
        assert!(Image::grid(&[&a, &Image::new(3, 1)], 2).is_none());
        assert_eq!(a.to_rgb8(), vec![0, 0, 0, 255, 0, 0]);
    }
}
