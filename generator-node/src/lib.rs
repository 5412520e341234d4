//! The generator-node: the daemon beside a simulation (docs/conventions.md, "The system").
//!
//! A simulation pushes time steps (one rank's brick each) over gRPC ([`service`]); they wait in
//! a bounded [`queue`] with a named policy; a worker turns each into a compressed VDI on the
//! blocking pool ([`work`]), with reference frames of the test views every k-th step; a
//! world's ranks that share the node are composed into box-shaped parts ([`host`]) and put into a
//! bounded outbox ([`outbox`]); the [`ship`]per delivers them to the viz-node, reconnecting with back-off.
//! With a tuner configured, the node dials out to it ([`tuner_link`], with its state in [`tuning`]): a summary per step up,
//! claims on [`hold`]s of fields, trials and `P_M` decisions down.
//! [`node`] wires it together and shuts it down gracefully; [`config`] is the TOML file.
//!
//! The public surface is what other crates use: [`start`], [`Config`] (and [`config`]'s
//! types), [`RunningNode`], the [`shared`] state the CLI's pipeline reads, and
//! [`ingest::check_header`] for the fuzz targets. Every other module is private; these docs
//! link them, so read them with `cargo doc -p insitu-generator-node --document-private-items`.

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]
#![allow(rustdoc::private_intra_doc_links)]

#[cfg(feature = "adios2")]
mod adios2_input;
pub mod config;
mod correct;
mod cpu;
mod faces;
mod hold;
mod host;
pub mod ingest;
mod layout;
mod node;
mod outbox;
mod pool;
mod preview;
mod queue;
mod refusals;
mod scene;
mod service;
mod settings;
pub mod shared;
mod ship;
mod shm;
mod spare;
mod spool;
mod stats;
mod tuner_link;
mod tuning;
mod viz_link;
mod work;

pub use config::Config;
pub use node::{start, RunningNode, StartError, Summary};
pub use queue::Policy;
