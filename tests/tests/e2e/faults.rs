//! Faults of the recording, with the viz-node as a real process: a retried VDI is stored once
//! and a different one for the same (step, rank) refused; a viz-node killed between storing
//! and scoring scores on restart and removes what the crash left; renders beyond the caps are
//! refused, not allowed to take the node's memory.

use crate::common::{index, load_vdi, local_q, viz, viz_status};
use insitu_core::evaluate::{render_references, Sizing};
use insitu_core::vdi::codec::{encode, Codec};
use insitu_core::vdi::{generate::generate, VdiParams};
use insitu_core::{Backend, Camera, RaycastParams, Raycaster, TransferFunction, Volume};
use insitu_e2e::{rt, wait_until};
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::{chunk, pb, transport};
use insitu_recording::store::{Entry, Recording, References};
use tonic::Code;

/// A small VDI file of a blob, with its reference frames at 0° and 40°.
pub(crate) fn vdi_and_refs(gamma: f32) -> (Vec<u8>, References) {
    let v = Volume::from_fn([16, 16, 16], |x, y, z| {
        let d2 = (x as f32 - 8.0).powi(2) + (y as f32 - 7.0).powi(2) + (z as f32 - 8.0).powi(2);
        (-d2 / 18.0).exp()
    })
    .unwrap();
    let tf = TransferFunction::default_for_range(0.0, 1.0);
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let camera = Camera::default_for_box(&v.world_box());
    let params = VdiParams {
        resolution: 24,
        gamma,
        precision: Default::default(),
    };
    let vdi = generate(&rc, &camera, params, tf.identity_hash(), "blob").unwrap();
    let backend = Backend::Cpu;
    let scene = backend.prepare(&rc).unwrap();
    let angles = vec![0.0, 40.0];
    let frames = render_references(&scene, &camera, &angles, 24).unwrap();
    let refs = References {
        camera,
        view_angles_deg: angles,
        frames,
        opacity: None,
    };
    (encode(&vdi, Codec::Zstd).unwrap(), refs)
}

pub(crate) fn header(step: u64, file: &[u8], gamma: f32) -> pb::VdiHeader {
    pb::VdiHeader {
        step,
        world_size: 1,
        resolution: 24,
        gamma,
        codec: pb::Codec::Zstd as i32,
        total_bytes: file.len() as u64,
        ..Default::default()
    }
}

#[test]
fn a_retried_vdi_is_stored_once_and_a_different_one_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let (file, _) = vdi_and_refs(0.01);
    let (other, _) = vdi_and_refs(0.2);
    rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let mut c = VizClient::new(channel);
        let ship = |h: pb::VdiHeader, f: &[u8]| {
            tokio_stream::iter(chunk::split::<pb::VdiChunk>(
                h,
                bytes::Bytes::from(f.to_vec()),
            ))
        };
        // A retry after a lost acknowledgement: the same bytes again are a success.
        let first = c
            .ship_vdi(ship(header(5, &file, 0.01), &file))
            .await
            .unwrap();
        let again = c
            .ship_vdi(ship(header(5, &file, 0.01), &file))
            .await
            .unwrap();
        assert_eq!(first.into_inner().path, again.into_inner().path);
        // Other content for the same step and rank would silently replace it: refused.
        let e = c
            .ship_vdi(ship(header(5, &other, 0.2), &other))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::AlreadyExists);
        assert!(e.message().contains("step 5 rank 0"), "{}", e.message());
        let s = c
            .get_status(pb::StatusRequest {})
            .await
            .unwrap()
            .into_inner();
        assert_eq!(s.vdis_stored, 1);
        // Renders beyond the caps are refused before any memory is taken.
        let e = c
            .render(pb::RenderRequest {
                step: 5,
                width: 8192,
                height: 8192,
                ..Default::default()
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::ResourceExhausted);
        assert!(e.message().contains("max_render_pixels"), "{}", e.message());
        // The largest allowed render (4096², 200 MB of f32 pixels) gives its memory back.
        let before = v.rss_mib();
        let png = c
            .render(pb::RenderRequest {
                step: 5,
                width: 4096,
                height: 4096,
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        assert!(!png.png.is_empty());
        let after = v.rss_mib();
        eprintln!(
            "render 4096²: viz-node RSS {before:.0} MiB before, peak {:.0} MiB, {after:.0} MiB after",
            v.peak_rss_mib()
        );
        assert!(v.peak_rss_mib() > before + 150.0, "the render did take memory");
        assert!(after < before + 48.0, "{before:.0} → {after:.0} MiB");
    });
    let e = index(&rec);
    assert_eq!(e.len(), 1);
    assert_eq!(load_vdi(&rec, &e[0]).meta().params.gamma, 0.01);
    v.terminate();
}

