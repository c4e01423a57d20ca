//! Training end to end on a tiny synthetic benchmark: the loss goes down (flex, ndarray,
//! wgpu), every parameter gets a gradient through decoders -> lift -> splat, each ablation
//! builds and steps, a stopped run resumes with its iteration count, the two learning rates
//! reach their parameter groups, the frame order survives a resume.

mod gaussianavatars;
mod gpu_sh;
mod study;
#[path = "../tiny/mod.rs"]
mod tiny;

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use burn::data::dataloader::DataLoader;
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Device, Gradients, Tensor};
use texavatars::data::refined::{self, RefinedParams};
use texavatars::data::{HeadBatcher, HeadDataset, Split};
use texavatars::device::BackendKind;
use texavatars::head::HeadAsset;
use texavatars::models::texavatars::{Ablations, Avatar, NetConfig};
use texavatars::synth::{self, SynthConfig};
use texavatars::train::refine;
use texavatars::train::{
    self, AvatarTraining, FrameLoader, IterationRecord, LossWeights, Objective, Schedule,
    TrainBatch, TrainConfig, TrainOptions, files, latest_checkpoint,
};

/// The tiny benchmark: 24 x 32 images, 2 frames per sequence (300 training frames).
fn data() -> &'static Path {
    static DATA: OnceLock<PathBuf> = OnceLock::new();
    DATA.get_or_init(|| {
        let out =
            std::env::temp_dir().join(format!("texavatars-train-data-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let config = SynthConfig {
            width: 24,
            height: 32,
            supersample: 2,
            frames_per_sequence: 2,
            free_frames: 2,
            texture_res: 64,
            ..SynthConfig::default()
        };
        let head = HeadAsset::embedded().expect("head");
        synth::generate(&config, &head, &out, &mut |_| {}).expect("synth");
        out.join("union")
    })
}

fn head() -> &'static HeadAsset {
    static HEAD: OnceLock<HeadAsset> = OnceLock::new();
    HEAD.get_or_init(|| HeadAsset::embedded().expect("head"))
}

fn out_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-train-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// The shipped tiny training config, with the embedded head's expression width.
fn tiny_config() -> TrainConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_tiny.json");
    let mut c = TrainConfig::load(&path).expect("configs/train_tiny.json");
    c.log_every = 0;
    c
}

fn options(out: &Path, backend: BackendKind) -> TrainOptions {
    let mut o = TrainOptions::new(data(), out);
    o.backend = Some(backend);
    o.head = Some(head().clone());
    o.app_log = false;
    o
}

fn vgg_installed() -> bool {
    let dir = texavatars::metrics::weights::weights_dir().expect("weights dir");
    texavatars::metrics::weights::file_in(&dir, texavatars::metrics::Net::Vgg16).is_file()
}

/// The training frames `indices` as one batch on `device`.
fn batch_of(indices: &[usize], device: &Device) -> TrainBatch {
    let ds = HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap();
    let items = indices.iter().map(|&i| ds.load_item(i).unwrap()).collect();
    TrainBatch {
        batch: HeadBatcher.try_batch(items, device).unwrap(),
        iteration: 0,
    }
}

/// `n` training frames spread over the split, as one batch.
fn batch(n: usize, device: &Device) -> TrainBatch {
    let ds = HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap();
    batch_of(&FrameLoader::spread(ds.len(), n), device)
}

fn no_vgg(avatar: Avatar) -> AvatarTraining {
    AvatarTraining {
        avatar,
        refine: None,
        objective: Objective {
            weights: LossWeights::default(),
            vgg: None,
            vgg_from: 0,
            guard: None,
        },
    }
}

/// The objective without VGG of `avatar` on 6 fixed training frames, one at a time.
fn eval_loss(avatar: &Avatar, device: &Device) -> f64 {
    let model = no_vgg(avatar.clone());
    let ds = HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap();
    let frames = FrameLoader::spread(ds.len(), 6);
    let total: f64 = frames
        .iter()
        .map(|&i| {
            let (terms, _) = model.losses(&batch_of(&[i], device), None);
            terms.total.into_scalar::<f32>() as f64
        })
        .sum();
    total / frames.len() as f64
}

/// Trains `iterations` steps of the tiny config on `backend` with the learning rates scaled
/// by `lr_scale` and checks that the loss on fixed frames went down by at least 5%.
fn loss_goes_down(backend: BackendKind, iterations: usize, lr_scale: f64, name: &str) {
    let mut c = tiny_config();
    c.lr_decoders *= lr_scale;
    c.lr_encoders *= lr_scale;
    c.iterations = iterations;
    c.checkpoint_every = iterations;
    c.val_frames = 1;
    let out = out_dir(name);
    let device = backend.autodiff_device();
    let initial = c
        .avatar()
        .unwrap()
        .init_seeded(c.seed, &head().mesh, &device)
        .unwrap();
    let inner = backend.device();
    let before = eval_loss(&initial.valid(), &inner);
    let report = train::train(&c, &options(&out, backend)).expect("train");
    assert_eq!(
        (report.start_iteration, report.end_iteration),
        (0, iterations)
    );
    let after = eval_loss(&report.avatar, &inner);
    println!(
        "{name}: loss on 6 fixed frames {before:.4} -> {after:.4} in {iterations} iterations, {:.1} s",
        report.seconds
    );
    assert!(
        after.is_finite() && after < 0.95 * before,
        "{before} -> {after}"
    );
    assert!(report.avatar_path.is_file());
    for f in [files::CONFIG, files::AVATAR_CONFIG] {
        assert!(out.join(f).is_file(), "{f}");
    }
    // burn's metric logs: every term, for training and validation.
    for split in ["train", "valid"] {
        for m in ["Loss", "L1", "D-SSIM", "VGG", "L_pos", "L_scale", "PSNR"] {
            let f = out.join(split).join("epoch-1").join(format!("{m}.log"));
            assert!(f.is_file(), "{}", f.display());
        }
    }
}

#[test]
fn tiny_run_lowers_the_loss_on_flex() {
    loss_goes_down(BackendKind::Flex, 30, 1.0, "flex");
}

