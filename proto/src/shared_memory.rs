//! The shared-memory push's contract between a client and a generator-node on one host
//! (`PushShared` in `insitu.proto`): how each tells that they share a host, and how the
//! client's files are named.

/// The prefix every shared-memory file's name carries (the node opens no other).
pub const FILE_PREFIX: &str = "insitu-";

/// This boot of this host: Linux's boot id, which every process of one boot reads the same
/// (containers that share the host's kernel included; whether they share the directory too,
/// a client finds out from its first push). `None` elsewhere, where steps are streamed.
pub fn host_id() -> Option<String> {
    let id = std::fs::read_to_string("/proc/sys/kernel/random/boot_id").ok()?;
    let id = id.trim();
    (!id.is_empty()).then(|| id.to_owned())
}
