//! The generator-node's configuration: one TOML file (every key documented in
//! `deploy/generator-node.toml`), overridden by command-line flags.

use crate::queue::Policy;
use insitu_core::budget::Budgets;
use insitu_core::raycast::{
    RaycastParams, DEFAULT_GENERATION_TERMINATION, DEFAULT_STEP, DEFAULT_TERMINATION,
};
use insitu_core::vdi::codec::Codec;
use insitu_core::BackendChoice;
use insitu_core::{Camera, NamedTf, Precision, TransferFunction, VdiParams};

/// The default precision of the VDI files a node writes: 8 bits of colour and opacity.
pub const DEFAULT_PRECISION: Precision = Precision::Bits(8);

/// The default guard on the tuner's size budget (`generation.size_guard`): a step over 1.25×
/// the budget is made again toward it.
pub const DEFAULT_SIZE_GUARD: f64 = 1.25;
pub use insitu_proto::daemon::ConfigError;
use insitu_proto::daemon::{DaemonConfig, ServeKeys};
use insitu_proto::tls::TlsFiles;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::PathBuf;

/// Limits and policy of a bounded queue.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct QueueConfig {
    /// Items at most (≥ 1).
    pub max_items: usize,
    /// Bytes at most (field data for the input queue, compressed VDIs and references for the
    /// outbox).
    pub max_bytes: u64,
    /// What a full queue does: `block`, `drop-oldest` or `latest-only`.
    pub policy: Policy,
}

/// A camera in the config file.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Eye position, world units.
    pub eye: [f32; 3],
    /// Point looked at.
    pub target: [f32; 3],
    /// Up hint.
    #[serde(default = "default_up")]
    pub up: [f32; 3],
    /// Vertical field of view, degrees.
    #[serde(default = "default_fov")]
    pub fov_y_deg: f32,
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

fn default_fov() -> f32 {
    30.0
}

impl From<CameraConfig> for Camera {
    fn from(c: CameraConfig) -> Self {
        Camera {
            eye: c.eye.into(),
            target: c.target.into(),
            up: c.up.into(),
            fov_y_deg: c.fov_y_deg,
        }
    }
}

/// What and how to generate (the scene and `P_M`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct GenerationConfig {
    /// `r`: VDI resolution, pixels per side.
    pub resolution: u32,
    /// `γ`: interrupt threshold of the merge criterion.
    pub gamma: f32,
    /// Ray-casting sample distance, world units.
    pub sample_distance: f32,
    /// Refused with a message naming `sample_distance` (a step is a time step).
    #[serde(rename = "step", skip_serializing)]
    pub old_step: Option<f32>,
    /// Early-termination opacity of the reference frames (DVR).
    pub termination: f32,
    /// Early-termination opacity of VDI generation rays; unset: off, rays run to the box exit
    /// and the VDI keeps what lies behind dense structures (`RaycastParams`).
    pub generation_termination: Option<f32>,
    /// `bzip2` (σ as in the paper), `zstd` or `none`: the entropy stage.
    pub codec: Codec,
    /// How the file stores the supersegments (`P_M`'s third parameter): `"f32"` (lossless,
    /// format 3, the paper's σ) or colour bits 4–16 (format 4; docs/conventions.md, "The VDI
    /// file"). Default 8: σ 2.7–4.3× below bzip2 floats for ≤ 0.06 dB of q.
    pub precision: Precision,
    /// Transfer function file (docs/conventions.md format); unset: the default over the global range of
    /// the first step, agreed with every rank through the viz-node (`AgreeScene`; without a
    /// viz-node, over this node's first brick).
    pub tf: Option<PathBuf>,
    /// Generation camera; unset: the default camera for the global box.
    pub camera: Option<CameraConfig>,
    /// Test views: orbit angles about +y, degrees.
    pub view_angles_deg: Vec<f32>,
    /// Render and ship reference frames every k-th step (by step index); 0 = never.
    pub reference_every: u64,
    /// Side of the reference frames, pixels; 0 = `resolution`.
    pub reference_size: u32,
    /// Hard limit on σ of a step, bytes (> 0; summed over its ranks; each rank keeps its
    /// share); unset: none. A VDI that comes out at or over it is made again at a coarser
    /// `P_M` before it ships (encoded again at a coarser precision, down to 6 bits, then γ
    /// raised, then, for a world of one rank, r lowered; τ counts every try:
    /// `work::coarser`), so no stored step exceeds it; one that cannot get under it is not
    /// shipped (counted as failed, logged).
    pub size_max: Option<u64>,
    /// Hard limit on τ of a step (its generation, every try counted), seconds (> 0); unset:
    /// none. A generation that would overrun it is stopped between bands of rows and the step
    /// made again at a resolution its measured rate fits into the time left (a world of one
    /// rank: the ranks of a step share r), so no stored step's τ exceeds it; one that cannot
    /// fit is not shipped (counted as failed, logged). On the GPU the kernel runs whole: a
    /// step over the limit there is not shipped.
    pub time_max: Option<f64>,
    /// The guard on the tuner's size budget, a ratio (≥ 1; 0: off; default
    /// [`DEFAULT_SIZE_GUARD`]). A step made under a decision of the tuner whose σ comes out
    /// over this many times the tuner's size budget is made again toward the budget, as the
    /// hard limit makes a step (`work::coarser`, at most [`crate::work::MAX_GUARD_RETRIES`]
    /// tries), and shipped at its last try whatever that came to: a step the decision did not
    /// foresee (the first of a new character) ships near the budget instead of several times
    /// it, and none is lost. Not applied with `time_max` (a try made again could break it).
    pub size_guard: f64,
    /// The field to render from steps that carry named fields (Blueprint `fields/<name>`);
    /// unset: each step's first. A step that names none holds one field, which is rendered.
    pub field: Option<String>,
}

