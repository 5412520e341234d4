//! Two-level composition, the host's level (docs/scale.md). A generator-node that serves
//! several ranks of a world composes each step's ranks before shipping: their bricks are
//! gathered into boxes (`box_groups`, when `crate::outbox` finds the step due), and each
//! box's sub-VDIs and reference frames are composed with the code the viz-node uses ([`insitu_core::compose`]) into one part, a VDI
//! whose header and file name the ranks it holds (`VdiHeader.covers`) and whose brick is
//! their box. The viz-node composes the parts as it composes ranks: what reaches it per step
//! falls by the ranks per host for frames, files and index rows (the supersegments are the
//! step's content and stay), and the picture is the one-level picture (the composed VDI bit
//! for bit, the frames within rounding).
//!
//! A step's parts ship once every rank of it that this node received is finished or settled
//! without a VDI (dropped, failed), and every rank the node served at its previous step (at
//! its first step: every rank of the world) has been received, or `wait_secs` after the
//! step's last progress when one has not: a rank that comes later ships alone, in a part of
//! its own, and the viz-node composes whatever parts hold the world's ranks. Steps found in
//! the spool after a restart ship rank by rank, so that a part the viz-node stored before the
//! crash is acknowledged rank by rank, never refused as a second holder of its ranks. Ranks
//! whose VDIs cannot be composed together (they differ in camera, `P_M`, TF, frames) ship
//! alone, with a warning.
//!
//! Memory: a step's finished ranks wait until its parts ship, each holding its compressed
//! VDI, its lists cropped to its footprint ([`VdiWindow`]: no `r²` offsets, a buffer of their
//! size) and its frames cut to their windows and compressed (`host::packed`); the VDI as the
//! worker made it goes back to the worker, whose next step reuses its memory. So the ranks a
//! node holds cost about one host VDI, whatever their number (docs/scale.md, "Memory").
//! Composing unpacks one view of the group's frame windows at a time.

mod packed;

use crate::config::HostConfig;
use crate::work::Product;
use bytes::Bytes;
use insitu_core::compose::{
    compose_frames, compose_vdis, frame_from_le_bytes, frame_to_le_bytes, BrickFrame, PixelLists,
};
use insitu_core::vdi::codec::{self, Codec};
use insitu_core::vdi::window::VdiWindow;
use insitu_core::vdi::{Supersegment, VdiMeta};
use insitu_core::volume::bricks::Brick;
use insitu_core::{Camera, Vdi};
use insitu_proto::convert::wire_enum;
use insitu_proto::pb;
use packed::PackedFrames;
use std::collections::{BTreeMap, BTreeSet, HashSet};
use std::sync::Mutex;
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tracing::warn;

/// A rank's finished step: what ships (compressed VDI, frames, spool entries) and its lists in
/// memory, for composing.
pub struct Finished {
    /// As the worker made it (its frames taken out while they are packed).
    pub product: Product,
    /// The lists `product.vdi` encodes.
    lists: Lists,
    /// While the rank waits for its host's other ranks: its frames, each view cut to its
    /// brick's window and compressed.
    packed: Option<PackedFrames>,
}

/// A finished rank's lists: the VDI as the worker made it, or, while the rank waits for its
/// host's other ranks, its window (the footprint's lists in buffers of their size).
enum Lists {
    Whole(Vdi),
    Window(VdiWindow),
}

impl Lists {
    fn into_whole(self) -> Option<Vdi> {
        match self {
            Lists::Whole(v) => Some(v),
            Lists::Window(_) => None,
        }
    }
}

impl PixelLists for Lists {
    fn meta(&self) -> &VdiMeta {
        match self {
            Lists::Whole(v) => v.meta(),
            Lists::Window(w) => w.meta(),
        }
    }
    fn supersegment_count(&self) -> usize {
        match self {
            Lists::Whole(v) => v.supersegments().len(),
            Lists::Window(w) => w.supersegments().len(),
        }
    }
    fn row_is_empty(&self, j: usize) -> bool {
        match self {
            Lists::Whole(v) => PixelLists::row_is_empty(v, j),
            Lists::Window(w) => w.row_is_empty(j),
        }
    }
    #[inline]
    fn list(&self, i: usize, j: usize) -> &[Supersegment] {
        match self {
            Lists::Whole(v) => PixelLists::list(v, i, j),
            Lists::Window(w) => w.list(i, j),
        }
    }
}

