//! What the viewer's render thread owns and does: the avatar, its head and subject, the
//! motion (and its dataset for ground truth), and the turn of one [`Request`] into a reply.
//!
//! A [`Scene`] is used from one thread only (the models are not `Send`); the server hands it
//! requests through a channel ([`super::server`]).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use burn::tensor::Device;
use glam::Vec3;
use serde::Serialize;

use super::limits;
use super::protocol::{CameraRequest, FrameHeader, Orbit, Output, Request, Timings};
use crate::camera::Camera;
use crate::data::dataset::pose_conditioning;
use crate::data::vhap::ETA_DIM;
use crate::data::{Conditioning, HeadDataset, Identity};
use crate::device::BackendKind;
use crate::drive::cameras::centre;
use crate::drive::fps::sync;
use crate::drive::{Motion, MotionKind};
use crate::error::{Error, Result};
use crate::head::{HeadAsset, HeadPose};
use crate::models::texavatars::{AvatarConfig, NetConfig};
use crate::models::{self, Drivable, ViewCache};
use crate::synth::cameras::look_at;

/// What the viewer shows.
#[derive(Clone, Debug)]
pub struct SceneOptions {
    /// A trained avatar (either model's output folder); `None`: an untrained TexAvatars
    /// avatar of `net` (random weights, for timing the networks).
    pub checkpoint: Option<PathBuf>,
    /// The networks of an untrained avatar.
    pub net: PathBuf,
    /// A motion to play (see `texavatars render --motion`).
    pub motion: Option<PathBuf>,
    /// Head model; default as `render` chooses it ([`crate::drive::motion::head_for`]).
    pub head: Option<PathBuf>,
    /// The avatar's subject; default the run's own, else the head's mean.
    pub identity: Option<PathBuf>,
    pub backend: BackendKind,
}

/// What the page needs to build its controls (`GET /api/info`).
#[derive(Clone, Debug, Serialize)]
pub struct Info {
    /// "TexAvatars" or "GaussianAvatars".
    pub model: String,
    /// Where the avatar came from ("untrained NET" without a checkpoint).
    pub source: String,
    pub backend: BackendKind,
    pub gaussians: usize,
    /// One name per expression coefficient (the head's `expr_names`, else "expr K").
    pub expressions: Vec<String>,
    /// Slider range of the expression coefficients (±).
    pub expression_range: f32,
    /// Whether the avatar's networks read eta (GaussianAvatars does not).
    pub reads_eta: bool,
    pub motion: Option<MotionInfo>,
    /// The orbit the page starts from (and resets to).
    pub default_orbit: Orbit,
    pub max_side: u32,
    pub min_side: u32,
}

/// The motion the page can play.
#[derive(Clone, Debug, Serialize)]
pub struct MotionInfo {
    /// "dataset", "parameters" or "curves".
    pub kind: String,
    pub source: String,
    pub frames: usize,
    /// The dataset's camera indices (preset cameras); empty for other motions.
    pub cameras: Vec<usize>,
    /// Whether the dataset's images can be shown beside the render.
    pub ground_truth: bool,
}

/// Expression coefficients of a head with named units (ARKit-like blendshapes) are weights
/// in [0, 1]; the sliders allow ±1.
const NAMED_EXPRESSION_RANGE: f32 = 1.0;
/// FLAME's expression coefficients are PCA weights in standard deviations; ±3 covers them.
const PCA_EXPRESSION_RANGE: f32 = 3.0;
/// JPEG quality of the live stream (8-bit renders; artefacts below what the eye sees at 88).
const JPEG_QUALITY: u8 = 88;

/// A dataset's frame index by (timestep, camera index).
type FrameIndex = HashMap<(usize, usize), usize>;

