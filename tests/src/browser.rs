//! Headless Chromium over WebDriver (Debian's `chromium` and `chromium-driver`), for the web
//! viewer's browser test and latency benchmark.

use fantoccini::{Client, ClientBuilder};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// Where screenshots are kept after the test.
pub fn artefacts() -> PathBuf {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/test-artifacts");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// chromedriver on a free port; killed on drop.
pub struct Driver(Child, u16);

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// chromedriver started, or `None` (the test skips) where Chromium or its driver is missing.
pub fn start_driver() -> Option<Driver> {
    use insitu_testenv::{file, Need};
    file(Path::new(CHROMIUM), Need::Browser)?;
    file(Path::new(CHROMEDRIVER), Need::Browser)?;
    let port = crate::free_port();
    let child = Command::new(CHROMEDRIVER)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting chromedriver");
    let up = crate::wait_until(20.0, || {
        std::net::TcpStream::connect(("127.0.0.1", port)).is_ok()
    });
    assert!(up, "chromedriver did not listen on {port}");
    Some(Driver(child, port))
}

pub async fn browser(driver: &Driver, profile: &Path) -> Client {
    let caps = json!({
        "goog:chromeOptions": {
            "binary": CHROMIUM,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run",
                "--window-size=1280,900",
                format!("--user-data-dir={}", profile.display()),
            ]
        }
    });
    let serde_json::Value::Object(caps) = caps else {
        unreachable!()
    };
    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{}", driver.1))
        .await
        .expect("connecting to chromedriver")
}

/// Runs `script` (which calls `done(value)`) in the page and returns the value.
pub async fn js(c: &Client, script: &str) -> Value {
    let body = format!("const done = arguments[arguments.length - 1]; (async () => {{ {script} }})().catch(e => done({{error: String(e)}}));");
    c.execute_async(&body, vec![]).await.expect("script")
}
