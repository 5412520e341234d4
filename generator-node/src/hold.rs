//! Fields of recent steps kept for the tuner's trials, within a byte bound.
//!
//! After each production step the node holds the step's field as *pending* until the tuner
//! answers its summary: a claim keeps it until released, a release (or no answer) frees it.
//! Pending fields make room for newer ones, oldest first; claimed fields are never dropped by
//! the node. When claimed fields alone leave no room, the step is not held and its summary says
//! so (`held = false`): the tuner is refused politely rather than the node growing.

use insitu_core::evaluate::Sizing;
use insitu_core::vdi::codec::Codec;
use insitu_core::vdi::VdiParams;
use insitu_core::{raycast::RaycastParams, Camera, Image, NamedTf, Volume};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Everything a trial on a held step needs: the field and the scene it was made with.
#[derive(Clone)]
pub struct HeldStep {
    /// The field (this node's brick).
    pub volume: Arc<Volume>,
    /// Transfer function and name.
    pub tf: Arc<NamedTf>,
    /// Generation camera.
    pub camera: Camera,
    /// Ray-casting step and termination.
    pub raycast: RaycastParams,
    /// Codec σ is measured with.
    pub codec: Codec,
    /// The precision its files are written at (trials measure σ with it).
    pub precision: insitu_core::Precision,
    /// Test views, degrees.
    pub view_angles_deg: Vec<f32>,
    /// Side of the reference frames, pixels; 0: the candidate's `r` (as production with
    /// `reference_size = 0`), so trial and production q compare at the same image size.
    pub reference_size: u32,
    /// Reference frames by side, rendered on the first trial that needs them.
    pub references: BTreeMap<u32, Arc<Vec<Image>>>,
    /// σ and τ of the candidates size-probed on this step, by r and γ's bits: a full trial of
    /// one of them need not encode its VDI again
    /// ([`insitu_core::evaluate::evaluate_sized`]).
    pub sizes: BTreeMap<(u32, u32, u32), Sizing>,
}

/// What a size probe is kept under in [`HeldStep::sizes`]: r, γ's bits and the precision's
/// bit count (σ depends on all three).
pub fn size_key(p: VdiParams) -> (u32, u32, u32) {
    (p.resolution, p.gamma.to_bits(), p.precision.bits())
}

impl HeldStep {
    fn bytes(&self) -> u64 {
        let refs: u64 = self
            .references
            .values()
            .flat_map(|r| r.iter())
            .map(|i| u64::from(i.width()) * u64::from(i.height()) * 12)
            .sum();
        self.volume.storage_bytes() as u64 + refs
    }
}

struct Slot {
    step: HeldStep,
    claimed: bool,
}

/// The held steps of one node.
pub struct Holds {
    max_bytes: u64,
    slots: Mutex<BTreeMap<Key, Slot>>,
}

/// A held field: (step, rank). One node may serve several ranks.
pub type Key = (u64, u32);

impl Holds {
    /// Holds at most `max_bytes` (0: holds nothing).
    pub fn new(max_bytes: u64) -> Self {
        Self {
            max_bytes,
            slots: Mutex::new(BTreeMap::new()),
        }
    }

    fn slots(&self) -> std::sync::MutexGuard<'_, BTreeMap<Key, Slot>> {
        self.slots.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Holds `step` as pending, dropping older pending steps when needed; whether it is held.
    pub fn offer(&self, index: Key, step: HeldStep) -> bool {
        let need = step.bytes();
        let mut slots = self.slots();
        slots.remove(&index);
        let used = |s: &BTreeMap<Key, Slot>| s.values().map(|x| x.step.bytes()).sum::<u64>();
        while used(&slots) + need > self.max_bytes {
            let oldest = slots.iter().find(|(_, s)| !s.claimed).map(|(&k, _)| k);
            match oldest {
                Some(k) => {
                    slots.remove(&k);
                }
                None => return false,
            }
        }
        slots.insert(
            index,
            Slot {
                step,
                claimed: false,
            },
        );
        true
    }

