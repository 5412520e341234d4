//! The recording's index: an SQLite database (`index.sqlite`, WAL mode, bundled SQLite) with
//! one row per stored (step, rank) and one per composed step. Each stored item is one
//! transaction, so a store costs the same at step 10 as at step 100 000 (the JSON index it
//! replaces was rewritten whole on every store), and a crash leaves the index as of the last
//! committed item. The payloads (VDIs, reference frames) stay files, written atomically before
//! their row names them.
//!
//! Columns beside the JSON of each row (step, rank, world size, P_M version, σ, τ, q) are what
//! the viewer's queries read (series of σ, τ, q; P_M versions); the JSON keeps everything else.
//! [`IndexDb::export`] and [`IndexDb::export_csv`] write it out for people who want a file.

use crate::rows::{Entry, StepEntry, StoreError};
use rusqlite::{params, Connection, OpenFlags, OptionalExtension};
use std::path::{Path, PathBuf};

/// The index file's name in the recording directory.
pub const INDEX_DB: &str = "index.sqlite";
/// The schema version kept in `meta`.
pub const SCHEMA_VERSION: u32 = 2;

/// The whole index ([`IndexDb::export`]).
#[derive(Debug, serde::Serialize)]
pub struct Export {
    /// [`SCHEMA_VERSION`].
    pub schema: u32,
    /// Every (step, rank) row.
    pub entries: Vec<Entry>,
    /// Every composed step's row.
    pub steps: Vec<StepEntry>,
}

/// The open index.
pub struct IndexDb {
    path: PathBuf,
    conn: Connection,
}

/// SQLite's errors as [`StoreError`]: a full disk is an I/O error of kind `StorageFull` (so it
/// reaches callers as `RESOURCE_EXHAUSTED`, like a payload that did not fit), the rest
/// [`StoreError::Corrupt`].
fn db_err(path: &Path) -> impl Fn(rusqlite::Error) -> StoreError + '_ {
    use rusqlite::ErrorCode;
    use std::io::ErrorKind;
    let io = |kind: ErrorKind, e: &rusqlite::Error| StoreError::Io {
        path: path.to_owned(),
        source: std::io::Error::new(kind, format!("SQLite: {e}")),
    };
    // What the storage did (full, read-only, refused, failing) is an I/O error an operator can
    // fix, not a corrupt index.
    move |e| match e.sqlite_error_code() {
        Some(ErrorCode::DiskFull) => io(ErrorKind::StorageFull, &e),
        Some(ErrorCode::ReadOnly) => io(ErrorKind::ReadOnlyFilesystem, &e),
        Some(ErrorCode::PermissionDenied) => io(ErrorKind::PermissionDenied, &e),
        // The device failed: reported as the EIO a payload write would get.
        Some(ErrorCode::SystemIoFailure) => StoreError::Io {
            path: path.to_owned(),
            source: std::io::Error::from_raw_os_error(crate::rows::EIO),
        },
        _ => StoreError::Corrupt {
            path: path.to_owned(),
            problem: format!("SQLite: {e}"),
        },
    }
}

fn json_err(path: &Path) -> impl Fn(serde_json::Error) -> StoreError + '_ {
    move |e| StoreError::Corrupt {
        path: path.to_owned(),
        problem: format!("a row's JSON: {e}"),
    }
}

/// Step indices are stored as SQLite's signed 64-bit integers.
fn step_key(step: u64) -> i64 {
    step as i64
}

/// Whether `dir` holds an index this crate made: `index.sqlite` with its tables. A missing
/// file, an empty one (0 bytes: truncated, or created by something else) or a database
/// without the tables is not one.
///
/// # Errors
/// [`StoreError::Corrupt`] when the file is there but is not a database.
pub fn holds_index(dir: &Path) -> Result<bool, StoreError> {
    let path = dir.join(INDEX_DB);
    if !path.exists() {
        return Ok(false);
    }
    let err = db_err(&path);
    let conn = open_read_only(&path).map_err(&err)?;
    let tables: i64 = conn
        .query_row(
            "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = 'entries'",
            [],
            |r| r.get(0),
        )
        .map_err(&err)?;
    Ok(tables > 0)
}

