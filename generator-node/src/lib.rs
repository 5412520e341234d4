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

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod config;
pub mod correct;
pub mod cpu;
pub mod hold;
pub mod host;
pub mod ingest;
pub mod layout;
pub mod node;
pub mod outbox;
pub mod pool;
pub mod preview;
pub mod queue;
pub mod refusals;
pub mod scene;
pub mod service;
pub mod settings;
pub mod shared;
pub mod ship;
pub mod shm;
pub mod spare;
pub mod spool;
pub mod stats;
pub mod tuner_link;
pub mod tuning;
pub mod work;

pub use config::Config;
pub use node::{start, RunningNode, StartError, Summary};
pub use queue::Policy;
