//! Admission of a part: the ranks it names, and the parts of its step already stored.

use super::admit::*;
use super::*;

fn part(step: u64, rank: u32, covers: &[u32], pm_version: u64) -> Entry {
    Entry {
        vdi: Some(insitu_recording::store::vdi_name(step, rank)),
        covers: covers.to_vec(),
        pm_version,
        world_size: 4,
        ..Entry::empty(step, rank)
    }
}

/// A part's ranks as its header states them: ascending from its rank, inside the world.
#[test]
fn a_part_names_its_ranks_in_order_inside_the_world() {
    assert_eq!(part_ranks(3, 1, 4, &[]).unwrap(), [1]);
    assert_eq!(part_ranks(3, 1, 4, &[1, 2, 3]).unwrap(), [1, 2, 3]);
    for bad in [&[2, 3][..], &[1, 1], &[1, 4], &[1, 3, 2]] {
        let e = part_ranks(3, 1, 4, bad).unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(e.message().contains("step 3 rank 1"), "{}", e.message());
    }
}

/// A part is new, the same part again, wholly held by stored parts (acknowledged) or
/// partly held (refused, naming the holder).
#[test]
fn ranks_held_by_stored_parts_are_acknowledged_or_refused() {
    let stored = [part(7, 0, &[0, 1], 2), part(7, 2, &[], 2)];
    // New: rank 3 alone.
    assert!(held_elsewhere(&stored, 7, (3, &[3]), Some(2))
        .unwrap()
        .is_none());
    // The same part again: the store compares bytes.
    assert!(held_elsewhere(&stored, 7, (0, &[0, 1]), Some(2))
        .unwrap()
        .is_none());
    // A restarted node's rank 1 alone: held by rank 0's part, acknowledged; rank 2
    // alone is the same part as stored (bytes compared by the store).
    let held = held_elsewhere(&stored, 7, (1, &[1]), Some(2)).unwrap();
    assert_eq!(held.map(|e| e.rank), Some(0));
    assert!(held_elsewhere(&stored, 7, (2, &[2]), Some(2))
        .unwrap()
        .is_none());
    // Frames carry no version: held is held.
    assert!(held_elsewhere(&stored, 7, (1, &[1]), None)
        .unwrap()
        .is_some());
    // Another P_M version, or a part holding a held rank and a new one: refused.
    let e = held_elsewhere(&stored, 7, (1, &[1]), Some(3)).unwrap_err();
    assert!(e
        .message()
        .contains("rank 1 is already held by the stored part of rank 0"));
    let e = held_elsewhere(&stored, 7, (2, &[2, 3]), Some(2)).unwrap_err();
    assert!(
        e.message().contains("rank 2 is already held") && e.message().contains("[2, 3]"),
        "{}",
        e.message()
    );
}