impl Default for GenerationConfig {
    fn default() -> Self {
        Self {
            resolution: 256,
            gamma: 0.013,
            sample_distance: DEFAULT_STEP,
            old_step: None,
            termination: DEFAULT_TERMINATION,
            generation_termination: DEFAULT_GENERATION_TERMINATION,
            codec: Codec::Bzip2,
            precision: DEFAULT_PRECISION,
            tf: None,
            camera: None,
            view_angles_deg: insitu_core::evaluate::DEFAULT_VIEW_ANGLES.to_vec(),
            reference_every: 10,
            reference_size: 0,
            size_max: None,
            time_max: None,
            size_guard: DEFAULT_SIZE_GUARD,
            field: None,
        }
    }
}

/// The whole file.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Address to serve on (port 0: an ephemeral port). Anything but loopback needs a token
    /// and TLS unless `insecure`.
    pub listen: SocketAddr,
    /// Allow a non-loopback `listen` without a token or TLS, and the token sent in clear text
    /// to non-loopback peers (logged as a warning at start).
    pub insecure: bool,
    /// `[tls]`: certificate, key (served on `listen`), CA (peers are dialled over TLS), mutual
    /// TLS.
    pub tls: TlsFiles,
    /// The viz-node, `host:port` (`https://` with `tls.ca_file`); unset: VDIs are generated,
    /// counted and discarded.
    pub viz: Option<String>,
    /// Further viz-nodes sharing the recording by step (docs/scale.md): with `n` in all
    /// (`viz` first), step `s` goes to the `s mod n`-th, every rank and part of it to the
    /// same one. The world's scene is agreed with `viz`.
    pub viz_shards: Vec<String>,
    /// File holding the bearer token (else the `INSITU_TOKEN` environment variable, if set);
    /// used both to check callers and to call the viz-node.
    pub token_file: Option<PathBuf>,
    /// Largest accepted time step (one rank's brick), bytes.
    pub max_step_bytes: u64,
    /// Time steps waiting for generation.
    pub queue: QueueConfig,
    /// Finished VDIs waiting to be shipped.
    pub outbox: QueueConfig,
    /// On shutdown, how long to keep shipping before counting the rest as dropped, seconds.
    pub drain_timeout_secs: f64,
    /// Longest wait between reconnect attempts to the viz-node, seconds.
    pub max_backoff_secs: f64,
    /// Where VDIs and reference frames are made: `cpu`, `gpu` or `auto` (a hardware GPU if
    /// found, else the CPU).
    pub backend: BackendChoice,
    /// CPU threads for generation, reference frames and trials (0: one per core). Fewer
    /// leave cores to the simulation on the same node.
    pub threads: usize,
    /// Nice level of those threads, 0–19 (Linux; 0, the default: the process's own
    /// priority). Above 0 a simulation on the same cores runs first and the node takes the
    /// time it leaves: a simulation that keeps every core busy then delays the VDIs, and τ
    /// (wall clock on the CPU) counts the waits, which a `time:` budget then pays for
    /// (docs/performance.md, "The simulation's share").
    pub nice: i32,
    /// The tuner service, `host:port`; unset: `P_M` stays as configured (or as pushed with
    /// SetConfig). The node dials out to it and reconnects with back-off.
    pub tuner: Option<String>,
    /// Most bytes of step fields held for the tuner's trials (field as f32 plus its reference
    /// frames); a step that does not fit is not held, and the tuner is told so.
    pub hold_bytes: u64,
    /// Trials run when no production step waits; when production alone keeps the node busy,
    /// one trial may run after every this many production steps (0: only when idle).
    pub trial_interleave: u64,
    /// Scene and `P_M`.
    pub generation: GenerationConfig,
    /// The durable spool; unset: acknowledged steps live in memory only.
    pub spool: Option<SpoolConfig>,
    /// Two-level composition of this node's ranks before shipping.
    pub host: HostConfig,
    /// Where simulations on this host may put a step's payload instead of streaming it
    /// (`PushShared`, `crate::shm`): a tmpfs directory; unset or not a directory: steps are
    /// streamed only. Clients use it on their own: one on the same host (the same Linux boot
    /// id) that can write there sends its steps that way.
    pub shared_memory_dir: Option<PathBuf>,
    /// `[adios2]`: steps read from an ADIOS2 stream or BP file instead of (or besides) pushes
    /// (`crate::adios2_input`; the cargo feature `adios2`).
    pub adios2: Option<Adios2Input>,
}

