//! Frame rate of a driven avatar with GaussianAvatars' protocol: one view of one frame
//! rendered `renders` times (500), in `rounds` rounds (3), at 802 x 550; frames per second
//! = renders / round time. Each render is timed by stage, with the device synchronised after
//! each (so GPU stages are charged to themselves): the model's own stages
//! ([`Drivable::frame_gaussians_staged`]: TexAvatars' decoders (Exp2Code, view encoder,
//! both decoders) and lifting operator; GaussianAvatars' binding), then the rasterizer. The
//! image stays on the device (no read-back), as in the protocol. What depends on the camera
//! alone ([`Drivable::view_cache`]: TexAvatars' Pluecker map) is computed once per round's
//! view before the loop, as a viewer holding its camera still would (its time is reported
//! on its own, [`FpsReport::view_input_ms`]).

use std::collections::BTreeMap;
use std::time::Instant;

use burn::tensor::Device;

use crate::camera::Camera;
use crate::data::BACKGROUND;
use crate::data::Conditioning;
use crate::error::{Error, Result};
use crate::models::Drivable;
use crate::splat::{self, SplatParams};

/// One round's figures (per render, milliseconds, means over the round): the model's stages
/// as `"{stage}_ms"` (e.g. `decoders_ms`, `lifting_ms`, `binding_ms`) and the rasterizer's.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Round {
    pub fps: f64,
    pub total_ms: f64,
    #[serde(flatten)]
    pub stages_ms: BTreeMap<String, f64>,
    pub rasterizer_ms: f64,
}

/// All rounds.
#[derive(Clone, Debug, serde::Serialize)]
pub struct FpsReport {
    /// The model ("TexAvatars", "GaussianAvatars").
    pub model: String,
    pub renders: usize,
    /// Time of what the view alone needs (once, before the renders).
    pub view_input_ms: f64,
    pub gaussians: usize,
    pub width: u32,
    pub height: u32,
    pub rounds: Vec<Round>,
}

impl FpsReport {
    /// The mean of the rounds.
    pub fn mean(&self) -> Round {
        let n = self.rounds.len().max(1) as f64;
        let sum = |f: &dyn Fn(&Round) -> f64| self.rounds.iter().map(f).sum::<f64>() / n;
        let mut stages_ms = BTreeMap::new();
        if let Some(first) = self.rounds.first() {
            for k in first.stages_ms.keys() {
                stages_ms.insert(
                    k.clone(),
                    sum(&|r| r.stages_ms.get(k).copied().unwrap_or(0.0)),
                );
            }
        }
        Round {
            fps: sum(&|r| r.fps),
            total_ms: sum(&|r| r.total_ms),
            stages_ms,
            rasterizer_ms: sum(&|r| r.rasterizer_ms),
        }
    }
}

/// Waits for the device's queued work (so a stage's time is its own).
pub fn sync(device: &Device) -> Result<()> {
    device
        .sync()
        .map_err(|e| Error::invalid("device", "sync", format!("{e:?}")))
}

/// Renders frame `c` from `camera` `renders` times per round for `rounds` rounds (after one
/// warm-up render); `progress(round)` after each round. The work runs on rayon's pool
/// ([`texavatars_cpu::threads::on_pool`]).
pub fn measure(
    avatar: &dyn Drivable,
    c: &Conditioning,
    camera: &Camera,
    device: &Device,
    renders: usize,
    rounds: usize,
    progress: &mut (dyn FnMut(usize, &Round) + Send),
) -> Result<FpsReport> {
    texavatars_cpu::threads::on_pool(|| {
        measure_here(avatar, c, camera, device, renders, rounds, progress)
    })
}

fn measure_here(
    avatar: &dyn Drivable,
    c: &Conditioning,
    camera: &Camera,
    device: &Device,
    renders: usize,
    rounds: usize,
    progress: &mut (dyn FnMut(usize, &Round) + Send),
) -> Result<FpsReport> {
    if renders == 0 || rounds == 0 {
        return Err(Error::invalid(
            "bench fps",
            "renders",
            "renders and rounds must be at least 1",
        ));
    }
    let params = SplatParams {
        camera: *camera,
        background: BACKGROUND,
    };
    let t = Instant::now();
    let view = avatar.view_cache(camera, device)?;
    sync(device)?;
    let view_input_ms = t.elapsed().as_secs_f64() * 1e3;
    let once = |times: &mut BTreeMap<String, f64>| -> Result<()> {
        let mut last = Instant::now();
        let g = avatar.frame_gaussians_staged(c, camera, view.as_ref(), device, &mut |stage| {
            sync(device)?;
            let now = Instant::now();
            *times.entry(format!("{stage}_ms")).or_insert(0.0) += (now - last).as_secs_f64();
            last = now;
            Ok(())
        })?;
        let out = splat::render(&g, &params)?;
        sync(device)?;
        drop(out);
        *times.entry("rasterizer".into()).or_insert(0.0) += last.elapsed().as_secs_f64();
        Ok(())
    };
    once(&mut BTreeMap::new())?;
    let mut report = FpsReport {
        model: avatar.model_name().into(),
        renders,
        view_input_ms,
        gaussians: avatar.num_gaussians(),
        width: camera.width,
        height: camera.height,
        rounds: Vec::with_capacity(rounds),
    };
    for k in 0..rounds {
        let mut t = BTreeMap::new();
        let start = Instant::now();
        for _ in 0..renders {
            once(&mut t)?;
        }
        let wall = start.elapsed().as_secs_f64();
        let per = 1e3 / renders as f64;
        let rasterizer_ms = t.remove("rasterizer").unwrap_or(0.0) * per;
        let r = Round {
            fps: renders as f64 / wall,
            total_ms: wall * per,
            stages_ms: t.into_iter().map(|(k, v)| (k, v * per)).collect(),
            rasterizer_ms,
        };
        progress(k + 1, &r);
        report.rounds.push(r);
    }
    Ok(report)
}
