//! The durable spool (`[spool]` in the config): every step is written to local disk before
//! `PushStep` acknowledges it, and removed once its VDI is stored by the viz-node (or dropped
//! or failed, and counted so). After kill -9 the restarted node finds the steps it had
//! acknowledged and not delivered, and generates them again; identical VDIs shipped twice are
//! idempotent at the viz-node, so a step stored just before the crash is not duplicated.
//!
//! With `durable = true` each file is fsync'd (and its directory) before the acknowledgement:
//! it survives a power loss, at the cost of a disk flush per step (measured in the note). The
//! spool is bounded in bytes; while it is full a push waits, like the `block` policy.
//!
//! The spool also keeps the node's run configuration (`run.pb`: TF, P_M and its version,
//! camera, views, cadence), rewritten atomically whenever it changes, so that a restarted node
//! continues the same scene instead of choosing a new default.
//!
//! File layout of a spooled step: `INSSPL1\n`, the header length (u64 LE), the `StepHeader`
//! as protobuf, then the field bytes.

use crate::ingest::{check_header, RawStep};
use insitu_proto::pb;
use prost::Message;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use tokio::sync::Notify;

const MAGIC: &[u8; 8] = b"INSSPL1\n";
/// The run configuration's file in the spool directory.
pub const RUN_CONFIG: &str = "run.pb";

