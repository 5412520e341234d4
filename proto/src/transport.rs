//! HTTP/2 settings for bulk transfers and per-message limits.
//!
//! Default windows cap loopback at 185–320 MB/s. With the field converted as it
//! arrives (the generator-node's receive), the windows were the limit again: pushes of 64 MiB
//! steps (`cargo bench -p insitu-e2e --bench pipeline`, 2-core VM) ran at 0.74–0.79 GB/s with
//! 16 MiB stream / 32 MiB connection windows, 0.87–0.95 GB/s with 32 / 64 MiB and no better
//! with 64 / 128 MiB (0.83–0.97). The connection window bounds what a peer may send that the
//! receiver has not read yet: at most 64 MiB per connection.

use std::time::Duration;
use tonic::transport::{Channel, Endpoint, Server};

/// Largest single gRPC message accepted or sent: a data chunk plus its framing.
pub const MAX_MESSAGE_BYTES: usize = crate::chunk::CHUNK_BYTES + (64 << 10);
const STREAM_WINDOW: u32 = 32 << 20;
const CONNECTION_WINDOW: u32 = 64 << 20;

/// A server builder with large flow-control windows and frames.
pub fn server() -> Server {
    Server::builder()
        .initial_stream_window_size(STREAM_WINDOW)
        .initial_connection_window_size(CONNECTION_WINDOW)
        .max_frame_size(Some((1 << 24) - 1))
        .tcp_nodelay(true)
}

/// An endpoint for `uri` (e.g. `http://127.0.0.1:50051`) with the same windows and a connect
/// timeout.
///
/// # Errors
/// When `uri` is not a valid URI.
pub fn endpoint(uri: &str) -> Result<Endpoint, tonic::transport::Error> {
    Ok(Endpoint::from_shared(uri.to_owned())?
        .initial_stream_window_size(STREAM_WINDOW)
        .initial_connection_window_size(CONNECTION_WINDOW)
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true))
}

/// Connects to `uri` now.
///
/// # Errors
/// When `uri` is invalid or nothing answers there.
pub async fn connect(uri: &str) -> Result<Channel, tonic::transport::Error> {
    endpoint(uri)?.connect().await
}

/// `http://` + `addr` unless it already names a scheme.
pub fn uri(addr: &str) -> String {
    if addr.contains("://") {
        addr.to_owned()
    } else {
        format!("http://{addr}")
    }
}
