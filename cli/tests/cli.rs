//! The `insitu` command end to end: happy paths and bad input (clear error, non-zero exit,
//! no output file left behind).

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly by design

use std::path::Path;
use std::process::{Command, Output};

fn insitu(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_insitu"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("insitu runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Runs `insitu` with `args`, then `--out out`, then `extra`; asserts that it succeeds and
/// returns the bytes it wrote to `out` and its standard output.
fn written(dir: &Path, args: &[&str], extra: &[&str], out: &str) -> (Vec<u8>, String) {
    let mut all = args.to_vec();
    all.extend_from_slice(&["--out", out]);
    all.extend_from_slice(extra);
    let o = insitu(&all, dir);
    assert!(o.status.success(), "{all:?}: {}", stderr(&o));
    let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
    (std::fs::read(dir.join(out)).unwrap(), stdout)
}

/// `insitu render` of `volume` with `extra` flags at 48² from 30°, on the CPU, into `out`:
/// the PNG's bytes.
fn small_render(dir: &Path, volume: &str, extra: &[&str], out: &str) -> Vec<u8> {
    let mut args = vec!["render", "--volume", volume];
    args.extend_from_slice(extra);
    args.extend_from_slice(&["--size", "48", "--angle", "30", "--backend", "cpu"]);
    written(dir, &args, &[], out).0
}

#[test]
fn evaluate_json_on_the_embedded_default() {
    let dir = tempfile::tempdir().unwrap();
    let o = evaluate_on("auto", &[], dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for key in [
        "r",
        "gamma",
        "codec",
        "sigma_bytes",
        "supersegments",
        "tau_s",
        "tau_compress_s",
        "q_db",
        "views",
    ] {
        assert!(v.get(key).is_some(), "missing {key} in {v}");
    }
    let views = v["views"].as_array().unwrap();
    assert_eq!(views.len(), 2);
    // At the generation view with r = size the VDI reproduces the DVR.
    let q0 = &views[0]["q_db"];
    assert!(q0 == "inf" || q0.as_f64().unwrap() >= 60.0, "q at 0°: {q0}");
    assert!(dir.path().join("evaluate.png").exists());
}

#[test]
fn generate_then_view() {
    let dir = tempfile::tempdir().unwrap();
    let o = insitu(
        &[
            "generate",
            "--volume",
            "gray-scott:16:50",
            "--r",
            "24",
            "--out",
            "a.vdi",
        ],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let o = insitu(
        &[
            "view", "--vdi", "a.vdi", "--angle", "90", "--size", "20", "--out", "v.png",
        ],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.path().join("v.png").exists());
}

/// `view --lod` renders from the coarsest level with the image's resolution: the VDI itself
/// at `size = r` (the same PNG as without `--lod`), its `r/2` level at `size = r/2`. The
/// camera flags move the view: a zoom or an elevation gives another image, and their
/// neutral values (zoom 1, elevation 0) the default one.
#[test]
fn view_lod_zoom_and_elevation_do_what_they_say() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let generate = ["generate", "--volume", "gray-scott:16:50", "--r", "32"];
    written(d, &generate, &[], "a.vdi");
    let view = |extra: &[&str], out: &str| {
        let args = [
            "view",
            "--vdi",
            "a.vdi",
            "--angle",
            "40",
            "--backend",
            "cpu",
        ];
        written(d, &args, extra, out)
    };
    let (full, _) = view(&["--size", "32"], "full.png");
    let (full_lod, line) = view(&["--size", "32", "--lod"], "full_lod.png");
    assert!(line.contains("from its level r=32"), "{line}");
    assert_eq!(full_lod, full, "--lod at size r must use the VDI itself");
    let (half, _) = view(&["--size", "16"], "half.png");
    let (half_lod, line) = view(&["--size", "16", "--lod"], "half_lod.png");
    assert!(line.contains("from its level r=16"), "{line}");
    assert_ne!(half_lod, half, "the r/2 level is a different VDI");
    let neutral = &["--size", "32", "--zoom", "1", "--elevation", "0"];
    assert_eq!(view(neutral, "neutral.png").0, full);
    assert_ne!(view(&["--size", "32", "--zoom", "2"], "zoom.png").0, full);
    let (raised, line) = view(&["--size", "32", "--elevation", "35"], "raised.png");
    assert!(line.contains("elevation 35°"), "{line}");
    assert_ne!(raised, full);
}

fn assert_fails(args: &[&str], dir: &Path, needle: &str, out: &str) {
    let o = insitu(args, dir);
    assert!(!o.status.success(), "{args:?} succeeded");
    let err = stderr(&o);
    assert!(
        err.contains(needle),
        "{args:?}: {err:?} does not mention {needle:?}"
    );
    assert!(!dir.join(out).exists(), "{args:?} left {out} behind");
}

#[test]
fn bad_input_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("short_4x4x4_uint8.raw"), [0u8; 10]).unwrap();
    std::fs::write(d.join("odd_2x2x2_int128.raw"), [0u8; 8]).unwrap();
    std::fs::write(d.join("ok_4x4x4_uint8.raw"), [7u8; 64]).unwrap();
    std::fs::write(
        d.join("bad.json"),
        r#"{"domain": [0, 1], "points": [[0.5,0,0,0,0],[0.2,0,0,0,0]]}"#,
    )
    .unwrap();
    std::fs::write(
        d.join("range.json"),
        r#"{"domain": [0, 1], "points": [[0,0,0,0,2]]}"#,
    )
    .unwrap();
    std::fs::write(d.join("empty.json"), r#"{"domain": [0, 1], "points": []}"#).unwrap();
    std::fs::write(d.join("corrupt.vdi"), b"\x89VDI\r\n\x1a\ngarbage").unwrap();
    fn render(v: &str) -> Vec<&str> {
        vec!["render", "--volume", v, "--size", "8", "--out", "o.png"]
    }
    assert_fails(&render("short_4x4x4_uint8.raw"), d, "10 bytes", "o.png");
    assert_fails(&render("odd_2x2x2_int128.raw"), d, "int128", "o.png");
    assert_fails(
        &render("missing_4x4x4_uint8.raw"),
        d,
        "missing_4x4x4_uint8.raw",
        "o.png",
    );
    assert_fails(&render("novolume.raw"), d, "novolume.raw", "o.png");
    // A raw file's flags with the built-in simulation: refused, not silently ignored.
    for raw_flag in [
        ["--spacing", "2"],
        ["--dims", "4x4x4"],
        ["--time-step", "1"],
    ] {
        let mut args = render("gray-scott:16:20");
        args.extend_from_slice(&raw_flag);
        assert_fails(&args, d, raw_flag[0], "o.png");
    }
    for (tf, needle) in [
        ("bad.json", "increase"),
        ("range.json", "outside"),
        ("empty.json", "no points"),
        ("nope.json", "nope.json"),
    ] {
        let args = [
            "render",
            "--volume",
            "ok_4x4x4_uint8.raw",
            "--tf",
            tf,
            "--size",
            "8",
            "--out",
            "o.png",
        ];
        assert_fails(&args, d, needle, "o.png");
    }
    let generate = |r: &str, g: &str| {
        vec![
            "generate".to_owned(),
            "--volume".into(),
            "ok_4x4x4_uint8.raw".into(),
            "--r".into(),
            r.into(),
            "--gamma".into(),
            g.into(),
            "--out".into(),
            "o.vdi".into(),
        ]
    };
    for (r, g, needle) in [
        ("0", "0.01", "r = 0"),
        ("8", "-0.5", "gamma = -0.5"),
        ("8", "NaN", "gamma = NaN"),
    ] {
        let args = generate(r, g);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_fails(&args, d, needle, "o.vdi");
    }
    assert_fails(
        &["view", "--vdi", "corrupt.vdi", "--out", "o.png"],
        d,
        "corrupt.vdi",
        "o.png",
    );
    assert_fails(
        &[
            "render",
            "--volume",
            "ok_4x4x4_uint8.raw",
            "--sample-distance",
            "0",
            "--out",
            "o.png",
        ],
        d,
        "step",
        "o.png",
    );
    assert_fails(
        &["render", "--volume", "gray-scott:4", "--out", "o.png"],
        d,
        "gray-scott",
        "o.png",
    );
    // A codec name is checked as the arguments are parsed (a usage error naming the value
    // and the choices), in each command that takes one.
    for command in [
        "generate", "evaluate", "accuracy", "study", "demo", "replay",
    ] {
        let args = [command, "--codec", "lzma"];
        let o = insitu(&args, d);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", stderr(&o));
        let err = stderr(&o);
        assert!(
            err.contains("--codec") && err.contains("lzma") && err.contains("zstd"),
            "{args:?}: {err}"
        );
    }
    // An output into a folder that does not exist: the error names the file.
    assert_fails(
        &[
            "generate",
            "--volume",
            "ok_4x4x4_uint8.raw",
            "--r",
            "8",
            "--out",
            "no-such-folder/o.vdi",
        ],
        d,
        "no-such-folder/o.vdi",
        "no-such-folder",
    );
}

/// `render --repeat N` renders N times, reports the cold render and the median of the warm
/// ones, and writes the same image as a single render (the renders are deterministic).
#[test]
fn render_repeat_reports_the_warm_median_and_the_same_image() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let render = |repeat: &str, out: &str| {
        insitu(
            &[
                "render",
                "--volume",
                "gray-scott:16:20",
                "--size",
                "24",
                "--backend",
                "cpu",
                "--repeat",
                repeat,
                "--out",
                out,
            ],
            d,
        )
    };
    let once = render("1", "once.png");
    assert!(once.status.success(), "{}", stderr(&once));
    assert!(!String::from_utf8_lossy(&once.stdout).contains("then"));
    let thrice = render("3", "thrice.png");
    assert!(thrice.status.success(), "{}", stderr(&thrice));
    let line = String::from_utf8_lossy(&thrice.stdout).into_owned();
    assert!(line.contains("(median of 2)"), "{line}");
    assert_eq!(
        std::fs::read(d.join("once.png")).unwrap(),
        std::fs::read(d.join("thrice.png")).unwrap()
    );
    assert_fails(
        &[
            "render",
            "--volume",
            "gray-scott:16:20",
            "--repeat",
            "0",
            "--out",
            "z.png",
        ],
        d,
        "repeat",
        "z.png",
    );
}

