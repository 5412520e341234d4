//! Steps read from an ADIOS2 writer's output (`[adios2]`, feature `adios2`): an SST stream
//! while the simulation runs, or a BP file step by step. A writer that already describes its
//! output through ADIOS2 changes its engine to SST (or its file's name) and nothing else.
//!
//! One thread owns the ADIOS2 engine (its calls block). For each step it reads this node's
//! part of the global array — part `i` of `n` is the `i`-th of `n` bricks that share their
//! boundary planes ([`bricks::grid_bricks`]), so the nodes that split one array compose
//! without seams and without exchanging a plane; or, `as_written`, the one block a writer
//! that opens a stream of its own put, whose neighbours' planes come through the exchange of
//! faces ([`crate::layout`]) — and hands it to the same path as a pushed step (layout check,
//! spool, queue), as rank `i` of a world of `n`. The queue's
//! policy applies: with `block`, a node that falls behind holds the writer back (SST's
//! queue fills), as a push would.
//!
//! A writer that goes through openPMD-api is read as openPMD: the field is a mesh by name,
//! each node's part is cut on the mesh's axes as labelled, read in the writer's order and put
//! x fastest (`insitu_readers::adios2::openpmd`).
//!
//! The stream ends when the writer closes it, when the writer goes away (SST reports an
//! error), or at shutdown; [`Input::finish`] says which, and after which step.

use crate::config::Adios2Input;
use crate::ingest::{RawStep, StepInfo};
use crate::service::GeneratorService;
use crate::shared::Shared;
use insitu_core::volume::{bricks, ScalarType, VoxelSlice};
use insitu_readers::adios2::{Engine, Step, Stream};
use insitu_readers::{adios2, ReadError};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tracing::{info, warn};

/// How long one wait for a step of a BP file lasts before the stop flag is looked at again.
const POLL: Duration = Duration::from_millis(250);

/// How long [`Input::finish`] waits for the reading thread. An SST reader waits for its next
/// step without a timeout (see `Stream::begin_step`), so at shutdown it may be waiting on a
/// writer that sends nothing more: it is then left to the process's exit.
const STOP_WAIT: Duration = Duration::from_secs(1);

/// The reading thread, and how it ended.
pub struct Input {
    stop: Arc<AtomicBool>,
    thread: std::thread::JoinHandle<()>,
    end: Arc<Mutex<Option<String>>>,
    progress: Arc<Mutex<Progress>>,
    stream: std::path::PathBuf,
}

/// What has been read: steps, and the last one.
#[derive(Default)]
struct Progress {
    steps: u64,
    last: Option<usize>,
}

impl Progress {
    fn describe(&self, stream: &std::path::Path, how: &str) -> String {
        match self.last {
            Some(last) => format!(
                "ADIOS2 stream {}: {} step(s) read, the last step {last}; {how}",
                stream.display(),
                self.steps
            ),
            None => format!("ADIOS2 stream {}: no step read; {how}", stream.display()),
        }
    }
}

impl Input {
    /// Starts reading `input` into `shared`'s queue on a thread of its own; steps are
    /// accepted through the tokio runtime `rt`.
    pub fn spawn(shared: Arc<Shared>, input: Adios2Input, rt: tokio::runtime::Handle) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let end = Arc::new(Mutex::new(None));
        let progress = Arc::new(Mutex::new(Progress::default()));
        let (s, e, p) = (stop.clone(), end.clone(), progress.clone());
        let stream = input.stream.clone();
        let thread = std::thread::spawn(move || {
            let how = match read(&shared, &input, &rt, &s, &p) {
                Ok(how) => how,
                Err(e) => {
                    warn!(error = %e, "the ADIOS2 input stopped");
                    format!("stopped by an error: {e}")
                }
            };
            let note = lock(&p).describe(&input.stream, &how);
            info!("{note}");
            *e.lock().unwrap_or_else(|e| e.into_inner()) = Some(note);
        });
        Self {
            stop,
            thread,
            end,
            progress,
            stream,
        }
    }

    /// Stops reading (at the next step or wait, within [`STOP_WAIT`]) and says how the
    /// stream ended.
    pub async fn finish(self) -> Option<String> {
        self.stop.store(true, Ordering::Relaxed);
        let deadline = tokio::time::Instant::now() + STOP_WAIT;
        while !self.thread.is_finished() && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        if !self.thread.is_finished() {
            let how = "stopped at shutdown while waiting for the writer's next step";
            return Some(lock(&self.progress).describe(&self.stream, how));
        }
        let thread = self.thread;
        let _ = tokio::task::spawn_blocking(move || thread.join()).await;
        self.end.lock().unwrap_or_else(|e| e.into_inner()).take()
    }
}

