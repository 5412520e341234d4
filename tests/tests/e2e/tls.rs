//! TLS: the daemons off loopback with a token and TLS, mutual TLS on every
//! link (simulation → generator-node → viz-node), certificates from a throw-away CA made here
//! with rcgen; and what is refused: clear text to a TLS node, a server certificate from
//! another CA, a client without a certificate or with one from another CA, a wrong token, and
//! an off-loopback bind without TLS unless `insecure = true`.

use crate::common::{field, index};
use insitu_client::{BearerToken, Peer, SimClient, Step, TlsFiles};
use insitu_e2e::{rt, Daemon};
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, IsCa, KeyPair, KeyUsagePurpose,
};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A CA and PEM files of certificates it signed.
struct Ca {
    issuer: CertifiedIssuer<'static, KeyPair>,
    pem: PathBuf,
}

impl Ca {
    fn new(dir: &Path, name: &str) -> Self {
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        p.distinguished_name.push(DnType::CommonName, name);
        p.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let issuer = CertifiedIssuer::self_signed(p, KeyPair::generate().unwrap()).unwrap();
        let pem = dir.join(format!("{name}.pem"));
        std::fs::write(&pem, issuer.pem()).unwrap();
        Self { issuer, pem }
    }

    /// A leaf for `names` (host names or IP addresses): (certificate, key) files.
    fn leaf(&self, dir: &Path, name: &str, names: &[&str]) -> (PathBuf, PathBuf) {
        let key = KeyPair::generate().unwrap();
        let names: Vec<String> = names.iter().map(|s| (*s).to_owned()).collect();
        let mut p = CertificateParams::new(names).unwrap();
        p.distinguished_name.push(DnType::CommonName, name);
        let cert = p.signed_by(&key, &self.issuer).unwrap();
        let (c, k) = (
            dir.join(format!("{name}.crt")),
            dir.join(format!("{name}.key")),
        );
        std::fs::write(&c, cert.pem()).unwrap();
        std::fs::write(&k, key.serialize_pem()).unwrap();
        (c, k)
    }
}

fn path(p: &Path) -> String {
    p.to_string_lossy().replace('\\', "/")
}

/// `0.0.0.0:PORT` as printed → `127.0.0.1:PORT`, the name in the certificates.
fn loopback(addr: &str) -> String {
    addr.replace("0.0.0.0", "127.0.0.1")
}

fn start(name: &str, toml: &str, dir: &Path) -> Daemon {
    let cfg = dir.join(format!("{name}.toml"));
    std::fs::write(&cfg, toml).unwrap();
    Daemon::start(name, &["--config", cfg.to_str().unwrap()], &[], dir)
}

fn client_tls(ca: &Path, id: Option<&(PathBuf, PathBuf)>) -> TlsFiles {
    TlsFiles {
        ca_file: Some(ca.to_owned()),
        cert_file: id.map(|i| i.0.clone()),
        key_file: id.map(|i| i.1.clone()),
        client_auth: false,
    }
}

/// The node's status through `peer`, or why not. A refusal may also be no answer: under TLS
/// 1.3 the client finishes its handshake before the server checks its certificate, and the
/// server's alert can go unread, so the call is bounded.
fn status_with(peer: Peer) -> Result<insitu_client::GeneratorStatus, String> {
    rt().block_on(async {
        let call = async {
            let mut c = SimClient::connect_with(peer)
                .await
                .map_err(|e| e.to_string())?;
            c.status().await.map_err(|e| e.to_string())
        };
        tokio::time::timeout(Duration::from_secs(20), call)
            .await
            .unwrap_or_else(|_| Err("no answer within 20 s".into()))
    })
}

