//! `insitu steer`: changes the running scene (transfer function, field, generation camera,
//! sample distance, shading) or the tuner's utility through a viz-node's steering API (`POST /api/steer`,
//! docs/steering.md), or shows the scene in force and the steering history (`--show`).

use anyhow::{bail, Context, Result};
use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper_util::client::legacy::Client;
use hyper_util::rt::TokioExecutor;
use insitu_core::TransferFunction;
use insitu_viz_node::http::steer::{CameraBody, SteerBody};
use insitu_viz_node::node::STEER_TOKEN_ENV;
use serde_json::Value;
use std::path::PathBuf;
use std::time::Duration;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The viz-node's web viewer: `host:port` or `http://host:port` (plain HTTP, e.g. through
    /// an SSH tunnel; for an HTTPS viewer use curl, docs/steering.md).
    #[arg(long)]
    viz: String,
    /// Transfer function file (docs/conventions.md format) to make the VDIs with from now on.
    #[arg(long)]
    tf: Option<PathBuf>,
    /// Its name in the VDIs' metadata (default: the file's stem).
    #[arg(long, requires = "tf")]
    tf_name: Option<String>,
    /// The field to render, by name (one the steps carry).
    #[arg(long)]
    field: Option<String>,
    /// The generation camera: `EX,EY,EZ:TX,TY,TZ` (eye and target, world units; +y up, 30°
    /// field of view), or `view:ANGLE,ELEVATION[,ZOOM]` (the newest stored step's generation
    /// camera orbited as the viewer orbits it: "generate from here").
    #[arg(long)]
    camera: Option<String>,
    /// The tuner's utility, e.g. `size:1MB`, `time:0.5s`, `quality:40dB`.
    #[arg(long)]
    utility: Option<String>,
    /// The ray-casting sample distance, world units (finer: better q, longer τ).
    #[arg(long, value_parser = sample_distance)]
    sample_distance: Option<f32>,
    /// Refused with a message naming `--sample-distance` (a step is a time step).
    #[arg(long = "step", hide = true, value_parser = refused_step)]
    old_step: Option<f32>,
    /// Gradient shading `on` or `off` (off: emission–absorption only).
    #[arg(long, value_parser = clap::builder::BoolishValueParser::new())]
    shading: Option<bool>,
    /// File holding the steering token (else INSITU_STEER_TOKEN).
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Print the scene in force and the steering history; change nothing.
    #[arg(long, conflicts_with_all = ["tf", "field", "camera", "utility", "sample_distance", "shading"])]
    show: bool,
}

/// `--step`, always refused: the flag is `--sample-distance`.
fn refused_step(_: &str) -> Result<f32, String> {
    Err("--step is not a steering flag: the ray-casting sample distance is --sample-distance (world units)".into())
}

/// A sample distance as given: a finite length > 0 (NaN would cross the wire as JSON `null`,
/// which reads as "no change").
fn sample_distance(text: &str) -> Result<f32, String> {
    match text.trim().parse::<f32>() {
        Ok(d) if d.is_finite() && d > 0.0 => Ok(d),
        _ => Err("the sample distance must be a finite length > 0, in world units".into()),
    }
}