/// `[adios2]`: an ADIOS2 writer's output as this node's input: every step of a 3-D global
/// array, this node's part of it read as one rank (docs/ranks-and-clients.md).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Adios2Input {
    /// The stream's name as the writer opened it (SST: its contact file is `NAME.sst` in
    /// this node's working directory), or a BP file (`.bp`, `.bp4`, `.bp5`: read step by
    /// step as it is written).
    pub stream: PathBuf,
    /// The variable (else `generation.field`, else the first 3-D global array by name).
    #[serde(default)]
    pub var: Option<String>,
    /// This node's part and the number of parts the array is split into (nodes reading the
    /// same stream): part `i` of `n` is rank `i` of a world of `n`, its brick one of `n` that
    /// share their boundary planes (`[0, 1]`: the whole array).
    #[serde(default = "whole")]
    pub part: [u32; 2],
    /// Read the one block the writer put in each step as it lies, as rank `i` of a world of
    /// `n` (`part`): for writers that each open a stream of their own (ADIOS2 on
    /// `MPI_COMM_SELF`, or a serial build in each process), whose blocks split the array
    /// without a shared plane; neighbours read by other nodes exchange their boundary planes
    /// through the viz-node.
    #[serde(default)]
    pub as_written: bool,
    /// How long to wait for an SST writer to open the stream, seconds.
    #[serde(default = "default_open_timeout")]
    pub open_timeout_secs: f64,
    /// ADIOS2 engine parameters (e.g. SST's `DataTransport = "WAN"`).
    #[serde(default)]
    pub parameters: std::collections::BTreeMap<String, String>,
}

fn whole() -> [u32; 2] {
    [0, 1]
}