/// The render thread's state.
pub struct Scene {
    avatar: Box<dyn Drivable>,
    head: HeadAsset,
    identity: Identity,
    device: Device,
    motion: Option<Motion>,
    /// The dataset of a dataset motion, and its frame index by (timestep, camera index).
    dataset: Option<(HeadDataset, FrameIndex)>,
    /// Orbit centres: the sliders' neutral head, and the motion's first frame.
    neutral_centre: Vec3,
    motion_centre: Vec3,
    /// The view cache of the last camera.
    view: Option<(Camera, Option<ViewCache>)>,
    info: Info,
}

impl Scene {
    /// Loads the avatar, its head, subject and motion.
    pub fn load(opts: &SceneOptions) -> Result<Scene> {
        let head = crate::drive::motion::head_for(opts.head.as_deref(), opts.motion.as_deref())?;
        let device = opts.backend.device();
        let (avatar, run_identity, source): (Box<dyn Drivable>, _, _) = match &opts.checkpoint {
            Some(run) => {
                let l = models::load(run, &head, &device)?;
                (l.avatar, l.identity, run.display().to_string())
            }
            None => {
                let mut net = NetConfig::load(&opts.net)?;
                net.condition.expression = head.model.num_expr;
                let a = AvatarConfig::new(net)
                    .init_seeded(0, &head.mesh, &device)?
                    .for_inference();
                (
                    Box::new(a),
                    None,
                    format!("untrained {}", opts.net.display()),
                )
            }
        };
        let identity = match opts.identity.as_ref().or(run_identity.as_ref()) {
            Some(p) => Identity::load(p)?,
            None => Identity::mean(&head.model),
        }
        .fit(&head.model)?;
        let motion = match &opts.motion {
            Some(p) => {
                let m = Motion::load(p, &head.model, &head.meta, &identity)?;
                crate::drive::render::check_motion(avatar.as_ref(), &m)?;
                Some(m)
            }
            None => None,
        };
        let dataset = match &motion {
            Some(m) if m.kind == MotionKind::Dataset => {
                // Cached: a ground-truth frame reads its image, not the timestep's mesh again.
                let ds = HeadDataset::from_transforms(&m.source, Arc::new(head.model.clone()))?
                    .with_cache(true);
                let at = ds
                    .frames()
                    .iter()
                    .enumerate()
                    .map(|(i, f)| ((f.timestep, f.camera_index), i))
                    .collect();
                Some((ds, at))
            }
            _ => None,
        };
        let neutral =
            slider_conditioning(&head, &identity, &Request::neutral(), vec![0.0; ETA_DIM])?;
        crate::drive::render::check_frame(avatar.as_ref(), &neutral, "the head's neutral pose")?;
        let neutral_centre = centre(&neutral.vertices);
        let motion_centre = motion.as_ref().map_or(neutral_centre, |m| {
            centre(&m.frames[0].conditioning.vertices)
        });
        let named = head.meta.expr_names.len() == head.model.num_expr;
        let info = Info {
            model: avatar.model_name().into(),
            source,
            backend: opts.backend,
            gaussians: avatar.num_gaussians(),
            expressions: (0..head.model.num_expr)
                .map(|k| match head.meta.expr_names.get(k) {
                    Some(n) if named => n.clone(),
                    _ => format!("expr {k}"),
                })
                .collect(),
            expression_range: if named {
                NAMED_EXPRESSION_RANGE
            } else {
                PCA_EXPRESSION_RANGE
            },
            reads_eta: avatar.condition_width().is_some(),
            motion: motion.as_ref().map(|m| MotionInfo {
                kind: match m.kind {
                    MotionKind::Dataset => "dataset",
                    MotionKind::Parameters => "parameters",
                    MotionKind::Curves => "curves",
                }
                .into(),
                source: m.source.display().to_string(),
                frames: m.frames.len(),
                cameras: m.camera_indices(),
                ground_truth: m.kind == MotionKind::Dataset,
            }),
            default_orbit: limits::DEFAULT_ORBIT,
            max_side: limits::MAX_SIDE,
            min_side: limits::MIN_SIDE,
        };
        Ok(Scene {
            avatar,
            head,
            identity,
            device,
            motion,
            dataset,
            neutral_centre,
            motion_centre,
            view: None,
            info,
        })
    }

