//! One ADIOS2 stream opened through the C library: an SST stream read live step by step, or
//! a BP file read at any step. Its variables, their Shape and type, a selection read into a
//! volume; each call's soundness is argued beside it.

use super::{ffi, openpmd};
use crate::bytes::{Endian, Sample, Samples};
use crate::ReadError;
use glam::Vec3;
use insitu_core::volume::bricks::Brick;
use insitu_core::Volume;
use std::ffi::{CStr, CString};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// An ADIOS2 engine the reader opens.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Engine {
    /// A BP4 or BP5 file (directory) read step by step; the library tells which.
    File,
    /// A live SST stream, found through the `NAME.sst` contact file the writer leaves in its
    /// working directory (a shared file system, or the same directory).
    Sst,
}

impl Engine {
    fn name(self) -> &'static CStr {
        match self {
            Self::File => c"BPFile",
            Self::Sst => c"SST",
        }
    }
}

/// What a variable holds, as this reader sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Variable {
    /// Its name.
    pub name: String,
    /// The global Shape as grid dims (x, y, z): the Shape reversed.
    pub dims: [usize; 3],
    /// The type of its samples.
    pub sample: Sample,
}

/// How a step began.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// A step is open; its ADIOS2 index.
    Ready(usize),
    /// None came within the timeout; the stream is still open.
    NotReady,
    /// The writer closed the stream: no more steps.
    End,
}

/// An open ADIOS2 engine: one ADIOS object, one IO, one engine, all closed on drop.
pub struct Stream {
    pub(super) name: PathBuf,
    adios: *mut ffi::adios2_adios,
    io: *mut ffi::adios2_io,
    engine: *mut ffi::adios2_engine,
    /// The bytes of the last selection read, kept for the next.
    scratch: Vec<u8>,
}

// SAFETY: the handles belong to this value alone and ADIOS2 keeps no thread-local state for
// them; `&mut self` on every call that touches the engine keeps calls serial.
unsafe impl Send for Stream {}

impl std::fmt::Debug for Stream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Stream").field("name", &self.name).finish()
    }
}

fn c_string(name: &Path, what: &str, s: &str) -> Result<CString, ReadError> {
    CString::new(s).map_err(|_| ReadError::invalid(name, format!("{what} {s:?} holds a NUL byte")))
}

impl Stream {
    /// Opens `name` with `engine` for reading step by step, with ADIOS2 engine `parameters`
    /// (e.g. SST's `DataTransport`). An SST stream waits at most `open_timeout` for its
    /// writer (SST's `OpenTimeoutSecs`).
    ///
    /// # Errors
    /// [`ReadError`] naming the stream: ADIOS2 cannot open it (no such file; no SST writer
    /// within the timeout, which it names), a parameter it refuses.
    pub fn open(
        name: &Path,
        engine: Engine,
        parameters: &[(String, String)],
        open_timeout: Duration,
    ) -> Result<Self, ReadError> {
        Self::open_mode(name, engine, parameters, open_timeout, ffi::MODE_READ)
    }

    pub(super) fn open_mode(
        name: &Path,
        engine: Engine,
        parameters: &[(String, String)],
        open_timeout: Duration,
        mode: ffi::adios2_mode,
    ) -> Result<Self, ReadError> {
        let c_name = c_string(name, "stream name", &name.to_string_lossy())?;
        // SAFETY: plain constructor; null on failure, checked.
        let adios = unsafe { ffi::adios2_init_serial() };
        if adios.is_null() {
            return Err(ReadError::invalid(name, "ADIOS2 could not be initialised"));
        }
        let mut s = Self {
            name: name.to_owned(),
            adios,
            io: std::ptr::null_mut(),
            engine: std::ptr::null_mut(),
            scratch: Vec::new(),
        };
        // SAFETY: `adios` is live; the name is a NUL-terminated string that outlives the call.
        s.io = unsafe { ffi::adios2_declare_io(adios, c"insitu".as_ptr()) };
        if s.io.is_null() {
            return Err(ReadError::invalid(name, "ADIOS2 declared no IO"));
        }
        // SAFETY: `io` is live; the engine's name is a static C string.
        let code = unsafe { ffi::adios2_set_engine(s.io, engine.name().as_ptr()) };
        s.check(code, "setting the engine")?;
        let mut all = parameters.to_vec();
        if engine == Engine::Sst && !parameters.iter().any(|(k, _)| k == "OpenTimeoutSecs") {
            all.push((
                "OpenTimeoutSecs".into(),
                open_timeout.as_secs().max(1).to_string(),
            ));
        }
        for (k, v) in &all {
            let (ck, cv) = (c_string(name, "parameter", k)?, c_string(name, "value", v)?);
            // SAFETY: `io` is live; both strings outlive the call.
            let code = unsafe { ffi::adios2_set_parameter(s.io, ck.as_ptr(), cv.as_ptr()) };
            s.check(code, &format!("parameter {k}={v}"))?;
        }
        // SAFETY: `io` is live; the name outlives the call; null when the engine cannot
        // open, checked.
        s.engine = unsafe { ffi::adios2_open(s.io, c_name.as_ptr(), mode) };
        if s.engine.is_null() {
            let why = match engine {
                Engine::Sst => format!(
                    "no SST writer opened it within {} s (its contact file {}.sst is looked \
                     for in this directory)",
                    open_timeout.as_secs().max(1),
                    name.display()
                ),
                Engine::File => "ADIOS2 cannot open it as a BP file (missing, truncated or \
                                 not BP3/BP4/BP5)"
                    .into(),
            };
            return Err(ReadError::invalid(name, why));
        }
        Ok(s)
    }

