//! Header-then-chunks streams (see the top of `insitu.proto`).
//!
//! [`split`] turns a header and a payload into the messages of one stream, slicing the payload
//! without copying; [`receive`] reassembles one, checking the declared size against a limit
//! before allocating and rejecting a missing or second header, an overrun and an early end.

use crate::pb;
use bytes::Bytes;
use tokio_stream::{Stream, StreamExt};
use tonic::Status;

/// Payload bytes per data message (the messages stay under [`crate::transport::MAX_MESSAGE_BYTES`]).
pub const CHUNK_BYTES: usize = 2 << 20;

/// One message of a header-then-chunks stream.
pub enum Part<H> {
    /// The header (first message only).
    Header(H),
    /// A slice of the payload.
    Data(Bytes),
}

/// A message type of a header-then-chunks stream.
pub trait Chunked: Sized + Send + 'static {
    /// The header message.
    type Header: Send + 'static;
    /// What the payload is, for error messages ("field data", "VDI", …).
    const WHAT: &'static str;
    /// Wraps a header.
    fn header(h: Self::Header) -> Self;
    /// Wraps a payload slice.
    fn data(b: Bytes) -> Self;
    /// Unwraps; `None` for an empty message.
    fn into_part(self) -> Option<Part<Self::Header>>;
    /// The payload length the header declares.
    fn declared_bytes(h: &Self::Header) -> u64;
}

macro_rules! chunked {
    ($msg:ident, $header:ident, $what:literal, $module:ident) => {
        impl Chunked for pb::$msg {
            type Header = pb::$header;
            const WHAT: &'static str = $what;
            fn header(h: pb::$header) -> Self {
                Self {
                    part: Some(pb::$module::Part::Header(h)),
                }
            }
            fn data(b: Bytes) -> Self {
                Self {
                    part: Some(pb::$module::Part::Data(b)),
                }
            }
            fn into_part(self) -> Option<Part<pb::$header>> {
                match self.part? {
                    pb::$module::Part::Header(h) => Some(Part::Header(h)),
                    pb::$module::Part::Data(b) => Some(Part::Data(b)),
                }
            }
            fn declared_bytes(h: &pb::$header) -> u64 {
                h.total_bytes
            }
        }
    };
}

chunked!(StepChunk, StepHeader, "field data", step_chunk);
chunked!(VdiChunk, VdiHeader, "VDI", vdi_chunk);
chunked!(
    ReferenceChunk,
    ReferenceHeader,
    "reference frames",
    reference_chunk
);

/// The messages of one stream: `header`, then `payload` in [`CHUNK_BYTES`] slices.
pub fn split<M: Chunked>(header: M::Header, payload: Bytes) -> Vec<M> {
    split_parts(header, [payload])
}

/// The messages of one stream whose payload is `parts` one after another (the named fields
/// of a step): `header`, then each part in [`CHUNK_BYTES`] slices of its own (no part is
/// copied to join another).
pub fn split_parts<M: Chunked>(
    header: M::Header,
    parts: impl IntoIterator<Item = Bytes>,
) -> Vec<M> {
    let mut out = vec![M::header(header)];
    for payload in parts {
        let mut at = 0;
        while at < payload.len() {
            let end = (at + CHUNK_BYTES).min(payload.len());
            out.push(M::data(payload.slice(at..end)));
            at = end;
        }
    }
    out
}

/// What can go wrong reassembling a stream; each maps to a gRPC status.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ChunkError {
    /// The first message is not a header.
    #[error("the stream must start with a header message, got data")]
    MissingHeader,
    /// The stream ended before any message.
    #[error("the stream ended before its header")]
    Empty,
    /// A second header.
    #[error("a second header message after {received} payload bytes")]
    SecondHeader {
        /// Payload bytes before it.
        received: u64,
    },
    /// An empty message.
    #[error("an empty message (neither header nor data)")]
    EmptyMessage,
    /// The declared size exceeds the receiver's limit.
    #[error("{what} of {declared} bytes exceeds this node's limit of {limit} bytes")]
    TooLarge {
        /// Payload kind.
        what: &'static str,
        /// Declared by the header.
        declared: u64,
        /// The limit.
        limit: u64,
    },
    /// More data than declared.
    #[error("{what} overruns its declared {declared} bytes")]
    Overrun {
        /// Payload kind.
        what: &'static str,
        /// Declared by the header.
        declared: u64,
    },
    /// The stream ended early.
    #[error("{what} stream ended after {received} of {declared} bytes")]
    Truncated {
        /// Payload kind.
        what: &'static str,
        /// Received.
        received: u64,
        /// Declared by the header.
        declared: u64,
    },
}

impl From<ChunkError> for Status {
    fn from(e: ChunkError) -> Self {
        match e {
            ChunkError::TooLarge { .. } => Status::resource_exhausted(e.to_string()),
            _ => Status::invalid_argument(e.to_string()),
        }
    }
}