#[test]
fn a_viz_node_killed_before_scoring_scores_on_restart_and_tidies_up() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    // What a viz-node killed with SIGKILL between storing a step and scoring it leaves: the
    // VDI and its references committed, no q, and a temporary file of a write in progress.
    {
        let r = Recording::open(&rec).unwrap();
        let (file, refs) = vdi_and_refs(0.01);
        let meta = Entry {
            world_size: 1,
            resolution: 24,
            gamma: 0.01,
            codec: Some(Codec::Zstd),
            sizing: Sizing {
                sigma_bytes: file.len() as u64,
                ..Sizing::default()
            },
            ..Entry::empty(8, 0)
        };
        r.store_vdi(meta, &file).unwrap();
        r.store_references(8, 0, &refs).unwrap();
    }
    std::fs::write(rec.join(".tmp-interrupted"), b"half a file").unwrap();
    assert!(index(&rec)[0].quality.is_none());
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let scored = wait_until(30.0, || {
        index(&rec).first().is_some_and(|e| e.quality.is_some())
    });
    assert!(scored, "the stored step was not scored after the restart");
    assert!(!rec.join(".tmp-interrupted").exists());
    let e = index(&rec).remove(0);
    let local = local_q(&rec, &e);
    assert!((e.quality.as_ref().unwrap().q_db.0 - local).abs() < 1e-9);
    // Nothing was kept decoded across the kill: both files were read from the recording.
    let status = viz_status(&v.addr);
    assert_eq!((status.decoded_reused, status.decoded_again), (0, 2));
    let peak = v.peak_rss_mib();
    // Killed again: the committed rows survive as they are.
    v.kill();
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    assert_eq!(index(&rec), vec![e]);
    eprintln!(
        "KillReader: acknowledged 1 (stored, unscored at the kill), stored 1, scored after restart, lost 0, duplicated 0, temporary file removed; peak RSS viz {peak:.0} MiB"
    );
    assert!(peak < RSS_BOUND_MIB);
    v.terminate();
}

#[test]
fn a_viz_node_that_refuses_the_token_makes_flush_fail_and_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let token = tmp.path().join("token");
    std::fs::write(&token, "s3cret-token").unwrap();
    let v = insitu_e2e::start_viz(
        &rec,
        "127.0.0.1:0",
        &["--token-file", token.to_str().unwrap()],
        tmp.path(),
    );
    // The generator-node has no token: every VDI it ships is refused.
    let g = crate::common::generator(
        &crate::common::small_config(&v.addr, "block", 16),
        tmp.path(),
        &[],
    );
    crate::common::push_steps(&g.addr, 0..3);
    let e = rt().block_on(async {
        insitu_client::SimClient::connect(&g.addr, None)
            .await
            .unwrap()
            .flush(std::time::Duration::from_secs(60))
            .await
            .unwrap_err()
    });
    let text = e.to_string();
    assert!(
        text.contains("refused 3 VDI(s)") && text.contains("Unauthenticated"),
        "{text}"
    );
    let s = crate::common::status(&g.addr);
    assert_eq!((s.ship_failed, s.steps_shipped), (3, 0));
    assert!(s.ship_error.contains("Unauthenticated"), "{}", s.ship_error);
    // The next flush has nothing new to report.
    crate::common::flush(&g.addr);
    assert!(index(&rec).is_empty());
    g.terminate();
    v.terminate();
}

