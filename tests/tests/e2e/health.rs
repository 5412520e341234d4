//! gRPC health checking on the three daemons (tonic-health, for readiness): each
//! answers `SERVING` for itself and its named service from its first connection on, without a
//! token; `insitu health` waits for that and says what it got otherwise; and on SIGTERM a
//! watcher sees `NOT_SERVING`, then its stream ends, and the daemon exits (an open watch does
//! not hold up the shutdown).

use crate::common::{free_port, generator, viz};
use insitu_e2e::{bin, rt, wait_until};
use std::process::Command;
use tokio_stream::StreamExt;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

/// `insitu health ARGS…`: (exit success, stdout, stderr).
fn health(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(bin("insitu"))
        .arg("health")
        .args(args)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn every_daemon_reports_serving_and_a_watcher_sees_the_shutdown() {
    let tmp = tempfile::tempdir().unwrap();
    let logs = tmp.path();
    let v = viz(&logs.join("rec"), "127.0.0.1:0", logs);
    let t = crate::tuned::tuner(
        &logs.join("state"),
        "127.0.0.1:0",
        &v.addr,
        "size:1MB",
        logs,
    );
    let g = generator(
        &format!(
            "listen = \"127.0.0.1:0\"\nviz = \"{}\"\ntuner = \"{}\"\nbackend = \"cpu\"\n",
            v.addr, t.addr
        ),
        logs,
        &[],
    );
    for (addr, service) in [
        (&g.addr, "insitu.v1.Generator"),
        (&v.addr, "insitu.v1.Viz"),
        (&t.addr, "insitu.v1.Tuner"),
    ] {
        for s in ["", service] {
            let (ok, out, err) = health(&[addr, "--service", s, "--wait", "10"]);
            assert!(ok && out.trim() == "SERVING", "{addr} {s:?}: {out} {err}");
        }
    }
    // A service the daemon does not have: named in the error, at once even with --wait.
    let (ok, _, err) = health(&[&g.addr, "--service", "insitu.v1.Viz", "--wait", "10"]);
    assert!(!ok && err.contains("insitu.v1.Viz"), "{err}");

    // A watch opened before SIGTERM: SERVING, NOT_SERVING, then the end of the stream.
    let statuses = rt().block_on(async {
        let channel = insitu_proto::transport::connect(&insitu_proto::transport::uri(&g.addr))
            .await
            .unwrap();
        let mut watch = HealthClient::new(channel)
            .watch(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .unwrap()
            .into_inner();
        let mut seen = vec![watch.next().await.unwrap().unwrap().status()];
        g.signal("TERM");
        let rest = tokio::time::timeout(std::time::Duration::from_secs(30), async {
            while let Some(Ok(m)) = watch.next().await {
                seen.push(m.status());
            }
        })
        .await;
        assert!(rest.is_ok(), "the watch stream did not end: {seen:?}");
        seen
    });
    assert_eq!(
        statuses,
        [ServingStatus::Serving, ServingStatus::NotServing],
        "the watcher's statuses"
    );
    let mut g = g;
    assert!(
        wait_until(30.0, || g.child.try_wait().unwrap().is_some()),
        "the generator-node exits although a watcher was connected"
    );
    let (ok, _, err) = health(&[&g.addr]);
    assert!(!ok && err.contains("no daemon answers"), "{err}");

    // Nothing there at all: --wait gives up and says how long it waited.
    let nothing = format!("127.0.0.1:{}", free_port());
    let (ok, _, err) = health(&[&nothing, "--wait", "0.5"]);
    assert!(!ok && err.contains("was not SERVING within 0.5 s"), "{err}");
    t.terminate();
    v.terminate();
}
