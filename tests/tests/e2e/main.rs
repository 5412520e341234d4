//! End-to-end tests with the daemons as real processes on 127.0.0.1.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod bad_input;
mod common;
mod faults;
mod fields;
mod fortran;
mod gpu;
mod health;
mod hostile;
mod install;
mod local_sh;
mod mpi;
mod mpi_runs;
mod outage;
mod own_simulation;
mod policies;
mod python;
mod ranks;
mod renders;
mod replay;
mod shards;
mod slurm;
mod steering;
mod tls;
mod tuned;
mod tuner;
mod viewer;