/// KillWriter: a generator-node killed with SIGKILL while it holds acknowledged, undelivered
/// steps (the viz-node is down, so nothing can be delivered). With a spool the restarted node
/// delivers every one of them exactly once, in the scene set before the crash; without one,
/// they are lost and the changed epoch says the node restarted.
#[test]
fn a_killed_generator_with_a_spool_loses_nothing_it_acknowledged() {
    for spooled in [true, false] {
        let tmp = tempfile::tempdir().unwrap();
        let rec = tmp.path().join("rec");
        let port = crate::common::free_port();
        let viz_addr = format!("127.0.0.1:{port}");
        let spool = tmp.path().join("spool");
        let mut cfg = crate::common::small_config(&viz_addr, "block", 16)
            .replace("max_items = 2\n", "max_items = 8\n");
        if spooled {
            cfg.push_str(&format!("[spool]\ndir = {:?}\n", spool.to_str().unwrap()));
        }
        let g = crate::common::generator(&cfg, tmp.path(), &[]);
        let (epoch, acknowledged) = rt().block_on(async {
            let mut c = insitu_client::SimClient::connect(&g.addr, None)
                .await
                .unwrap();
            // The scene of this run: r = 40 and a TF, pushed by an operator.
            let tf = TransferFunction::default_for_range(0.0, 1.0);
            c.set_config(pb::GenerationConfig {
                resolution: 40,
                gamma: 0.01,
                tf: Some(pb::TransferFunction::from(&tf)),
                tf_name: Some("pushed".into()),
                ..Default::default()
            })
            .await
            .unwrap();
            let mut epoch = 0;
            for s in 0..5u64 {
                let field = crate::common::field(16, s);
                let r = c
                    .push_step(insitu_client::Step::whole_f32(s, s as f64, [16; 3], &field))
                    .await
                    .unwrap();
                epoch = r.epoch;
            }
            (epoch, 5u64)
        });
        let peak_before = g.peak_rss_mib();
        g.kill();
        let v = viz(&rec, &viz_addr, tmp.path());
        let g = crate::common::generator(&cfg, tmp.path(), &[]);
        let s = crate::common::flush(&g.addr);
        assert_ne!(s.epoch, epoch, "a restarted node has a new epoch");
        let stored = index(&rec);
        if spooled {
            assert_eq!(s.recovered, acknowledged);
            let steps: Vec<u64> = stored.iter().map(|e| e.step).collect();
            assert_eq!(
                steps,
                [0, 1, 2, 3, 4],
                "each acknowledged step stored exactly once"
            );
            assert!(stored
                .iter()
                .all(|e| e.resolution == 40 && e.tf_name == "pushed"));
            assert_eq!(s.spooled_bytes, 0);
            let left: Vec<_> = std::fs::read_dir(&spool)
                .unwrap()
                .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| n != "run.pb")
                .collect();
            assert!(left.is_empty(), "{left:?}");
        } else {
            assert_eq!((s.recovered, stored.len()), (0, 0));
        }
        eprintln!(
            "KillWriter ({}): acknowledged {acknowledged}, stored {}, lost {}{}, duplicated 0; peak RSS generator {:.0} MiB before the kill, {:.0} MiB after restart, viz {:.0} MiB",
            if spooled { "spool" } else { "no spool" },
            stored.len(),
            acknowledged - stored.len() as u64,
            if spooled { "" } else { " (the new epoch tells the client)" },
            peak_before,
            g.peak_rss_mib(),
            v.peak_rss_mib()
        );
        assert!(peak_before.max(g.peak_rss_mib()) < RSS_BOUND_MIB);
        g.terminate();
        v.terminate();
    }
}

