//! The `splat` commands end to end: the PLY path against the fixtures, the demo, bad input.

use std::path::PathBuf;
use std::process::Command;

use texavatars::io::npy;

use crate::common;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_texavatars"))
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-cli-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn ply_render_matches_fixture_images() {
    let dir = common::fixtures_dir();
    let out = tmp("ply");
    for name in ["small", "medium", "edge"] {
        let d = dir.join(name);
        let png = out.join(format!("{name}.png"));
        let raw = out.join(format!("{name}.npy"));
        let st = bin()
            .args(["splat", "render", "--backend", "cpu", "--ply"])
            .arg(d.join("scene.ply"))
            .arg("--camera")
            .arg(d.join("camera.json"))
            .arg("--out")
            .arg(&png)
            .arg("--raw")
            .arg(&raw)
            .status()
            .unwrap();
        assert!(st.success(), "{name}: render failed");
        assert!(png.is_file());
        let got = npy::read(&raw).unwrap();
        let want = npy::read(&d.join("image.npy")).unwrap();
        assert_eq!(got.shape, want.shape);
        let err = common::max_abs(&got.data, &want.data);
        println!("{name}: PLY path max abs error {err:.2e}");
        assert!(err <= 1e-4, "{name}: PLY path error {err}");
    }
}

#[test]
fn demo_writes_scene_and_render() {
    let out = tmp("demo");
    let st = bin()
        .args(["splat", "demo", "--gaussians", "2000", "--out"])
        .arg(&out)
        .status()
        .unwrap();
    assert!(st.success());
    for f in ["scene.ply", "camera.json", "render.png"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let img = image::open(out.join("render.png")).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (550, 802));
    // The head covers the centre; the corner stays white background.
    assert_eq!(img.get_pixel(0, 0).0, [255, 255, 255]);
    assert_ne!(img.get_pixel(275, 401).0, [255, 255, 255]);
}

#[test]
fn bad_inputs_fail_with_named_errors_and_keep_existing_output() {
    let out = tmp("bad");
    let png = out.join("keep.png");
    std::fs::write(&png, b"previous result").unwrap();
    let cam = out.join("camera.json");
    std::fs::write(
        &cam,
        r#"{"width": 4, "height": 4, "fx": 1, "fy": 1, "cx": 2, "cy": 2,
        "world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#,
    )
    .unwrap();
    let trunc = out.join("trunc.ply");
    std::fs::write(&trunc, b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\x00\x00").unwrap();
    let badcam = out.join("badcam.json");
    std::fs::write(
        &badcam,
        r#"{"width": 4, "height": 4, "fx": -1, "fy": 1, "cx": 2, "cy": 2,
        "world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#,
    )
    .unwrap();
    let cases: [(PathBuf, PathBuf, &str); 4] = [
        (out.join("missing.ply"), cam.clone(), "missing.ply"),
        (trunc.clone(), cam.clone(), "trunc.ply"),
        (trunc.clone(), out.join("nocam.json"), "nocam.json"),
        (trunc, badcam, "fx"),
    ];
    for (ply, camera, needle) in cases {
        let o = bin()
            .args(["splat", "render", "--ply"])
            .arg(&ply)
            .arg("--camera")
            .arg(&camera)
            .arg("--out")
            .arg(&png)
            .output()
            .unwrap();
        assert!(!o.status.success(), "{needle}: must fail");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(needle), "{needle} not named in: {err}");
        assert_eq!(std::fs::read(&png).unwrap(), b"previous result");
    }
}
