//! `insitu tune`: the best `P_M` for a utility function (Sec. 5.4), by the paper's grid or the
//! adaptive search; `--ladder` compares both over the paper's ladder of size budgets (Fig. 8).

use super::q_text;
use super::study::{run_grid, StudyArgs};
use anyhow::{bail, Context, Result};
use insitu_tuner::charts::{self, LadderPoint};
use insitu_tuner::search::{adaptive_search, grid_search, size_ladder, Outcome};
use insitu_tuner::utility::{bytes_text, SizeBudget, UtilitySpec};
use insitu_tuner::{Measurement, Oracle, TableOracle};

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Strategy {
    /// Measure every candidate of the grid (the paper).
    Grid,
    /// Bisection on gamma per r and a climb over r (any utility: size or time budgets, quality).
    Adaptive,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    study: StudyArgs,
    /// Utility: size:2MB (Eq. 1), time:0.5 (Eq. 2, seconds), size:2MB,time:0.5, quality:40.
    /// Default: the config's, else size:1MB.
    #[arg(long)]
    utility: Option<String>,
    /// Search strategy: adaptive (seconds on a 64³ volume) or grid (every candidate, the
    /// paper's study: minutes). Default: the config's, else adaptive.
    #[arg(long, value_enum)]
    strategy: Option<Strategy>,
    /// TOML file with `utility` and `strategy` (see deploy/tuner.toml); flags override it.
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Instead: study the whole grid, then for each size budget of the paper's ladder (each
    /// 1.5x the previous) compare the grid optimum with the adaptive one (priced from the table).
    #[arg(long)]
    ladder: bool,
    /// With --ladder: draw the ladder (grid and adaptive) to this PNG.
    #[arg(long, default_value = "ladder.png")]
    chart: std::path::PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

fn row_json(m: &Measurement) -> serde_json::Value {
    serde_json::json!({
        "r": m.r, "gamma": insitu_core::json::f32_number(m.gamma), "sigma_bytes": m.sizing.sigma_bytes, "tau_s": m.sizing.tau_secs,
        "q_db": super::q_json(m.q()), "ssim": m.ssim,
    })
}

/// The tuner's config file: which built-in utility, with which budget, and how to search.
#[derive(serde::Deserialize, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TuneConfig {
    /// As `--utility`.
    pub utility: Option<String>,
    /// As `--strategy`: "grid" or "adaptive".
    pub strategy: Option<String>,
}

impl TuneConfig {
    /// Reads a config file.
    pub fn load(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read tuner config {}", path.display()))?;
        toml::from_str(&text).with_context(|| format!("tuner config {}", path.display()))
    }
}

/// The utility spec and strategy: flags, else the config, else the defaults.
fn resolve(a: &Args) -> Result<(String, Strategy)> {
    let cfg = match &a.config {
        Some(p) => TuneConfig::load(p)?,
        None => TuneConfig::default(),
    };
    let utility = a
        .utility
        .clone()
        .or(cfg.utility)
        .unwrap_or_else(|| "size:1MB".into());
    let strategy = match (a.strategy, cfg.strategy.as_deref()) {
        (Some(s), _) => s,
        (None, Some("grid")) => Strategy::Grid,
        (None, None | Some("adaptive")) => Strategy::Adaptive,
        (None, Some(other)) => bail!("tuner config: strategy {other:?} is not grid or adaptive"),
    };
    Ok((utility, strategy))
}

pub fn run(a: Args) -> Result<()> {
    if a.ladder {
        return ladder(&a);
    }
    let (spec, strategy) = resolve(&a)?;
    let spec = UtilitySpec::parse(&spec)?;
    let utility = spec.utility();
    let p = a.study.prepare()?;
    let rc = p.raycaster()?;
    let mut study = a.study.study(&p, &rc)?;
    let out: Outcome = match strategy {
        Strategy::Grid => {
            // Measure with a progress bar, then pick from the (now cached) rows.
            let t = std::time::Instant::now();
            run_grid(&mut study, &p.grid)?;
            let mut o = grid_search(&mut study, &p.grid, utility.as_ref())?;
            o.generations = study.generations();
            o.generation_secs = study.generation_secs();
            o.wall_secs = t.elapsed().as_secs_f64();
            o
        }
        Strategy::Adaptive => adaptive_search(&mut study, &p.grid, spec)?,
    };
    study.save()?;
    let Some(best) = &out.best else {
        bail!(
            "no P_M of the {} candidates meets \"{}\" (infeasible budget); loosen it or widen the grid",
            p.grid.len(),
            utility.describe()
        );
    };
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "utility": utility.describe(), "strategy": format!("{strategy:?}").to_lowercase(),
                "best": row_json(best), "generated": out.generations, "grid_candidates": p.grid.len(),
                "generation_secs": out.generation_secs, "wall_secs": out.wall_secs,
            })
        );
    } else {
        println!("{} ({strategy:?} search)", utility.describe());
        println!(
            "best P_M: r = {}, gamma = {} | sigma = {} ({}), q = {} dB, tau = {:.3} s",
            best.r,
            best.gamma,
            best.sizing.sigma_bytes,
            bytes_text(best.sizing.sigma_bytes),
            q_text(best.q()),
            best.sizing.tau_secs
        );
        println!(
            "generated {} of {} candidates (the rest from the cache or not needed), sum of tau {:.2} s, wall clock {:.1} s",
            out.generations,
            p.grid.len(),
            out.generation_secs,
            out.wall_secs
        );
    }
    Ok(())
}

