//! The charts people open first, as PNG with a bundled font (DejaVu Sans,
//! `assets/`), so nothing depends on the system's fonts:
//!
//! - [`study_map`]: the Fig. 7 map — γ across, r up; each candidate a disc whose colour is q,
//!   whose area is σ and whose rim brightness is τ;
//! - [`pareto`]: q against σ and q against τ, every candidate with its Pareto front;
//! - [`ladder`]: Fig. 8 — the best q per size budget, grid and adaptive search;
//! - [`accuracy`]: q against τ for each knob of the accuracy sweep.

use crate::accuracy::AccuracyRow;
use crate::measure::Measurement;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use std::path::Path;
use std::sync::OnceLock;

const FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");
const W: u32 = 1200;
const H: u32 = 800;

/// Errors drawing or writing a chart.
#[derive(Debug, thiserror::Error)]
pub enum ChartError {
    /// Drawing failed.
    #[error("drawing {path}: {message}")]
    Draw {
        /// The file.
        path: String,
        /// Why.
        message: String,
    },
    /// Nothing to draw.
    #[error("nothing to draw in {0}: no rows with a finite q")]
    Empty(String),
    /// Writing failed.
    #[error("writing {path}: {source}")]
    Write {
        /// The file.
        path: String,
        /// Why.
        source: image::ImageError,
    },
}

fn font() {
    static DONE: OnceLock<()> = OnceLock::new();
    DONE.get_or_init(|| {
        // The bundled font is valid; if registration failed, text would be missing, not wrong.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

fn draw(
    path: &Path,
    f: impl FnOnce(DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>) -> Result<(), String>,
) -> Result<(), ChartError> {
    font();
    let mut buf = vec![255u8; (W * H * 3) as usize];
    let name = path.display().to_string();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (W, H)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| ChartError::Draw {
            path: name.clone(),
            message: e.to_string(),
        })?;
        f(root.clone()).map_err(|message| ChartError::Draw {
            path: name.clone(),
            message,
        })?;
        root.present().map_err(|e| ChartError::Draw {
            path: name.clone(),
            message: e.to_string(),
        })?;
    }
    let img = image::RgbImage::from_raw(W, H, buf).ok_or_else(|| ChartError::Draw {
        path: name.clone(),
        message: "buffer size".into(),
    })?;
    img.save(path)
        .map_err(|source| ChartError::Write { path: name, source })
}

/// A compact axis label: 3 significant digits.
fn short(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let digits = (2 - v.abs().log10().floor() as i32).max(0) as usize;
    format!("{v:.digits$}")
}

fn finite_q(rows: &[Measurement]) -> Vec<&Measurement> {
    rows.iter().filter(|m| m.q().is_finite()).collect()
}

fn range(v: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
        (lo.min(x), hi.max(x))
    });
    if hi > lo {
        (lo, hi)
    } else {
        (lo - 1.0, lo + 1.0)
    }
}

/// The study map (Fig. 7). Rows with `q = ∞` are drawn with the highest colour.
///
/// # Errors
/// [`ChartError`].
pub fn study_map(rows: &[Measurement], title: &str, path: &Path) -> Result<(), ChartError> {
    let fin = finite_q(rows);
    if fin.is_empty() {
        return Err(ChartError::Empty(path.display().to_string()));
    }
    let (qlo, qhi) = range(fin.iter().map(|m| m.q()));
    let (glo, ghi) = range(rows.iter().map(|m| f64::from(m.gamma)));
    let (rlo, rhi) = range(rows.iter().map(|m| f64::from(m.r)));
    let (_, tmax) = range(rows.iter().map(|m| m.sizing.tau_secs));
    let smax = rows
        .iter()
        .map(|m| m.sizing.sigma_bytes)
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    let (gpad, rpad) = ((ghi - glo) * 0.04, (rhi - rlo) * 0.05);
    draw(path, |root| {
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("{title} — colour: q {qlo:.1}–{qhi:.1} dB · area: σ ≤ {:.2} MB · rim: τ ≤ {tmax:.2} s", smax / 1e6),
                ("sans-serif", 18),
            )
            .margin(20)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d((glo - gpad)..(ghi + gpad), (rlo - rpad)..(rhi + rpad))
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("γ (interrupt threshold)")
            .y_desc("r (VDI resolution, pixels per side)")
            .label_style(("sans-serif", 16))
            .draw()
            .map_err(|e| e.to_string())?;
        let rs: std::collections::BTreeSet<u32> = rows.iter().map(|m| m.r).collect();
        let gs: std::collections::BTreeSet<u32> = rows.iter().map(|m| m.gamma.to_bits()).collect();
        let cell_px = ((W as f64 - 150.0) / gs.len().max(1) as f64)
            .min((H as f64 - 150.0) / rs.len().max(1) as f64);
        let rmax_px = (cell_px * 0.5).clamp(2.0, 40.0);
        chart
            .draw_series(rows.iter().map(|m| {
                let t = ((m.q().min(qhi) - qlo) / (qhi - qlo)).clamp(0.0, 1.0);
                let fill = ViridisRGB::get_color(t as f32);
                let radius =
                    (rmax_px * (m.sizing.sigma_bytes as f64 / smax).sqrt()).max(3.0) as i32;
                let rim = (255.0 * (m.sizing.tau_secs / tmax.max(1e-12)).clamp(0.0, 1.0)) as u8;
                let at = (f64::from(m.gamma), f64::from(m.r));
                EmptyElement::at(at)
                    + Circle::new((0, 0), radius, fill.filled())
                    + Circle::new((0, 0), radius, RGBColor(rim, rim, rim).stroke_width(1))
            }))
            .map_err(|e| e.to_string())?;
        Ok(())
    })
}