    /// The stream's name as opened.
    pub fn name(&self) -> &Path {
        &self.name
    }

    fn check(&self, code: ffi::adios2_error, what: &str) -> Result<(), ReadError> {
        if code == ffi::ERROR_NONE {
            return Ok(());
        }
        let kind = match code {
            1 => "invalid argument",
            2 => "system error",
            3 => "runtime error",
            _ => "exception",
        };
        Err(ReadError::invalid(
            &self.name,
            format!("{what}: ADIOS2 reports a {kind} (its message is on standard error)"),
        ))
    }

    /// Waits at most `timeout` for the next step (`None`: until one comes or the stream
    /// ends).
    ///
    /// An SST reader should wait without a timeout: SST arms an EVPath timer for a finite one
    /// and removes it when the step comes first, and that removal crashed the process now and
    /// then (a SIGSEGV in `CMremove_task`, about one run in four of 17 steps of 64 MiB with
    /// the wheel 2.12).
    ///
    /// # Errors
    /// [`ReadError`] naming the stream when ADIOS2 reports an error (a truncated file, a
    /// writer gone without closing).
    pub fn begin_step(&mut self, timeout: Option<Duration>) -> Result<Step, ReadError> {
        let mut status = ffi::STEP_OK;
        // ADIOS2's "no timeout": a negative number of seconds.
        let secs = timeout.map_or(-1.0, |t| t.as_secs_f32());
        // SAFETY: `engine` is live; `status` outlives the call.
        let code =
            unsafe { ffi::adios2_begin_step(self.engine, ffi::STEP_MODE_READ, secs, &mut status) };
        self.check(code, "beginning a step")?;
        match status {
            ffi::STEP_OK => {
                let mut step = 0usize;
                // SAFETY: as above.
                let code = unsafe { ffi::adios2_current_step(&mut step, self.engine) };
                self.check(code, "the current step")?;
                Ok(Step::Ready(step))
            }
            ffi::STEP_NOT_READY => Ok(Step::NotReady),
            ffi::STEP_END_OF_STREAM => Ok(Step::End),
            _ => Err(ReadError::invalid(
                &self.name,
                "beginning a step: ADIOS2 reports an error of the stream",
            )),
        }
    }

    /// Ends the step begun.
    ///
    /// # Errors
    /// [`ReadError`] naming the stream when ADIOS2 reports an error.
    pub fn end_step(&mut self) -> Result<(), ReadError> {
        // SAFETY: `engine` is live.
        let code = unsafe { ffi::adios2_end_step(self.engine) };
        self.check(code, "ending a step")
    }

    /// The names of the variables of the current step (or of the file).
    pub fn variables(&self) -> Vec<String> {
        let mut n = 0usize;
        // SAFETY: `io` is live; the array and its strings are malloc'd by the library and
        // freed here after being copied.
        unsafe {
            let names = ffi::adios2_available_variables(self.io, &mut n);
            if names.is_null() {
                return Vec::new();
            }
            let out = (0..n)
                .filter_map(|i| {
                    let p = *names.add(i);
                    (!p.is_null()).then(|| {
                        let s = CStr::from_ptr(p).to_string_lossy().into_owned();
                        free(p.cast());
                        s
                    })
                })
                .collect();
            free(names.cast());
            let mut out: Vec<String> = out;
            out.sort();
            out
        }
    }

