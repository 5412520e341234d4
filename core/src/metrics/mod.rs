//! Image quality metrics: PSNR (the paper's q, Sec. 5.3) and SSIM.
//!
//! Both compare RGB images with channels in [0, 1] and are computed in f64.
//! - PSNR = `10·log10(1 / MSE)` with the MSE over all pixels and the three channels; identical
//!   images give `+∞` (never NaN). Over several views, [`pooled_psnr`] is the PSNR of the mean
//!   MSE (so one bad view weighs as much as it hurts).
//! - SSIM (Wang et al. 2004) per channel with an 11×11 Gaussian window (σ = 1.5), `K1 = 0.01`,
//!   `K2 = 0.03`, data range 1, population (not sample) covariances, averaged over the pixels
//!   whose window lies inside the image and then over R, G and B. This is scikit-image's
//!   `structural_similarity(a, b, channel_axis=2, data_range=1, gaussian_weights=True,
//!   sigma=1.5, use_sample_covariance=False)`.

use crate::image::Image;

mod ssim;

/// Errors from comparing images.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricError {
    /// The two images differ in size.
    #[error("images differ in size: {0}x{1} vs {2}x{3}")]
    SizeMismatch(u32, u32, u32, u32),
    /// Too small for the metric.
    #[error("image of {0}x{1} is too small: {2}")]
    TooSmall(u32, u32, &'static str),
}

fn check_sizes(a: &Image, b: &Image) -> Result<(), MetricError> {
    if a.width() != b.width() || a.height() != b.height() {
        return Err(MetricError::SizeMismatch(
            a.width(),
            a.height(),
            b.width(),
            b.height(),
        ));
    }
    if a.pixels().is_empty() {
        return Err(MetricError::TooSmall(a.width(), a.height(), "no pixels"));
    }
    Ok(())
}

/// A PSNR in dB that may be `+∞` (identical images); JSON has no infinity, so it is written as
/// the string `"inf"` (and the values no PSNR should take, `−∞` and NaN, as `"-inf"` and
/// `"nan"`, so that they read back as what they were rather than as identical images).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Db(pub f64);

impl serde::Serialize for Db {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        if self.0.is_finite() {
            s.serialize_f64(self.0)
        } else if self.0.is_nan() {
            s.serialize_str("nan")
        } else if self.0 > 0.0 {
            s.serialize_str("inf")
        } else {
            s.serialize_str("-inf")
        }
    }
}

impl<'de> serde::Deserialize<'de> for Db {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Repr {
            Num(f64),
            Str(String),
        }
        match <Repr as serde::Deserialize>::deserialize(d)? {
            Repr::Num(v) => Ok(Db(v)),
            Repr::Str(s) if s == "inf" => Ok(Db(f64::INFINITY)),
            Repr::Str(s) if s == "-inf" => Ok(Db(f64::NEG_INFINITY)),
            Repr::Str(s) if s == "nan" => Ok(Db(f64::NAN)),
            Repr::Str(s) => Err(serde::de::Error::custom(format!(
                "expected a number or \"inf\", got {s:?}"
            ))),
        }
    }
}

/// Mean squared error over all pixels and channels.
///
/// # Errors
/// [`MetricError`] for different sizes or empty images.
pub fn mse(a: &Image, b: &Image) -> Result<f64, MetricError> {
    check_sizes(a, b)?;
    let sum: f64 = a
        .pixels()
        .iter()
        .zip(b.pixels())
        .flat_map(|(p, q)| p.iter().zip(q).map(|(x, y)| f64::from(x - y).powi(2)))
        .sum();
    Ok(sum / (a.pixels().len() * 3) as f64)
}

/// PSNR in dB from an MSE over a unit data range; `+∞` for 0.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse <= 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// PSNR in dB of `test` against `reference`.
///
/// # Errors
/// As [`mse`].
pub fn psnr(test: &Image, reference: &Image) -> Result<f64, MetricError> {
    mse(test, reference).map(psnr_from_mse)
}