/// Opens the index at `path` for reading, writing nothing beside it. A recording that no
/// viz-node is writing (no write-ahead log with content) opens *immutable*: SQLite then
/// creates no `-shm` file and needs no write access, so a recording on read-only media or
/// owned by another user reads too. One being written opens read-only through its log (to
/// see the newest rows), and where that cannot be (the log's shared memory not creatable) as
/// immutable, which reads the rows checkpointed so far.
fn open_read_only(path: &Path) -> rusqlite::Result<Connection> {
    let wal = path.with_file_name(format!("{INDEX_DB}-wal"));
    let written = wal.metadata().is_ok_and(|m| m.len() > 0);
    if written {
        if let Ok(conn) = Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY) {
            // Opening is lazy: a read shows whether the log can be used.
            if conn
                .query_row("SELECT count(*) FROM sqlite_master", [], |_| Ok(()))
                .is_ok()
            {
                return Ok(conn);
            }
        }
    }
    let uri = format!("file:{}?immutable=1", uri_path(path));
    Connection::open_with_flags(
        uri,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_URI,
    )
}

/// `path` percent-encoded for an SQLite URI (all but unreserved characters and `/`).
fn uri_path(path: &Path) -> String {
    let mut out = String::new();
    for &b in path.as_os_str().as_encoded_bytes() {
        if b.is_ascii_alphanumeric() || b"-._~/".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

impl IndexDb {
    /// Opens (creating when `create`) the index of `dir`; without `create`, for reading only
    /// and leaving nothing behind (immutable when no viz-node writes it).
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] when the file is not an index of this version.
    pub fn open(dir: &Path, create: bool) -> Result<Self, StoreError> {
        let path = dir.join(INDEX_DB);
        let err = db_err(&path);
        let conn = if create {
            let flags = OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_CREATE;
            Connection::open_with_flags(&path, flags).map_err(&err)?
        } else {
            open_read_only(&path).map_err(&err)?
        };
        conn.busy_timeout(std::time::Duration::from_secs(10))
            .map_err(&err)?;
        if create {
            // WAL: readers (the export, tests, a viewer) never block the writer; FULL: a
            // committed row survives power loss, like the fsync'd payload files it names.
            conn.pragma_update(None, "journal_mode", "WAL")
                .map_err(&err)?;
            conn.pragma_update(None, "synchronous", "FULL")
                .map_err(&err)?;
            conn.execute_batch(
                "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
                 CREATE TABLE IF NOT EXISTS entries (
                     step INTEGER NOT NULL, rank INTEGER NOT NULL, world_size INTEGER NOT NULL,
                     pm_version INTEGER NOT NULL, sigma_bytes INTEGER NOT NULL,
                     tau_secs REAL NOT NULL, q_db REAL, vdi TEXT, refs TEXT,
                     entry TEXT NOT NULL, PRIMARY KEY (step, rank));
                 CREATE TABLE IF NOT EXISTS steps (
                     step INTEGER PRIMARY KEY, world_size INTEGER NOT NULL,
                     pm_version INTEGER NOT NULL, sigma_bytes INTEGER NOT NULL,
                     tau_secs REAL NOT NULL, q_db REAL, partial INTEGER NOT NULL, error TEXT,
                     entry TEXT NOT NULL);",
            )
            .map_err(&err)?;
            conn.execute(
                "INSERT OR IGNORE INTO meta (key, value) VALUES ('schema', ?1)",
                params![SCHEMA_VERSION.to_string()],
            )
            .map_err(&err)?;
        }
        let version: Option<String> = conn
            .query_row("SELECT value FROM meta WHERE key = 'schema'", [], |r| {
                r.get(0)
            })
            .optional()
            .map_err(&err)?;
        if version.as_deref() != Some(&SCHEMA_VERSION.to_string()) {
            return Err(StoreError::Corrupt {
                path: path.clone(),
                problem: format!(
                    "index schema {version:?} is not {SCHEMA_VERSION}; move it away to start a new recording here"
                ),
            });
        }
        Ok(Self {
            path: path.clone(),
            conn,
        })
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// SQLite's `quick_check`: whether every page and tree of the file is whole (a file cut
    /// short, or overwritten in part, fails it).
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] naming the database and the first problem SQLite found.
    pub fn check(&self) -> Result<(), StoreError> {
        let found: String = self
            .conn
            .query_row("PRAGMA quick_check", [], |r| r.get(0))
            .map_err(db_err(&self.path))?;
        if found == "ok" {
            Ok(())
        } else {
            Err(StoreError::Corrupt {
                path: self.path.clone(),
                problem: format!("damaged (SQLite quick_check: {found})"),
            })
        }
    }

    /// Inserts or replaces the row of `e` (one transaction).
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] naming the database when SQLite fails (disk full, I/O).
    pub fn put_entry(&self, e: &Entry) -> Result<(), StoreError> {
        let json = serde_json::to_string(e).map_err(json_err(&self.path))?;
        self.conn
            .execute(
                "INSERT OR REPLACE INTO entries
                 (step, rank, world_size, pm_version, sigma_bytes, tau_secs, q_db, vdi, refs, entry)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)",
                params![
                    step_key(e.step),
                    e.rank,
                    e.world_size,
                    e.pm_version as i64,
                    e.sizing.sigma_bytes as i64,
                    e.sizing.tau_secs,
                    e.quality.as_ref().map(|q| q.q_db.0),
                    e.vdi,
                    e.references,
                    json
                ],
            )
            .map_err(db_err(&self.path))?;
        Ok(())
    }

    /// Inserts or replaces the row of a composed step (one transaction).
    ///
    /// # Errors
    /// As [`Self::put_entry`].
    pub fn put_step(&self, s: &StepEntry) -> Result<(), StoreError> {
        let json = serde_json::to_string(s).map_err(json_err(&self.path))?;
        self.conn
            .execute(
                "INSERT OR REPLACE INTO steps
                 (step, world_size, pm_version, sigma_bytes, tau_secs, q_db, partial, error, entry)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
                params![
                    step_key(s.step),
                    s.world_size,
                    s.pm_version as i64,
                    s.sizing.sigma_bytes as i64,
                    s.sizing.tau_secs,
                    s.quality.as_ref().map(|q| q.q_db.0),
                    !s.missing.is_empty(),
                    s.error,
                    json
                ],
            )
            .map_err(db_err(&self.path))?;
        Ok(())
    }

    /// Every (step, rank) row, by step then rank. A row's file names are only ever its own
    /// ([`Entry::confine_names`]): any other name is dropped, with a warning.
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] for an unreadable row.
    pub fn entries(&self) -> Result<Vec<Entry>, StoreError> {
        let mut rows: Vec<Entry> = self.rows("SELECT entry FROM entries ORDER BY step, rank")?;
        for e in &mut rows {
            let dropped = e.confine_names();
            if !dropped.is_empty() {
                tracing::warn!(index = %self.path.display(), step = e.step, rank = e.rank, names = ?dropped, "an index row names files that are not its own; they are not read");
            }
        }
        Ok(rows)
    }

    /// Every composed step, in order, its file names confined as [`Self::entries`]'.
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] for an unreadable row.
    pub fn steps(&self) -> Result<Vec<StepEntry>, StoreError> {
        let mut rows: Vec<StepEntry> = self.rows("SELECT entry FROM steps ORDER BY step")?;
        for s in &mut rows {
            let dropped = s.confine_names();
            if !dropped.is_empty() {
                tracing::warn!(index = %self.path.display(), step = s.step, names = ?dropped, "an index row names files that are not its own; they are not read");
            }
        }
        Ok(rows)
    }

    fn rows<T: serde::de::DeserializeOwned>(&self, sql: &str) -> Result<Vec<T>, StoreError> {
        let err = db_err(&self.path);
        let mut stmt = self.conn.prepare(sql).map_err(&err)?;
        let texts = stmt
            .query_map([], |r| r.get::<_, String>(0))
            .map_err(&err)?
            .collect::<Result<Vec<_>, _>>()
            .map_err(&err)?;
        texts
            .iter()
            .map(|t| serde_json::from_str(t).map_err(json_err(&self.path)))
            .collect()
    }

    /// The index as one document, `{"schema", "entries": [...], "steps": [...]}` in JSON (the
    /// rows' JSON). Serialise it directly: through a `serde_json::Value` an `f32` such as γ
    /// would print widened (0.013000000268220901).
    ///
    /// # Errors
    /// As [`Self::entries`].
    pub fn export(&self) -> Result<Export, StoreError> {
        Ok(Export {
            schema: SCHEMA_VERSION,
            entries: self.entries()?,
            steps: self.steps()?,
        })
    }

    /// The index as CSV, one line per (step, rank) and one per composed step (`rank` empty):
    /// `step,rank,world_size,pm_version,scene_version,r,gamma,sigma_bytes,tau_secs,q_db,missing,vdi,error`
    /// (`error`: why a step of several ranks could not be composed, quoted as CSV quotes).
    ///
    /// # Errors
    /// As [`Self::entries`].
    pub fn export_csv(&self) -> Result<String, StoreError> {
        Ok(csv(&self.export()?))
    }
}

