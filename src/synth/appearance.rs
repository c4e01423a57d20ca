//! Appearance baked in UV space: a procedural albedo (skin, hair, brows, lips, irises,
//! teeth, tongue), a specular map, and expression wrinkle maps whose activations the
//! expression coefficients drive.
//!
//! Everything is a function of the canonical (rest) surface point, in head units `q`:
//! metres relative to the point between the eyes, divided by the eye distance (so the
//! patterns fit any head with FLAME's eye joints). Parts come from the meta's vertex sets
//! (`eye_l`, `eye_r`, `teeth_upper`, `teeth_lower`, `tongue`, `lips`); heads without them
//! are all skin.
//!
//! # Wrinkles
//! Seven kinds: forehead lines, glabellar lines, crow's feet (left, right), nasolabial
//! folds (left, right), chin dimpling. Each appears where its driving blendshapes move the
//! surface (their displacement, normalised) — except forehead lines, which sit in the band
//! above the brows that the brow raisers fold — times a line pattern: horizontal lines,
//! vertical lines, rays around the eye, one fold from the nose wing down, mottling. Each
//! kind's *drive* is the weighted sum of its driving expression coefficients
//! ([`WRINKLE_DRIVERS`]); its activation is `clamp(gain * drive + rest, 0, 1)`, where the
//! gain and the resting activation are the frame's hidden muscle tension
//! ([`crate::synth::tension`]), which the expression coefficients do not determine. The
//! geometry moves with the blendshapes but never shows these lines: only shading does
//! (darker albedo, less specular).
//!
//! # Subjects
//! Colours, hairline, brow thickness and the wrinkles' depth and placement come from the
//! [`Subject`]; the patterns are laid out on the subject's rest shape.
//!
//! # Eta
//! The side signal stands in for an image encoder (EMOPortraits in the paper): a fixed
//! random two-layer code of what the image shows, `eta = tanh(P a + Q x + b) + noise`, with
//! `a` the true activations, `x` the true expression coefficients and Gaussian noise
//! ([`Appearance::eta`]). It is saturating and mixes the expression in, as a learned
//! encoder's features do, but it carries the activations, which the coefficients alone
//! do not.

use glam::Vec3;

use crate::error::Result;
use crate::head::{HeadAsset, HeadPose, lbs};
use crate::synth::subject::Subject;
use crate::synth::tension::Tension;
use crate::texel::layout::UvLayout;
use crate::util::rng::Pcg;

/// Number of wrinkle kinds.
pub const WRINKLES: usize = 7;
/// Wrinkle names, in map order.
pub const WRINKLE_NAMES: [&str; WRINKLES] = [
    "forehead", "glabella", "crow_l", "crow_r", "naso_l", "naso_r", "chin",
];
/// Driving units and weights of each wrinkle.
pub const WRINKLE_DRIVERS: [&[(&str, f32)]; WRINKLES] = [
    &[
        ("browInnerUp", 1.0),
        ("browOuterUpLeft", 0.5),
        ("browOuterUpRight", 0.5),
    ],
    &[
        ("browDownLeft", 0.6),
        ("browDownRight", 0.6),
        ("noseSneerLeft", 0.3),
        ("noseSneerRight", 0.3),
    ],
    &[
        ("eyeSquintLeft", 1.0),
        ("cheekSquintLeft", 0.6),
        ("mouthSmileLeft", 0.5),
    ],
    &[
        ("eyeSquintRight", 1.0),
        ("cheekSquintRight", 0.6),
        ("mouthSmileRight", 0.5),
    ],
    &[
        ("mouthSmileLeft", 1.0),
        ("noseSneerLeft", 0.6),
        ("mouthUpperUpLeft", 0.5),
    ],
    &[
        ("mouthSmileRight", 1.0),
        ("noseSneerRight", 0.6),
        ("mouthUpperUpRight", 0.5),
    ],
    &[
        ("mouthShrugLower", 1.0),
        ("mouthPressLeft", 0.4),
        ("mouthPressRight", 0.4),
        ("mouthFrownLeft", 0.3),
        ("mouthFrownRight", 0.3),
    ],
];
/// Length of the eta side signal.
pub const ETA_DIM: usize = crate::data::vhap::ETA_DIM;
/// Gain of the activations in eta's pre-activation (each row of the projection has unit
/// expected norm per input).
const ETA_ACT_GAIN: f32 = 1.5;
/// Gain of the expression coefficients in eta's pre-activation.
const ETA_EXPR_GAIN: f32 = 0.6;
/// Standard deviation of eta's fixed per-feature bias.
const ETA_BIAS: f32 = 0.3;

