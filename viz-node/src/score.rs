//! q of a stored VDI: render it at the test views of its step's reference frames and compare
//! (Alg. 1, lines 13–17: PSNR per view, pooled as the PSNR of the mean MSE; SSIM beside it).

use crate::store::{Db, Quality, References};
use insitu_core::metrics::{self, MetricError};
use insitu_core::vdi::render;
use insitu_core::Vdi;

/// Renders `vdi` at each view of `refs` (same size as the frames) and scores it.
///
/// # Errors
/// [`MetricError`] when a frame's size does not match (cannot happen for frames built by
/// [`References::from_bytes`]).
pub fn score(vdi: &Vdi, refs: &References, termination: f32) -> Result<Quality, MetricError> {
    let mut view_mse = Vec::with_capacity(refs.frames.len());
    let mut ssims = Vec::new();
    for (&angle, reference) in refs.view_angles_deg.iter().zip(&refs.frames) {
        let image = render::render(
            vdi,
            &refs.camera.orbit_y(angle),
            reference.width(),
            reference.height(),
            termination,
        );
        view_mse.push(metrics::mse(&image, reference)?);
        if let Ok(s) = metrics::ssim(&image, reference) {
            ssims.push(s);
        }
    }
    Ok(Quality {
        q_db: Db(metrics::pooled_psnr(&view_mse)),
        view_q_db: view_mse
            .iter()
            .map(|&m| Db(metrics::psnr_from_mse(m)))
            .collect(),
        ssim: (!ssims.is_empty() && ssims.len() == view_mse.len())
            .then(|| ssims.iter().sum::<f64>() / ssims.len() as f64),
        view_mse,
    })
}
