//! The synthetic multi-view head benchmark: `texavatars synth`.
//!
//! From any head (the embedded CC0 head by default) it renders a capture in exactly VHAP's
//! NeRSemble export for GaussianAvatars (see [`crate::data::vhap`]), with known ground
//! truth. The output folder:
//!
//! ```text
//! OUT/<sequence>/images/TTTTT_CC.png       RGB, white background
//! OUT/<sequence>/fg_masks/TTTTT_CC.png     8-bit coverage
//! OUT/<sequence>/flame_param/TTTTT.npz     translation, rotation, neck_pose, jaw_pose,
//!                                          eyes_pose (1, 6), expr (1, E), shape (S,)
//! OUT/<sequence>/eta/TTTTT.npy             float32 [128] side signal
//! OUT/<sequence>/transforms.json           every frame of the sequence, local timesteps
//! OUT/union/transforms_{train,val,test,free}.json   the splits, `../<sequence>/...` paths,
//!                                          global timesteps
//! OUT/union/canonical_flame_param.npz      the neutral parameters
//! OUT/head/head.{npz,obj,json}             the head it was rendered from
//! OUT/synth/{config.json, summary.json, albedo.png, wrinkles_*.png}
//! ```
//!
//! Splits (NeRSemble protocol): train = the ten training sequences on every camera but
//! `val_camera`; val = the same frames from `val_camera` (novel view); test = the held-out
//! sequence on every camera (novel expression); free = the FREE sequence on every camera.
//!
//! Per frame the conditioning is the expression coefficients (the tracked signal, here
//! exact), the 15 pose values, and eta: a fixed random projection of the frame's true
//! wrinkle activations plus Gaussian noise (a stand-in for an image-based expression
//! encoder). Rendering a timestep is skipped when all its files exist, so an interrupted
//! run resumes where it stopped; files are written through temporary names.

pub mod appearance;
pub mod cameras;
pub mod config;
pub mod render;
pub mod sequences;

use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use crate::data::vhap::{FrameRecord, eta_path, save_transforms};
use crate::error::{Error, Result};
use crate::head::{HeadAsset, HeadPose, lbs};
use crate::io;
use crate::splat::demo::Pcg;

pub use config::SynthConfig;
pub use sequences::{Role, Sequence};

/// What a run produced.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Summary {
    pub sequences: usize,
    pub timesteps: usize,
    pub cameras: usize,
    pub images: usize,
    pub rendered_timesteps: usize,
    pub skipped_timesteps: usize,
    pub seconds: f64,
    pub bytes: u64,
    pub split_frames: [usize; 4],
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> Error + '_ {
    move |e| Error::io(path, e)
}

fn frame_names(t: usize, c: usize) -> (String, String) {
    (
        format!("images/{t:05}_{c:02}.png"),
        format!("fg_masks/{t:05}_{c:02}.png"),
    )
}

/// Total size of the files under `dir`.
pub fn folder_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok())
        .map(|e| {
            let p = e.path();
            if p.is_dir() {
                folder_bytes(&p)
            } else {
                e.metadata().map_or(0, |m| m.len())
            }
        })
        .sum()
}