/// Sends the change and prints the tuner's answer (scene version, decision, first step made
/// with it, versions superseded) as JSON; or, with `--show`, the scene.
pub fn run(a: Args) -> Result<()> {
    let base = base_url(&a.viz)?;
    let token = token(a.token_file.as_ref())?;
    let (method, path, body) = if a.show {
        ("GET", "/api/scene", None)
    } else {
        ("POST", "/api/steer", Some(body(&a)?))
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let (status, text) = rt.block_on(call(method, &format!("{base}{path}"), token, body))?;
    let v: Value = serde_json::from_str(&text)
        .with_context(|| format!("{base}{path} answered {status} with {text:?}"))?;
    if !(200..300).contains(&status) {
        let why = v["error"].as_str().unwrap_or(&text);
        bail!("{base}{path}: {status}: {why}");
    }
    println!("{}", serde_json::to_string_pretty(&v)?);
    Ok(())
}

/// `http://host:port` from `host:port` or the URL itself.
fn base_url(viz: &str) -> Result<String> {
    if viz.starts_with("https://") {
        bail!("--viz {viz}: `insitu steer` speaks plain HTTP; steer an HTTPS viewer with curl (docs/steering.md)");
    }
    let url = if viz.starts_with("http://") {
        viz.trim_end_matches('/').to_owned()
    } else {
        format!("http://{viz}")
    };
    url.parse::<hyper::Uri>()
        .with_context(|| format!("--viz {viz}: not host:port or http://host:port"))?;
    Ok(url)
}

fn token(file: Option<&PathBuf>) -> Result<Option<String>> {
    let raw = match file {
        Some(f) => Some(
            std::fs::read_to_string(f).with_context(|| format!("--token-file {}", f.display()))?,
        ),
        None => std::env::var(STEER_TOKEN_ENV).ok(),
    };
    Ok(raw.map(|t| t.trim().to_owned()).filter(|t| !t.is_empty()))
}

/// The request's body: the viewer's own type, the transfer function read and checked here.
fn body(a: &Args) -> Result<SteerBody> {
    let mut b = SteerBody::default();
    if let Some(path) = &a.tf {
        b.tf = Some(TransferFunction::load(path).context("--tf")?);
        b.tf_name = a
            .tf_name
            .clone()
            .or_else(|| path.file_stem().map(|s| s.to_string_lossy().into_owned()));
    }
    b.field.clone_from(&a.field);
    b.camera = a.camera.as_deref().map(camera).transpose()?;
    b.utility.clone_from(&a.utility);
    b.sample_distance = a.sample_distance;
    b.shading = a.shading;
    if b.is_empty() {
        bail!("nothing to steer: give --tf, --field, --camera, --sample-distance, --shading or --utility (or --show)");
    }
    Ok(b)
}

/// `--camera` as the API takes it.
fn camera(s: &str) -> Result<CameraBody> {
    let numbers = |t: &str| -> Result<Vec<f32>> {
        t.split(',')
            .map(|x| {
                x.trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .with_context(|| format!("--camera {s}: {x:?} is not a finite number"))
            })
            .collect()
    };
    if let Some(view) = s.strip_prefix("view:") {
        let v = numbers(view)?;
        let (angle, elevation, zoom) = match v[..] {
            [angle, elevation] => (angle, elevation, 1.0),
            [angle, elevation, zoom] => (angle, elevation, zoom),
            _ => bail!("--camera {s}: view:ANGLE,ELEVATION[,ZOOM]"),
        };
        return Ok(CameraBody::View {
            step: None,
            angle,
            elevation,
            zoom,
        });
    }
    let Some((eye, target)) = s.split_once(':') else {
        bail!("--camera {s}: EX,EY,EZ:TX,TY,TZ or view:ANGLE,ELEVATION[,ZOOM]");
    };
    match (&numbers(eye)?[..], &numbers(target)?[..]) {
        (&[ex, ey, ez], &[tx, ty, tz]) => Ok(CameraBody::Explicit {
            eye: [ex, ey, ez],
            target: [tx, ty, tz],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 30.0,
        }),
        _ => bail!("--camera {s}: eye and target take three numbers each"),
    }
}

/// One HTTP request; the status and the body's text.
async fn call(
    method: &str,
    url: &str,
    token: Option<String>,
    body: Option<SteerBody>,
) -> Result<(u16, String)> {
    let client = Client::builder(TokioExecutor::new()).build_http::<Full<Bytes>>();
    let mut req = hyper::Request::builder()
        .method(method)
        .uri(url)
        .header("content-type", "application/json");
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    let bytes = match body {
        Some(b) => Bytes::from(serde_json::to_vec(&b)?),
        None => Bytes::new(),
    };
    if bytes.len() > insitu_viz_node::http::MAX_BODY_BYTES {
        bail!(
            "the request is {} bytes (its transfer function, as JSON): the viewer takes at most {} (a transfer function has a few hundred control points at most)",
            bytes.len(),
            insitu_viz_node::http::MAX_BODY_BYTES
        );
    }
    let req = req.body(Full::new(bytes))?;
    let reply = tokio::time::timeout(Duration::from_secs(30), client.request(req))
        .await
        .with_context(|| format!("{url}: no answer within 30 s"))?
        .map_err(|e| {
            let cause = insitu_proto::peer::error_chain(&e);
            anyhow::anyhow!(
                "{url}: the request failed ({cause}); is the viz-node's viewer (--http) there?"
            )
        })?;
    let status = reply.status().as_u16();
    let text = reply.into_body().collect().await?.to_bytes();
    Ok((status, String::from_utf8_lossy(&text).into_owned()))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn cameras_parse_as_the_api_takes_them_and_bad_ones_are_named() {
        let json = |c: CameraBody| serde_json::to_value(c).unwrap();
        assert_eq!(
            json(camera("1,2,30:1,2,3").unwrap()),
            serde_json::json!({"eye": [1.0, 2.0, 30.0], "target": [1.0, 2.0, 3.0], "up": [0.0, 1.0, 0.0], "fov_y_deg": 30.0})
        );
        assert_eq!(
            json(camera("view:45,10").unwrap()),
            serde_json::json!({"angle": 45.0, "elevation": 10.0, "zoom": 1.0})
        );
        assert_eq!(json(camera("view:0,0,1.5").unwrap())["zoom"], 1.5);
        for bad in [
            "1,2:3,4,5",
            "view:1",
            "1,2,3",
            "a,b,c:1,2,3",
            "1,2,nan:0,0,0",
        ] {
            let e = camera(bad).unwrap_err().to_string();
            assert!(e.contains("--camera"), "{bad}: {e}");
        }
        assert_eq!(base_url("127.0.0.1:8080").unwrap(), "http://127.0.0.1:8080");
        assert!(base_url("https://x:1").is_err());
    }
}
