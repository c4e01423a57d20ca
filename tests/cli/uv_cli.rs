//! `texavatars uv inspect` end to end, and its errors on bad input.

use std::path::PathBuf;
use std::process::Command;

use texavatars::lift::Topology;
use texavatars::mesh::UvMesh;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_texavatars"))
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-uv-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

#[test]
fn inspect_writes_pictures_and_counts_gaussians() {
    let dir = tmp("inspect");
    let mesh = UvMesh::cylinder_patch(10);
    let obj = dir.join("patch.obj");
    std::fs::write(&obj, mesh.to_obj()).expect("write obj");
    let out = dir.join("out");
    let o = bin()
        .args(["uv", "inspect", "--res", "64", "--samples", "48", "--mesh"])
        .arg(&obj)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("run");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout} {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let want = Topology::new(&UvMesh::load(&obj).expect("load"), 64, 48)
        .expect("topology")
        .len();
    assert!(stdout.contains(&format!("{want} Gaussians")), "{stdout}");
    for (name, size) in [("validity.png", 64), ("faces.png", 64), ("samples.png", 48)] {
        let img = image::open(out.join(name)).expect(name).to_rgb8();
        assert_eq!(img.dimensions(), (size, size), "{name}");
    }
}

#[test]
fn inspect_reports_bad_input() {
    let dir = tmp("bad");
    let missing = dir.join("missing.obj");
    let o = bin()
        .args(["uv", "inspect", "--mesh"])
        .arg(&missing)
        .arg("--out")
        .arg(dir.join("o1"))
        .output()
        .expect("run");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("missing.obj"), "{err}");

    let bad = dir.join("bad.obj");
    std::fs::write(&bad, "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 7/1\n").expect("write");
    let o = bin()
        .args(["uv", "inspect", "--mesh"])
        .arg(&bad)
        .arg("--out")
        .arg(dir.join("o2"))
        .output()
        .expect("run");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("bad.obj:5"), "{err}");
    assert!(!dir.join("o2").exists(), "nothing written on bad input");
}