/// What every fault case checks of the recording: each of `steps` stored exactly once, every
/// stored VDI decodes, every sampled step (divisible by `every`) scored, no temporary file.
fn assert_recording(rec: &std::path::Path, steps: &[u64], every: u64) {
    let scored = wait_until(30.0, || {
        index(rec)
            .iter()
            .filter(|e| e.step % every == 0)
            .all(|e| e.quality.is_some())
    });
    assert!(scored, "a sampled step was not scored");
    let stored = index(rec);
    let got: Vec<u64> = stored.iter().map(|e| e.step).collect();
    assert_eq!(got, steps, "stored exactly once, in order");
    for e in &stored {
        load_vdi(rec, e);
    }
    let temps: Vec<_> = std::fs::read_dir(rec)
        .unwrap()
        .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".tmp-"))
        .collect();
    assert!(temps.is_empty(), "{temps:?}");
}

/// Resident-memory bound of either daemon in these cases (16³ fields, r = 32), MiB.
const RSS_BOUND_MIB: f64 = 400.0;

fn sampled_config(viz: &str, policy: &str) -> String {
    crate::common::small_config(viz, policy, 4)
        .replace("reference_every = 0", "reference_every = 4")
}

/// DelayedReader: the viz-node is stopped (SIGSTOP) for 10 s while 20 steps are pushed with
/// the `block` policy; the simulation waits, nothing is lost or duplicated.
#[test]
fn delayed_reader_loses_and_duplicates_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = crate::common::generator(&sampled_config(&v.addr, "block"), tmp.path(), &[]);
    v.signal("STOP");
    let resume = std::thread::spawn({
        let pid = v.child.id();
        move || {
            std::thread::sleep(std::time::Duration::from_secs(10));
            let _ = std::process::Command::new("kill")
                .args(["-CONT", &pid.to_string()])
                .status();
        }
    });
    let replies = crate::common::push_steps(&g.addr, 0..20);
    assert_eq!(replies.iter().map(|r| r.dropped_by_push).sum::<u64>(), 0);
    resume.join().unwrap();
    let s = crate::common::flush(&g.addr);
    assert_eq!(
        (s.steps_shipped, s.dropped_queue + s.dropped_outbox),
        (20, 0)
    );
    assert_recording(&rec, &(0..20).collect::<Vec<_>>(), 4);
    eprintln!(
        "DelayedReader: acknowledged 20, stored 20, lost 0, duplicated 0; peak RSS generator {:.0} MiB, viz {:.0} MiB",
        g.peak_rss_mib(),
        v.peak_rss_mib()
    );
    assert!(g.peak_rss_mib() < RSS_BOUND_MIB && v.peak_rss_mib() < RSS_BOUND_MIB);
    g.terminate();
    v.terminate();
}

/// LatestReader: `latest-only` under a stopped viz-node: pushes never wait, every step is
/// stored or counted as dropped, none twice.
#[test]
fn latest_reader_never_waits_and_accounts_for_every_step() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let cfg = sampled_config(&v.addr, "latest-only").replace(
        "[outbox]\nmax_items = 4\nmax_bytes = 1073741824\npolicy = \"block\"",
        "[outbox]\nmax_items = 1\nmax_bytes = 1073741824\npolicy = \"latest-only\"",
    );
    let g = crate::common::generator(&cfg, tmp.path(), &[]);
    v.signal("STOP");
    let t = std::time::Instant::now();
    crate::common::push_steps(&g.addr, 0..20);
    let pushing = t.elapsed().as_secs_f64();
    v.signal("CONT");
    let s = crate::common::flush(&g.addr);
    assert_eq!(
        s.steps_shipped + s.dropped_queue + s.dropped_outbox + s.failed,
        20
    );
    assert!(s.dropped_queue + s.dropped_outbox > 0, "{s:?}");
    let stored: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(stored.len() as u64, s.steps_shipped);
    assert!(stored.windows(2).all(|w| w[0] < w[1]), "{stored:?}");
    assert_eq!(stored.last(), Some(&19), "the latest step is kept");
    eprintln!(
        "LatestReader: pushed 20 in {pushing:.2} s, stored {}, dropped {} (counted), duplicated 0; peak RSS generator {:.0} MiB, viz {:.0} MiB",
        s.steps_shipped,
        s.dropped_queue + s.dropped_outbox,
        g.peak_rss_mib(),
        v.peak_rss_mib()
    );
    assert!(g.peak_rss_mib() < RSS_BOUND_MIB && v.peak_rss_mib() < RSS_BOUND_MIB);
    g.terminate();
    v.terminate();
}

