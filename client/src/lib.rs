//! The simulation client: what a simulation links to hand its time steps to a generator-node
//! (`proto/insitu.proto` is the contract for other languages).
//!
//! ```no_run
//! # async fn run() -> Result<(), insitu_client::ClientError> {
//! use insitu_client::{SimClient, Step};
//! let mut client = SimClient::connect("127.0.0.1:50051", None).await?;
//! let field = vec![0.0f32; 64 * 64 * 64];
//! for step in 0..10u64 {
//!     // ... advance the simulation ...
//!     let reply = client.push_step(Step::whole_f32(step, step as f64, [64, 64, 64], &field)).await?;
//!     println!("queued, depth {}", reply.queue_depth);
//! }
//! client.close(std::time::Duration::from_secs(60)).await?;
//! # Ok(()) }
//! ```
//!
//! `push_step` returns once the node has the whole step in its queue (with the node's `block`
//! policy, once there is room), never after generation. Errors say whether the node was
//! unreachable or refused the step; the simulation decides whether to go on.
//!
//! A client on the node's own host pushes through shared memory on its own ([`shm`]: the
//! payload written into a file of the node's `/dev/shm`, only the header sent), and streams
//! otherwise; [`SimClient::shared_memory`] says which, `INSITU_SHARED_MEMORY=0` keeps to
//! streaming.

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

use insitu_proto::auth::{AttachToken, Token};
use insitu_proto::pb::generator_client::GeneratorClient;
use insitu_proto::{chunk, pb, transport};
use std::borrow::Borrow;
use std::time::Duration;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;

pub mod shm;

pub use bytes::Bytes;
pub use insitu_proto::auth::Token as BearerToken;
pub use insitu_proto::pb::{
    Association, ConfigReply, GenerationConfig, GeneratorStatus, PushReply, ScalarType,
};
pub use insitu_proto::peer::Peer;
pub use insitu_proto::tls::TlsFiles;
pub use tonic::Code;