#[test]
fn every_link_is_mutual_tls_off_loopback_and_what_lacks_a_part_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let ca = Ca::new(d, "ca");
    let rogue = Ca::new(d, "rogue-ca");
    let node = ca.leaf(d, "node", &["127.0.0.1", "localhost"]);
    let sim = ca.leaf(d, "sim", &["simulation"]);
    let rogue_sim = rogue.leaf(d, "rogue-sim", &["simulation"]);
    let token_file = d.join("token");
    std::fs::write(&token_file, "tls-test-token").unwrap();
    let token = BearerToken::new("tls-test-token", "test").unwrap();
    let tls_table = format!(
        "[tls]\ncert_file = \"{}\"\nkey_file = \"{}\"\nca_file = \"{}\"\nclient_auth = true\n",
        path(&node.0),
        path(&node.1),
        path(&ca.pem)
    );

    let viz = start(
        "viz-node",
        &format!(
            "listen = \"0.0.0.0:0\"\nrecording_dir = \"{}\"\ntoken_file = \"{}\"\nbackend = \"cpu\"\n{tls_table}",
            path(&d.join("rec")),
            path(&token_file)
        ),
        d,
    );
    // The generator-node dials the viz-node over TLS (ca_file) with its own certificate.
    let gen = start(
        "generator-node",
        &format!(
            r#"listen = "0.0.0.0:0"
viz = "{}"
token_file = "{}"
backend = "cpu"
max_backoff_secs = 0.2
[generation]
resolution = 32
reference_every = 2
{tls_table}"#,
            loopback(&viz.addr),
            path(&token_file)
        ),
        d,
    );
    let g = loopback(&gen.addr);

    // The simulation, with its certificate: steps reach the recording, scored.
    let pushed = async {
        let tls = client_tls(&ca.pem, Some(&sim)).client().unwrap();
        let peer = Peer::new(&g, Some(token.clone()), tls, false).unwrap();
        assert!(peer.uri().starts_with("https://"));
        let mut c = SimClient::connect_with(peer).await.unwrap();
        for s in 0..4 {
            c.push_step(Step::whole_f32(s, s as f64, [16; 3], &field(16, s)))
                .await
                .unwrap();
        }
        let st = c.flush(Duration::from_secs(120)).await.unwrap();
        assert_eq!((st.steps_shipped, st.failed), (4, 0));
    };
    rt().block_on(async { tokio::time::timeout(Duration::from_secs(180), pushed).await })
        .expect("four steps pushed and flushed over mutual TLS within 180 s");
    let rec = d.join("rec");
    let ok = insitu_e2e::wait_until(60.0, || {
        let e = index(&rec);
        e.len() == 4 && e.iter().filter(|e| e.quality.is_some()).count() == 2
    });
    assert!(ok, "stored over TLS and scored: {:?}", index(&rec));

    let with = |tls: TlsFiles, token: Option<BearerToken>| {
        status_with(Peer::new(&g, token, tls.client().unwrap(), false).unwrap())
    };
    // Clear text to a TLS node.
    let e = status_with(Peer::new(&g, Some(token.clone()), None, false).unwrap()).unwrap_err();
    assert!(!e.is_empty());
    // The node's certificate is not from the CA the client trusts.
    let e = with(client_tls(&rogue.pem, Some(&sim)), Some(token.clone())).unwrap_err();
    assert!(e.to_lowercase().contains("certificate"), "{e}");
    // Mutual TLS: no client certificate, or one from another CA.
    assert!(with(client_tls(&ca.pem, None), Some(token.clone())).is_err());
    assert!(with(client_tls(&ca.pem, Some(&rogue_sim)), Some(token.clone())).is_err());
    // TLS is not a substitute for the token.
    let e = with(
        client_tls(&ca.pem, Some(&sim)),
        Some(BearerToken::new("wrong", "t").unwrap()),
    )
    .unwrap_err();
    assert!(e.contains("Unauthenticated"), "{e}");
    // …nor the other way round, and the right pair still works.
    assert!(with(client_tls(&ca.pem, Some(&sim)), None).is_err());
    let st = with(client_tls(&ca.pem, Some(&sim)), Some(token.clone())).unwrap();
    assert_eq!(st.steps_shipped, 4);
    // The health check over mutual TLS needs no token; without a client certificate, or in
    // clear text, it gets no answer.
    let health = |extra: &[&str]| {
        std::process::Command::new(insitu_e2e::bin("insitu"))
            .args(["health", &g])
            .args(extra)
            .env_remove("INSITU_TOKEN")
            .output()
            .unwrap()
    };
    let (ca_pem, sim_crt, sim_key) = (path(&ca.pem), path(&sim.0), path(&sim.1));
    let out = health(&[
        "--tls-ca",
        &ca_pem,
        "--tls-cert",
        &sim_crt,
        "--tls-key",
        &sim_key,
    ]);
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "SERVING",
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for extra in [
        &["--wait", "1", "--tls-ca", ca_pem.as_str()][..],
        &["--wait", "1"][..],
    ] {
        let out = health(extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("was not SERVING within 1 s"),
            "{extra:?}: {err}"
        );
    }
    // A token never goes in clear text to a host that is not loopback.
    let e = Peer::new("10.255.255.1:1", Some(token), None, false).unwrap_err();
    assert!(e.to_string().contains("clear text"), "{e}");

    gen.terminate();
    viz.terminate();
}