impl Finished {
    /// A rank's product and the VDI it encodes.
    pub fn new(product: Product, vdi: Vdi) -> Self {
        Self {
            product,
            lists: Lists::Whole(vdi),
            packed: None,
        }
    }

    /// Readies the rank for the wait, on the worker threads, for a rank whose node
    /// [`Gather::gathers`]: its VDI cropped to its footprint ([`VdiWindow`]: a brick's lists
    /// without `r²` offsets, in a buffer of their size) and its frames cut to their windows
    /// and compressed (left as they are when they are not whole views). Returns the VDI as
    /// made, whose memory the worker's next step reuses; `None` when already packed.
    pub fn pack(&mut self) -> Option<Vdi> {
        self.pack_frames();
        let window = match &self.lists {
            Lists::Whole(v) => Lists::Window(VdiWindow::crop(v)),
            Lists::Window(_) => return None,
        };
        std::mem::replace(&mut self.lists, window).into_whole()
    }

    fn pack_frames(&mut self) {
        let Some((header, bytes)) = &self.product.references else {
            return;
        };
        if let Some(packed) = PackedFrames::pack(header.clone(), bytes) {
            self.product.references = None;
            self.packed = Some(packed);
        }
    }

    /// Bytes the rank holds while it waits: its file, its lists and its frames.
    pub fn held_bytes(&self) -> usize {
        let lists = match &self.lists {
            Lists::Whole(v) => v.memory_bytes(),
            Lists::Window(w) => w.memory_bytes(),
        };
        let frames = self.packed.as_ref().map_or_else(
            || self.product.references.as_ref().map_or(0, |(_, b)| b.len()),
            PackedFrames::held_bytes,
        );
        self.product.vdi.len() + lists + frames
    }

    /// The VDI as the worker made it, unless it was packed (its memory, for the next step).
    pub fn into_vdi(self) -> Option<Vdi> {
        self.lists.into_whole()
    }

    /// The product as it ships alone, its frames unpacked.
    pub(crate) fn into_product(self) -> Product {
        self.unpack().0
    }

    /// The product as it ships alone (its frames unpacked) and the VDI it encodes, unless it
    /// was packed (its memory, for the next step).
    pub fn unpack(mut self) -> (Product, Option<Vdi>) {
        if let Some(packed) = self.packed.take() {
            match packed.unpack() {
                (header, Some(bytes)) => self.product.references = Some((header, bytes)),
                // Frames lost, the VDI still ships (the viz-node scores without).
                (header, None) => {
                    warn!(
                        step = header.step,
                        rank = header.rank,
                        "frames could not be unpacked; the VDI ships without them"
                    );
                    self.product.vdi_header.with_references = false;
                }
            }
        }
        (self.product, self.lists.into_whole())
    }

    /// The frames' header, packed or not.
    fn frames_header(&self) -> Option<&pb::ReferenceHeader> {
        self.packed.as_ref().map(PackedFrames::header).or(self
            .product
            .references
            .as_ref()
            .map(|(h, _)| h))
    }

    /// View `v`'s frame as a window (the whole frame when not packed), of `size` pixels.
    fn window(&self, v: usize, size: (u32, u32)) -> Option<packed::Window> {
        match (&self.packed, &self.product.references) {
            (Some(p), _) => p.window(v),
            (None, Some((_, bytes))) => {
                let per_view = size.0 as usize * size.1 as usize * 16;
                let view = bytes.get(v * per_view..(v + 1) * per_view)?;
                let (image, opacity) = frame_from_le_bytes(view, size)?;
                Some(([0, 0], image, opacity))
            }
            (None, None) => None,
        }
    }
}

/// The ranks of the steps in flight on this node, and their finished VDIs until they ship.
pub struct Gather {
    compose: bool,
    wait: Duration,
    state: Mutex<State>,
    /// Woken whenever a step may have become due (the shipping loop waits on it).
    pub(crate) wake: Notify,
}