/// Errors of the client.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The address is not usable.
    #[error("invalid generator-node address {addr:?}: {source}")]
    Address {
        /// As given.
        addr: String,
        /// Why.
        source: tonic::transport::Error,
    },
    /// Nothing answers at the address, or the TLS handshake failed (the cause is in the
    /// message: e.g. a certificate not signed by the CA).
    #[error("generator-node at {addr} is unreachable: {cause}")]
    Unreachable {
        /// As given.
        addr: String,
        /// Why, with every cause in the chain.
        cause: String,
    },
    /// The token would travel in clear text off loopback, or TLS is asked for without a CA,
    /// or the TLS files are unusable.
    #[error(transparent)]
    Security(#[from] insitu_proto::auth::AuthError),
    /// TLS files.
    #[error(transparent)]
    Tls(#[from] insitu_proto::tls::TlsError),
    /// The node answered with an error (bad step, shutting down, wrong token, …), or the
    /// call failed on the way (`Unavailable`: the node went away).
    #[error("{}", refusal_text(*code, message))]
    Refused {
        /// gRPC status code.
        code: tonic::Code,
        /// The node's message.
        message: String,
    },
    /// The step's description is inconsistent (checked before sending).
    #[error("invalid step: {0}")]
    InvalidStep(String),
}

/// What a failed call says: what happened, and for the codes a user can act on, what to do.
fn refusal_text(code: tonic::Code, message: &str) -> String {
    // A call in flight when the connection drops ends `Unknown: transport error`, or
    // `Cancelled: operation was canceled` where hyper's connection task ended under it (a node
    // killed mid-call); one started after, `Unavailable`.
    let lost = code == tonic::Code::Unavailable
        || (code == tonic::Code::Unknown && message.starts_with("transport error"))
        || (code == tonic::Code::Cancelled && message.starts_with("operation was canceled"));
    match code {
        _ if lost => format!(
            "the generator-node went away ({message}): it stopped or the link broke; restart \
             it and push again (with a [spool] it resumes the steps it had acknowledged)"
        ),
        tonic::Code::Unauthenticated => format!(
            "the generator-node refused the token (Unauthenticated: {message}): give the \
             client the token the node was started with (INSITU_TOKEN or its token file)"
        ),
        code => format!("generator-node refused the call: {code:?}: {message}"),
    }
}

impl From<tonic::Status> for ClientError {
    fn from(s: tonic::Status) -> Self {
        Self::Refused {
            code: s.code(),
            message: s.message().to_owned(),
        }
    }
}

/// One time step (one rank's brick of it).
#[derive(Clone, Debug)]
pub struct Step {
    /// Step index.
    pub step: u64,
    /// Simulation time.
    pub sim_time: f64,
    /// Scalar type of `data`.
    pub dtype: ScalarType,
    /// The whole grid, voxels.
    pub global_dims: [u32; 3],
    /// This brick's first voxel in the whole grid.
    pub brick_offset: [u32; 3],
    /// This brick's size, voxels.
    pub brick_dims: [u32; 3],
    /// This rank.
    pub rank: u32,
    /// Number of ranks.
    pub world_size: u32,
    /// Voxel spacing, world units.
    pub spacing: [f32; 3],
    /// World position of the whole grid's first voxel (where the brick at offset 0 starts).
    pub origin: [f32; 3],
    /// The field, little-endian, x fastest: `brick voxels × dtype size` bytes; empty when the
    /// step carries named `fields` instead.
    pub data: Bytes,
    /// The step's named fields (Conduit Blueprint's `fields/<name>` on the uniform mesh the
    /// dims, origin and spacing above describe); empty: `data` is the step's one field.
    pub fields: Vec<Field>,
}

/// One named field of a step (Blueprint `fields/<name>`: `association`, `values`).
#[derive(Clone, Debug)]
pub struct Field {
    /// Its name, unique within the step, 1 to 128 bytes.
    pub name: String,
    /// On the grid's points (`brick_dims` values) or cells (`brick_dims − 1` per axis).
    pub association: Association,
    /// Scalar type of `values`.
    pub dtype: ScalarType,
    /// The values, little-endian, x fastest.
    pub values: Bytes,
}

impl Field {
    /// A vertex-associated `f32` field.
    pub fn vertex_f32(name: &str, values: &[f32]) -> Self {
        Self {
            name: name.into(),
            association: Association::Vertex,
            dtype: ScalarType::F32,
            values: f32_bytes(values),
        }
    }

    /// An element-associated (cell) `f32` field.
    pub fn element_f32(name: &str, values: &[f32]) -> Self {
        Self {
            association: Association::Element,
            ..Self::vertex_f32(name, values)
        }
    }
}

/// Longest field name, bytes.
pub const MAX_FIELD_NAME: usize = 128;

/// Bytes per sample of `t`.
fn size_of(t: ScalarType) -> Result<u64, String> {
    Ok(match t {
        ScalarType::U8 => 1,
        ScalarType::U16 | ScalarType::I16 => 2,
        ScalarType::F32 => 4,
        ScalarType::F64 => 8,
        ScalarType::Unspecified => return Err("dtype is unspecified".into()),
    })
}

impl Step {
    /// A whole single-rank `f32` field (x fastest), unit spacing.
    pub fn whole_f32(step: u64, sim_time: f64, dims: [u32; 3], field: &[f32]) -> Self {
        Self::whole(step, sim_time, ScalarType::F32, dims, f32_bytes(field))
    }

    /// [`Self::whole_f32`] taking the field's vector, which is sent without a copy (a
    /// simulation that copies its field out of its own buffers each push pays that one copy
    /// only).
    pub fn whole_f32_owned(step: u64, sim_time: f64, dims: [u32; 3], field: Vec<f32>) -> Self {
        Self::whole(step, sim_time, ScalarType::F32, dims, f32_vec_bytes(field))
    }

    /// [`Self::whole_f32`] sending the vector `field` holds, without a copy, while the
    /// simulation keeps its own handle: once the push has returned the client holds no
    /// reference to it, so `Arc::get_mut` gives the buffer back for the next step's copy
    /// (memory reused push after push, no fresh page faulted in for each).
    pub fn whole_f32_shared(
        step: u64,
        sim_time: f64,
        dims: [u32; 3],
        field: std::sync::Arc<Vec<f32>>,
    ) -> Self {
        Self::whole(
            step,
            sim_time,
            ScalarType::F32,
            dims,
            f32_owner_bytes(field),
        )
    }

    /// A whole single-rank `u8` field (x fastest), unit spacing.
    pub fn whole_u8(step: u64, sim_time: f64, dims: [u32; 3], field: impl Into<Bytes>) -> Self {
        Self::whole(step, sim_time, ScalarType::U8, dims, field.into())
    }

    /// The step with named `fields` in place of one unnamed field (`data` emptied, `dtype`
    /// then unused).
    pub fn with_fields(self, fields: Vec<Field>) -> Self {
        Self {
            data: Bytes::new(),
            fields,
            ..self
        }
    }

    fn whole(step: u64, sim_time: f64, dtype: ScalarType, dims: [u32; 3], data: Bytes) -> Self {
        Self {
            step,
            sim_time,
            dtype,
            global_dims: dims,
            brick_offset: [0; 3],
            brick_dims: dims,
            rank: 0,
            world_size: 1,
            spacing: [1.0; 3],
            origin: [0.0; 3],
            data,
            fields: Vec::new(),
        }
    }

    /// The payload: `data`, or each field's values in order.
    fn payload(&self) -> Vec<Bytes> {
        if self.fields.is_empty() {
            vec![self.data.clone()]
        } else {
            self.fields.iter().map(|f| f.values.clone()).collect()
        }
    }

    /// Checks the named fields against the brick: names, types, and each field's bytes.
    fn check_fields(&self) -> Result<Vec<pb::Field>, String> {
        if !self.data.is_empty() {
            return Err("a step carries either data or named fields, not both".into());
        }
        let points: u64 = self.brick_dims.iter().map(|&d| u64::from(d)).product();
        let cells: u64 = self
            .brick_dims
            .iter()
            .map(|&d| u64::from(d.saturating_sub(1)))
            .product();
        let mut out = Vec::with_capacity(self.fields.len());
        for (i, f) in self.fields.iter().enumerate() {
            if f.name.is_empty() || f.name.len() > MAX_FIELD_NAME {
                return Err(format!(
                    "field {i}: a name of 1 to {MAX_FIELD_NAME} bytes, not {:?}",
                    f.name
                ));
            }
            if self.fields[..i].iter().any(|g| g.name == f.name) {
                return Err(format!("field {:?} is named twice", f.name));
            }
            let size = size_of(f.dtype).map_err(|e| format!("field {:?}: {e}", f.name))?;
            let (count, what) = match f.association {
                Association::Vertex => (points, "points"),
                Association::Element => (cells, "cells"),
            };
            if count * size != f.values.len() as u64 {
                return Err(format!(
                    "field {:?}: {} bytes for the {count} {what} of a brick of {:?} points at {size} bytes each",
                    f.name,
                    f.values.len(),
                    self.brick_dims
                ));
            }
            out.push(pb::Field {
                name: f.name.clone(),
                association: f.association as i32,
                dtype: f.dtype as i32,
            });
        }
        Ok(out)
    }

    fn header(&self) -> Result<pb::StepHeader, ClientError> {
        let fields = if self.fields.is_empty() {
            let size = size_of(self.dtype).map_err(ClientError::InvalidStep)?;
            let voxels: u64 = self.brick_dims.iter().map(|&d| u64::from(d)).product();
            if voxels * size != self.data.len() as u64 {
                return Err(ClientError::InvalidStep(format!(
                    "{} bytes for a brick of {:?} voxels of {size} bytes",
                    self.data.len(),
                    self.brick_dims
                )));
            }
            Vec::new()
        } else {
            self.check_fields().map_err(ClientError::InvalidStep)?
        };
        let total_bytes = self.payload().iter().map(|b| b.len() as u64).sum();
        let d = |v: [u32; 3]| {
            Some(pb::Dims3 {
                x: v[0],
                y: v[1],
                z: v[2],
            })
        };
        Ok(pb::StepHeader {
            step: self.step,
            sim_time: self.sim_time,
            dtype: self.dtype as i32,
            global_dims: d(self.global_dims),
            brick_offset: d(self.brick_offset),
            brick_dims: d(self.brick_dims),
            rank: self.rank,
            world_size: self.world_size,
            total_bytes,
            spacing: Some(pb::Vec3 {
                x: self.spacing[0],
                y: self.spacing[1],
                z: self.spacing[2],
            }),
            origin: Some(pb::Vec3 {
                x: self.origin[0],
                y: self.origin[1],
                z: self.origin[2],
            }),
            fields,
        })
    }
}

/// `field` as little-endian bytes: one copy, a `memcpy` on a little-endian machine.
pub fn f32_bytes(field: &[f32]) -> Bytes {
    if cfg!(target_endian = "little") {
        Bytes::copy_from_slice(bytemuck::cast_slice(field))
    } else {
        field
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
            .into()
    }
}

/// A `Vec<f32>`, owned or shared, seen as its bytes (the buffer of [`f32_vec_bytes`] and
/// [`Step::whole_f32_shared`]).
struct F32Bytes<T>(T);

impl<T: Borrow<Vec<f32>>> AsRef<[u8]> for F32Bytes<T> {
    fn as_ref(&self) -> &[u8] {
        bytemuck::cast_slice(self.0.borrow().as_slice())
    }
}

/// `field` as little-endian bytes without a copy on a little-endian machine: the vector
/// becomes the buffer the step's chunks are cut from, freed (or, shared, given back) when the
/// last is sent. On a big-endian machine, converted as [`f32_bytes`] does.
fn f32_owner_bytes<T: Borrow<Vec<f32>> + Send + 'static>(field: T) -> Bytes {
    if cfg!(target_endian = "little") {
        Bytes::from_owner(F32Bytes(field))
    } else {
        f32_bytes(field.borrow())
    }
}

