//! The TexAvatars run: [`train`] builds the avatar and its objective, prepares the folder
//! and launches burn's learner.

use std::path::Path;
use std::sync::Arc;

use burn::module::Module;

use super::config::{NetSpec, TrainConfig};
use super::folder::{OWNED, files, prepare_folder};
use super::frames::open_frames;
use super::launch::Launch;
use super::loader::Schedule;
use super::optim::{lr_scheduler, optimizer};
use super::options::{TrainOptions, TrainReport};
use super::refine;
use super::step::{AvatarTraining, Objective};
use crate::error::{Error, Result};
use crate::head::HeadAsset;
use crate::metrics::VggPerceptual;
use crate::models::texavatars::AvatarConfig;

/// The head of `options`: given, or `data/../head/head.npz`, or the embedded default.
fn find_head(options: &TrainOptions) -> Result<HeadAsset> {
    if let Some(h) = &options.head {
        return Ok(h.clone());
    }
    let next_to_data = options.data.join("..").join("head").join("head.npz");
    if next_to_data.is_file() {
        HeadAsset::load(&next_to_data, None)
    } else {
        HeadAsset::embedded()
    }
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|e| Error::io(path, e))
}

/// Trains the avatar of `config` on `options.data` (see the module documentation), writes
/// `out/avatar.bpk` and returns the trained avatar.
///
/// A resumed run restores the optimiser state on burn's `Device::default()` first (burn
/// 0.22); set `BURN_DEVICE` to the run's backend to keep a CPU run off wgpu (the `train`
/// command does).
///
/// Before anything runs, the data is checked against the avatar (the posed meshes' vertex
/// count) and, when the VGG loss is on, the VGG16 weights must be installed (`texavatars
/// weights install`). The net config's expression width is set to the head model's (the
/// loader pads or truncates every frame's coefficients to it).
///
/// Runs on rayon's pool ([`texavatars_cpu::threads::on_pool`]), so a library caller gets
/// the speed of the `texavatars` binary.
pub fn train(config: &TrainConfig, options: &TrainOptions) -> Result<TrainReport> {
    texavatars_cpu::threads::on_pool(|| train_here(config, options))
}