fn lock(p: &Mutex<Progress>) -> std::sync::MutexGuard<'_, Progress> {
    p.lock().unwrap_or_else(|e| e.into_inner())
}

/// Reads steps until the stream ends or `stop` is set; says how it ended.
fn read(
    shared: &Arc<Shared>,
    input: &Adios2Input,
    rt: &tokio::runtime::Handle,
    stop: &AtomicBool,
    progress: &Mutex<Progress>,
) -> Result<String, ReadError> {
    let engine = if adios2::is_bp(&input.stream) {
        Engine::File
    } else {
        Engine::Sst
    };
    let parameters: Vec<(String, String)> = input
        .parameters
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let timeout = Duration::from_secs_f64(input.open_timeout_secs);
    let mut stream = Stream::open(&input.stream, engine, &parameters, timeout)?;
    info!(stream = %input.stream.display(), ?engine, part = ?input.part, "reading an ADIOS2 stream");
    let service = GeneratorService(shared.clone());
    loop {
        if stop.load(Ordering::Relaxed) {
            return Ok("stopped at shutdown".into());
        }
        // SST waits without a timer (`Stream::begin_step`); a file is polled.
        let wait = (engine == Engine::File).then_some(POLL);
        let step = match stream.begin_step(wait) {
            Ok(Step::Ready(_)) if stop.load(Ordering::Relaxed) => {
                return Ok("stopped at shutdown".into())
            }
            Ok(Step::Ready(step)) => step,
            Ok(Step::NotReady) => continue,
            Ok(Step::End) => return Ok("the writer closed the stream".into()),
            // SST: the writer went away without closing; what was read stays.
            Err(e) => return Ok(format!("the writer went away ({e})")),
        };
        let raw = brick(shared, &service, &mut stream, input, step)?;
        stream.end_step()?;
        let (n, rank) = (raw.info.step, raw.info.rank);
        if let Err(status) = rt.block_on(service.accept(raw)) {
            return Ok(format!(
                "step {n} (rank {rank}) not taken: {}",
                status.message()
            ));
        }
        let mut p = lock(progress);
        p.steps += 1;
        p.last = Some(step);
    }
}

/// This node's brick of ADIOS2 step `step`, as a received step.
fn brick(
    shared: &Arc<Shared>,
    service: &GeneratorService,
    stream: &mut Stream,
    input: &Adios2Input,
    step: usize,
) -> Result<RawStep, ReadError> {
    let wanted = service
        .wanted_field(step as u64)
        .or_else(|| input.var.clone());
    let source = Source::of(stream, wanted, &input.stream, step)?;
    let (var, dims) = (source.name().to_owned(), source.dims());
    let [part, parts] = input.part;
    let own = if input.as_written {
        written(stream, &source, input, step)?
    } else {
        bricks::split_ranks(parts as usize, dims)
            .and_then(|split| bricks::grid_bricks(dims, split))
            .and_then(|b| b.get(part as usize).copied())
            .ok_or_else(|| ReadError::Invalid {
                path: input.stream.clone(),
                problem: format!(
                    "variable {var}: a grid of {dims:?} points cannot be split into {parts} \
                     parts that share their planes",
                ),
            })?
    };
    let (spacing, origin) = source.grid();
    let field = match &source {
        Source::Array { var, .. } => stream.read(var, own.offset, own.dims, None, spacing)?,
        Source::Mesh { var, layout, .. } => {
            stream.read_mesh(var, layout, own.offset, own.dims, None, spacing)?
        }
    };
    let info = StepInfo {
        step: step as u64,
        sim_time: step as f64,
        rank: part,
        world_size: parts,
        // The type kept (a type the core does not keep arrives as f32).
        dtype: match field.voxels() {
            VoxelSlice::U8(_) => ScalarType::U8,
            VoxelSlice::U16(_) => ScalarType::U16,
            VoxelSlice::I16(_) => ScalarType::I16,
            VoxelSlice::F32(_) => ScalarType::F32,
        },
        global_dims: dims,
        brick_offset: own.offset,
        brick_dims: own.dims,
        spacing,
        origin,
    };
    let at = origin + glam::Vec3::from(own.offset.map(|o| o as f32)) * spacing;
    let field = field.with_origin(at).map_err(|e| ReadError::Invalid {
        path: input.stream.clone(),
        problem: format!("step {step}: {e}"),
    })?;
    shared
        .layout
        .admit(&info)
        .map_err(|status| ReadError::Invalid {
            path: input.stream.clone(),
            problem: format!("step {step}: {}", status.message()),
        })?;
    Ok(RawStep {
        info,
        field,
        spool: None,
        fields: vec![var.clone()],
        field_name: Some(var),
    })
}

