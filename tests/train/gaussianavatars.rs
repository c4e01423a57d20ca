//! GaussianAvatars trained in texavatars (`train --model gaussianavatars`): the loss goes
//! down on every backend, densification keeps every Gaussian bound to a triangle and never
//! empties one, a run stopped inside an interval resumes to the same Gaussians, the
//! optimiser's moments follow densification's rows, the shipped config loads and the
//! command line trains and writes GaussianAvatars' folder layout.

use std::path::Path;

use burn::module::{Module, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use texavatars::device::BackendKind;
use texavatars::models::gaussianavatars::GaModel;
use texavatars::splat::ply;
use texavatars::train::gaussianavatars::{self as ga, GaTrainConfig, edit_moments, objective};
use texavatars::train::{FrameLoader, files};

use super::{batch_of, data, head, options, out_dir};

fn tiny(iterations: usize) -> GaTrainConfig {
    GaTrainConfig {
        iterations,
        checkpoint_every: iterations,
        sh_degree: 1,
        val_frames: 0,
        log_every: 0,
        seed: 1,
        backend: BackendKind::Flex,
        flame_refinement: true,
    }
}

/// The objective of `model` on 4 fixed training frames.
fn eval_loss(model: &GaModel, device: &Device) -> f64 {
    let ds = texavatars::data::HeadDataset::open(
        data(),
        texavatars::data::Split::Train,
        std::sync::Arc::new(head().model.clone()),
    )
    .unwrap();
    let frames = FrameLoader::spread(ds.len(), 4);
    let total: f64 = frames
        .iter()
        .map(|&i| {
            let f = objective(
                model,
                &head().model.faces,
                &batch_of(&[i], device),
                model.sh_degree,
                false,
                None,
            );
            f.terms.total.into_scalar::<f32>() as f64
        })
        .sum();
    total / frames.len() as f64
}

fn loss_goes_down(backend: BackendKind, iterations: usize, name: &str) {
    let c = tiny(iterations);
    let out = out_dir(name);
    let inner = backend.device();
    let faces = head().model.faces.len();
    let initial = GaModel::init(faces, c.sh_degree, c.seed, &inner).unwrap();
    let before = eval_loss(&initial, &inner);
    let r = ga::train(&c, &options(&out, backend)).expect("train");
    assert!(r.complete);
    let after = eval_loss(&r.model, &inner);
    println!(
        "{name}: loss on 4 fixed frames {before:.4} -> {after:.4} in {iterations} iterations, \
         {} -> {} Gaussians, {:.1} s",
        initial.len(),
        r.gaussians,
        r.seconds
    );
    assert!(
        after.is_finite() && after < 0.9 * before,
        "{before} -> {after}"
    );
    // Densification ran and kept every Gaussian on a valid triangle, none emptied.
    let (stored, binding) = ply::read_bound(&r.output.join("point_cloud.ply")).unwrap();
    assert_eq!(stored.len(), r.gaussians);
    assert_ne!(r.gaussians, faces, "densification changed the count");
    let mut per_face = vec![0usize; faces];
    for &b in &binding {
        assert!((b as usize) < faces);
        per_face[b as usize] += 1;
    }
    assert!(
        per_face.iter().all(|&c| c > 0),
        "a triangle lost all its Gaussians"
    );
    assert!(r.output.join("flame_param.npz").is_file());
    assert!(out.join(files::IDENTITY).is_file());
    // FLAME refinement is on by default: the refined parameters moved from the tracked ones.
    let refined = texavatars::data::refined::RefinedParams::load(&out)
        .unwrap()
        .expect("refined parameters");
    let train = texavatars::data::HeadDataset::open(
        data(),
        texavatars::data::Split::Train,
        std::sync::Arc::new(head().model.clone()),
    )
    .unwrap();
    let tracked = texavatars::train::refine::Timesteps::of_dataset(&train).unwrap();
    assert_eq!(refined.keys, tracked.keys);
    assert_ne!(refined.poses, tracked.tracked);
}

#[test]
fn ga_tiny_run_lowers_the_loss_on_flex() {
    loss_goes_down(BackendKind::Flex, 30, "ga-flex");
}

#[test]
fn ga_tiny_run_lowers_the_loss_on_ndarray() {
    loss_goes_down(BackendKind::Cpu, 10, "ga-ndarray");
}

#[test]
fn ga_tiny_run_lowers_the_loss_on_wgpu() {
    loss_goes_down(BackendKind::Wgpu, 10, "ga-wgpu");
}

/// Stopped after 3 of 8 iterations (checkpoints every 4, densification every iteration at
/// this length), resumed: the same Gaussians, to the bit, as the uninterrupted run.
#[test]
fn ga_run_stopped_inside_an_interval_resumes_to_the_same_gaussians() {
    let mut c = tiny(8);
    c.checkpoint_every = 4;
    let straight = ga::train(&c, &options(&out_dir("ga-straight"), BackendKind::Flex)).unwrap();
    let out = out_dir("ga-stopped");
    let mut o = options(&out, BackendKind::Flex);
    o.stop_after = Some(3);
    let r = ga::train(&c, &o).unwrap();
    assert_eq!((r.end_iteration, r.complete), (3, false));
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    o.stop_after = Some(3);
    let r = ga::train(&c, &o).unwrap();
    assert_eq!((r.start_iteration, r.end_iteration), (3, 6));
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let r = ga::train(&c, &o).unwrap();
    assert!(r.complete);
    assert_ne!(straight.gaussians, head().model.faces.len());
    assert_eq!(r.model.to_stored(), straight.model.to_stored());
}

/// `edit_moments`: Adam's moments of the re-rowed parameters follow `old_from_new` (new rows
/// zero), the zeroed parameter's are all zero, the others untouched.
#[test]
fn optimiser_moments_follow_the_rows() {
    /// An optimiser record tensor: name, parameter id, shape, values.
    type Moment = (String, Option<u64>, Vec<usize>, Vec<f32>);
    #[derive(Module, Debug)]
    struct Two {
        a: Param<Tensor<2>>,
        b: Param<Tensor<1>>,
    }
    let device = Device::flex().autodiff();
    let m = Two {
        a: Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0], [3, 2]),
            &device,
        )),
        b: Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![1.0f32, 2.0], [2]),
            &device,
        )),
    };
    let loss = (m.a.val() * m.a.val()).sum() + (m.b.val() * 3.0).sum();
    let grads = GradientsParams::from_grads(loss.backward(), &m);
    let mut optim = ga::optimizer();
    let m = optim.step(0.1f64, m, grads);
    let moments = |o: &burn::optim::ModuleOptimizer| {
        let bytes = o.to_record().into_bytes().unwrap();
        let r = burn_pack::Reader::from_bytes(bytes).unwrap();
        let mut v: Vec<Moment> = r
            .into_tensors()
            .unwrap()
            .into_iter()
            .map(|t| {
                let (name, dtype, shape, id, bytes) = t.into_parts().unwrap();
                let d = TensorData::from_bytes(bytes, shape.clone(), dtype);
                (
                    name,
                    id,
                    shape.as_slice().to_vec(),
                    d.iter::<f32>().collect(),
                )
            })
            .collect();
        v.sort_by(|x, y| x.0.cmp(&y.0));
        v
    };
    let before = moments(&optim);
    assert!(before.iter().any(|t| t.1 == Some(m.a.id.val())));
    let edited = edit_moments(
        &optim,
        &[m.a.id],
        &[Some(2), None, Some(0), Some(0)],
        Some(m.b.id),
    );
    let after = moments(&edited);
    assert_eq!(before.len(), after.len());
    for (x, y) in before.iter().zip(&after) {
        assert_eq!(x.0, y.0);
        if x.1 == Some(m.a.id.val()) && x.2.len() == 2 {
            assert_eq!(y.2, vec![4, 2], "{}", x.0);
            let row = |v: &Vec<f32>, i: usize| v[2 * i..2 * i + 2].to_vec();
            assert_eq!(row(&y.3, 0), row(&x.3, 2));
            assert_eq!(row(&y.3, 1), vec![0.0, 0.0]);
            assert_eq!(row(&y.3, 2), row(&x.3, 0));
            assert_eq!(row(&y.3, 3), row(&x.3, 0));
            assert!(x.3.iter().any(|v| *v != 0.0));
        } else if x.1 == Some(m.b.id.val()) && x.2.len() == 1 {
            assert!(x.3.iter().any(|v| *v != 0.0));
            assert!(y.3.iter().all(|v| *v == 0.0), "{}", x.0);
        } else {
            assert_eq!(x, y);
        }
    }
}

