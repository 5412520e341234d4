use super::*;
use glam::Vec3;
use insitu_core::volume::ScalarType;

const N: usize = 8;

fn info(step: u64, rank: u32, z0: usize, nz: usize) -> StepInfo {
    StepInfo {
        step,
        sim_time: 0.0,
        rank,
        world_size: 2,
        dtype: ScalarType::F32,
        global_dims: [N, N, N],
        brick_offset: [0, 0, z0],
        brick_dims: [N, N, nz],
        spacing: Vec3::ONE,
        origin: Vec3::ZERO,
    }
}

/// A whole field whose points are all distinct.
fn whole() -> Volume {
    Volume::from_fn([N; 3], |x, y, z| (x + 10 * y + 100 * z) as f32).unwrap()
}

/// `info`'s brick of [`whole`].
fn field(info: &StepInfo) -> Volume {
    whole()
        .brick(&Brick {
            offset: info.brick_offset,
            dims: info.brick_dims,
        })
        .unwrap()
}

fn record(l: &Layouts, info: &StepInfo) -> Option<DecompositionError> {
    l.record(info, &field(info))
}

const WAIT: Duration = Duration::from_secs(5);

/// What a worker gets for `info`: asked, then again whenever a step completes or the
/// deadline passes.
async fn growth(l: &Layouts, info: &StepInfo, first_wait: Duration) -> Growth {
    let since = Instant::now();
    loop {
        let changed = l.changed();
        match l.decide(info, first_wait, since) {
            Ok(g) => return g,
            Err(deadline) => {
                let _ = tokio::time::timeout_at(deadline.into(), changed).await;
            }
        }
    }
}

#[tokio::test]
async fn disjoint_halves_grow_into_the_whole_field_s_bricks() {
    let l = Layouts::default();
    for step in 0..3 {
        let (lower, upper) = (info(step, 0, 0, 4), info(step, 1, 4, 4));
        // The upper half is pushed first at step 0, last after.
        if step == 0 {
            assert!(record(&l, &upper).is_none());
        }
        l.admit(&lower).unwrap();
        assert!(record(&l, &lower).is_none());
        if step > 0 {
            assert!(record(&l, &upper).is_none());
        }
        // The upper half reaches the grid's end: made as pushed.
        assert!(matches!(growth(&l, &upper, WAIT).await, Growth::AsPushed));
        let grows = growth(&l, &lower, WAIT).await;
        let mut grown_info = lower;
        let grown = grows
            .apply(&mut grown_info, &field(&lower), None)
            .unwrap()
            .expect("the lower half grows");
        assert_eq!(grown_info.brick_dims, [N, N, 5]);
        assert_eq!(
            grown,
            field(&grown_info),
            "the whole field's points z 0..=4"
        );
        // Both ranks made: the step is forgotten.
        assert!(!l.state().pending.contains_key(&step));
    }
    assert!(l.summary().is_none());
    assert!(l.whole_world_here(2));
}

#[tokio::test]
async fn a_brick_waits_for_its_neighbour_s_faces() {
    let l = Arc::new(Layouts::default());
    let (lower, upper) = (info(0, 0, 0, 4), info(0, 1, 4, 4));
    assert!(record(&l, &lower).is_none());
    let waiting = {
        let l = l.clone();
        tokio::spawn(async move { growth(&l, &lower, WAIT).await })
    };
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert!(!waiting.is_finished(), "rank 1 not in yet");
    assert!(record(&l, &upper).is_none());
    let growth = tokio::time::timeout(WAIT, waiting).await.unwrap().unwrap();
    assert!(matches!(growth, Growth::Grow { brick, .. } if brick.dims == [N, N, 5]));
}

#[tokio::test]
async fn a_world_whose_ranks_push_elsewhere_is_waited_for_once() {
    let l = Layouts::default();
    let lower = info(0, 0, 0, 4);
    assert!(record(&l, &lower).is_none());
    let short = Duration::from_millis(30);
    assert!(matches!(growth(&l, &lower, short).await, Growth::AsPushed));
    // Later steps do not wait, nor keep faces.
    let next = info(1, 0, 0, 4);
    assert!(record(&l, &next).is_none());
    let t = Instant::now();
    assert!(matches!(growth(&l, &next, WAIT).await, Growth::AsPushed));
    assert!(t.elapsed() < WAIT);
    let upper = info(2, 1, 4, 4);
    assert!(record(&l, &upper).is_none());
    assert!(l.state().pending[&2].faces.is_empty());
}