#[test]
fn tiny_run_lowers_the_loss_on_ndarray() {
    loss_goes_down(BackendKind::Cpu, 30, 1.0, "ndarray");
}

/// lavapipe (no GPU) is slow and starts cold: few iterations, at 5x the learning rates.
#[test]
fn tiny_run_lowers_the_loss_on_wgpu() {
    loss_goes_down(BackendKind::Wgpu, 8, 5.0, "wgpu");
}

/// Checks that every float parameter has a finite, non-zero gradient.
struct GradCheck<'a> {
    grads: &'a Gradients,
    path: Vec<String>,
    checked: usize,
    failures: Vec<String>,
}

impl ModuleVisitor for GradCheck<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.checked += 1;
        let name = format!("{} {:?}", self.path.join("."), param.val().dims());
        match param.val().grad(self.grads) {
            None => self.failures.push(format!("{name}: no gradient")),
            Some(g) => {
                let g: Vec<f32> = g.into_data().iter::<f32>().collect();
                if g.iter().any(|v| !v.is_finite()) {
                    self.failures.push(format!("{name}: non-finite gradient"));
                } else if g.iter().all(|&v| v == 0.0) {
                    self.failures.push(format!("{name}: zero gradient"));
                }
            }
        }
    }
}

#[test]
fn every_parameter_receives_a_gradient_through_decoders_lift_and_splat() {
    let device = Device::flex().autodiff();
    let c = tiny_config();
    let avatar = c
        .avatar()
        .unwrap()
        .init_seeded(3, &head().mesh, &device)
        .unwrap();
    // burn's module display stays readable (the topology's tables are not printed).
    let shown = format!("{avatar}");
    assert!(
        shown.contains("gaussians: 339") && shown.len() < 20_000,
        "{shown}"
    );
    let model = no_vgg(avatar);
    let b = batch(2, &device);
    let (terms, psnr) = model.losses(&b, None);
    assert_eq!(psnr.dims(), [2]);
    let grads = terms.total.backward();
    let mut check = GradCheck {
        grads: &grads,
        path: Vec::new(),
        checked: 0,
        failures: Vec::new(),
    };
    model.visit(&mut check);
    // Exp2Code 3, view encoder 2 x 3, geometry 2 x 3, appearance (1 + 2 + 1) x 3.
    assert_eq!(check.checked, 3 + 6 + 6 + 12);
    assert!(check.failures.is_empty(), "{:#?}", check.failures);
}

#[test]
fn each_ablation_builds_and_runs_one_step() {
    let off = |f: fn(&mut Ablations)| {
        let mut a = Ablations {
            vgg: false,
            ..Ablations::default()
        };
        f(&mut a);
        a
    };
    let mut cases = vec![
        ("no-global-uv", off(|a| a.global_uv = false)),
        ("no-jacobian", off(|a| a.jacobian = false)),
        ("no-eta", off(|a| a.eta = false)),
        ("no-flame-refinement", off(|a| a.flame_refinement = false)),
    ];
    if vgg_installed() {
        cases.push(("vgg", Ablations::default()));
    } else {
        println!("VGG16 weights not installed (texavatars weights install): skipping the VGG case");
    }
    for (name, ablations) in cases {
        let mut c = tiny_config();
        c.ablations = ablations;
        c.iterations = 1;
        c.checkpoint_every = 1;
        c.val_frames = 1;
        // VGG from the first iteration, so that the one step uses it.
        c.vgg_start = 0.0;
        let out = out_dir(&format!("ablation-{name}"));
        let r = train::train(&c, &options(&out, BackendKind::Flex))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(r.end_iteration, 1, "{name}");
        let saved: texavatars::models::texavatars::AvatarConfig =
            serde_json::from_str(&std::fs::read_to_string(out.join(files::AVATAR_CONFIG)).unwrap())
                .unwrap();
        assert_eq!(saved.ablations, ablations, "{name}");
        assert_eq!(r.avatar.lift.mode, ablations.lift_mode(), "{name}");
        assert_eq!(r.avatar.lift.frame, ablations.frame_kind(), "{name}");
        assert_eq!(r.avatar.net.zero_eta, !ablations.eta, "{name}");
        assert_eq!(
            out.join(refined::REFINED_NPZ).is_file(),
            ablations.flame_refinement,
            "{name}"
        );
        let vgg_log = out.join("train/epoch-1/VGG.log");
        let vgg: f64 = std::fs::read_to_string(&vgg_log)
            .unwrap()
            .lines()
            .next()
            .and_then(|l| l.split(',').next().map(|v| v.trim().parse().unwrap()))
            .unwrap();
        if ablations.vgg {
            assert!(vgg > 0.0 && vgg.is_finite(), "{name}: VGG term {vgg}");
        } else {
            assert_eq!(vgg, 0.0, "{name}");
        }
    }
}

#[test]
fn vgg_on_without_weights_is_a_clear_error() {
    // Only meaningful where the weights are absent; elsewhere the VGG case above runs.
    if vgg_installed() {
        println!("VGG16 weights installed: the missing-weights error is not reachable here");
        return;
    }
    let mut c = tiny_config();
    c.ablations.vgg = true;
    let e = train::train(&c, &options(&out_dir("novgg"), BackendKind::Flex)).unwrap_err();
    assert!(e.to_string().contains("weights install"), "{e}");
}

/// `crop` trains on windows; a window larger than the frames is refused before anything is
/// written, and a run cannot be resumed with another crop.
#[test]
fn a_cropping_run_trains_and_keeps_its_crop() {
    use texavatars::data::crop::CropSize;
    let mut c = tiny_config();
    c.iterations = 2;
    c.checkpoint_every = 2;
    c.val_frames = 1;
    c.crop = Some(CropSize {
        width: 64,
        height: 16,
    });
    let out = out_dir("crop");
    let e = train::train(&c, &options(&out, BackendKind::Flex)).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("transforms_train.json") && msg.contains("64x16"),
        "{msg}"
    );
    assert!(!out.exists(), "nothing written for a refused crop");
    c.crop = Some(CropSize {
        width: 16,
        height: 16,
    });
    let run = train::train(&c, &options(&out, BackendKind::Flex)).unwrap();
    assert_eq!(run.end_iteration, 2);
    let saved = TrainConfig::load(&out.join(files::CONFIG)).unwrap();
    assert_eq!(saved.crop, c.crop);
    let mut other = c.clone();
    other.iterations = 4;
    other.crop = None;
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let e = train::train(&other, &o).unwrap_err();
    assert!(e.to_string().contains("crop"), "{e}");
}