/// `field` as little-endian bytes without a copy on a little-endian machine: the vector
/// becomes the buffer the step's chunks are cut from, freed when the last is sent. On a
/// big-endian machine, converted as [`f32_bytes`] does.
pub fn f32_vec_bytes(field: Vec<f32>) -> Bytes {
    f32_owner_bytes(field)
}

/// A connection to one generator-node.
#[derive(Clone)]
pub struct SimClient {
    inner: GeneratorClient<InterceptedService<Channel, AttachToken>>,
    /// The ranks this client pushed steps for: a flush reports their refusals only.
    ranks: std::collections::BTreeSet<u32>,
    /// Whether steps go through shared memory ([`shm`]).
    shm: shm::SharedMemory,
}

impl SimClient {
    /// Connects to the node at `addr` (`host:port` or `http://host:port`) in clear text,
    /// sending `token` with every call.
    ///
    /// # Errors
    /// [`ClientError::Address`], [`ClientError::Unreachable`], or [`ClientError::Security`]
    /// when a token would go in clear text to a host that is not loopback (use
    /// [`SimClient::connect_with`] and TLS).
    pub async fn connect(addr: &str, token: Option<&Token>) -> Result<Self, ClientError> {
        Self::connect_with(Peer::new(addr, token.cloned(), None, false)?).await
    }

