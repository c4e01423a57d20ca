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
//!                                          eyes_pose (1, 6), expr (1, E), shape (S,):
//!                                          what a tracker reports (truth plus noise)
//! OUT/<sequence>/eta/TTTTT.npy             float32 [128] side signal
//! OUT/<sequence>/truth/TTTTT.npz           the true parameters (same keys) and
//!                                          activations (7,), tension_gain (7,),
//!                                          tension_rest (7,); for analysis, never read
//!                                          by training
//! OUT/<sequence>/transforms.json           every frame of the sequence, local timesteps
//! OUT/union/transforms_{train,val,test,free}.json   the splits, `../<sequence>/...` paths,
//!                                          global timesteps
//! OUT/union/canonical_flame_param.npz      the neutral parameters
//! OUT/head/head.{npz,obj,json}             the head it was rendered from
//! OUT/synth/{config.json, summary.json, albedo.png, wrinkles_*.png}
//! OUT/synth/analysis.json                  `texavatars synth --analyse OUT` ([`analysis`])
//! ```
//!
//! Splits (NeRSemble protocol): train = the ten training sequences on every camera but
//! `val_camera`; val = the same frames from `val_camera` (novel view); test = the held-out
//! sequence on every camera (novel expression); free = the FREE sequence on every camera.
//!
//! The capture is of one subject ([`subject`], `SynthConfig::subject`; one export folder
//! per subject). Images are rendered from the true parameters; per frame the conditioning
//! is what a tracker would report ([`tracking`]: the truth plus noise on the expression,
//! the joint rotations and the translation), the 15 pose values, and eta: an image-like
//! encoding of the frame's true wrinkle activations plus noise (a stand-in for an
//! image-based expression encoder, [`appearance`]). The activations depend on the
//! expression *and* on a hidden per-frame muscle tension ([`tension`]) that the
//! coefficients do not determine; [`analysis`] measures how much of them each signal
//! explains. Rendering a timestep is skipped when all its files exist, so an interrupted
//! run resumes where it stopped; files are written through temporary names (`X.partial`),
//! which a run removes when it fails and, left by a killed run, when it starts.
//!
//! The settings are recorded in `OUT/synth/config.json` and the head in `OUT/head/`. A run
//! into a folder that records the same settings and head resumes it (complete timesteps are
//! skipped, not rendered again). A folder that records different ones is refused, naming
//! the first field that differs (or `head`), unless [`generate_with`] is called with
//! `force`: then the files a run writes (the layout above, matched by name; nothing else)
//! are deleted first and everything is rendered again.

pub mod analysis;
pub mod appearance;
pub mod cameras;
pub mod config;
pub mod render;
pub mod sequences;
pub mod subject;
pub mod tension;
pub mod tracking;

use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use crate::data::vhap::{FrameRecord, eta_path, save_transforms};
use crate::error::{Error, Result};
use crate::head::{HeadAsset, HeadPose, lbs};
use crate::io;
use crate::util::rng::Pcg;

pub use config::SynthConfig;
pub use sequences::{Role, Sequence};
pub use subject::Subject;