/// Surface parts with their own colour and gloss.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Part {
    Skin,
    Eye,
    Teeth,
    Tongue,
}

/// The baked maps (`res x res`, row-major, row 0 at `v = 0`).
#[derive(Clone, Debug)]
pub struct Appearance {
    pub res: usize,
    /// RGB albedo.
    pub albedo: Vec<[f32; 3]>,
    /// Specular strength.
    pub specular: Vec<f32>,
    /// Per wrinkle kind, darkening at full activation, in [0, 1].
    pub wrinkles: Vec<[f32; WRINKLES]>,
    /// Driver indices and weights per wrinkle kind (resolved against the head's names).
    pub drivers: Vec<Vec<(usize, f32)>>,
    /// The eta projection of the activations [ETA_DIM x WRINKLES], row-major.
    pub eta_projection: Vec<f32>,
    /// The eta projection of the expression coefficients [ETA_DIM x E], row-major.
    pub eta_expr_projection: Vec<f32>,
    /// Eta's per-feature bias [ETA_DIM].
    pub eta_bias: Vec<f32>,
}

fn smoothstep(a: f32, b: f32, x: f32) -> f32 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Thin periodic lines: 1 on the lines, 0 between.
fn lines(x: f32, period: f32, width: f32) -> f32 {
    let f = (x / period).rem_euclid(1.0) - 0.5;
    (-(f / width).powi(2)).exp()
}

/// Smooth 3D value noise stand-in: a fixed sum of sines.
fn noise(p: Vec3, freq: f32) -> f32 {
    let q = p * freq;
    ((q.x * 1.7 + q.y * 0.3).sin()
        + (q.y * 2.1 - q.z * 0.7 + 1.3).sin()
        + (q.z * 1.3 + q.x * 0.9 + 2.1).sin())
        / 3.0
}

/// Distance from `p` to the segment `a`-`b` (2D).
fn seg_dist(p: glam::Vec2, a: glam::Vec2, b: glam::Vec2) -> f32 {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0);
    (p - (a + t * ab)).length()
}

struct Frame {
    mid: Vec3,
    scale: f32,
    eye_l: Vec3,
    eye_r: Vec3,
}

impl Frame {
    fn q(&self, p: Vec3) -> Vec3 {
        (p - self.mid) / self.scale
    }
}

fn skin_albedo(q: Vec3, lips: f32, subject: &Subject) -> [f32; 3] {
    let base = Vec3::from(subject.skin);
    let mut c = base * (1.0 + 0.05 * noise(q, 6.0) + 0.03 * noise(q, 23.0));
    // Flushed cheeks and nose tip.
    let cheek = (-((q.x.abs() - 0.7).powi(2) + (q.y + 0.75).powi(2)) / 0.12).exp()
        * smoothstep(0.0, 0.5, q.z);
    let nose = (-(q.x.powi(2) + (q.y + 0.55).powi(2)) / 0.03).exp() * smoothstep(0.5, 1.0, q.z);
    c += Vec3::new(0.05, -0.04, -0.03) * (cheek + 0.6 * nose);
    // Hair: a cap above the hairline, which drops towards the back of the head.
    let hairline = subject.hairline - 1.2 * smoothstep(0.2, -1.2, q.z);
    let hair =
        smoothstep(hairline - 0.05, hairline + 0.1, q.y) * (1.0 - smoothstep(1.35, 1.7, q.x.abs()));
    let hair_c = Vec3::from(subject.hair) * (1.0 + 0.25 * lines(q.x + 0.3 * q.z, 0.05, 0.3));
    c = c.lerp(hair_c, hair);
    // Brows: a band over each eye, thicker inside.
    let ax = q.x.abs();
    let centre = 0.42 + 0.10 * (1.0 - ((ax - 0.55) / 0.45).powi(2)).max(0.0);
    let half = 0.09 * subject.brow_thickness * (1.0 - 0.5 * smoothstep(0.2, 1.0, ax));
    let brow = (1.0 - smoothstep(half * 0.6, half, (q.y - centre).abs()))
        * smoothstep(0.08, 0.2, ax)
        * (1.0 - smoothstep(0.9, 1.05, ax))
        * smoothstep(0.2, 0.5, q.z);
    c = c.lerp(Vec3::from(subject.brow), 0.9 * brow);
    // Lips.
    c = c.lerp(Vec3::from(subject.lips), lips);
    c.to_array()
}