fn default_open_timeout() -> f64 {
    60.0
}

impl Adios2Input {
    /// A stream read whole, with the defaults.
    pub fn new(stream: PathBuf) -> Self {
        Self {
            stream,
            var: None,
            part: whole(),
            as_written: false,
            open_timeout_secs: default_open_timeout(),
            parameters: Default::default(),
        }
    }
}

/// `[host]`: the ranks of one step that this node serves are composed into box-shaped parts
/// before they are shipped, so that the viz-node receives one part per host instead of one
/// VDI per rank (`crate::host`, docs/scale.md).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct HostConfig {
    /// Compose (false: every rank's VDI is shipped as it is made).
    pub compose: bool,
    /// How long a step's finished ranks wait for a rank this node served at the previous
    /// step and has not received for this one, seconds (ranks received are always waited
    /// for); after it, what is finished ships, and the late rank follows alone.
    pub wait_secs: f64,
}

impl Default for HostConfig {
    fn default() -> Self {
        Self {
            compose: true,
            wait_secs: 2.0,
        }
    }
}

/// `[spool]`: acknowledged steps on local disk until delivered (see `spool.rs`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SpoolConfig {
    /// Directory (created if missing; one per node).
    pub dir: PathBuf,
    /// fsync each step before acknowledging it (survives power loss, not only kill -9).
    #[serde(default = "default_durable")]
    pub durable: bool,
    /// Most bytes of steps held; a push waits while it is full.
    #[serde(default = "default_spool_bytes")]
    pub max_bytes: u64,
}

fn default_durable() -> bool {
    true
}

fn default_spool_bytes() -> u64 {
    8 << 30
}

impl Default for Config {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 50051)),
            insecure: false,
            tls: TlsFiles::default(),
            viz: None,
            viz_shards: Vec::new(),
            token_file: None,
            max_step_bytes: 4 << 30,
            queue: QueueConfig {
                max_items: 2,
                max_bytes: 2 << 30,
                policy: Policy::Block,
            },
            outbox: QueueConfig {
                max_items: 16,
                max_bytes: 1 << 30,
                policy: Policy::Block,
            },
            drain_timeout_secs: 30.0,
            max_backoff_secs: 5.0,
            backend: BackendChoice::Auto,
            threads: 0,
            nice: 0,
            tuner: None,
            hold_bytes: 1 << 30,
            trial_interleave: 1,
            generation: GenerationConfig::default(),
            spool: None,
            host: HostConfig::default(),
            shared_memory_dir: Some(PathBuf::from("/dev/shm")),
            adios2: None,
        }
    }
}

/// The generation settings, validated and resolved (TF loaded, codec parsed).
#[derive(Clone, Debug)]
pub struct Generation {
    /// `P_M`.
    pub params: VdiParams,
    /// Step, termination (shading off: emission–absorption).
    pub raycast: RaycastParams,
    /// Codec.
    pub codec: Codec,
    /// Transfer function and its name; `None` until the first step picks a default.
    pub tf: Option<NamedTf>,
    /// Camera; `None`: default for the global box.
    pub camera: Option<Camera>,
    /// Test views, degrees.
    pub view_angles_deg: Vec<f32>,
    /// Reference cadence (0 = never).
    pub reference_every: u64,
    /// Reference side (0 = `r`).
    pub reference_size: u32,
    /// Hard limits on a step's σ and τ (see `GenerationConfig::size_max` and `time_max`).
    pub limits: Budgets,
    /// The guard's ratio to the tuner's size budget (see `GenerationConfig::size_guard`);
    /// `None`: off.
    pub size_guard: Option<f64>,
    /// The tuner's size budget for a whole step, bytes, while a decision of the tuner is in
    /// force (set per step by the node); `None` otherwise. With `size_guard`, what the guard
    /// holds σ against.
    pub tuner_size_budget: Option<u64>,
    /// The field to render by name; `None`: each step's first.
    pub field: Option<String>,
    /// Version of the tuner's decision `params` came from (0: the config or an operator).
    pub pm_version: u64,
    /// The steered scene version `tf`, `field` and `camera` stand for (docs/steering.md;
    /// 0: the config's, the world's agreed default or an operator's).
    pub scene_version: u64,
    /// The settings in force before the last decision (its `P_M` and scene), for the steps
    /// before `from_step` (a decision applies from a step boundary, the same for every rank
    /// of a step, so that the viz-node can compose it); `None` without one.
    pub previous: Option<Box<Generation>>,
    /// The first step made with these settings when `previous` is set.
    pub from_step: u64,
}