/// TimeoutReader: the viz-node is absent past the generator-node's drain timeout. The node
/// stops and counts the undelivered VDIs as dropped; with a spool they stay on disk and the
/// restarted node delivers them once the viz-node is back.
#[test]
fn timeout_reader_keeps_spooled_steps_for_the_next_run() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let viz_addr = format!("127.0.0.1:{}", crate::common::free_port());
    let spool = tmp.path().join("spool");
    let tf = tmp.path().join("tf.json");
    std::fs::write(
        &tf,
        serde_json::to_string(&TransferFunction::default_for_range(0.0, 1.0)).unwrap(),
    )
    .unwrap();
    let cfg = sampled_config(&viz_addr, "block")
        .replace("drain_timeout_secs = 5.0", "drain_timeout_secs = 1.0")
        .replace(
            "[generation]\n",
            &format!("[generation]\ntf = {:?}\n", tf.to_str().unwrap()),
        )
        + &format!("[spool]\ndir = {:?}\n", spool.to_str().unwrap());
    let g = crate::common::generator(&cfg, tmp.path(), &[]);
    crate::common::push_steps(&g.addr, 0..6);
    let summary = g.terminate();
    assert!(summary.contains("unshipped at shutdown"), "{summary}");
    let v = viz(&rec, &viz_addr, tmp.path());
    let g = crate::common::generator(&cfg, tmp.path(), &[]);
    let s = crate::common::flush(&g.addr);
    assert_eq!(s.recovered, 6);
    assert_recording(&rec, &(0..6).collect::<Vec<_>>(), 4);
    eprintln!(
        "TimeoutReader (spool): acknowledged 6, undelivered at the drain timeout 6, stored after restart 6, lost 0, duplicated 0; peak RSS generator {:.0} MiB, viz {:.0} MiB",
        g.peak_rss_mib(),
        v.peak_rss_mib()
    );
    g.terminate();
    v.terminate();
}

/// A tmpfs of `mib` MiB mounted at `dir` (needs root, as in CI), unmounted on drop; `None`,
/// said on stderr, where mounting is not permitted.
struct Tmpfs(std::path::PathBuf);

impl Tmpfs {
    fn mount(dir: &std::path::Path, mib: u32) -> Option<Self> {
        std::fs::create_dir_all(dir).unwrap();
        let ok = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mib}m"), "tmpfs"])
            .arg(dir)
            .status()
            .is_ok_and(|s| s.success());
        ok.then(|| Self(dir.to_owned()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.0)
            .status();
    }
}

/// Fills the file system of `dir` with `path` until a write fails with "no space".
fn fill(path: &std::path::Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(path).unwrap();
    let block = vec![0x5au8; 4096];
    loop {
        match f.write_all(&block).and_then(|()| f.sync_all()) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::StorageFull => return,
            Err(e) => panic!("filling {}: {e}", path.display()),
        }
    }
}

