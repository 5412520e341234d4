//! A waiting rank's reference frames, held small: each view cut to the window its brick
//! covers ([`frame_window`]: outside it every byte is zero) and zstd-compressed, in buffers of
//! their size. A brick's frame is mostly empty, so a waiting rank holds a few kB instead of
//! views × side² × 16 B, and composing decompresses only the windows.

use bytes::Bytes;
use insitu_core::compose::{frame_from_le_bytes, frame_to_le_bytes, frame_window};
use insitu_core::Image;
use insitu_proto::pb;

/// One view: its window's top-left pixel and size, and the window's RGBA little-endian f32
/// bytes, zstd-compressed.
struct View {
    origin: [u32; 2],
    size: (u32, u32),
    zstd: Vec<u8>,
}

/// A rank's frames, packed ([`PackedFrames::pack`]).
pub struct PackedFrames {
    header: pb::ReferenceHeader,
    views: Vec<View>,
}

/// One frame's window: its top-left pixel, colour and opacity.
pub type Window = ([u32; 2], Image, Vec<f32>);

impl PackedFrames {
    /// The frames of `header` (`bytes`: the views one after another, each `width · height`
    /// pixels of RGBA little-endian f32, as the worker writes them), packed; `None` when the
    /// bytes do not hold whole views or a view does not compress.
    pub fn pack(header: pb::ReferenceHeader, bytes: &[u8]) -> Option<Self> {
        let (w, h) = (header.width, header.height);
        let per_view = w as usize * h as usize * 16;
        if per_view == 0 || bytes.len() != per_view * header.view_angles_deg.len() {
            return None;
        }
        let views = bytes
            .chunks_exact(per_view)
            .map(|view| {
                let (origin, image, opacity) = frame_window((w, h), |p| rgba_at(view, p));
                let raw: Vec<u8> = frame_to_le_bytes(&image, &opacity).collect();
                // zstd's buffer is sized for the worst case: kept, it would hold that much
                // memory per waiting rank.
                let mut zstd = zstd::bulk::compress(&raw, 1).ok()?;
                zstd.shrink_to_fit();
                Some(View {
                    origin,
                    size: (image.width(), image.height()),
                    zstd,
                })
            })
            .collect::<Option<_>>()?;
        Some(Self { header, views })
    }

    /// The frames' header.
    pub fn header(&self) -> &pb::ReferenceHeader {
        &self.header
    }

    /// Bytes held (the compressed windows' buffers).
    pub fn held_bytes(&self) -> usize {
        self.views.iter().map(|v| v.zstd.capacity()).sum()
    }

    /// View `v`'s window; `None` past the views or when it does not decompress.
    pub fn window(&self, v: usize) -> Option<Window> {
        let view = self.views.get(v)?;
        let bytes = self.raw(view)?;
        let (image, opacity) = frame_from_le_bytes(&bytes, view.size)?;
        Some((view.origin, image, opacity))
    }

    /// The frames as they were: header and bytes, byte for byte; no bytes when a view does
    /// not decompress (compressed here from these very bytes, it fails only for want of
    /// memory).
    pub fn unpack(self) -> (pb::ReferenceHeader, Option<Bytes>) {
        let (w, h) = (self.header.width as usize, self.header.height as usize);
        let mut out = vec![0u8; w * h * 16 * self.views.len()];
        for (k, view) in self.views.iter().enumerate() {
            let Some(raw) = self.raw(view) else {
                return (self.header, None);
            };
            let ([x0, y0], (ww, wh)) = (view.origin, view.size);
            let row = ww as usize * 16;
            for (b, src) in raw.chunks_exact(row.max(1)).take(wh as usize).enumerate() {
                let at = k * w * h * 16 + ((y0 as usize + b) * w + x0 as usize) * 16;
                out[at..at + row].copy_from_slice(src);
            }
        }
        (self.header, Some(Bytes::from(out)))
    }

    fn raw(&self, view: &View) -> Option<Vec<u8>> {
        let len = view.size.0 as usize * view.size.1 as usize * 16;
        zstd::bulk::decompress(&view.zstd, len)
            .ok()
            .filter(|b| b.len() == len)
    }
}

/// Pixel `p`'s RGBA of a frame of little-endian f32 (the caller checked the length).
fn rgba_at(bytes: &[u8], p: usize) -> [f32; 4] {
    let at = |k: usize| {
        let o = 16 * p + 4 * k;
        f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]])
    };
    [at(0), at(1), at(2), at(3)]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(views: usize, (w, h): (u32, u32)) -> pb::ReferenceHeader {
        pb::ReferenceHeader {
            width: w,
            height: h,
            view_angles_deg: (0..views).map(|v| 90.0 * v as f32).collect(),
            opacity: true,
            ..Default::default()
        }
    }

    fn frame(values: &[(usize, [f32; 4])], pixels: usize) -> Vec<u8> {
        let mut px = vec![[0.0f32; 4]; pixels];
        for &(p, v) in values {
            px[p] = v;
        }
        px.iter().flatten().flat_map(|c| c.to_le_bytes()).collect()
    }

    /// Views come back byte for byte, whatever their pixels hold (an empty view, −0.0 and
    /// NaN at the window's corners, a full view), and a view's window holds exactly the
    /// pixels that are not all zero bytes.
    #[test]
    fn packed_frames_unpack_byte_for_byte() {
        let size = (7u32, 5u32);
        let n = 35;
        let views = [
            frame(&[], n),
            frame(
                &[
                    (7 + 2, [-0.0, 0.0, 0.0, 0.0]),
                    (21 + 5, [f32::NAN, 0.1, 0.2, 0.5]),
                ],
                n,
            ),
            frame(
                &(0..n)
                    .map(|p| (p, [0.5, 0.25, 1.0, 0.75]))
                    .collect::<Vec<_>>(),
                n,
            ),
        ];
        let bytes: Vec<u8> = views.concat();
        let packed = PackedFrames::pack(header(3, size), &bytes).unwrap();
        let (origin, image, opacity) = packed.window(0).unwrap();
        assert_eq!((origin, image.width(), opacity.len()), ([0, 0], 0, 0));
        let (origin, image, opacity) = packed.window(1).unwrap();
        assert_eq!((origin, image.width(), image.height()), ([2, 1], 4, 3));
        assert_eq!(opacity[opacity.len() - 1], 0.5);
        assert!(image.pixels()[image.pixels().len() - 1][0].is_nan());
        assert_eq!(packed.window(2).unwrap().1.pixels().len(), n);
        assert!(packed.window(3).is_none());
        let (h, back) = packed.unpack();
        assert_eq!(
            (h.view_angles_deg.len(), &back.unwrap()[..]),
            (3, &bytes[..])
        );
        // Bytes that are not whole views are left unpacked.
        assert!(PackedFrames::pack(header(3, size), &bytes[1..]).is_none());
        assert!(PackedFrames::pack(header(2, size), &bytes).is_none());
    }
}
