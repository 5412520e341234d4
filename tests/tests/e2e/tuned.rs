//! The tuned pipeline's parts as real processes on 127.0.0.1, shared by the tuner's tests
//! (`e2e::tuner`) and the timed ones (`timed`): a tuner-node on a small grid, a generator-node
//! that dials it, a replay of the ocean series through them, and readers of the tuner's status,
//! decisions and persisted state.

use crate::common::{finish, free_port, generator, small_config, status, viz};
use insitu_e2e::{bin, ocean, rt, wait_until, Daemon};
use insitu_proto::pb::tuner_client::TunerClient;
use insitu_proto::{pb, transport};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// A tuner-node with a small grid (fast trials) and no trial share limit in a short test.
pub(crate) fn tuner(state: &Path, listen: &str, viz: &str, utility: &str, logs: &Path) -> Daemon {
    tuner_paced(
        state,
        listen,
        viz,
        utility,
        "timeout_secs = 60.0\nshare = 1.0\nburst_secs = 600.0",
        logs,
    )
}

/// As [`tuner`] with the trial budget `trials` (TOML keys of `[trials]`): a small share makes
/// a tuning last long enough to interrupt it.
pub(crate) fn tuner_paced(
    state: &Path,
    listen: &str,
    viz: &str,
    utility: &str,
    trials: &str,
    logs: &Path,
) -> Daemon {
    let cfg = logs.join(format!("tuner-{}.toml", free_port()));
    std::fs::write(
        &cfg,
        format!(
            r#"listen = "{listen}"
state_dir = "{}"
viz = "{viz}"
utility = "{utility}"
[grid]
r = "64:256:64"
gamma = "0.001:0.26:0.016"
[characteristic]
threshold = 0.15
max = 4
[trials]
hold_wait_secs = 2.0
{trials}
"#,
            state.display()
        ),
    )
    .unwrap();
    Daemon::start(
        "tuner-node",
        &["--config", cfg.to_str().unwrap()],
        &[],
        logs,
    )
}

/// A generator-node shipping to `viz` and dialling `tuner`, once its stream to the tuner is up
/// (steps made before that are not summarised: there is no one to send them to).
pub(crate) fn tuned_generator(viz: &str, tuner: &str, logs: &Path) -> Daemon {
    tuned_generator_from(&small_config(viz, "block", 16), tuner, logs)
}

/// As [`tuned_generator`] with the config `toml` ([`small_config`] or one made from it).
pub(crate) fn tuned_generator_from(toml: &str, tuner: &str, logs: &Path) -> Daemon {
    let toml = toml.replace(
        "max_backoff_secs = 0.2",
        &format!("max_backoff_secs = 0.2\ntuner = \"{tuner}\""),
    );
    let g = generator(&toml, logs, &[]);
    assert!(
        wait_until(30.0, || status(&g.addr).tuner_connected),
        "the generator-node did not reach the tuner"
    );
    g
}

pub(crate) async fn client(addr: &str) -> TunerClient<tonic::transport::Channel> {
    TunerClient::new(transport::connect(&transport::uri(addr)).await.unwrap())
}

pub(crate) fn tuner_status(addr: &str) -> pb::TunerStatus {
    rt().block_on(async {
        client(addr)
            .await
            .get_status(pb::StatusRequest {})
            .await
            .unwrap()
            .into_inner()
    })
}

pub(crate) fn decision(addr: &str, version: u64) -> Result<pb::PmDecision, tonic::Status> {
    rt().block_on(async {
        client(addr)
            .await
            .get_decision(pb::DecisionRequest {
                pm_version: version,
            })
            .await
            .map(tonic::Response::into_inner)
    })
}

/// The newest decision up to version `newest` that the search pushed as it found it: not a
/// correction between tunings, not coarsened for the forecast (those name a candidate the
/// trials may never have measured). `None` when every one was. (Read by the timed tests.)
#[allow(dead_code)]
pub(crate) fn as_found(addr: &str, newest: u64) -> Option<pb::PmDecision> {
    (1..=newest)
        .rev()
        .filter_map(|v| decision(addr, v).ok())
        .find(|d| d.corrects_version == 0 && d.forecast_ratio == 0.0)
}

/// The persisted state.
pub(crate) fn state(dir: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(dir.join("tuner-state.json")).unwrap()).unwrap()
}

/// `insitu replay` of `series` pushing to `generator`, started in the background.
pub(crate) fn replay(series: &Path, generator: &str, extra: &[&str]) -> Child {
    Command::new(bin("insitu"))
        .args(["replay", "--series", series.to_str().unwrap()])
        .args(["--generator", generator, "--r", "128", "--codec", "zstd"])
        .args(extra)
        .env_remove("INSITU_TOKEN")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// A viz-node, a tuner for `utility` and a tuned generator-node, after `insitu replay` of the
/// ocean series (with `args`) through them has finished; `None` without the shared data.
pub(crate) struct TunedOcean {
    pub(crate) rec: PathBuf,
    pub(crate) st: PathBuf,
    pub(crate) v: Daemon,
    pub(crate) t: Daemon,
    pub(crate) g: Daemon,
    _tmp: tempfile::TempDir,
}

impl TunedOcean {
    /// Stops the daemons, the generator-node first.
    pub(crate) fn stop(self) {
        self.g.terminate();
        self.t.terminate();
        self.v.terminate();
    }
}

pub(crate) fn tuned_ocean(utility: &str, args: &[&str]) -> Option<TunedOcean> {
    let series = ocean()?;
    let tmp = tempfile::tempdir().unwrap();
    let (rec, st) = (tmp.path().join("rec"), tmp.path().join("state"));
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let t = tuner(&st, "127.0.0.1:0", &v.addr, utility, tmp.path());
    let g = tuned_generator(&v.addr, &t.addr, tmp.path());
    finish(replay(&series, &g.addr, args));
    Some(TunedOcean {
        rec,
        st,
        v,
        t,
        g,
        _tmp: tmp,
    })
}

/// The persisted trial of decision `d` on `step`.
pub(crate) fn decision_trial<'s>(
    state: &'s serde_json::Value,
    step: u64,
    d: &pb::PmDecision,
) -> &'s serde_json::Value {
    state["trials"]
        .as_array()
        .unwrap()
        .iter()
        .find(|x| {
            x["step"].as_u64() == Some(step)
                && x["measurement"]["r"].as_u64() == Some(u64::from(d.resolution))
                && (x["measurement"]["gamma"].as_f64().unwrap() as f32) == d.gamma
        })
        .unwrap_or_else(|| panic!("no trial of the decision on step {step}"))
}