#[test]
fn a_stopped_run_resumes_with_its_iteration_count() {
    let mut c = tiny_config();
    c.iterations = 4;
    c.checkpoint_every = 2;
    c.val_frames = 1;
    let out = out_dir("resume");
    let mut o = options(&out, BackendKind::Flex);
    o.stop_after = Some(2);
    let first = train::train(&c, &o).unwrap();
    assert_eq!((first.start_iteration, first.end_iteration), (0, 2));
    let ckpt = out.join(files::CHECKPOINTS);
    assert_eq!(latest_checkpoint(&ckpt), Some(1));

    // Without --resume the folder is refused.
    let e = train::train(&c, &options(&out, BackendKind::Flex)).unwrap_err();
    assert!(e.to_string().contains("--resume"), "{e}");

    // A resumed run starts from the checkpoint's weights and continues the count.
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let second = train::train(&c, &o).unwrap();
    assert_eq!((second.start_iteration, second.end_iteration), (2, 4));
    assert_eq!(latest_checkpoint(&ckpt), Some(2));
    assert!(out.join("train/epoch-2/Loss.log").is_file());

    // A half-written newest checkpoint is skipped for the one before.
    std::fs::write(ckpt.join("optim-2.bpk"), b"truncated").unwrap();
    assert_eq!(latest_checkpoint(&ckpt), Some(1));

    // A different avatar cannot resume this run.
    let mut other = c.clone();
    other.ablations.jacobian = false;
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let e = train::train(&other, &o).unwrap_err();
    assert!(e.to_string().contains("ablations"), "{e}");
}

/// The tiny benchmark's training split.
fn train_set() -> Arc<HeadDataset> {
    Arc::new(HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap())
}

/// A batch-1 schedule over whole frames.
fn whole_frames(seed: u64, per_epoch: usize, total: usize) -> Schedule {
    Schedule {
        seed,
        per_epoch,
        total,
        batch_size: 1,
        resume: None,
        crop: None,
    }
}

#[test]
fn the_frame_order_is_the_same_after_a_resume() {
    let ds = train_set();
    let schedule = whole_frames(9, 7, 700);
    let device = Device::flex();
    let frames = |l: &FrameLoader| -> Vec<(usize, usize, usize)> {
        l.iter()
            .map(|b| {
                let b = b.unwrap();
                (b.iteration, b.batch.timesteps[0], b.batch.camera_indices[0])
            })
            .collect()
    };
    let straight = FrameLoader::training(ds.clone(), schedule.clone(), 0, &device);
    let _ = frames(&straight);
    let second_epoch = frames(&straight);
    let resumed = FrameLoader::training(ds.clone(), schedule.clone(), 1, &device);
    assert_eq!(frames(&resumed), second_epoch);
    assert_eq!(second_epoch.first().map(|f| f.0), Some(7));
    assert_eq!(straight.num_items(), 7);
    // Every frame once per pass.
    let mut pass = train::loader::pass_order(9, 3, ds.len());
    pass.sort_unstable();
    assert_eq!(pass, (0..ds.len()).collect::<Vec<_>>());
}

/// A cropping schedule hands out windows of the frames it would have handed out whole: the
/// same frames in the same order, each image the window of the whole image, each camera the
/// window's; the windows are a function of the seed and the iteration (a resume draws the
/// same ones) and move between iterations.
#[test]
fn a_cropping_loader_hands_out_windows_of_the_same_frames() {
    let ds = train_set();
    let whole = whole_frames(4, 6, 60);
    let size = texavatars::data::crop::CropSize {
        width: 16,
        height: 20,
    };
    let cropped = Schedule {
        crop: Some(size),
        ..whole.clone()
    };
    let device = Device::flex();
    let second_epoch = |schedule: Schedule| -> Vec<TrainBatch> {
        FrameLoader::training(ds.clone(), schedule, 1, &device)
            .iter()
            .map(|b| b.unwrap())
            .collect()
    };
    let a = second_epoch(whole);
    let b = second_epoch(cropped.clone());
    let again = second_epoch(cropped);
    assert_eq!(a.len(), 6);
    let mut origins = std::collections::HashSet::new();
    for ((a, b), c) in a.iter().zip(&b).zip(&again) {
        assert_eq!(a.iteration, b.iteration);
        assert_eq!(a.batch.timesteps, b.batch.timesteps);
        assert_eq!(a.batch.camera_indices, b.batch.camera_indices);
        let (ca, cb) = (a.batch.cameras[0], b.batch.cameras[0]);
        assert_eq!((cb.width, cb.height), (16, 20));
        assert_eq!(
            (cb.fx, cb.fy, cb.world_to_camera),
            (ca.fx, ca.fy, ca.world_to_camera)
        );
        let (x0, y0) = (
            (ca.cx - cb.cx).round() as usize,
            (ca.cy - cb.cy).round() as usize,
        );
        let window = train::loader::crop_window(&size, 4, a.iteration, 0, ca.width, ca.height);
        assert_eq!((window.x0 as usize, window.y0 as usize), (x0, y0));
        origins.insert((x0, y0));
        let full = a
            .batch
            .images
            .clone()
            .into_data()
            .iter::<f32>()
            .collect::<Vec<_>>();
        let part = b
            .batch
            .images
            .clone()
            .into_data()
            .iter::<f32>()
            .collect::<Vec<_>>();
        let w = ca.width as usize;
        for y in 0..20 {
            for x in 0..16 {
                for ch in 0..3 {
                    assert_eq!(
                        part[(y * 16 + x) * 3 + ch],
                        full[((y0 + y) * w + x0 + x) * 3 + ch]
                    );
                }
            }
        }
        assert_eq!(c.batch.cameras[0], cb, "the same window on every pass");
        assert_eq!(
            a.batch.expr.clone().into_data(),
            b.batch.expr.clone().into_data()
        );
    }
    assert!(origins.len() > 3, "windows move: {origins:?}");
}