/// What a run produced.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Summary {
    /// The subject rendered.
    pub subject: usize,
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
/// A folder made with other settings or another head is refused ([`generate_with`]).
pub fn generate(
    config: &SynthConfig,
    head: &HeadAsset,
    out: &Path,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<Summary> {
    generate_with(config, head, out, false, progress)
}

/// [`generate`]; with `force`, a folder made with other settings or another head is cleared
/// of the files a run writes and generated again instead of refused (see the module docs).
/// Runs on rayon's pool ([`texavatars_cpu::threads::on_pool`]), as [`crate::train::train`].
pub fn generate_with(
    config: &SynthConfig,
    head: &HeadAsset,
    out: &Path,
    force: bool,
    progress: &mut (dyn FnMut(&str) + Send),
) -> Result<Summary> {
    texavatars_cpu::threads::on_pool(|| generate_here(config, head, out, force, progress))
}

/// [`generate_with`] on the calling thread.
fn generate_here(
    config: &SynthConfig,
    head: &HeadAsset,
    out: &Path,
    force: bool,
    progress: &mut dyn FnMut(&str),
) -> Result<Summary> {
    config.validate("synth config")?;
    config.check_memory("synth config")?;
    if let Some((what, field, why)) = recorded_difference(config, head, out)? {
        if !force {
            return Err(Error::invalid(
                what,
                field,
                format!(
                    "{why}: {} holds a benchmark made with other settings; re-run with --force to delete its files and generate it again, or choose another output folder",
                    out.display()
                ),
            ));
        }
        let n = clear_owned(out, &|_| true)?;
        progress(&format!(
            "--force: {field} differs ({why}); removed {n} file(s) of the earlier run"
        ));
    }
    let stale = clear_owned(out, &partial)?;
    if stale > 0 {
        progress(&format!(
            "removed {stale} unfinished temporary file(s) of an earlier run"
        ));
    }
    let r = generate_into(config, head, out, progress);
    if r.is_err() {
        let _ = clear_owned(out, &partial);
    }
    r
}

/// Whether a file name is a temporary one (`X.partial`).
fn partial(name: &str) -> bool {
    name.ends_with(".partial")
}

/// Where `out` holds a run made with other settings or another head: `(file, field, why)`
/// for the first difference. `None` for a folder without a recorded run, or the same one.
pub fn recorded_difference(
    config: &SynthConfig,
    head: &HeadAsset,
    out: &Path,
) -> Result<Option<(String, String, String)>> {
    let cfg_path = out.join("synth/config.json");
    let what = cfg_path.display().to_string();
    let text = match std::fs::read_to_string(&cfg_path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Error::io(&cfg_path, e)),
    };
    let recorded: SynthConfig = match serde_json::from_str(&text) {
        Ok(c) => c,
        Err(e) => {
            return Ok(Some((
                what,
                "config".into(),
                format!("the recorded settings cannot be read ({e})"),
            )));
        }
    };
    if recorded != *config {
        let json = |c: &SynthConfig| serde_json::to_value(c).unwrap_or_default();
        let (old, new) = (json(&recorded), json(config));
        let field = new
            .as_object()
            .and_then(|n| {
                n.iter()
                    .find(|(k, v)| old.get(k.as_str()) != Some(*v))
                    .map(|(k, v)| (k.clone(), old.get(k.as_str()).cloned(), v.clone()))
            })
            .map(|(k, o, n)| {
                let o = o.map_or_else(|| "nothing".into(), |o| o.to_string());
                (k, format!("recorded {o}, now {n}"))
            })
            .unwrap_or_else(|| ("config".into(), "the settings differ".into()));
        return Ok(Some((what, field.0, field.1)));
    }
    // The head: the files this run would write, compared with the recorded ones.
    let head_dir = out.join("head");
    if head_dir.join("head.npz").exists() {
        let scratch = std::env::temp_dir().join(format!(
            "texavatars-synth-head-{}-{}",
            std::process::id(),
            HEAD_CHECKS.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&scratch).map_err(io_err(&scratch))?;
        let r = write_head(head, &scratch).and_then(|()| {
            for f in ["head.npz", "head.obj", "head.json"] {
                let new = std::fs::read(scratch.join(f)).map_err(io_err(&scratch.join(f)))?;
                if std::fs::read(head_dir.join(f)).ok().as_deref() != Some(new.as_slice()) {
                    return Ok(Some((
                        head_dir.join(f).display().to_string(),
                        "head".to_string(),
                        "the folder was made from another head model".to_string(),
                    )));
                }
            }
            Ok(None)
        });
        let _ = std::fs::remove_dir_all(&scratch);
        return r;
    }
    Ok(None)
}

/// Distinguishes the scratch folders of concurrent head comparisons in one process.
static HEAD_CHECKS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Writes the head files (`head.npz`, `head.obj`, `head.json`) into `dir`.
fn write_head(head: &HeadAsset, dir: &Path) -> Result<()> {
    head.model.save(&dir.join("head.npz"))?;
    let obj = dir.join("head.obj");
    std::fs::write(&obj, head.mesh.to_obj()).map_err(io_err(&obj))?;
    head.meta.save(&dir.join("head.json"))
}

/// Whether `name` is `DIGITS_DIGITS.ext` (an image or mask) or `DIGITS.ext`, optionally
/// with `.partial` appended.
fn frame_file(name: &str, ext: &str, with_camera: bool) -> bool {
    let name = name.strip_suffix(".partial").unwrap_or(name);
    let Some(stem) = name.strip_suffix(ext) else {
        return false;
    };
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    match (with_camera, stem.split_once('_')) {
        (true, Some((t, c))) => digits(t) && digits(c),
        (false, None) => digits(stem),
        _ => false,
    }
}

/// Removes the files a run writes into `out` (see the module docs) that `pick` also
/// accepts; returns how many. Sub-folders and files of other names are left alone.
fn clear_owned(out: &Path, pick: &dyn Fn(&str) -> bool) -> Result<usize> {
    use crate::util::files::clear_matching;
    let base = |n: &str| n.strip_suffix(".partial").unwrap_or(n).to_string();
    let mut n = 0;
    n += clear_matching(&out.join("synth"), &|f| {
        let b = base(f);
        pick(f)
            && (matches!(
                b.as_str(),
                "config.json" | "summary.json" | "analysis.json" | "albedo.png"
            ) || (b.starts_with("wrinkles_") && b.ends_with(".png")))
    })?;
    n += clear_matching(&out.join("head"), &|f| {
        pick(f) && matches!(base(f).as_str(), "head.npz" | "head.obj" | "head.json")
    })?;
    n += clear_matching(&out.join("union"), &|f| {
        let b = base(f);
        pick(f)
            && (b == "canonical_flame_param.npz"
                || ["train", "val", "test", "free"]
                    .iter()
                    .any(|s| b == format!("transforms_{s}.json")))
    })?;
    let names = sequences::TRAIN_FAMILIES
        .iter()
        .map(|f| f.0)
        .chain([sequences::TEST_FAMILY.0, sequences::FREE_NAME]);
    for seq in names {
        let dir = out.join(seq);
        n += clear_matching(&dir, &|f| pick(f) && base(f) == "transforms.json")?;
        n += clear_matching(&dir.join("images"), &|f| {
            pick(f) && frame_file(f, ".png", true)
        })?;
        n += clear_matching(&dir.join("fg_masks"), &|f| {
            pick(f) && frame_file(f, ".png", true)
        })?;
        n += clear_matching(&dir.join("flame_param"), &|f| {
            pick(f) && frame_file(f, ".npz", false)
        })?;
        n += clear_matching(&dir.join("eta"), &|f| {
            pick(f) && frame_file(f, ".npy", false)
        })?;
        n += clear_matching(&dir.join(TRUTH_DIR), &|f| {
            pick(f) && frame_file(f, ".npz", false)
        })?;
    }
    Ok(n)
}

/// The folder of a sequence that holds the true parameters (`truth/TTTTT.npz`).
pub const TRUTH_DIR: &str = "truth";

/// Where the truth of a timestep lives, given its `flame_param` path
/// (`<sequence>/flame_param/TTTTT.npz` → `<sequence>/truth/TTTTT.npz`).
pub fn truth_path(flame_param: &Path) -> PathBuf {
    let dir = flame_param
        .parent()
        .and_then(Path::parent)
        .unwrap_or(Path::new("."));
    dir.join(TRUTH_DIR)
        .join(flame_param.file_name().unwrap_or_default())
}

/// Writes a frame's truth: the true parameters under VHAP's keys
/// ([`HeadPose::save_npz`]'s), its wrinkle activations and its hidden tension.
fn write_truth(
    path: &Path,
    pose: &HeadPose,
    act: &[f32; appearance::WRINKLES],
    tension: &tension::Tension,
) -> Result<()> {
    pose.check_finite(&path.display().to_string())?;
    let w = appearance::WRINKLES;
    let mut out = io::npz::NpzOut::default();
    out.floats("translation", &[1, 3], pose.translation.to_vec())
        .floats("rotation", &[1, 3], pose.rotation.to_vec())
        .floats("neck_pose", &[1, 3], pose.neck.to_vec())
        .floats("jaw_pose", &[1, 3], pose.jaw.to_vec())
        .floats("eyes_pose", &[1, 6], pose.eyes.to_vec())
        .floats("expr", &[1, pose.expr.len()], pose.expr.clone())
        .floats("shape", &[pose.shape.len()], pose.shape.clone())
        .floats("activations", &[w], act.to_vec())
        .floats("tension_gain", &[w], tension.gain.to_vec())
        .floats("tension_rest", &[w], tension.rest.to_vec());
    out.write(path)
}

/// One captured frame: the truth, what the tracker reports, the hidden tension, the true
/// wrinkle activations and eta.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The true parameters (the images are rendered from them).
    pub truth: HeadPose,
    /// What a tracker reports: the truth plus noise (`flame_param/`).
    pub reported: HeadPose,
    /// The hidden muscle tension.
    pub tension: tension::Tension,
    /// The true wrinkle activations.
    pub activations: [f32; appearance::WRINKLES],
    /// The eta side signal.
    pub eta: Vec<f32>,
}

