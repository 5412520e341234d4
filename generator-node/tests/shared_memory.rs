#![allow(clippy::unwrap_used, clippy::expect_used)]

//! Steps pushed through shared memory by a client on the node's host: taken and counted as
//! such, the client's file kept between pushes and removed with the client; a node without a
//! shared-memory directory, or a client kept to streaming, streams; what the node refuses.

use insitu_client::{SimClient, Step};
use insitu_generator_node::{start, Config, RunningNode};
use insitu_proto::pb;
use insitu_proto::pb::generator_client::GeneratorClient;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

async fn node(shared_memory_dir: Option<&Path>) -> RunningNode {
    let mut cfg = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        backend: insitu_core::BackendChoice::Cpu,
        shared_memory_dir: shared_memory_dir.map(Path::to_owned),
        ..Default::default()
    };
    cfg.generation.resolution = 16;
    cfg.generation.reference_every = 0;
    start(cfg).await.unwrap()
}

fn field(n: usize, k: u64) -> Vec<f32> {
    (0..n * n * n)
        .map(|i| ((i as u64 + k) % 17) as f32)
        .collect()
}

/// The `insitu-…` files in `dir`.
fn files(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("insitu-"))
        .collect()
}

#[tokio::test]
async fn a_client_on_the_node_s_host_pushes_through_shared_memory() {
    if insitu_client::shm::host_id().is_none() {
        eprintln!("skipped: shared memory is for Linux only");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let node = node(Some(dir.path())).await;
    let addr = node.local_addr().to_string();
    let mut client = SimClient::connect(&addr, None).await.unwrap();
    assert_eq!(
        client.shared_memory(),
        None,
        "not known before the first push"
    );
    // The simulation's buffer, reused push after push: the client lets go of it each time.
    let mut staging = Arc::new(Vec::new());
    for k in 0..3 {
        let n = if k == 2 { 10 } else { 12 }; // a smaller step over a larger one
        let buffer = Arc::get_mut(&mut staging).expect("the last push let go");
        buffer.clear();
        buffer.extend(field(n, k));
        client
            .push_step(Step::whole_f32_shared(
                k,
                0.0,
                [n as u32; 3],
                staging.clone(),
            ))
            .await
            .unwrap();
    }
    assert!(Arc::get_mut(&mut staging).is_some());
    assert_eq!(client.shared_memory(), Some(true));
    assert_eq!(files(dir.path()).len(), 1, "one file, written over");
    let status = client.flush(Duration::from_secs(60)).await.unwrap();
    assert_eq!((status.steps_received, status.shared_pushes), (3, 3));
    assert_eq!(status.steps_generated, 3);
    assert_eq!(status.failed, 0);
    assert_eq!(
        Path::new(&status.shared_memory_dir),
        dir.path().canonicalize().unwrap()
    );
    assert_eq!(
        Some(status.host_id.as_str()),
        insitu_client::shm::host_id().as_deref()
    );

    // A client kept to streaming streams.
    let mut streaming = SimClient::connect(&addr, None).await.unwrap();
    streaming.set_shared_memory(false);
    let mut staging = Arc::new(field(12, 3));
    streaming
        .push_step(Step::whole_f32_shared(3, 0.0, [12; 3], staging.clone()))
        .await
        .unwrap();
    assert!(
        Arc::get_mut(&mut staging).is_some(),
        "a streamed push lets go of the buffer too"
    );
    assert_eq!(streaming.shared_memory(), Some(false));
    let status = streaming.flush(Duration::from_secs(60)).await.unwrap();
    assert_eq!((status.steps_received, status.shared_pushes), (4, 3));

    drop(client);
    assert!(
        files(dir.path()).is_empty(),
        "the file goes with its client"
    );
    node.shutdown().await;
}

#[tokio::test]
async fn a_node_without_shared_memory_is_streamed_to() {
    let node = node(None).await;
    let addr = node.local_addr().to_string();
    let mut client = SimClient::connect(&addr, None).await.unwrap();
    client
        .push_step(Step::whole_f32(0, 0.0, [12; 3], &field(12, 0)))
        .await
        .unwrap();
    assert_eq!(client.shared_memory(), Some(false));
    let status = client.flush(Duration::from_secs(60)).await.unwrap();
    assert_eq!((status.steps_received, status.shared_pushes), (1, 0));
    assert!(status.shared_memory_dir.is_empty());

    // Asked directly, it says why and that streaming is the way.
    let mut raw = GeneratorClient::connect(format!("http://{addr}"))
        .await
        .unwrap();
    let e = raw
        .push_shared(pb::SharedStep::default())
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition);
    assert!(e.message().contains("stream the step"), "{}", e.message());
    node.shutdown().await;
}

/// A file the node may not use is refused, naming it, and nothing is received; a header
/// that is bad or too large is refused before any file is opened.
#[tokio::test]
async fn what_the_node_refuses_it_names_and_receives_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let node = node(Some(dir.path())).await;
    let mut raw = GeneratorClient::connect(format!("http://{}", node.local_addr()))
        .await
        .unwrap();
    let d = |n| Some(pb::Dims3 { x: n, y: n, z: n });
    let header = |total_bytes| pb::StepHeader {
        dtype: pb::ScalarType::F32 as i32,
        global_dims: d(4),
        brick_offset: d(0),
        brick_dims: d(4),
        world_size: 1,
        total_bytes,
        ..Default::default()
    };
    let path = dir.path().join("insitu-short");
    std::fs::write(&path, [0u8; 100]).unwrap();
    let push = |h: Option<pb::StepHeader>, path: &Path| pb::SharedStep {
        header: h,
        path: path.display().to_string(),
    };
    for (request, code, says) in [
        (
            push(Some(header(256)), &path),
            tonic::Code::FailedPrecondition,
            "100 bytes where the header says 256",
        ),
        (
            push(Some(header(256)), Path::new("/etc/passwd")),
            tonic::Code::FailedPrecondition,
            "must start with \"insitu-\"",
        ),
        (
            push(None, &path),
            tonic::Code::InvalidArgument,
            "without a header",
        ),
        (
            push(Some(header(100)), &path),
            tonic::Code::InvalidArgument,
            "total_bytes",
        ),
        (
            push(Some(header(1 << 40)), &path),
            tonic::Code::ResourceExhausted,
            "limit",
        ),
    ] {
        let e = raw.push_shared(request).await.unwrap_err();
        assert_eq!(e.code(), code, "{}", e.message());
        assert!(e.message().contains(says), "{says}: {}", e.message());
    }
    let status = raw
        .get_status(pb::StatusRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!((status.steps_received, status.shared_pushes), (0, 0));
    assert!(path.exists(), "the node leaves the client's file alone");
    node.shutdown().await;
}