/// The flags for data whose file name says nothing (docs/data.md): `--dims` and
/// `--type` read a file as its descriptive name would, `--dims …xT` with `--time-step` picks one step
/// of a time series, and `--no-skipping` changes the time, never the image. Each compared as
/// PNG bytes against the render of an equivalent file.
#[test]
fn own_data_flags_read_the_file_as_its_name_would() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Two steps of a 12×10×8 byte blob, the second shifted along x.
    let step = |shift: f32| -> Vec<u8> {
        let mut v = Vec::new();
        for z in 0..8 {
            for y in 0..10 {
                for x in 0..12 {
                    let r2 = (x as f32 - 5.0 - shift).powi(2)
                        + (y as f32 - 4.5).powi(2)
                        + (z as f32 - 3.5).powi(2);
                    v.push((255.0 * (-r2 / 12.0).exp()) as u8);
                }
            }
        }
        v
    };
    let (first, second) = (step(0.0), step(2.0));
    std::fs::write(d.join("blob_12x10x8_uint8.raw"), &first).unwrap();
    std::fs::write(d.join("shifted_12x10x8_uint8.raw"), &second).unwrap();
    std::fs::write(d.join("blob.dat"), &first).unwrap();
    std::fs::write(d.join("series.dat"), [first, second].concat()).unwrap();
    let render = |extra: &[&str], out: &str| {
        let args = [
            "render",
            "--size",
            "32",
            "--angle",
            "30",
            "--backend",
            "cpu",
        ];
        written(d, &args, extra, out).0
    };
    let named = render(&["--volume", "blob_12x10x8_uint8.raw"], "named.png");
    let flags = &[
        "--volume", "blob.dat", "--dims", "12x10x8", "--type", "uint8",
    ];
    assert_eq!(render(flags, "flags.png"), named, "--dims/--type");
    let unskipped = &["--volume", "blob_12x10x8_uint8.raw", "--no-skipping"];
    assert_eq!(render(unskipped, "unskipped.png"), named, "--no-skipping");
    let shifted = render(&["--volume", "shifted_12x10x8_uint8.raw"], "shifted.png");
    assert_ne!(
        shifted, named,
        "the two steps must differ for --time-step to be tested"
    );
    let series = &[
        "--volume",
        "series.dat",
        "--dims",
        "12x10x8x2",
        "--type",
        "uint8",
    ];
    let mut t1 = series.to_vec();
    t1.extend_from_slice(&["--time-step", "1"]);
    assert_eq!(render(&t1, "t1.png"), shifted, "--time-step 1");
    assert_eq!(
        render(series, "t0.png"),
        named,
        "--time-step 0 (the default)"
    );
    // A name that says nothing, and no flags: the error names the file.
    assert_fails(
        &["render", "--volume", "blob.dat", "--out", "none.png"],
        d,
        "blob.dat",
        "none.png",
    );
}

