//! The GaussianAvatars run: [`train`], the files it writes in its folder ([`ga_files`],
//! [`OWNED`]) and its report ([`GaTrainReport`]).

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use super::checkpoint::from_checkpoint;
use super::config::GaTrainConfig;
use super::schedule::{GaSchedule, lr_scheduler, optimizer};
use super::state::{DensityState, GaSetup};
use super::step::GaTraining;
use crate::error::{Error, Result};
use crate::head::HeadAsset;
use crate::models::gaussianavatars::binding::check_binding;
use crate::models::gaussianavatars::folder::write_point_cloud;
use crate::models::gaussianavatars::model::GaModel;
use crate::train::gaussianavatars::density::{self, Stats};
use crate::train::refine::{FlameRefinement, Timesteps};
use crate::train::{Launch, Schedule, TrainOptions, files, open_frames, prepare_folder};

/// Files of a GaussianAvatars run in its output folder.
pub mod ga_files {
    /// The resolved config of the run (read back by `--resume`).
    pub const CONFIG: &str = "train_gaussianavatars.json";
    /// GaussianAvatars' output layout: `point_cloud/iteration_N/point_cloud.ply`.
    pub const POINT_CLOUD_DIR: &str = "point_cloud";
}

/// What a GaussianAvatars run writes into its folder, removed by `--force`.
pub const OWNED: [&str; 9] = [
    ga_files::CONFIG,
    crate::data::refined::REFINED_NPZ,
    crate::data::refined::REFINED_INDEX,
    ga_files::POINT_CLOUD_DIR,
    files::CHECKPOINTS,
    files::IDENTITY,
    "train",
    "valid",
    "experiment.log",
];

/// What a GaussianAvatars [`train`] did.
#[derive(Debug)]
pub struct GaTrainReport {
    pub start_iteration: usize,
    pub end_iteration: usize,
    /// Gaussians at the end.
    pub gaussians: usize,
    /// The trained Gaussians (on the inner, non-autodiff device).
    pub model: GaModel,
    pub seconds: f64,
    /// `OUT/point_cloud/iteration_N/` (only a complete run writes it).
    pub output: PathBuf,
    pub complete: bool,
}

/// Trains a GaussianAvatars avatar on `options.data` (see the module documentation) and
/// writes `OUT/point_cloud/iteration_N/point_cloud.ply` (with `binding_0`) and the subject's
/// `flame_param.npz` next to it: a folder `render`, `eval` and `export ply` read as any
/// GaussianAvatars output.
///
/// Runs on rayon's pool ([`texavatars_cpu::threads::on_pool`]), as [`crate::train::train`].
pub fn train(config: &GaTrainConfig, options: &TrainOptions) -> Result<GaTrainReport> {
    texavatars_cpu::threads::on_pool(|| train_here(config, options))
}