/// The MSE a PSNR stands for (the inverse of [`psnr_from_mse`]): `10^(−q/10)`, 0 for `+∞`.
pub fn mse_from_psnr(q_db: f64) -> f64 {
    if q_db == f64::INFINITY {
        0.0
    } else {
        10f64.powf(-q_db / 10.0)
    }
}

/// PSNR of the mean of per-view MSEs (pooled q over the test views); `+∞` for no views.
pub fn pooled_psnr(mses: &[f64]) -> f64 {
    if mses.is_empty() {
        return f64::INFINITY;
    }
    psnr_from_mse(mses.iter().sum::<f64>() / mses.len() as f64)
}

/// Mean SSIM of `test` against `reference` (see the module documentation).
///
/// The window is separable: each of the five fields x, y, x², y² and xy is filtered along the
/// rows, then down the columns, one output row at a time, with the symmetric taps paired
/// (`g[t]·(f[c+t] + f[c+10−t])`). The loops run over contiguous rows, compiled with AVX2 where
/// the CPU has it; both paths do the same f64 operations in the same order, so they agree to
/// the bit (tested). 2.7 ms for a 256² view on this project's 2-core VM, where the window
/// applied pixel by pixel took 8.0 ms (the `teapot_256_scoring/ssim` benchmark).
///
/// # Errors
/// [`MetricError`] for different sizes, or images narrower or lower than 11 pixels.
pub fn ssim(test: &Image, reference: &Image) -> Result<f64, MetricError> {
    check_sizes(test, reference)?;
    let (w, h) = (test.width() as usize, test.height() as usize);
    if w < ssim::TAPS || h < ssim::TAPS {
        return Err(MetricError::TooSmall(
            test.width(),
            test.height(),
            "SSIM needs at least 11x11",
        ));
    }
    let total: f64 = (0..3)
        .map(|ch| ssim::channel(test.pixels(), reference.pixels(), ch, w))
        .sum();
    Ok(total / 3.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn db_reads_back_as_written_infinite_and_nan_included() {
        for (q, text) in [
            (40.5, "40.5"),
            (f64::INFINITY, "\"inf\""),
            (f64::NEG_INFINITY, "\"-inf\""),
            (f64::NAN, "\"nan\""),
        ] {
            let json = serde_json::to_string(&Db(q)).unwrap();
            assert_eq!(json, text);
            let back: Db = serde_json::from_str(&json).unwrap();
            assert!(
                back.0 == q || (q.is_nan() && back.0.is_nan()),
                "{q}: {}",
                back.0
            );
        }
        assert!(serde_json::from_str::<Db>("\"infinite\"").is_err());
    }

    /// The fixed test images; the same formulas are in the Python snippet below.
    fn pattern(w: u32, h: u32, phase: f64) -> Image {
        let mut px = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (xf, yf) = (f64::from(x), f64::from(y));
                let r = 0.5 + 0.5 * (0.3 * xf + phase).sin();
                let g = 0.5 + 0.5 * (0.2 * yf - 0.5 * phase).cos();
                let b = ((xf * yf + 10.0 * phase) % 17.0) / 17.0;
                px.push([r as f32, g as f32, b as f32]);
            }
        }
        Image::from_pixels(w, h, px).unwrap()
    }

    // Reference values from scikit-image 0.26.0 / numpy 2.4.6 with the same images built
    // from the f32-rounded formulas in `pattern`:
    //
    //   import numpy as np; from skimage.metrics import peak_signal_noise_ratio as P, structural_similarity as S
    //   def pat(w,h,ph):
    //     y,x = np.mgrid[0:h,0:w].astype(np.float64)
    //     return np.stack([0.5+0.5*np.sin(0.3*x+ph), 0.5+0.5*np.cos(0.2*y-0.5*ph),
    //                      np.fmod(x*y+10*ph,17)/17], -1).astype(np.float32).astype(np.float64)
    //   a, b = pat(40,32,0.0), pat(40,32,0.4)
    //   P(b, a, data_range=1)
    //   S(a, b, channel_axis=2, data_range=1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    const SKIMAGE_PSNR: f64 = 11.926436420440394;
    const SKIMAGE_SSIM: f64 = 0.5495817299957163;

    #[test]
    fn agrees_with_scikit_image() {
        let (a, b) = (pattern(40, 32, 0.0), pattern(40, 32, 0.4));
        let p = psnr(&b, &a).unwrap();
        let s = ssim(&a, &b).unwrap();
        assert!((p - SKIMAGE_PSNR).abs() < 1e-6, "psnr {p}");
        assert!((s - SKIMAGE_SSIM).abs() < 1e-6, "ssim {s}");
    }

    /// SSIM straight from its definition: for each pixel whose 11×11 window lies inside the
    /// image, the window's Gaussian-weighted moments summed over all 121 taps at once.
    fn ssim_by_definition(a: &Image, b: &Image) -> f64 {
        let (w, h) = (a.width() as usize, a.height() as usize);
        let g1: Vec<f64> = (0..11)
            .map(|i| (-((i as f64 - 5.0).powi(2)) / 4.5).exp())
            .collect();
        let norm: f64 = g1.iter().sum();
        let (c1, c2) = (1e-4, 9e-4);
        let mut total = 0.0;
        for ch in 0..3 {
            let mut sum = 0.0;
            for r in 0..=h - 11 {
                for c in 0..=w - 11 {
                    let mut m = [0.0f64; 5];
                    for (i, gi) in g1.iter().enumerate() {
                        for (j, gj) in g1.iter().enumerate() {
                            let k = (r + i) * w + c + j;
                            let (x, y) =
                                (f64::from(a.pixels()[k][ch]), f64::from(b.pixels()[k][ch]));
                            let wt = gi * gj / (norm * norm);
                            for (mk, v) in m.iter_mut().zip([x, y, x * x, y * y, x * y]) {
                                *mk += wt * v;
                            }
                        }
                    }
                    let [ux, uy, xx, yy, xy] = m;
                    sum += ((2.0 * ux * uy + c1) * (2.0 * (xy - ux * uy) + c2))
                        / ((ux * ux + uy * uy + c1) * (xx - ux * ux + yy - uy * uy + c2));
                }
            }
            total += sum / ((w - 10) * (h - 10)) as f64;
        }
        total / 3.0
    }

    #[test]
    fn separable_ssim_matches_the_windows_definition_at_odd_sizes() {
        // 11×11 (one window), widths that leave vector tails, heights that wrap the ring of
        // rows several times.
        for (w, h) in [(11, 11), (12, 31), (37, 19), (70, 45)] {
            let (a, b) = (pattern(w, h, 0.0), pattern(w, h, 0.7));
            let (fast, slow) = (ssim(&a, &b).unwrap(), ssim_by_definition(&a, &b));
            assert!((fast - slow).abs() < 1e-12, "{w}x{h}: {fast} vs {slow}");
        }
    }

    #[test]
    fn identical_images_give_inf_and_one() {
        let a = pattern(16, 12, 1.0);
        assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
        let black = Image::new(16, 12);
        assert!((ssim(&black, &black).unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(pooled_psnr(&[0.0, 0.0]), f64::INFINITY);
    }

    #[test]
    fn pooled_is_psnr_of_mean_mse() {
        let q = pooled_psnr(&[1e-4, 1e-2]);
        assert!((q - psnr_from_mse(0.00505)).abs() < 1e-12);
        for mse in [0.0, 1e-9, 0.00505, 1.0] {
            assert!((mse_from_psnr(psnr_from_mse(mse)) - mse).abs() <= 1e-15 + mse * 1e-12);
        }
        // Black vs white: MSE 1, PSNR 0.
        let mut white = Image::new(4, 4);
        white.pixels_mut().iter_mut().for_each(|p| *p = [1.0; 3]);
        assert_eq!(psnr(&Image::new(4, 4), &white).unwrap(), 0.0);
    }

    #[test]
    fn errors_on_bad_sizes() {
        assert!(matches!(
            psnr(&Image::new(2, 2), &Image::new(2, 3)),
            Err(MetricError::SizeMismatch(..))
        ));
        assert!(matches!(
            ssim(&Image::new(10, 20), &Image::new(10, 20)),
            Err(MetricError::TooSmall(..))
        ));
        assert!(psnr(&Image::new(0, 0), &Image::new(0, 0)).is_err());
    }
}
