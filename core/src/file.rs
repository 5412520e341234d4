//! Files written whole or not at all: the one atomic write that every crate's outputs, records
//! and caches go through.
//!
//! The bytes go to a temporary file beside the target (named [`TEMP_PREFIX`]`*`, so a crash
//! between the write and the rename leaves only such a file, which the daemons remove when
//! they start), then the temporary file is renamed over the target: readers see the old file
//! or the new one, never part of either.

use std::io::Write;
use std::path::Path;

/// The name prefix of the temporary files [`write_atomic`] leaves behind if it is interrupted.
pub const TEMP_PREFIX: &str = ".tmp-";

/// What a completed [`write_atomic`] survives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Durability {
    /// A crash of the process: the file is renamed into place complete, but after a power
    /// loss the rename may have reached the disk before the data (a cache that can be
    /// measured again).
    Crash,
    /// A power loss too: the file is flushed to the disk before the rename and its folder
    /// after it (what a node acknowledges, a recording, a saved state).
    PowerLoss,
}

/// Writes `bytes` to `path` through a temporary file in the same folder renamed into place,
/// flushed as `durability` asks. The folder must exist. A file already at `path` is replaced
/// only by a complete one; when any step fails it is left as it was, and the temporary file
/// is removed.
///
/// # Errors
/// The I/O error of the step that failed: creating or writing the temporary file (no such
/// folder, no permission, disk full), flushing it, renaming it (e.g. `path` is a folder) or
/// flushing the folder.
pub fn write_atomic(path: &Path, bytes: &[u8], durability: Durability) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let durable = durability == Durability::PowerLoss;
    let mut tmp = tempfile::Builder::new()
        .prefix(TEMP_PREFIX)
        .tempfile_in(dir)?;
    tmp.write_all(bytes)?;
    if durable {
        tmp.as_file().sync_all()?;
    }
    tmp.persist(path).map_err(|e| e.error)?;
    if durable {
        std::fs::File::open(dir)?.sync_all()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn writes_and_replaces_whole_files_and_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        for durability in [Durability::Crash, Durability::PowerLoss] {
            write_atomic(&path, b"first version", durability).unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), b"first version");
            write_atomic(&path, b"second", durability).unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), b"second");
            write_atomic(&path, b"", durability).unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), b"");
        }
        assert_eq!(names(dir.path()), ["out.bin"]);
    }

    #[test]
    fn a_failed_write_names_the_cause_and_leaves_the_target_as_it_was() {
        let dir = tempfile::tempdir().unwrap();
        // No such folder: nothing is created.
        let missing = dir.path().join("no-such-folder").join("out.bin");
        let err = write_atomic(&missing, b"x", Durability::PowerLoss).unwrap_err();
        assert_eq!(err.kind(), std::io::ErrorKind::NotFound);
        assert!(names(dir.path()).is_empty());
        // The target is a non-empty folder: the rename fails, the folder keeps its content,
        // and the temporary file is gone.
        let target = dir.path().join("taken");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("kept"), b"kept").unwrap();
        assert!(write_atomic(&target, b"x", Durability::Crash).is_err());
        assert_eq!(names(dir.path()), ["taken"]);
        assert_eq!(std::fs::read(target.join("kept")).unwrap(), b"kept");
    }

    #[test]
    fn a_bare_file_name_is_written_in_the_working_folder() {
        // `Path::parent` of a bare name is empty: the temporary file goes to ".", beside the
        // target, not to a folder named "".
        let name = format!("insitu-write-atomic-{}.tmp-test", std::process::id());
        let path = Path::new(&name);
        write_atomic(path, b"here", Durability::Crash).unwrap();
        let read = std::fs::read(path);
        let _ = std::fs::remove_file(path);
        assert_eq!(read.unwrap(), b"here");
    }
}