/// Largest |after - before| over the parameters whose path contains `part`.
struct MaxStep<'a> {
    before: &'a AvatarTraining,
    path: Vec<String>,
    steps: Vec<(String, f32)>,
}

impl ModuleVisitor for MaxStep<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        struct Find {
            id: burn::module::ParamId,
            found: Option<Vec<f32>>,
        }
        impl ModuleVisitor for Find {
            fn visit_float<const F: usize>(&mut self, p: &Param<Tensor<F>>) {
                if p.id == self.id {
                    self.found = Some(p.val().into_data().iter::<f32>().collect());
                }
            }
        }
        let mut find = Find {
            id: param.id,
            found: None,
        };
        self.before.visit(&mut find);
        let old = find.found.expect("same parameter ids");
        let new: Vec<f32> = param.val().into_data().iter::<f32>().collect();
        let max = old
            .iter()
            .zip(&new)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        self.steps.push((self.path.join("."), max));
    }
}

#[test]
fn decoders_and_encoders_train_at_their_learning_rates() {
    let device = Device::flex().autodiff();
    let c = tiny_config();
    let avatar = c
        .avatar()
        .unwrap()
        .init_seeded(4, &head().mesh, &device)
        .unwrap();
    let mut model = no_vgg(avatar);
    model.refine = Some(refinement(&device));
    let (terms, _) = model.losses(&batch(1, &device), None);
    let grads = burn::optim::GradientsParams::from_grads(terms.total.backward(), &model);
    let mut optim = train::optimizer(&c);
    let mut lr = train::lr_scheduler(&c);
    let stepped = optim.step(lr.step(), model.clone(), grads);
    let mut v = MaxStep {
        before: &model,
        path: Vec::new(),
        steps: Vec::new(),
    };
    stepped.visit(&mut v);
    // Adam's first step moves every parameter with a non-zero gradient by exactly lr (its
    // bias-corrected m / sqrt(v) is the gradient's sign; eps is 1e-15).
    for (path, step) in &v.steps {
        let want = if path.contains("exp2code") || path.contains("view_encoder") {
            c.lr_encoders
        } else if path.contains(refine::REFINE_EXPR) {
            c.lr_flame_expr
        } else if path.contains(refine::REFINE_POSE) {
            c.lr_flame_pose
        } else if path.contains(refine::REFINE_TRANSLATION) {
            c.lr_flame_translation
        } else {
            c.lr_decoders
        } as f32;
        assert!(
            (step - want).abs() < 0.02 * want,
            "{path}: largest step {step}, learning rate {want}"
        );
    }
    // The networks' 27 and FLAME refinement's 3 (expression, pose, translation).
    assert_eq!(v.steps.len(), 30);
    for part in [
        refine::REFINE_EXPR,
        refine::REFINE_POSE,
        refine::REFINE_TRANSLATION,
    ] {
        assert!(
            v.steps.iter().any(|(p, _)| p.contains(part)),
            "{part}: {:?}",
            v.steps
        );
    }
}

/// FLAME refinement of the tiny benchmark's training split (zero corrections).
pub(crate) fn refinement(device: &Device) -> refine::FlameRefinement {
    let ds = HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap();
    let timesteps = refine::Timesteps::of_dataset(&ds).unwrap();
    refine::FlameRefinement::new(&head().model, timesteps, device).unwrap()
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

/// At zero corrections the tensor LBS reproduces the loader's vertices (the host's f64
/// `lbs`) and the condition, for training frames and for validation frames of the same
/// timesteps; a frame of a timestep that was not trained (held-out) passes through as it is.
#[test]
fn flame_refinement_at_zero_reproduces_the_tracked_frames() {
    let device = Device::flex().autodiff();
    let r = refinement(&device);
    let train = HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap();
    // 2 frames per sequence x 10 sequences.
    assert_eq!(r.timesteps.len(), 20);
    let val = HeadDataset::open(data(), Split::Val, Arc::new(head().model.clone())).unwrap();
    let test = HeadDataset::open(data(), Split::Test, Arc::new(head().model.clone())).unwrap();
    let items = vec![
        train.load_item(0).unwrap(),
        val.load_item(1).unwrap(),
        test.load_item(0).unwrap(),
    ];
    assert!(r.timesteps.row(&items[0].flame_key).is_some());
    assert!(r.timesteps.row(&items[1].flame_key).is_some());
    assert!(r.timesteps.row(&items[2].flame_key).is_none());
    let b = HeadBatcher.try_batch(items, &device).unwrap();
    let (vertices, condition) = r.apply(&b);
    let (got, want) = (host(vertices), host(b.vertices.clone()));
    let err = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(err < 2e-6, "largest vertex difference {err}");
    assert_eq!(host(condition), host(b.condition.clone()));
}

#[test]
fn shipped_training_configs_load() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    for name in ["train_tiny", "train_cpu", "train_paper", "train_paper_cpu"] {
        let c = TrainConfig::load(&dir.join(format!("{name}.json"))).unwrap();
        assert_eq!(c.batch_size, 1, "{name}");
        assert_eq!(
            (c.lr_decoders, c.lr_encoders, c.adam_eps),
            (6e-4, 4e-4, 1e-15),
            "{name}"
        );
        assert_eq!(c.loss, LossWeights::default(), "{name}");
    }
    let paper = TrainConfig::load(&dir.join("train_paper.json")).unwrap();
    assert_eq!(paper.net_config().unwrap(), &NetConfig::paper());
    assert_eq!(paper.iterations, 600_000);
    assert_eq!(paper.vgg_from(), 300_000);
    assert_eq!(paper.ablations, Ablations::default());
    // The paper's networks on 2 cores: the same networks and objective, 20,000 iterations,
    // a checkpoint often enough to lose at most a few minutes of work (docs/training.md).
    let cpu = TrainConfig::load(&dir.join("train_paper_cpu.json")).unwrap();
    assert_eq!(cpu.net_config().unwrap(), &NetConfig::paper());
    assert_eq!((cpu.iterations, cpu.checkpoint_every), (20_000, 200));
    assert_eq!(cpu.ablations, Ablations::default());
    assert_eq!(cpu.backend, BackendKind::Flex);
    // Unknown fields and bad values name the field.
    let bad = out_dir("badconfig");
    std::fs::create_dir_all(&bad).unwrap();
    let p = bad.join("c.json");
    std::fs::write(
        &p,
        r#"{"net": "../x.json", "iterations": 0, "checkpoint_every": 1}"#,
    )
    .unwrap();
    let e = TrainConfig::load(&p).unwrap_err().to_string();
    assert!(e.contains("x.json"), "{e}");
    let mut c = tiny_config();
    c.iterations = 0;
    assert!(
        c.validate("t")
            .unwrap_err()
            .to_string()
            .contains("iterations")
    );
}