    pub fn info(&self) -> &Info {
        &self.info
    }

    /// Renders (or exports) what `r` asks for: the reply's header (with `dropped` 0) and
    /// payload. Errors name the request's field at fault.
    pub fn reply(&mut self, r: &Request) -> Result<(FrameHeader, Vec<u8>)> {
        let start = Instant::now();
        let cond = self.conditioning(r)?;
        let camera = self.camera(r)?;
        if self.view.as_ref().is_none_or(|(c, _)| *c != camera) {
            let cache = self.avatar.view_cache(&camera, &self.device)?;
            self.view = Some((camera, cache));
        }
        let cache = self.view.as_ref().and_then(|(_, v)| v.as_ref());
        let mut stages: Vec<(String, f64)> = Vec::new();
        let mut last = Instant::now();
        let device = &self.device;
        let g = self
            .avatar
            .frame_gaussians_staged(&cond, &camera, cache, device, &mut |s| {
                sync(device)?;
                let now = Instant::now();
                stages.push((s.into(), ms(now - last)));
                last = now;
                Ok(())
            })?;
        let gaussians = g.len();
        let (w, h) = (camera.width as usize, camera.height as usize);
        let (payload, gt, psnr, encode, mime) = if r.output == Output::Ply {
            let t = Instant::now();
            let (ply, _) = crate::drive::export::frame_ply(self.avatar.as_ref(), &cond, g)?;
            let bytes = crate::splat::ply::to_bytes(&ply);
            stages.push(("export".into(), ms(t.elapsed())));
            (bytes, Vec::new(), None, 0.0, "application/octet-stream")
        } else {
            let params = crate::splat::SplatParams {
                camera,
                background: crate::data::BACKGROUND,
            };
            let rgb: Vec<f32> = crate::splat::render(&g, &params)?
                .image
                .into_data()
                .iter::<f32>()
                .collect();
            stages.push(("rasterizer".into(), ms(last.elapsed())));
            let t = Instant::now();
            let (quality, mime) = match r.output {
                Output::Png => (None, "image/png"),
                _ => (Some(JPEG_QUALITY), "image/jpeg"),
            };
            let bytes = crate::io::image::encode_rgb(w, h, &rgb, quality)?;
            let encode = ms(t.elapsed());
            let (gt, psnr) = match self.ground_truth(r)? {
                Some(gt) => {
                    let png = crate::io::image::encode_rgb(w, h, &gt, None)?;
                    (png, psnr(&rgb, &gt))
                }
                None => (Vec::new(), None),
            };
            (bytes, gt, psnr, encode, mime)
        };
        let header = FrameHeader {
            output: r.output,
            id: r.id,
            mime: mime.into(),
            width: camera.width,
            height: camera.height,
            bytes: payload.len(),
            gt_bytes: gt.len(),
            psnr,
            frame: r.frame,
            gaussians,
            timings_ms: Timings {
                stages,
                encode,
                total: ms(start.elapsed()),
            },
            dropped: 0,
        };
        let mut out = payload;
        out.extend_from_slice(&gt);
        Ok((header, out))
    }

    fn motion_frame(&self, k: usize, field: &str) -> Result<&crate::drive::MotionFrame> {
        let m = self
            .motion
            .as_ref()
            .ok_or_else(|| Error::invalid("request", field, "the viewer has no --motion"))?;
        m.frames.get(k).ok_or_else(|| {
            Error::invalid(
                "request",
                field,
                format!("frame {k} is past the motion's {} frames", m.frames.len()),
            )
        })
    }