/// A volume one voxel thick has a flat box (docs/conventions.md: `(n − 1)·s` per axis), so its image is
/// empty; the command says why instead of writing a black image unexplained, and a volume
/// two voxels thick renders without the warning.
#[test]
fn a_flat_volume_renders_empty_and_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let slab = |z: usize| -> Vec<u8> { (0..6 * 5 * z).map(|i| (40 + i % 200) as u8).collect() };
    std::fs::write(d.join("flat_6x5x1_uint8.raw"), slab(1)).unwrap();
    std::fs::write(d.join("thick_6x5x2_uint8.raw"), slab(2)).unwrap();
    let render = |volume: &str, out: &str| {
        let o = insitu(
            &[
                "render",
                "--volume",
                volume,
                "--size",
                "16",
                "--backend",
                "cpu",
                "--out",
                out,
            ],
            d,
        );
        assert!(o.status.success(), "{volume}: {}", stderr(&o));
        let pixels = image::open(d.join(out)).unwrap().to_rgb8();
        (stderr(&o), pixels.pixels().any(|p| p.0 != [0, 0, 0]))
    };
    let (said, lit) = render("flat_6x5x1_uint8.raw", "flat.png");
    assert!(!lit, "a flat box has no depth to composite");
    assert!(
        said.contains("flat_6x5x1_uint8.raw is one voxel thick along z"),
        "{said}"
    );
    let (said, lit) = render("thick_6x5x2_uint8.raw", "thick.png");
    assert!(lit, "two slices have depth");
    assert!(!said.contains("one voxel thick"), "{said}");
}

/// The accuracy knobs reach the marcher: `--generation-termination 0.3` stops generation
/// rays early, so the VDI holds fewer supersegments than with `off`; `--termination 0.3`
/// and `--shading` change the direct rendering; values outside (0, 1] are refused, naming
/// the flag, with nothing written.
#[test]
fn termination_and_shading_flags_reach_the_marcher() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let supersegments = |termination: &str, out: &str| -> u64 {
        let args = ["generate", "--volume", "gray-scott:24:300", "--r", "32"];
        let (_, line) = written(d, &args, &["--generation-termination", termination], out);
        let count = line
            .split(" supersegments")
            .next()
            .and_then(|head| head.rsplit(' ').next())
            .and_then(|n| n.parse().ok());
        count.unwrap_or_else(|| panic!("no supersegment count in {line:?}"))
    };
    let (off, early) = (
        supersegments("off", "off.vdi"),
        supersegments("0.3", "early.vdi"),
    );
    assert!(early < off, "0.3: {early} supersegments, off: {off}");
    let render = |extra: &[&str], out: &str| {
        let args = [
            "render",
            "--volume",
            "gray-scott:24:300",
            "--size",
            "24",
            "--backend",
            "cpu",
        ];
        written(d, &args, extra, out).0
    };
    let plain = render(&[], "plain.png");
    assert_ne!(render(&["--termination", "0.3"], "early.png"), plain);
    assert_ne!(render(&["--shading"], "shaded.png"), plain);
    let bad_generation = [
        "generate",
        "--volume",
        "gray-scott:16:20",
        "--generation-termination",
        "0",
        "--out",
        "bad.vdi",
    ];
    assert_fails(&bad_generation, d, "--generation-termination", "bad.vdi");
    let bad_render = [
        "render",
        "--volume",
        "gray-scott:16:20",
        "--termination",
        "1.5",
        "--out",
        "bad.png",
    ];
    assert_fails(&bad_render, d, "1.5", "bad.png");
}

#[test]
fn demo_runs_the_pipeline_and_prints_a_line_per_step() {
    let dir = tempfile::tempdir().unwrap();
    let o = insitu(
        &[
            "demo",
            "--size",
            "24",
            "--warmup",
            "50",
            "--every",
            "10",
            "--pushes",
            "4",
            "--sample-every",
            "2",
            "--r",
            "32",
            "--codec",
            "zstd",
            "--recording",
            "rec",
        ],
        dir.path(),
    );
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}\n{out}", stderr(&o));
    let lines: Vec<&str> = out.lines().filter(|l| l.starts_with("step ")).collect();
    assert_eq!(lines.len(), 4, "{out}");
    // Steps that are multiples of `every × sample-every` (20) carry reference frames, so the
    // lines of steps 60 and 80 have q, those of 50 and 70 not.
    let mut with_q: Vec<&str> = lines
        .iter()
        .filter(|l| l.contains(" dB"))
        .filter_map(|l| l.split_whitespace().nth(1))
        .collect();
    with_q.sort_unstable();
    assert_eq!(with_q, ["60", "80"], "{out}");
    assert!(out.contains("stored 4, dropped 0"), "{out}");
    assert!(out.contains("recording: rec"), "{out}");
    // By default the viz-node serves the web viewer and a tuner is attached.
    assert!(out.contains("web viewer: http://"), "{out}");
    assert!(out.contains("tuner (max q"), "{out}");
    // The index, exported: four stored VDIs, two with q.
    let o = insitu(
        &["export", "--recording", "rec", "--format", "csv"],
        dir.path(),
    );
    let csv = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        csv.lines().filter(|l| l.contains(".vdi")).count(),
        4,
        "{csv}"
    );
    let o = insitu(&["export", "--recording", "rec"], dir.path());
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(json["entries"].as_array().map(Vec::len), Some(4), "{json}");
    // γ as it was given (an f32 through a serde_json::Value would print 0.013000000268220901).
    let text = String::from_utf8_lossy(&o.stdout);
    assert_eq!(text.matches("\"gamma\": 0.013,").count(), 4, "{text}");
    // With the run's budget: the adherence of the steps made with a tuned P_M, and each
    // line's σ over the budget.
    let o = insitu(
        &["export", "--recording", "rec", "--budget", "size:10kB"],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let with: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let tuned: Vec<u64> = json["entries"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["pm_version"].as_u64() > Some(0))
        .map(|e| e["sigma_bytes"].as_u64().unwrap())
        .collect();
    let a = &with["adherence"]["sigma"];
    assert_eq!(a["steps"].as_u64(), Some(tuned.len() as u64), "{a}");
    let within = tuned.iter().filter(|&&s| s < 10_000).count() as u64;
    assert_eq!(a["within"].as_u64(), Some(within), "{a}");
    assert!(with["adherence"]["tau"].is_null(), "{with}");
    let o = insitu(
        &[
            "export",
            "--recording",
            "rec",
            "--format",
            "csv",
            "--budget",
            "size:10kB",
        ],
        dir.path(),
    );
    let csv = String::from_utf8_lossy(&o.stdout);
    assert!(
        csv.starts_with("step,")
            && csv
                .lines()
                .next()
                .unwrap()
                .ends_with(",sigma_budget_ratio,tau_budget_ratio"),
        "{csv}"
    );
    for line in csv.lines().skip(1) {
        let cols: Vec<&str> = line.split(',').collect();
        let sigma: f64 = cols[6].parse().unwrap();
        let ratio: f64 = cols[cols.len() - 2].parse().unwrap();
        assert!((ratio - sigma / 1e4).abs() < 1e-9, "{line}");
    }
    let o = insitu(
        &["export", "--recording", "rec", "--budget", "quality:40"],
        dir.path(),
    );
    assert!(!o.status.success() && stderr(&o).contains("states no size or time budget"));
    // A recorded step renders; one the recording lacks is refused, naming the steps it has.
    let (png, _) = written(
        dir.path(),
        &["view", "--recording", "rec"],
        &["--time-step", "60"],
        "s.png",
    );
    assert!(image::load_from_memory(&png).is_ok());
    assert_fails(
        &[
            "view",
            "--recording",
            "rec",
            "--time-step",
            "61",
            "--out",
            "x.png",
        ],
        dir.path(),
        "step 61 is not in rec: it holds 4 steps from 50 to 80",
        "x.png",
    );
    // --no-http and --no-tune: the same steps, without the viewer and the tuner.
    let o = insitu(
        &[
            "demo",
            "--size",
            "24",
            "--warmup",
            "50",
            "--every",
            "10",
            "--pushes",
            "2",
            "--r",
            "32",
            "--recording",
            "bare",
            "--no-http",
            "--no-tune",
        ],
        dir.path(),
    );
    let out = String::from_utf8_lossy(&o.stdout);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}\n{out}");
    assert!(out.contains("P_M fixed (--no-tune)"), "{out}");
    assert!(
        !out.contains("tuner (") && !out.contains("web viewer"),
        "{out}"
    );
    assert!(!err.contains("web viewer"), "{err}");
    assert!(out.contains("stored 2, dropped 0"), "{out}");
}

