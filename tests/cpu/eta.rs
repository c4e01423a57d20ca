//! eta from a capture's own images (`texavatars eta`, `src/eta/`): the face crop and the
//! VGG16 features against an independent numpy computation
//! (`tests/fixtures/eta/make_expected.py`), and the command on the tiny synthetic set: every
//! timestep coded, the projection fitted on the training split only, existing files kept
//! unless `--force`, a given projection's cameras enforced.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use texavatars::data::eta::{EtaFiles, EtaSource};
use texavatars::data::vhap::{ETA_DIM, eta_path, load_transforms};
use texavatars::data::{HeadDataset, Split};
use texavatars::eta::compute::frontal_camera;
use texavatars::eta::crop::{SquareBox, crop};
use texavatars::eta::projection::FILE_NAME;
use texavatars::eta::{EtaOptions, Extractor, Projection, compute};
use texavatars::head::HeadAsset;
use texavatars::io::npy::{self, Array};
use texavatars::metrics::nets::Net;
use texavatars::metrics::weights::HostWeights;

use crate::common::fixture_path;

/// Chris Wellons' lowbias32, as `make_expected.py` computes it.
fn lowbias32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// `n` values in [-1, 1) of stream `layer` (`uniform` of `make_expected.py`).
fn uniform(layer: u32, n: usize) -> Vec<f64> {
    (0..n as u32)
        .map(|i| {
            f64::from(lowbias32(i.wrapping_add(1_000_003 * layer))) / 4_294_967_296.0 * 2.0 - 1.0
        })
        .collect()
}

/// VGG16 weights from the hash (`weights` of `make_expected.py`); the layers past relu4_3
/// and the LPIPS layers, which the features do not read, are zeros.
fn hashed_vgg16() -> HostWeights {
    let net = Net::Vgg16;
    let convs = net
        .convs()
        .iter()
        .enumerate()
        .map(|(l, c)| {
            let n = c.out_channels * c.in_channels * 9;
            let fan_in = (c.in_channels * 9) as f64;
            let (w, b) = if l < 10 {
                let s = 3f64.sqrt() * (2.0 / fan_in).sqrt();
                (
                    uniform(l as u32, n)
                        .iter()
                        .map(|u| (u * s) as f32)
                        .collect(),
                    uniform(l as u32 + 100, c.out_channels)
                        .iter()
                        .map(|u| (0.02 * u) as f32)
                        .collect(),
                )
            } else {
                (vec![0.0; n], vec![0.0; c.out_channels])
            };
            (
                Array {
                    shape: vec![c.out_channels, c.in_channels, 3, 3],
                    data: w,
                },
                Array {
                    shape: vec![c.out_channels],
                    data: b,
                },
            )
        })
        .collect();
    let lins = net
        .tap_channels()
        .into_iter()
        .map(|c| Array {
            shape: vec![1, c, 1, 1],
            data: vec![0.0; c],
        })
        .collect();
    HostWeights { net, convs, lins }
}

fn extractor() -> Extractor {
    Extractor::from_host(&hashed_vgg16(), &Device::flex())
}

#[test]
fn crop_and_features_match_an_independent_numpy_computation() {
    let spec: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixture_path("eta/expected.json")).expect("read"),
    )
    .expect("json");
    let b = &spec["box"];
    let f = |k: &str| b[k].as_f64().expect("number") as f32;
    let bx = SquareBox {
        cx: f("cx"),
        cy: f("cy"),
        side: f("side"),
    };
    let size = spec["size"].as_u64().expect("size") as usize;
    let img = texavatars::io::image::read_rgb(&fixture_path("metrics/reference.png")).expect("png");
    let c = crop(&img.rgb, img.width, img.height, &bx, size);
    let want = npy::read(&fixture_path("eta/crop.npy")).expect("crop.npy");
    assert_eq!(want.shape, [size, size, 3]);
    let worst = c
        .iter()
        .zip(&want.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst < 2e-5, "crop differs from numpy's by {worst}");

    let got = extractor().features(&[c], size);
    let want = npy::read(&fixture_path("eta/expected.npy")).expect("expected.npy");
    assert_eq!(got.len(), 1);
    assert_eq!(got[0].len(), want.data.len());
    assert_eq!(want.data.len(), texavatars::eta::features::dims());
    let top = want.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    for (i, (a, e)) in got[0].iter().zip(&want.data).enumerate() {
        assert!(
            (a - e).abs() <= 1e-4 * top + 1e-3 * e.abs(),
            "feature {i}: {a} vs numpy {e}"
        );
    }
}