/// Generates the benchmark into `out`. `progress` receives one line per finished sequence.
pub fn generate(
    config: &SynthConfig,
    head: &HeadAsset,
    out: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<Summary> {
    config.validate("synth config")?;
    let start = Instant::now();
    let model = &head.model;
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    // The head and the settings travel with the data.
    let head_dir = out.join("head");
    std::fs::create_dir_all(&head_dir).map_err(io_err(&head_dir))?;
    model.save(&head_dir.join("head.npz"))?;
    let obj = head_dir.join("head.obj");
    std::fs::write(&obj, head.mesh.to_obj()).map_err(io_err(&obj))?;
    head.meta.save(&head_dir.join("head.json"))?;
    let synth_dir = out.join("synth");
    std::fs::create_dir_all(&synth_dir).map_err(io_err(&synth_dir))?;
    let cfg_path = synth_dir.join("config.json");
    let cfg_text = serde_json::to_string_pretty(config)
        .map_err(|e| Error::invalid("synth config", "json", e.to_string()))?;
    std::fs::write(&cfg_path, cfg_text).map_err(io_err(&cfg_path))?;

    let appearance = appearance::bake(head, config.texture_res, config.seed)?;
    write_maps(&appearance, &synth_dir)?;
    let seqs = sequences::sequences(config, model, &head.meta);
    // Look at the middle of the head's bounding box.
    let (lo, hi) = model
        .v_template
        .iter()
        .fold(([f32::MAX; 3], [f32::MIN; 3]), |(lo, hi), p| {
            (
                std::array::from_fn(|i| lo[i].min(p[i])),
                std::array::from_fn(|i| hi[i].max(p[i])),
            )
        });
    let target = glam::Vec3::from(std::array::from_fn::<f32, 3, _>(|i| 0.5 * (lo[i] + hi[i])));
    let rig = cameras::rig(config, target);

    let mut rng = Pcg::new(config.seed ^ 0xe7a_0b5e);
    let mut global = 0usize;
    let mut splits: [Vec<FrameRecord>; 4] = Default::default();
    let (mut rendered, mut skipped) = (0usize, 0usize);
    for seq in &seqs {
        let t0 = Instant::now();
        let dir = out.join(&seq.name);
        for sub in ["images", "fg_masks", "flame_param", "eta"] {
            let d = dir.join(sub);
            std::fs::create_dir_all(&d).map_err(io_err(&d))?;
        }
        let mut records = Vec::new();
        let mut todo = Vec::new();
        for (t, pose) in seq.frames.iter().enumerate() {
            let act = appearance.activations(pose);
            let eta = appearance.eta(&act, config.eta_noise, &mut rng); // drawn even when skipped: resumable runs stay identical
            let param = dir.join(format!("flame_param/{t:05}.npz"));
            let complete = param.exists()
                && eta_path(&param).exists()
                && (0..rig.len()).all(|c| {
                    let (i, m) = frame_names(t, c);
                    dir.join(i).exists() && dir.join(m).exists()
                });
            if complete {
                skipped += 1;
            } else {
                todo.push((t, pose, act, eta, param));
            }
            for (c, cam) in rig.iter().enumerate() {
                let (i, m) = frame_names(t, c);
                let rec = FrameRecord {
                    timestep: global + t,
                    camera_index: c,
                    file_path: format!("../{}/{i}", seq.name),
                    fg_mask_path: format!("../{}/{m}", seq.name),
                    flame_param_path: format!("../{}/flame_param/{t:05}.npz", seq.name),
                    camera: *cam,
                };
                let split = match seq.role {
                    Role::Train if c == config.val_camera => 1,
                    Role::Train => 0,
                    Role::Test => 2,
                    Role::Free => 3,
                };
                splits[split].push(rec.clone());
                records.push(FrameRecord {
                    timestep: t,
                    file_path: i,
                    fg_mask_path: m,
                    flame_param_path: format!("flame_param/{t:05}.npz"),
                    ..rec
                });
            }
        }
        rendered += todo.len();
        for (t, pose, act, eta, param) in todo {
            let verts = lbs(model, pose)?;
            let views: Vec<Result<()>> = rig
                .par_iter()
                .enumerate()
                .map(|(c, cam)| {
                    let v = render::render(
                        cam,
                        config.supersample,
                        &verts,
                        &head.mesh,
                        &appearance,
                        &act,
                        config.wrinkle_strength,
                    );
                    let (i, m) = frame_names(t, c);
                    let (w, h) = (cam.width as usize, cam.height as usize);
                    io::image::write_png(&dir.join(i), w, h, &v.rgb)?;
                    io::image::write_gray_png(&dir.join(m), w, h, &v.mask)
                })
                .collect();
            views.into_iter().collect::<Result<Vec<()>>>()?;
            io::npy::write(&eta_path(&param), &[eta.len()], &eta)?;
            pose.save_npz(&param)?; // last: its presence marks the timestep complete
        }
        save_transforms(&dir.join("transforms.json"), &records)?;
        global += seq.frames.len();
        progress(&format!(
            "{:<8} {:>3} frames x {} cameras in {:.1} s ({:.1} s so far)",
            seq.name,
            seq.frames.len(),
            rig.len(),
            t0.elapsed().as_secs_f64(),
            start.elapsed().as_secs_f64()
        ));
    }
    let union = out.join("union");
    std::fs::create_dir_all(&union).map_err(io_err(&union))?;
    for (name, frames) in ["train", "val", "test", "free"].iter().zip(&splits) {
        save_transforms(&union.join(format!("transforms_{name}.json")), frames)?;
    }
    HeadPose::neutral(model).save_npz(&union.join("canonical_flame_param.npz"))?;
    let mut summary = Summary {
        sequences: seqs.len(),
        timesteps: global,
        cameras: rig.len(),
        images: global * rig.len(),
        rendered_timesteps: rendered,
        skipped_timesteps: skipped,
        seconds: start.elapsed().as_secs_f64(),
        bytes: 0,
        split_frames: std::array::from_fn(|i| splits[i].len()),
    };
    summary.bytes = folder_bytes(out);
    let path: PathBuf = synth_dir.join("summary.json");
    let text = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::invalid("summary", "json", e.to_string()))?;
    std::fs::write(&path, text).map_err(io_err(&path))?;
    Ok(summary)
}

/// Writes the baked maps as pictures (`v` up).
fn write_maps(a: &appearance::Appearance, dir: &Path) -> Result<()> {
    let r = a.res;
    let flip = |j: usize| r - 1 - j;
    let mut rgb = vec![0.0f32; r * r * 3];
    for j in 0..r {
        for i in 0..r {
            let o = (flip(j) * r + i) * 3;
            rgb[o..o + 3].copy_from_slice(&a.albedo[j * r + i]);
        }
    }
    io::image::write_png(&dir.join("albedo.png"), r, r, &rgb)?;
    for (k, name) in appearance::WRINKLE_NAMES.iter().enumerate() {
        let mut g = vec![0.0f32; r * r];
        for j in 0..r {
            for i in 0..r {
                g[flip(j) * r + i] = a.wrinkles[j * r + i][k];
            }
        }
        io::image::write_gray_png(&dir.join(format!("wrinkles_{name}.png")), r, r, &g)?;
    }
    Ok(())
}
