//! The tuner-node's configuration: one TOML file (every key documented in
//! `deploy/tuner-node.toml`), overridden by command-line flags.

pub use insitu_proto::daemon::ConfigError;
use insitu_proto::daemon::{DaemonConfig, ServeKeys};
use insitu_proto::tls::TlsFiles;
use insitu_tuner::utility::{Budgets, Utility, UtilitySpec};
use insitu_tuner::ParamGrid;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::PathBuf;

/// How candidates are searched.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Strategy {
    /// Bisection over γ per r and a climb over r (size and quality utilities).
    Adaptive,
    /// Every candidate of the grid (any utility).
    Grid,
}

/// The precisions a tuning chooses among unless configured: 6 and 8 bits. On the demo's
/// Gray–Scott under 1 MB a step, 6 bits bought the finer γ that 8 bits could not afford
/// (q 37.4 against 35.8 dB), for about 1.6× the trials; floats never pay under a budget.
pub const DEFAULT_PRECISIONS: &str = "6,8";

/// The candidate grid, as `START:END:STEP` or comma lists.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridConfig {
    /// Resolutions `r`.
    pub r: String,
    /// Thresholds `γ`.
    pub gamma: String,
    /// The VDI file's precisions, `P_M`'s third parameter: colour bits (4–16) and `f32`,
    /// comma-separated. With several, the first tuning (and one for a steered utility)
    /// searches (r, γ) at each and keeps the best; re-tunes search at the precision it chose.
    /// Default [`DEFAULT_PRECISIONS`].
    pub precision: String,
}

impl Default for GridConfig {
    fn default() -> Self {
        Self {
            r: "64:512:64".into(),
            gamma: "0.001:0.26:0.008".into(),
            precision: DEFAULT_PRECISIONS.into(),
        }
    }
}

/// Characteristic steps.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CharacteristicConfig {
    /// Histogram distance (total variation, in [0, 1]) above which a step is characteristic.
    pub threshold: f64,
    /// Most characteristic steps kept (≥ 1); the most redundant is evicted beyond it.
    pub max: usize,
    /// A production step made under the last tuning (its decision or a correction of it)
    /// whose σ is at least this factor over what its decision planned for it is
    /// characteristic (> 1): its data is not what the plan was measured on, whatever its
    /// histogram says (docs/tuning.md, "A new character").
    pub sigma_miss: f64,
}

impl Default for CharacteristicConfig {
    fn default() -> Self {
        Self {
            threshold: 0.15,
            max: 6,
            sigma_miss: 1.5,
        }
    }
}

/// What trials may cost.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrialConfig {
    /// A trial whose results do not arrive within this many seconds is abandoned (and with it
    /// the tuning that asked for it; the previous decision stays).
    pub timeout_secs: f64,
    /// Share of the wall clock the trials may take, in (0, 1]: trials (their wall clock on
    /// the nodes) may use `max(burst, share × seconds since start)`; beyond that the next
    /// trial waits.
    pub share: f64,
    /// Trial seconds allowed before the share has accrued them: it lets the first tuning run
    /// at once, and what that tuning leaves of it lapses when it decides. It is an advance on
    /// the share: later trials wait until the share has caught up with what the first tuning
    /// used, so the trials keep to `share` of any run longer than that.
    pub burst_secs: f64,
    /// Trial seconds a tuning for a new character (or a steered utility) may run ahead of
    /// `share`: it starts at once instead of waiting for the share to
    /// accrue, and the trials after it wait until the share has caught up (so the long-run
    /// share holds).
    pub overdraft_secs: f64,
    /// How long a trial waits for a node that holds its step to (re)connect, seconds.
    pub hold_wait_secs: f64,
}

impl Default for TrialConfig {
    fn default() -> Self {
        Self {
            timeout_secs: 120.0,
            share: 0.1,
            burst_secs: 15.0,
            overdraft_secs: 2.0,
            hold_wait_secs: 10.0,
        }
    }
}

