//! The SSIM kernel behind [`super::ssim`]: one channel's mean SSIM, the 11×11 Gaussian window
//! applied as two passes of 11 taps over contiguous rows.

// `target_feature` functions are `unsafe` to call; this module is one of the workspace's few
// exceptions to `unsafe_code = "deny"` and exposes only a safe function: the AVX2 build of the
// kernel runs only behind an [`Avx2`] token (proof of detection).
#![allow(unsafe_code)]

#[cfg(target_arch = "x86_64")]
use crate::raycast::Avx2;

const RADIUS: usize = 5;
const SIGMA: f64 = 1.5;
/// Taps of the SSIM window.
pub(super) const TAPS: usize = 2 * RADIUS + 1;

fn gaussian_window() -> [f64; TAPS] {
    let mut w = [0.0; TAPS];
    for (i, v) in w.iter_mut().enumerate() {
        let x = i as f64 - RADIUS as f64;
        *v = (-x * x / (2.0 * SIGMA * SIGMA)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// Mean SSIM of channel `ch` (0–2) of two `w`-wide images of the same size, at least 11×11.
pub(super) fn channel(test: &[[f32; 3]], reference: &[[f32; 3]], ch: usize, w: usize) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if let Some(avx2) = Avx2::detect() {
        // SAFETY: the token proves that this CPU has AVX2.
        return unsafe { channel_avx2(avx2, test, reference, ch, w) };
    }
    kernel(test, reference, ch, w)
}

/// [`kernel`] compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn channel_avx2(
    _: Avx2,
    test: &[[f32; 3]],
    reference: &[[f32; 3]],
    ch: usize,
    w: usize,
) -> f64 {
    kernel(test, reference, ch, w)
}

/// `out[c] = Σ_t g[t]·tap(t)[c]` for every `c` of `out`, with the taps `t` and `10 − t`
/// paired (`g` is symmetric). `tap(t)` is the input shifted by `t`, at least `out.len()` long:
/// a row from its `t`-th element (along a row), or the `t`-th row below (down the columns).
#[inline(always)]
fn filter<'a>(g: &[f64; TAPS], tap: impl Fn(usize) -> &'a [f64], out: &mut [f64]) {
    for (o, &v) in out.iter_mut().zip(tap(RADIUS)) {
        *o = g[RADIUS] * v;
    }
    for (t, &gt) in g.iter().enumerate().take(RADIUS) {
        for ((o, &u), &v) in out.iter_mut().zip(tap(t)).zip(tap(TAPS - 1 - t)) {
            *o += gt * (u + v);
        }
    }
}

/// Mean SSIM of channel `ch` over the pixels whose window lies inside the `w`-wide images.
/// Each image row's five fields are filtered along the row into a ring of the last 11 such
/// rows (five planes of `11 × (w − 10)`, small enough to stay in cache); once 11 are there,
/// they are filtered down the columns into the window's moments for one output row, and the
/// SSIM formula is summed over it per column.
#[inline(always)]
fn kernel(test: &[[f32; 3]], reference: &[[f32; 3]], ch: usize, w: usize) -> f64 {
    let g = gaussian_window();
    let (c1, c2) = ((0.01f64).powi(2), (0.03f64).powi(2));
    let h = test.len() / w;
    let (ow, oh) = (w - TAPS + 1, h - TAPS + 1);
    let mut ring: [Vec<f64>; 5] = std::array::from_fn(|_| vec![0.0; TAPS * ow]);
    let mut fields: [Vec<f64>; 5] = std::array::from_fn(|_| vec![0.0; w]);
    let mut moments: [Vec<f64>; 5] = std::array::from_fn(|_| vec![0.0; ow]);
    let mut sums = vec![0.0; ow];
    for row in 0..h {
        let span = row * w..(row + 1) * w;
        for (col, (a, b)) in test[span.clone()].iter().zip(&reference[span]).enumerate() {
            let (x, y) = (f64::from(a[ch]), f64::from(b[ch]));
            fields[0][col] = x;
            fields[1][col] = y;
            fields[2][col] = x * x;
            fields[3][col] = y * y;
            fields[4][col] = x * y;
        }
        let slot = row % TAPS;
        for (plane, field) in ring.iter_mut().zip(&fields) {
            filter(&g, |t| &field[t..], &mut plane[slot * ow..(slot + 1) * ow]);
        }
        // Rows `row − 10 ..= row` are in the ring: the moments of output row `row − 10`.
        let Some(top) = (row + 1).checked_sub(TAPS) else {
            continue;
        };
        for (m, plane) in moments.iter_mut().zip(&ring) {
            filter(&g, |t| &plane[((top + t) % TAPS) * ow..], m);
        }
        let [ux, uy, xx, yy, xy] = &moments;
        for (c, sum) in sums.iter_mut().enumerate() {
            let (ux, uy) = (ux[c], uy[c]);
            let (vx, vy, vxy) = (xx[c] - ux * ux, yy[c] - uy * uy, xy[c] - ux * uy);
            *sum += ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
        }
    }
    sums.iter().sum::<f64>() / (ow * oh) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AVX2 build of the kernel (where this CPU has AVX2) and the portable one do the same
    /// f64 operations in the same order: every channel's SSIM agrees to the bit.
    #[test]
    fn the_avx2_kernel_agrees_with_the_portable_one_to_the_bit() {
        let (w, h) = (37usize, 29usize);
        let image = |phase: f32| -> Vec<[f32; 3]> {
            (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f32, (i / w) as f32);
                    [
                        0.5 + 0.5 * (0.3 * x + phase).sin(),
                        0.5 + 0.5 * (0.2 * y - phase).cos(),
                        ((x * y + 10.0 * phase) % 17.0) / 17.0,
                    ]
                })
                .collect()
        };
        let (a, b) = (image(0.0), image(0.4));
        for ch in 0..3 {
            let (dispatched, portable) = (channel(&a, &b, ch, w), kernel(&a, &b, ch, w));
            assert!(portable > -1.0 && portable < 1.0, "{portable}");
            assert_eq!(dispatched.to_bits(), portable.to_bits(), "channel {ch}");
        }
    }
}