#[test]
fn study_then_tune_reuses_the_cache_and_says_when_a_budget_is_infeasible() {
    let dir = tempfile::tempdir().unwrap();
    let common = [
        "--volume",
        "gray-scott:24:300",
        "--r-grid",
        "16:32:8",
        "--gamma-grid",
        "0.01,0.05,0.2",
        "--views",
        "0,30",
        "--size",
        "24",
        "--codec",
        "zstd",
        "--cache-dir",
        "cache",
    ];
    let mut study = vec!["study", "--json", "--out", "s"];
    study.extend_from_slice(&common);
    let o = insitu(&study, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (v["candidates"].as_u64(), v["generated"].as_u64()),
        (Some(9), Some(9))
    );
    let csv = std::fs::read_to_string(dir.path().join("s.csv")).unwrap();
    assert_eq!(csv.lines().count(), 10, "{csv}");
    for chart in ["s_map.png", "s_pareto.png", "s_ladder.png"] {
        assert!(dir.path().join(chart).exists(), "{chart} missing: {v}");
    }
    // --no-charts: the same tables (from the cache), no charts.
    let mut bare = vec!["study", "--json", "--no-charts", "--out", "t"];
    bare.extend_from_slice(&common);
    let o = insitu(&bare, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["charts"].as_array().map(Vec::len), Some(0), "{v}");
    assert!(dir.path().join("t.csv").exists());
    assert!(!dir.path().join("t_map.png").exists());
    // tune on the same scene: everything comes from the cache; adaptive unless asked.
    let mut tune = vec!["tune", "--json", "--utility", "size:1GB"];
    tune.extend_from_slice(&common);
    let o = insitu(&tune, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["generated"].as_u64(), Some(0), "{v}");
    assert_eq!(v["strategy"], "adaptive", "{v}");
    assert_eq!(
        v["best"]["gamma"].as_f64().map(|g| (g * 100.0).round()),
        Some(1.0),
        "{v}"
    );
    // An impossible budget is a clear error, not a default.
    let mut bad = vec!["tune", "--utility", "size:10B"];
    bad.extend_from_slice(&common);
    let o = insitu(&bad, dir.path());
    assert!(!o.status.success());
    assert!(stderr(&o).contains("infeasible"), "{}", stderr(&o));
    // The config picks the utility and the strategy; flags override it.
    std::fs::write(
        dir.path().join("t.toml"),
        "utility = \"size:10B\"\nstrategy = \"adaptive\"\n",
    )
    .unwrap();
    let mut cfg = vec!["tune", "--config", "t.toml", "--json"];
    cfg.extend_from_slice(&common);
    let o = insitu(&cfg, dir.path());
    assert!(
        !o.status.success() && stderr(&o).contains("infeasible"),
        "{}",
        stderr(&o)
    );
    let mut cfg = vec![
        "tune",
        "--config",
        "t.toml",
        "--utility",
        "size:1GB",
        "--json",
    ];
    cfg.extend_from_slice(&common);
    let o = insitu(&cfg, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["strategy"], "adaptive", "{v}");
    // The adaptive search takes time budgets too (from the cache: no generation).
    let mut time = vec![
        "tune",
        "--utility",
        "time:1000",
        "--strategy",
        "adaptive",
        "--json",
    ];
    time.extend_from_slice(&common);
    let o = insitu(&time, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["generated"].as_u64(), Some(0), "{v}");
    assert!(
        v["best"]["tau_s"].as_f64().is_some_and(|t| t < 1000.0),
        "{v}"
    );
    time[2] = "time:1e-9";
    let o = insitu(&time, dir.path());
    assert!(
        !o.status.success() && stderr(&o).contains("infeasible"),
        "{}",
        stderr(&o)
    );
}

