//! `insitu study`: Alg. 1's parameter study over a grid of `P_M` (Sec. 5.5), cached on disk,
//! written as CSV and JSON.

use crate::output::write_atomic;
use crate::progress::bar;
use crate::scene::{Scene, SceneArgs};
use anyhow::Result;
use insitu_core::evaluate::DEFAULT_VIEW_ANGLES;
use insitu_core::vdi::codec::Codec;
use insitu_core::Precision;
use insitu_core::Raycaster;
use insitu_tuner::charts::{self, LadderPoint};
use insitu_tuner::search::size_ladder;
use insitu_tuner::utility::{best, SizeBudget};
use insitu_tuner::{report, Measurement, Oracle, ParamGrid, Study, StudySetup};
use std::path::Path;
use std::path::PathBuf;
use std::time::Instant;

/// What a study measures and where it caches: shared by `study` and `tune`.
#[derive(clap::Args, Debug, Clone)]
pub struct StudyArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub backend: super::BackendArgs,
    /// Resolutions r: START:END:STEP or a list (the paper's 160:768:32).
    #[arg(long, default_value = "160:768:32")]
    pub r_grid: String,
    /// Thresholds gamma: START:END:STEP or a list (the paper's 0.001:0.26:0.004).
    #[arg(long, default_value = "0.001:0.26:0.004", allow_hyphen_values = true)]
    pub gamma_grid: String,
    /// Test view angles about +y, degrees.
    #[arg(
        long,
        default_value = "0,10,20,30,40,50,60",
        allow_hyphen_values = true
    )]
    pub views: String,
    /// Image size of references and VDI renders: N or WxH (the paper's 768²).
    #[arg(long, default_value = "768")]
    pub size: String,
    /// Precisions of the VDI file (P_M's third parameter): colour bits 4–16 and f32, a list
    /// (e.g. 6,8,f32). Each candidate not at f32 with bzip2 also reports the paper's sigma
    /// (the same VDI as floats under bzip2).
    #[arg(long, default_value = "8")]
    pub precision: String,
    /// Codec for sigma: bzip2 (the paper's), zstd or none.
    #[arg(long, default_value = "bzip2", value_parser = super::codec_arg)]
    pub codec: Codec,
    /// Cache directory (results are reused whenever nothing they depend on changed).
    #[arg(long, default_value = ".insitu-cache")]
    pub cache_dir: PathBuf,
    /// Do not read or write the cache.
    #[arg(long)]
    pub no_cache: bool,
}

/// A loaded scene with the study's settings.
pub struct Prepared {
    pub scene: Scene,
    pub grid: ParamGrid,
    pub views: Vec<f32>,
    pub size: (u32, u32),
    pub codec: Codec,
    pub backend: insitu_core::Backend,
}

impl Prepared {
    /// The scene's ray-caster.
    pub fn raycaster(&self) -> Result<Raycaster<'_>> {
        let s = &self.scene;
        Ok(Raycaster::new(&s.volume, &s.tf, s.params)?)
    }
}

impl StudyArgs {
    /// Parses everything and loads the scene.
    pub fn prepare(&self) -> Result<Prepared> {
        let grid =
            ParamGrid::parse(&self.r_grid, &self.gamma_grid)?.with_precisions(&self.precision)?;
        let views = if self.views.is_empty() {
            DEFAULT_VIEW_ANGLES.to_vec()
        } else {
            super::parse_views(&self.views)?
        };
        let size = super::parse_size(&self.size)?;
        Ok(Prepared {
            scene: self.scene.load()?,
            grid,
            views,
            size,
            codec: self.codec,
            backend: self.backend.open()?,
        })
    }

    /// A study of `p` with its ray-caster `rc` (references rendered here, once).
    pub fn study<'a>(&self, p: &'a Prepared, rc: &'a Raycaster<'a>) -> Result<Study<'a>> {
        let s = &p.scene;
        let scene = StudySetup::new(
            p.backend.prepare(rc)?,
            s.volume.content_hash(),
            &s.tf,
            &s.tf_name,
            SceneArgs::camera(s),
            &p.views,
            p.size,
            p.codec,
        )?;
        Ok(Study::new(
            scene,
            (!self.no_cache).then_some(self.cache_dir.as_path()),
        ))
    }
}

