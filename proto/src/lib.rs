//! The gRPC contract of the in situ VDI service and the pieces every peer shares.
//!
//! - [`pb`]: the messages and services generated from `proto/insitu.proto` (tonic + prost,
//!   compiled with protox, so no system `protoc` is needed).
//! - [`chunk`]: large payloads travel as one header message plus data chunks; sending and
//!   receiving such streams with every limit checked before allocating.
//! - [`auth`]: bearer tokens (required off loopback) for servers and clients.
//! - [`tls`]: TLS settings (certificates, CA, mutual TLS) from PEM files.
//! - [`peer`]: a peer to dial: address, token and TLS together.
//! - [`security`]: a daemon's token, TLS and `insecure` keys, for its server and its peers.
//! - [`transport`]: HTTP/2 windows and message limits tuned for bulk field data.
//! - `convert` (feature `core`): wire messages ↔ `insitu-core` types.
//! - `daemon` (feature `daemon`): logging, signals, TOML loading and the flags every daemon
//!   takes.
//! - `health` (feature `daemon`): the daemons' gRPC health service (`grpc.health.v1`) and a
//!   probe that waits for it.

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod auth;
pub mod chunk;
#[cfg(feature = "core")]
pub mod convert;
#[cfg(feature = "daemon")]
pub mod daemon;
#[cfg(feature = "daemon")]
pub mod health;
pub mod peer;
pub mod security;
pub mod shared_memory;
pub mod tls;
pub mod transport;

/// Generated code for package `insitu.v1`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod pb {
    tonic::include_proto!("insitu.v1");
}