/// Everything a run renders and writes, before any image: the subject, its appearance and
/// per sequence its frames. Deterministic in the config.
pub struct Capture {
    pub subject: Subject,
    pub appearance: appearance::Appearance,
    pub sequences: Vec<(Sequence, Vec<Frame>)>,
}

/// The capture of `config`'s subject with `head` (see the module docs): subject, baked
/// appearance, sequences with their true and reported parameters, tension, activations
/// and eta.
pub fn capture(config: &SynthConfig, head: &HeadAsset) -> Result<Capture> {
    let model = &head.model;
    let subject = Subject::new(config.subject, model.num_shape, config.seed);
    let appearance = appearance::bake_subject(head, config.texture_res, config.seed, &subject)?;
    let mut seqs = sequences::sequences(config, model, &head.meta);
    for pose in seqs.iter_mut().flat_map(|s| s.frames.iter_mut()) {
        pose.shape.clone_from(&subject.shape);
    }
    let expr_std = tracking::expr_noise_std(model, config.tracking.expr_mm);
    // Every subject performs the same sequences, each with its own tension, its own
    // tracking errors and its own eta noise (subject 0 keeps the config's seed).
    let seed = config.seed ^ (config.subject as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let mut rng = Pcg::new(seed ^ 0xe7a_0b5e);
    let sequences = seqs
        .into_iter()
        .enumerate()
        .map(|(si, seq)| {
            let tensions = tension::sequence_tension(seq.frames.len(), si, config.tension, seed);
            let reported = tracking::track(
                &seq.frames,
                &config.tracking,
                expr_std,
                &mut Pcg::new(seed ^ 0x7_2ac6 ^ (si as u64).wrapping_mul(0x51_7cc1)),
            );
            let frames = seq
                .frames
                .iter()
                .zip(reported)
                .zip(tensions)
                .map(|((truth, reported), tension)| {
                    let act = appearance.activations_with(truth, &tension);
                    let eta = appearance.eta(&act, &truth.expr, config.eta_noise, &mut rng);
                    Frame {
                        truth: truth.clone(),
                        reported,
                        tension,
                        activations: act,
                        eta,
                    }
                })
                .collect();
            (seq, frames)
        })
        .collect();
    Ok(Capture {
        subject,
        appearance,
        sequences,
    })
}

fn generate_into(
    config: &SynthConfig,
    head: &HeadAsset,
    out: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<Summary> {
    let start = Instant::now();
    let model = &head.model;
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    // The head and the settings travel with the data.
    let head_dir = out.join("head");
    std::fs::create_dir_all(&head_dir).map_err(io_err(&head_dir))?;
    write_head(head, &head_dir)?;
    let synth_dir = out.join("synth");
    std::fs::create_dir_all(&synth_dir).map_err(io_err(&synth_dir))?;
    let cfg_path = synth_dir.join("config.json");
    let cfg_text = serde_json::to_string_pretty(config)
        .map_err(|e| Error::invalid("synth config", "json", e.to_string()))?;
    let cfg_tmp = cfg_path.with_extension("json.partial");
    std::fs::write(&cfg_tmp, cfg_text).map_err(io_err(&cfg_tmp))?;
    std::fs::rename(&cfg_tmp, &cfg_path).map_err(io_err(&cfg_path))?;

    let Capture {
        subject,
        appearance,
        sequences: seqs,
    } = capture(config, head)?;
    write_maps(&appearance, &synth_dir)?;
    // Look at the middle of the subject's bounding box.
    let rest = lbs(model, &subject.neutral(model))?;
    let (lo, hi) = rest
        .iter()
        .fold(([f32::MAX; 3], [f32::MIN; 3]), |(lo, hi), p| {
            (
                std::array::from_fn(|i| lo[i].min(p[i])),
                std::array::from_fn(|i| hi[i].max(p[i])),
            )
        });
    let target = glam::Vec3::from(std::array::from_fn::<f32, 3, _>(|i| 0.5 * (lo[i] + hi[i])));
    let rig = cameras::rig(config, target);

    let mut global = 0usize;
    let mut splits: [Vec<FrameRecord>; 4] = Default::default();
    let (mut rendered, mut skipped) = (0usize, 0usize);
    for (seq, frames) in &seqs {
        let t0 = Instant::now();
        let dir = out.join(&seq.name);
        for sub in ["images", "fg_masks", "flame_param", "eta", TRUTH_DIR] {
            let d = dir.join(sub);
            std::fs::create_dir_all(&d).map_err(io_err(&d))?;
        }
        let mut records = Vec::new();
        let mut todo = Vec::new();
        for (t, frame) in frames.iter().enumerate() {
            let param = dir.join(format!("flame_param/{t:05}.npz"));
            let complete = param.exists()
                && eta_path(&param).exists()
                && truth_path(&param).exists()
                && (0..rig.len()).all(|c| {
                    let (i, m) = frame_names(t, c);
                    dir.join(i).exists() && dir.join(m).exists()
                });
            if complete {
                skipped += 1;
            } else {
                todo.push((t, frame, param));
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
        for (t, frame, param) in todo {
            let verts = lbs(model, &frame.truth)?;
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
                        &frame.activations,
                        config.wrinkle_strength,
                    );
                    let (i, m) = frame_names(t, c);
                    let (w, h) = (cam.width as usize, cam.height as usize);
                    io::image::write_png(&dir.join(i), w, h, &v.rgb)?;
                    io::image::write_gray_png(&dir.join(m), w, h, &v.mask)
                })
                .collect();
            views.into_iter().collect::<Result<Vec<()>>>()?;
            io::npy::write(&eta_path(&param), &[frame.eta.len()], &frame.eta)?;
            write_truth(
                &truth_path(&param),
                &frame.truth,
                &frame.activations,
                &frame.tension,
            )?;
            frame.reported.save_npz(&param)?; // last: its presence marks the timestep complete
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
    subject
        .neutral(model)
        .save_npz(&union.join("canonical_flame_param.npz"))?;
    let mut summary = Summary {
        subject: config.subject,
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