/// Runs the whole grid with a progress bar; returns the rows.
pub fn run_grid(study: &mut Study, grid: &ParamGrid) -> Result<Vec<insitu_tuner::Measurement>> {
    let pb = bar(grid.len() as u64, "study");
    let rows = study.run(&grid.candidates(), |i, m| {
        pb.set_position(i as u64);
        pb.set_message(format!("study r={} γ={:.3}", m.r, m.gamma));
    })?;
    pb.finish_and_clear();
    Ok(rows)
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    study: StudyArgs,
    /// Output prefix: writes PREFIX.csv and PREFIX.json.
    #[arg(long, default_value = "study")]
    out: PathBuf,
    /// Do not draw PREFIX_map.png (Fig. 7), PREFIX_pareto.png and PREFIX_ladder.png (Fig. 8).
    #[arg(long)]
    no_charts: bool,
    /// Print a JSON summary instead of text.
    #[arg(long)]
    json: bool,
}

/// Draws the study's charts next to `prefix`; returns the files written. With several
/// precisions, the map and the Pareto front are drawn for each (`PREFIX_map_8bit.png`, …) and
/// the ladder (the best `P_M` under each size budget, Fig. 8) chooses among all of them.
pub fn draw_charts(rows: &[Measurement], title: &str, prefix: &Path) -> Result<Vec<PathBuf>> {
    let name = |suffix: &str| {
        let stem = prefix
            .file_name()
            .map_or_else(|| "study".into(), |s| s.to_string_lossy().into_owned());
        prefix.with_file_name(format!("{stem}_{suffix}.png"))
    };
    let mut precisions: Vec<_> = rows.iter().map(|m| m.precision).collect();
    precisions.sort_by_key(|p| p.bits());
    precisions.dedup();
    let mut written = Vec::new();
    for &p in &precisions {
        let at: Vec<Measurement> = rows.iter().filter(|m| m.precision == p).cloned().collect();
        let (suffix, title) = if precisions.len() > 1 {
            let suffix = match p {
                Precision::Float32 => "_f32".to_owned(),
                Precision::Bits(b) => format!("_{b}bit"),
            };
            (suffix, format!("{title}, {p}"))
        } else {
            (String::new(), title.to_owned())
        };
        let (map, par) = (
            name(&format!("map{suffix}")),
            name(&format!("pareto{suffix}")),
        );
        charts::study_map(&at, &title, &map)?;
        charts::pareto(&at, &title, &par)?;
        written.extend([map, par]);
    }
    let lad = name("ladder");
    let points: Vec<LadderPoint> = size_ladder(rows)
        .into_iter()
        .filter_map(|t| {
            best(rows, &SizeBudget { sigma_target: t }).map(|(m, _)| LadderPoint {
                sigma_target: t,
                grid: (m.r, m.gamma, m.q()),
                adaptive: None,
            })
        })
        .collect();
    charts::ladder(&points, title, &lad)?;
    written.push(lad);
    Ok(written)
}

pub fn run(a: Args) -> Result<()> {
    let p = a.study.prepare()?;
    let t = Instant::now();
    let rc = p.raycaster()?;
    let mut study = a.study.study(&p, &rc)?;
    let rows = run_grid(&mut study, &p.grid)?;
    let csv = a.out.with_extension("csv");
    let json = a.out.with_extension("json");
    write_atomic(&csv, report::csv(&rows).as_bytes())?;
    write_atomic(&json, report::json(&rows)?.as_bytes())?;
    let (generated, secs) = (study.generations(), t.elapsed().as_secs_f64());
    let title = format!("{} ({})", short_name(&p.scene.volume_name), p.scene.tf_name);
    let charts = if a.no_charts {
        Vec::new()
    } else {
        draw_charts(&rows, &title, &a.out)?
    };
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "volume": p.scene.volume_name, "tf": p.scene.tf_name,
                "candidates": rows.len(), "generated": generated, "cached": rows.len() as u64 - generated,
                "secs": secs, "csv": csv, "json": json, "charts": charts,
            })
        );
    } else {
        println!(
            "{} with {}: {} candidates ({} generated, {} from the cache) in {secs:.1} s",
            p.scene.volume_name,
            p.scene.tf_name,
            rows.len(),
            generated,
            rows.len() as u64 - generated
        );
        println!("-> {} and {}", csv.display(), json.display());
        for c in &charts {
            println!("-> {}", c.display());
        }
    }
    Ok(())
}

/// The file name of a volume source, for chart titles.
pub fn short_name(source: &str) -> String {
    Path::new(source)
        .file_name()
        .map_or_else(|| source.to_owned(), |n| n.to_string_lossy().into_owned())
}
