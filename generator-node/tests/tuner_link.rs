#![allow(clippy::unwrap_used, clippy::expect_used)]

//! The generator-node's side of the tuner stream, against a scripted tuner on loopback: the
//! node dials out and says hello, summarises every step (64 bins over the TF's domain), runs a
//! trial on a claimed step with the viz-node's scoring, renders a preview of another transfer
//! function on it, refuses politely a trial on a step it does not hold and a decision that is
//! not newer than its own, and applies a good decision from the next step, stamping its
//! version.

use insitu_generator_node::{start, Config};
use insitu_proto::pb::node_message::Msg as Up;
use insitu_proto::pb::tuner_message::Msg as Down;
use insitu_proto::pb::tuner_server::{Tuner, TunerServer};
use insitu_proto::{pb, transport};
use std::pin::Pin;
use std::sync::Mutex;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_stream::wrappers::{ReceiverStream, TcpListenerStream};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

type Out = Result<pb::TunerMessage, Status>;

/// A tuner that hands the test the node's messages and sends what the test scripts.
struct Scripted {
    up: mpsc::Sender<pb::NodeMessage>,
    down: Mutex<Option<mpsc::Receiver<Out>>>,
}

#[tonic::async_trait]
impl Tuner for Scripted {
    type AttachStream = Pin<Box<dyn Stream<Item = Out> + Send>>;
    type WatchDecisionsStream = Pin<Box<dyn Stream<Item = Result<pb::PmDecision, Status>> + Send>>;