/// [`IndexDb::export_csv`] of rows read already (e.g. [`export_shards`]).
pub fn csv(e: &Export) -> String {
    let mut out = String::from(
        "step,rank,world_size,pm_version,scene_version,r,gamma,sigma_bytes,tau_secs,q_db,missing,vdi,error\n",
    );
    let q = |q: Option<f64>| q.map_or_else(String::new, |q| q.to_string());
    for e in &e.entries {
        out.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},,{},\n",
            e.step,
            e.rank,
            e.world_size,
            e.pm_version,
            e.scene_version,
            e.resolution,
            e.gamma,
            e.sizing.sigma_bytes,
            e.sizing.tau_secs,
            q(e.quality.as_ref().map(|q| q.q_db.0)),
            e.vdi.as_deref().unwrap_or_default()
        ));
    }
    for s in &e.steps {
        let missing: Vec<String> = s.missing.iter().map(u32::to_string).collect();
        out.push_str(&format!(
            "{},,{},{},{},{},{},{},{},{},{},{},{}\n",
            s.step,
            s.world_size,
            s.pm_version,
            s.scene_version,
            s.resolution,
            s.gamma,
            s.sizing.sigma_bytes,
            s.sizing.tau_secs,
            q(s.quality.as_ref().map(|q| q.q_db.0)),
            missing.join(" "),
            s.vdi.as_deref().unwrap_or_default(),
            csv_field(s.error.as_deref().unwrap_or_default())
        ));
    }
    out
}

