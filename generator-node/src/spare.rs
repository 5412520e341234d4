//! Fields no step needs any more, kept so that the next pushes are received into their memory.
//!
//! A field written into fresh memory costs the kernel a zeroed page per page touched; written
//! into a field of an earlier step it costs none. A receive, the queue and the worker each
//! hold a field while a simulation pushes back to back, so one spare is often not enough: the
//! worker hands its field back while the next push is already being received into a fresh
//! one, and the fields of steps the queue's policy drops (`latest-only`) used to be freed.
//! [`SpareFields`] keeps a few, from generated and dropped steps alike. The node's resident
//! memory therefore includes up to [`MAX_SPARE_FIELDS`] idle fields between pushes.

use insitu_core::Volume;
use std::sync::Mutex;

/// How many spare fields are kept at most (beyond what the queue and the worker hold).
pub const MAX_SPARE_FIELDS: usize = 2;

/// A small stack of fields whose steps are settled (generated or dropped).
#[derive(Debug, Default)]
pub struct SpareFields {
    fields: Mutex<Vec<Volume>>,
}

impl SpareFields {
    /// Keeps `field` for a later receive, or frees it when [`MAX_SPARE_FIELDS`] are kept.
    pub fn put(&self, field: Volume) {
        let mut fields = self.fields.lock().unwrap_or_else(|e| e.into_inner());
        if fields.len() < MAX_SPARE_FIELDS {
            fields.push(field);
        }
    }

    /// The field kept last (its memory the most likely still in cache), if any.
    pub fn take(&self) -> Option<Volume> {
        self.fields.lock().unwrap_or_else(|e| e.into_inner()).pop()
    }

    /// How many are kept now.
    pub fn len(&self) -> usize {
        self.fields.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// Whether none is kept.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
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
        let spares = SpareFields::default();
        assert!(spares.take().is_none());
        for v in 0..=MAX_SPARE_FIELDS {
            spares.put(field(v as f32));
        }
        assert_eq!(spares.len(), MAX_SPARE_FIELDS);
        for v in (0..MAX_SPARE_FIELDS).rev() {
            let f = spares.take().expect("a spare is kept");
            assert_eq!(f.data()[0], v as f32, "the one kept last comes first");
        }
        assert!(spares.is_empty());
    }
}
