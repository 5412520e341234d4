//! Pushing through shared memory when the generator-node runs on the simulation's own host
//! (`PushShared` in `proto/insitu.proto`): the step's payload is written into a file of the
//! node's shared-memory directory (a tmpfs such as `/dev/shm`: memory, not disk) and only its
//! header and path go over gRPC. One `memcpy` of the field on the simulation's side, instead of
//! encoding it into gRPC messages and copying it through a socket while the node, on the same
//! cores, takes it apart again.
//!
//! A client finds out once, from the node's status, whether it shares the node's host (the
//! same Linux boot id) and where to write. It keeps one file (`insitu-<pid>-<n>`, mode 0600 in
//! that directory), writes each step over the last one (the pages stay; no fault per push), and
//! removes it when dropped. Whatever does not work — no such directory here, no room in it, a
//! node that refuses the file (another container's `/dev/shm`) — turns shared memory off for
//! this client and the step is streamed instead; `INSITU_SHARED_MEMORY=0` turns it off from
//! the start.

use bytes::Bytes;
use insitu_proto::pb;
pub use insitu_proto::shared_memory::host_id;
use insitu_proto::shared_memory::FILE_PREFIX;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The environment variable that turns shared-memory pushes off (`0`, `off`, `false`, `no`).
pub const ENV: &str = "INSITU_SHARED_MEMORY";

/// Whether this client pushes through shared memory.
#[derive(Debug, Default)]
pub(crate) enum SharedMemory {
    /// Not found out yet (at the first push).
    #[default]
    Unknown,
    /// Streamed: another host, no directory, or it failed once.
    Off,
    /// Written into a file of `dir`, kept between pushes.
    On {
        dir: PathBuf,
        segment: Option<Segment>,
    },
}

impl Clone for SharedMemory {
    /// A clone pushes on its own (possibly at the same time), so it gets a file of its own.
    fn clone(&self) -> Self {
        match self {
            Self::Unknown => Self::Unknown,
            Self::Off => Self::Off,
            Self::On { dir, .. } => Self::On {
                dir: dir.clone(),
                segment: None,
            },
        }
    }
}

impl SharedMemory {
    /// What the node's `status` says about pushing to it through shared memory from here.
    pub(crate) fn for_node(status: &pb::GeneratorStatus) -> Self {
        let dir = Path::new(&status.shared_memory_dir);
        let usable = !disabled_by_env()
            && !status.shared_memory_dir.is_empty()
            && !status.host_id.is_empty()
            && host_id().as_deref() == Some(status.host_id.as_str())
            && dir.is_dir();
        if usable {
            Self::On {
                dir: dir.to_owned(),
                segment: None,
            }
        } else {
            Self::Off
        }
    }
}

/// Whether `INSITU_SHARED_MEMORY` turns shared memory off.
fn disabled_by_env() -> bool {
    std::env::var(ENV).is_ok_and(|v| {
        matches!(
            v.trim().to_ascii_lowercase().as_str(),
            "0" | "off" | "false" | "no"
        )
    })
}

/// Files made by this process so far (part of each new file's name).
static MADE: AtomicU64 = AtomicU64::new(0);

/// The client's shared-memory file: created on first use, written over at every push,
/// removed when dropped.
#[derive(Debug)]
pub(crate) struct Segment {
    path: PathBuf,
    file: File,
}

impl Segment {
    /// A new file in `dir`, readable and writable by this user only, named
    /// `insitu-<pid>-<n>` (a name left by an earlier process of the same pid is passed over).
    pub(crate) fn create(dir: &Path) -> std::io::Result<Self> {
        let pid = std::process::id();
        loop {
            let n = MADE.fetch_add(1, Ordering::Relaxed);
            let path = dir.join(format!("{FILE_PREFIX}{pid}-{n}"));
            let mut options = std::fs::OpenOptions::new();
            options.read(true).write(true).create_new(true);
            #[cfg(unix)]
            std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
            match options.open(&path) {
                Ok(file) => return Ok(Self { path, file }),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && n < 1 << 20 => {}
                Err(e) => return Err(e),
            }
        }
    }

    /// The file's path, as the node is sent it.
    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// The file holding exactly `parts`, one after another.
    ///
    /// # Errors
    /// The write's (e.g. no room left in the directory).
    pub(crate) fn write(&mut self, parts: &[Bytes]) -> std::io::Result<()> {
        use std::io::{Seek, SeekFrom, Write};
        let total: u64 = parts.iter().map(|p| p.len() as u64).sum();
        if self.file.metadata()?.len() != total {
            self.file.set_len(total)?;
        }
        self.file.seek(SeekFrom::Start(0))?;
        for p in parts {
            self.file.write_all(p)?;
        }
        Ok(())
    }
}

impl Drop for Segment {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(dir: &Path, host: &str) -> pb::GeneratorStatus {
        pb::GeneratorStatus {
            shared_memory_dir: dir.display().to_string(),
            host_id: host.into(),
            ..Default::default()
        }
    }

    /// Shared memory only with a node of this boot that names a directory found here.
    #[test]
    fn shared_memory_needs_the_same_host_and_the_directory() {
        let dir = tempfile::tempdir().unwrap();
        let Some(here) = host_id() else {
            return; // not Linux: always streamed
        };
        let on =
            |s: &pb::GeneratorStatus| matches!(SharedMemory::for_node(s), SharedMemory::On { .. });
        if !disabled_by_env() {
            assert!(on(&status(dir.path(), &here)));
        }
        assert!(!on(&status(dir.path(), "another-boot")));
        assert!(!on(&status(&dir.path().join("missing"), &here)));
        assert!(!on(&status(dir.path(), "")));
        assert!(!on(&pb::GeneratorStatus::default()));
    }

    /// A segment holds exactly the last parts written (longer, then shorter), is private to
    /// its user, and is gone once dropped; two segments of one process never share a name.
    #[test]
    fn a_segment_holds_the_last_step_written_and_is_removed_when_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = Segment::create(dir.path()).unwrap();
        let b = Segment::create(dir.path()).unwrap();
        assert_ne!(a.path(), b.path());
        a.write(&[Bytes::from_static(b"0123456789"), Bytes::from_static(b"ab")])
            .unwrap();
        assert_eq!(std::fs::read(a.path()).unwrap(), b"0123456789ab");
        a.write(&[Bytes::from_static(b"xyz")]).unwrap();
        assert_eq!(std::fs::read(a.path()).unwrap(), b"xyz");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(a.path()).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        let path = a.path().to_owned();
        drop(a);
        assert!(!path.exists());
        assert!(b.path().exists());
    }
}