/// `text` as one CSV field: quoted (quotes doubled) when it holds a comma, a quote or a line
/// break.
fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_owned()
    }
}

/// `e` with how to recover when it says the index of `dir` is damaged.
pub fn with_recovery_advice(e: StoreError, dir: &Path) -> StoreError {
    match e {
        StoreError::Corrupt { path, problem } if path.ends_with(INDEX_DB) => StoreError::Corrupt {
            path,
            problem: format!(
                "{problem}: restore it, or rebuild it from the recording's files with `insitu recover --recording {}` (the damaged file is kept beside)",
                dir.display()
            ),
        },
        other => other,
    }
}

/// Reads the index of the recording in `dir` without creating or changing anything (another
/// process may be writing it: WAL readers see the last committed rows).
///
/// # Errors
/// [`StoreError::Corrupt`] when there is no index or it cannot be read, saying how to rebuild
/// it (`insitu recover`).
pub fn read(dir: &Path) -> Result<(Vec<Entry>, Vec<StepEntry>), StoreError> {
    let shards = shards(dir);
    if shards.is_empty() {
        let rows = IndexDb::open(dir, false).and_then(|db| Ok((db.entries()?, db.steps()?)));
        return rows.map_err(|e| with_recovery_advice(e, dir));
    }
    let e = export_shards(&shards)?;
    Ok((e.entries, e.steps))
}