/// The whole file.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Address to serve on (port 0: ephemeral). Anything but loopback needs a token and TLS
    /// unless `insecure`.
    pub listen: SocketAddr,
    /// Allow a non-loopback `listen` without a token or TLS, and the token sent in clear text
    /// to a non-loopback viz-node (logged as a warning at start).
    pub insecure: bool,
    /// `[tls]`: certificate, key (served on `listen`), CA (the viz-node is dialled over TLS),
    /// mutual TLS.
    pub tls: TlsFiles,
    /// File holding the bearer token (else `INSITU_TOKEN`); checked on every call and sent
    /// to the viz-node.
    pub token_file: Option<PathBuf>,
    /// Directory of the persisted state (`tuner-state.json`); created if missing.
    pub state_dir: PathBuf,
    /// The viz-node, `host:port`, whose quality reports are watched; unset: only σ and τ of
    /// production steps are watched.
    pub viz: Option<String>,
    /// Further viz-nodes sharing the recording by step (docs/scale.md): their reports are
    /// watched too (needs `viz`).
    pub viz_shards: Vec<String>,
    /// The utility ν: `size:BYTES`, `time:SECS`, `size:BYTES,time:SECS` or `quality:DB`.
    /// For a world of ranks σ is a step's VDIs summed over ranks and τ the slowest rank's.
    pub utility: String,
    /// `adaptive` (bisects the budgets or the quality target; see `insitu_tuner::search`) or
    /// `grid` (every candidate on every characteristic step).
    pub strategy: Strategy,
    /// Candidates.
    pub grid: GridConfig,
    /// Characteristic steps.
    pub characteristic: CharacteristicConfig,
    /// Trial budget.
    pub trials: TrialConfig,
    /// A production step whose q is more than this many dB below the decision's prediction
    /// becomes characteristic (re-tuning).
    pub q_margin_db: f64,
    /// Production steps in a row, made with the P_M in force, whose τ must break τ_target
    /// before the last becomes characteristic (re-tuning); ≥ 1. τ counts whatever else the
    /// node runs meanwhile (the simulation), so one slow step alone is noise more often than
    /// a changed field. A σ over σ_target acts at once (σ is no timing).
    pub time_breaks: u32,
    /// Share of σ_target and τ_target kept free when choosing, in [0, 0.5): the search plans
    /// for `(1 − headroom) × target`, so alike steps that drift a little do not break the
    /// budget at once (the optimum of ν_size sits right at the budget). Production steps are
    /// checked against the full target.
    pub headroom: f64,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 50053)),
            insecure: false,
            tls: TlsFiles::default(),
            token_file: None,
            state_dir: PathBuf::from("tuner-state"),
            viz: None,
            viz_shards: Vec::new(),
            utility: "size:1MB".into(),
            strategy: Strategy::Adaptive,
            grid: GridConfig::default(),
            characteristic: CharacteristicConfig::default(),
            trials: TrialConfig::default(),
            q_margin_db: 3.0,
            time_breaks: 2,
            headroom: 0.05,
        }
    }
}

fn invalid(key: &'static str, problem: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key,
        problem: problem.into(),
    }
}

/// The settings, validated and parsed.
pub struct Resolved {
    /// ν as configured (what is reported).
    pub utility: Box<dyn Utility>,
    /// ν with the headroom taken off the budgets (what the search optimises).
    pub plan: Box<dyn Utility>,
    /// For the adaptive strategy: the utility it bisects (with the headroom).
    pub target: Option<UtilitySpec>,
    /// Candidates.
    pub grid: ParamGrid,
    /// ν as configured, parsed: its budgets ([`Resolved::budgets`]) or its quality target.
    pub spec: UtilitySpec,
}

impl Resolved {
    /// σ_target and τ_target of the utility, where it has them: what a production step is
    /// checked against.
    pub fn budgets(&self) -> Budgets {
        self.spec.budgets()
    }
}

impl DaemonConfig for Config {
    fn serve(&self) -> ServeKeys<'_> {
        ServeKeys {
            listen: self.listen,
            insecure: self.insecure,
            tls: &self.tls,
            token_file: self.token_file.as_deref(),
        }
    }
    fn listen_mut(&mut self) -> &mut SocketAddr {
        &mut self.listen
    }
    fn token_file_mut(&mut self) -> &mut Option<PathBuf> {
        &mut self.token_file
    }
    /// [`Config::resolve`], its result dropped.
    fn validate(&self) -> Result<(), ConfigError> {
        self.resolve().map(|_| ())
    }
}