fn eye_albedo(d: Vec3, iris: [f32; 3]) -> [f32; 3] {
    // d: unit direction from the eyeball centre; the iris faces +z.
    let ang = d.z.clamp(-1.0, 1.0).acos();
    let sclera = Vec3::new(0.92, 0.90, 0.87);
    let iris = Vec3::from(iris) * (0.8 + 0.2 * (12.0 * d.y.atan2(d.x)).sin());
    let mut c = sclera.lerp(iris, 1.0 - smoothstep(0.42, 0.48, ang));
    c = c.lerp(Vec3::splat(0.03), 1.0 - smoothstep(0.15, 0.19, ang));
    c.to_array()
}

/// Bakes the maps for `head` at `res` (subject 0).
pub fn bake(head: &HeadAsset, res: usize, seed: u64) -> Result<Appearance> {
    bake_subject(head, res, seed, &Subject::original(head.model.num_shape))
}

/// Bakes the maps of `subject` for `head` at `res`; `seed` draws the eta code.
pub fn bake_subject(
    head: &HeadAsset,
    res: usize,
    seed: u64,
    subject: &Subject,
) -> Result<Appearance> {
    let model = &head.model;
    let meta = &head.meta;
    let v = model.num_vertices();
    let layout = UvLayout::new(&head.mesh, res)?;
    let rest_pose: HeadPose = subject.neutral(model);
    let rest = lbs(model, &rest_pose)?;
    let joints = lbs::joints(model, &rest_pose);
    let eye_l = Vec3::from(joints[3]);
    let eye_r = Vec3::from(joints[4]);
    let frame = Frame {
        mid: 0.5 * (eye_l + eye_r),
        scale: (eye_l - eye_r).length().max(1e-4),
        eye_l,
        eye_r,
    };
    let part_of: Vec<Part> = {
        let mut p = vec![Part::Skin; v];
        for (set, part) in [
            ("eye_l", Part::Eye),
            ("eye_r", Part::Eye),
            ("teeth_upper", Part::Teeth),
            ("teeth_lower", Part::Teeth),
            ("tongue", Part::Tongue),
        ] {
            for (i, m) in meta.mask(set, v).into_iter().enumerate() {
                if m {
                    p[i] = part;
                }
            }
        }
        p
    };
    let eye_of: Vec<u8> = {
        let l = meta.mask("eye_l", v);
        let r = meta.mask("eye_r", v);
        (0..v)
            .map(|i| {
                if l[i] {
                    1
                } else if r[i] {
                    2
                } else {
                    0
                }
            })
            .collect()
    };
    let lips = meta.mask("lips", v);
    // Drivers and their normalised displacement per vertex.
    let k = model.num_shape + model.num_expr;
    let drivers: Vec<Vec<(usize, f32)>> = WRINKLE_DRIVERS
        .iter()
        .map(|d| {
            d.iter()
                .filter_map(|(n, w)| meta.expr(n).map(|i| (i, *w)))
                .collect()
        })
        .collect();
    let region: Vec<Vec<f32>> = drivers
        .iter()
        .map(|d| {
            let mut m: Vec<f32> = (0..v)
                .map(|i| {
                    d.iter()
                        .map(|&(e, w)| {
                            let c = model.num_shape + e;
                            w * Vec3::new(
                                model.shapedirs[(i * 3) * k + c],
                                model.shapedirs[(i * 3 + 1) * k + c],
                                model.shapedirs[(i * 3 + 2) * k + c],
                            )
                            .length()
                        })
                        .sum::<f32>()
                })
                .collect();
            let max = m.iter().copied().fold(0.0f32, f32::max);
            if max > 0.0 {
                m.iter_mut()
                    .for_each(|x| *x = smoothstep(0.08, 0.5, *x / max));
            }
            m
        })
        .collect();
    let n = res * res;
    let mut albedo = vec![[1.0f32; 3]; n];
    let mut specular = vec![0.0f32; n];
    let mut wrinkles = vec![[0.0f32; WRINKLES]; n];
    for t in 0..n {
        let Some(_) = layout.face[t] else { continue };
        let vs = layout.verts[t];
        let b = layout.bary[t];
        let interp =
            |f: &dyn Fn(usize) -> f32| -> f32 { (0..3).map(|c| b[c] * f(vs[c] as usize)).sum() };
        let p: Vec3 = (0..3)
            .map(|c| b[c] * Vec3::from(rest[vs[c] as usize]))
            .sum();
        let q = frame.q(p);
        let part = part_of[vs[0] as usize];
        let (col, spec) = match part {
            Part::Skin => {
                let l = interp(&|i| f32::from(u8::from(lips[i])));
                (skin_albedo(q, l, subject), 0.05 + 0.08 * l)
            }
            Part::Eye => {
                let centre = if eye_of[vs[0] as usize] == 1 {
                    frame.eye_l
                } else {
                    frame.eye_r
                };
                (
                    eye_albedo((p - centre).normalize_or_zero(), subject.iris),
                    0.6,
                )
            }
            Part::Teeth => {
                let gap = lines(q.x, 0.12, 0.06);
                (
                    (Vec3::new(0.92, 0.89, 0.80) * (1.0 - 0.35 * gap)).to_array(),
                    0.3,
                )
            }
            Part::Tongue => (
                (Vec3::new(0.72, 0.36, 0.38) * (1.0 + 0.05 * noise(q, 40.0))).to_array(),
                0.25,
            ),
        };
        albedo[t] = col;
        specular[t] = spec;
        if part != Part::Skin {
            continue;
        }
        let r = |kind: usize| interp(&|i| region[kind][i]);
        let qe = |e: Vec3| frame.q(e);
        let mut w = [0.0f32; WRINKLES];
        // Forehead lines lie above what the brow raisers move (the frontalis pulls the brows
        // up and folds the skin above them): an anatomical band instead of the displacement.
        // The subject's placement: line spacing and offset, vertical shift.
        let (per, ph, sh) = (
            subject.wrinkle_period,
            subject.wrinkle_phase,
            subject.wrinkle_shift,
        );
        let band = smoothstep(0.55 + sh, 0.7 + sh, q.y)
            * (1.0 - smoothstep(1.15 + sh, 1.4 + sh, q.y))
            * (1.0 - smoothstep(0.8, 1.1, q.x.abs()))
            * smoothstep(-0.2, 0.2, q.z);
        w[0] = band * lines(q.y + ph * 0.11 * per, 0.11 * per, 0.14);
        w[1] = r(1)
            * lines(q.x + ph * 0.07 * per, 0.07 * per, 0.12)
            * (1.0 - smoothstep(0.12, 0.2, q.x.abs()))
            * smoothstep(0.05, 0.2, q.y);
        for (i, e) in [(2usize, qe(frame.eye_l)), (3, qe(frame.eye_r))] {
            let d = glam::Vec2::new(q.x - e.x, q.y - e.y);
            let lateral = smoothstep(0.25, 0.4, d.x * e.x.signum());
            let ring = smoothstep(0.3, 0.4, d.length()) * (1.0 - smoothstep(0.7, 0.85, d.length()));
            w[i] = r(i)
                * lines(d.y.atan2(d.x.abs()) + ph * 0.16 * per, 0.16 * per, 0.15)
                * lateral
                * ring;
        }
        for (i, s) in [(4usize, 1.0f32), (5, -1.0)] {
            let p2 = glam::Vec2::new(q.x, q.y);
            let d = seg_dist(
                p2,
                glam::Vec2::new(0.33 * s, -0.62 + sh),
                glam::Vec2::new(0.62 * s, -1.3 + sh),
            );
            w[i] = r(i) * (-(d / 0.04).powi(2)).exp();
        }
        w[6] = r(6)
            * (0.6 + 0.4 * noise(q, 60.0))
            * smoothstep(-1.6, -1.45, q.y)
            * (1.0 - smoothstep(-1.3, -1.2, q.y));
        wrinkles[t] = std::array::from_fn(|k| (w[k] * subject.wrinkle_depth[k]).clamp(0.0, 1.0));
    }
    dilate(&layout, res, &mut albedo, &mut specular, &mut wrinkles);
    // The eta code is the same for every subject of a seed (one encoder).
    let mut rng = Pcg::new(seed ^ 0xe7a);
    let eta_projection = (0..ETA_DIM * WRINKLES)
        .map(|_| rng.normal() / (WRINKLES as f32).sqrt())
        .collect();
    let e = model.num_expr.max(1);
    let eta_expr_projection = (0..ETA_DIM * model.num_expr)
        .map(|_| rng.normal() / (e as f32).sqrt())
        .collect();
    let eta_bias = (0..ETA_DIM).map(|_| ETA_BIAS * rng.normal()).collect();
    Ok(Appearance {
        res,
        albedo,
        specular,
        wrinkles,
        drivers,
        eta_projection,
        eta_expr_projection,
        eta_bias,
    })
}