impl Generation {
    /// The settings step `step` is made with: `params` from `from_step` on, the previous
    /// `P_M` and version before it.
    pub fn for_step(mut self, step: u64) -> Self {
        match self.previous.take() {
            Some(previous) if step < self.from_step => *previous,
            _ => self,
        }
    }

    /// As [`Self::for_step`], for a step that holds the field named `held` (the one kept at
    /// receipt): a step received before a decision that changes the field reached this node
    /// holds the old field, and is made with the settings it was received under (logged), so
    /// that its VDI says truly which scene it shows.
    pub fn for_step_holding(self, step: u64, held: Option<&str>) -> Self {
        let stale = step >= self.from_step
            && matches!((self.field.as_deref(), held), (Some(f), Some(h)) if f != h);
        match self.previous {
            Some(previous) if stale && previous.field.as_deref() == held => {
                tracing::warn!(
                    step,
                    held,
                    field = self.field.as_deref(),
                    "a step received before the change of field reached this node is made with the scene it was received under"
                );
                *previous
            }
            _ => self.for_step(step),
        }
    }

    /// The field step `step` is rendered from (as [`Self::for_step`] would say, without the
    /// copy): what a push keeps of a step that carries several.
    pub fn field_for(&self, step: u64) -> Option<&str> {
        match &self.previous {
            Some(previous) if step < self.from_step => previous.field.as_deref(),
            _ => self.field.as_deref(),
        }
    }

    /// The camera `P_A` of a step: the configured one, else the default for the whole
    /// domain's box (the same for every rank of a step).
    pub fn camera_for(&self, info: &crate::ingest::StepInfo) -> Camera {
        self.camera
            .unwrap_or_else(|| Camera::default_for_box(&info.global_box()))
    }

    /// Side of the reference frames for the current `r`.
    pub fn reference_side(&self) -> u32 {
        if self.reference_size == 0 {
            self.params.resolution
        } else {
            self.reference_size
        }
    }
}

fn invalid(key: &'static str, problem: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key,
        problem: problem.into(),
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
    /// [`Config::generation`], its result dropped.
    fn validate(&self) -> Result<(), ConfigError> {
        self.generation().map(|_| ())
    }
}

impl Config {
    /// Checks the limits and resolves the generation settings
    /// ([`GenerationConfig::resolve`]).
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the key.
    pub fn generation(&self) -> Result<Generation, ConfigError> {
        self.check_limits()?;
        self.generation.resolve()
    }

