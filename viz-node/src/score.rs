//! q of a stored VDI: render it at the test views of its step's reference frames and compare
//! (Alg. 1, lines 13–17, through [`insitu_core::evaluate::score_views`]: PSNR per view, pooled
//! as the PSNR of the mean MSE; SSIM beside it).

use insitu_core::evaluate::{mean_ssim, score_views, EvalError};
use insitu_core::metrics;
use insitu_core::{Backend, Vdi};
use insitu_recording::store::{Db, Quality, References};

/// Renders `vdi` on `backend` at each view of `refs` (same size as the frames) and scores it.
///
/// # Errors
/// [`EvalError`] when the frames do not match the views (cannot happen for frames built by
/// [`References::from_bytes`]) or the backend fails.
pub fn score(
    backend: &Backend,
    vdi: &Vdi,
    refs: &References,
    termination: f32,
) -> Result<Quality, EvalError> {
    let (views, _, _) = score_views(
        &backend.prepare_vdi(vdi)?,
        &refs.camera,
        &refs.view_angles_deg,
        &refs.frames,
        termination,
    )?;
    let view_mse: Vec<f64> = views.iter().map(|v| v.mse).collect();
    Ok(Quality {
        q_db: Db(metrics::pooled_psnr(&view_mse)),
        view_q_db: views.iter().map(|v| Db(v.q_db)).collect(),
        ssim: mean_ssim(&views),
        view_mse,
    })
}
