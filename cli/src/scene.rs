//! Scene flags shared by the subcommands: volume source, transfer function, camera, step.

use anyhow::{bail, Context, Result};
use clap::Args;
use insitu_core::raycast::{DEFAULT_GENERATION_TERMINATION, DEFAULT_STEP, DEFAULT_TERMINATION};
use insitu_core::volume::{GrayScott, RawFormat, ScalarType};
use insitu_core::{Camera, RaycastParams, Shading, TransferFunction, Volume};
use std::path::PathBuf;

/// The embedded default volume source.
pub const DEFAULT_SOURCE: &str = "gray-scott:64:1000";

/// Where the data comes from and how it is classified and sampled.
#[derive(Args, Debug, Clone)]
pub struct SceneArgs {
    /// Volume: a file (`.vti`, `.vtk`, `.nrrd`/`.nhdr`, `.nc`, `.h5`, `.xmf`, ADIOS2 `.bp`/`.bp5`
    /// with openPMD meshes read as such and `run_%T.bp5` for one file per iteration, or raw
    /// `<name>_<X>x<Y>x<Z>[x<T>]_<type>.raw`; docs/data.md), or `gray-scott:N[:STEPS]` (the
    /// built-in simulation). Default: the built-in Gray–Scott run.
    #[arg(long)]
    pub volume: Option<String>,
    /// The field to render from a file with several (a VTK array, a NetCDF variable, an HDF5
    /// dataset's path, an XDMF attribute, an ADIOS2 variable, an openPMD mesh: `rho`, `E/x`).
    /// Default: the file's active scalars, else its first.
    #[arg(long, visible_aliases = ["var", "dataset"])]
    pub field: Option<String>,
    /// How an uneven NetCDF axis (an ocean model's depth levels) is taken: `resample` (to an
    /// even grid at its smallest gap, linearly; said on stderr) or `index` (its levels one unit
    /// apart, as a raw file would hold them).
    #[arg(long, value_enum, default_value_t = UnevenAxis::Resample)]
    pub uneven: UnevenAxis,
    /// Dimensions `XxYxZ[xT]` when the file name does not carry them.
    #[arg(long)]
    pub dims: Option<String>,
    /// Voxel type (uint8, uint16, int16, float32, float64) when the file name does not carry it.
    #[arg(long = "type")]
    pub scalar_type: Option<String>,
    /// Time step of a 4-D file (its index along T, from 0).
    #[arg(long = "time-step", default_value_t = 0)]
    pub t: usize,
    /// Voxel spacing `sx,sy,sz` in world units (default: the file's; 1,1,1 for raw files).
    #[arg(long)]
    pub spacing: Option<String>,
    /// Transfer function JSON (docs/conventions.md format). Default: a ramp over the data range.
    #[arg(long)]
    pub tf: Option<PathBuf>,
    /// Ray-casting sample distance, world units (voxels at spacing 1).
    #[arg(long = "sample-distance", default_value_t = DEFAULT_STEP)]
    pub step: f32,
    /// Early ray termination threshold on accumulated opacity, in (0, 1], of direct renderings
    /// and of VDI rendering.
    #[arg(long, default_value_t = DEFAULT_TERMINATION)]
    pub termination: f32,
    /// Early termination of VDI generation rays: a threshold in (0, 1], or `off` (rays run to
    /// the box exit, so the VDI keeps what lies behind dense structures).
    #[arg(long, default_value_t = GenerationTermination(DEFAULT_GENERATION_TERMINATION), value_parser = parse_generation_termination)]
    pub generation_termination: GenerationTermination,
    /// Turn on Blinn–Phong gradient shading (off: emission–absorption only).
    #[arg(long)]
    pub shading: bool,
    /// Turn off empty-space skipping (same image, slower; for measurements).
    #[arg(long)]
    pub no_skipping: bool,
}

/// A loaded scene.
pub struct Scene {
    pub volume: Volume,
    pub tf: TransferFunction,
    pub tf_name: String,
    pub volume_name: String,
    pub params: RaycastParams,
}