    /// Connects to `peer`: its address, token and TLS settings (e.g.
    /// `Peer::new(addr, token, TlsFiles { ca_file, .. }.client()?, false)`).
    ///
    /// # Errors
    /// [`ClientError::Address`] or [`ClientError::Unreachable`] (a failed TLS handshake
    /// included, with its cause).
    pub async fn connect_with(peer: Peer) -> Result<Self, ClientError> {
        let endpoint = peer.endpoint().map_err(|source| ClientError::Address {
            addr: peer.uri().to_owned(),
            source,
        })?;
        let channel = endpoint
            .connect()
            .await
            .map_err(|e| ClientError::Unreachable {
                addr: peer.uri().to_owned(),
                cause: insitu_proto::peer::error_chain(&e),
            })?;
        Ok(Self {
            inner: GeneratorClient::with_interceptor(channel, peer.auth())
                .max_decoding_message_size(transport::MAX_MESSAGE_BYTES)
                .max_encoding_message_size(transport::MAX_MESSAGE_BYTES),
            ranks: Default::default(),
            shm: Default::default(),
        })
    }

    /// Hands `step` to the node; returns once it is queued there (see the crate docs):
    /// through shared memory where the node shares this host ([`shm`]), else streamed.
    ///
    /// # Errors
    /// [`ClientError::InvalidStep`] before sending; [`ClientError::Refused`] from the node.
    pub async fn push_step(&mut self, step: Step) -> Result<PushReply, ClientError> {
        let header = step.header()?;
        self.ranks.insert(step.rank);
        let payload = step.payload();
        if let Some(reply) = self.push_shared(&header, &payload).await? {
            return Ok(reply);
        }
        let msgs = chunk::split_parts::<pb::StepChunk>(header, payload);
        Ok(self
            .inner
            .push_step(tokio_stream::iter(msgs))
            .await?
            .into_inner())
    }

    /// Whether this client's steps go through shared memory: `Some(true)` after a push that
    /// did, `Some(false)` once it streams (another host, or shared memory failed once), `None`
    /// before the first push.
    pub fn shared_memory(&self) -> Option<bool> {
        match self.shm {
            shm::SharedMemory::Unknown => None,
            shm::SharedMemory::Off => Some(false),
            shm::SharedMemory::On { .. } => Some(true),
        }
    }