    /// The frame's conditioning: the motion frame's, or the sliders' pose on the subject.
    fn conditioning(&self, r: &Request) -> Result<Arc<Conditioning>> {
        if let Some(k) = r.frame {
            let c = self.motion_frame(k, "frame")?.conditioning.clone();
            if r.eta {
                return Ok(c);
            }
            let mut c = (*c).clone();
            c.eta.iter_mut().for_each(|v| *v = 0.0);
            return Ok(Arc::new(c));
        }
        let eta = match (r.eta, r.eta_frame) {
            (true, Some(k)) => self.motion_frame(k, "eta_frame")?.conditioning.eta.clone(),
            _ => vec![0.0; ETA_DIM],
        };
        Ok(Arc::new(slider_conditioning(
            &self.head,
            &self.identity,
            r,
            eta,
        )?))
    }

    fn camera(&self, r: &Request) -> Result<Camera> {
        match r.camera {
            CameraRequest::Orbit(o) => {
                let centre = if r.frame.is_some() {
                    self.motion_centre
                } else {
                    self.neutral_centre
                };
                Ok(orbit_camera(&o, centre))
            }
            CameraRequest::Preset(index) => {
                let k = r.frame.or(r.eta_frame).unwrap_or(0);
                let f = self.motion_frame(k, "camera.preset")?;
                f.camera(index)
                    .ok_or_else(|| {
                        Error::invalid(
                            "request",
                            "camera.preset",
                            format!(
                                "motion frame {k} has no dataset camera {index} (it has {:?})",
                                f.cameras.iter().map(|c| c.0).collect::<Vec<_>>()
                            ),
                        )
                    })
                    .and_then(|c| {
                        limits::check_side("camera.preset", c.width)?;
                        limits::check_side("camera.preset", c.height)?;
                        Ok(c)
                    })
            }
        }
    }

    /// The dataset's image for a ground-truth request (a dataset motion frame seen from a
    /// preset camera); `None` otherwise.
    fn ground_truth(&self, r: &Request) -> Result<Option<Vec<f32>>> {
        let (Some(k), CameraRequest::Preset(index), true) = (r.frame, r.camera, r.ground_truth)
        else {
            return Ok(None);
        };
        let Some((ds, at)) = &self.dataset else {
            return Ok(None);
        };
        let timestep = self.motion_frame(k, "frame")?.timestep;
        match at.get(&(timestep, index)) {
            Some(&i) => Ok(Some(ds.load_item(i)?.image)),
            None => Ok(None),
        }
    }
}

impl Request {
    /// The rest pose from the default orbit.
    pub fn neutral() -> Request {
        Request {
            output: Output::Frame,
            id: 0,
            camera: CameraRequest::Orbit(limits::DEFAULT_ORBIT),
            frame: None,
            expr: Vec::new(),
            jaw: [0.0; 3],
            neck: [0.0; 3],
            eyes: [0.0; 6],
            eta: true,
            eta_frame: None,
            ground_truth: false,
        }
    }
}

/// The sliders' pose (expression, jaw, neck, eyes; no global rotation or translation) on the
/// subject `identity`, with `eta`.
fn slider_conditioning(
    head: &HeadAsset,
    identity: &Identity,
    r: &Request,
    eta: Vec<f32>,
) -> Result<Conditioning> {
    let mut pose = HeadPose {
        shape: identity.shape.clone(),
        static_offset: identity.static_offset.clone(),
        ..HeadPose::neutral(&head.model)
    };
    pose.shape.resize(head.model.num_shape, 0.0);
    let n = r.expr.len().min(pose.expr.len());
    pose.expr[..n].copy_from_slice(&r.expr[..n]);
    pose.jaw = r.jaw;
    pose.neck = r.neck;
    pose.eyes = r.eyes;
    pose_conditioning(&head.model, pose, eta, "request")
}

