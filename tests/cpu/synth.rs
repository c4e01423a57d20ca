//! The synthetic benchmark end to end: generate a tiny one from the embedded head, read it
//! back through the VHAP loader and the burn dataset, and check what it promises.
//!
//! The `truth/` and `flame_param/` files use VHAP's FLAME parameter keys (`expr`,
//! `rotation`, `neck_pose`, `jaw_pose`, `eyes_pose`, `translation`, `shape`), as VHAP's
//! `vhap/export_as_nerf_dataset.py` writes them and GaussianAvatars'
//! `scene/flame_gaussian_model.py` (`load_meshes`) reads them; the reader that checks them
//! here is `HeadPose::load_npz`, itself checked against those names in `src/head/params.rs`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use texavatars::data::{HeadDataset, Split};
use texavatars::head::{HeadAsset, HeadPose, lbs};
use texavatars::synth::{self, SynthConfig};

use crate::cli;

fn tiny_config() -> SynthConfig {
    SynthConfig {
        width: 24,
        height: 32,
        supersample: 2,
        frames_per_sequence: 2,
        free_frames: 3,
        texture_res: 64,
        ..SynthConfig::default()
    }
}

fn out_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-synth-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn generate(out: &Path) -> synth::Summary {
    let head = HeadAsset::embedded().expect("head");
    synth::generate(&tiny_config(), &head, out, &mut |_| {}).expect("synth")
}