    /// The queues' bounds and the timeouts.
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the key.
    fn check_limits(&self) -> Result<(), ConfigError> {
        for (key, q) in [("queue", &self.queue), ("outbox", &self.outbox)] {
            if q.max_items == 0 || q.max_bytes == 0 {
                return Err(invalid(key, "max_items and max_bytes must be ≥ 1"));
            }
        }
        if !(self.drain_timeout_secs.is_finite() && self.drain_timeout_secs >= 0.0) {
            return Err(invalid("drain_timeout_secs", "must be finite and ≥ 0"));
        }
        if !(self.max_backoff_secs.is_finite() && self.max_backoff_secs > 0.0) {
            return Err(invalid("max_backoff_secs", "must be finite and > 0"));
        }
        if !self.viz_shards.is_empty() && self.viz.is_none() {
            return Err(invalid("viz_shards", "needs viz, the first shard"));
        }
        if !(0..=19).contains(&self.nice) {
            return Err(invalid(
                "nice",
                format!("{} is not a nice level in 0–19", self.nice),
            ));
        }
        if !(self.host.wait_secs.is_finite() && (0.0..=3600.0).contains(&self.host.wait_secs)) {
            return Err(invalid("host.wait_secs", "must be seconds in [0, 3600]"));
        }
        if let Some(a) = &self.adios2 {
            if !cfg!(feature = "adios2") {
                return Err(invalid(
                    "adios2",
                    "this generator-node was built without ADIOS2; build it with `--features \
                     adios2` (ADIOS2's C library, docs/ranks-and-clients.md)",
                ));
            }
            let [part, parts] = a.part;
            if parts == 0 || part >= parts {
                return Err(invalid(
                    "adios2.part",
                    format!("[{part}, {parts}]: part i of n needs 0 ≤ i < n"),
                ));
            }
            if !(a.open_timeout_secs.is_finite() && a.open_timeout_secs > 0.0) {
                return Err(invalid(
                    "adios2.open_timeout_secs",
                    "must be finite and > 0",
                ));
            }
        }
        Ok(())
    }
}