/// `tune --ladder`: at every size budget of the ladder (each 1.5× the previous) both choices
/// fit the budget, and the adaptive search, which walks the same grid priced from the table,
/// finds no better q than the grid's optimum and generates no more candidates than the grid has.
#[test]
fn the_ladder_compares_the_grid_and_the_adaptive_choice_at_every_budget() {
    let dir = tempfile::tempdir().unwrap();
    let o = insitu(
        &[
            "tune",
            "--ladder",
            "--json",
            "--chart",
            "ladder.png",
            "--volume",
            "gray-scott:24:300",
            "--r-grid",
            "16:32:8",
            "--gamma-grid",
            "0.01,0.05,0.2",
            "--views",
            "0,30",
            "--size",
            "24",
            "--cache-dir",
            "cache",
        ],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let rungs: Vec<serde_json::Value> = serde_json::from_slice(&o.stdout).unwrap();
    assert!(rungs.len() >= 2, "{rungs:?}");
    // "inf" for a view the VDI reproduces exactly.
    let q = |m: &serde_json::Value| m["q_db"].as_f64().unwrap_or(f64::INFINITY);
    let mut previous = 0;
    for rung in &rungs {
        let target = rung["sigma_target"].as_u64().unwrap();
        assert!(target as f64 >= 1.49 * previous as f64, "{rungs:?}");
        previous = target;
        for choice in ["grid", "adaptive"] {
            let sigma = rung[choice]["sigma_bytes"].as_u64().unwrap();
            assert!(sigma < target, "{choice} over budget: {rung}");
        }
        assert!(q(&rung["adaptive"]) <= q(&rung["grid"]), "{rung}");
        assert_eq!(rung["grid_evaluations"].as_u64(), Some(9), "{rung}");
        assert!(
            rung["adaptive_evaluations"].as_u64().unwrap() <= 9,
            "{rung}"
        );
    }
    assert!(dir.path().join("ladder.png").exists());
}

#[test]
fn series_picks_one_step_per_regime_and_cross_evaluates() {
    let dir = tempfile::tempdir().unwrap();
    // 12³ × 6 steps: steps 0–2 a dim blob, steps 3–5 a bright, larger one.
    let mut bytes = Vec::new();
    for t in 0..6 {
        let (amp, rad) = if t < 3 { (1.0f32, 3.0f32) } else { (4.0, 5.0) };
        for z in 0..12 {
            for y in 0..12 {
                for x in 0..12 {
                    let d = ((x as f32 - 6.0).powi(2)
                        + (y as f32 - 6.0).powi(2)
                        + (z as f32 - 6.0).powi(2))
                    .sqrt();
                    let v = amp * (rad - d).max(0.0) + 0.001 * t as f32;
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
    }
    std::fs::write(dir.path().join("s_12x12x12x6_float32.raw"), bytes).unwrap();
    let series = |extra: &[&str]| {
        let mut args = vec![
            "series",
            "--volume",
            "s_12x12x12x6_float32.raw",
            "--r-grid",
            "16,24",
            "--gamma-grid",
            "0.01,0.1",
            "--views",
            "0,30",
            "--size",
            "16",
            "--codec",
            "zstd",
            "--utility",
            "size:1GB",
            "--no-cache",
            "--json",
        ];
        args.extend_from_slice(extra);
        let o = insitu(&args, dir.path());
        assert!(o.status.success(), "{extra:?}: {}", stderr(&o));
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let steps: Vec<u64> = v["characteristic_steps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s.as_u64().unwrap())
            .collect();
        (steps, v)
    };
    let (steps, v) = series(&[]);
    assert_eq!(steps.len(), 2, "{v}");
    assert!(steps[0] < 3 && steps[1] >= 3, "{steps:?}");
    assert_eq!(v["cross"].as_array().unwrap().len(), 4);
    assert!(v["cross"]
        .as_array()
        .unwrap()
        .iter()
        .all(|c| c["holds"] == true));
    assert!(v["conservative"]["r"].is_u64(), "{v}");
    // Fewer steps when asked for at most one, or when no distance can exceed the threshold
    // (a total-variation distance is at most 1).
    for extra in [["--max-steps", "1"], ["--threshold", "1"]] {
        let (steps, v) = series(&extra);
        assert_eq!(steps.len(), 1, "{extra:?}: {v}");
    }
}

/// `evaluate --json` on a small Gray–Scott field with `--backend B` and environment `env`.
fn evaluate_on(backend: &str, env: &[(&str, &str)], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_insitu"))
        .args([
            "evaluate",
            "--volume",
            "gray-scott:24:100",
            "--size",
            "32",
            "--r",
            "32",
            "--views",
            "0,30",
            "--json",
            "--codec",
            "zstd",
            "--backend",
            backend,
        ])
        .envs(env.iter().copied())
        .current_dir(dir)
        .output()
        .expect("insitu runs")
}

#[test]
fn the_gpu_backend_agrees_with_the_cpu_and_reports_its_time_source() {
    let dir = tempfile::tempdir().unwrap();
    let cpu = evaluate_on("cpu", &[], dir.path());
    assert!(cpu.status.success(), "{}", stderr(&cpu));
    let gpu = evaluate_on("gpu", &[], dir.path());
    if stderr(&gpu).contains("no GPU adapter found") {
        let _: Option<()> = insitu_testenv::skip(insitu_testenv::Need::Gpu, &stderr(&gpu));
        return;
    }
    assert!(
        gpu.status.success(),
        "--backend gpu needs an adapter (lavapipe: mesa-vulkan-drivers): {}",
        stderr(&gpu)
    );
    let cpu: serde_json::Value = serde_json::from_slice(&cpu.stdout).unwrap();
    let gpu: serde_json::Value = serde_json::from_slice(&gpu.stdout).unwrap();
    assert!(cpu["backend"].as_str().unwrap().starts_with("cpu"), "{cpu}");
    assert!(gpu["backend"].as_str().unwrap().starts_with("gpu"), "{gpu}");
    assert_eq!(cpu["tau_source"], "wall-clock");
    assert!(
        ["wall-clock", "gpu-timestamps"].contains(&gpu["tau_source"].as_str().unwrap()),
        "{gpu}"
    );
    // Same data, same kernels: the same supersegments (up to rounding) and the same quality.
    let count = |v: &serde_json::Value| v["supersegments"].as_f64().unwrap();
    assert!(
        (count(&cpu) - count(&gpu)).abs() <= 0.01 * count(&cpu),
        "{cpu}\n{gpu}"
    );
    let q30 = |v: &serde_json::Value| v["views"][1]["q_db"].as_f64().unwrap();
    assert!((q30(&cpu) - q30(&gpu)).abs() < 0.5, "{cpu}\n{gpu}");
}

#[test]
fn without_an_adapter_auto_falls_back_and_gpu_fails_clearly() {
    let dir = tempfile::tempdir().unwrap();
    // This build has only the Vulkan backend: asking wgpu for Metal finds no adapter.
    let none = [("WGPU_BACKEND", "metal")];
    let auto = evaluate_on("auto", &none, dir.path());
    assert!(auto.status.success(), "{}", stderr(&auto));
    let lines: Vec<String> = stderr(&auto)
        .lines()
        .filter(|l| l.contains("backend"))
        .map(str::to_owned)
        .collect();
    assert_eq!(lines.len(), 1, "one line says what auto chose: {lines:?}");
    assert!(
        lines[0].starts_with("backend auto: cpu") && lines[0].contains("no GPU adapter"),
        "{lines:?}"
    );
    let gpu = evaluate_on("gpu", &none, dir.path());
    assert!(!gpu.status.success());
    let err = stderr(&gpu);
    assert!(
        err.contains("--backend gpu") && err.contains("no GPU adapter found"),
        "{err}"
    );
    assert!(gpu.stdout.is_empty(), "no output on failure");
    let bad = evaluate_on("cuda", &[], dir.path());
    assert!(!bad.status.success());
    assert!(
        stderr(&bad).contains("expected one of cpu, gpu, auto"),
        "{}",
        stderr(&bad)
    );
}

/// Without a display session (`XDG_RUNTIME_DIR` unset: compute nodes, batch jobs, ssh) a
/// command prints only its own lines: the GPU probe of `--backend auto` and the GPU path itself
/// stay quiet (Mesa's device-selection layer would otherwise complain at every probe).
#[test]
fn without_a_display_session_stderr_holds_only_our_lines() {
    let dir = tempfile::tempdir().unwrap();
    for backend in ["cpu", "auto", "gpu"] {
        let out = Command::new(env!("CARGO_BIN_EXE_insitu"))
            .args([
                "render",
                "--size",
                "32",
                "--backend",
                backend,
                "--out",
                "x.png",
            ])
            .env_remove("XDG_RUNTIME_DIR")
            .env_remove("NODEVICE_SELECT")
            .env_remove("RUST_LOG")
            .current_dir(dir.path())
            .output()
            .unwrap();
        let err = stderr(&out);
        if backend == "gpu" && err.contains("no GPU adapter found") {
            let _: Option<()> = insitu_testenv::skip(insitu_testenv::Need::Gpu, &err);
            continue;
        }
        assert!(out.status.success(), "{backend}: {err}");
        for line in err.lines() {
            assert!(
                line.starts_with("backend"),
                "{backend}: a line on stderr that is not ours: {line:?}\n{err}"
            );
        }
    }
}

/// A run too short for any decision to apply says so in its summary, instead of leaving the
/// user to wonder why every step kept the configured P_M.
#[test]
fn a_run_too_short_for_a_tuned_p_m_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let o = insitu(
        &[
            "demo", "--size", "16", "--warmup", "10", "--every", "10", "--pushes", "2",
        ],
        dir.path(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("no stored step was made with a tuned P_M"),
        "{out}"
    );
}

/// The in-process nodes of `insitu demo` take INSITU_TOKEN as daemons do, and the demo's own
/// clients send it: a token in the environment does not break the demo. A time budget is
/// taken with its unit, as the docs write it.
#[test]
fn the_demo_runs_with_a_token_in_the_environment_and_units_on_its_budget() {
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_insitu"))
        .args([
            "demo", "--size", "16", "--warmup", "10", "--every", "10", "--pushes", "2",
        ])
        .args(["--utility", "time:0.5s", "--no-http"])
        .env("INSITU_TOKEN", "x")
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
}

/// What `insitu steer` can tell before it sends anything, it says: a sample distance that is
/// not a length (and `--step` for one), a transfer function over what the viewer takes.
#[test]
fn steer_refuses_what_the_viewer_would_refuse_before_sending() {
    let dir = tempfile::tempdir().unwrap();
    let o = insitu(
        &["steer", "--viz", "127.0.0.1:9", "--sample-distance", "NaN"],
        dir.path(),
    );
    assert!(!o.status.success());
    assert!(stderr(&o).contains("finite length > 0"), "{}", stderr(&o));
    // `--step` is a time step's word: the flag is refused and the right one named.
    let o = insitu(
        &["steer", "--viz", "127.0.0.1:9", "--step", "0.25"],
        dir.path(),
    );
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--sample-distance"), "{}", stderr(&o));
    // A valid transfer function of 3 MB: over the viewer's 2 MiB, said without a connection.
    let n = 100_000;
    let points: Vec<String> = (0..n)
        .map(|i| format!("[{:.8}, 0.5, 0.5, 0.5, 0.5]", i as f64 / (n - 1) as f64))
        .collect();
    let big = format!("{{\"domain\": [0, 1], \"points\": [{}]}}", points.join(","));
    assert!(big.len() > 3_000_000);
    std::fs::write(dir.path().join("big.json"), big).unwrap();
    let o = insitu(
        &["steer", "--viz", "127.0.0.1:9", "--tf", "big.json"],
        dir.path(),
    );
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("the viewer takes at most 2097152"), "{e}");
    assert!(!e.contains("request failed"), "{e}");
    // One that is not a transfer function, or breaks a rule, is named before anything is sent.
    for (text, says) in [
        (
            r#"{"points": [{"value": 1}]}"#,
            "not valid JSON of the form",
        ),
        (
            r#"{"domain": [1, 0], "points": [[0, 0, 0, 0, 0]]}"#,
            "domain [1, 0]",
        ),
    ] {
        std::fs::write(dir.path().join("bad.json"), text).unwrap();
        let o = insitu(
            &["steer", "--viz", "127.0.0.1:9", "--tf", "bad.json"],
            dir.path(),
        );
        assert!(!o.status.success());
        let e = stderr(&o);
        assert!(e.contains("--tf") && e.contains(says), "{e}");
        assert!(!e.contains("request failed"), "{e}");
    }
}

/// Writes a growing ball over 3 steps of 17³ (`ball_17x17x17x3_float32.raw`) in `dir` and
/// replays it into the recording `dir/rec` as 2 ranks with frames every step (so each step is
/// composed and scored); returns the replay's arguments.
fn ball_recording(dir: &Path) -> [&'static str; 11] {
    let (n, steps) = (17usize, 3usize);
    let mut bytes = Vec::with_capacity(n * n * n * steps * 4);
    for t in 0..steps {
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let d = [x, y, z].map(|c| c as f32 - 8.0);
                    let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    bytes.extend_from_slice(&(5.0 + t as f32 - r).max(0.0).to_le_bytes());
                }
            }
        }
    }
    std::fs::write(dir.join("ball_17x17x17x3_float32.raw"), bytes).unwrap();
    let replay = [
        "replay",
        "--series",
        "ball_17x17x17x3_float32.raw",
        "--ranks",
        "2",
        "--r",
        "32",
        "--no-tune",
        "--no-http",
        "--recording",
        "rec",
    ];
    let o = insitu(&replay, dir);
    assert!(o.status.success(), "{}", stderr(&o));
    replay
}

/// A Cinema database of a recording of two ranks: one row per step and view with the step's
/// P_M and metrics and FILE last; every image is what `insitu view` renders of that step and
/// view, byte for byte; an independent reader (pandas and Pillow) accepts it; an existing
/// database is not overwritten.
#[test]
fn cinema_export_renders_every_step_at_every_view() {
    let dir = tempfile::tempdir().unwrap();
    ball_recording(dir.path());
    let export = [
        "export",
        "--recording",
        "rec",
        "--cinema",
        "run.cdb",
        "--phi",
        "0,120,-90",
        "--theta",
        "0,30",
        "--size",
        "40",
        "--backend",
        "cpu",
    ];
    let o = insitu(&export, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let db = dir.path().join("run.cdb");
    let csv = std::fs::read_to_string(db.join("data.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "time,phi,theta,step,pm_version,r,gamma,sigma_bytes,tau_s,q_db,FILE"
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 3 * 3 * 2, "{csv}");
    for row in &rows {
        let (phi, theta, step, file) = (row[1], row[2], row[3], row[10]);
        assert_eq!(row[5], "32", "r");
        assert!(
            row[9].parse::<f64>().is_ok_and(|q| q > 10.0),
            "q {}",
            row[9]
        );
        let out = format!("view_{step}_{phi}_{theta}.png");
        let args = [
            "view",
            "--recording",
            "rec",
            "--time-step",
            step,
            "--angle",
            phi,
            "--elevation",
            theta,
            "--size",
            "40",
            "--backend",
            "cpu",
            "--out",
            &out,
        ];
        let o = insitu(&args, dir.path());
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(
            std::fs::read(db.join(file)).unwrap(),
            std::fs::read(dir.path().join(&out)).unwrap(),
            "{file} is not `insitu view` of step {step} at {phi}, {theta}"
        );
    }
    let o = insitu(&export, dir.path());
    assert!(
        !o.status.success() && stderr(&o).contains("exists"),
        "{}",
        stderr(&o)
    );
    if let Some(python) = insitu_testenv::fixture_python() {
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/check_cinema.py");
        let o = Command::new(python)
            .args([script, db.to_str().unwrap(), "time", "phi", "theta", "q_db"])
            .output()
            .unwrap();
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "{}{out}", stderr(&o));
        assert!(out.contains("18 rows") && out.contains("(40, 40)"), "{out}");
    }
}

/// A movie of a recording: the frames the orbit asks for, H.264 at the size asked, read back
/// by ffprobe; without ffmpeg on PATH a clear error and no file.
#[test]
fn movie_export_encodes_every_frame_or_says_ffmpeg_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    ball_recording(dir.path());
    let export = [
        "export",
        "--recording",
        "rec",
        "--movie",
        "run.mp4",
        "--frames-per-step",
        "5",
        "--size",
        "48x32",
        "--backend",
        "cpu",
    ];
    let o = Command::new(env!("CARGO_BIN_EXE_insitu"))
        .args(export)
        .current_dir(dir.path())
        .env("PATH", dir.path())
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("ffmpeg is not installed"),
        "{}",
        stderr(&o)
    );
    assert!(!dir.path().join("run.mp4").exists());
    let Some(ffprobe) = insitu_testenv::tool("ffprobe", insitu_testenv::Need::Ffmpeg) else {
        return;
    };
    let o = insitu(&export, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let probe = Command::new(ffprobe)
        .args([
            "-v",
            "error",
            "-count_frames",
            "-select_streams",
            "v:0",
            "-show_entries",
        ])
        .args([
            "stream=nb_read_frames,width,height,codec_name",
            "-of",
            "csv=p=0",
        ])
        .arg(dir.path().join("run.mp4"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&probe.stdout);
    assert_eq!(text.trim(), "h264,48,32,15", "{text}");
}

/// The rows of `insitu export --recording rec` as JSON, without what a rebuild cannot know:
/// τ and the compression time are measurements, not kept in the files (a VDI made again must
/// have the same bytes).
fn exported_rows(dir: &Path) -> serde_json::Value {
    let o = insitu(&["export", "--recording", "rec"], dir);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for key in ["entries", "steps"] {
        for row in v[key].as_array_mut().unwrap() {
            let row = row.as_object_mut().unwrap();
            for key in [
                "tau_secs",
                "tau_source",
                "tau_compress_secs",
                "compose_secs",
            ] {
                row.remove(key);
            }
        }
    }
    v
}

/// An emptied or cut index beside stored steps stops the next run (nothing is overwritten), and
/// `insitu recover` rebuilds it from the files: the same rows, q scored again to the same
/// values, the steps of two ranks composed again; the damaged index is kept beside.
#[test]
fn recover_rebuilds_an_emptied_or_cut_index_from_the_files() {
    let dir = tempfile::tempdir().unwrap();
    let replay = ball_recording(dir.path());
    let before = exported_rows(dir.path());
    // The local generator-node serves both ranks: one part per step holds them.
    let parts = before["entries"].as_array().unwrap();
    assert_eq!(parts.len(), 3, "{before}");
    assert!(
        parts
            .iter()
            .all(|p| p["covers"] == serde_json::json!([0, 1])),
        "{before}"
    );
    assert_eq!(before["steps"].as_array().unwrap().len(), 3, "{before}");
    let rec = dir.path().join("rec");
    let vdi = rec.join("step_00000000_rank_0000.vdi");
    let original = std::fs::read(&vdi).unwrap();
    for damage in ["emptied", "cut"] {
        let index = rec.join("index.sqlite");
        match damage {
            "emptied" => std::fs::write(&index, b"").unwrap(),
            _ => {
                let f = std::fs::OpenOptions::new()
                    .write(true)
                    .open(&index)
                    .unwrap();
                f.set_len(f.metadata().unwrap().len() / 2).unwrap();
            }
        }
        let o = insitu(&replay, dir.path());
        assert!(!o.status.success(), "{damage}: a run started on it");
        // The advice is the command as it is typed.
        assert!(
            stderr(&o).contains("insitu recover --recording"),
            "{}",
            stderr(&o)
        );
        // Reading it says the same, not only SQLite's words.
        for read in [
            &["view", "--recording", "rec", "--time-step", "0"][..],
            &["export", "--recording", "rec", "--out", "rows.json"],
        ] {
            let o = insitu(read, dir.path());
            assert!(!o.status.success(), "{damage}: {read:?} read it");
            assert!(
                stderr(&o).contains("insitu recover --recording"),
                "{read:?}: {}",
                stderr(&o)
            );
        }
        assert_eq!(std::fs::read(&vdi).unwrap(), original, "{damage}");
        let o = insitu(
            &["recover", "--recording", "rec", "--backend", "cpu"],
            dir.path(),
        );
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "{damage}: {}\n{out}", stderr(&o));
        assert!(out.contains("rebuilt 3 rows"), "{out}");
        assert!(out.contains("kept the damaged index.sqlite as"), "{out}");
        assert_eq!(exported_rows(dir.path()), before, "{damage}");
    }
    let kept: Vec<String> = std::fs::read_dir(&rec)
        .unwrap()
        .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| {
            name.starts_with("index.sqlite.damaged-")
                && !name.ends_with("-wal")
                && !name.ends_with("-shm")
        })
        .collect();
    assert_eq!(kept.len(), 2, "both damaged indexes are kept: {kept:?}");
    // A sound index is left alone.
    let o = insitu(&["recover", "--recording", "rec"], dir.path());
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("sound index with 3 rows"),
        "{}",
        stderr(&o)
    );
}