type Axis = fn(&Measurement) -> f64;

fn legend<'a, CT: plotters::coord::CoordTranslate>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, CT>,
) -> Result<(), String> {
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .label_font(("sans-serif", 16))
        .border_style(BLACK)
        .draw()
        .map_err(|e| e.to_string())
}

fn front(points: &mut [(f64, f64)]) -> Vec<(f64, f64)> {
    points.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut best = f64::NEG_INFINITY;
    points
        .iter()
        .filter(|p| {
            let keep = p.1 > best;
            best = best.max(p.1);
            keep
        })
        .copied()
        .collect()
}

/// q against σ (MB, log scale) and against τ (s), with the Pareto fronts.
///
/// # Errors
/// [`ChartError`].
pub fn pareto(rows: &[Measurement], title: &str, path: &Path) -> Result<(), ChartError> {
    let fin = finite_q(rows);
    if fin.is_empty() {
        return Err(ChartError::Empty(path.display().to_string()));
    }
    let (qlo, qhi) = range(fin.iter().map(|m| m.q()));
    draw(path, |root| {
        let panels = root.split_evenly((1, 2));
        let axes: [(&str, Axis); 2] = [
            ("σ (compressed VDI, MB)", |m| {
                m.sizing.sigma_bytes as f64 / 1e6
            }),
            ("τ (generation, s)", |m| m.sizing.tau_secs),
        ];
        for (area, (label, x)) in panels.iter().zip(axes) {
            let (xlo, xhi) = range(fin.iter().map(|m| x(m)));
            let mut chart = ChartBuilder::on(area)
                .caption(
                    format!("{title}: q vs {}", label.split(' ').next().unwrap_or("")),
                    ("sans-serif", 22),
                )
                .margin(20)
                .x_label_area_size(50)
                .y_label_area_size(60)
                .build_cartesian_2d(
                    (xlo.max(1e-9) * 0.9..xhi * 1.1).log_scale(),
                    (qlo - 1.0)..(qhi + 1.0),
                )
                .map_err(|e| e.to_string())?;
            chart
                .configure_mesh()
                .x_labels(6)
                .x_label_formatter(&|v| short(*v))
                .x_desc(label)
                .y_desc("q (pooled PSNR, dB)")
                .label_style(("sans-serif", 16))
                .draw()
                .map_err(|e| e.to_string())?;
            chart
                .draw_series(
                    fin.iter()
                        .map(|m| Circle::new((x(m), m.q()), 3, RGBColor(120, 120, 120).filled())),
                )
                .map_err(|e| e.to_string())?;
            let mut pts: Vec<(f64, f64)> = fin.iter().map(|m| (x(m), m.q())).collect();
            chart
                .draw_series(LineSeries::new(front(&mut pts), RED.stroke_width(3)))
                .map_err(|e| e.to_string())?
                .label("Pareto front")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(3)));
            legend(&mut chart)?;
        }
        Ok(())
    })
}

/// One step of a budget ladder: the target and the q of each strategy's choice.
#[derive(Clone, Debug)]
pub struct LadderPoint {
    /// σ_target, bytes.
    pub sigma_target: u64,
    /// Grid optimum (r, γ, q).
    pub grid: (u32, f32, f64),
    /// Adaptive optimum (r, γ, q), if run.
    pub adaptive: Option<(u32, f32, f64)>,
}