    /// The 3-D global arrays among [`Self::variables`].
    pub fn volumes(&self) -> Vec<String> {
        self.variables()
            .into_iter()
            .filter(|v| self.variable(v).is_ok())
            .collect()
    }

    fn handle(&self, var: &str) -> Result<*mut ffi::adios2_variable, ReadError> {
        let c = c_string(&self.name, "variable", var)?;
        // SAFETY: `io` is live; null when absent, checked.
        let h = unsafe { ffi::adios2_inquire_variable(self.io, c.as_ptr()) };
        if h.is_null() {
            let known = self.variables();
            return Err(ReadError::invalid(
                &self.name,
                format!(
                    "no variable {var:?} in this step; variables here: {}",
                    if known.is_empty() {
                        "none".into()
                    } else {
                        known.join(", ")
                    }
                ),
            ));
        }
        Ok(h)
    }

    /// What `var` holds.
    ///
    /// # Errors
    /// [`ReadError`] naming the stream and the variable: absent, not a global array, not
    /// 3-D, or of a type this reader does not take.
    pub fn variable(&self, var: &str) -> Result<Variable, ReadError> {
        let h = self.handle(var)?;
        let bad = |what: String| ReadError::invalid(&self.name, format!("variable {var}: {what}"));
        let (mut shape_id, mut ndims, mut t) = (0, 0usize, 0);
        // SAFETY: `h` is live while `io` is; the out-parameters outlive the calls.
        unsafe {
            self.check(ffi::adios2_variable_shapeid(&mut shape_id, h), var)?;
            self.check(ffi::adios2_variable_ndims(&mut ndims, h), var)?;
            self.check(ffi::adios2_variable_type(&mut t, h), var)?;
        }
        if shape_id != ffi::SHAPE_GLOBAL_ARRAY {
            return Err(bad(
                "not a global array (a value, or a local array without a Shape): a volume is \
                 a 3-D global array"
                    .into(),
            ));
        }
        if ndims != 3 {
            return Err(bad(format!(
                "{ndims}-D: a volume is a 3-D global array (z, y, x), one ADIOS2 step per time step"
            )));
        }
        let mut shape = [0usize; 3];
        // SAFETY: `shape` has room for the three dimensions checked above.
        unsafe { self.check(ffi::adios2_variable_shape(shape.as_mut_ptr(), h), var)? };
        let sample = match (sample_of(t), t) {
            (Some(s), _) => s,
            (None, ffi::TYPE_STRING) => return Err(bad("holds strings, not numbers".into())),
            (None, other) => {
                return Err(bad(format!(
                    "of ADIOS2 type {other} (complex or long double): volumes are integers or \
                     floats"
                )))
            }
        };
        Ok(Variable {
            name: var.to_owned(),
            dims: [shape[2], shape[1], shape[0]],
            sample,
        })
    }

    /// Reads the box `offset + [0, count)` (x, y, z, in grid points) of `var` in the current
    /// step (or, for a file opened by [`open`], of step `step`) into `self`'s scratch bytes,
    /// in the variable's own type; returns them with that type.
    ///
    /// # Errors
    /// [`ReadError`] naming the stream and variable: as [`Self::variable`], a box outside
    /// the Shape (naming both), a box over the read limit, or ADIOS2 failing to read it.
    pub fn read_bytes(
        &mut self,
        var: &str,
        offset: [usize; 3],
        count: [usize; 3],
        step: Option<usize>,
    ) -> Result<(&[u8], Sample), ReadError> {
        let v = self.variable(var)?;
        let inside = (0..3).all(|a| {
            count[a] > 0
                && offset[a]
                    .checked_add(count[a])
                    .is_some_and(|end| end <= v.dims[a])
        });
        if !inside {
            return Err(ReadError::invalid(
                &self.name,
                format!(
                    "variable {var}: the selection at {offset:?} of {count:?} points (x, y, z) \
                     lies outside its Shape {:?}",
                    v.dims
                ),
            ));
        }
        let n = crate::samples(&self.name, &count)?;
        crate::limit::check(&self.name, n, v.sample.size())?;
        let bytes = n * v.sample.size();
        self.scratch.clear();
        self.scratch.try_reserve_exact(bytes).map_err(|_| {
            ReadError::invalid(
                &self.name,
                format!("out of memory: {bytes} bytes for variable {var}"),
            )
        })?;
        self.scratch.resize(bytes, 0);
        let h = self.handle(var)?;
        let (start, count_zyx) = (
            [offset[2], offset[1], offset[0]],
            [count[2], count[1], count[0]],
        );
        // SAFETY: `h` and `engine` are live; the selection arrays hold three entries; the
        // scratch buffer holds exactly the selection's samples in the variable's own type, as
        // a synchronous get writes them.
        unsafe {
            self.check(
                ffi::adios2_set_selection(h, 3, start.as_ptr(), count_zyx.as_ptr()),
                &format!("selecting {var}"),
            )?;
            if let Some(t) = step {
                self.check(
                    ffi::adios2_set_step_selection(h, t, 1),
                    &format!("selecting step {t} of {var}"),
                )?;
            }
            let code = ffi::adios2_get(
                self.engine,
                h,
                self.scratch.as_mut_ptr().cast(),
                ffi::MODE_SYNC,
            );
            self.check(code, &format!("reading {var}"))?;
        }
        Ok((&self.scratch, v.sample))
    }