/// The same field as a raw file, an NRRD and a legacy VTK file (the VTK one moved by its
/// origin, which the camera follows) renders the same image; a wrong field or a raw-only flag
/// is refused by name.
#[test]
fn every_format_renders_the_field_it_holds() {
    let dir = tempfile::tempdir().unwrap();
    let n = 12usize;
    let v: Vec<f32> = (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, i / n % n, i / (n * n));
            let d = [x, y, z].map(|c| c as f32 - 5.5);
            (5.0 - (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()).max(0.0)
        })
        .collect();
    let le: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(dir.path().join("ball_12x12x12_float32.raw"), &le).unwrap();
    let mut nrrd =
        b"NRRD0004\ntype: float\ndimension: 3\nsizes: 12 12 12\nendian: little\nencoding: raw\n\n"
            .to_vec();
    nrrd.extend_from_slice(&le);
    std::fs::write(dir.path().join("ball.nrrd"), &nrrd).unwrap();
    let mut vtk = b"# vtk DataFile Version 3.0\nball\nBINARY\nDATASET STRUCTURED_POINTS\nDIMENSIONS 12 12 12\nORIGIN 100 -50 7\nSPACING 1 1 1\nPOINT_DATA 1728\nSCALARS rho float\nLOOKUP_TABLE default\n".to_vec();
    vtk.extend(v.iter().flat_map(|x| x.to_be_bytes()));
    std::fs::write(dir.path().join("ball.vtk"), &vtk).unwrap();
    let render = |volume: &str| small_render(dir.path(), volume, &[], &format!("{volume}.png"));
    let raw = render("ball_12x12x12_float32.raw");
    assert_eq!(render("ball.nrrd"), raw, "NRRD");
    // --spacing overrides a file's spacing as it sets a raw file's.
    let stretched = |volume: &str| {
        let out = format!("{volume}.stretched.png");
        small_render(dir.path(), volume, &["--spacing", "1,2,0.5"], &out)
    };
    let raw_stretched = stretched("ball_12x12x12_float32.raw");
    assert_ne!(raw_stretched, raw, "the spacing changes the picture");
    assert_eq!(stretched("ball.nrrd"), raw_stretched, "NRRD with --spacing");
    assert_eq!(render("ball.vtk"), raw, "legacy VTK");
    // Through the pipeline the grid keeps the file's origin: the stored VDI's box starts there.
    let args = [
        "replay",
        "--series",
        "ball.vtk",
        "--r",
        "16",
        "--no-tune",
        "--no-http",
        "--recording",
        "rec",
    ];
    let o = insitu(&args, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(dir.path().join("rec/step_00000000_rank_0000.vdi")).unwrap();
    let vdi = insitu_core::vdi::codec::decode(&bytes, &Default::default()).unwrap();
    let b = vdi.meta().volume_box;
    assert_eq!(
        (b.min.to_array(), b.max.to_array()),
        ([100.0, -50.0, 7.0], [111.0, -39.0, 18.0])
    );
    assert_fails(
        &[
            "render", "--volume", "ball.vtk", "--field", "p", "--size", "8",
        ],
        dir.path(),
        "no array \"p\"; arrays here: rho",
        "x.png",
    );
    assert_fails(
        &[
            "render",
            "--volume",
            "ball.nrrd",
            "--dims",
            "12x12x12",
            "--size",
            "8",
        ],
        dir.path(),
        "--dims describe a raw file",
        "x.png",
    );
    assert_fails(
        &["render", "--volume", "ball.grib", "--size", "8"],
        dir.path(),
        "unknown volume format",
        "x.png",
    );
    // A format read through a C library names the feature that reads it when it is off.
    assert_fails(
        &["render", "--volume", "ball.h5", "--size", "8"],
        dir.path(),
        if cfg!(feature = "hdf5") {
            "HDF5 cannot open it"
        } else {
            "--features hdf5"
        },
        "x.png",
    );
}