#[derive(Default)]
struct State {
    steps: BTreeMap<u64, Pending>,
    /// The ranks of the newest step shipped: those this node serves, as far as it knows.
    served: BTreeSet<u32>,
    /// Steps from the spool, shipped rank by rank.
    alone: HashSet<(u64, u32)>,
    closed: bool,
}

struct Pending {
    /// Ranks in the step's world.
    world_size: u32,
    /// Ranks received (or being received).
    received: BTreeSet<u32>,
    /// Ranks finished or settled without a VDI.
    settled: BTreeSet<u32>,
    done: Vec<Finished>,
    /// When a rank last arrived or settled.
    progress: Instant,
}

impl Pending {
    fn new(world_size: u32, now: Instant) -> Self {
        Self {
            world_size,
            received: BTreeSet::new(),
            settled: BTreeSet::new(),
            done: Vec::new(),
            progress: now,
        }
    }
}

/// What to do with a step at `now`.
enum Due {
    /// Its parts ship.
    Ship,
    /// Wait for a rank not received yet, until the instant.
    Until(Instant),
    /// Wait for a received rank to finish.
    Wait,
}

impl Gather {
    /// A gatherer with `[host]`'s settings.
    pub fn new(cfg: &HostConfig) -> Self {
        Self {
            compose: cfg.compose,
            wait: Duration::from_secs_f64(cfg.wait_secs),
            state: Mutex::new(State::default()),
            wake: Notify::new(),
        }
    }