/// FullDisk: the recording on a 16 MiB tmpfs made here, filled to the last byte while steps
/// arrive. The viz-node refuses each item with `RESOURCE_EXHAUSTED` and leaves no file behind;
/// the generator-node keeps the VDIs (retrying with back-off), says why in `GetStatus` and in
/// a `Flush` that times out; once space is freed every acknowledged step is stored exactly
/// once and scored.
#[test]
fn full_disk_delays_delivery_and_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let disk = tmp.path().join("disk");
    let Some(_mount) = Tmpfs::mount(&disk, 16) else {
        eprintln!("SKIPPED full_disk_delays_delivery_and_loses_nothing: cannot mount a tmpfs here (needs root; CI runs as root)");
        return;
    };
    let rec = disk.join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = crate::common::generator(&sampled_config(&v.addr, "block"), tmp.path(), &[]);
    crate::common::push_steps(&g.addr, 0..2);
    crate::common::flush(&g.addr);
    fill(&disk.join("filler"));
    let replies = crate::common::push_steps(&g.addr, 2..8);
    assert_eq!(replies.len(), 6, "every push acknowledged");
    let refused = wait_until(30.0, || {
        crate::common::status(&g.addr)
            .ship_error
            .contains("ResourceExhausted")
    });
    assert!(refused, "{:?}", crate::common::status(&g.addr));
    let e = rt()
        .block_on(async {
            insitu_client::SimClient::connect(&g.addr, None)
                .await
                .unwrap()
                .flush(std::time::Duration::from_secs(2))
                .await
        })
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("out of space") && e.contains("No space left"),
        "{e}"
    );
    let names = |d: &std::path::Path| -> Vec<String> {
        std::fs::read_dir(d)
            .unwrap()
            .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
            .collect()
    };
    assert!(!names(&rec).iter().any(|n| n.starts_with(".tmp-")));
    assert!(index(&rec).iter().all(|e| e.step < 2));

    std::fs::remove_file(disk.join("filler")).unwrap();
    let s = crate::common::flush(&g.addr);
    assert_eq!((s.steps_shipped, s.failed), (8, 0));
    assert_recording(&rec, &(0..8).collect::<Vec<_>>(), 4);
    eprintln!(
        "FullDisk: acknowledged 8, stored 8 (6 after space was freed), lost 0, duplicated 0; peak RSS generator {:.0} MiB, viz {:.0} MiB",
        g.peak_rss_mib(),
        v.peak_rss_mib()
    );
    assert!(g.peak_rss_mib() < RSS_BOUND_MIB && v.peak_rss_mib() < RSS_BOUND_MIB);
    g.terminate();
    v.terminate();
}

/// ReadOnly: the recording directory turned read-only while steps arrive (a read-only bind
/// mount over it, as an operator's mistake or a file system remounted read-only after errors
/// makes it; files already open stay writable, new ones fail with EROFS). The viz-node refuses
/// each item as a storage fault (`RESOURCE_EXHAUSTED`, naming the read-only file system), the
/// generator-node keeps and retries them instead of counting them failed, and once the
/// directory is writable again every acknowledged step is stored exactly once and scored.
#[test]
fn a_read_only_recording_delays_delivery_and_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = crate::common::generator(&sampled_config(&v.addr, "block"), tmp.path(), &[]);
    crate::common::push_steps(&g.addr, 0..2);
    crate::common::flush(&g.addr);
    let mount = |args: &[&str]| {
        std::process::Command::new("mount")
            .args(args)
            .arg(&rec)
            .arg(&rec)
            .status()
            .is_ok_and(|s| s.success())
    };
    if !mount(&["--bind"]) {
        eprintln!("SKIPPED a_read_only_recording_delays_delivery_and_loses_nothing: cannot bind-mount here (needs root; CI runs as root)");
        return;
    }
    let ro = std::process::Command::new("mount")
        .args(["-o", "remount,bind,ro"])
        .arg(&rec)
        .status()
        .is_ok_and(|s| s.success());
    let unmount = || {
        let _ = std::process::Command::new("umount").arg(&rec).status();
    };
    if !ro {
        unmount();
        panic!("mount -o remount,bind,ro {} failed", rec.display());
    }
    outlasts_storage_fault(&g, &rec, "ead-only", unmount, "ReadOnly");
    g.terminate();
    v.terminate();
}

/// With steps 0 and 1 stored and the recording now refusing writes: steps 2 to 7 pushed while
/// it lasts are acknowledged, each refused as a storage fault naming `cause` and kept by the
/// generator-node (none counted failed); once `undo` ends the fault every step is stored
/// exactly once and scored. `case` names the fault in the line printed.
fn outlasts_storage_fault(
    g: &insitu_e2e::Daemon,
    rec: &std::path::Path,
    cause: &str,
    undo: impl FnOnce(),
    case: &str,
) {
    let replies = crate::common::push_steps(&g.addr, 2..8);
    let refused = wait_until(30.0, || {
        crate::common::status(&g.addr)
            .ship_error
            .contains("ResourceExhausted")
    });
    let status = crate::common::status(&g.addr);
    undo();
    assert_eq!(replies.len(), 6, "every push acknowledged");
    assert!(refused, "{status:?}");
    assert!(status.ship_error.contains(cause), "{}", status.ship_error);
    assert_eq!(status.failed, 0, "a storage fault fails no VDI");
    let s = crate::common::flush(&g.addr);
    assert_eq!((s.steps_shipped, s.failed), (8, 0));
    assert_recording(rec, &(0..8).collect::<Vec<_>>(), 4);
    eprintln!(
        "{case}: acknowledged 8, stored 8 (6 after the fault was undone), lost 0, duplicated 0"
    );
}