/// [`train`] on the calling thread.
fn train_here(config: &GaTrainConfig, options: &TrainOptions) -> Result<GaTrainReport> {
    config.validate("train config")?;
    let head = match &options.head {
        Some(h) => h.clone(),
        None => {
            let next = options.data.join("..").join("head").join("head.npz");
            if next.is_file() {
                HeadAsset::load(&next, None)?
            } else {
                HeadAsset::embedded()?
            }
        }
    };
    let model = Arc::new(head.model.clone());
    let (train_set, val_set) = open_frames(options, model, config.val_frames)?;
    let out = &options.out;
    let folder = prepare_folder(options, &OWNED, ga_files::POINT_CLOUD_DIR, || {
        let path = out.join(ga_files::CONFIG);
        let saved = GaTrainConfig::load(&path)?;
        saved.resumable_as(config).map_err(|field| {
            Error::invalid(
                path.display().to_string(),
                field,
                "differs from the given config; a resumed run must keep its schedule (only \
                 val_frames, log_every and backend may change)",
            )
        })
    })?;
    let probe = train_set.load_item(0)?;
    if probe.vertices.len() != head.model.num_vertices() {
        return Err(Error::invalid(
            train_set.transforms_path().display().to_string(),
            "flame_param_path",
            format!(
                "posed meshes have {} vertices, the head model {}",
                probe.vertices.len(),
                head.model.num_vertices()
            ),
        ));
    }
    let centers: Vec<[f32; 3]> = train_set
        .frames()
        .iter()
        .map(|f| f.camera.position())
        .collect();
    let extent = density::cameras_extent(&centers);
    let backend = options.backend.unwrap_or(config.backend);
    let device = backend.autodiff_device();
    let stop = options.stop.clone().unwrap_or_default();
    let faces = Arc::new(head.model.faces.clone());
    let setup = GaSetup {
        faces: faces.clone(),
        schedule: GaSchedule::new(config.iterations),
        extent,
        seed: config.seed,
        pending: Arc::new(Mutex::new(None)),
        guard: Some(stop.clone()),
    };
    let refine = if config.flame_refinement {
        let timesteps = Timesteps::of_dataset(&train_set)?;
        Some(FlameRefinement::new(&head.model, timesteps, &device)?)
    } else {
        None
    };
    let training = match folder.checkpoint {
        Some(c) => from_checkpoint(
            &folder.ckpt_dir.join(format!("model-{c}.bpk")),
            setup,
            refine,
            &device,
        )?,
        None => {
            let model = GaModel::init(faces.len(), config.sh_degree, config.seed, &device)?;
            let n = model.len();
            GaTraining {
                model,
                density: DensityState::new(Stats::zeros(n), vec![1.0; faces.len()], &device),
                refine,
                setup,
            }
        }
    };
    let start_gaussians = training.model.len();

    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    std::fs::write(out.join(ga_files::CONFIG), config.to_json())
        .map_err(|e| Error::io(&out.join(ga_files::CONFIG), e))?;
    train_set
        .identity()
        .save(&head.model, &out.join(files::IDENTITY))?;

    let launch = Launch {
        schedule: Schedule {
            seed: config.seed,
            per_epoch: config.checkpoint_every,
            total: config.iterations,
            batch_size: 1,
            resume: folder.resume_at,
            crop: None,
        },
        checkpoint: folder.checkpoint,
        log_every: config.log_every,
        val_frames: config.val_frames,
        stop,
        model_arg: " --model gaussianavatars",
    };
    let frames = train_set.len();
    let ga_schedule = GaSchedule::new(config.iterations);
    let launched = launch.run(
        options,
        training,
        (optimizer(), lr_scheduler(config.iterations, extent)),
        (train_set, val_set),
        &device,
        |start, end| {
            eprintln!(
                "train: GaussianAvatars, {frames} frames, {start_gaussians} Gaussians, {} backend, \
                 iterations {start}..{end} of {}, extent {extent:.3}, densify from {} every {}, \
                 opacity reset every {}, SH degree up every {}",
                format!("{backend:?}").to_lowercase(),
                config.iterations,
                ga_schedule.densify_from,
                ga_schedule.densify_interval,
                ga_schedule.opacity_reset,
                ga_schedule.sh_interval,
            )
        },
    )?;
    let error = launched.result.error.as_ref().map(|e| e.to_string());
    let (reached, complete) = launch.outcome(options, error, launched.end_iteration)?;
    let trained = launched.result.model;
    let gaussians = trained.model.len();
    let output = out
        .join(ga_files::POINT_CLOUD_DIR)
        .join(format!("iteration_{}", config.iterations));
    if complete {
        let (stored, binding) = trained.model.to_stored();
        check_binding(&binding, stored.len(), faces.len())?;
        std::fs::create_dir_all(&output).map_err(|e| Error::io(&output, e))?;
        write_point_cloud(&output, &stored, &binding)?;
        let identity = out.join(files::IDENTITY);
        let flame = output.join(crate::models::gaussianavatars::folder::FLAME_PARAM);
        std::fs::copy(&identity, &flame).map_err(|e| Error::io(&flame, e))?;
        if let Some(r) = &trained.refine {
            r.refined().save(out)?;
        }
    } else {
        launch.stopped(options, reached)?;
    }
    drop(folder);
    Ok(GaTrainReport {
        start_iteration: launched.start_iteration,
        end_iteration: reached,
        gaussians,
        model: trained.model,
        seconds: launched.seconds,
        output,
        complete,
    })
}