/// Errors of the spool, naming the file.
#[derive(Debug, thiserror::Error)]
pub enum SpoolError {
    /// A file could not be read or written.
    #[error("spool {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A step is larger than the whole spool.
    #[error("a step of {bytes} bytes does not fit a spool of max_bytes {max}")]
    TooLarge {
        /// The step's bytes.
        bytes: u64,
        /// The spool's bound.
        max: u64,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SpoolError + '_ {
    move |source| SpoolError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The spool directory and its byte budget.
pub struct Spool {
    dir: PathBuf,
    durable: bool,
    max_bytes: u64,
    used: Mutex<u64>,
    freed: Notify,
    seq: AtomicU64,
}

/// Writes `bytes` to `dir/name` atomically ([`insitu_core::file::write_atomic`]); with
/// `durable`, fsync'd (file and directory) before returning.
fn write_file(dir: &Path, name: &str, bytes: &[u8], durable: bool) -> Result<(), SpoolError> {
    use insitu_core::file::{write_atomic, Durability};
    let path = dir.join(name);
    let durability = if durable {
        Durability::PowerLoss
    } else {
        Durability::Crash
    };
    write_atomic(&path, bytes, durability).map_err(io(&path))
}

fn header_of(raw: &RawStep) -> pb::StepHeader {
    let d = pb::Dims3::from;
    pb::StepHeader {
        step: raw.info.step,
        sim_time: raw.info.sim_time,
        // The field as held (u8, u16 or f32), which is what the data bytes below are.
        dtype: pb::ScalarType::from(raw.field.voxels().scalar_type()) as i32,
        global_dims: Some(d(raw.info.global_dims)),
        brick_offset: Some(d(raw.info.brick_offset)),
        brick_dims: Some(d(raw.info.brick_dims)),
        rank: raw.info.rank,
        world_size: raw.info.world_size,
        total_bytes: raw.bytes(),
        spacing: Some(pb::Vec3 {
            x: raw.info.spacing.x,
            y: raw.info.spacing.y,
            z: raw.info.spacing.z,
        }),
        origin: Some(pb::Vec3 {
            x: raw.info.origin.x,
            y: raw.info.origin.y,
            z: raw.info.origin.z,
        }),
        // The field kept (the one the scene renders, as received; cell data already on the
        // grid of its cells' centres) as the step's one unnamed field.
        fields: Vec::new(),
    }
}

impl Spool {
    /// Opens (creating) the spool in `dir` and reads back the steps a previous run left there,
    /// in the order they were acknowledged. Unreadable files are reported by name and moved
    /// aside (`*.bad`), never silently dropped.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the directory cannot be created or read.
    pub fn open(
        dir: &Path,
        durable: bool,
        max_bytes: u64,
    ) -> Result<(Self, Vec<RawStep>), SpoolError> {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .map_err(io(dir))?
            .filter_map(Result::ok)
            .map(|d| d.file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        let mut steps = Vec::new();
        let mut used = 0;
        let mut last_seq = 0;
        for name in names {
            let path = dir.join(&name);
            if name.starts_with(insitu_core::file::TEMP_PREFIX) {
                // A write the crash interrupted: never acknowledged.
                let _ = std::fs::remove_file(&path);
                continue;
            }
            let Some(seq) = name
                .strip_prefix("step_")
                .and_then(|n| n.split('_').next())
                .and_then(|n| n.parse::<u64>().ok())
            else {
                continue;
            };
            match Self::read(&path) {
                Ok(mut raw) => {
                    used += raw.bytes();
                    last_seq = last_seq.max(seq);
                    raw.spool = Some(name);
                    steps.push(raw);
                }
                Err(problem) => {
                    tracing::error!(file = %path.display(), %problem, "unreadable spooled step moved aside");
                    let _ = std::fs::rename(&path, dir.join(format!("{name}.bad")));
                }
            }
        }
        Ok((
            Self {
                dir: dir.to_owned(),
                durable,
                max_bytes,
                used: Mutex::new(used),
                freed: Notify::new(),
                seq: AtomicU64::new(last_seq + 1),
            },
            steps,
        ))
    }

    fn read(path: &Path) -> Result<RawStep, String> {
        let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err("not a spooled step".into());
        }
        let mut n = [0u8; 8];
        n.copy_from_slice(&bytes[8..16]);
        let n = usize::try_from(u64::from_le_bytes(n)).map_err(|e| e.to_string())?;
        let header = bytes
            .get(16..16usize.saturating_add(n))
            .ok_or("header runs past the end")?;
        let h = pb::StepHeader::decode(header).map_err(|e| e.to_string())?;
        let info = check_header(&h).map_err(|s| s.message().to_owned())?;
        let data = &bytes[16 + n..];
        if data.len() as u64 != h.total_bytes {
            return Err(format!(
                "{} field bytes, the header says {}",
                data.len(),
                h.total_bytes
            ));
        }
        let mut field = info.assembler(None);
        field.push(data);
        info.with_field(field).map_err(|s| s.message().to_owned())
    }

    /// Writes `raw` to the spool (waiting while the spool is full) and returns its file name.
    ///
    /// # Errors
    /// [`SpoolError::TooLarge`] for a step larger than the spool; [`SpoolError::Io`].
    pub async fn put(&self, raw: &RawStep) -> Result<String, SpoolError> {
        let n = raw.bytes();
        if n > self.max_bytes {
            return Err(SpoolError::TooLarge {
                bytes: n,
                max: self.max_bytes,
            });
        }
        loop {
            let notified = self.freed.notified();
            {
                let mut used = self.used.lock().unwrap_or_else(|p| p.into_inner());
                if *used + n <= self.max_bytes {
                    *used += n;
                    break;
                }
            }
            notified.await;
        }
        let seq = self.seq.fetch_add(1, Ordering::Relaxed);
        let name = format!("step_{seq:016}_s{}_r{}.step", raw.info.step, raw.info.rank);
        let header = header_of(raw).encode_to_vec();
        let data = raw.field.voxels().to_le_bytes();
        let mut file = Vec::with_capacity(16 + header.len() + data.len());
        file.extend_from_slice(MAGIC);
        file.extend_from_slice(&(header.len() as u64).to_le_bytes());
        file.extend_from_slice(&header);
        file.extend_from_slice(&data);
        let (dir, durable, file_name) = (self.dir.clone(), self.durable, name.clone());
        let written =
            tokio::task::spawn_blocking(move || write_file(&dir, &file_name, &file, durable))
                .await
                .unwrap_or_else(|e| {
                    Err(SpoolError::Io {
                        path: self.dir.clone(),
                        source: std::io::Error::other(e.to_string()),
                    })
                });
        if let Err(e) = written {
            self.release(n);
            return Err(e);
        }
        Ok(name)
    }

    fn release(&self, n: u64) {
        let mut used = self.used.lock().unwrap_or_else(|p| p.into_inner());
        *used = used.saturating_sub(n);
        self.freed.notify_waiters();
    }

    /// Removes a step whose fate is settled (stored, dropped or failed, and counted).
    pub fn remove(&self, name: &str, bytes: u64) {
        let path = self.dir.join(name);
        if let Err(e) = std::fs::remove_file(&path) {
            tracing::warn!(file = %path.display(), error = %e, "could not remove a settled spooled step");
        }
        self.release(bytes);
    }

    /// Bytes held.
    pub fn used(&self) -> u64 {
        *self.used.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records the run configuration (atomically, fsync'd when durable).
    ///
    /// # Errors
    /// [`SpoolError::Io`].
    pub fn save_run(
        &self,
        pm_version: u64,
        config: &pb::GenerationConfig,
    ) -> Result<(), SpoolError> {
        let mut bytes = pm_version.to_le_bytes().to_vec();
        bytes.extend_from_slice(&config.encode_to_vec());
        write_file(&self.dir, RUN_CONFIG, &bytes, self.durable)
    }

    /// The run configuration a previous run recorded, if any. A record whose transfer
    /// function is JSON text (written before the typed field) is read into the typed field,
    /// so that a spool outlives the upgrade; JSON that does not parse is left for
    /// [`crate::settings::apply_config`] to refuse by name.
    pub fn load_run(&self) -> Option<(u64, pb::GenerationConfig)> {
        let bytes = std::fs::read(self.dir.join(RUN_CONFIG)).ok()?;
        let (v, rest) = bytes.split_at_checked(8)?;
        let version = u64::from_le_bytes(v.try_into().ok()?);
        let mut run = pb::GenerationConfig::decode(rest).ok()?;
        if let Some(json) = run.legacy_tf_json.as_deref().filter(|_| run.tf.is_none()) {
            if let Ok(tf) = insitu_core::TransferFunction::from_json(json, RUN_CONFIG) {
                run.tf = Some(pb::TransferFunction::from(&tf));
                run.legacy_tf_json = None;
            }
        }
        Some((version, run))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw(step: u64, n: usize) -> RawStep {
        let h = pb::StepHeader {
            step,
            sim_time: step as f64,
            dtype: pb::ScalarType::F32 as i32,
            global_dims: Some(pb::Dims3 {
                x: n as u32,
                y: 1,
                z: 1,
            }),
            brick_offset: Some(pb::Dims3 { x: 0, y: 0, z: 0 }),
            brick_dims: Some(pb::Dims3 {
                x: n as u32,
                y: 1,
                z: 1,
            }),
            rank: 0,
            world_size: 1,
            total_bytes: 4 * n as u64,
            spacing: None,
            origin: None,
            fields: Vec::new(),
        };
        let info = check_header(&h).unwrap();
        let mut field = info.assembler(None);
        field.push(&(0..4 * n).map(|i| i as u8).collect::<Vec<_>>());
        info.with_field(field).unwrap()
    }

    #[tokio::test]
    async fn spooled_steps_come_back_in_order_until_removed_and_the_bound_holds() {
        let dir = tempfile::tempdir().unwrap();
        let (spool, old) = Spool::open(dir.path(), true, 100).unwrap();
        assert!(old.is_empty());
        let a = spool.put(&raw(7, 10)).await.unwrap();
        let b = spool.put(&raw(8, 10)).await.unwrap();
        assert_eq!(spool.used(), 80);
        // A third step of 40 bytes waits until one is removed.
        let third = raw(9, 10);
        let waiting = tokio::time::timeout(std::time::Duration::from_millis(50), spool.put(&third));
        assert!(waiting.await.is_err());
        spool.remove(&a, 40);
        let c = spool.put(&raw(9, 10)).await.unwrap();
        std::fs::write(dir.path().join(".tmp-x"), b"half").unwrap();
        drop(spool);
        let (spool, back) = Spool::open(dir.path(), true, 100).unwrap();
        let steps: Vec<u64> = back.iter().map(|r| r.info.step).collect();
        assert_eq!(steps, [8, 9]);
        assert_eq!(back[0].field, raw(8, 10).field);
        assert_eq!(back[0].spool.as_deref(), Some(b.as_str()));
        assert_eq!(back[1].spool.as_deref(), Some(c.as_str()));
        assert!(!dir.path().join(".tmp-x").exists());
        assert_eq!(spool.used(), 80);
        assert!(matches!(
            spool.put(&raw(1, 30)).await,
            Err(SpoolError::TooLarge {
                bytes: 120,
                max: 100
            })
        ));
        std::fs::write(dir.path().join("step_0000000000000099_s1_r0.step"), b"junk").unwrap();
        let (_, back) = Spool::open(dir.path(), true, 100).unwrap();
        assert_eq!(back.len(), 2);
        assert!(dir
            .path()
            .join("step_0000000000000099_s1_r0.step.bad")
            .exists());
    }

    /// A run record written when the transfer function travelled as JSON text reads back
    /// with it typed (the spool outlives the upgrade); the typed record round-trips.
    #[test]
    fn a_run_record_with_the_transfer_function_as_text_reads_back_typed() {
        let dir = tempfile::tempdir().unwrap();
        let (spool, _) = Spool::open(dir.path(), false, 1 << 20).unwrap();
        let json = r#"{"domain":[0,4],"points":[[0,0,0,0,0],[1,1,0.5,0,0.8]]}"#;
        let old = pb::GenerationConfig {
            resolution: 64,
            legacy_tf_json: Some(json.into()),
            tf_name: Some("old".into()),
            ..Default::default()
        };
        spool.save_run(3, &old).unwrap();
        let (version, run) = spool.load_run().unwrap();
        let tf = insitu_core::TransferFunction::from_json(json, "t").unwrap();
        assert_eq!(version, 3);
        assert_eq!(run.tf, Some(pb::TransferFunction::from(&tf)));
        assert_eq!(run.legacy_tf_json, None);
        assert_eq!(run.tf_name.as_deref(), Some("old"));
        spool.save_run(4, &run).unwrap();
        assert_eq!(spool.load_run().unwrap(), (4, run));
    }
}
