//! The viz-node's refusals of this node's VDIs, kept per rank until a flush reports them, so
//! that each rank's client hears of its own steps' refusals and of no other rank's.

use std::collections::BTreeMap;
use std::sync::Mutex;

/// Refusals not yet reported, per rank: how many, and the last one's cause.
#[derive(Debug, Default)]
pub struct Refusals(Mutex<BTreeMap<u32, (u64, String)>>);

impl Refusals {
    /// Records that the viz-node refused a VDI of `rank` for `why`.
    pub fn record(&self, rank: u32, why: String) {
        let mut m = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let e = m.entry(rank).or_default();
        e.0 += 1;
        e.1 = why;
    }

    /// Takes the unreported refusals of `ranks` (every rank's when empty): their count and the
    /// last cause among them (by rank), or `None`.
    pub fn take(&self, ranks: &[u32]) -> Option<(u64, String)> {
        let mut m = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let chosen: Vec<u32> = if ranks.is_empty() {
            m.keys().copied().collect()
        } else {
            ranks
                .iter()
                .copied()
                .filter(|r| m.contains_key(r))
                .collect()
        };
        chosen
            .into_iter()
            .filter_map(|r| m.remove(&r))
            .reduce(|(n, _), (k, why)| (n + k, why))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_rank_hears_of_its_own_refusals_once() {
        let r = Refusals::default();
        r.record(1, "overlap".into());
        r.record(1, "world size".into());
        r.record(3, "disk".into());
        assert_eq!(r.take(&[0]), None, "rank 0 had none");
        assert_eq!(r.take(&[1, 2]), Some((2, "world size".into())));
        assert_eq!(r.take(&[1]), None, "reported once");
        assert_eq!(
            r.take(&[]),
            Some((1, "disk".into())),
            "an old client hears of all"
        );
        assert_eq!(r.take(&[]), None);
    }
}