/// Prefix of a shard's directory in a recording shared by step among viz-nodes.
pub const SHARD_PREFIX: &str = "shard-";

/// The shards of a recording shared by step among several viz-nodes (docs/scale.md): the
/// subdirectories `shard-0`, `shard-1`, … of `dir` that hold an index, as (directory, its
/// name), in shard order; empty when `dir` holds an index itself or no shard.
pub fn shards(dir: &Path) -> Vec<(PathBuf, String)> {
    if dir.join(INDEX_DB).exists() {
        return Vec::new();
    }
    let Ok(read) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut found: Vec<(u64, PathBuf, String)> = read
        .filter_map(|d| {
            let d = d.ok()?;
            let name = d.file_name().to_str()?.to_owned();
            let k: u64 = name.strip_prefix(SHARD_PREFIX)?.parse().ok()?;
            d.path()
                .join(INDEX_DB)
                .exists()
                .then(|| (k, d.path(), name))
        })
        .collect();
    found.sort_by_key(|(k, _, _)| *k);
    found.into_iter().map(|(_, p, n)| (p, n)).collect()
}

/// The rows of every shard, their file names made relative to the shared recording
/// (`shard-K/…`), sorted by step and rank.
///
/// # Errors
/// [`StoreError`] naming the shard's index that cannot be read.
pub fn export_shards(shards: &[(PathBuf, String)]) -> Result<Export, StoreError> {
    let mut all = Export {
        schema: SCHEMA_VERSION,
        entries: Vec::new(),
        steps: Vec::new(),
    };
    let under = |name: &mut Option<String>, shard: &str| {
        if let Some(n) = name {
            *n = format!("{shard}/{n}");
        }
    };
    for (dir, shard) in shards {
        let db = IndexDb::open(dir, false).map_err(|e| with_recovery_advice(e, dir))?;
        for mut e in db.entries()? {
            under(&mut e.vdi, shard);
            under(&mut e.references, shard);
            all.entries.push(e);
        }
        for mut st in db.steps()? {
            under(&mut st.vdi, shard);
            under(&mut st.references, shard);
            all.steps.push(st);
        }
    }
    all.entries.sort_by_key(|e| (e.step, e.rank));
    all.steps.sort_by_key(|st| st.step);
    Ok(all)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step that could not compose carries its reason in the CSV, quoted, in the last
    /// column; rows of ranks leave it empty.
    #[test]
    fn the_csv_export_says_why_a_step_did_not_compose() {
        let dir = tempfile::tempdir().unwrap();
        let db = IndexDb::open(dir.path(), true).unwrap();
        db.put_step(&StepEntry {
            error: Some("step 3: bricks of ranks [0, 1] do not cover the grid".into()),
            ..StepEntry::of_ranks(3, 2, &[], vec![])
        })
        .unwrap();
        let csv = db.export_csv().unwrap();
        let mut lines = csv.lines();
        assert!(lines.next().unwrap().ends_with(",vdi,error"));
        let row = lines.next().unwrap();
        assert!(
            row.ends_with(",\"step 3: bricks of ranks [0, 1] do not cover the grid\""),
            "{row}"
        );
        assert_eq!(csv_field("a \"b\", c"), "\"a \"\"b\"\", c\"");
        assert_eq!(csv_field("plain"), "plain");
    }
}
