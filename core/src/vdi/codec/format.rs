//! The file format's vocabulary, shared by the codec and the provenance block it carries:
//! the magic and current version, the entropy codecs, the errors, and the bounds-checked
//! reader every field is read through.

use glam::Vec3;

/// File magic.
pub const MAGIC: [u8; 8] = [0x89, b'V', b'D', b'I', 0x0d, 0x0a, 0x1a, 0x0a];
/// Current format version: quantised supersegments ([`super::quantized`]), written for
/// [`crate::vdi::Precision::Bits`].
pub const FORMAT_VERSION: u16 = 4;

/// Compression applied to the payload. In files and JSON by its [`Codec::name`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Codec {
    /// Stored as is.
    None,
    /// bzip2, block size 900k: the paper's σ (Sec. 5.3).
    Bzip2,
    /// zstd, level 3: much faster, similar ratio on float planes.
    Zstd,
}

impl Codec {
    /// All codecs.
    pub const ALL: [Codec; 3] = [Codec::None, Codec::Bzip2, Codec::Zstd];

    pub(super) fn id(self) -> u8 {
        match self {
            Self::None => 0,
            Self::Bzip2 => 1,
            Self::Zstd => 2,
        }
    }

    pub(super) fn from_id(id: u8) -> Option<Self> {
        Self::ALL.into_iter().find(|c| c.id() == id)
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Bzip2 => "bzip2",
            Self::Zstd => "zstd",
        }
    }
}

impl std::fmt::Display for Codec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Codec {
    type Err = CodecError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|c| c.name() == s.to_ascii_lowercase())
            .ok_or_else(|| CodecError::UnknownCodecName(s.to_owned()))
    }
}

/// Why bytes are not a valid VDI file.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    /// Fewer bytes than a field needs.
    #[error("VDI data truncated: {what} needs {needed} bytes, {available} left")]
    Truncated {
        /// The field being read.
        what: &'static str,
        /// Bytes needed.
        needed: u64,
        /// Bytes left.
        available: u64,
    },
    /// Not a VDI file.
    #[error("not a VDI file (bad magic)")]
    BadMagic,
    /// A version this build does not read.
    #[error(
        "VDI format version {0} is not supported (this build reads versions 1 to {FORMAT_VERSION})"
    )]
    UnsupportedVersion(u16),
    /// Unknown codec byte.
    #[error("unknown VDI codec id {0}")]
    UnknownCodec(u8),
    /// Unknown codec name (CLI, config).
    #[error("unknown codec {0:?} (expected none, bzip2 or zstd)")]
    UnknownCodecName(String),
    /// Claimed size over the limit.
    #[error("VDI payload of {claimed} bytes exceeds the limit of {limit} bytes")]
    TooLarge {
        /// Claimed payload length.
        claimed: u64,
        /// The limit.
        limit: u64,
    },
    /// Checksum mismatch: the bytes were altered.
    #[error("VDI checksum mismatch (stored {stored:#010x}, computed {computed:#010x}): the file is corrupt")]
    Checksum {
        /// Stored CRC.
        stored: u32,
        /// Computed CRC.
        computed: u32,
    },
    /// The decompressor failed.
    #[error("VDI body does not decompress with {codec}: {source}")]
    Decompress {
        /// Codec used.
        codec: Codec,
        /// The cause.
        source: std::io::Error,
    },
    /// Compression failed (I/O inside the encoder).
    #[error("VDI compression with {codec} failed: {source}")]
    Compress {
        /// Codec used.
        codec: Codec,
        /// The cause.
        source: std::io::Error,
    },
    /// A field is out of range or inconsistent with another.
    #[error("invalid VDI: {0}")]
    Invalid(String),
}

/// Bounds-checked little-endian reader.
pub(in crate::vdi) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub(in crate::vdi) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, pos: 0 }
    }

    pub(in crate::vdi) fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    pub(in crate::vdi) fn rest(&mut self) -> &'a [u8] {
        let rest = &self.bytes[self.pos..];
        self.pos = self.bytes.len();
        rest
    }

    pub(in crate::vdi) fn take(
        &mut self,
        n: usize,
        what: &'static str,
    ) -> Result<&'a [u8], CodecError> {
        if n > self.remaining() {
            return Err(CodecError::Truncated {
                what,
                needed: n as u64,
                available: self.remaining() as u64,
            });
        }
        let out = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(out)
    }

    pub(in crate::vdi) fn array<const N: usize>(
        &mut self,
        what: &'static str,
    ) -> Result<[u8; N], CodecError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }

    pub(in crate::vdi) fn u8(&mut self, what: &'static str) -> Result<u8, CodecError> {
        Ok(self.array::<1>(what)?[0])
    }

    pub(in crate::vdi) fn u16(&mut self, what: &'static str) -> Result<u16, CodecError> {
        Ok(u16::from_le_bytes(self.array(what)?))
    }

    pub(in crate::vdi) fn u32(&mut self, what: &'static str) -> Result<u32, CodecError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    pub(in crate::vdi) fn u64(&mut self, what: &'static str) -> Result<u64, CodecError> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    pub(in crate::vdi) fn finite(&mut self, what: &'static str) -> Result<f32, CodecError> {
        let v = f32::from_le_bytes(self.array(what)?);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(CodecError::Invalid(format!("{what} is {v}")))
        }
    }

    pub(in crate::vdi) fn vec3(&mut self, what: &'static str) -> Result<Vec3, CodecError> {
        Ok(Vec3::new(
            self.finite(what)?,
            self.finite(what)?,
            self.finite(what)?,
        ))
    }
}
