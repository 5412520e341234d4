//! A run's recording on disk, as the viz-node writes it and the CLI, the Python package and
//! the viz-node read it: each stored VDI and reference-frame file
//! (`step_SSSSSSSS_rank_RRRRR.vdi`, `…_composed.*`, written atomically), the index of their
//! rows in SQLite (`index.sqlite`, one shard per viz-node shard), the rows themselves
//! ([`rows`]: step, rank, `P_M`, σ, τ, q and the files' names, confined to their own), the
//! recording opened for writing or read-only with recovery of what a crash left unscored
//! ([`store`]), the index rebuilt from the files alone ([`rebuild`]), and stored VDIs read
//! back with their checks and a cache of the decoded ones ([`decoded`]).

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod decoded;
pub mod index;
pub mod rebuild;
pub mod rows;
pub mod store;