impl Config {
    /// Checks every key and parses the utility and the grid.
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the key: a bad or non-positive budget, an empty or
    /// malformed grid, a threshold outside [0, 1],
    /// `max` 0, a non-positive timeout or share, `time_breaks` 0.
    pub fn resolve(&self) -> Result<Resolved, ConfigError> {
        let spec =
            UtilitySpec::parse(&self.utility).map_err(|e| invalid("utility", e.to_string()))?;
        if !(0.0..0.5).contains(&self.headroom) {
            return Err(invalid("headroom", "must be in [0, 0.5)"));
        }
        if !self.viz_shards.is_empty() && self.viz.is_none() {
            return Err(invalid("viz_shards", "needs viz, the first shard"));
        }
        let plan = spec.scaled(1.0 - self.headroom);
        let target = match self.strategy {
            Strategy::Adaptive => Some(plan),
            Strategy::Grid => None,
        };
        let grid = ParamGrid::parse(&self.grid.r, &self.grid.gamma)
            .and_then(|g| g.with_precisions(&self.grid.precision))
            .map_err(|e| invalid("grid", e.to_string()))?;
        if grid.is_empty() {
            return Err(invalid("grid", "the grid is empty"));
        }
        let c = &self.characteristic;
        if !(0.0..=1.0).contains(&c.threshold) {
            return Err(invalid("characteristic.threshold", "must be in [0, 1]"));
        }
        if c.max == 0 {
            return Err(invalid("characteristic.max", "must be ≥ 1"));
        }
        if !(c.sigma_miss.is_finite() && c.sigma_miss > 1.0) {
            return Err(invalid(
                "characteristic.sigma_miss",
                "must be finite and > 1",
            ));
        }
        let t = &self.trials;
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(t.timeout_secs) {
            return Err(invalid("trials.timeout_secs", "must be finite and > 0"));
        }
        if !(positive(t.share) && t.share <= 1.0) {
            return Err(invalid("trials.share", "must be in (0, 1]"));
        }
        if !(t.burst_secs.is_finite() && t.burst_secs >= 0.0) {
            return Err(invalid("trials.burst_secs", "must be finite and ≥ 0"));
        }
        if !(t.overdraft_secs.is_finite() && t.overdraft_secs >= 0.0) {
            return Err(invalid("trials.overdraft_secs", "must be finite and ≥ 0"));
        }
        if !(t.hold_wait_secs.is_finite() && t.hold_wait_secs >= 0.0) {
            return Err(invalid("trials.hold_wait_secs", "must be finite and ≥ 0"));
        }
        if !(self.q_margin_db.is_finite() && self.q_margin_db >= 0.0) {
            return Err(invalid("q_margin_db", "must be finite and ≥ 0"));
        }
        if self.time_breaks == 0 {
            return Err(invalid("time_breaks", "must be ≥ 1"));
        }
        Ok(Resolved {
            utility: spec.utility(),
            plan: plan.utility(),
            target,
            grid,
            spec,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_documented_example_parses_and_matches_the_defaults() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/tuner-node.toml");
        assert_eq!(Config::load(&path).unwrap(), Config::default());
    }

    #[test]
    fn bad_values_name_their_key() {
        let bad = |toml: &str| match toml::from_str::<Config>(toml) {
            Ok(c) => c.resolve().err().map(|e| e.to_string()).unwrap_or_default(),
            Err(e) => e.to_string(),
        };
        assert!(bad("utility = \"size:0\"").contains("utility"));
        assert!(bad("utility = \"size:-1MB\"").contains("utility"));
        assert!(bad("utility = \"time:0\"\nstrategy = \"grid\"").contains("utility"));
        assert!(bad("utility = \"time:0.5\"").is_empty());
        assert!(bad("utility = \"time:0.5\"\nstrategy = \"grid\"").is_empty());
        assert!(bad("[grid]\nr = \"\"").contains("grid"));
        assert!(bad("[grid]\ngamma = \"0.2:0.1:0.01\"").contains("grid"));
        assert!(bad("[characteristic]\nthreshold = 1.5").contains("characteristic.threshold"));
        assert!(bad("[characteristic]\nmax = 0").contains("characteristic.max"));
        assert!(bad("[characteristic]\nsigma_miss = 1").contains("characteristic.sigma_miss"));
        assert!(bad("[trials]\noverdraft_secs = -1").contains("trials.overdraft_secs"));
        assert!(bad("[trials]\nshare = 0").contains("trials.share"));
        assert!(bad("[trials]\ntimeout_secs = -1").contains("trials.timeout_secs"));
        assert!(bad("colour = 3").contains("colour"));
        assert!(bad("headroom = 0.5").contains("headroom"));
        assert!(bad("time_breaks = 0").contains("time_breaks"));
        let r = toml::from_str::<Config>("utility = \"size:1MB,time:2\"\nstrategy = \"grid\"")
            .unwrap()
            .resolve()
            .unwrap();
        assert_eq!(
            r.budgets(),
            Budgets {
                size_bytes: Some(1_000_000),
                time_secs: Some(2.0)
            }
        );
        assert_eq!(r.plan.describe(), "max q with σ < 950.0 kB and τ < 1.9 s");
    }
}