#[test]
fn train_command_runs_and_resumes() {
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_tiny.json");
    let out = out_dir("cli");
    let run = |resume: bool| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"));
        cmd.args(["train", "--backend", "flex", "--data"])
            .arg(data())
            .arg("--config")
            .arg(&config)
            .arg("--out")
            .arg(&out)
            .env_remove("BURN_DEVICE");
        if resume {
            cmd.arg("--resume");
        }
        let o = cmd.output().expect("run texavatars");
        let (stdout, stderr) = (
            String::from_utf8_lossy(&o.stdout).into_owned(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        );
        assert!(o.status.success(), "{stdout}\n{stderr}");
        (stdout, stderr)
    };
    let (stdout, stderr) = run(false);
    assert!(stdout.contains("trained iterations 0..20"), "{stdout}");
    // Where eta comes from, per split: the benchmark's side files.
    for split in ["train", "val"] {
        let line = format!("eta ({split}): side files without eta/source.json for");
        assert!(stderr.contains(&line), "{line}: {stderr}");
    }
    // Progress lines with every term, and a validation line per checkpoint.
    assert!(stderr.contains("train  it 20/20"), "{stderr}");
    assert!(stderr.contains("valid  it 10"), "{stderr}");
    for term in ["Loss", "L1", "D-SSIM", "VGG", "L_pos", "L_scale", "PSNR"] {
        assert!(stderr.contains(term), "{term}: {stderr}");
    }
    assert!(out.join(files::AVATAR).is_file());
    refined_parameters_are_saved_and_exported(&out, 20);
    // A finished run resumes to its end without training again (and without wgpu: the
    // optimiser state is restored on the run's backend).
    let (stdout, stderr) = run(true);
    assert!(stdout.contains("trained iterations 20..20"), "{stdout}");
    assert!(!stderr.contains("XDG_RUNTIME_DIR"), "{stderr}");
}

/// A finished run of `iterations` steps with FLAME refinement (the default): its refined
/// parameters are saved, moved from the tracked ones by at most what Adam's steps allow,
/// exported as VHAP `flame_param` files, and used by the dataset for the timesteps they
/// refine.
fn refined_parameters_are_saved_and_exported(run: &Path, iterations: usize) {
    let c = tiny_config();
    let refined = RefinedParams::load(run)
        .unwrap()
        .expect("refined parameters");
    let train = HeadDataset::open(data(), Split::Train, Arc::new(head().model.clone())).unwrap();
    let tracked = refine::Timesteps::of_dataset(&train).unwrap();
    assert_eq!(refined.keys, tracked.keys);
    assert_eq!(refined.timesteps, tracked.timesteps);
    let (mut moved_expr, mut moved_pose, mut moved_t) = (0.0f32, 0.0f32, 0.0f32);
    let max_diff = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    for (p, t) in refined.poses.iter().zip(&tracked.tracked) {
        moved_expr = moved_expr.max(max_diff(&p.expr, &t.expr));
        moved_pose = moved_pose.max(max_diff(&p.pose15(), &t.pose15()));
        moved_t = moved_t.max(max_diff(&p.translation, &t.translation));
        assert_eq!(p.shape, t.shape);
    }
    // Adam moves a parameter by at most about lr per step (|m / sqrt(v)| <= 1 after bias
    // correction, up to (1 - beta1) / sqrt(1 - beta2) for a lone spike).
    let bound = |lr: f64| (lr * iterations as f64 * 3.2) as f32;
    for (name, moved, lr) in [
        ("expr", moved_expr, c.lr_flame_expr),
        ("pose", moved_pose, c.lr_flame_pose),
        ("translation", moved_t, c.lr_flame_translation),
    ] {
        assert!(
            moved > 0.0 && moved <= bound(lr),
            "{name}: moved {moved}, lr {lr}"
        );
    }
    // `export flame-param`: one VHAP file per timestep, the arrays and shapes VHAP's
    // `NeRFDatasetWriter.write_flame_param` (vhap/export_as_nerf_dataset.py) writes:
    // translation, rotation, neck_pose, jaw_pose (1, 3), eyes_pose (1, 6), expr (1, E),
    // shape (S,), static_offset (1, V, 3) when the subject has one.
    let export = run.join("exported");
    let export_cmd = || {
        std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
            .args(["export", "flame-param", "--run"])
            .arg(run)
            .arg("--out")
            .arg(&export)
            .output()
            .unwrap()
    };
    let o = export_cmd();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let files: Vec<_> = std::fs::read_dir(export.join("flame_param"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(files.len(), refined.poses.len());
    for (t, p) in refined.timesteps.iter().zip(&refined.poses) {
        let f = export.join("flame_param").join(format!("{t:05}.npz"));
        let mut z = texavatars::io::npz::Npz::open(&f).unwrap();
        for (name, shape) in [
            ("translation", vec![1, 3]),
            ("rotation", vec![1, 3]),
            ("neck_pose", vec![1, 3]),
            ("jaw_pose", vec![1, 3]),
            ("eyes_pose", vec![1, 6]),
            ("expr", vec![1, p.expr.len()]),
            ("shape", vec![p.shape.len()]),
        ] {
            assert_eq!(z.floats(name).unwrap().shape, shape, "{name}");
        }
        assert_eq!(&texavatars::head::HeadPose::load_npz(&f).unwrap(), p);
    }
    // A second export into the same folder is refused and leaves the files alone.
    let again = export_cmd();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("not empty"));
    // The validation split (the same timesteps, another camera) is posed with the refined
    // parameters; the held-out split keeps its tracked ones.
    let model = Arc::new(head().model.clone());
    let shared = Arc::new(refined.clone());
    let val = HeadDataset::open(data(), Split::Val, model.clone()).unwrap();
    let key = val.flame_key(0).unwrap();
    let pose = refined.get(&key).expect("a training timestep").clone();
    let want = texavatars::head::lbs(&model, &pose).unwrap();
    let tracked_v = val.conditioning(0).unwrap().vertices.clone();
    let val = val.with_refined(shared.clone());
    let got = val.conditioning(0).unwrap();
    assert_eq!(got.vertices, want);
    assert_ne!(got.vertices, tracked_v);
    assert_eq!(got.expr, pose.expr);
    let test = HeadDataset::open(data(), Split::Test, model.clone()).unwrap();
    let before = test.conditioning(0).unwrap();
    let test = test.with_refined(shared);
    assert_eq!(test.conditioning(0).unwrap(), before);
}

#[test]
fn an_export_without_a_validation_split_trains_without_validation() {
    let noval = data().parent().unwrap().join("union_noval");
    std::fs::create_dir_all(&noval).unwrap();
    std::fs::copy(
        data().join("transforms_train.json"),
        noval.join("transforms_train.json"),
    )
    .unwrap();
    let mut c = tiny_config();
    c.iterations = 2;
    c.checkpoint_every = 1;
    c.val_frames = 3;
    let out = out_dir("noval");
    let mut o = options(&out, BackendKind::Flex);
    o.data = noval;
    let r = train::train(&c, &o).unwrap();
    assert_eq!(r.end_iteration, 2);
    assert!(r.avatar_path.is_file());
}

/// Every float parameter of `m` as host values, in visiting order.
fn all_params<M: Module>(m: &M) -> Vec<Vec<f32>> {
    struct All(Vec<Vec<f32>>);
    impl ModuleVisitor for All {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            self.0.push(p.val().into_data().iter::<f32>().collect());
        }
    }
    let mut all = All(Vec::new());
    m.visit(&mut all);
    all.0
}