/// Permission denied: the recording directory's write permission removed while steps arrive
/// (an operator's `chmod`, a quota tool), then restored. The viz-node runs as `nobody` so that
/// the permission binds it (root ignores it; CI runs as root, and a machine where the test is
/// not root runs it as itself). Each item is refused as a storage fault naming the denial, the
/// generator-node keeps and retries them, and once the permission is back every acknowledged
/// step is stored exactly once and scored.
#[test]
fn permission_denied_delays_delivery_and_loses_nothing() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    std::fs::create_dir(&rec).unwrap();
    let root = std::process::Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| o.stdout.starts_with(b"0\n"));
    let viz = if root {
        // nobody reaches its own copy of the binary and a recording it owns, nothing else.
        std::fs::set_permissions(tmp.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
        let exe = tmp.path().join("viz-node");
        std::fs::copy(insitu_e2e::bin("viz-node"), &exe).unwrap();
        let owned = std::process::Command::new("chown")
            .args(["65534:65534"])
            .arg(&rec)
            .status()
            .is_ok_and(|s| s.success());
        assert!(owned, "chown nobody {}", rec.display());
        let mut cmd = std::process::Command::new("setpriv");
        cmd.env_remove("INSITU_TOKEN")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups"])
            .arg(&exe)
            .args(["--listen", "127.0.0.1:0", "--recording-dir"])
            .arg(&rec)
            .args(["--backend", "cpu"]);
        insitu_e2e::Daemon::spawn("viz-node", cmd, tmp.path())
    } else {
        viz(&rec, "127.0.0.1:0", tmp.path())
    };
    let g = crate::common::generator(&sampled_config(&viz.addr, "block"), tmp.path(), &[]);
    crate::common::push_steps(&g.addr, 0..2);
    crate::common::flush(&g.addr);
    let mode = |m: u32| std::fs::set_permissions(&rec, std::fs::Permissions::from_mode(m)).unwrap();
    mode(0o555);
    outlasts_storage_fault(
        &g,
        &rec,
        "ermission denied",
        || mode(0o755),
        "PermissionDenied",
    );
    g.terminate();
    viz.terminate();
}

