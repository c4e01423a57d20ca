//! Resource bounds ([`texavatars::limits`]) and output folders: every over-limit input is an
//! error naming the flag or file and field, before any work (so nothing is allocated or
//! written); `render` and `export ply` clear only their own stale files; `synth` refuses a
//! folder made with other settings unless `--force`.
//!
//! Tests that go through `cli::run` pass `--max-memory 1G`, which holds for the rest of this
//! test process (the flag is process-wide, so these tests are a binary of their own); every
//! input here that should pass fits in 1 GiB.

use std::path::{Path, PathBuf};
use std::process::Command;

use clap::Parser;
use texavatars::cli::{self, Cli};
use texavatars::drive::Motion;
use texavatars::drive::motion::Identity;
use texavatars::drive::outputs;
use texavatars::head::HeadAsset;
use texavatars::io::npz::NpzOut;
use texavatars::limits::{self, Budget, Estimate, Source};
use texavatars::models::texavatars::NetConfig;
use texavatars::synth::SynthConfig;
use texavatars::train::TrainConfig;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-limits-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// Runs the command line (with `--max-memory 1G`); the error's text on failure.
fn run(args: &[&str]) -> Result<(), String> {
    let argv = ["texavatars", "--max-memory", "1G"].iter().chain(args);
    let cli = Cli::try_parse_from(argv).map_err(|e| e.to_string())?;
    cli::run(cli).map_err(|e| format!("{e:#}"))
}

fn err(args: &[&str]) -> String {
    run(args).expect_err("expected an error")
}

fn assert_has(e: &str, parts: &[&str]) {
    for p in parts {
        assert!(e.contains(p), "{p:?} not in: {e}");
    }
}

