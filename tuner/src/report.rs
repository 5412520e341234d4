//! A study table as CSV (one row per `P_M`) and JSON.

use crate::measure::Measurement;

/// CSV with a header; q is `inf` when the images were identical. `precision` is `f32` or the
/// colour bits; `sigma_paper_bytes` the same VDI as floats under bzip2 (empty where σ is
/// that already).
pub fn csv(rows: &[Measurement]) -> String {
    let mut out = String::from(
        "r,gamma,precision,sigma_bytes,sigma_paper_bytes,supersegments,tau_secs,tau_compress_secs,tau_render_secs,q_db,ssim\n",
    );
    for m in rows {
        out.push_str(&format!(
            "{},{},{},{},{},{},{:.6},{:.6},{:.6},{},{}\n",
            m.r,
            m.gamma,
            m.precision.name(),
            m.sizing.sigma_bytes,
            m.sigma_paper_bytes
                .map_or_else(String::new, |s| s.to_string()),
            m.sizing.supersegments,
            m.sizing.tau_secs,
            m.sizing.tau_compress_secs,
            m.tau_render_secs,
            if m.q().is_finite() {
                format!("{:.4}", m.q())
            } else {
                "inf".into()
            },
            m.ssim.map_or_else(String::new, |s| format!("{s:.5}")),
        ));
    }
    out
}

/// JSON array of the rows.
///
/// # Errors
/// Never in practice (plain data); the serializer's error otherwise.
pub fn json(rows: &[Measurement]) -> Result<String, serde_json::Error> {
    serde_json::to_string_pretty(rows)
}