fn ladder(a: &Args) -> Result<()> {
    let p = a.study.prepare()?;
    let rc = p.raycaster()?;
    let mut study = a.study.study(&p, &rc)?;
    let rows = run_grid(&mut study, &p.grid)?;
    let grid_tau: f64 = rows.iter().map(|m| m.sizing.tau_secs).sum();
    let mut out = Vec::new();
    let mut points = Vec::new();
    if !a.json {
        println!(
            "{} with {}: {} candidates, grid sum of tau {:.1} s",
            p.scene.volume_name,
            p.scene.tf_name,
            rows.len(),
            grid_tau
        );
        println!(
            "{:>11} | {:>5} {:>6} {:>7} | {:>5} {:>6} {:>7} {:>7} | {:>6} {:>9}",
            "sigma_tgt", "r", "gamma", "q dB", "r", "gamma", "q dB", "dq", "evals", "tau share"
        );
    }
    for t in size_ladder(&rows) {
        let g = insitu_tuner::utility::best(&rows, &SizeBudget { sigma_target: t });
        let mut oracle = TableOracle::new(&rows);
        let ad = adaptive_search(&mut oracle, &p.grid, UtilitySpec::Size(t))?;
        let rung = match (g, &ad.best) {
            (Some((grid, _)), Some(adaptive)) => Rung {
                sigma_target: t,
                grid,
                adaptive,
                evaluations: ad.generations,
                tau_share: ad.generation_secs / grid_tau.max(1e-12),
            },
            _ => {
                if !a.json {
                    println!("{:>11} | infeasible", bytes_text(t));
                }
                continue;
            }
        };
        points.push(rung.point());
        if a.json {
            out.push(rung.json(rows.len()));
        } else {
            println!("{}", rung.text());
        }
    }
    let title = format!(
        "{} ({})",
        super::study::short_name(&p.scene.volume_name),
        p.scene.tf_name
    );
    charts::ladder(&points, &title, &a.chart)?;
    if a.json {
        println!("{}", serde_json::Value::Array(out));
    } else {
        println!("-> {}", a.chart.display());
    }
    Ok(())
}

/// One rung of `--ladder`: the grid's and the adaptive search's choices under one size budget.
struct Rung<'a> {
    /// σ_target, bytes.
    sigma_target: u64,
    grid: &'a Measurement,
    adaptive: &'a Measurement,
    /// Candidates the adaptive search generated.
    evaluations: u64,
    /// The adaptive search's sum of τ over the grid's.
    tau_share: f64,
}

impl Rung<'_> {
    /// The rung as the chart draws it.
    fn point(&self) -> LadderPoint {
        let (g, a) = (self.grid, self.adaptive);
        LadderPoint {
            sigma_target: self.sigma_target,
            grid: (g.r, g.gamma, g.q()),
            adaptive: Some((a.r, a.gamma, a.q())),
        }
    }

    /// The rung as `--json` prints it, beside the grid's `grid_evaluations`.
    fn json(&self, grid_evaluations: usize) -> serde_json::Value {
        serde_json::json!({
            "sigma_target": self.sigma_target, "grid": row_json(self.grid),
            "adaptive": row_json(self.adaptive), "adaptive_evaluations": self.evaluations,
            "grid_evaluations": grid_evaluations, "adaptive_tau_share": self.tau_share,
        })
    }

    /// The rung as a row of the table under the header `ladder` prints.
    fn text(&self) -> String {
        let (g, a) = (self.grid, self.adaptive);
        format!(
            "{:>11} | {:>5} {:>6.3} {:>7} | {:>5} {:>6.3} {:>7} {:>7.2} | {:>6} {:>8.1}%",
            bytes_text(self.sigma_target),
            g.r,
            g.gamma,
            q_text(g.q()),
            a.r,
            a.gamma,
            q_text(a.q()),
            a.q() - g.q(),
            self.evaluations,
            100.0 * self.tau_share
        )
    }
}

#[cfg(test)]
mod tests {
    use super::TuneConfig;
    use insitu_tuner::parse_utility;

    #[test]
    fn the_documented_config_holds_the_defaults() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/tuner.toml");
        let cfg = TuneConfig::load(&path).unwrap_or_default();
        assert_eq!(cfg.utility.as_deref(), Some("size:1MB"));
        assert_eq!(cfg.strategy.as_deref(), Some("adaptive"));
        assert!(parse_utility(cfg.utility.as_deref().unwrap_or("")).is_ok());
        assert!(toml::from_str::<TuneConfig>("budget = 3").is_err());
    }
}