/// Fig. 8: best q per size budget, labelled with the chosen (r, γ).
///
/// # Errors
/// [`ChartError`].
pub fn ladder(points: &[LadderPoint], title: &str, path: &Path) -> Result<(), ChartError> {
    let fin: Vec<&LadderPoint> = points.iter().filter(|p| p.grid.2.is_finite()).collect();
    if fin.is_empty() {
        return Err(ChartError::Empty(path.display().to_string()));
    }
    let (slo, shi) = range(fin.iter().map(|p| p.sigma_target as f64 / 1e6));
    let (qlo, qhi) = range(
        fin.iter()
            .flat_map(|p| [Some(p.grid.2), p.adaptive.map(|a| a.2)])
            .flatten()
            .filter(|q| q.is_finite()),
    );
    draw(path, |root| {
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("{title}: best q per size budget σ_target (each 1.5× the previous)"),
                ("sans-serif", 22),
            )
            .margin(20)
            .x_label_area_size(50)
            .y_label_area_size(60)
            .build_cartesian_2d(
                (slo * 0.8..shi * 1.25).log_scale(),
                (qlo - 1.0)..(qhi + 1.5),
            )
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_labels(6)
            .x_label_formatter(&|v| short(*v))
            .x_desc("σ_target (MB)")
            .y_desc("q of the chosen P_M (dB)")
            .label_style(("sans-serif", 16))
            .draw()
            .map_err(|e| e.to_string())?;
        let blue = RGBColor(30, 90, 200);
        chart
            .draw_series(LineSeries::new(
                fin.iter().map(|p| (p.sigma_target as f64 / 1e6, p.grid.2)),
                blue.stroke_width(2),
            ))
            .map_err(|e| e.to_string())?
            .label("grid (the paper)")
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], blue.stroke_width(2))
            });
        chart
            .draw_series(fin.iter().map(|p| {
                EmptyElement::at((p.sigma_target as f64 / 1e6, p.grid.2))
                    + Circle::new((0, 0), 4, blue.filled())
                    + Text::new(
                        format!("r {} γ {:.3}", p.grid.0, p.grid.1),
                        (6, 6),
                        ("sans-serif", 13),
                    )
            }))
            .map_err(|e| e.to_string())?;
        let adaptive: Vec<(f64, f64)> = fin
            .iter()
            .filter_map(|p| p.adaptive.map(|a| (p.sigma_target as f64 / 1e6, a.2)))
            .collect();
        if !adaptive.is_empty() {
            chart
                .draw_series(
                    adaptive
                        .iter()
                        .map(|&(x, y)| Cross::new((x, y), 7, RED.stroke_width(2))),
                )
                .map_err(|e| e.to_string())?
                .label("adaptive")
                .legend(|(x, y)| Cross::new((x + 10, y), 6, RED.stroke_width(2)));
        }
        legend(&mut chart)?;
        Ok(())
    })
}

/// q against τ for each knob of an accuracy sweep (rows without a finite q are left out).
///
/// # Errors
/// [`ChartError`].
pub fn accuracy(rows: &[AccuracyRow], title: &str, path: &Path) -> Result<(), ChartError> {
    let fin: Vec<&AccuracyRow> = rows
        .iter()
        .filter(|r| r.q_db.is_some_and(f64::is_finite))
        .collect();
    if fin.is_empty() {
        return Err(ChartError::Empty(path.display().to_string()));
    }
    let (_, thi) = range(fin.iter().map(|r| r.tau_secs.max(1e-6)));
    let (qlo, qhi) = range(fin.iter().filter_map(|r| r.q_db));
    let knobs: Vec<&str> = fin.iter().fold(Vec::new(), |mut v, r| {
        if !v.contains(&r.knob) {
            v.push(r.knob);
        }
        v
    });
    draw(path, |root| {
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("{title}: what accuracy costs in time"),
                ("sans-serif", 22),
            )
            .margin(20)
            .x_label_area_size(50)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..thi * 1.1, (qlo - 2.0)..(qhi + 2.0))
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_labels(6)
            .x_label_formatter(&|v| short(*v))
            .x_desc("τ (s; DVR per view, or VDI generation)")
            .y_desc("q (dB)")
            .label_style(("sans-serif", 16))
            .draw()
            .map_err(|e| e.to_string())?;
        for (i, knob) in knobs.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let pts: Vec<&&AccuracyRow> = fin.iter().filter(|r| r.knob == *knob).collect();
            chart
                .draw_series(LineSeries::new(
                    pts.iter()
                        .map(|r| (r.tau_secs.max(1e-6), r.q_db.unwrap_or(0.0))),
                    color.stroke_width(2),
                ))
                .map_err(|e| e.to_string())?
                .label(*knob)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            chart
                .draw_series(pts.iter().map(|r| {
                    EmptyElement::at((r.tau_secs.max(1e-6), r.q_db.unwrap_or(0.0)))
                        + Circle::new((0, 0), 4, color.filled())
                        + Text::new(r.value.clone(), (6, -14), ("sans-serif", 13))
                }))
                .map_err(|e| e.to_string())?;
        }
        legend(&mut chart)?;
        Ok(())
    })
}