#[test]
fn a_run_stopped_inside_an_interval_resumes_to_the_same_avatar() {
    let mut c = tiny_config();
    c.iterations = 6;
    c.checkpoint_every = 4;
    c.val_frames = 0;
    let straight = train::train(&c, &options(&out_dir("mid-straight"), BackendKind::Flex)).unwrap();
    assert!(straight.complete);

    // Stopped after 3 iterations: checkpoint 1 holds 0..3, recorded; no avatar yet.
    let out = out_dir("mid-stopped");
    let ckpt = out.join(files::CHECKPOINTS);
    let mut o = options(&out, BackendKind::Flex);
    o.stop_after = Some(3);
    let r = train::train(&c, &o).unwrap();
    assert_eq!(
        (r.start_iteration, r.end_iteration, r.complete),
        (0, 3, false)
    );
    assert_eq!(latest_checkpoint(&ckpt), Some(1));
    let rec = IterationRecord::load(&ckpt, 1).unwrap().unwrap();
    assert_eq!(rec.iteration, 3);
    assert!(!out.join(files::AVATAR).exists());

    // Resumed and stopped again inside the last interval: 3..5, checkpoint 2 holds 0..5.
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    o.stop_after = Some(2);
    let r = train::train(&c, &o).unwrap();
    assert_eq!(
        (r.start_iteration, r.end_iteration, r.complete),
        (3, 5, false)
    );
    assert_eq!(
        IterationRecord::load(&ckpt, 2).unwrap().unwrap().iteration,
        5
    );

    // Resumed to the end: the same parameters, to the bit, as the uninterrupted run.
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let r = train::train(&c, &o).unwrap();
    assert_eq!(
        (r.start_iteration, r.end_iteration, r.complete),
        (5, 6, true)
    );
    assert!(out.join(files::AVATAR).is_file());
    assert!(all_params(&r.avatar) == all_params(&straight.avatar));
}

#[test]
fn a_diverging_run_stops_naming_the_iteration_and_keeps_its_last_checkpoint() {
    let mut c = tiny_config();
    c.iterations = 6;
    c.checkpoint_every = 1;
    c.val_frames = 0;
    // The issue's case: a learning rate of 1e6 and more. Adam's first step moves every
    // weight by about the learning rate; the next forward pass overflows.
    c.lr_decoders = 1e30;
    c.lr_encoders = 1e30;
    let out = out_dir("nan");
    let e = train::train(&c, &options(&out, BackendKind::Flex)).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("iteration 1") && msg.contains("not finite"),
        "{msg}"
    );
    assert!(msg.contains("Loss"), "{msg}");
    assert!(msg.contains("the last good checkpoint is 1"), "{msg}");
    let ckpt = out.join(files::CHECKPOINTS);
    assert_eq!(latest_checkpoint(&ckpt), Some(1));
    assert!(!out.join(files::AVATAR).exists());

    // An avatar with a non-finite parameter is refused by everything that loads one.
    struct Poison;
    impl ModuleMapper for Poison {
        fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
            p.map(|t| t.clone() + t.zeros_like().add_scalar(f32::NAN))
        }
    }
    let device = Device::flex();
    let avatar = c.avatar().unwrap().init(&head().mesh, &device).unwrap();
    let run = out_dir("nan-avatar");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::copy(
        out.join(files::AVATAR_CONFIG),
        run.join(files::AVATAR_CONFIG),
    )
    .unwrap();
    avatar
        .map(&mut Poison)
        .save_file(run.join(files::AVATAR))
        .unwrap();
    let e = texavatars::models::load_avatar(&run, head(), &device).unwrap_err();
    assert!(e.to_string().contains("NaN or infinite"), "{e}");
}