/// netCDF-4 and XDMF over HDF5 (written by PyPI's netCDF4 and h5py; `scripts/write-fixtures.sh`)
/// go through the commands as the pure-Rust formats do: the same values on the same grid give
/// the same picture as the classic NetCDF file, and a replay of cell data stores every step
/// with its box half a cell in from the grid's origin.
#[cfg(all(feature = "netcdf4", feature = "hdf5"))]
#[test]
fn netcdf4_and_xdmf_over_hdf5_render_and_replay() {
    let Some(fixtures) = insitu_testenv::fixture_dir() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let render = |file: &str, field: &str| {
        let volume = fixtures.join(file);
        let out = format!("{file}.png");
        small_render(
            dir.path(),
            volume.to_str().unwrap(),
            &["--field", field],
            &out,
        )
    };
    let classic = render("nc_classic.nc", "rho");
    assert_eq!(render("nc_nc4.nc", "rho"), classic, "netCDF-4");
    assert_eq!(render("xdmf_series.xmf", "rho"), classic, "XDMF");
    let series = fixtures.join("xdmf_series.xmf");
    let args = [
        "replay",
        "--series",
        series.to_str().unwrap(),
        "--field",
        "cellrho",
        "--r",
        "16",
        "--no-tune",
        "--no-http",
        "--recording",
        "rec",
    ];
    let o = insitu(&args, dir.path());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("cellrho is cell data"),
        "{}",
        stderr(&o)
    );
    for step in 0..3 {
        let name = format!("rec/step_{step:08}_rank_0000.vdi");
        let bytes = std::fs::read(dir.path().join(&name)).unwrap();
        let vdi = insitu_core::vdi::codec::decode(&bytes, &Default::default()).unwrap();
        let b = vdi.meta().volume_box;
        // The grid: origin (1.5, -2, 10), spacing (0.5, 1, 2.5), 12×10×8 points; its cells'
        // centres from (1.75, -1.5, 11.25), 11×9×7 of them.
        assert_eq!(
            (b.min.to_array(), b.max.to_array()),
            ([1.75, -1.5, 11.25], [6.75, 6.5, 26.25]),
            "{name}"
        );
    }
}

