//! The memory a reader may take for one step: a file's header can claim any size, so the
//! volume it claims is checked against this limit before a byte is allocated, and a
//! compressed body (gzip, zlib) grows the volume as it decodes, under the same ceiling.
//!
//! The limit is `INSITU_READ_LIMIT` (a size as budgets write it,
//! [`insitu_core::units::parse_bytes`]: `8GiB`, `512MiB`, `8GB`), else half of what the process may have: the machine's
//! memory (`MemTotal` of `/proc/meminfo`) or the address-space limit (`ulimit -v`), whichever
//! is less; 16 GiB where neither can be read. An allocation that fails under the limit all the
//! same is an error naming its size, never an abort.

use insitu_core::units::parse_bytes;
use std::path::Path;

/// The environment variable that sets the limit.
pub const ENV: &str = "INSITU_READ_LIMIT";
/// The limit where the machine's memory cannot be read, bytes.
pub const FALLBACK: u64 = 16 << 30;

/// The limit in force, bytes.
///
/// # Errors
/// A message naming [`ENV`] and its value when the variable is set but not a size.
pub fn limit() -> Result<u64, String> {
    match std::env::var(ENV) {
        Ok(v) => parse_bytes(&v)
            .filter(|&b| b > 0)
            .ok_or_else(|| format!("{ENV}={v:?} is not a size in bytes (e.g. 8GiB, 512MiB)")),
        Err(_) => Ok(match (machine_memory(), address_space()) {
            (Some(m), Some(a)) => m.min(a) / 2,
            (Some(m), None) | (None, Some(m)) => m / 2,
            (None, None) => FALLBACK,
        }),
    }
}

/// The machine's memory from `/proc/meminfo`, bytes (Linux; none elsewhere).
fn machine_memory() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// The soft address-space limit from `/proc/self/limits` (`ulimit -v`), bytes; none when
/// unlimited or not Linux.
fn address_space() -> Option<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// `bytes` in the largest binary unit that keeps it ≥ 1 (`8.0 GiB`).
pub fn human(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = bytes as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{bytes} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

/// Refuses a volume of `samples` samples of `bytes_per_sample` bytes in memory over the limit,
/// naming the file, the size, the limit and how to raise it.
///
/// # Errors
/// [`crate::ReadError::Invalid`] naming `path` when the volume is over the limit or the limit
/// is malformed.
pub fn check(path: &Path, samples: usize, bytes_per_sample: usize) -> Result<(), crate::ReadError> {
    let limit = limit().map_err(|m| crate::ReadError::invalid(path, m))?;
    let bytes = (samples as u64).saturating_mul(bytes_per_sample as u64);
    if bytes > limit {
        return Err(crate::ReadError::invalid(
            path,
            format!(
                "a volume of {samples} samples needs {} of memory, over the read limit of {} (set {ENV} to raise it)",
                human(bytes),
                human(limit)
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_read_back_in_binary_units() {
        assert_eq!(human(512), "512 B");
        assert_eq!(human(8 << 30), "8.0 GiB");
        assert_eq!(human(3 << 19), "1.5 MiB");
    }
}