#[test]
fn a_finished_run_is_replaced_only_with_force() {
    let mut c = tiny_config();
    c.iterations = 1;
    c.checkpoint_every = 1;
    c.val_frames = 0;
    let out = out_dir("force");
    train::train(&c, &options(&out, BackendKind::Flex)).unwrap();
    // The checkpoints gone, the finished avatar still guards the folder.
    std::fs::remove_dir_all(out.join(files::CHECKPOINTS)).unwrap();
    let e = train::train(&c, &options(&out, BackendKind::Flex)).unwrap_err();
    assert!(e.to_string().contains("--force"), "{e}");
    // A stale scratch file of a killed save is removed at the start.
    std::fs::write(out.join("avatar.bpk.123-0.tmp"), b"x").unwrap();
    let mut o = options(&out, BackendKind::Flex);
    o.force = true;
    let unrelated = out.join("notes.txt");
    std::fs::write(&unrelated, b"mine").unwrap();
    let r = train::train(&c, &o).unwrap();
    assert!(r.complete);
    assert!(
        unrelated.is_file(),
        "--force removes only train's own files"
    );
    assert!(!out.join("avatar.bpk.123-0.tmp").exists());
}

/// Reads a child's stderr lines into a channel.
fn stderr_lines(child: &mut std::process::Child) -> std::sync::mpsc::Receiver<String> {
    use std::io::BufRead;
    let (tx, rx) = std::sync::mpsc::channel();
    let err = child.stderr.take().expect("piped stderr");
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(err).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    rx
}

/// `texavatars train` on the tiny benchmark with a long interval, progress on every
/// iteration; returns the child once it has trained `after` iterations.
#[cfg(unix)]
fn train_child(
    out: &Path,
    after: usize,
) -> (
    std::process::Child,
    std::sync::mpsc::Receiver<String>,
    Vec<String>,
) {
    train_child_with(out, after, 400, 200)
}

/// [`train_child`] with `iterations` and `checkpoint_every`.
#[cfg(unix)]
fn train_child_with(
    out: &Path,
    after: usize,
    iterations: usize,
    checkpoint_every: usize,
) -> (
    std::process::Child,
    std::sync::mpsc::Receiver<String>,
    Vec<String>,
) {
    let mut c = tiny_config();
    c.iterations = iterations;
    c.checkpoint_every = checkpoint_every;
    c.val_frames = 1;
    c.log_every = 1;
    std::fs::create_dir_all(out).unwrap();
    let config = out.with_extension("json");
    std::fs::write(&config, c.to_json()).unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["train", "--backend", "flex", "--data"])
        .arg(data())
        .arg("--config")
        .arg(&config)
        .arg("--out")
        .arg(out)
        .env_remove("BURN_DEVICE")
        .stderr(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("run texavatars");
    let rx = stderr_lines(&mut child);
    let mut seen = Vec::new();
    let mark = format!("train  it {after}/");
    loop {
        let line = rx
            .recv_timeout(std::time::Duration::from_secs(300))
            .unwrap_or_else(|_| panic!("no progress: {seen:?}"));
        let done = line.starts_with(&mark);
        seen.push(line);
        if done {
            return (child, rx, seen);
        }
    }
}

#[cfg(unix)]
fn kill(pid: u32, signals: &[&str]) {
    let script: Vec<String> = signals.iter().map(|s| format!("kill -{s} {pid}")).collect();
    let st = std::process::Command::new("sh")
        .arg("-c")
        .arg(script.join("; "))
        .status()
        .unwrap();
    assert!(st.success());
}

#[test]
#[cfg(unix)]
fn sigint_checkpoints_the_step_in_progress_and_says_how_to_resume() {
    let out = out_dir("sigint");
    let (mut child, rx, mut seen) = train_child(&out, 3);
    kill(child.id(), &["INT"]);
    let status = child.wait().unwrap();
    seen.extend(rx.iter());
    let stderr = seen.join("\n");
    assert_eq!(status.code(), Some(130), "{stderr}");
    assert!(
        stderr.contains("SIGINT") && stderr.contains("--resume"),
        "{stderr}"
    );
    let ckpt = out.join(files::CHECKPOINTS);
    assert_eq!(latest_checkpoint(&ckpt), Some(1), "{stderr}");
    let at = IterationRecord::load(&ckpt, 1).unwrap().unwrap().iteration;
    assert!((3..200).contains(&at), "{at}");
    assert!(
        stderr.contains(&format!("stopped at iteration {at} of 400")),
        "{stderr}"
    );
    assert!(!out.join(files::AVATAR).exists());
}

#[test]
#[cfg(unix)]
fn a_second_signal_exits_at_once() {
    let out = out_dir("sigterm2");
    let (mut child, rx, mut seen) = train_child(&out, 2);
    // Two signals microseconds apart: the second arrives while the first's step runs. Two
    // different ones: the kernel merges a signal into a pending one of the same number.
    kill(child.id(), &["INT", "TERM"]);
    let status = child.wait().unwrap();
    seen.extend(rx.iter());
    let stderr = seen.join("\n");
    // 128 + the number of whichever signal came second (delivery order is the kernel's).
    assert!(
        matches!(status.code(), Some(130 | 143)),
        "{status:?}: {stderr}"
    );
    assert!(!stderr.contains("stopped at iteration"), "{stderr}");
    assert_eq!(latest_checkpoint(&out.join(files::CHECKPOINTS)), None);
}

/// Copies a folder tree (the tests that damage a dataset work on their own copy).
fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), dest).unwrap();
        }
    }
}

/// The training images of a synth output (`<root>/<sequence>/images/*.png`).
fn training_images(root: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    for seq in std::fs::read_dir(root).unwrap() {
        let images = seq.unwrap().path().join("images");
        if let Ok(files) = std::fs::read_dir(&images) {
            v.extend(files.map(|f| f.unwrap().path()));
        }
    }
    v.sort();
    v
}