/// [`train`] on the calling thread.
fn train_here(config: &TrainConfig, options: &TrainOptions) -> Result<TrainReport> {
    let mut config = config.clone();
    config.validate("train config")?;
    let head = find_head(options)?;
    if let NetSpec::Inline(net) = &mut config.net
        && net.condition.expression != head.model.num_expr
    {
        eprintln!(
            "train: the head model has {} expression coefficients; net.condition.expression {} -> {}",
            head.model.num_expr, net.condition.expression, head.model.num_expr
        );
        net.condition.expression = head.model.num_expr;
    }
    let avatar_config: AvatarConfig = config.avatar()?;

    let model = Arc::new(head.model.clone());
    let (train_set, val_set) = open_frames(options, model, config.val_frames)?;
    if let Some(crop) = &config.crop {
        let what = train_set.transforms_path().display().to_string();
        for f in train_set.frames() {
            crop.check_fits(&what, f.camera.width, f.camera.height)?;
        }
        eprintln!(
            "train: crop: each step scores a random {}x{} window of its frame",
            crop.width, crop.height
        );
    }

    let out = &options.out;
    let folder = prepare_folder(options, &OWNED, files::AVATAR, || {
        let saved = TrainConfig::load(&out.join(files::CONFIG))?;
        saved.resumable_as(&config).map_err(|field| {
            Error::invalid(
                out.join(files::CONFIG).display().to_string(),
                field,
                "differs from the given config; a resumed run must train the same avatar with \
                 the same schedule (only iterations, val_frames, log_every and backend may change)",
            )
        })
    })?;

    let backend = options.backend.unwrap_or(config.backend);
    let device = backend.autodiff_device();
    let avatar = avatar_config.init_seeded(config.seed, &head.mesh, &device)?;
    // One frame through the checks the step cannot report (it may only panic).
    let probe = train_set.load_item(0)?;
    if probe.vertices.len() != avatar.num_vertices() {
        return Err(Error::invalid(
            train_set.transforms_path().display().to_string(),
            "flame_param_path",
            format!(
                "posed meshes have {} vertices, the avatar's UV mesh {}",
                probe.vertices.len(),
                avatar.num_vertices()
            ),
        ));
    }
    // The weights are needed only where the schedule reaches the VGG term.
    let vgg = if config.ablations.vgg && config.vgg_from() < config.iterations {
        let v = VggPerceptual::load(&device)
            .map_err(|e| {
                Error::invalid(
                    "train config",
                    "ablations.vgg",
                    format!(
                        "the VGG loss needs the VGG16 weights: {e} (or set ablations.vgg to false)"
                    ),
                )
            })?
            .no_grad();
        Some(Arc::new(v))
    } else {
        None
    };
    let stop = options.stop.clone().unwrap_or_default();
    let refine = if config.ablations.flame_refinement {
        let timesteps = refine::Timesteps::of_dataset(&train_set)?;
        Some(refine::FlameRefinement::new(
            &head.model,
            timesteps,
            &device,
        )?)
    } else {
        None
    };
    let training = AvatarTraining {
        avatar,
        refine,
        objective: Objective {
            weights: config.loss.clone(),
            vgg,
            vgg_from: config.vgg_from(),
            guard: Some(stop.clone()),
        },
    };
    let gaussians = training.avatar.num_gaussians();

    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    write(&out.join(files::CONFIG), &config.to_json())?;
    // The subject the avatar is trained on, for eval and driving (crate::data::identity).
    train_set
        .identity()
        .save(&head.model, &out.join(files::IDENTITY))?;
    // The eta projection of the training codes, for coding captures that drive the avatar.
    if let Some(p) = crate::eta::projection::copy_for_run(train_set.frames(), out)? {
        eprintln!(
            "train: the eta projection is saved with the run: {}",
            p.display()
        );
    }
    write(
        &out.join(files::AVATAR_CONFIG),
        &(serde_json::to_string_pretty(&avatar_config).expect("serialises") + "\n"),
    )?;

    let launch = Launch {
        schedule: Schedule {
            seed: config.seed,
            per_epoch: config.checkpoint_every,
            total: config.iterations,
            batch_size: config.batch_size,
            resume: folder.resume_at,
            crop: config.crop,
        },
        checkpoint: folder.checkpoint,
        log_every: config.log_every,
        val_frames: config.val_frames,
        stop,
        model_arg: "",
    };
    let frames = train_set.len();
    let launched = launch.run(
        options,
        training,
        (optimizer(&config), lr_scheduler(&config)),
        (train_set, val_set),
        &device,
        |start, end| {
            eprintln!(
                "train: {frames} frames, {gaussians} Gaussians (R = S = {}), {} backend, iterations {start}..{end} of {}, VGG from iteration {}",
                avatar_config.net.uv_res,
                format!("{backend:?}").to_lowercase(),
                config.iterations,
                if config.ablations.vgg {
                    config.vgg_from().to_string()
                } else {
                    "never".into()
                }
            )
        },
    )?;
    let error = launched.result.error.as_ref().map(|e| e.to_string());
    let (reached, complete) = launch.outcome(options, error, launched.end_iteration)?;
    let model = launched.result.model;
    let avatar = model.avatar;
    let avatar_path = out.join(files::AVATAR);
    if complete {
        if let Some(refine) = &model.refine {
            refine.refined().save(out)?;
        }
        avatar.clone().save_file(&avatar_path).map_err(|e| {
            Error::invalid(avatar_path.display().to_string(), "save", e.to_string())
        })?;
    } else {
        launch.stopped(options, reached)?;
    }
    drop(folder);
    Ok(TrainReport {
        start_iteration: launched.start_iteration,
        end_iteration: reached,
        avatar,
        gaussians,
        seconds: launched.seconds,
        avatar_path,
        complete,
    })
}