/// A `.vti` with a non-zero origin and anisotropic spacing, written by VTK, rendered by VTK
/// (which places it by its own reader) and by `insitu render` (by ours) from the same view:
/// the images agree (≥ 40 dB), as they can only where the two put the grid alike.
#[test]
fn a_vti_renders_where_vtk_puts_it() {
    let (Some(python), Some(fixtures)) = (
        insitu_testenv::fixture_python(),
        insitu_testenv::fixture_dir(),
    ) else {
        return;
    };
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../bench/vtk_compare.py");
    let vti = fixtures.join("vti_appended_raw_zlib.vti");
    for (field, angle) in [("rho", "30"), ("temp", "100")] {
        let o = Command::new(&python)
            .arg(script)
            .arg("--volume")
            .arg(&vti)
            .args([
                "--field", field, "--angle", angle, "--size", "128", "--runs", "1",
            ])
            .args(["--insitu", env!("CARGO_BIN_EXE_insitu")])
            .output()
            .unwrap();
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "{}{out}", stderr(&o));
        let db: f64 = out
            .split("PSNR between the images: ")
            .nth(1)
            .and_then(|s| s.split(' ').next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no PSNR in {out}"));
        assert!(db >= 40.0, "{field} at {angle}°: {db} dB\n{out}");
    }
}