    /// Allows shared memory for the next pushes (found out again at the next one), or keeps
    /// this client to streaming.
    pub fn set_shared_memory(&mut self, allowed: bool) {
        self.shm = if allowed {
            shm::SharedMemory::Unknown
        } else {
            shm::SharedMemory::Off
        };
    }

    /// The push through shared memory, when this client uses it: the payload written into its
    /// file (on the blocking pool), the header and path sent. `None` when the step is to be
    /// streamed: shared memory off, or failing now (then off for good: no room for the file,
    /// a node that cannot read it or cannot say where it would).
    async fn push_shared(
        &mut self,
        header: &pb::StepHeader,
        payload: &[Bytes],
    ) -> Result<Option<PushReply>, ClientError> {
        if matches!(self.shm, shm::SharedMemory::Unknown) {
            // A node that does not answer the question is streamed to: the push itself then
            // says whatever is wrong.
            self.shm = match self.status().await {
                Ok(status) => shm::SharedMemory::for_node(&status),
                Err(_) => shm::SharedMemory::Off,
            };
        }
        let shm::SharedMemory::On { dir, segment } = &mut self.shm else {
            return Ok(None);
        };
        let (dir, held, parts) = (dir.clone(), segment.take(), payload.to_vec());
        let written = tokio::task::spawn_blocking(move || {
            let mut s = match held {
                Some(s) => s,
                None => shm::Segment::create(&dir)?,
            };
            s.write(&parts).map(|()| s)
        })
        .await;
        let Ok(Ok(written)) = written else {
            self.shm = shm::SharedMemory::Off;
            return Ok(None);
        };
        let request = pb::SharedStep {
            header: Some(header.clone()),
            path: written.path().display().to_string(),
        };
        *segment = Some(written);
        match self.inner.push_shared(request).await {
            Ok(reply) => Ok(Some(reply.into_inner())),
            Err(s) if matches!(s.code(), Code::FailedPrecondition | Code::Unimplemented) => {
                self.shm = shm::SharedMemory::Off;
                Ok(None)
            }
            Err(s) => Err(s.into()),
        }
    }

    /// Sets `P_M` and the rest of the generation config for the steps that follow.
    ///
    /// # Errors
    /// [`ClientError::Refused`] naming the bad field.
    pub async fn set_config(
        &mut self,
        config: GenerationConfig,
    ) -> Result<ConfigReply, ClientError> {
        Ok(self.inner.set_config(config).await?.into_inner())
    }

    /// The node's counters.
    ///
    /// # Errors
    /// [`ClientError::Refused`].
    pub async fn status(&mut self) -> Result<GeneratorStatus, ClientError> {
        Ok(self
            .inner
            .get_status(pb::StatusRequest {})
            .await?
            .into_inner())
    }

    /// Waits until everything the node has received so far is shipped (or dropped by policy).
    ///
    /// # Errors
    /// [`ClientError::Refused`] with `DeadlineExceeded` after `timeout`, or with
    /// `FailedPrecondition` when the viz-node refused VDIs of the ranks this client pushed
    /// since their last flush (each refusal reported once; other ranks' are left to their own
    /// clients).
    pub async fn flush(&mut self, timeout: Duration) -> Result<GeneratorStatus, ClientError> {
        let req = pb::FlushRequest {
            timeout_secs: timeout.as_secs_f64(),
            ranks: self.ranks.iter().copied().collect(),
        };
        Ok(self.inner.flush(req).await?.into_inner())
    }