/// KillHost: a generator-node serving all 4 ranks of a world (spool on) is killed while it
/// holds a composed part in flight (the viz-node stopped mid-delivery) and ranks waiting for
/// their host's last rank, with the spool still naming two steps whose parts the viz-node had
/// stored (a crash between the viz-node's acknowledgement and the spool's removal). After the
/// restart every acknowledged rank is held by exactly one stored part: the stored parts
/// acknowledge the ranks shipped again, the rest are stored; 0 lost, 0 failed, every step
/// composes whole.
#[test]
fn a_host_killed_holding_composed_and_uncomposed_ranks_loses_nothing() {
    use crate::ranks::slab;
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let viz_addr = format!("127.0.0.1:{}", crate::common::free_port());
    let spool = tmp.path().join("spool");
    let mut cfg = crate::common::small_config(&viz_addr, "block", 1)
        .replace("max_items = 2\n", "max_items = 8\n");
    cfg.push_str(&format!(
        "[host]\nwait_secs = 600\n[spool]\ndir = {:?}\n",
        spool.to_str().unwrap()
    ));
    let push = |addr: &str, steps: Vec<insitu_client::Step>| {
        rt().block_on(async {
            let mut c = insitu_client::SimClient::connect(addr, None).await.unwrap();
            for s in steps {
                c.push_step(s).await.unwrap();
            }
        })
    };
    let all = |step: u64| (0..4).map(|r| slab(step, r, 4, 1.0 + r as f32)).collect();
    let g = crate::common::generator(&cfg, tmp.path(), &[]);
    rt().block_on(async {
        let mut c = insitu_client::SimClient::connect(&g.addr, None)
            .await
            .unwrap();
        let tf = TransferFunction::default_for_range(0.0, 5.0);
        c.set_config(pb::GenerationConfig {
            resolution: 32,
            gamma: 0.01,
            tf: Some(pb::TransferFunction::from(&tf)),
            tf_name: Some("fixed".into()),
            ..Default::default()
        })
        .await
        .unwrap();
    });
    // Steps 0 and 1 acknowledged while the viz-node is down: the spool as it was then.
    push(&g.addr, [all(0), all(1)].concat());
    let snapshot = tmp.path().join("spool-then");
    std::fs::create_dir_all(&snapshot).unwrap();
    let spooled: Vec<std::path::PathBuf> = std::fs::read_dir(&spool)
        .unwrap()
        .map(|d| d.unwrap().path())
        .filter(|p| p.file_name().is_some_and(|n| n != "run.pb"))
        .collect();
    assert_eq!(spooled.len(), 8);
    for p in &spooled {
        std::fs::copy(p, snapshot.join(p.file_name().unwrap())).unwrap();
    }
    // Step 2 without rank 3: its ranks wait for it (rank 3 was served at step 1).
    push(
        &g.addr,
        (0..3).map(|r| slab(2, r, 4, 1.0 + r as f32)).collect(),
    );
    let v = viz(&rec, &viz_addr, tmp.path());
    assert!(
        wait_until(60.0, || index(&rec).len() == 2),
        "{:?}",
        index(&rec)
    );
    assert!(index(&rec).iter().all(|e| e.ranks() == [0, 1, 2, 3]));
    // Step 3 whole while the viz-node is stopped: its part is composed and in flight.
    v.signal("STOP");
    push(&g.addr, all(3));
    let status = || {
        rt().block_on(async {
            insitu_client::SimClient::connect(&g.addr, None)
                .await
                .unwrap()
                .status()
                .await
                .unwrap()
        })
    };
    assert!(
        wait_until(60.0, || status().host_parts == 3),
        "{:?}",
        status()
    );
    g.kill();
    v.signal("CONT");
    // The crash came before the spool forgot steps 0 and 1.
    for p in &spooled {
        std::fs::copy(snapshot.join(p.file_name().unwrap()), p).unwrap();
    }
    // Restarted with the default wait: its first step waits at most 2 s for the world.
    let cfg = cfg.replace("wait_secs = 600\n", "");
    let g = crate::common::generator(&cfg, tmp.path(), &[]);
    push(&g.addr, vec![slab(2, 3, 4, 4.0)]);
    let s = crate::common::flush(&g.addr);
    assert_eq!(
        (s.recovered, s.failed, s.dropped_outbox),
        (4 + 4 + 3 + 4, 0, 0),
        "{s:?}"
    );
    assert!(wait_until(60.0, || crate::common::steps(&rec).len() == 4));
    let stored = index(&rec);
    for step in 0..4u64 {
        let mut held: Vec<u32> = stored
            .iter()
            .filter(|e| e.step == step)
            .flat_map(Entry::ranks)
            .collect();
        held.sort_unstable();
        assert_eq!(held, [0, 1, 2, 3], "step {step}: {stored:?}");
    }
    assert!(crate::common::steps(&rec)
        .iter()
        .all(|s| s.missing.is_empty() && s.error.is_none()));
    assert_eq!(s.spooled_bytes, 0);
    eprintln!(
        "KillHost: 16 ranks' steps acknowledged, {} parts stored (steps 0 and 1 whole, 2 and 3 rank by rank), 0 lost, 0 failed",
        stored.len()
    );
    g.terminate();
    v.terminate();
}