#[test]
fn ga_config_loads_and_names_bad_fields() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let c = GaTrainConfig::load(&dir.join("train_gaussianavatars.json")).unwrap();
    assert_eq!((c.iterations, c.sh_degree), (3500, 3));
    let bad = out_dir("ga-badconfig");
    std::fs::create_dir_all(&bad).unwrap();
    let p = bad.join("c.json");
    std::fs::write(
        &p,
        r#"{"iterations": 10, "checkpoint_every": 5, "sh_degree": 4}"#,
    )
    .unwrap();
    let e = GaTrainConfig::load(&p).unwrap_err().to_string();
    assert!(e.contains("sh_degree") && e.contains("c.json"), "{e}");
}

/// The command line: `train --model gaussianavatars`, then `export ply` reads its folder.
#[test]
fn ga_train_command_writes_gaussianavatars_layout() {
    let out = out_dir("ga-cli");
    std::fs::create_dir_all(&out).unwrap();
    let cfg = out.join("ga.json");
    std::fs::write(&cfg, serde_json::to_string(&tiny(4)).unwrap()).unwrap();
    let run = out.join("run");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["train", "--model", "gaussianavatars", "--data"])
        .arg(data())
        .args(["--config", &s(&cfg), "--out", &s(&run)])
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let stdout = String::from_utf8_lossy(&status.stdout);
    assert!(stdout.contains("GaussianAvatars"), "{stdout}");
    assert!(
        run.join("point_cloud/iteration_4/point_cloud.ply")
            .is_file()
    );
    // A second run into the same folder is refused without --force.
    let again = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["train", "--model", "gaussianavatars", "--data"])
        .arg(data())
        .args(["--config", &s(&cfg), "--out", &s(&run)])
        .output()
        .unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already holds a training run"));
}