    /// Flushes and disconnects; returns the final status.
    ///
    /// # Errors
    /// As [`SimClient::flush`].
    pub async fn close(mut self, timeout: Duration) -> Result<GeneratorStatus, ClientError> {
        self.flush(timeout).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A node that went away and a refused token say what happened and what to do; other
    /// refusals keep the node's own words.
    #[test]
    fn failed_calls_say_what_to_do() {
        let text = |code, m: &str| ClientError::from(tonic::Status::new(code, m)).to_string();
        let gone = text(tonic::Code::Unavailable, "tcp connect error");
        assert!(gone.contains("went away (tcp connect error)"), "{gone}");
        assert!(gone.contains("restart it and push again"), "{gone}");
        let cut = text(tonic::Code::Unknown, "transport error");
        assert!(cut.contains("went away (transport error)"), "{cut}");
        let killed = text(tonic::Code::Cancelled, "operation was canceled");
        assert!(
            killed.contains("went away (operation was canceled)"),
            "{killed}"
        );
        assert!(killed.contains("restart it"), "{killed}");
        let token = text(
            tonic::Code::Unauthenticated,
            "missing or wrong bearer token",
        );
        assert!(token.contains("INSITU_TOKEN"), "{token}");
        let bad = text(tonic::Code::InvalidArgument, "dtype 42");
        assert_eq!(
            bad,
            "generator-node refused the call: InvalidArgument: dtype 42"
        );
    }

    /// Both conversions give each value's little-endian bytes in order, NaN and infinities
    /// and signed zeros bit for bit; the owned one shares the vector's memory.
    #[test]
    fn f32_fields_become_their_little_endian_bytes() {
        let values_again = || {
            vec![
                0.0f32,
                -0.0,
                1.5,
                -3.25e-38,
                f32::MAX,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::from_bits(0x7fc0_0001),
            ]
        };
        let values = values_again();
        let expected: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(&f32_bytes(&values)[..], &expected[..]);
        let at = values.as_ptr() as usize;
        let owned = f32_vec_bytes(values);
        assert_eq!(&owned[..], &expected[..]);
        if cfg!(target_endian = "little") {
            assert_eq!(owned.as_ptr() as usize, at, "copied");
        }
        let step = Step::whole_f32_owned(3, 0.5, [2, 2, 2], vec![1.0; 8]);
        assert_eq!(step.data.len(), 32);
        // Shared: the same bytes in the simulation's own buffer, which it gets back whole
        // once the step is gone.
        let mut shared = std::sync::Arc::new(values_again());
        let at = shared.as_ptr() as usize;
        let step = Step::whole_f32_shared(4, 0.5, [2, 2, 2], shared.clone());
        assert_eq!(&step.data[..], &expected[..]);
        if cfg!(target_endian = "little") {
            assert_eq!(step.data.as_ptr() as usize, at, "copied");
        }
        assert!(std::sync::Arc::get_mut(&mut shared).is_none(), "in use");
        drop(step);
        assert!(std::sync::Arc::get_mut(&mut shared).is_some(), "given back");
    }

    #[test]
    fn a_step_whose_bytes_do_not_match_is_refused_before_sending() {
        let mut s = Step::whole_f32(1, 0.0, [2, 2, 2], &[0.0; 8]);
        assert_eq!(s.header().unwrap().total_bytes, 32);
        s.brick_dims = [2, 2, 3];
        assert!(matches!(s.header(), Err(ClientError::InvalidStep(m)) if m.contains("32 bytes")));
        s.dtype = ScalarType::Unspecified;
        assert!(s.header().is_err());
    }

    #[test]
    fn named_fields_are_checked_against_the_brick_before_sending() {
        let points = [0.0f32; 24];
        let cells = [0.0f32; 6];
        let s = Step::whole_f32(1, 0.0, [4, 3, 2], &[]).with_fields(vec![
            Field::vertex_f32("u", &points),
            Field::element_f32("p", &cells),
        ]);
        let h = s.header().unwrap();
        assert_eq!(h.total_bytes, 120);
        assert_eq!(
            h.fields.iter().map(|f| f.name.as_str()).collect::<Vec<_>>(),
            ["u", "p"]
        );
        assert_eq!(s.payload().len(), 2, "each field's values sent as they are");
        let refused = |s: &Step, words: &str| match s.header() {
            Err(ClientError::InvalidStep(m)) => assert!(m.contains(words), "{m}"),
            other => panic!("{other:?}"),
        };
        let mut bad = s.clone();
        bad.fields[1] = Field::element_f32("p", &points);
        refused(&bad, "field \"p\": 96 bytes for the 6 cells");
        let mut bad = s.clone();
        bad.fields[1].name = "u".into();
        refused(&bad, "field \"u\" is named twice");
        let mut bad = s.clone();
        bad.fields[0].name = String::new();
        refused(&bad, "field 0: a name of 1 to 128 bytes");
        let mut bad = s.clone();
        bad.data = f32_bytes(&points);
        refused(&bad, "either data or named fields");
    }

    #[test]
    fn an_unreachable_node_is_a_clear_error() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        // Port 1 on loopback: nothing listens there.
        let e = rt
            .block_on(SimClient::connect("127.0.0.1:1", None))
            .err()
            .unwrap();
        assert!(matches!(e, ClientError::Unreachable { .. }), "{e}");
        assert!(e.to_string().contains("127.0.0.1:1"));
    }
}