/// The camera of an orbit around `centre`: azimuth `yaw` around world y, elevation `pitch`,
/// the centre shifted by `pan` along the image's right and up directions.
pub fn orbit_camera(o: &Orbit, centre: Vec3) -> Camera {
    let (yaw, pitch) = (o.yaw.to_radians(), o.pitch.to_radians());
    let dir = Vec3::new(
        yaw.sin() * pitch.cos(),
        pitch.sin(),
        yaw.cos() * pitch.cos(),
    );
    // The image's right and up directions for a camera looking along -dir with world y up
    // (as `look_at` builds it).
    let forward = -dir;
    let right = forward.cross(Vec3::Y).normalize_or_zero();
    let up = right.cross(forward);
    let target = centre + o.pan[0] * right + o.pan[1] * up;
    Camera::from_fov(
        o.width,
        o.height,
        o.fov,
        look_at(target + o.distance * dir, target),
    )
}

/// PSNR in dB of two [H, W, 3] images in [0, 1] (clamped), as [`crate::metrics::psnr`];
/// `None` for identical images.
pub fn psnr(a: &[f32], b: &[f32]) -> Option<f64> {
    let n = a.len().min(b.len());
    if n == 0 {
        return None;
    }
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| {
            let d = f64::from(x.clamp(0.0, 1.0)) - f64::from(y.clamp(0.0, 1.0));
            d * d
        })
        .sum::<f64>()
        / n as f64;
    (mse > 0.0).then(|| -10.0 * mse.log10())
}

fn ms(d: std::time::Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Tensor, TensorData};

    #[test]
    fn psnr_matches_the_metrics_module() {
        let (h, w) = (5, 4);
        let a: Vec<f32> = (0..h * w * 3)
            .map(|i| (i as f32 * 0.37).sin() * 0.6 + 0.4)
            .collect();
        let b: Vec<f32> = (0..h * w * 3)
            .map(|i| (i as f32 * 0.11).cos() * 0.5 + 0.5)
            .collect();
        let device = BackendKind::Flex.device();
        let t = |v: &[f32]| {
            Tensor::<4>::from_data(TensorData::new(v.to_vec(), [1, h, w, 3]), &device)
                .permute([0, 3, 1, 2])
        };
        let want = crate::metrics::psnr(t(&a), t(&b))
            .into_data()
            .iter::<f32>()
            .next();
        let got = psnr(&a, &b).expect("different images");
        assert!(
            (got - f64::from(want.expect("one value"))).abs() < 1e-3,
            "{got} {want:?}"
        );
        assert_eq!(psnr(&a, &a), None);
    }

    #[test]
    fn the_orbit_looks_at_its_centre_from_its_angles() {
        let o = Orbit {
            yaw: 90.0,
            pitch: 0.0,
            distance: 2.0,
            pan: [0.0, 0.0],
            fov: 20.0,
            width: 40,
            height: 60,
        };
        let c = Vec3::new(0.1, 0.2, 0.3);
        let cam = orbit_camera(&o, c);
        // The centre projects to the principal point, at depth `distance`.
        let m = cam.world_to_camera;
        let p = [
            m[0][0] * c.x + m[0][1] * c.y + m[0][2] * c.z + m[0][3],
            m[1][0] * c.x + m[1][1] * c.y + m[1][2] * c.z + m[1][3],
            m[2][0] * c.x + m[2][1] * c.y + m[2][2] * c.z + m[2][3],
        ];
        assert!(p[0].abs() < 1e-5 && p[1].abs() < 1e-5, "{p:?}");
        assert!((p[2] - 2.0).abs() < 1e-5, "{p:?}");
        // Yaw 90: the camera sits on +x.
        let eye_x = -(m[0][0] * m[0][3] + m[1][0] * m[1][3] + m[2][0] * m[2][3]);
        assert!((eye_x - (c.x + 2.0)).abs() < 1e-4, "{eye_x}");
        // Panning right moves the centre left in the image.
        let panned = orbit_camera(
            &Orbit {
                pan: [0.05, 0.0],
                ..o
            },
            c,
        );
        let m = panned.world_to_camera;
        let x = m[0][0] * c.x + m[0][1] * c.y + m[0][2] * c.z + m[0][3];
        assert!((x + 0.05).abs() < 1e-5, "{x}");
    }
}