/// Fills uncovered texels from covered neighbours (a few rings), so bilinear lookups at
/// island borders do not blend in the background.
fn dilate(
    layout: &UvLayout,
    res: usize,
    albedo: &mut [[f32; 3]],
    spec: &mut [f32],
    wr: &mut [[f32; WRINKLES]],
) {
    let mut filled: Vec<bool> = layout.face.iter().map(Option::is_some).collect();
    for _ in 0..4 {
        let prev = filled.clone();
        for j in 0..res {
            for i in 0..res {
                let t = j * res + i;
                if prev[t] {
                    continue;
                }
                let nb = [
                    (i.wrapping_sub(1), j),
                    (i + 1, j),
                    (i, j.wrapping_sub(1)),
                    (i, j + 1),
                ];
                if let Some(&(a, b)) = nb
                    .iter()
                    .find(|&&(a, b)| a < res && b < res && prev[b * res + a])
                {
                    let s = b * res + a;
                    albedo[t] = albedo[s];
                    spec[t] = spec[s];
                    wr[t] = wr[s];
                    filled[t] = true;
                }
            }
        }
    }
}

impl Appearance {
    /// Each wrinkle kind's drive: the weighted sum of its driving expression coefficients
    /// (not clamped).
    pub fn drive(&self, pose: &HeadPose) -> [f32; WRINKLES] {
        std::array::from_fn(|k| {
            self.drivers[k]
                .iter()
                .map(|&(e, w)| w * pose.expr.get(e).copied().unwrap_or(0.0))
                .sum::<f32>()
        })
    }

