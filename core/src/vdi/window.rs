//! A sub-VDI cropped to its footprint: the lists of the smallest pixel rectangle holding every
//! non-empty list of a [`Vdi`] (docs/scale.md, "Memory").
//!
//! A rank's brick covers a part of the generation image, often a small one (a brick of a
//! 256-rank grid projects to a few percent of it), yet its [`Vdi`] keeps `r² + 1` list offsets
//! whatever the brick's size. A host that holds its ranks' sub-VDIs until their step composes
//! keeps them as windows instead: the offsets of the footprint and the supersegments, in a
//! buffer of exactly their size. Composing reads a window as it reads the VDI
//! ([`crate::compose::PixelLists`]), so the result is the same bit for bit.

use super::{Supersegment, Vdi, VdiMeta};

/// The lists of a [`Vdi`] inside the pixel rectangle `[x0, x0 + width) × [y0, y0 + height)`
/// that holds all of its supersegments (pixels outside hold empty lists).
#[derive(Clone, Debug, PartialEq)]
pub struct VdiWindow {
    meta: VdiMeta,
    x0: usize,
    y0: usize,
    width: usize,
    height: usize,
    /// `width · height + 1` prefix offsets, pixel `(x0 + a, y0 + b)` at `a + width · b`.
    offsets: Vec<u32>,
    supersegments: Vec<Supersegment>,
}

impl VdiWindow {
    /// The window of `vdi`: its footprint's lists, copied into buffers of exactly their size
    /// (`width = height = 0` for a VDI without supersegments). Time `O(r² + supersegments)`.
    pub fn crop(vdi: &Vdi) -> Self {
        let r = vdi.resolution() as usize;
        let offsets = vdi.offsets();
        let (mut x0, mut y0, mut x1, mut y1) = (r, r, 0, 0);
        for j in 0..r {
            let row = &offsets[r * j..=r * (j + 1)];
            if row[0] == row[r] {
                continue;
            }
            y0 = y0.min(j);
            y1 = j + 1;
            // The row's first and last non-empty pixel.
            if let Some(a) = row.windows(2).position(|w| w[0] < w[1]) {
                x0 = x0.min(a);
            }
            if let Some(b) = row.windows(2).rposition(|w| w[0] < w[1]) {
                x1 = x1.max(b + 1);
            }
        }
        let (width, height) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        let mut window_offsets = Vec::with_capacity(width * height + 1);
        window_offsets.push(0u32);
        let mut supersegments = Vec::new();
        if width > 0 && height > 0 {
            let first = offsets[x0 + r * y0] as usize;
            let last = offsets[x1 - 1 + r * (y1 - 1) + 1] as usize;
            supersegments.reserve_exact(last - first);
            for j in y0..y1 {
                let (a, b) = (x0 + r * j, x1 + r * j);
                for p in a..b {
                    window_offsets.push(offsets[p + 1] - first as u32);
                }
                supersegments.extend_from_slice(
                    &vdi.supersegments()[offsets[a] as usize..offsets[b] as usize],
                );
            }
            // Pixels between rows' rectangles (left of x0, right of x1) hold nothing, so the
            // rows' slices follow one another without gaps in the VDI's flat array.
            debug_assert_eq!(supersegments.len(), last - first);
        }
        Self {
            meta: vdi.meta().clone(),
            x0: if width > 0 { x0 } else { 0 },
            y0: if height > 0 { y0 } else { 0 },
            width,
            height,
            offsets: window_offsets,
            supersegments,
        }
    }

    /// Generation metadata (the VDI's).
    pub fn meta(&self) -> &VdiMeta {
        &self.meta
    }

    /// The footprint `(x0, y0, width, height)`, pixels (`width = height = 0` when empty).
    pub fn rect(&self) -> (usize, usize, usize, usize) {
        (self.x0, self.y0, self.width, self.height)
    }

    /// All supersegments, pixel after pixel of the footprint.
    pub fn supersegments(&self) -> &[Supersegment] {
        &self.supersegments
    }

    /// Whether row `j` of the image holds no supersegment.
    pub fn row_is_empty(&self, j: usize) -> bool {
        if j < self.y0 || j >= self.y0 + self.height {
            return true;
        }
        let b = j - self.y0;
        self.offsets[self.width * b] == self.offsets[self.width * (b + 1)]
    }

    /// The depth-ordered list of pixel `(i, j)` of the `r × r` image (empty outside the
    /// footprint).
    #[inline]
    pub fn list(&self, i: usize, j: usize) -> &[Supersegment] {
        if i < self.x0 || j < self.y0 || i >= self.x0 + self.width || j >= self.y0 + self.height {
            return &[];
        }
        let q = (i - self.x0) + self.width * (j - self.y0);
        &self.supersegments[self.offsets[q] as usize..self.offsets[q + 1] as usize]
    }

    /// Bytes held in memory by the lists (against [`Vdi::memory_bytes`]'s `4 (r² + 1)` for
    /// the offsets).
    pub fn memory_bytes(&self) -> usize {
        self.offsets.len() * 4 + self.supersegments.len() * std::mem::size_of::<Supersegment>()
    }

    /// The whole VDI again (`r² + 1` offsets).
    pub fn to_vdi(&self) -> Vdi {
        let r = self.meta.params.resolution as usize;
        let mut offsets = Vec::with_capacity(r * r + 1);
        offsets.push(0u32);
        let mut sum = 0u32;
        for j in 0..r {
            for i in 0..r {
                sum += self.list(i, j).len() as u32;
                offsets.push(sum);
            }
        }
        Vdi {
            meta: self.meta.clone(),
            offsets,
            supersegments: self.supersegments.clone(),
            derived: Default::default(),
        }
    }
}