    async fn attach(
        &self,
        request: Request<Streaming<pb::NodeMessage>>,
    ) -> Result<Response<Self::AttachStream>, Status> {
        let mut inbound = request.into_inner();
        let up = self.up.clone();
        tokio::spawn(async move {
            while let Some(Ok(m)) = inbound.next().await {
                let _ = up.send(m).await;
            }
        });
        let rx = self.down.lock().unwrap().take().expect("one stream");
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn get_status(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::TunerStatus>, Status> {
        Err(Status::unimplemented("scripted"))
    }

    async fn get_decision(
        &self,
        _: Request<pb::DecisionRequest>,
    ) -> Result<Response<pb::PmDecision>, Status> {
        Err(Status::unimplemented("scripted"))
    }

    async fn watch_decisions(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<Self::WatchDecisionsStream>, Status> {
        Err(Status::unimplemented("scripted"))
    }

    async fn steer(
        &self,
        _: Request<pb::SteerRequest>,
    ) -> Result<Response<pb::SteerReply>, Status> {
        Err(Status::unimplemented("scripted"))
    }

    async fn preview(
        &self,
        _: Request<pb::PreviewRequest>,
    ) -> Result<Response<pb::PreviewReply>, Status> {
        Err(Status::unimplemented("scripted"))
    }
}

fn field(n: usize, t: u64) -> Vec<f32> {
    (0..n * n * n)
        .map(|i| {
            let (x, y, z) = ((i % n) as f32, ((i / n) % n) as f32, (i / (n * n)) as f32);
            let c = 6.0 + t as f32;
            (-((x - c).powi(2) + (y - 8.0).powi(2) + (z - 8.0).powi(2)) / 10.0).exp()
        })
        .collect()
}

async fn next(up: &mut mpsc::Receiver<pb::NodeMessage>) -> Up {
    tokio::time::timeout(Duration::from_secs(60), up.recv())
        .await
        .expect("the node answered in time")
        .and_then(|m| m.msg)
        .expect("a message")
}

fn send(tx: &mpsc::Sender<Out>, m: Down) {
    tx.try_send(Ok(pb::TunerMessage { msg: Some(m) })).unwrap();
}

/// A node (r = 32, CPU, zstd, no reference frames unless a trial asks) attached to a scripted
/// tuner, once its hello is in and the node says it is connected: the node, the node's
/// messages and the tuner's sender.
async fn scripted_node() -> (
    insitu_generator_node::RunningNode,
    mpsc::Receiver<pb::NodeMessage>,
    mpsc::Sender<Out>,
    pb::NodeHello,
) {
    let (up_tx, mut up) = mpsc::channel(1024);
    let (down, down_rx) = mpsc::channel(256);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let tuner_addr = listener.local_addr().unwrap();
    tokio::spawn(
        transport::server()
            .add_service(TunerServer::new(Scripted {
                up: up_tx,
                down: Mutex::new(Some(down_rx)),
            }))
            .serve_with_incoming(TcpListenerStream::new(listener)),
    );
    let mut cfg = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tuner: Some(tuner_addr.to_string()),
        backend: insitu_core::BackendChoice::Cpu,
        max_backoff_secs: 0.2,
        ..Default::default()
    };
    cfg.generation.resolution = 32;
    cfg.generation.reference_every = 0;
    cfg.generation.reference_size = 24;
    cfg.generation.view_angles_deg = vec![0.0, 20.0];
    cfg.generation.codec = insitu_core::vdi::codec::Codec::Zstd;
    let node = start(cfg).await.unwrap();
    let Up::Hello(hello) = next(&mut up).await else {
        panic!("the first message must be a hello")
    };
    assert!(tokio::time::timeout(Duration::from_secs(10), async {
        while !node.shared().status().tuner_connected {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await
    .is_ok());
    (node, up, down, hello)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_node_summarises_runs_trials_and_applies_decisions() {
    let (node, mut up, down, hello) = scripted_node().await;
    assert_eq!((hello.pm_version, hello.resolution), (0, 32));
    assert!(hello.held.is_empty());

    let mut client = insitu_client::SimClient::connect(&node.local_addr().to_string(), None)
        .await
        .unwrap();
    let push = |t: u64| insitu_client::Step::whole_f32(t, t as f64, [16; 3], &field(16, t));
    client.push_step(push(0)).await.unwrap();
    let Up::Summary(s) = next(&mut up).await else {
        panic!("expected a summary")
    };
    assert_eq!(
        (s.step, s.rank, s.world_size, s.voxels),
        (0, 0, 1, 16 * 16 * 16)
    );
    assert_eq!(s.histogram.len(), 64);
    assert_eq!(s.histogram.iter().sum::<u64>() + s.nan_count, s.voxels);
    // No TF configured: the default over the first step's range is the histogram's range.
    assert_eq!((s.range_lo, s.range_hi), (s.min, s.max));
    assert!(s.held && s.sigma_bytes > 0 && s.resolution == 32);

    // A trial on the claimed step: σ, τ and q against references at the configured side.
    send(
        &down,
        Down::Hold(pb::HoldRequest {
            step: 0,
            keep: true,
        }),
    );
    let trial = |id, step, r| {
        Down::Trial(pb::TrialRequest {
            precision_bits: None,
            trial_id: id,
            step,
            resolution: r,
            gamma: 0.01,
            size_only: false,
            reuse_probe: false,
        })
    };
    send(&down, trial(1, 0, 24));
    let Up::Trial(r) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert!(r.error.is_empty(), "{}", r.error);
    assert_eq!((r.trial_id, r.step, r.rank, r.resolution), (1, 0, 0, 24));
    assert_eq!((r.view_mse.len(), r.view_q_db.len()), (2, 2));
    assert!(r.sigma_bytes > 0 && r.tau_secs > 0.0 && r.reference_secs > 0.0);
    // At r = reference side and the generation view, the VDI reproduces the DVR (docs/conventions.md).
    assert!(r.view_q_db[0] > 60.0, "{:?}", r.view_q_db);
    send(&down, trial(2, 0, 24));
    let Up::Trial(again) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert_eq!(
        again.reference_secs, 0.0,
        "references are rendered once per step"
    );
    assert_eq!(again.view_mse, r.view_mse, "trials are deterministic");
    // A preview of another transfer function on the claimed step: its window, answered on
    // the stream; one of a step not held, refused with why.
    let preview = |id, step| {
        Down::Preview(pb::PreviewRequest {
            preview_id: id,
            step: Some(step),
            tf: Some(pb::TransferFunction::from(
                &insitu_core::TransferFunction::from_json(
                    r#"{"domain":[0,1],"points":[[0,0,0,1,0],[1,0,0,1,0.9]]}"#,
                    "blue",
                )
                .unwrap(),
            )),
            size: 32,
            ..Default::default()
        })
    };
    send(&down, preview(8, 0));
    let Up::Preview(f) = next(&mut up).await else {
        panic!("expected a preview frame")
    };
    assert!(f.error.is_empty(), "{}", f.error);
    assert_eq!((f.preview_id, f.step, f.rank), (8, 0, 0));
    assert!(f.width > 0 && f.width <= 32 && !f.rgba_zstd.is_empty());
    send(&down, preview(9, 77));
    let Up::Preview(f) = next(&mut up).await else {
        panic!("expected a preview frame")
    };
    assert_eq!(
        (f.preview_id, f.error.as_str()),
        (9, "step 77 is not held here")
    );
    // A size probe: the same σ and supersegments, no views and no scoring.
    // The candidate of the full trials above on step 0, as a size probe or a full trial that
    // may score the VDI the probe left.
    let on_step_0 = |id, size_only, reuse_probe| {
        Down::Trial(pb::TrialRequest {
            trial_id: id,
            resolution: 24,
            gamma: 0.01,
            size_only,
            reuse_probe,
            ..Default::default()
        })
    };
    send(&down, on_step_0(5, true, false));
    let Up::Trial(probe) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert!(probe.error.is_empty(), "{}", probe.error);
    assert_eq!(
        (probe.sigma_bytes, probe.supersegments),
        (r.sigma_bytes, r.supersegments)
    );
    assert!(probe.view_mse.is_empty() && probe.ssim.is_none() && probe.tau_secs > 0.0);
    // A full trial of the probed candidate: scored as before, its σ the probe's, its VDI not
    // encoded again (the compression time is the probe's).
    send(&down, trial(6, 0, 24));
    let Up::Trial(sized) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert!(sized.error.is_empty(), "{}", sized.error);
    assert_eq!(sized.view_mse, r.view_mse, "scored as the full trial");
    assert_eq!(
        (sized.sigma_bytes, sized.supersegments),
        (probe.sigma_bytes, probe.supersegments)
    );
    assert_eq!(sized.tau_compress_secs, probe.tau_compress_secs);
    // A probe again, then a full trial that may score the VDI it left: the same scores, with
    // the probe's σ and τ (nothing generated again).
    send(&down, on_step_0(10, true, false));
    let Up::Trial(second_probe) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    send(&down, on_step_0(11, false, true));
    let Up::Trial(reused) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert!(reused.error.is_empty(), "{}", reused.error);
    assert_eq!(reused.view_mse, r.view_mse, "scored as the full trial");
    assert_eq!(
        (reused.sigma_bytes, reused.supersegments, reused.tau_secs),
        (
            second_probe.sigma_bytes,
            second_probe.supersegments,
            second_probe.tau_secs
        ),
        "σ and τ are the probe's"
    );
    // Each trial's CPU time is counted on the node, and the node's status sums them inside
    // its process's CPU time.
    let trials_cpu = [&r, &again, &probe, &sized, &second_probe, &reused]
        .iter()
        .map(|t| t.trial_cpu_secs)
        .sum::<f64>();
    assert!(
        r.trial_cpu_secs > 0.0 && again.trial_cpu_secs > 0.0 && probe.trial_cpu_secs > 0.0,
        "{} {} {}",
        r.trial_cpu_secs,
        again.trial_cpu_secs,
        probe.trial_cpu_secs
    );
    let status = client.status().await.unwrap();
    assert!(
        (status.trial_cpu_secs - trials_cpu).abs() < 1e-9 && status.cpu_secs > trials_cpu,
        "status {} of {} s, trials {trials_cpu}",
        status.trial_cpu_secs,
        status.cpu_secs
    );

    // A burst beyond the node's trial backlog: every trial gets exactly one answer, a result
    // or a refusal that says the backlog is full (none is queued without bound or lost).
    let burst = 200u64;
    for id in 100..100 + burst {
        send(
            &down,
            Down::Trial(pb::TrialRequest {
                precision_bits: None,
                trial_id: id,
                step: 0,
                resolution: 16,
                gamma: 0.01,
                size_only: true,
                reuse_probe: false,
            }),
        );
    }
    let mut answered = std::collections::BTreeSet::new();
    let mut busy = 0;
    while answered.len() < burst as usize {
        let Up::Trial(t) = next(&mut up).await else {
            panic!("expected a trial result")
        };
        assert!(
            answered.insert(t.trial_id),
            "trial {} answered twice",
            t.trial_id
        );
        if !t.error.is_empty() {
            assert!(t.error.contains("trials already wait"), "{}", t.error);
            busy += 1;
        }
    }
    assert_eq!(answered, (100..100 + burst).collect());
    eprintln!("burst of {burst} trials: {busy} refused as over the backlog");

    // A step the node does not hold: refused with a reason, the stream stays up.
    send(&down, trial(3, 7, 24));
    let Up::Trial(refused) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert!(refused.not_held);
    assert!(
        refused.error.contains("step 7 is not held"),
        "{}",
        refused.error
    );
    send(
        &down,
        Down::Hold(pb::HoldRequest {
            step: 0,
            keep: false,
        }),
    );
    send(&down, trial(4, 0, 24));
    let Up::Trial(released) = next(&mut up).await else {
        panic!("expected a trial result")
    };
    assert!(released.error.contains("not held"), "{}", released.error);

    // A decision: applied from the next step and stamped; an older one is refused.
    let decision = |v, r| {
        Down::Decision(pb::PmDecision {
            pm_version: v,
            resolution: r,
            gamma: 0.02,
            ..Default::default()
        })
    };
    send(&down, decision(3, 20));
    let Up::Ack(ack) = next(&mut up).await else {
        panic!("expected an ack")
    };
    assert_eq!((ack.pm_version, ack.error.as_str()), (3, ""));
    send(&down, decision(2, 40));
    let Up::Ack(ack) = next(&mut up).await else {
        panic!("expected an ack")
    };
    assert!(ack.error.contains("not newer"), "{}", ack.error);
    send(&down, decision(4, 0));
    let Up::Ack(ack) = next(&mut up).await else {
        panic!("expected an ack")
    };
    assert!(!ack.error.is_empty(), "r = 0 is refused");
    let st = node.shared().status();
    assert_eq!((st.pm_version, st.resolution, st.gamma), (3, 20, 0.02));
    client.push_step(push(1)).await.unwrap();
    let Up::Summary(s) = next(&mut up).await else {
        panic!("expected a summary")
    };
    assert_eq!(
        (s.step, s.pm_version, s.resolution, s.gamma),
        (1, 3, 20, 0.02)
    );
    node.shutdown().await;
}

/// Pushes rank `rank` of step `t` of a 16³ field cut in two z-bricks (sharing a plane) and
/// returns the version and r its summary reports.
async fn made(
    client: &mut insitu_client::SimClient,
    up: &mut mpsc::Receiver<pb::NodeMessage>,
    t: u64,
    rank: u32,
) -> (u64, u32) {
    let whole = field(16, t);
    // z 0–8 and 8–15: the halves share the plane z = 8.
    let (z0, nz) = (8 * rank as usize, 9 - rank as usize);
    let step = insitu_client::Step {
        step: t,
        sim_time: t as f64,
        dtype: insitu_client::ScalarType::F32,
        global_dims: [16, 16, 16],
        brick_offset: [0, 0, z0 as u32],
        brick_dims: [16, 16, nz as u32],
        rank,
        world_size: 2,
        spacing: [1.0; 3],
        origin: [0.0; 3],
        data: insitu_client::f32_bytes(&whole[z0 * 256..(z0 + nz) * 256]),
        fields: Vec::new(),
    };
    client.push_step(step).await.unwrap();
    let Up::Summary(s) = next(up).await else {
        panic!("expected a summary")
    };
    assert_eq!((s.step, s.rank), (t, rank));
    (s.pm_version, s.resolution)
}

/// Every rank of a step is made with one P_M, whatever the moment a decision arrives: a node
/// applies it from the first step no rank of which it has begun, or from the decision's
/// `from_step` when that is later (the viz-node composes only ranks that agree).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_decision_applies_from_a_step_boundary_for_every_rank() {
    let (node, mut up, down, _) = scripted_node().await;
    let mut client = insitu_client::SimClient::connect(&node.local_addr().to_string(), None)
        .await
        .unwrap();
    let decide = |v: u64, r: u32, from_step: u64| {
        Down::Decision(pb::PmDecision {
            pm_version: v,
            resolution: r,
            gamma: 0.02,
            from_step,
            ..Default::default()
        })
    };
    assert_eq!(made(&mut client, &mut up, 0, 0).await, (0, 32));
    // v1 arrives between the ranks of step 0 (its from_step already past): rank 1 of step 0
    // keeps r = 32, step 1 takes it.
    send(&down, decide(1, 24, 0));
    let Up::Ack(ack) = next(&mut up).await else {
        panic!("expected an ack")
    };
    assert_eq!((ack.pm_version, ack.error.as_str()), (1, ""));
    assert_eq!(made(&mut client, &mut up, 0, 1).await, (0, 32));
    assert_eq!(made(&mut client, &mut up, 1, 0).await, (1, 24));
    // v2 from step 3: steps 1 and 2 keep v1 on both ranks.
    send(&down, decide(2, 40, 3));
    let Up::Ack(_) = next(&mut up).await else {
        panic!("expected an ack")
    };
    assert_eq!(made(&mut client, &mut up, 1, 1).await, (1, 24));
    assert_eq!(made(&mut client, &mut up, 2, 0).await, (1, 24));
    assert_eq!(made(&mut client, &mut up, 2, 1).await, (1, 24));
    assert_eq!(made(&mut client, &mut up, 3, 0).await, (2, 40));
    assert_eq!(made(&mut client, &mut up, 3, 1).await, (2, 40));
    node.shutdown().await;
}
