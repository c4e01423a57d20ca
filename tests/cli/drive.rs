//! `render`, `export ply` and `bench fps` on a tiny trained avatar (a tiny synthetic set, a
//! few training iterations), with each kind of motion, and their errors on bad motions; and
//! `view`, the live browser viewer (`drive/view.rs`).

mod gaussianavatars;
mod view;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use texavatars::device::BackendKind;
use texavatars::drive::{self, CameraPath, Identity, Motion, View};
use texavatars::head::HeadAsset;
use texavatars::io;
use texavatars::models::load_avatar;
use texavatars::models::texavatars::constants::BACKGROUND;
use texavatars::splat::{self, SplatParams};

use crate::tiny;

struct Fixture {
    data: PathBuf,
    run: PathBuf,
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-drive-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// A tiny synthetic set and an avatar trained on it for 4 iterations (built once).
fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let data = tmp("data");
        tiny::synth_data(&data);
        let run = tmp("run");
        tiny::train_tiny(&data, &run, 4, 4);
        Fixture { data, run }
    })
}

fn texavatars(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(args)
        .output()
        .expect("run texavatars")
}

fn ok(out: &Output) -> String {
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "failed: {}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

fn fails(out: &Output) -> String {
    assert!(!out.status.success(), "expected a failure");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

fn gif_frames(path: &Path) -> usize {
    use image::AnimationDecoder;
    let f = std::io::BufReader::new(std::fs::File::open(path).expect("gif"));
    image::codecs::gif::GifDecoder::new(f)
        .expect("decodable gif")
        .into_frames()
        .count()
}

#[test]
fn render_a_dataset_split_from_its_cameras() {
    let f = fixture();
    let out = tmp("render-split");
    let motion = f.data.join("union/transforms_test.json");
    let text = ok(&texavatars(&[
        "render",
        "--checkpoint",
        s(&f.run),
        "--motion",
        s(&motion),
        "--out",
        s(&out),
        "--no-mp4",
    ]));
    // The test split of the tiny set: 2 timesteps.
    assert!(text.contains("rendered 2 frames"), "{text}");
    for i in 0..2 {
        let img = io::image::read_rgb(&out.join(format!("frames/{i:05}.png"))).expect("frame");
        assert_eq!(
            (img.width, img.height),
            (24, 32),
            "the dataset camera's size"
        );
    }
    assert!(!out.join("frames/00002.png").exists());
    let sheet = io::image::read_rgb(&out.join("contact_sheet.png")).expect("sheet");
    assert_eq!((sheet.width, sheet.height), (2 * 24, 32));
    assert_eq!(gif_frames(&out.join("render.gif")), 2);
}

#[test]
fn render_cross_reenactment_and_curves_from_an_orbit() {
    let f = fixture();
    // Another subject's parameters: a sequence folder with flame_param/ (the synthetic set's
    // own, with the mean identity).
    let out = tmp("render-flame");
    let text = ok(&texavatars(&[
        "render",
        "--checkpoint",
        s(&f.run),
        "--motion",
        s(&f.data.join("jaw")),
        "--head",
        s(&f.data.join("head/head.npz")),
        "--size",
        "20x28",
        "--out",
        s(&out),
        "--no-mp4",
    ]));
    assert!(text.contains("rendered 2 frames"), "{text}");
    let a = io::image::read_rgb(&out.join("frames/00000.png")).expect("frame");
    assert_eq!((a.width, a.height), (20, 28));

    let curves = tmp("curves.json");
    std::fs::write(
        &curves,
        r#"{"frames": 4,
            "expression": {"jawOpen": [[0, 0.0], [3, 1.0]]},
            "pose": {"rotation": [[0, [0, 0.3, 0]]], "eyes": [[0, [0, 0, 0, 0, 0, 0]]]}}"#,
    )
    .expect("write curves");
    let out = tmp("render-curves");
    let text = ok(&texavatars(&[
        "render",
        "--checkpoint",
        s(&f.run),
        "--motion",
        s(&curves),
        "--cameras",
        "front",
        "--size",
        "16x20",
        "--fps",
        "10",
        "--out",
        s(&out),
        "--no-mp4",
    ]));
    assert!(text.contains("rendered 4 frames"), "{text}");
    assert_eq!(gif_frames(&out.join("render.gif")), 4);
    // The jaw opens: the first and last frames differ.
    let a = io::image::read_rgb(&out.join("frames/00000.png")).expect("frame");
    let b = io::image::read_rgb(&out.join("frames/00003.png")).expect("frame");
    assert_ne!(a.rgb, b.rgb);
}

#[test]
fn bad_motions_fail_with_the_file_and_field() {
    let f = fixture();
    let run = s(&f.run);
    let out = tmp("render-bad");
    let render = |motion: &Path, extra: &[&str]| {
        let mut args = vec!["render", "--checkpoint", run, "--motion", s(motion)];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--out", s(&out), "--no-mp4"]);
        texavatars(&args)
    };
    let missing = tmp("no-such-motion.json");
    let e = fails(&render(&missing, &[]));
    assert!(e.contains("no-such-motion.json"), "{e}");

    let unknown = tmp("unknown.json");
    std::fs::write(
        &unknown,
        r#"{"frames": 2, "expression": {"fooBar": [[0, 1.0]]}}"#,
    )
    .expect("write");
    let e = fails(&render(&unknown, &[]));
    assert!(
        e.contains("expression.fooBar") && e.contains("jawOpen"),
        "{e}"
    );

    let short = tmp("short.json");
    std::fs::write(
        &short,
        r#"{"frames": 2, "pose": {"jaw": [[0, [0.1, 0.0]]]}}"#,
    )
    .expect("write");
    let e = fails(&render(&short, &[]));
    assert!(e.contains("pose.jaw[0]") && e.contains("expected 3"), "{e}");

    let truncated = tmp("truncated");
    std::fs::create_dir_all(truncated.join("flame_param")).expect("dir");
    let good = std::fs::read(f.data.join("jaw/flame_param/00000.npz"))
        .or_else(|_| {
            let dir = f.data.join("jaw/flame_param");
            let first = std::fs::read_dir(&dir)?
                .filter_map(|e| e.ok())
                .map(|e| e.path())
                .min()
                .expect("a flame_param file");
            std::fs::read(first)
        })
        .expect("read npz");
    std::fs::write(
        truncated.join("flame_param/00000.npz"),
        &good[..good.len() / 2],
    )
    .expect("write");
    let e = fails(&render(&truncated, &[]));
    assert!(e.contains("00000.npz"), "{e}");

    let split = f.data.join("union/transforms_test.json");
    let e = fails(&render(&split, &["--frames", "5..2"]));
    assert!(e.contains("frames"), "{e}");
    let e = fails(&render(
        &split,
        &["--cameras", "dataset", "--camera-index", "99"],
    ));
    assert!(e.contains("no camera 99"), "{e}");
    let still = tmp("still.json");
    std::fs::write(&still, r#"{"frames": 1}"#).expect("write");
    let e = fails(&render(&still, &["--cameras", "dataset"]));
    assert!(e.contains("dataset motion"), "{e}");
    let e = fails(&render(&still, &["--size", "20by30"]));
    assert!(e.contains("--size"), "{e}");
}

/// Re-rendering an exported PLY with `splat render` gives the avatar's own image: exactly
/// its Gaussians where the colours are representable. A PLY's degree-0 colour is clamped at
/// 0 by every 3DGS viewer (and by `splat render`), so the reference is the avatar's render
/// with negative colour channels clamped; where the avatar has none the two are the same.
#[test]
fn exported_ply_re_renders_like_the_avatar() {
    let f = fixture();
    let out = tmp("export");
    let motion = f.data.join("union/transforms_test.json");
    let text = ok(&texavatars(&[
        "export",
        "ply",
        "--checkpoint",
        s(&f.run),
        "--motion",
        s(&motion),
        "--frames",
        "0..2",
        "--render",
        "--out",
        s(&out),
    ]));
    assert!(text.contains("exported 2 frames"), "{text}");

    let head = HeadAsset::load(&f.data.join("head/head.npz"), None).expect("head");
    let device = BackendKind::Flex.device();
    let avatar = load_avatar(&f.run, &head, &device).expect("avatar");
    let mut m = Motion::load(
        &motion,
        &head.model,
        &head.meta,
        &Identity::mean(&head.model),
    )
    .expect("motion");
    m.select(0..2).expect("frames");
    let cams =
        drive::cameras(&m, CameraPath::Dataset { index: None }, &View::default()).expect("cameras");
    for (i, (frame, cam)) in m.frames.iter().zip(&cams).enumerate() {
        let (own, g) =
            drive::render_frame(&avatar, &frame.conditioning, cam, &device).expect("render");
        let exported = io::npy::read(&out.join(format!("{i:05}_render.npy"))).expect("npy");
        assert_eq!(exported.data, own, "--render writes the avatar's own image");
        let colors: Vec<f32> = g.colors.clone().into_data().iter::<f32>().collect();
        let clamped = splat::Gaussians {
            colors: g.colors.clone().clamp_min(0.0),
            ..g
        };
        let params = SplatParams {
            camera: *cam,
            background: BACKGROUND,
        };
        let reference: Vec<f32> = splat::render(&clamped, &params)
            .expect("render")
            .image
            .into_data()
            .iter::<f32>()
            .collect();
        if colors.iter().all(|&c| c >= 0.0) {
            assert_eq!(reference, own);
        }
        let raw = out.join(format!("{i:05}_splat.npy"));
        ok(&texavatars(&[
            "splat",
            "render",
            "--ply",
            s(&out.join(format!("{i:05}.ply"))),
            "--camera",
            s(&out.join(format!("{i:05}_camera.json"))),
            "--out",
            s(&out.join(format!("{i:05}_splat.png"))),
            "--raw",
            s(&raw),
        ]));
        let again = io::npy::read(&raw).expect("npy").data;
        let d = again
            .iter()
            .zip(&reference)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(d <= 1e-3, "frame {i}: max difference {d}");
    }
}

#[test]
fn bench_fps_reports_every_stage() {
    let f = fixture();
    let json = tmp("fps.json");
    let text = ok(&texavatars(&[
        "bench",
        "fps",
        "--checkpoint",
        s(&f.run),
        "--head",
        s(&f.data.join("head/head.npz")),
        "--renders",
        "2",
        "--rounds",
        "2",
        "--size",
        "24x32",
        "--json",
        s(&json),
    ]));
    assert!(
        text.contains("FPS") && text.contains("rasterizer"),
        "{text}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    let rounds = v["rounds"].as_array().expect("rounds");
    assert_eq!(rounds.len(), 2);
    for r in rounds {
        for k in ["fps", "decoders_ms", "lifting_ms", "rasterizer_ms"] {
            assert!(r[k].as_f64().is_some_and(|x| x > 0.0), "{k}: {r}");
        }
    }
}