/// Issue 15.5: every frame's files are checked before anything is written, all problems in
/// one report; a frame that breaks only when decoded (past its header) stops the run with
/// its checkpoint, naming the file and how to resume.
#[test]
fn bad_frames_are_found_up_front_or_stop_with_a_checkpoint() {
    let root = out_dir("bad-frames-data");
    copy_tree(data().parent().unwrap(), &root);
    let union = root.join("union");
    let images = training_images(&root);
    let mut c = tiny_config();
    c.iterations = 4;
    c.checkpoint_every = 1;
    c.val_frames = 0;
    let options = |out: &Path| {
        let mut o = TrainOptions::new(&union, out);
        o.backend = Some(BackendKind::Flex);
        o.head = Some(head().clone());
        o.app_log = false;
        o
    };

    // Two frames missing, far apart: both named, nothing written.
    let frames =
        texavatars::data::vhap::load_transforms(&union.join("transforms_train.json")).unwrap();
    let (first, last) = (
        frames[0].image.clone(),
        frames[frames.len() - 1].image.clone(),
    );
    let keep: Vec<_> = [&first, &last].map(|p| std::fs::read(p).unwrap()).into();
    std::fs::remove_file(&first).unwrap();
    std::fs::remove_file(&last).unwrap();
    let out = out_dir("bad-frames");
    let e = train::train(&c, &options(&out)).unwrap_err().to_string();
    let name = |p: &Path| p.file_name().unwrap().to_string_lossy().into_owned();
    assert!(e.contains("problem(s)"), "{e}");
    assert!(e.contains(&name(&first)) && e.contains(&name(&last)), "{e}");
    assert!(!out.exists(), "nothing is written before the check passes");
    std::fs::write(&first, &keep[0]).unwrap();
    std::fs::write(&last, &keep[1]).unwrap();

    // Two iterations trained and checkpointed; then every image but frame 0's (which `train`
    // decodes before it starts) cut in half (headers intact, pixels gone): the resumed run
    // stops at iteration 2 and keeps checkpoint 2.
    let mut o = options(&out);
    o.stop_after = Some(2);
    train::train(&c, &o).unwrap();
    let frame0 = first.canonicalize().unwrap();
    for p in images
        .iter()
        .filter(|p| p.canonicalize().unwrap() != frame0)
    {
        let bytes = std::fs::read(p).unwrap();
        std::fs::write(p, &bytes[..bytes.len() / 2]).unwrap();
    }
    let mut o = options(&out);
    o.resume = true;
    let e = train::train(&c, &o).unwrap_err().to_string();
    assert!(
        e.contains("iteration 2") && e.contains("could not be read"),
        "{e}"
    );
    assert!(
        e.contains("holds iterations 0..2") && e.contains("--resume"),
        "{e}"
    );
    assert_eq!(latest_checkpoint(&out.join(files::CHECKPOINTS)), Some(2));
    assert!(!out.join(files::AVATAR).exists());
    std::fs::remove_dir_all(&root).unwrap();
}

/// Issue 15.8, "a full disk": every write past a size fails in the child (`ulimit -f`, with
/// SIGXFSZ ignored so the write returns EFBIG as a full disk returns ENOSPC). The run exits
/// non-zero, the last complete checkpoint is untouched, and a later `--resume` on a disk
/// with room finishes the run.
#[test]
#[cfg(unix)]
fn a_failed_checkpoint_write_keeps_the_last_checkpoint() {
    let out = out_dir("full-disk");
    let mut c = tiny_config();
    c.iterations = 3;
    c.checkpoint_every = 1;
    c.val_frames = 0;
    let mut o = options(&out, BackendKind::Flex);
    o.stop_after = Some(1);
    train::train(&c, &o).unwrap();
    let ckpt = out.join(files::CHECKPOINTS);
    assert_eq!(latest_checkpoint(&ckpt), Some(1));
    let snapshot = |dir: &Path| -> Vec<(String, Vec<u8>)> {
        let mut v: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap())
            .filter(|e| e.file_name().to_string_lossy().ends_with("-1.bpk"))
            .map(|e| {
                (
                    e.file_name().to_string_lossy().into(),
                    std::fs::read(e.path()).unwrap(),
                )
            })
            .collect();
        v.sort();
        v
    };
    let before = snapshot(&ckpt);
    let model_bytes = std::fs::metadata(ckpt.join("model-1.bpk")).unwrap().len();
    // Blocks of 512 (dash) or 1024 (bash) bytes: a limit of a quarter or half the model.
    let blocks = (model_bytes / 2048).max(1);
    let config = out.with_extension("json");
    std::fs::write(&config, c.to_json()).unwrap();
    let run = std::process::Command::new("sh")
        .arg("-c")
        .arg(format!(
            "trap '' XFSZ; ulimit -f {blocks}; exec \"$0\" \"$@\""
        ))
        .arg(env!("CARGO_BIN_EXE_texavatars"))
        .args(["train", "--backend", "flex", "--resume", "--data"])
        .arg(data())
        .arg("--config")
        .arg(&config)
        .arg("--out")
        .arg(&out)
        .env_remove("BURN_DEVICE")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "{stderr}");
    assert_eq!(
        snapshot(&ckpt),
        before,
        "checkpoint 1 is untouched: {stderr}"
    );
    assert_eq!(latest_checkpoint(&ckpt), Some(1), "{stderr}");
    assert!(!out.join(files::AVATAR).exists());

    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let r = train::train(&c, &o).unwrap();
    assert_eq!(
        (r.start_iteration, r.end_iteration, r.complete),
        (1, 3, true)
    );
}

/// Issue 15.2 and 15.8, "a kill": a second run on a busy folder is refused naming the
/// holder's pid; after `kill -9` the kernel has released the lock, and `--resume` continues
/// from the newest complete checkpoint to the end.
#[test]
#[cfg(unix)]
fn a_busy_folder_is_refused_and_a_killed_run_resumes() {
    let out = out_dir("kill9");
    let (mut child, _rx, _seen) = train_child_with(&out, 3, 400, 2);
    let mut c = TrainConfig::load(&out.with_extension("json")).unwrap();
    c.log_every = 0;
    let mut o = options(&out, BackendKind::Flex);
    o.resume = true;
    let e = train::train(&c, &o).unwrap_err().to_string();
    assert!(
        e.contains(&format!("process {} is training", child.id())),
        "{e}"
    );
    kill(child.id(), &["KILL"]);
    child.wait().unwrap();
    let ckpt = out.join(files::CHECKPOINTS);
    let newest = latest_checkpoint(&ckpt).expect("checkpoint 1 was written at iteration 2");
    // The rest of the run, shortened to one more interval (`iterations` may change).
    c.iterations = 2 * newest + 2;
    let r = train::train(&c, &o).unwrap();
    assert_eq!(r.start_iteration, 2 * newest);
    assert!(r.complete && out.join(files::AVATAR).is_file());
}
