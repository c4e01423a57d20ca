//! Frame rate of a driven avatar with GaussianAvatars' protocol: one view of one frame
//! rendered `renders` times (500), in `rounds` rounds (3), at 802 x 550; frames per second
//! = renders / round time. Each render is timed by stage, with the device synchronised after
//! each (so GPU stages are charged to themselves): the decoders (Pluecker map, Exp2Code,
//! view encoder, both decoders), the lifting operator, the rasterizer. The image stays on
//! the device (no read-back), as in the protocol. The view's Pluecker map depends on the
//! camera alone, so, as a viewer holding its camera still would, it is computed once per
//! round's view before the loop (its time is reported on its own, [`FpsReport::view_input_ms`]).

use std::time::Instant;

use burn::tensor::Device;

use crate::camera::Camera;
use crate::data::Conditioning;
use crate::error::{Error, Result};
use crate::model::Avatar;
use crate::model::constants::BACKGROUND;
use crate::model::drivable::frame_inputs;
use crate::splat::{self, SplatParams};

/// One round's figures (per render, milliseconds, means over the round).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Round {
    pub fps: f64,
    pub total_ms: f64,
    pub decoders_ms: f64,
    pub lifting_ms: f64,
    pub rasterizer_ms: f64,
}

/// All rounds.
#[derive(Clone, Debug, serde::Serialize)]
pub struct FpsReport {
    pub renders: usize,
    /// Time of the camera's Pluecker map (once, before the renders).
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
        let sum = |f: fn(&Round) -> f64| self.rounds.iter().map(f).sum::<f64>() / n;
        Round {
            fps: sum(|r| r.fps),
            total_ms: sum(|r| r.total_ms),
            decoders_ms: sum(|r| r.decoders_ms),
            lifting_ms: sum(|r| r.lifting_ms),
            rasterizer_ms: sum(|r| r.rasterizer_ms),
        }
    }
}

fn sync(device: &Device) -> Result<()> {
    device
        .sync()
        .map_err(|e| Error::invalid("device", "sync", format!("{e:?}")))
}

/// Renders frame `c` from `camera` `renders` times per round for `rounds` rounds (after one
/// warm-up render); `progress(round)` after each round.
pub fn measure(
    avatar: &Avatar,
    c: &Conditioning,
    camera: &Camera,
    device: &Device,
    renders: usize,
    rounds: usize,
    progress: &mut dyn FnMut(usize, &Round),
) -> Result<FpsReport> {
    if renders == 0 || rounds == 0 {
        return Err(Error::invalid(
            "bench fps",
            "renders",
            "renders and rounds must be at least 1",
        ));
    }
    let (cond, verts) = frame_inputs(c, device);
    let verts = verts.squeeze_dim::<2>(0);
    let params = SplatParams {
        camera: *camera,
        background: BACKGROUND,
    };
    let t = Instant::now();
    let pluecker = avatar
        .net
        .view_input(std::slice::from_ref(camera), device)?;
    sync(device)?;
    let view_input_ms = t.elapsed().as_secs_f64() * 1e3;
    let once = |times: &mut [f64; 3]| -> Result<()> {
        let t0 = Instant::now();
        let maps = avatar.net.forward(cond.clone(), pluecker.clone())?;
        sync(device)?;
        let t1 = Instant::now();
        let g = avatar.gaussians(&maps, 0, verts.clone())?;
        sync(device)?;
        let t2 = Instant::now();
        let out = splat::render(&g, &params)?;
        sync(device)?;
        drop(out);
        let t3 = Instant::now();
        times[0] += (t1 - t0).as_secs_f64();
        times[1] += (t2 - t1).as_secs_f64();
        times[2] += (t3 - t2).as_secs_f64();
        Ok(())
    };
    once(&mut [0.0; 3])?;
    let mut report = FpsReport {
        renders,
        view_input_ms,
        gaussians: avatar.num_gaussians(),
        width: camera.width,
        height: camera.height,
        rounds: Vec::with_capacity(rounds),
    };
    for k in 0..rounds {
        let mut t = [0.0f64; 3];
        let start = Instant::now();
        for _ in 0..renders {
            once(&mut t)?;
        }
        let wall = start.elapsed().as_secs_f64();
        let per = 1e3 / renders as f64;
        let r = Round {
            fps: renders as f64 / wall,
            total_ms: wall * per,
            decoders_ms: t[0] * per,
            lifting_ms: t[1] * per,
            rasterizer_ms: t[2] * per,
        };
        report.rounds.push(r);
        progress(k + 1, &r);
    }
    Ok(report)
}