#[test]
fn benchmark_reads_back_through_the_loader_with_the_protocol_splits() {
    let out = out_dir("splits");
    let s = generate(&out);
    let c = tiny_config();
    // 10 training sequences, the held-out one, FREE.
    assert_eq!(s.sequences, 12);
    assert_eq!(s.timesteps, 10 * 2 + 2 + 3);
    assert_eq!(s.split_frames, [10 * 2 * 15, 10 * 2, 2 * 16, 3 * 16]);
    let head = HeadAsset::embedded().expect("head");
    let model = Arc::new(head.model.clone());
    let union = out.join("union");
    for (split, n) in Split::ALL.iter().zip(s.split_frames) {
        let ds = HeadDataset::open(&union, *split, model.clone()).expect("open split");
        assert_eq!(ds.len(), n, "{split}");
        let frames = ds.frames();
        match split {
            Split::Val => assert!(frames.iter().all(|f| f.camera_index == c.val_camera)),
            Split::Train => assert!(frames.iter().all(|f| f.camera_index != c.val_camera)),
            _ => {
                let mut cams: Vec<usize> = frames.iter().map(|f| f.camera_index).collect();
                cams.sort_unstable();
                cams.dedup();
                assert_eq!(cams.len(), 16);
            }
        }
        // Paths are VHAP's combined-set paths.
        assert!(
            frames[0].image.to_string_lossy().contains("../"),
            "{:?}",
            frames[0].image
        );
    }
    // Every timestep of every split shows the head (front camera): no empty frames.
    for split in Split::ALL {
        let ds = HeadDataset::open(&union, split, model.clone()).expect("open split");
        for i in 0..ds.len() {
            if ds.frames()[i].camera_index != c.val_camera {
                continue;
            }
            let item = ds.load_item(i).expect("item");
            let fg = item.mask.iter().filter(|&&m| m > 0.5).count();
            assert!(fg > 50, "{split} item {i}: {fg} foreground pixels");
        }
    }
    // Train and test timesteps are disjoint (novel expression), val shares train's.
    let ts = |split| -> Vec<usize> {
        let ds = HeadDataset::open(&union, split, model.clone()).expect("open");
        let mut t: Vec<usize> = ds.frames().iter().map(|f| f.timestep).collect();
        t.dedup();
        t
    };
    let (train, val, test) = (ts(Split::Train), ts(Split::Val), ts(Split::Test));
    assert!(test.iter().all(|t| !train.contains(t)));
    assert!(val.iter().all(|t| train.contains(t)));

    // An item: the front camera sees the head in the middle and white in the corner; the
    // mask agrees; the vertices are the pose's; eta is present and not all zero.
    let ds = HeadDataset::open(&union, Split::Val, model.clone()).expect("val");
    let item = ds.load_item(0).expect("item");
    let (w, h) = (item.width(), item.height());
    let centre = (h / 2) * w + w / 2;
    assert_eq!(item.mask[centre], 1.0);
    assert_eq!(item.mask[0], 0.0);
    assert_eq!(&item.image[0..3], &[1.0, 1.0, 1.0]);
    assert!(
        item.image[centre * 3..centre * 3 + 3]
            .iter()
            .all(|&x| x < 0.95)
    );
    // Anti-aliasing leaves fractional coverage on the silhouette.
    assert!(item.mask.iter().any(|&m| m > 0.0 && m < 1.0));
    let param = ds.frames()[0].flame_param.clone().expect("param");
    let pose = HeadPose::load_npz(&param).expect("pose");
    let want = lbs(&head.model, &pose).expect("lbs");
    assert_eq!(item.vertices, want);
    assert_eq!(item.eta.len(), 128);
    assert!(item.eta.iter().any(|&x| x != 0.0));

    // The truth of every timestep sits in truth/ under VHAP's keys, with the activations;
    // flame_param/ holds what a tracker reports: the truth plus small noise.
    let (mut n, mut max_expr, mut max_rot) = (0usize, 0.0f32, 0.0f32);
    for seq in ["brows", "anger", "free"] {
        for t in 0..2 {
            let truth = out.join(format!("{seq}/truth/{t:05}.npz"));
            let reported = out.join(format!("{seq}/flame_param/{t:05}.npz"));
            let a = HeadPose::load_npz(&truth).expect("truth");
            let b = HeadPose::load_npz(&reported).expect("flame_param");
            assert_eq!(a.shape, b.shape);
            assert_ne!(a.expr, b.expr, "{seq} {t}: tracked expression is noisy");
            for (x, y) in a.expr.iter().zip(&b.expr) {
                max_expr = max_expr.max((x - y).abs());
            }
            for (x, y) in a.rotation.iter().zip(&b.rotation) {
                max_rot = max_rot.max((x - y).abs());
            }
            let mut z = texavatars::io::npz::Npz::open(&truth).expect("npz");
            let act = z.floats("activations").expect("activations");
            assert_eq!(act.shape, vec![7]);
            assert!(act.data.iter().all(|a| (0.0..=1.0).contains(a)));
            n += 1;
        }
    }
    assert_eq!(n, 6);
    // A few standard deviations of the default levels at most (0.5 degrees of rotation).
    assert!(max_expr > 0.0 && max_expr < 0.5, "{max_expr}");
    assert!(max_rot > 0.0 && max_rot < 3.0f32.to_radians(), "{max_rot}");
    // Training never reads truth/: without it the splits load and read as before.
    for seq in std::fs::read_dir(&out).expect("out").flatten() {
        let t = seq.path().join("truth");
        if t.is_dir() {
            std::fs::remove_dir_all(&t).expect("rm truth");
        }
    }
    let ds = HeadDataset::open(&union, Split::Val, model.clone()).expect("val");
    let again = ds.load_item(0).expect("item without truth/");
    assert_eq!(again.vertices, item.vertices);
    assert_eq!(again.eta, item.eta);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn interrupted_runs_resume_and_reproduce() {
    let out = out_dir("resume");
    let first = generate(&out);
    assert_eq!(first.skipped_timesteps, 0);
    let img = out.join("jaw/images/00001_03.png");
    let before = std::fs::read(&img).expect("image");
    let json_before = std::fs::read(out.join("union/transforms_train.json")).expect("json");
    // Lose one image, as if the run had stopped while writing it.
    std::fs::remove_file(&img).expect("remove");
    let again = generate(&out);
    assert_eq!(again.rendered_timesteps, 1);
    assert_eq!(again.skipped_timesteps, first.timesteps - 1);
    assert_eq!(std::fs::read(&img).expect("image"), before);
    assert_eq!(
        std::fs::read(out.join("union/transforms_train.json")).expect("json"),
        json_before
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn free_goes_beyond_training_and_test_is_a_new_combination() {
    let head = HeadAsset::embedded().expect("head");
    let c = SynthConfig::default();
    let seqs = synth::sequences::sequences(&c, &head.model, &head.meta);
    let max_rot = |s: &synth::Sequence| {
        s.frames
            .iter()
            .map(|p| p.rotation.iter().map(|x| x.abs()).fold(0.0, f32::max))
            .fold(0.0, f32::max)
    };
    let max_expr = |s: &synth::Sequence| {
        s.frames
            .iter()
            .map(|p| p.expr.iter().copied().fold(0.0, f32::max))
            .fold(0.0, f32::max)
    };
    let active = |p: &HeadPose| p.expr.iter().filter(|&&x| x > 0.3).count();
    let train: Vec<_> = seqs
        .iter()
        .filter(|s| s.role == synth::Role::Train)
        .collect();
    let free = seqs
        .iter()
        .find(|s| s.role == synth::Role::Free)
        .expect("free");
    let test = seqs
        .iter()
        .find(|s| s.role == synth::Role::Test)
        .expect("test");
    assert_eq!(train.len(), 10);
    let train_rot = train.iter().map(|s| max_rot(s)).fold(0.0, f32::max);
    let train_expr = train.iter().map(|s| max_expr(s)).fold(0.0, f32::max);
    assert!(
        max_rot(free) > 1.5 * train_rot,
        "{} vs {}",
        max_rot(free),
        train_rot
    );
    assert!(max_expr(free) > train_expr);
    // No training frame activates as many units at once as the held-out peak.
    let train_active = train
        .iter()
        .flat_map(|s| &s.frames)
        .map(active)
        .max()
        .unwrap_or(0);
    let test_active = test.frames.iter().map(active).max().unwrap_or(0);
    assert!(
        test_active > train_active,
        "{test_active} vs {train_active}"
    );
}

#[test]
fn wrinkles_change_shading_only_and_eta_encodes_them() {
    let head = HeadAsset::embedded().expect("head");
    let app = synth::appearance::bake(&head, 128, 7).expect("bake");
    let meta = &head.meta;
    let mut pose = HeadPose::neutral(&head.model);
    let act0 = app.activations(&pose);
    assert!(act0.iter().all(|&a| a == 0.0));
    pose.expr[meta.expr("browInnerUp").expect("unit")] = 1.0;
    let act = app.activations(&pose);
    assert_eq!(act[0], 1.0, "forehead lines follow browInnerUp");
    assert_eq!(act[2], 0.0, "crow's feet do not");
    // Same geometry, with and without the wrinkles: same mask, darker forehead.
    let c = SynthConfig {
        width: 48,
        height: 64,
        ..SynthConfig::default()
    };
    let cams = synth::cameras::rig(&c, glam::Vec3::new(0.0, -0.02, -0.02));
    let verts = lbs(&head.model, &pose).expect("lbs");
    let cam = &cams[c.val_camera];
    let r = |a: &[f32; 7]| synth::render::render(cam, 2, &verts, &head.mesh, &app, a, 0.5);
    let (plain, lined) = (r(&act0), r(&act));
    assert_eq!(plain.mask, lined.mask);
    let diff: Vec<f32> = plain
        .rgb
        .iter()
        .zip(&lined.rgb)
        .map(|(a, b)| a - b)
        .collect();
    assert!(diff.iter().all(|&d| d >= -1e-6), "wrinkles only darken");
    let changed: Vec<usize> = (0..diff.len() / 3)
        .filter(|&p| diff[p * 3] > 0.01)
        .collect();
    assert!(!changed.is_empty());
    // Changed pixels are in the upper part of the face (forehead).
    let mean_row = changed.iter().map(|&p| (p / 48) as f32).sum::<f32>() / changed.len() as f32;
    assert!(mean_row < 30.0, "{mean_row}");
    // Eta without noise is the projection of the activations.
    // Eta without noise is a deterministic, bounded code that moves with the activations
    // at a fixed expression.
    let mut rng = texavatars::util::rng::Pcg::new(1);
    let e = app.eta(&act, &pose.expr, 0.0, &mut rng);
    assert_eq!(e, app.eta(&act, &pose.expr, 0.0, &mut rng));
    assert!(e.iter().all(|x| x.abs() <= 1.0));
    let e0 = app.eta(&act0, &pose.expr, 0.0, &mut rng);
    let d: f32 = e.iter().zip(&e0).map(|(a, b)| (a - b).powi(2)).sum();
    assert!(d > 1.0, "{d}");
    // Hidden tension: the same expression with lines at rest, or none at all.
    let mut t = texavatars::synth::tension::Tension::RELAXED;
    t.gain = [0.0; 7];
    assert!(app.activations_with(&pose, &t).iter().all(|&a| a == 0.0));
    t.rest[1] = 0.6;
    assert_eq!(app.activations_with(&pose, &t)[1], 0.6);
}

/// The default capture, without rendering: the hidden tension makes the activations
/// something the expression coefficients do not determine, and eta recovers them.
#[test]
fn activations_need_eta_and_free_stays_beyond_training_in_the_tracked_parameters() {
    let head = HeadAsset::embedded().expect("head");
    let c = SynthConfig {
        texture_res: 64,
        ..SynthConfig::default()
    };
    let cap = synth::capture(&c, &head).expect("capture");
    let frames: Vec<&synth::Frame> = cap.sequences.iter().flat_map(|s| &s.1).collect();
    assert_eq!(frames.len() as u64, c.timesteps());
    // Lines at a near-neutral expression, and none at a strong one.
    let max = |a: &[f32]| a.iter().copied().fold(0.0f32, f32::max);
    let lines_at_rest = frames
        .iter()
        .filter(|f| {
            max(cap.appearance.drive(&f.truth).as_slice()) < 0.1
                && max(f.activations.as_slice()) > 0.2
        })
        .count();
    let smooth_when_strong = frames
        .iter()
        .filter(|f| {
            max(cap.appearance.drive(&f.truth).as_slice()) > 0.6
                && max(f.activations.as_slice()) < 0.2
        })
        .count();
    assert!(
        lines_at_rest > 0 && smooth_when_strong > 0,
        "{lines_at_rest} {smooth_when_strong}"
    );
    // The regressions of `synth --analyse`: eta explains the activations far better.
    let samples: Vec<synth::analysis::Sample> = frames.iter().map(|f| (*f).into()).collect();
    let [tracked, truth, eta] = synth::analysis::explain(&samples).expect("explain");
    eprintln!(
        "R^2 tracked {:.3} {:?}\nR^2 true {:.3} {:?}\nR^2 eta {:.3}",
        tracked.mean, tracked.per_activation, truth.mean, truth.per_activation, eta.mean
    );
    assert!(eta.mean > 0.8, "eta R^2 {}", eta.mean);
    assert!(
        tracked.mean < eta.mean - 0.25,
        "{} vs {}",
        tracked.mean,
        eta.mean
    );
    assert!(
        truth.mean < eta.mean - 0.2,
        "{} vs {}",
        truth.mean,
        eta.mean
    );
    // FREE is beyond every training frame also in what the tracker reports.
    let rot = |f: &synth::Frame| {
        f.reported
            .rotation
            .iter()
            .map(|x| x.abs())
            .fold(0.0, f32::max)
    };
    let of = |role| {
        cap.sequences
            .iter()
            .filter(|s| s.0.role == role)
            .flat_map(|s| s.1.iter())
            .map(rot)
            .fold(0.0f32, f32::max)
    };
    assert!(of(synth::Role::Free) > 1.5 * of(synth::Role::Train));
}

/// `synth --subject K` and `synth --analyse DIR` through the command line: another shape
/// and appearance in the same layout, and the analysis printed and written.
#[test]
fn subjects_differ_in_shape_and_appearance_and_the_analysis_runs() {
    let dir = out_dir("subject");
    std::fs::create_dir_all(&dir).expect("dir");
    let cfg = dir.join("tiny.json");
    std::fs::write(&cfg, serde_json::to_string(&tiny_config()).expect("json")).expect("write");
    let one = dir.join("s1");
    cli::texavatars_ok([
        "synth".as_ref(),
        "--subject".as_ref(),
        "1".as_ref(),
        "--config".as_ref(),
        cfg.as_os_str(),
        "--out".as_ref(),
        one.as_os_str(),
    ]);
    let head = HeadAsset::embedded().expect("head");
    let s1 = synth::Subject::new(1, head.model.num_shape, tiny_config().seed);
    let canonical = HeadPose::load_npz(&one.join("union/canonical_flame_param.npz")).expect("c");
    assert_eq!(canonical.shape, s1.shape);
    assert!(canonical.shape.iter().any(|&x| x != 0.0));
    let p = HeadPose::load_npz(&one.join("jaw/flame_param/00001.npz")).expect("param");
    assert_eq!(p.shape, s1.shape);
    let recorded = SynthConfig::load(&one.join("synth/config.json")).expect("recorded");
    assert_eq!(recorded.subject, 1);
    // Subject 0 of the same settings looks different.
    let zero = dir.join("s0");
    synth::generate(&tiny_config(), &head, &zero, &mut |_| {}).expect("subject 0");
    let img = |d: &Path| {
        texavatars::io::image::read_rgb(&d.join("jaw/images/00001_08.png")).expect("png")
    };
    let (a, b) = (img(&zero), img(&one));
    let diff = a
        .rgb
        .iter()
        .zip(&b.rgb)
        .filter(|(x, y)| (*x - *y).abs() > 0.05)
        .count();
    assert!(diff > 20, "{diff} pixels differ");
    // The analysis of an export.
    let text = cli::texavatars_ok(["synth".as_ref(), "--analyse".as_ref(), one.as_os_str()]);
    assert!(
        text.contains("tracked expression") && text.contains("eta") && text.contains("R^2"),
        "{text}"
    );
    assert!(text.contains("tracking error"), "{text}");
    assert!(one.join("synth/analysis.json").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn shipped_configs_load_and_the_default_matches_the_code() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let small = SynthConfig::load(&root.join("synth.json")).expect("synth.json");
    assert_eq!(small, SynthConfig::default());
    // A config written before subjects, tension and tracking noise existed still reads,
    // with their defaults.
    let dir = out_dir("oldcfg");
    std::fs::create_dir_all(&dir).expect("dir");
    let old = dir.join("old.json");
    std::fs::write(
        &old,
        r#"{"width": 138, "height": 200, "frames_per_sequence": 8}"#,
    )
    .expect("write");
    let c = SynthConfig::load(&old).expect("old config");
    assert_eq!((c.frames_per_sequence, c.subject), (8, 0));
    assert_eq!(c.tracking, SynthConfig::default().tracking);
    let _ = std::fs::remove_dir_all(&dir);
    let full = SynthConfig::load(&root.join("synth_802x550.json")).expect("802x550");
    assert_eq!((full.width, full.height), (550, 802));
}

#[test]
fn bad_configs_name_the_file_and_field() {
    let dir = out_dir("badcfg");
    std::fs::create_dir_all(&dir).expect("dir");
    let p = dir.join("c.json");
    std::fs::write(&p, r#"{"width": 100, "colour": 3}"#).expect("write");
    let e = SynthConfig::load(&p).unwrap_err().to_string();
    assert!(e.contains("c.json") && e.contains("colour"), "{e}");
    std::fs::write(&p, r#"{"val_camera": 16}"#).expect("write");
    let e = SynthConfig::load(&p).unwrap_err().to_string();
    assert!(e.contains("c.json") && e.contains("val_camera"), "{e}");
    std::fs::write(&p, r#"{"width": 10"#).expect("write");
    let e = SynthConfig::load(&p).unwrap_err().to_string();
    assert!(e.contains("c.json") && e.contains("line 1"), "{e}");
    // Through the command line: a non-zero exit and the message.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["synth", "--out"])
        .arg(dir.join("never"))
        .arg("--config")
        .arg(&p)
        .output()
        .expect("run");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("c.json"), "{err}");
    assert!(!dir.join("never").exists(), "nothing written on bad input");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_demo_refuses_a_benchmark_made_with_other_defaults_and_keeps_it() {
    // An `out/demo` from before this version: its benchmark records 8 frames per sequence.
    let out = out_dir("demo-old");
    let data = out.join("data");
    std::fs::create_dir_all(data.join("synth")).expect("dir");
    let old = SynthConfig {
        frames_per_sequence: 8,
        ..SynthConfig::default()
    };
    let recorded = data.join("synth/config.json");
    std::fs::write(&recorded, serde_json::to_string(&old).expect("json")).expect("write");
    std::fs::create_dir_all(out.join("run")).expect("run dir");
    std::fs::write(out.join("run/avatar.bpk"), b"earlier avatar").expect("avatar");
    let opts = texavatars::demo::DemoOptions {
        out: out.clone(),
        synth_config: SynthConfig::default(),
        train_config: texavatars::demo::default_train_config(),
        eval_stride: 4,
        install_weights: false,
        force: false,
    };
    let e = texavatars::demo::run(&opts, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("config.json")
            && e.contains("frames_per_sequence")
            && e.contains("`texavatars demo` command with --force"),
        "{e}"
    );
    // The paper-scale demo (`--paper`) checks against its own benchmark settings.
    let (paper, train) = texavatars::demo::paper_configs().expect("paper configs");
    std::fs::write(
        &recorded,
        serde_json::to_string(&SynthConfig::default()).expect("json"),
    )
    .expect("write");
    let e = texavatars::demo::run(
        &texavatars::demo::DemoOptions {
            synth_config: paper,
            train_config: train,
            ..opts.clone()
        },
        &mut |_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("recorded 200, now 802") && e.contains("--force"),
        "{e}"
    );
    // Nothing was deleted or overwritten.
    assert!(recorded.is_file());
    assert_eq!(
        std::fs::read(out.join("run/avatar.bpk")).expect("avatar"),
        b"earlier avatar"
    );
    let _ = std::fs::remove_dir_all(&out);
}