impl GenerationConfig {
    /// The settings checked and resolved: VDI and ray-casting parameters, codec, the TF file
    /// read, the camera.
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the key (`generation.…`).
    pub fn resolve(&self) -> Result<Generation, ConfigError> {
        let params = VdiParams {
            resolution: self.resolution,
            gamma: self.gamma,
            precision: self.precision,
        };
        params
            .validate()
            .map_err(|e| invalid("generation.resolution/gamma/precision", e.to_string()))?;
        if self.old_step.is_some() {
            return Err(invalid(
                "generation.step",
                "not a key: the ray-casting sample distance is `sample_distance` (world units)",
            ));
        }
        let raycast = RaycastParams {
            sample_distance: self.sample_distance,
            termination: self.termination,
            generation_termination: self.generation_termination,
            ..Default::default()
        };
        raycast.validate().map_err(|e| {
            invalid(
                "generation.sample_distance/termination/generation_termination",
                e.to_string(),
            )
        })?;
        let codec = self.codec;
        let tf = match &self.tf {
            Some(p) => {
                let tf = TransferFunction::load(p)
                    .map_err(|e| invalid("generation.tf", e.to_string()))?;
                let name = p.file_name().map_or_else(
                    || p.display().to_string(),
                    |n| n.to_string_lossy().into_owned(),
                );
                Some(NamedTf::new(tf, name))
            }
            None => None,
        };
        let camera = self.camera.map(Camera::from);
        if camera.is_some_and(|c| !c.is_valid()) {
            return Err(invalid("generation.camera", "degenerate camera"));
        }
        if self.view_angles_deg.iter().any(|a| !a.is_finite()) {
            return Err(invalid(
                "generation.view_angles_deg",
                "angles must be finite",
            ));
        }
        if self.reference_size > insitu_core::vdi::MAX_RESOLUTION {
            return Err(invalid("generation.reference_size", "too large"));
        }
        if self.size_max == Some(0) {
            return Err(invalid(
                "generation.size_max",
                "0 bytes is no size; leave the key out for no limit",
            ));
        }
        if let Some(t) = self.time_max.filter(|t| !(t.is_finite() && *t > 0.0)) {
            return Err(invalid(
                "generation.time_max",
                format!("{t} is not a time in seconds > 0; leave the key out for no limit"),
            ));
        }
        if !(self.size_guard == 0.0 || (self.size_guard.is_finite() && self.size_guard >= 1.0)) {
            return Err(invalid(
                "generation.size_guard",
                format!(
                    "{} is not a ratio ≥ 1 of the tuner's size budget; 0 turns the guard off",
                    self.size_guard
                ),
            ));
        }
        if let Some(f) = &self.field {
            crate::ingest::check_field_name(f).map_err(|e| invalid("generation.field", e))?;
        }
        Ok(Generation {
            params,
            raycast,
            codec,
            tf,
            camera,
            view_angles_deg: self.view_angles_deg.clone(),
            reference_every: self.reference_every,
            reference_size: self.reference_size,
            limits: Budgets {
                size_bytes: self.size_max,
                time_secs: self.time_max,
            },
            size_guard: (self.size_guard > 0.0).then_some(self.size_guard),
            tuner_size_budget: None,
            field: self.field.clone(),
            pm_version: 0,
            scene_version: 0,
            previous: None,
            from_step: 0,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_documented_example_parses_and_matches_the_defaults() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/generator-node.toml");
        let cfg = Config::load(&path).unwrap();
        assert_eq!(cfg, Config::default());
    }

    #[test]
    fn bad_values_name_their_key() {
        let bad = |toml: &str| match toml::from_str::<Config>(toml) {
            Ok(c) => c.generation().unwrap_err().to_string(),
            Err(e) => e.to_string(),
        };
        assert!(bad("[generation]\nresolution = 0").contains("generation.resolution"));
        assert!(bad("[generation]\ngamma = -1.0").contains("generation.resolution/gamma"));
        for precision in ["3", "17", "\"half\""] {
            let e = bad(&format!("[generation]\nprecision = {precision}"));
            assert!(e.contains("precision"), "{precision}: {e}");
        }
        // The sample distance has its own name; `step` is a time step's word.
        let step = bad("[generation]\nstep = 0.25");
        assert!(step.contains("`sample_distance`"), "{step}");
        assert!(bad("[generation]\nsample_distance = -1.0").contains("sample_distance"));
        let codec = bad("[generation]\ncodec = \"lzma\"");
        assert!(codec.contains("codec") && codec.contains("lzma"), "{codec}");
        assert!(bad("[queue]\nmax_items = 0\nmax_bytes = 1\npolicy = \"block\"").contains("queue"));
        assert!(
            bad("[queue]\nmax_items = 1\nmax_bytes = 1\npolicy = \"drop-newest\"")
                .contains("drop-newest")
        );
        assert!(bad("listen = \"nowhere\"").contains("listen"));
        assert!(bad("nice = -5").contains("nice"));
        assert!(bad("nice = 20").contains("nice"));
        assert!(bad("colour = 3").contains("colour"));
        assert!(bad("[generation]\ntf = \"/no/such/tf.json\"").contains("generation.tf"));
        // No limit is the key left out, not a zero.
        let zero = bad("[generation]\nsize_max = 0");
        assert!(zero.contains("generation.size_max") && zero.contains("leave the key out"));
        assert!(bad("[generation]\ntime_max = 0.0").contains("generation.time_max"));
        assert!(bad("[generation]\ntime_max = -1.0").contains("generation.time_max"));
        let limits = |toml: &str| {
            toml::from_str::<Config>(toml)
                .unwrap()
                .generation()
                .unwrap()
        };
        let both = limits("[generation]\nsize_max = 1000\ntime_max = 0.5").limits;
        assert_eq!((both.size_bytes, both.time_secs), (Some(1000), Some(0.5)));
        assert!(limits("").limits.is_none());
        // The guard: a ratio ≥ 1, 0 for off, 1.25 by default.
        assert_eq!(limits("").size_guard, Some(DEFAULT_SIZE_GUARD));
        assert_eq!(limits("[generation]\nsize_guard = 0.0").size_guard, None);
        assert_eq!(
            limits("[generation]\nsize_guard = 2.0").size_guard,
            Some(2.0)
        );
        assert!(bad("[generation]\nsize_guard = 0.5").contains("generation.size_guard"));
        assert!(bad("[generation]\nsize_guard = nan").contains("generation.size_guard"));
        // An ADIOS2 input: its part checked where it can be read, the feature named where not.
        let part = bad("[adios2]\nstream = \"gs\"\npart = [2, 2]");
        if cfg!(feature = "adios2") {
            assert!(
                part.contains("adios2.part") && part.contains("[2, 2]"),
                "{part}"
            );
        } else {
            assert!(part.contains("--features adios2"), "{part}");
        }
    }
}