    /// Claims (`keep`) or releases every rank of `step` held here; whether any is held.
    pub fn answer(&self, step: u64, keep: bool) -> bool {
        let mut slots = self.slots();
        if keep {
            let mut any = false;
            for (_, s) in slots.range_mut((step, 0)..=(step, u32::MAX)) {
                s.claimed = true;
                any = true;
            }
            any
        } else {
            slots.retain(|k, _| k.0 != step);
            false
        }
    }

    /// The ranks of `step` held here, for a trial.
    pub fn ranks(&self, step: u64) -> Vec<(u32, HeldStep)> {
        self.slots()
            .range((step, 0)..=(step, u32::MAX))
            .map(|(k, s)| (k.1, s.step.clone()))
            .collect()
    }

    /// Keeps the reference frames of side `side` rendered for `index`.
    pub fn set_references(&self, index: Key, side: u32, refs: Arc<Vec<Image>>) {
        if let Some(s) = self.slots().get_mut(&index) {
            s.step.references.insert(side, refs);
        }
    }

    /// Keeps the sizing a size probe of `params` measured on `index` ([`size_key`]).
    pub fn set_sizing(&self, index: Key, params: VdiParams, sizing: Sizing) {
        if let Some(s) = self.slots().get_mut(&index) {
            let key = size_key(params);
            s.step.sizes.insert(key, sizing);
        }
    }

    /// The claimed steps (told to a tuner on reconnect); pending ones are released, since no
    /// one will answer their summaries.
    pub fn claimed_after_reconnect(&self) -> Vec<Key> {
        let mut slots = self.slots();
        slots.retain(|_, s| s.claimed);
        slots.keys().copied().collect()
    }

    /// Bytes held.
    #[cfg(test)]
    fn bytes(&self) -> u64 {
        self.slots().values().map(|s| s.step.bytes()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn step(n: usize) -> HeldStep {
        HeldStep {
            volume: Arc::new(Volume::new([n, 1, 1], Vec3::ONE, vec![0.0; n]).unwrap()),
            tf: Arc::new(NamedTf::new(
                insitu_core::TransferFunction::default_for_range(0.0, 1.0),
                "t",
            )),
            camera: Camera::default_for_box(&insitu_core::volume::Aabb {
                min: Vec3::ZERO,
                max: Vec3::ONE,
            }),
            raycast: RaycastParams::default(),
            codec: Codec::Zstd,
            precision: insitu_core::Precision::Float32,
            view_angles_deg: vec![0.0],
            reference_size: 8,
            references: BTreeMap::new(),
            sizes: BTreeMap::new(),
        }
    }

    #[test]
    fn pending_steps_make_room_claimed_ones_never_do() {
        let h = Holds::new(100);
        let held = |s: u64| h.ranks(s).len();
        assert!(h.offer((1, 0), step(10)) && h.offer((2, 0), step(10))); // 40 B each
        assert!(h.answer(1, true));
        assert!(!h.answer(9, true), "not held");
        assert!(
            h.offer((3, 0), step(5)) && h.offer((3, 1), step(5)),
            "step 2 (pending) makes room"
        );
        assert_eq!((held(1), held(2), held(3)), (1, 0, 2));
        assert!(h.answer(3, true), "claims both ranks");
        assert!(
            !h.offer((4, 0), step(10)),
            "only claimed steps left: refused"
        );
        assert_eq!(held(4), 0);
        assert!(!h.answer(1, false) && held(1) == 0);
        assert!(h.offer((4, 0), step(10)));
        assert_eq!(h.claimed_after_reconnect(), vec![(3, 0), (3, 1)]);
        assert_eq!(h.bytes(), 40);
        assert!(!Holds::new(0).offer((1, 0), step(1)));
    }
}