/// The one block the writer put of `source` in step `step`, as this node's brick
/// (`as_written`).
///
/// # Errors
/// [`ReadError`] naming the stream and variable: an openPMD mesh (its blocks are read by
/// `part`), or a step that holds other than one block.
fn written(
    stream: &Stream,
    source: &Source,
    input: &Adios2Input,
    step: usize,
) -> Result<bricks::Brick, ReadError> {
    let bad = |problem: String| ReadError::Invalid {
        path: input.stream.clone(),
        problem,
    };
    let Source::Array { var, .. } = source else {
        return Err(bad(format!(
            "mesh {}: as_written reads a plain global array's block; read an openPMD mesh by part",
            source.name()
        )));
    };
    match stream.blocks(var, step)?.as_slice() {
        [brick] => Ok(*brick),
        blocks => Err(bad(format!(
            "variable {var}: step {step} holds {} blocks; as_written reads the one block of a \
             writer that opens a stream of its own (read a stream of several blocks by part)",
            blocks.len()
        ))),
    }
}

/// What a step's field is read from: a plain 3-D global array, or an openPMD mesh (its
/// variable in this step, and how its axes lie).
enum Source {
    Array {
        var: String,
        dims: [usize; 3],
        /// Spacing and origin.
        grid: (glam::Vec3, glam::Vec3),
    },
    Mesh {
        name: String,
        var: String,
        layout: adios2::openpmd::Layout,
    },
}

impl Source {
    /// The field `wanted` (else the first) of the current step of `stream`: an openPMD mesh
    /// by its name where the writer is openPMD, else a global array.
    fn of(
        stream: &Stream,
        wanted: Option<String>,
        path: &std::path::Path,
        step: usize,
    ) -> Result<Self, ReadError> {
        let missing = |what: &str, here: String| ReadError::Invalid {
            path: path.to_owned(),
            problem: format!("step {step} holds no {what}; here: {here}"),
        };
        if adios2::openpmd::is_openpmd(stream) {
            // This step's meshes: one variable each (steps of one variable, or this
            // iteration's group).
            let meshes = adios2::openpmd::meshes(stream, |_| 1);
            let names = || {
                meshes
                    .iter()
                    .map(|m| m.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            let mesh = match &wanted {
                Some(w) => meshes.iter().find(|m| &m.name == w),
                None => meshes.first(),
            };
            let Some((name, it)) = mesh.and_then(|m| Some((&m.name, m.iterations.last()?))) else {
                let what = wanted.map_or("openPMD mesh".into(), |w| format!("openPMD mesh {w:?}"));
                return Err(missing(&what, names()));
            };
            let layout = adios2::openpmd::layout(stream, name, &it.var)?;
            return Ok(Self::Mesh {
                name: name.clone(),
                var: it.var.clone(),
                layout,
            });
        }
        let var = match wanted {
            Some(w) => w,
            None => stream
                .volumes()
                .into_iter()
                .next()
                .ok_or_else(|| missing("3-D global array", stream.variables().join(", ")))?,
        };
        let dims = stream.variable(&var)?.dims;
        let (spacing, origin, _) = stream.grid(&var);
        Ok(Self::Array {
            var,
            dims,
            grid: (spacing, origin),
        })
    }

    /// The field's name: the variable, or the mesh (`rho`, `E/x`).
    fn name(&self) -> &str {
        match self {
            Self::Array { var, .. } => var,
            Self::Mesh { name, .. } => name,
        }
    }

    /// The grid's points (x, y, z).
    fn dims(&self) -> [usize; 3] {
        match self {
            Self::Array { dims, .. } => *dims,
            Self::Mesh { layout, .. } => layout.dims,
        }
    }

    /// Spacing and origin.
    fn grid(&self) -> (glam::Vec3, glam::Vec3) {
        match self {
            Self::Array { grid, .. } => *grid,
            Self::Mesh { layout, .. } => (layout.spacing, layout.origin),
        }
    }
}