    /// The blocks the writers put of `var` in step `step` (the current one of a stream), as
    /// bricks of the grid (offset and count in points, x, y, z), in the order ADIOS2 lists
    /// them (writer, then block).
    ///
    /// # Errors
    /// [`ReadError`] naming the stream and variable: as [`Self::variable`], or ADIOS2 telling
    /// nothing of its blocks.
    pub fn blocks(&self, var: &str, step: usize) -> Result<Vec<Brick>, ReadError> {
        self.variable(var)?;
        let h = self.handle(var)?;
        // SAFETY: `engine` and `h` are live; the library allocates the answer, which is read
        // within its `nblocks` entries of `Dims` (3, checked) starts and counts each, and freed
        // once here.
        unsafe {
            let info = ffi::adios2_inquire_blockinfo(self.engine, h, step);
            if info.is_null() {
                return Err(ReadError::invalid(
                    &self.name,
                    format!("variable {var}: ADIOS2 lists no blocks of it in step {step}"),
                ));
            }
            let i = &*info;
            let mut out = Vec::new();
            if i.Dims == 3 && !i.BlocksInfo.is_null() {
                for b in std::slice::from_raw_parts(i.BlocksInfo, i.nblocks) {
                    if b.Start.is_null() || b.Count.is_null() {
                        continue;
                    }
                    let start = std::slice::from_raw_parts(b.Start, 3);
                    let count = std::slice::from_raw_parts(b.Count, 3);
                    out.push(Brick {
                        offset: [start[2], start[1], start[0]],
                        dims: [count[2], count[1], count[0]],
                    });
                }
            }
            let dims = i.Dims;
            ffi::adios2_free_blockinfo(info);
            if dims != 3 {
                return Err(ReadError::invalid(
                    &self.name,
                    format!("variable {var}: its blocks have {dims} dimensions, not 3"),
                ));
            }
            Ok(out)
        }
    }

    /// The box of [`Self::read_bytes`] as a volume at `spacing` (placed at the origin).
    ///
    /// # Errors
    /// As [`Self::read_bytes`].
    pub fn read(
        &mut self,
        var: &str,
        offset: [usize; 3],
        count: [usize; 3],
        step: Option<usize>,
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let name = self.name.clone();
        let (bytes, sample) = self.read_bytes(var, offset, count, step)?;
        volume(&name, bytes, sample, count, spacing)
    }

    /// The box `offset + [0, count)` (x, y, z of the mesh, in grid points) of openPMD mesh
    /// variable `var` laid out as `layout` says, as a volume at `spacing` (placed at the
    /// origin): the samples read in the writer's order and reordered x fastest.
    ///
    /// # Errors
    /// As [`Self::read_bytes`]; and where the variable's Shape no longer matches `layout`.
    pub fn read_mesh(
        &mut self,
        var: &str,
        layout: &openpmd::Layout,
        offset: [usize; 3],
        count: [usize; 3],
        step: Option<usize>,
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let name = self.name.clone();
        let v = self.variable(var)?;
        let shape = [v.dims[2], v.dims[1], v.dims[0]];
        let dims = layout.axes.map(|d| shape[d]);
        if dims != layout.dims {
            return Err(ReadError::invalid(
                &name,
                format!(
                    "openPMD mesh {var}: {dims:?} points (x, y, z) where its first step had {:?}",
                    layout.dims
                ),
            ));
        }
        // The box in the array's own dimensions (0 the slowest).
        let (mut at, mut size) = ([0usize; 3], [0usize; 3]);
        for a in 0..3 {
            at[layout.axes[a]] = offset[a];
            size[layout.axes[a]] = count[a];
        }
        let (bytes, sample) = self.read_bytes(
            var,
            [at[2], at[1], at[0]],
            [size[2], size[1], size[0]],
            step,
        )?;
        let ordered;
        let bytes = if layout.is_zyx() {
            bytes
        } else {
            ordered = openpmd::reorder(bytes, sample.size(), size, layout.axes);
            &ordered
        };
        volume(&name, bytes, sample, count, spacing)
    }