/// The tiny benchmark (24 x 32 pixels, two frames per sequence) in a fresh folder.
fn tiny(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("texavatars-eta-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    crate::tiny::synth_data(&dir);
    dir.join("union")
}

fn opts(data: &Path) -> EtaOptions {
    let mut o = EtaOptions::new(data);
    o.crop = 32;
    o
}

fn timestep_files(data: &Path, split: Split) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = load_transforms(&data.join(split.file_name()))
        .expect("transforms")
        .into_iter()
        .filter_map(|f| f.flame_param)
        .collect();
    v.sort();
    v.dedup();
    v
}

fn code(param: &Path) -> Vec<f32> {
    npy::read(&eta_path(param)).expect("eta file").data
}

#[test]
fn eta_codes_every_timestep_with_a_projection_fitted_on_train_only() {
    let data = tiny("codes");
    let ex = extractor();
    // The benchmark's own eta files are there: nothing is written without --force.
    let e = compute(&opts(&data), &ex, &mut |_| {}).expect_err("existing eta files");
    let msg = e.to_string();
    assert!(
        msg.contains("eta") && msg.contains(".npy") && msg.contains("--force"),
        "{msg}"
    );
    assert!(
        !data.join(FILE_NAME).exists(),
        "nothing written before the refusal"
    );

    let mut o = opts(&data);
    o.force = true;
    let r = compute(&o, &ex, &mut |_| {}).expect("eta");
    assert!(r.fitted);
    assert_eq!(r.projection, data.join(FILE_NAME));
    // The default camera is the training split's most frontal one. The benchmark's rig
    // (src/synth/cameras.rs) puts camera 8, the validation camera, at 0 degrees and camera 7
    // a few degrees from it; every other camera is at least 8 degrees off the front.
    let model = std::sync::Arc::new(HeadAsset::embedded().expect("head").model);
    let test_set = HeadDataset::open(&data, Split::Test, model.clone()).expect("test split");
    let all = frontal_camera(&test_set).expect("frontal");
    assert!(all == 7 || all == 8, "all cameras: {all}");
    assert_eq!(r.cameras, [7], "the training split's most frontal camera");

    let train = timestep_files(&data, Split::Train);
    let test = timestep_files(&data, Split::Test);
    let free = timestep_files(&data, Split::Free);
    assert_eq!(r.timesteps["train"], train.len());
    assert_eq!(r.timesteps["test"], test.len());
    assert_eq!(r.timesteps["free"], free.len());
    for p in train.iter().chain(&test).chain(&free) {
        let c = code(p);
        assert_eq!(c.len(), ETA_DIM, "{}", p.display());
        assert!(c.iter().all(|v| v.is_finite()));
    }
    // Every split reports image codes of this projection.
    for split in Split::ALL {
        let files = EtaFiles::scan(&load_transforms(&data.join(split.file_name())).expect("split"))
            .expect("scan");
        assert_eq!(files.with_file, files.timesteps, "{split}");
        assert_eq!(
            files.projection_ids().into_iter().collect::<Vec<_>>(),
            [r.projection_id.as_str()]
        );
    }
    let src_dir = eta_path(&train[0]).parent().expect("eta dir").to_path_buf();
    let source = EtaSource::read(&src_dir)
        .expect("read")
        .expect("source.json");
    assert_eq!(source.cameras, r.cameras);

    // Fitted on training timesteps only: over them the codes are centred, with mean
    // variance 1 over the components that carry variance.
    let p = Projection::load(&data.join(FILE_NAME)).expect("projection");
    assert_eq!(p.meta.timesteps, train.len());
    assert!(p.meta.rank >= 1 && p.meta.rank < train.len());
    let codes: Vec<Vec<f32>> = train.iter().map(|t| code(t)).collect();
    let mut mean_var = 0.0;
    for k in 0..p.meta.rank {
        let m: f32 = codes.iter().map(|c| c[k]).sum::<f32>() / codes.len() as f32;
        let v: f32 =
            codes.iter().map(|c| (c[k] - m).powi(2)).sum::<f32>() / (codes.len() - 1) as f32;
        assert!(m.abs() < 1e-3, "component {k}: mean {m}");
        mean_var += v / p.meta.rank as f32;
    }
    assert!((mean_var - 1.0).abs() < 1e-2, "mean variance {mean_var}");
    assert!(
        codes
            .iter()
            .all(|c| c[p.meta.rank..].iter().all(|v| *v == 0.0))
    );

    // Changing a test image changes that timestep's code and nothing of the projection.
    let before = std::fs::read(data.join(FILE_NAME)).expect("read");
    let test_frames = load_transforms(&data.join(Split::Test.file_name())).expect("test");
    let f = test_frames
        .iter()
        .find(|f| f.camera_index == r.cameras[0])
        .expect("a test frame of the code's camera");
    let img = image::open(&f.image).expect("png").to_rgb8();
    let dark = image::RgbImage::from_pixel(img.width(), img.height(), image::Rgb([40, 30, 20]));
    dark.save(&f.image).expect("save");
    let param = f.flame_param.clone().expect("param");
    let old = code(&param);
    compute(&o, &ex, &mut |_| {}).expect("again");
    assert_eq!(
        std::fs::read(data.join(FILE_NAME)).expect("read"),
        before,
        "projection unchanged"
    );
    assert_ne!(
        code(&param),
        old,
        "the test timestep's code follows its own image"
    );
    assert_eq!(code(&train[0]), codes[0], "training codes unchanged");

    // A run trained on these codes keeps their projection; codes made with another one
    // are told apart (cross-reenactment needs the avatar's projection).
    let run = data.parent().expect("root").join("run");
    std::fs::create_dir_all(&run).expect("mkdir");
    let train_frames = load_transforms(&data.join(Split::Train.file_name())).expect("train");
    let kept = texavatars::eta::projection::copy_for_run(&train_frames, &run)
        .expect("copy")
        .expect("image codes have a projection");
    assert_eq!(std::fs::read(&kept).expect("read"), before);
    let same = EtaSource::read(&src_dir).expect("read").expect("source");
    assert!(texavatars::eta::projection::run_mismatch([&same], &run, "motion").is_none());
    let other = EtaSource {
        projection_id: "0000000000000000".into(),
        ..same.clone()
    };
    let w = texavatars::eta::projection::run_mismatch([&other], &run, "motion").expect("warning");
    assert!(
        w.contains("--projection") && w.contains(&r.projection_id),
        "{w}"
    );

    // A given projection's cameras are the codes' cameras.
    let mut given = opts(&data);
    given.force = true;
    given.projection = Some(data.join(FILE_NAME));
    given.cameras = vec![(r.cameras[0] + 1) % 16];
    let e = compute(&given, &ex, &mut |_| {}).expect_err("other camera");
    assert!(
        e.to_string().contains("--camera") && e.to_string().contains("fitted on cameras"),
        "{e}"
    );
    given.cameras.clear();
    let applied = compute(&given, &ex, &mut |_| {}).expect("apply");
    assert!(!applied.fitted);
    assert_eq!(applied.projection_id, r.projection_id);
    assert_eq!(
        code(&train[0]),
        codes[0],
        "the same projection gives the same codes"
    );

    // A single sequence's export (the FREE sequence's own transforms.json) takes the
    // training export's projection; it cannot fit one.
    let free_export = data.parent().expect("root").join("free");
    let e = compute(&opts(&free_export), &ex, &mut |_| {}).expect_err("no training split");
    assert!(e.to_string().contains("--projection"), "{e}");
    let mut single = opts(&free_export);
    single.projection = Some(data.join(FILE_NAME));
    single.force = true;
    let coded = compute(&single, &ex, &mut |_| {}).expect("free export");
    assert_eq!(coded.timesteps["transforms"], free.len());
    assert_eq!(coded.projection_id, r.projection_id);
    let _ = std::fs::remove_dir_all(data.parent().expect("root"));
}

#[test]
fn eta_without_a_training_split_needs_a_projection() {
    let dir = std::env::temp_dir().join(format!("texavatars-eta-none-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("mkdir");
    let e = compute(&opts(&dir), &extractor(), &mut |_| {}).expect_err("empty");
    assert!(e.to_string().contains("no split found"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn eta_command_without_weights_names_the_install_command() {
    let dir = std::env::temp_dir().join(format!("texavatars-eta-noweights-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("mkdir");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["eta", "--data"])
        .arg(&dir)
        .env("TEXAVATARS_WEIGHTS", &dir)
        .output()
        .expect("run");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("vgg16.safetensors") && stderr.contains("texavatars weights install"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