impl SceneArgs {
    /// Loads the volume and TF and checks the parameters.
    pub fn load(&self) -> Result<Scene> {
        let source = self.volume.as_deref().unwrap_or(DEFAULT_SOURCE);
        // Raw samples: a `.raw` file, one described by --dims and --type, or one whose name
        // gives its layout; the formats with a header go to their reader (which names the
        // formats it knows when the extension is none of them).
        let path = std::path::Path::new(source);
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        let has_header = ext != "raw" && insitu_readers::EXTENSIONS.contains(&ext.as_str());
        let is_raw = !has_header
            && (ext == "raw"
                || self.dims.is_some()
                || self.scalar_type.is_some()
                || RawFormat::from_file_name(path).is_ok());
        let volume = if source.starts_with("gray-scott") {
            self.refuse_raw_flags(source, "the built-in simulation on its own unit grid")?;
            tracing::info!(source, "running the built-in Gray-Scott simulation");
            GrayScott::from_spec(source)?.v_volume()
        } else if is_raw {
            self.load_raw(source)?
        } else {
            self.load_file(source)?
        };
        warn_if_flat(source, &volume);
        let tf_name;
        let tf = match &self.tf {
            Some(path) => {
                tf_name = path
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default();
                TransferFunction::load(path)?
            }
            None => {
                let named = TransferFunction::default_for_volume(&volume);
                tf_name = named.name;
                named.tf
            }
        };
        let params = RaycastParams {
            sample_distance: self.step,
            termination: self.termination,
            generation_termination: self.generation_termination.0,
            shading: self.shading.then(Shading::default),
            empty_space_skipping: !self.no_skipping,
        };
        params.validate()?;
        Ok(Scene {
            volume,
            tf,
            tf_name,
            volume_name: source.to_owned(),
            params,
        })
    }

    /// The flags that describe a raw file, refused for a source that says all of it itself
    /// (`what` it is) rather than silently ignored.
    fn refuse_raw_flags(&self, source: &str, what: &str) -> Result<()> {
        let builtin = source.starts_with("gray-scott");
        let given = [
            ("--dims", self.dims.is_some()),
            ("--type", self.scalar_type.is_some()),
            ("--time-step", builtin && self.t != 0),
            ("--spacing", builtin && self.spacing.is_some()),
            ("--field", builtin && self.field.is_some()),
        ];
        let given: Vec<&str> = given.iter().filter(|g| g.1).map(|g| g.0).collect();
        if !given.is_empty() {
            bail!(
                "{} describe a raw file; {source} is {what}",
                given.join(", ")
            );
        }
        Ok(())
    }

    /// A file in one of the formats `insitu-readers` takes: step `--time-step`, the file's
    /// origin and spacing (`--spacing` overrides the spacing); what the reader did to fit the
    /// grid is said on stderr.
    fn load_file(&self, source: &str) -> Result<Volume> {
        self.refuse_raw_flags(source, "a file that gives its own dims and type")?;
        let data = open_dataset(
            std::path::Path::new(source),
            self.field.as_deref(),
            self.uneven,
        )?;
        let volume = data.read_step(self.t)?;
        Ok(match &self.spacing {
            Some(s) => volume
                .with_spacing(parse_spacing(s)?)
                .with_context(|| format!("--spacing {s}"))?,
            None => volume,
        })
    }

    fn load_raw(&self, source: &str) -> Result<Volume> {
        let path = PathBuf::from(source);
        let spacing = parse_spacing(self.spacing.as_deref().unwrap_or("1,1,1"))?;
        let from_name = || RawFormat::from_file_name(&path);
        let format = match (&self.dims, &self.scalar_type) {
            (None, None) => from_name()?,
            (dims, scalar) => {
                let (dims, steps) = match dims {
                    Some(d) => parse_dims(d)?,
                    None => from_name().map(|f| (f.dims, f.steps))?,
                };
                let scalar = match scalar {
                    Some(t) => t.parse::<ScalarType>()?,
                    None => from_name()?.scalar,
                };
                RawFormat {
                    dims,
                    steps,
                    scalar,
                }
            }
        };
        Ok(format.load(&path, self.t, spacing)?)
    }