    /// The numbers of attribute `name` (none when absent or text).
    pub fn numbers(&self, name: &str) -> Option<Vec<f64>> {
        let a = self.attribute(name)?;
        let (mut t, mut n) = (0, 0usize);
        // SAFETY: `a` is live; the out-parameters outlive the calls.
        unsafe {
            if ffi::adios2_attribute_type(&mut t, a) != ffi::ERROR_NONE
                || ffi::adios2_attribute_size(&mut n, a) != ffi::ERROR_NONE
            {
                return None;
            }
        }
        let sample = sample_of(t)?;
        let size = sample.size();
        if n == 0 || n > 64 {
            return None;
        }
        let mut bytes = vec![0u8; n * size];
        let mut got = 0usize;
        // SAFETY: `bytes` holds the attribute's `n` values of `size` bytes.
        if unsafe { ffi::adios2_attribute_data(bytes.as_mut_ptr().cast(), &mut got, a) }
            != ffi::ERROR_NONE
        {
            return None;
        }
        Some(
            (0..n.min(got.max(1)))
                .map(|i| crate::bytes::value(&bytes, i, sample, Endian::Little))
                .collect(),
        )
    }

    fn attribute(&self, name: &str) -> Option<*mut ffi::adios2_attribute> {
        let c = CString::new(name).ok()?;
        // SAFETY: `io` is live; null when absent, checked.
        let a = unsafe { ffi::adios2_inquire_attribute(self.io, c.as_ptr()) };
        (!a.is_null()).then_some(a)
    }

    /// Whether attribute `name` exists (in the current step, or in the file).
    pub fn has_attribute(&self, name: &str) -> bool {
        self.attribute(name).is_some()
    }

    /// The text of attribute `name`, one string per element (none when absent, not text, of
    /// more than 64 elements, or where this build's ADIOS2 cannot tell a text's length before
    /// copying it: see `build.rs`).
    #[cfg(adios2_string_data)]
    pub fn texts(&self, name: &str) -> Option<Vec<String>> {
        let a = self.attribute(name)?;
        let (mut t, mut n, mut single) = (0, 0usize, 0);
        // SAFETY: `a` is live; the out-parameters outlive the calls.
        unsafe {
            if ffi::adios2_attribute_type(&mut t, a) != ffi::ERROR_NONE
                || ffi::adios2_attribute_size(&mut n, a) != ffi::ERROR_NONE
                || ffi::adios2_attribute_is_value(&mut single, a) != ffi::ERROR_NONE
            {
                return None;
            }
        }
        if t != ffi::TYPE_STRING || n == 0 || n > 64 {
            return None;
        }
        let text = |mut b: Vec<u8>, len: usize| {
            b.truncate(len);
            String::from_utf8_lossy(&b).into_owned()
        };
        if single != 0 {
            let mut len = 0usize;
            // SAFETY: a null buffer asks for the length only; then the buffer holds it and
            // the terminating NUL the library may write.
            unsafe {
                if ffi::adios2_attribute_string_data(a, std::ptr::null_mut(), &mut len)
                    != ffi::ERROR_NONE
                    || len > 1 << 16
                {
                    return None;
                }
                let mut b = vec![0u8; len + 1];
                if ffi::adios2_attribute_string_data(a, b.as_mut_ptr().cast(), &mut len)
                    != ffi::ERROR_NONE
                {
                    return None;
                }
                return Some(vec![text(b, len)]);
            }
        }
        let mut lens = vec![0usize; n];
        // SAFETY: `lens` holds the `n` elements' lengths; each buffer then holds its
        // element and a terminating NUL, and the pointer array outlives the call.
        unsafe {
            if ffi::adios2_attribute_string_data_array(a, std::ptr::null_mut(), lens.as_mut_ptr())
                != ffi::ERROR_NONE
                || lens.iter().any(|&l| l > 1 << 16)
            {
                return None;
            }
            let mut bufs: Vec<Vec<u8>> = lens.iter().map(|&l| vec![0u8; l + 1]).collect();
            let mut ptrs: Vec<*mut std::ffi::c_char> =
                bufs.iter_mut().map(|b| b.as_mut_ptr().cast()).collect();
            if ffi::adios2_attribute_string_data_array(a, ptrs.as_mut_ptr(), lens.as_mut_ptr())
                != ffi::ERROR_NONE
            {
                return None;
            }
            Some(
                bufs.into_iter()
                    .zip(lens)
                    .map(|(b, l)| text(b, l))
                    .collect(),
            )
        }
    }