/// GaussianAvatars' learning rates reach their attributes (`training_setup`): Adam's first
/// step moves every entry of a parameter with a non-zero gradient by its learning rate; the
/// position's is `position_lr_init x extent` decayed to its first step.
#[test]
fn each_attribute_trains_at_gaussianavatars_rate() {
    use texavatars::train::gaussianavatars::constants as c;
    #[derive(Module, Debug)]
    struct Wrap {
        model: GaModel,
        refine: texavatars::train::refine::FlameRefinement,
    }
    let device = Device::flex().autodiff();
    let w = Wrap {
        model: GaModel::init(5, 1, 3, &device).unwrap(),
        refine: super::refinement(&device),
    };
    let m = &w.model;
    let before = m.to_stored().0;
    let r = &w.refine;
    let loss = m.xyz.val().sum()
        + m.features_dc.val().sum()
        + m.features_rest.as_ref().unwrap().val().sum()
        + m.opacity.val().sum()
        + m.scaling.val().sum()
        + m.rotation.val().sum()
        + r.refine_expr.val().sum()
        + r.refine_pose.val().sum()
        + r.refine_translation.val().sum();
    let grads = GradientsParams::from_grads(loss.backward(), &w);
    let (total, extent) = (100, 2.5f32);
    let mut lr = ga::lr_scheduler(total, extent);
    let rates = lr.step();
    let mut optim = ga::optimizer();
    let w = optim.step(rates, w, grads);
    let after = w.model.to_stored().0;
    let moved = |a: &[f32], b: &[f32]| -> Vec<f64> {
        a.iter()
            .zip(b)
            .map(|(x, y)| (*x as f64 - *y as f64).abs())
            .collect()
    };
    let check = |name: &str, d: Vec<f64>, want: f64| {
        for v in d {
            assert!(
                (v - want).abs() <= 1e-3 * want + 1e-7,
                "{name}: moved {v}, want {want}"
            );
        }
    };
    let pos = c::expon_lr(
        c::POSITION_LR_INIT * extent as f64,
        c::POSITION_LR_FINAL * extent as f64,
        1,
        total,
    );
    check("xyz", moved(&after.means, &before.means), pos);
    check(
        "opacity",
        moved(&after.opacity_logits, &before.opacity_logits),
        c::OPACITY_LR,
    );
    check(
        "scaling",
        moved(&after.log_scales, &before.log_scales),
        c::SCALING_LR,
    );
    check(
        "rotation",
        moved(&after.quats, &before.quats),
        c::ROTATION_LR,
    );
    // FLAME refinement (`FlameGaussianModel.training_setup`: expr, pose, translation groups).
    let values = |t: Tensor<2>| -> Vec<f32> { t.into_data().iter::<f32>().collect() };
    let zeros = |n: usize| vec![0.0f32; n];
    for (name, got, want) in [
        (
            "refine_expr",
            values(w.refine.refine_expr.val()),
            c::FLAME_EXPR_LR,
        ),
        (
            "refine_pose",
            values(w.refine.refine_pose.val()),
            c::FLAME_POSE_LR,
        ),
        (
            "refine_translation",
            values(w.refine.refine_translation.val()),
            c::FLAME_TRANS_LR,
        ),
    ] {
        check(name, moved(&got, &zeros(got.len())), want);
    }
    let sh = moved(&after.sh, &before.sh);
    // [N, 4, 3] per Gaussian: the DC coefficient first, then the three degree-1 ones.
    for (i, v) in sh.into_iter().enumerate() {
        let want = if i % 12 < 3 {
            c::FEATURE_LR
        } else {
            c::FEATURE_LR / c::FEATURE_REST_LR_DIVISOR
        };
        assert!(
            (v - want).abs() <= 1e-3 * want,
            "sh[{i}]: moved {v}, want {want}"
        );
    }
}