    /// The generation camera: the default view of the volume box.
    pub fn camera(scene: &Scene) -> Camera {
        Camera::default_for_box(&scene.volume.world_box())
    }
}

/// Warns when `volume` is one voxel thick along an axis: its box spans `(n − 1)·s` there
/// (docs/conventions.md, "Volume"), so it has no depth, rays cross nothing, and every image and VDI of
/// it is empty — right by the convention, but a black image should not come unexplained.
fn warn_if_flat(source: &str, volume: &Volume) {
    let flat: Vec<&str> = ["x", "y", "z"]
        .into_iter()
        .zip(volume.dims())
        .filter(|&(_, n)| n == 1)
        .map(|(axis, _)| axis)
        .collect();
    if !flat.is_empty() {
        tracing::warn!(
            "{source} is one voxel thick along {}: its box spans (n − 1) × spacing there, so it \
             has no depth and renders empty; give it two or more slices",
            flat.join(" and ")
        );
    }
}

fn parse_dims(s: &str) -> Result<([usize; 3], usize)> {
    let nums: Vec<usize> = s
        .split('x')
        .map(str::parse)
        .collect::<Result<_, _>>()
        .with_context(|| format!("--dims {s:?} is not XxYxZ[xT]"))?;
    match nums.as_slice() {
        [x, y, z] => Ok(([*x, *y, *z], 1)),
        [x, y, z, t] => Ok(([*x, *y, *z], *t)),
        _ => bail!("--dims {s:?} is not XxYxZ[xT]"),
    }
}

/// How an uneven axis of a NetCDF file is taken (`--uneven`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum UnevenAxis {
    /// Resampled to an even grid at its smallest gap, linearly.
    Resample,
    /// Its levels taken one unit apart.
    Index,
}

/// Opens `path` with the reader its extension names (`field` chosen, an uneven NetCDF axis
/// taken as `uneven` says) and says on stderr what the reader did to fit the grid.
///
/// # Errors
/// What the reader finds wrong, naming the file.
pub fn open_dataset(
    path: &std::path::Path,
    field: Option<&str>,
    uneven: UnevenAxis,
) -> Result<insitu_readers::Dataset> {
    let options = insitu_readers::Options {
        field: field.map(str::to_owned),
        uneven: match uneven {
            UnevenAxis::Resample => insitu_readers::Uneven::Resample,
            UnevenAxis::Index => insitu_readers::Uneven::Index,
        },
    };
    let data = insitu_readers::open(path, &options)?;
    for note in &data.notes {
        eprintln!("note: {}: {note}", path.display());
    }
    Ok(data)
}

fn parse_spacing(s: &str) -> Result<glam::Vec3> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--spacing {s:?} is not sx,sy,sz"))?;
    match v.as_slice() {
        [x, y, z] => Ok(glam::Vec3::new(*x, *y, *z)),
        [s] => Ok(glam::Vec3::splat(*s)),
        _ => bail!("--spacing {s:?} is not sx,sy,sz"),
    }
}

/// `--generation-termination`: a threshold, or `None` for off.
#[derive(Clone, Copy, Debug)]
pub struct GenerationTermination(pub Option<f32>);

impl std::fmt::Display for GenerationTermination {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            Some(a) => write!(f, "{a}"),
            None => f.write_str("off"),
        }
    }
}

/// Parses `off` or a threshold in (0, 1].
pub fn parse_generation_termination(s: &str) -> Result<GenerationTermination, String> {
    if s.eq_ignore_ascii_case("off") {
        return Ok(GenerationTermination(None));
    }
    match s.parse::<f32>() {
        Ok(a) if a > 0.0 && a <= 1.0 => Ok(GenerationTermination(Some(a))),
        _ => Err(format!("{s:?} is neither `off` nor a threshold in (0, 1]")),
    }
}