    /// Wrinkle activations of a frame's expression coefficients without hidden tension
    /// (gain 1, nothing at rest), each in [0, 1].
    pub fn activations(&self, pose: &HeadPose) -> [f32; WRINKLES] {
        self.activations_with(pose, &Tension::RELAXED)
    }

    /// Wrinkle activations of a frame: `clamp(gain * drive + rest, 0, 1)` per kind, the
    /// gain and rest being the frame's hidden muscle tension.
    pub fn activations_with(&self, pose: &HeadPose, tension: &Tension) -> [f32; WRINKLES] {
        let d = self.drive(pose);
        std::array::from_fn(|k| (tension.gain[k] * d[k] + tension.rest[k]).clamp(0.0, 1.0))
    }

    /// The eta side signal of a frame with true activations `act` and true expression
    /// coefficients `expr`: `tanh(P act + Q expr + b)` plus Gaussian noise of standard
    /// deviation `noise` (see the module docs).
    pub fn eta(&self, act: &[f32; WRINKLES], expr: &[f32], noise: f32, rng: &mut Pcg) -> Vec<f32> {
        let e = self.eta_expr_projection.len() / ETA_DIM;
        (0..ETA_DIM)
            .map(|r| {
                let a = (0..WRINKLES)
                    .map(|k| self.eta_projection[r * WRINKLES + k] * act[k])
                    .sum::<f32>();
                let x = (0..e.min(expr.len()))
                    .map(|j| self.eta_expr_projection[r * e + j] * expr[j])
                    .sum::<f32>();
                (ETA_ACT_GAIN * a + ETA_EXPR_GAIN * x + self.eta_bias[r]).tanh()
                    + noise * rng.normal()
            })
            .collect()
    }

    /// Bilinear lookup at `uv` (OBJ convention, clamped to the map): albedo, specular and
    /// wrinkle darkening for the given activations.
    pub fn sample(&self, uv: [f32; 2], act: &[f32; WRINKLES]) -> ([f32; 3], f32, f32) {
        let r = self.res;
        let x = (uv[0] * r as f32 - 0.5).clamp(0.0, (r - 1) as f32);
        let y = (uv[1] * r as f32 - 0.5).clamp(0.0, (r - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(r - 1), (y0 + 1).min(r - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let taps = [
            (x0, y0, (1.0 - fx) * (1.0 - fy)),
            (x1, y0, fx * (1.0 - fy)),
            (x0, y1, (1.0 - fx) * fy),
            (x1, y1, fx * fy),
        ];
        let mut a = [0.0f32; 3];
        let (mut s, mut w) = (0.0f32, 0.0f32);
        for (i, j, wt) in taps {
            let t = j * r + i;
            for (ac, &x) in a.iter_mut().zip(&self.albedo[t]) {
                *ac += wt * x;
            }
            s += wt * self.specular[t];
            w += wt
                * (0..WRINKLES)
                    .map(|k| act[k] * self.wrinkles[t][k])
                    .sum::<f32>();
        }
        (a, s, w.clamp(0.0, 1.0))
    }
}