#[test]
fn off_loopback_without_tls_needs_insecure_and_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let token_file = d.join("token");
    std::fs::write(&token_file, "t0ken").unwrap();
    let cfg = |extra: &str| {
        let p = d.join(format!("viz-{}.toml", extra.len()));
        std::fs::write(
            &p,
            format!(
                "listen = \"0.0.0.0:0\"\nrecording_dir = \"{}\"\ntoken_file = \"{}\"\n{extra}",
                path(&d.join("rec")),
                path(&token_file)
            ),
        )
        .unwrap();
        p
    };
    let out = std::process::Command::new(insitu_e2e::bin("viz-node"))
        .arg("--config")
        .arg(cfg(""))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("without TLS") && err.contains("insecure"),
        "{err}"
    );

    let v = insitu_e2e::Daemon::start(
        "viz-node",
        &["--config", cfg("insecure = true\n").to_str().unwrap()],
        &[],
        d,
    );
    let log = v.log.clone();
    v.terminate();
    let log = std::fs::read_to_string(log).unwrap();
    assert!(log.contains("INSECURE") && log.contains("TLS"), "{log}");
}

/// One HTTPS GET, verifying the server against `ca`; the status code and the body.
fn https_get(addr: &str, ca: &Path, target: &str, headers: &[&str]) -> (u16, String) {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, ServerName};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    rt().block_on(async {
        let mut roots = rustls::RootCertStore::empty();
        for c in CertificateDer::pem_file_iter(ca).unwrap() {
            roots.add(c.unwrap()).unwrap();
        }
        let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
        let cfg = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .unwrap()
            .with_root_certificates(roots)
            .with_no_client_auth();
        let connector = tokio_rustls::TlsConnector::from(std::sync::Arc::new(cfg));
        let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
        let name = ServerName::try_from("127.0.0.1").unwrap();
        let mut tls = connector.connect(name, tcp).await.unwrap();
        let mut req = format!("GET {target} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
        for h in headers {
            req.push_str(h);
            req.push_str("\r\n");
        }
        req.push_str("\r\n");
        tls.write_all(req.as_bytes()).await.unwrap();
        let mut out = Vec::new();
        let _ = tls.read_to_end(&mut out).await;
        insitu_e2e::parse_http_response(&out)
    })
}

#[test]
fn the_web_viewer_serves_https_with_the_node_certificate_and_still_needs_the_token() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let ca = Ca::new(d, "ca");
    let (cert, key) = ca.leaf(d, "viz", &["127.0.0.1"]);
    let token_file = d.join("token");
    std::fs::write(&token_file, "t0ken").unwrap();
    let mut v = start(
        "viz-node",
        &format!(
            "listen = \"0.0.0.0:0\"\nhttp_listen = \"0.0.0.0:0\"\nrecording_dir = \"{}\"\ntoken_file = \"{}\"\n[tls]\ncert_file = \"{}\"\nkey_file = \"{}\"\n",
            path(&d.join("rec")),
            path(&token_file),
            path(&cert),
            path(&key)
        ),
        d,
    );
    let line = v.read_line();
    let url = line
        .strip_prefix("web viewer on https://")
        .unwrap_or_else(|| panic!("{line}"));
    let addr = loopback(url.trim_end_matches('/'));
    let (code, body) = https_get(
        &addr,
        &ca.pem,
        "/api/steps",
        &["Authorization: Bearer t0ken"],
    );
    assert!(code == 200 && body.contains("\"steps\""), "{code} {body}");
    let (code, body) = https_get(&addr, &ca.pem, "/?token=t0ken", &[]);
    assert!(code == 200 && body.contains("app.js"), "{code}");
    let (code, _) = https_get(&addr, &ca.pem, "/api/steps", &[]);
    assert_eq!(code, 401, "TLS does not replace the token");
    // Clear text to the HTTPS port gets no HTTP answer.
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    use std::io::{Read, Write};
    s.write_all(b"GET /api/steps HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .unwrap();
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    assert!(!out.starts_with(b"HTTP/1.1 200"), "clear text was served");
}