#[test]
fn a_real_hole_is_named_once_and_its_later_pushes_refused() {
    let l = Layouts::default();
    // z 0..=3 and 5..=7: the points z = 4 lie in no brick.
    l.admit(&info(0, 0, 0, 4)).unwrap();
    assert!(record(&l, &info(0, 0, 0, 4)).is_none(), "rank 1 not in yet");
    let why = record(&l, &info(0, 1, 5, 3)).unwrap();
    assert!(
        why.to_string()
            .ends_with("beside rank 0's brick, no brick holds the points z = 4..=4"),
        "{why}"
    );
    // Step 1's pushes of the same bricks are refused at their header, naming step 0.
    for (rank, z0, nz) in [(0, 0, 4), (1, 5, 3)] {
        let refused = l.admit(&info(1, rank, z0, nz)).unwrap_err();
        assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
        assert!(
            refused.message().starts_with(&format!(
                "step 1 rank {rank}: not taken, the ranks' bricks cannot be composed (found when step 0 had all its ranks)"
            )),
            "{}",
            refused.message()
        );
    }
    // Bricks that tile are taken, checked and found whole.
    l.admit(&info(2, 0, 0, 5)).unwrap();
    assert!(record(&l, &info(2, 0, 0, 5)).is_none());
    assert!(record(&l, &info(2, 1, 4, 4)).is_none());
    let summary = l.summary().unwrap();
    assert!(
        summary.starts_with("1 step(s) whose ranks' bricks cannot be composed (first: step 0), 2 later push(es) of them refused: "),
        "{summary}"
    );
}

#[tokio::test]
async fn shared_planes_keep_no_faces_and_a_lone_rank_is_not_checked() {
    let l = Layouts::default();
    for step in 0..3 {
        l.admit(&info(step, 0, 0, 5)).unwrap();
        assert!(record(&l, &info(step, 0, 0, 5)).is_none());
        assert!(record(&l, &info(step, 1, 4, 4)).is_none());
        if step > 0 {
            // The layout is known to share its planes: no faces kept.
            assert!(l.state().pending[&step].faces.is_empty());
        }
        for rank in [0, 1] {
            let i = if rank == 0 {
                info(step, 0, 0, 5)
            } else {
                info(step, 1, 4, 4)
            };
            assert!(matches!(growth(&l, &i, WAIT).await, Growth::AsPushed));
        }
    }
    assert!(l.summary().is_none());
    assert!(l.whole_world_here(2) && l.whole_world_here(1) && !l.whole_world_here(3));
    let mut lone = info(0, 0, 0, 4);
    lone.world_size = 1;
    assert!(record(&l, &lone).is_none());
    // A node serving part of a world forgets the oldest of the steps it never sees whole.
    for step in 0..200 {
        assert!(record(&l, &info(step, 0, 0, 5)).is_none());
    }
    assert!(l.state().pending.len() <= MAX_PENDING);
}

/// Node `a` receives the lower z-half (points 0–3), node `b` the upper (4–7) of each step:
/// after the first step's wait each posts its bricks, the upper one with its low face; fed
/// the other's posts (as the viz-node relays them), the lower brick grows into the bricks of
/// the whole field's layout, from a face that came from the other node, and so do the later
/// steps' without a first wait.
#[tokio::test]
async fn halves_on_two_nodes_grow_by_the_faces_they_exchange() {
    let (a, b) = (Layouts::new(true), Layouts::new(true));
    let short = Duration::from_millis(100);
    let exchange = |from: &Layouts, to: &Layouts| {
        for p in from.posts() {
            assert_eq!((p.world_size, p.global), (2, [N; 3]));
            to.remote(p.step, p.bricks);
        }
    };
    for step in 0..3 {
        let (lower, upper) = (info(step, 0, 0, 4), info(step, 1, 4, 4));
        assert!(record(&a, &lower).is_none() && record(&b, &upper).is_none());
        // The upper brick does not grow: made as pushed (after the first step's wait).
        assert!(matches!(growth(&b, &upper, short).await, Growth::AsPushed));
        // The viz-node's relay, every 10 ms, until the lower brick is decided.
        let waiting = growth(&a, &lower, short);
        tokio::pin!(waiting);
        let grown = loop {
            tokio::select! {
                g = &mut waiting => break g,
                () = tokio::time::sleep(Duration::from_millis(10)) => {
                    exchange(&b, &a);
                    exchange(&a, &b);
                }
            }
        };
        match grown {
            Growth::Grow {
                brick,
                across,
                ref faces,
            } => {
                assert_eq!(
                    (brick.offset, brick.dims, across),
                    ([0; 3], [N, N, 5], true)
                );
                let mut grown_info = lower;
                let v = grown
                    .apply(&mut grown_info, &field(&lower), None)
                    .unwrap()
                    .unwrap();
                let expected = whole().brick(&brick).unwrap();
                assert_eq!(v.voxels().to_le_bytes(), expected.voxels().to_le_bytes());
                assert!(!faces.is_empty());
            }
            other => panic!("step {step}: {other:?}"),
        }
    }
    // Nothing is posted twice, and nothing of a made step is kept.
    assert!(a.posts().is_empty() && b.posts().is_empty());
    assert!(a.state().pending.is_empty() && b.state().pending.is_empty());
    assert!(!a.whole_world_here(2) && !b.whole_world_here(2));
}