    /// Without the length-first calls no text attribute is read (see `build.rs`).
    #[cfg(not(adios2_string_data))]
    pub fn texts(&self, _name: &str) -> Option<Vec<String>> {
        None
    }

    /// How many steps of the file hold `var` (random-access files only).
    ///
    /// # Errors
    /// [`ReadError`] naming the stream and the variable: absent, or ADIOS2 failing.
    pub fn steps(&self, var: &str) -> Result<usize, ReadError> {
        let h = self.handle(var)?;
        let mut steps = 0usize;
        // SAFETY: `h` is live while the stream is.
        let code = unsafe { ffi::adios2_variable_steps(&mut steps, h) };
        self.check(code, var)?;
        Ok(steps)
    }

    /// The first step of the file that holds `var` (random-access files only).
    ///
    /// # Errors
    /// [`ReadError`] naming the stream and the variable: absent, or ADIOS2 failing.
    pub fn first_step(&self, var: &str) -> Result<usize, ReadError> {
        let h = self.handle(var)?;
        let mut start = 0usize;
        // SAFETY: `h` is live while the stream is.
        let code = unsafe { ffi::adios2_variable_steps_start(&mut start, h) };
        self.check(code, var)?;
        Ok(start)
    }

    /// Spacing and origin of `var`'s grid from its attributes (`VAR/spacing`, `VAR/origin`,
    /// else `spacing`, `origin`; x, y, z), and a note where they are missing.
    pub fn grid(&self, var: &str) -> (Vec3, Vec3, Option<String>) {
        let three = |what: &str| {
            [format!("{var}/{what}"), what.to_owned()]
                .iter()
                .find_map(|n| self.numbers(n))
                .filter(|v| v.len() == 3 && v.iter().all(|x| x.is_finite()))
                .map(|v| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
        };
        let spacing = three("spacing").filter(|s| s.min_element() > 0.0);
        let origin = three("origin");
        let note = spacing.is_none().then(|| {
            format!(
                "no attribute {var}/spacing or spacing (three positive numbers, x y z): unit \
                 spacing from the origin"
            )
        });
        (
            spacing.unwrap_or(Vec3::ONE),
            origin.unwrap_or(Vec3::ZERO),
            note,
        )
    }
}

/// `bytes`, samples of `sample` (little-endian, x fastest), as a volume of `dims` at
/// `spacing`, the core's types kept and others converted to f32.
fn volume(
    name: &Path,
    bytes: &[u8],
    sample: Sample,
    dims: [usize; 3],
    spacing: Vec3,
) -> Result<Volume, ReadError> {
    let n = bytes.len() / sample.size();
    let mut samples = Samples::new(name, sample, Endian::Little, n, n)?;
    samples.push(bytes)?;
    samples.finish(name, dims, spacing)
}

/// The sample type of ADIOS2 type `t`, for the integer and float types.
fn sample_of(t: ffi::adios2_type) -> Option<Sample> {
    Some(match t {
        ffi::TYPE_INT8 => Sample::I8,
        ffi::TYPE_UINT8 => Sample::U8,
        ffi::TYPE_INT16 => Sample::I16,
        ffi::TYPE_UINT16 => Sample::U16,
        ffi::TYPE_INT32 => Sample::I32,
        ffi::TYPE_UINT32 => Sample::U32,
        ffi::TYPE_INT64 => Sample::I64,
        ffi::TYPE_UINT64 => Sample::U64,
        ffi::TYPE_FLOAT => Sample::F32,
        ffi::TYPE_DOUBLE => Sample::F64,
        _ => return None,
    })
}

impl Drop for Stream {
    fn drop(&mut self) {
        // SAFETY: each handle is closed once, engine before ADIOS, and not used after.
        unsafe {
            if !self.engine.is_null() {
                ffi::adios2_close(self.engine);
            }
            ffi::adios2_finalize(self.adios);
        }
    }
}

extern "C" {
    /// The C library's `free`, for the names `adios2_available_variables` allocates.
    fn free(p: *mut std::ffi::c_void);
}
