//! # insitu-core
//!
//! The maths of the in situ VDI service, shared by every node: volumes, transfer functions,
//! cameras, the reference ray-caster, Volumetric Depth Image (VDI) generation, the VDI codec,
//! VDI rendering from new views and image metrics. Synchronous and deterministic; no
//! networking, no CLI. The method is Frey & Ertl, "Auto-Tuning Intermediate Representations
//! for In Situ Visualization"; conventions are those of `docs/conventions.md`.
//!
//! Main types: [`Volume`], [`TransferFunction`], [`Camera`], [`Raycaster`] (shared sampling),
//! [`Vdi`] (supersegment lists), [`Image`].
//!
//! ```
//! use insitu_core::{dvr, metrics, vdi, Camera, RaycastParams, Raycaster, TransferFunction, Volume};
//!
//! let volume = Volume::from_fn([16, 16, 16], |x, y, z| (x + y + z) as f32).unwrap();
//! let tf = TransferFunction::default_for_range(0.0, 45.0);
//! let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
//! let camera = Camera::default_for_box(&volume.world_box());
//! let reference = dvr::render(&rc, &camera, 32, 32);
//! let params = vdi::VdiParams { resolution: 32, gamma: 0.01, precision: Default::default()  };
//! let m = vdi::generate::generate(&rc, &camera, params, tf.identity_hash(), "ramp").unwrap();
//! let bytes = vdi::codec::encode(&m, vdi::codec::Codec::Zstd).unwrap(); // σ = bytes.len()
//! let image = vdi::render::render(&m, &camera, 32, 32, 0.99);
//! let q = metrics::psnr(&image, &reference).unwrap();
//! assert!(q > 60.0);
//! # let _ = bytes;
//! ```

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod adherence;
pub mod backend;
pub mod budget;
pub mod camera;
pub mod cancel;
pub mod compose;
pub mod dvr;
pub mod evaluate;
pub(crate) mod fastmath;
pub mod file;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod image;
pub mod json;
pub mod metrics;
pub mod raycast;
pub mod tf;
pub mod units;
pub mod vdi;
pub mod volume;

pub use backend::{Backend, BackendChoice};
pub use camera::{Camera, Ray};
pub use image::Image;
pub use raycast::{RaycastParams, Raycaster, Shading};
pub use tf::{NamedTf, TfIdentity, TransferFunction};
pub use vdi::{Precision, Supersegment, Vdi, VdiParams};
pub use volume::Volume;
