//! Fields no step needs any more, kept so that the next pushes are received into their memory.
//!
//! A field written into fresh memory costs the kernel a zeroed page per page touched; written
//! into a field of an earlier step it costs none. A receive, the queue and the worker each
//! hold a field while a simulation pushes back to back, so one spare is often not enough: the
//! worker hands its field back while the next push is already being received into a fresh
//! one, and the fields of steps the queue's policy drops (`latest-only`) would be freed.
//! [`SpareFields`] keeps a few, from generated and dropped steps alike. The node's resident
//! memory therefore includes idle fields between pushes: one always, a second only while both fit the byte bound the node gives (its queue's
//! `max_bytes`, the memory the operator set aside for waiting steps), so that large bricks do
//! not double what a node holds idle.

use insitu_core::Volume;
use std::sync::Mutex;

/// How many spare fields are kept at most (beyond what the queue and the worker hold).
pub const MAX_SPARE_FIELDS: usize = 2;

/// A small stack of fields whose steps are settled (generated or dropped).
#[derive(Debug)]
pub struct SpareFields {
    fields: Mutex<Vec<Volume>>,
    /// Most bytes kept in more than one field.
    max_bytes: u64,
}

impl SpareFields {
    /// None kept yet; beyond the first, fields are kept while all fit `max_bytes`.
    pub fn new(max_bytes: u64) -> Self {
        Self {
            fields: Mutex::new(Vec::new()),
            max_bytes,
        }
    }

    /// Keeps `field` for a later receive: always when none is kept, else while fewer than
    /// [`MAX_SPARE_FIELDS`] are kept and all fit the byte bound; otherwise frees it.
    pub fn put(&self, field: Volume) {
        let mut fields = self.fields.lock().unwrap_or_else(|e| e.into_inner());
        let bytes = |v: &Volume| v.storage_bytes() as u64;
        let kept: u64 = fields.iter().map(bytes).sum();
        if fields.is_empty()
            || (fields.len() < MAX_SPARE_FIELDS
                && kept.saturating_add(bytes(&field)) <= self.max_bytes)
        {
            fields.push(field);
        }
    }

    /// The field kept last (its memory the most likely still in cache), if any.
    pub fn take(&self) -> Option<Volume> {
        self.fields.lock().unwrap_or_else(|e| e.into_inner()).pop()
    }

    /// How many are kept now.
    #[cfg(test)]
    fn len(&self) -> usize {
        self.fields.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(value: f32) -> Volume {
        Volume::new([2, 2, 2], glam::Vec3::ONE, vec![value; 8]).expect("a valid volume")
    }

    #[test]
    fn keeps_at_most_the_bound_and_gives_the_last_kept_first() {
        let spares = SpareFields::new(u64::MAX);
        assert!(spares.take().is_none());
        for v in 0..=MAX_SPARE_FIELDS {
            spares.put(field(v as f32));
        }
        assert_eq!(spares.len(), MAX_SPARE_FIELDS);
        for v in (0..MAX_SPARE_FIELDS).rev() {
            let f = spares.take().expect("a spare is kept");
            assert_eq!(f.data()[0], v as f32, "the one kept last comes first");
        }
        assert_eq!(spares.len(), 0);
    }

    #[test]
    fn keeps_a_second_field_only_within_the_byte_bound() {
        // Each test field holds 8 f32 voxels: 32 bytes.
        let one = field(1.0).storage_bytes() as u64;
        let tight = SpareFields::new(one);
        tight.put(field(1.0));
        tight.put(field(2.0));
        assert_eq!(
            tight.len(),
            1,
            "one field is always kept, a second only within the bound"
        );
        assert_eq!(tight.take().expect("kept").data()[0], 1.0);

        let roomy = SpareFields::new(2 * one);
        roomy.put(field(1.0));
        roomy.put(field(2.0));
        assert_eq!(
            roomy.len(),
            2,
            "two fields of {one} bytes fit {} bytes",
            2 * one
        );
    }
}