/// Files (names relative to `dir`) under `dir`, sorted.
fn files(dir: &Path) -> Vec<String> {
    fn walk(base: &Path, dir: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                let rel = p.strip_prefix(base).expect("under base");
                out.push(rel.to_string_lossy().replace('\\', "/"));
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

fn touch(p: &Path) {
    if let Some(d) = p.parent() {
        std::fs::create_dir_all(d).expect("dir");
    }
    std::fs::write(p, b"x").expect("write");
}

#[test]
fn max_memory_flag_parses_sizes_and_refuses_others() {
    for ok in ["1G", "512M", "16GiB", "2048"] {
        assert!(
            Cli::try_parse_from(["texavatars", "--max-memory", ok, "uv", "inspect", "--help"])
                .map_err(|e| e.kind())
                .err()
                .is_none_or(|k| k == clap::error::ErrorKind::DisplayHelp),
            "{ok}"
        );
    }
    // Global: accepted after the subcommand too.
    let c = Cli::try_parse_from([
        "texavatars",
        "uv",
        "inspect",
        "--mesh",
        "m.obj",
        "--out",
        "o",
        "--max-memory",
        "3G",
    ])
    .expect("parse");
    assert_eq!(c.max_memory, Some(3 << 30));
    let e = Cli::try_parse_from([
        "texavatars",
        "--max-memory",
        "lots",
        "uv",
        "inspect",
        "--mesh",
        "m.obj",
        "--out",
        "o",
    ])
    .expect_err("bad size")
    .to_string();
    assert_has(&e, &["--max-memory", "lots", "not a size"]);
}

#[test]
fn render_size_is_checked_before_anything_is_loaded() {
    let out = tmp("render-size");
    let o = out.join("out");
    // The checkpoint and motion do not exist: the size is refused before they are read.
    let base = [
        "render",
        "--checkpoint",
        "/nonexistent/run",
        "--motion",
        "/nonexistent/m.json",
        "--out",
        s(&o),
        "--size",
    ];
    let with = |size: &'static str| {
        let mut v = base.to_vec();
        v.push(size);
        v
    };
    let e = err(&with("100000x100000"));
    assert_has(
        &e,
        &[
            "--size 100000x100000",
            "`width`",
            "100000 pixels",
            "cap of 16384",
        ],
    );
    // Within the caps but over the 1 GiB budget: 8000 x 8000 frames need about 5.7 GiB.
    let e = err(&with("8000x8000"));
    assert_has(
        &e,
        &[
            "--size 8000x8000",
            "needs about 5.7 GiB",
            "limit of 1.0 GiB (--max-memory)",
            "TEXAVATARS_MAX_MEMORY",
        ],
    );
    let e = err(&with("12x"));
    assert_has(&e, &["--size", "WIDTHxHEIGHT"]);
    assert!(!o.exists(), "nothing written");
    // The same for `export ply` (the same drive arguments).
    let e = err(&[
        "export",
        "ply",
        "--checkpoint",
        "/nonexistent/run",
        "--motion",
        "/nonexistent/m.json",
        "--out",
        s(&o),
        "--size",
        "20000x10",
    ]);
    assert_has(&e, &["--size 20000x10", "`width`", "cap of 16384"]);
    assert!(!o.exists(), "nothing written");
}

#[test]
fn motions_with_too_many_frames_are_refused_before_they_are_built() {
    let dir = tmp("motion");
    let head = HeadAsset::embedded().expect("head");
    let id = Identity::mean(&head.model);
    // A curves file of 10^8 frames: refused before any frame is evaluated.
    let curves = dir.join("long.json");
    std::fs::write(
        &curves,
        r#"{"frames": 100000000, "expression": {"0": [[0, 0.5]]}}"#,
    )
    .expect("write");
    let e = Motion::load(&curves, &head.model, &head.meta, &id)
        .expect_err("too long")
        .to_string();
    assert_has(
        &e,
        &["long.json", "`frames`", "100000000 frames", "cap of 100000"],
    );
    // A FLAME parameter file of 100001 frames (only its `expr` array): refused on the
    // count, before its frames are read.
    let npz = dir.join("long.npz");
    NpzOut::default()
        .floats("expr", &[100_001, 1], vec![0.0; 100_001])
        .write(&npz)
        .expect("npz");
    let e = Motion::load(&npz, &head.model, &head.meta, &id)
        .expect_err("too long")
        .to_string();
    assert_has(
        &e,
        &[
            "long.npz",
            "expr (frames)",
            "100001 frames",
            "cap of 100000",
        ],
    );
    // Within the cap the memory decides: the estimate of 100000 frames of the head, over a
    // small budget.
    let per = limits::motion_frame_bytes(head.model.num_vertices(), 200);
    let est = Estimate::new().add("100000 motion frames", 100_000 * per);
    let small = Budget {
        bytes: 64 << 20,
        source: Source::Flag,
    };
    let e = limits::check_estimate_against("m.json", "frames", &est, &small)
        .expect_err("over")
        .to_string();
    assert_has(
        &e,
        &["m.json", "`frames`", "needs about", "100000 motion frames"],
    );
    // A short one loads.
    let short = dir.join("short.json");
    std::fs::write(&short, r#"{"frames": 3}"#).expect("write");
    let m = Motion::load(&short, &head.model, &head.meta, &id).expect("short motion");
    assert_eq!(m.frames.len(), 3);
}

#[test]
fn splat_camera_sizes_and_gaussian_counts_are_checked_before_reading_the_ply() {
    let dir = tmp("splat");
    let cam = |w: u32, h: u32| {
        let p = dir.join(format!("cam_{w}x{h}.json"));
        let text = serde_json::json!({
            "width": w, "height": h, "fx": 100.0, "fy": 100.0, "cx": 8.0, "cy": 8.0,
            "world_to_camera": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                                [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]],
        });
        std::fs::write(&p, text.to_string()).expect("camera");
        p
    };
    let out = dir.join("render.png");
    // The PLY does not exist: the camera is refused before it is read.
    let big = cam(100_000, 100_000);
    let e = err(&[
        "splat",
        "render",
        "--ply",
        "/nonexistent/s.ply",
        "--camera",
        s(&big),
        "--out",
        s(&out),
    ]);
    assert_has(&e, &["cam_100000x100000.json", "`width`", "cap of 16384"]);
    let heavy = cam(10_000, 10_000);
    let e = err(&[
        "splat",
        "render",
        "--ply",
        "/nonexistent/s.ply",
        "--camera",
        s(&heavy),
        "--out",
        s(&out),
    ]);
    assert_has(
        &e,
        &[
            "cam_10000x10000.json",
            "`width x height`",
            "needs about 6.0 GiB",
        ],
    );
    assert!(!out.exists());
    let e = err(&[
        "splat",
        "demo",
        "--out",
        s(&dir.join("demo")),
        "--gaussians",
        "100000000",
    ]);
    assert_has(&e, &["splat demo", "--gaussians", "cap of 16777216"]);
    assert!(!dir.join("demo").exists());
}

#[test]
fn uv_inspect_resolutions_are_capped_and_budgeted() {
    let dir = tmp("uv");
    let out = dir.join("out");
    let base = [
        "uv",
        "inspect",
        "--mesh",
        "/nonexistent/m.obj",
        "--out",
        s(&out),
    ];
    let with = |extra: &[&'static str]| {
        let mut v = base.to_vec();
        v.extend_from_slice(extra);
        v
    };
    let e = err(&with(&["--res", "1000000"]));
    assert_has(
        &e,
        &["uv inspect", "`--res`", "1000000 texels", "cap of 4096"],
    );
    let e = err(&with(&["--res", "64", "--samples", "100000"]));
    assert_has(&e, &["`--samples`", "cap of 4096"]);
    // 4096^2 texels and samples: about 3.5 GiB, over 1 GiB.
    let e = err(&with(&["--res", "4096"]));
    assert_has(&e, &["`--res`", "needs about", "limit of 1.0 GiB"]);
    assert!(!out.exists());
}

fn train_json(dir: &Path, net: &NetConfig, batch_size: usize) -> PathBuf {
    let mut c = TrainConfig::new(net.clone(), 10, 5);
    c.batch_size = batch_size;
    let p = dir.join(format!("train_b{batch_size}_r{}.json", net.uv_res));
    std::fs::write(&p, c.to_json()).expect("write");
    p
}

#[test]
fn training_batch_size_uv_res_and_memory_are_checked() {
    let dir = tmp("train");
    let tiny = NetConfig::scaled(16, 64).expect("tiny net");
    // batch_size: the cap.
    let e = TrainConfig::load(&train_json(&dir, &tiny, 1000))
        .expect_err("batch 1000")
        .to_string();
    assert_has(
        &e,
        &[
            "train_b1000_r16.json",
            "`batch_size`",
            "1000 frames",
            "cap of 64",
        ],
    );
    assert!(TrainConfig::load(&train_json(&dir, &tiny, 4)).is_ok());
    // uv_res: the cap, checked before the networks' shapes.
    let mut huge = tiny.clone();
    huge.uv_res = 1 << 20;
    let e = TrainConfig::load(&train_json(&dir, &huge, 1))
        .expect_err("uv_res")
        .to_string();
    assert_has(&e, &["`net.uv_res`", "1048576 texels", "cap of 4096"]);
    // Memory: the paper's networks at batch 64 need tens of GiB; batch 1 about 1 GiB.
    let paper = TrainConfig {
        batch_size: 64,
        ..TrainConfig::new(NetConfig::paper(), 10, 5)
    };
    let big = paper.memory_estimate(None).expect("inline net");
    let one = TrainConfig {
        batch_size: 1,
        ..paper.clone()
    }
    .memory_estimate(None)
    .expect("inline net");
    assert!(big.total() > 16 << 30, "{}", big.breakdown());
    assert!(
        one.total() < 2 << 30 && one.total() > 256 << 20,
        "{}",
        one.breakdown()
    );
    let budget = Budget {
        bytes: 8 << 30,
        source: Source::Flag,
    };
    let e = limits::check_estimate_against("train.json", "batch_size", &big, &budget)
        .expect_err("over")
        .to_string();
    assert_has(
        &e,
        &["`batch_size`", "activations of 64 frame(s)", "--max-memory"],
    );
    // With the frames' images (550 x 802) and the VGG loss the estimate grows.
    let with_images = paper.memory_estimate(Some(550 * 802)).expect("inline");
    assert!(with_images.total() > big.total() + (64 * 550 * 802 * 4096));
}

#[test]
fn synth_sizes_are_capped_and_budgeted() {
    let c = |f: &dyn Fn(&mut SynthConfig)| {
        let mut c = SynthConfig::default();
        f(&mut c);
        c
    };
    let e = c(&|c| c.width = 100_000)
        .validate("s.json")
        .expect_err("width")
        .to_string();
    assert_has(&e, &["s.json", "`width`", "cap of 16384"]);
    let e = c(&|c| c.frames_per_sequence = 100_000_000)
        .validate("s.json")
        .expect_err("frames")
        .to_string();
    assert_has(&e, &["`frames_per_sequence`", "cap of 100000"]);
    let e = c(&|c| c.cameras = 100_000)
        .validate("s.json")
        .expect_err("cameras")
        .to_string();
    assert_has(&e, &["`cameras`", "cap of 256"]);
    let e = c(&|c| c.texture_res = 1 << 20)
        .validate("s.json")
        .expect_err("texture")
        .to_string();
    assert_has(&e, &["`texture_res`", "cap of 8192"]);
    // Within the caps, 16384^2 at 8x8 supersampling needs hundreds of GiB per view.
    let huge = c(&|c| {
        c.width = 16_384;
        c.height = 16_384;
        c.supersample = 8;
    });
    assert!(huge.validate("s.json").is_ok());
    let e = huge.check_memory("s.json").expect_err("memory").to_string();
    assert_has(&e, &["s.json", "`width/height/supersample`", "needs about"]);
    // Through the command line: the config file is named, nothing is written.
    let dir = tmp("synth-big");
    let p = dir.join("big.json");
    std::fs::write(&p, r#"{"width": 8000, "height": 8000, "supersample": 8}"#).expect("write");
    let out = dir.join("out");
    let e = err(&["synth", "--out", s(&out), "--config", s(&p)]);
    assert_has(&e, &["big.json", "needs about"]);
    assert!(!out.exists());
}

#[test]
fn memory_budget_comes_from_the_environment_in_a_fresh_process() {
    let bin = env!("CARGO_BIN_EXE_texavatars");
    let dir = tmp("env");
    let o = Command::new(bin)
        .args([
            "uv",
            "inspect",
            "--mesh",
            "/nonexistent/m.obj",
            "--res",
            "2048",
            "--out",
        ])
        .arg(dir.join("out"))
        .env("TEXAVATARS_MAX_MEMORY", "256M")
        .output()
        .expect("run");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert_has(
        &e,
        &["`--res`", "limit of 256.0 MiB (TEXAVATARS_MAX_MEMORY)"],
    );
    // The flag wins over the variable (2048^2 fits 4G; then the mesh is missing).
    let o = Command::new(bin)
        .args([
            "--max-memory",
            "4G",
            "uv",
            "inspect",
            "--mesh",
            "/nonexistent/m.obj",
        ])
        .args(["--res", "2048", "--out"])
        .arg(dir.join("out"))
        .env("TEXAVATARS_MAX_MEMORY", "256M")
        .output()
        .expect("run");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("m.obj") && !e.contains("needs about"), "{e}");
    // A malformed variable is an error before any work.
    let o = Command::new(bin)
        .args(["uv", "inspect", "--mesh", "/nonexistent/m.obj", "--out"])
        .arg(dir.join("out"))
        .env("TEXAVATARS_MAX_MEMORY", "lots")
        .output()
        .expect("run");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert_has(&e, &["TEXAVATARS_MAX_MEMORY", "not a size"]);
    assert!(!dir.join("out").exists());
}

#[test]
fn render_and_export_clear_only_their_own_stale_files() {
    let dir = tmp("clear");
    // An earlier, longer render (10 frames), an unfinished write, and unrelated files.
    let render = dir.join("render");
    for i in 0..10 {
        touch(&render.join(format!("frames/{i:05}.png")));
    }
    for f in [
        "frames/00003.png.partial",
        "contact_sheet.png",
        "render.gif",
        "render.gif.partial",
        "render.mp4",
        "render.partial.mp4",
        "notes.txt",
        "frames/keep.png",
        "frames/0001.png",
        "mine/00000.png",
        "00000.ply",
    ] {
        touch(&render.join(f));
    }
    let n = outputs::clear_render_outputs(&render).expect("clear");
    assert_eq!(n, 16);
    assert_eq!(
        files(&render),
        [
            "00000.ply",
            "frames/0001.png",
            "frames/keep.png",
            "mine/00000.png",
            "notes.txt"
        ]
    );
    // An earlier export of frames 0..6, a partial, and unrelated files.
    let export = dir.join("export");
    for i in 0..6 {
        for suffix in [".ply", "_camera.json", "_render.png", "_render.npy"] {
            touch(&export.join(format!("{i:05}{suffix}")));
        }
    }
    for f in [
        "00006.ply.partial",
        "scene.ply",
        "camera.json",
        "frames/00000.png",
        "a/00001.ply",
    ] {
        touch(&export.join(f));
    }
    let n = outputs::clear_export_outputs(&export).expect("clear");
    assert_eq!(n, 25);
    assert_eq!(
        files(&export),
        [
            "a/00001.ply",
            "camera.json",
            "frames/00000.png",
            "scene.ply"
        ]
    );
    // A missing folder has nothing to clear.
    assert_eq!(
        outputs::clear_export_outputs(&dir.join("none")).expect("none"),
        0
    );
}

fn tiny_synth(width: u32) -> SynthConfig {
    SynthConfig {
        width,
        height: 16,
        supersample: 1,
        cameras: 2,
        val_camera: 1,
        frames_per_sequence: 2,
        free_frames: 2,
        texture_res: 16,
        ..SynthConfig::default()
    }
}

#[test]
fn synth_refuses_a_folder_made_with_other_settings_unless_forced() {
    let dir = tmp("synth-force");
    let out = dir.join("out");
    let cfg = |c: &SynthConfig, name: &str| {
        let p = dir.join(name);
        std::fs::write(&p, serde_json::to_string(c).expect("json")).expect("write");
        p
    };
    let a = cfg(&tiny_synth(16), "a.json");
    let b = cfg(&tiny_synth(24), "b.json");
    run(&["synth", "--out", s(&out), "--config", s(&a)]).expect("first run");
    let recorded = SynthConfig::load(&out.join("synth/config.json")).expect("recorded");
    assert_eq!(recorded, tiny_synth(16));
    let image = out.join("jaw/images/00001_01.png");
    let before = std::fs::read(&image).expect("image");
    // Unrelated files, and a stale temporary file of a killed run.
    touch(&out.join("notes.txt"));
    touch(&out.join("jaw/images/notes.txt"));
    touch(&out.join("jaw/images/00001_00.png.partial"));
    // The same settings: resumed, every timestep skipped; the stale partial is removed.
    run(&["synth", "--out", s(&out), "--config", s(&a)]).expect("same settings");
    assert_eq!(std::fs::read(&image).expect("image"), before);
    assert!(!out.join("jaw/images/00001_00.png.partial").exists());
    // Other settings: refused, naming the field, nothing touched.
    let e = err(&["synth", "--out", s(&out), "--config", s(&b)]);
    assert_has(
        &e,
        &["config.json", "`width`", "recorded 16, now 24", "--force"],
    );
    assert_eq!(std::fs::read(&image).expect("image"), before);
    // Forced: the earlier run's files are replaced, unrelated files kept.
    run(&["synth", "--out", s(&out), "--config", s(&b), "--force"]).expect("forced");
    let img = texavatars::io::image::read_rgb(&image).expect("image");
    assert_eq!((img.width, img.height), (24, 16));
    assert_eq!(
        SynthConfig::load(&out.join("synth/config.json")).expect("recorded"),
        tiny_synth(24)
    );
    assert!(out.join("notes.txt").exists() && out.join("jaw/images/notes.txt").exists());
    // No file of the earlier layout is left: the image count is the new run's.
    let images = files(&out.join("jaw/images"))
        .into_iter()
        .filter(|f| f.ends_with(".png"))
        .count();
    assert_eq!(images, 2 * 2);
    let _ = std::fs::remove_dir_all(&dir);
}
