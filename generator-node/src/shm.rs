//! Steps pushed through shared memory (`PushShared`): a simulation on the node's own host
//! writes a step's payload into a file of the node's shared-memory directory (`/dev/shm` by
//! default, a tmpfs: the file is memory) and sends only the header and the file's path; the
//! node reads the payload from there into the step's field. That takes the transfer off the
//! simulation's cores: no gRPC encoding, no socket copies, no chunk assembly, only one copy
//! in (the client's write) and one copy out (the node's read), each a `memcpy` of the field.
//!
//! What the node opens is checked so that a caller (who holds the token) cannot make it read
//! anything else: a path directly inside the directory, named `insitu-…`, opened without
//! following links, a regular file owned by the node's own user, exactly the header's
//! `total_bytes` long. The client keeps the file and writes the next step over it once the
//! call returns: by then the node has read it.

use crate::ingest::FieldWindow;
use insitu_core::volume::FieldAssembler;
use insitu_proto::shared_memory::{host_id, FILE_PREFIX};
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use tonic::Status;

/// Bytes read from the file at a time.
const PIECE: usize = 4 << 20;

/// Where a node takes shared-memory pushes from, and who it is.
#[derive(Clone, Debug)]
pub struct SharedMemory {
    /// The directory, canonical.
    dir: PathBuf,
    /// The node's own user (the owner files must have).
    uid: u32,
    /// This boot of this host (`/proc/sys/kernel/random/boot_id`).
    host_id: String,
}

impl SharedMemory {
    /// Shared-memory pushes from files in `dir`, or why not: only on Linux, where a boot id
    /// tells clients they share the node's host, and `dir` must be a directory.
    ///
    /// # Errors
    /// The problem, in words, naming `dir`.
    pub fn new(dir: &Path) -> Result<Self, String> {
        let host_id = host_id().ok_or("no boot id (/proc/sys/kernel/random/boot_id): not Linux")?;
        let canonical = dir
            .canonicalize()
            .map_err(|e| format!("{}: {e}", dir.display()))?;
        if !canonical.is_dir() {
            return Err(format!("{}: not a directory", dir.display()));
        }
        Ok(Self {
            dir: canonical,
            uid: own_uid().ok_or("the node's own user is unknown (/proc/self)")?,
            host_id,
        })
    }

    /// The directory, as clients are told it.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// This host's boot id, as clients are told it.
    pub fn host_id(&self) -> &str {
        &self.host_id
    }

    /// Opens the file at `path`, checked: directly inside the directory, named `insitu-…`, a
    /// regular file (not followed through a link) owned by the node's user, `total_bytes`
    /// long.
    ///
    /// # Errors
    /// `FAILED_PRECONDITION` naming the path and what is wrong with it.
    pub fn open(&self, path: &str, total_bytes: u64) -> Result<File, Status> {
        let refuse =
            |why: &str| Status::failed_precondition(format!("shared-memory file {path:?}: {why}"));
        let p = Path::new(path);
        let name = p
            .file_name()
            .and_then(|n| n.to_str())
            .filter(|n| n.starts_with(FILE_PREFIX))
            .ok_or_else(|| refuse(&format!("its name must start with {FILE_PREFIX:?}")))?;
        let parent = p
            .parent()
            .and_then(|d| d.canonicalize().ok())
            .ok_or_else(|| refuse("not an absolute path to an existing directory"))?;
        if parent != self.dir {
            return Err(refuse(&format!(
                "not in the node's shared-memory directory {}",
                self.dir.display()
            )));
        }
        let file = open_no_follow(&self.dir.join(name)).map_err(|e| refuse(&e.to_string()))?;
        let meta = file.metadata().map_err(|e| refuse(&e.to_string()))?;
        if !meta.file_type().is_file() {
            return Err(refuse("not a regular file"));
        }
        if file_uid(&meta) != Some(self.uid) {
            return Err(refuse("not owned by the node's user"));
        }
        if meta.len() != total_bytes {
            return Err(refuse(&format!(
                "{} bytes where the header says {total_bytes}",
                meta.len()
            )));
        }
        Ok(file)
    }
}

/// Reads the whole payload of `file` (`total_bytes`) into `field` through `window` (the bytes
/// of other fields passed over as they come), as a stream's chunks would be.
///
/// # Errors
/// `FAILED_PRECONDITION` when the file cannot be read to its end (it shrank: the client broke
/// its side of the contract).
pub fn read_payload(
    mut file: File,
    total_bytes: u64,
    window: &mut FieldWindow,
    field: &mut FieldAssembler,
) -> Result<(), Status> {
    let mut buf = vec![0u8; PIECE.min(total_bytes as usize)];
    let mut left = total_bytes;
    while left > 0 {
        let n = (left as usize).min(buf.len());
        file.read_exact(&mut buf[..n]).map_err(|e| {
            Status::failed_precondition(format!(
                "shared-memory file: read {} of {total_bytes} bytes: {e}",
                total_bytes - left
            ))
        })?;
        field.push(window.take(&buf[..n]));
        left -= n as u64;
    }
    Ok(())
}

#[cfg(unix)]
fn own_uid() -> Option<u32> {
    use std::os::unix::fs::MetadataExt;
    // `/proc/self` belongs to the process's own (effective) user.
    std::fs::metadata("/proc/self").ok().map(|m| m.uid())
}

#[cfg(not(unix))]
fn own_uid() -> Option<u32> {
    None
}