/// Reassembles a stream into (header, payload) with the payload at most `limit` bytes.
/// `check` validates the header before any payload is read or allocated. Generic over the
/// stream so the rules are testable without a network (a server passes its
/// `tonic::Streaming<M>`).
///
/// # Errors
/// A [`ChunkError`] as a status, or `check`'s status; a transport error from the stream is
/// passed through.
pub async fn receive<M, S>(
    stream: &mut S,
    limit: u64,
    check: impl FnOnce(&M::Header) -> Result<(), Status>,
) -> Result<(M::Header, Vec<u8>), Status>
where
    M: Chunked,
    S: Stream<Item = Result<M, Status>> + Unpin,
{
    receive_into(
        stream,
        limit,
        |h: &M::Header| {
            check(h)?;
            // `declared ≤ limit`, and the limit is a memory budget the node chose.
            Ok(Vec::with_capacity(
                usize::try_from(M::declared_bytes(h)).unwrap_or(0),
            ))
        },
        |payload: &mut Vec<u8>, b: &[u8]| payload.extend_from_slice(b),
    )
    .await
}

/// [`receive`] into a sink of the caller's making: `begin` validates the header and returns
/// the sink (sized for the declared bytes, which are at most `limit`), `put` hands it each
/// chunk's bytes as they arrive, so a receiver can convert the payload on the way in instead
/// of keeping a copy of the bytes.
///
/// # Errors
/// As [`receive`]; `begin`'s status.
pub async fn receive_into<M, S, K>(
    stream: &mut S,
    limit: u64,
    begin: impl FnOnce(&M::Header) -> Result<K, Status>,
    mut put: impl FnMut(&mut K, &[u8]),
) -> Result<(M::Header, K), Status>
where
    M: Chunked,
    S: Stream<Item = Result<M, Status>> + Unpin,
{
    let header = match stream.next().await.transpose()?.map(M::into_part) {
        None => return Err(ChunkError::Empty.into()),
        Some(None) => return Err(ChunkError::EmptyMessage.into()),
        Some(Some(Part::Data(_))) => return Err(ChunkError::MissingHeader.into()),
        Some(Some(Part::Header(h))) => h,
    };
    let declared = M::declared_bytes(&header);
    if declared > limit {
        return Err(ChunkError::TooLarge {
            what: M::WHAT,
            declared,
            limit,
        }
        .into());
    }
    let mut sink = begin(&header)?;
    let mut received = 0u64;
    loop {
        match stream.next().await.transpose()?.map(M::into_part) {
            None if received == declared => return Ok((header, sink)),
            None => {
                return Err(ChunkError::Truncated {
                    what: M::WHAT,
                    received,
                    declared,
                }
                .into())
            }
            Some(None) => return Err(ChunkError::EmptyMessage.into()),
            Some(Some(Part::Header(_))) => return Err(ChunkError::SecondHeader { received }.into()),
            Some(Some(Part::Data(b))) => {
                if received + b.len() as u64 > declared {
                    return Err(ChunkError::Overrun {
                        what: M::WHAT,
                        declared,
                    }
                    .into());
                }
                received += b.len() as u64;
                put(&mut sink, &b);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(total: u64) -> pb::VdiHeader {
        pb::VdiHeader {
            step: 3,
            total_bytes: total,
            ..Default::default()
        }
    }

    async fn run(msgs: Vec<pb::VdiChunk>, limit: u64) -> Result<(pb::VdiHeader, Vec<u8>), Status> {
        let mut s = tokio_stream::iter(msgs.into_iter().map(Ok));
        receive(&mut s, limit, |_| Ok(())).await
    }

    fn block_on<F: std::future::Future>(f: F) -> F::Output {
        tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap()
            .block_on(f)
    }

    #[test]
    fn split_then_assemble_round_trips() {
        for n in [0usize, 1, CHUNK_BYTES - 1, CHUNK_BYTES, 2 * CHUNK_BYTES + 5] {
            let payload: Vec<u8> = (0..n).map(|i| (i * 31 % 251) as u8).collect();
            let msgs = split::<pb::VdiChunk>(header(n as u64), Bytes::from(payload.clone()));
            assert_eq!(msgs.len(), 1 + n.div_ceil(CHUNK_BYTES));
            let (h, p) = block_on(run(msgs, u64::MAX)).unwrap();
            assert_eq!((h.step, p), (3, payload), "n = {n}");
        }
    }

    #[test]
    fn malformed_streams_are_rejected() {
        let data = |n: usize| pb::VdiChunk::data(Bytes::from(vec![7u8; n]));
        let code = |msgs, limit| block_on(run(msgs, limit)).unwrap_err().code();
        use tonic::Code::*;
        assert_eq!(code(vec![], 10), InvalidArgument);
        assert_eq!(code(vec![data(3)], 10), InvalidArgument);
        assert_eq!(code(vec![pb::VdiChunk { part: None }], 10), InvalidArgument);
        assert_eq!(
            code(vec![pb::VdiChunk::header(header(11))], 10),
            ResourceExhausted
        );
        assert_eq!(
            code(vec![pb::VdiChunk::header(header(4)), data(3)], 10),
            InvalidArgument
        );
        assert_eq!(
            code(vec![pb::VdiChunk::header(header(4)), data(5)], 10),
            InvalidArgument
        );
        assert_eq!(
            code(
                vec![
                    pb::VdiChunk::header(header(4)),
                    data(2),
                    pb::VdiChunk::header(header(2))
                ],
                10
            ),
            InvalidArgument
        );
        let msg = block_on(run(vec![pb::VdiChunk::header(header(4)), data(3)], 10))
            .unwrap_err()
            .message()
            .to_owned();
        assert!(msg.contains("ended after 3 of 4 bytes"), "{msg}");
    }
}