    /// `[host]`'s `wait_secs`.
    pub fn wait(&self) -> Duration {
        self.wait
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether this node gathers the ranks of a world of `world_size` (composition on, more
    /// than one rank): a rank's frames are then packed before [`Self::finish`].
    pub fn gathers(&self, world_size: u32) -> bool {
        self.compose && world_size > 1
    }

    /// What the oldest step still gathered waits for, for a flush that times out: "step 1
    /// waits for its ranks: 1 of 4 received, shipped as it is 30 s after the last arrived".
    pub fn waiting(&self) -> Option<String> {
        let s = self.state();
        let (step, p) = s.steps.iter().next()?;
        Some(format!(
            "step {step} waits for its ranks: {} of {} received, shipped as it is {} s after the last arrived ([host] wait_secs)",
            p.received.len(),
            p.world_size,
            self.wait.as_secs_f64()
        ))
    }

    /// Rank `rank` of `step`, of a world of `world_size`, is being received.
    pub fn received(&self, step: u64, rank: u32, world_size: u32) {
        if !self.gathers(world_size) {
            return;
        }
        let now = Instant::now();
        let mut s = self.state();
        let p = s
            .steps
            .entry(step)
            .or_insert_with(|| Pending::new(world_size, now));
        p.received.insert(rank);
        p.progress = now;
    }

    /// Rank `rank` of `step` settled without a VDI (dropped from the queue, failed, not
    /// received after all).
    pub fn settled(&self, step: u64, rank: u32) {
        let mut s = self.state();
        if let Some(p) = s.steps.get_mut(&step) {
            p.settled.insert(rank);
            p.progress = Instant::now();
            drop(s);
            self.wake.notify_one();
        }
    }

    /// Rank `rank` of `step` comes from the spool: it ships alone.
    pub fn alone(&self, step: u64, rank: u32) {
        self.state().alone.insert((step, rank));
    }

    /// A finished rank: handed back when it ships as it is (a world of one, composition off,
    /// a step from the spool, a rank never announced; [`Finished::unpack`] it), else kept for
    /// its step's parts.
    pub fn finish(&self, f: Finished) -> Option<Finished> {
        let h = &f.product.vdi_header;
        let (step, rank) = (h.step, h.rank);
        if !self.gathers(h.world_size) {
            return Some(f);
        }
        let mut s = self.state();
        if s.alone.remove(&(step, rank)) {
            return Some(f);
        }
        let Some(p) = s
            .steps
            .get_mut(&step)
            .filter(|p| p.received.contains(&rank))
        else {
            return Some(f);
        };
        p.settled.insert(rank);
        p.progress = Instant::now();
        p.done.push(f);
        drop(s);
        self.wake.notify_one();
        None
    }

    /// No more ranks: everything held ships now.
    pub fn close(&self) {
        self.state().closed = true;
        self.wake.notify_one();
    }

    /// The steps whose parts ship at `now`, taken out (every step once closed), the earliest
    /// instant another may, and whether the gatherer is closed and empty.
    pub(crate) fn take_due(&self, now: Instant) -> (Vec<Vec<Finished>>, Option<Instant>, bool) {
        let mut s = self.state();
        let closed = s.closed;
        let mut due = Vec::new();
        let mut next: Option<Instant> = None;
        let keys: Vec<u64> = s.steps.keys().copied().collect();
        for step in keys {
            let when = match s.steps.get(&step) {
                Some(_) if closed => Some(Due::Ship),
                Some(p) => Some(self.due(p, &s.served, now)),
                None => None,
            };
            match when {
                Some(Due::Ship) => {
                    if let Some(p) = s.steps.remove(&step) {
                        s.served = p.received;
                        if !p.done.is_empty() {
                            due.push(p.done);
                        }
                    }
                }
                Some(Due::Until(t)) => next = Some(next.map_or(t, |n| n.min(t))),
                Some(Due::Wait) | None => {}
            }
        }
        let finished = closed && s.steps.is_empty();
        (due, next, finished)
    }

    fn due(&self, p: &Pending, served: &BTreeSet<u32>, now: Instant) -> Due {
        if !p.received.is_subset(&p.settled) {
            return Due::Wait;
        }
        // Before a step has shipped, the node does not know which ranks it serves: it waits
        // for the whole world (a node serving fewer waits once, on its first step).
        let all_in = if served.is_empty() {
            p.received.len() >= p.world_size as usize
        } else {
            served.is_subset(&p.received)
        };
        let deadline = p.progress + self.wait;
        if all_in || now >= deadline {
            Due::Ship
        } else {
            Due::Until(deadline)
        }
    }
}

/// Why ranks could not be composed into one part.
#[derive(Debug, thiserror::Error)]
pub enum PartError {
    /// The sub-VDIs or frames differ ([`insitu_core::compose::ComposeError`]).
    #[error("rank {rank}: {source}")]
    Compose {
        /// The part's first rank.
        rank: u32,
        /// What differs.
        source: insitu_core::compose::ComposeError,
    },
    /// The ranks' reference frames are not alike (some missing, other views or sizes).
    #[error("reference frames: {0}")]
    Frames(String),
    /// Encoding the part (or reading a rank's file) failed.
    #[error(transparent)]
    Codec(#[from] codec::CodecError),
    /// A rank's file says nowhere where in the run it comes from.
    #[error("rank {rank}: its VDI file carries no provenance")]
    NoProvenance {
        /// The rank.
        rank: u32,
    },
}

/// `group` (ranks sorted, bricks forming `brick`) composed into one part: the VDI merged
/// ([`compose_vdis`]), encoded in the first rank's codec with a provenance naming every rank,
/// the frames composited per view ([`compose_frames`]); σ is the part's file, τ the slowest
/// rank's, the spool entries and retries those of all.
///
/// # Errors
/// [`PartError`] when the ranks were made differently or the part cannot be encoded.
pub fn compose_part(group: &[Finished], brick: Brick) -> Result<Product, PartError> {
    let lead = &group[0].product.vdi_header;
    let covers: Vec<u32> = group.iter().map(|f| f.product.vdi_header.rank).collect();
    let lists: Vec<&Lists> = group.iter().map(|f| &f.lists).collect();
    let vdi = compose_vdis(&lists).map_err(|source| PartError::Compose {
        rank: lead.rank,
        source,
    })?;
    let references = compose_references(group, &covers)?;
    // The first rank's provenance (as the worker wrote it), its brick the part's box.
    let mut provenance = codec::provenance(&group[0].product.vdi)?
        .ok_or(PartError::NoProvenance { rank: lead.rank })?;
    provenance.placement = provenance.placement.map(|(global, _)| (global, brick));
    provenance.covers = covers.clone();
    let codec = wire_enum::<pb::Codec>(lead.codec, "codec")
        .map(Option::<Codec>::from)
        .ok()
        .flatten()
        .unwrap_or(Codec::Zstd);
    let t = Instant::now();
    let file = codec::encode_with_provenance(&vdi, codec, Some(&provenance))?;
    let tau_compress_secs = t.elapsed().as_secs_f64();
    let slowest = group
        .iter()
        .map(|f| f.product.vdi_header.tau_secs)
        .fold(0.0, f64::max);
    let vdi_header = pb::VdiHeader {
        total_bytes: file.len() as u64,
        supersegments: vdi.supersegments().len() as u64,
        tau_secs: slowest,
        tau_compress_secs,
        brick_offset: Some(pb::Dims3::from(brick.offset)),
        brick_dims: Some(pb::Dims3::from(brick.dims)),
        with_references: references.is_some(),
        covers,
        ..lead.clone()
    };
    Ok(Product {
        vdi_header,
        vdi: Bytes::from(file),
        references,
        spool: group
            .iter()
            .flat_map(|f| f.product.spool.iter().cloned())
            .collect(),
        limit_retries: group.iter().fold((0, 0.0), |(n, s), f| {
            (n + f.product.limit_retries.0, s + f.product.limit_retries.1)
        }),
        // Each rank's first try went to the tuner with its own summary.
        first_try: None,
    })
}

/// The ranks' reference frames composited per view, as the part's (none when no rank has
/// frames).
///
/// # Errors
/// [`PartError::Frames`] when only some ranks have frames, or theirs differ in views, size,
/// camera or opacity.
fn compose_references(
    group: &[Finished],
    covers: &[u32],
) -> Result<Option<(pb::ReferenceHeader, Bytes)>, PartError> {
    let with: Vec<&pb::ReferenceHeader> =
        group.iter().filter_map(Finished::frames_header).collect();
    let Some(&lead) = with.first() else {
        return Ok(None);
    };
    let alike = |h: &pb::ReferenceHeader| {
        h.width == lead.width
            && h.height == lead.height
            && h.camera == lead.camera
            && h.view_angles_deg == lead.view_angles_deg
            && h.opacity
    };
    if with.len() != group.len() || !with.iter().all(|h| alike(h)) {
        return Err(PartError::Frames(format!(
            "{} of {} ranks have frames with opacity of the same views",
            with.iter().filter(|h| alike(h)).count(),
            group.len()
        )));
    }
    let camera: Camera = lead
        .camera
        .as_ref()
        .ok_or_else(|| PartError::Frames("no camera".into()))
        .and_then(|c| Camera::try_from(c).map_err(|e| PartError::Frames(e.message().into())))?;
    let (w, h) = (lead.width, lead.height);
    let per_view = w as usize * h as usize * 16;
    let views = lead.view_angles_deg.len();
    let mut out = Vec::with_capacity(per_view * views);
    // One view at a time: each rank's window of the view (the part of the frame its brick
    // covers; packed ranks hold only that) unpacked, the windows composited, the view written.
    for (v, &angle) in lead.view_angles_deg.iter().enumerate() {
        let windows: Vec<packed::Window> = group
            .iter()
            .map(|f| {
                f.window(v, (w, h)).ok_or_else(|| {
                    PartError::Frames(format!(
                        "rank {}: no view {v} of {w}×{h} RGBA f32",
                        f.product.vdi_header.rank
                    ))
                })
            })
            .collect::<Result<_, PartError>>()?;
        let bricks: Vec<BrickFrame> = windows
            .iter()
            .zip(group)
            .map(|((origin, image, opacity), f)| BrickFrame {
                image,
                opacity,
                origin: *origin,
                world_box: f.lists.meta().volume_box,
            })
            .collect();
        let (image, opacity) =
            compose_frames(&camera.orbit_y(angle), (w, h), &bricks).map_err(|source| {
                PartError::Compose {
                    rank: covers[0],
                    source,
                }
            })?;
        out.extend(frame_to_le_bytes(&image, &opacity));
    }
    let header = pb::ReferenceHeader {
        total_bytes: out.len() as u64,
        covers: covers.to_vec(),
        ..lead.clone()
    };
    Ok(Some((header, Bytes::from(out))))
}

#[cfg(test)]
mod tests;