#[cfg(unix)]
fn file_uid(meta: &std::fs::Metadata) -> Option<u32> {
    use std::os::unix::fs::MetadataExt;
    Some(meta.uid())
}

#[cfg(not(unix))]
fn file_uid(_: &std::fs::Metadata) -> Option<u32> {
    None
}

/// Opens `path` for reading, failing on a symbolic link instead of following it.
#[cfg(target_os = "linux")]
fn open_no_follow(path: &Path) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW)
        .open(path)
}

#[cfg(not(target_os = "linux"))]
fn open_no_follow(path: &Path) -> std::io::Result<File> {
    Err(std::io::Error::new(
        std::io::ErrorKind::Unsupported,
        format!("{}: shared memory only on Linux", path.display()),
    ))
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;
    use crate::ingest::check_step;
    use insitu_proto::pb;

    /// A 4×3×2 step with two named vertex fields: `u` f32 (0..24) and `flag` u8 (100..124).
    fn step() -> (pb::StepHeader, Vec<u8>) {
        let d = |x, y, z| Some(pb::Dims3 { x, y, z });
        let field = |name: &str, dtype: pb::ScalarType| pb::Field {
            name: name.into(),
            association: pb::Association::Vertex as i32,
            dtype: dtype as i32,
        };
        let mut payload: Vec<u8> = (0..24u32).flat_map(|i| (i as f32).to_le_bytes()).collect();
        payload.extend(100..124u8);
        let header = pb::StepHeader {
            step: 3,
            global_dims: d(4, 3, 2),
            brick_offset: d(0, 0, 0),
            brick_dims: d(4, 3, 2),
            world_size: 1,
            total_bytes: payload.len() as u64,
            fields: vec![
                field("u", pb::ScalarType::F32),
                field("flag", pb::ScalarType::U8),
            ],
            ..Default::default()
        };
        (header, payload)
    }

    /// The field read from the file is the one a stream of the same payload gives, for the
    /// first field and for one after another that is passed over.
    #[test]
    fn a_step_read_from_shared_memory_equals_the_streamed_one() {
        let dir = tempfile::tempdir().unwrap();
        let shm = SharedMemory::new(dir.path()).unwrap();
        let (header, payload) = step();
        let path = dir.path().join("insitu-test");
        std::fs::write(&path, &payload).unwrap();
        for wanted in ["u", "flag"] {
            let (info, mut window) = check_step(&header, Some(wanted)).unwrap();
            let mut field = info.assembler(None);
            let file = shm
                .open(path.to_str().unwrap(), header.total_bytes)
                .unwrap();
            read_payload(file, header.total_bytes, &mut window, &mut field).unwrap();
            let shared = info.with_field(field).unwrap();

            let (info, mut window) = check_step(&header, Some(wanted)).unwrap();
            let mut field = info.assembler(None);
            for c in payload.chunks(5) {
                field.push(window.take(c));
            }
            let streamed = info.with_field(field).unwrap();
            assert_eq!(shared.field, streamed.field, "{wanted}");
        }
    }

    /// Only a regular file of the node's user, directly in the directory, named `insitu-…`
    /// and of the declared size is opened; every refusal names the path and the problem.
    #[test]
    fn only_a_file_of_the_directory_with_the_declared_size_is_opened() {
        let dir = tempfile::tempdir().unwrap();
        let other = tempfile::tempdir().unwrap();
        let shm = SharedMemory::new(dir.path()).unwrap();
        assert!(!shm.host_id().is_empty());
        let good = dir.path().join("insitu-1");
        std::fs::write(&good, [0u8; 16]).unwrap();
        let s = |p: &Path| p.to_str().unwrap().to_owned();
        assert!(shm.open(&s(&good), 16).is_ok());
        // A path through `..` that lands in the directory is the same file.
        let dotted = dir.path().join("sub/../insitu-1");
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        assert!(shm.open(&s(&dotted), 16).is_ok());

        let outside = other.path().join("insitu-1");
        std::fs::write(&outside, [0u8; 16]).unwrap();
        let unprefixed = dir.path().join("data");
        std::fs::write(&unprefixed, [0u8; 16]).unwrap();
        let link = dir.path().join("insitu-link");
        std::os::unix::fs::symlink(&outside, &link).unwrap();
        let directory = dir.path().join("insitu-dir");
        std::fs::create_dir(&directory).unwrap();
        let nested = dir.path().join("sub/insitu-2");
        std::fs::write(&nested, [0u8; 16]).unwrap();
        for (path, size, problem) in [
            (s(&good), 15, "16 bytes where the header says 15"),
            (s(&outside), 16, "not in the node's shared-memory directory"),
            (s(&nested), 16, "not in the node's shared-memory directory"),
            (s(&unprefixed), 16, "must start with \"insitu-\""),
            (s(&link), 16, "symbolic links"),
            (s(&directory), 16, "not a regular file"),
            (s(&dir.path().join("insitu-missing")), 16, "No such file"),
            ("insitu-1".to_owned(), 16, "not an absolute path"),
            (String::new(), 16, "must start with"),
        ] {
            let e = shm.open(&path, size).unwrap_err();
            assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{path}");
            assert!(
                e.message().contains(problem) && e.message().contains(&path),
                "{path}: {}",
                e.message()
            );
        }
        assert!(SharedMemory::new(&dir.path().join("missing")).is_err());
        assert!(SharedMemory::new(&good).is_err());
    }
}
