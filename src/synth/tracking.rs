//! Tracking error: what a tracker would report instead of the truth.
//!
//! The images are rendered from the true parameters; `flame_param/TTTTT.npz` holds the
//! truth plus noise on the expression coefficients, the joint rotations and the
//! translation ([`track`]), as a real tracker's output is wrong by millimetres. The truth
//! is kept in `truth/TTTTT.npz` for analysis only.
//!
//! The noise is Gaussian, correlated from frame to frame within a sequence (first-order
//! autoregressive with coefficient `correlation`: trackers smooth over time, so their
//! errors drift rather than flicker) and independent between sequences. Its levels are
//! [`TrackingNoise`]; the expression noise is given as the RMS vertex error it causes on
//! the face ([`expr_noise_std`] turns it into a coefficient standard deviation for the
//! head model at hand). Where the default levels come from is in `docs/benchmark.md`.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::head::{HeadModel, HeadPose, lbs};
use crate::util::rng::Pcg;

/// Noise levels of the tracked parameters (standard deviations per value).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingNoise {
    /// RMS vertex error over the face that the expression-coefficient noise causes, mm.
    pub expr_mm: f32,
    /// Global head rotation, degrees per axis-angle component.
    pub rotation_deg: f32,
    /// Neck rotation, degrees per component.
    pub neck_deg: f32,
    /// Jaw rotation, degrees per component.
    pub jaw_deg: f32,
    /// Eye rotations (gaze), degrees per component.
    pub eyes_deg: f32,
    /// Translation, mm per axis (model units are metres).
    pub translation_mm: f32,
    /// Frame-to-frame correlation of the noise within a sequence, in [0, 1).
    pub correlation: f32,
}

impl Default for TrackingNoise {
    fn default() -> Self {
        TrackingNoise {
            expr_mm: 1.0,
            rotation_deg: 0.5,
            neck_deg: 0.3,
            jaw_deg: 0.5,
            eyes_deg: 1.5,
            translation_mm: 1.0,
            correlation: 0.6,
        }
    }
}

impl TrackingNoise {
    /// No noise: `flame_param/` holds the truth.
    pub fn none() -> Self {
        TrackingNoise {
            expr_mm: 0.0,
            rotation_deg: 0.0,
            neck_deg: 0.0,
            jaw_deg: 0.0,
            eyes_deg: 0.0,
            translation_mm: 0.0,
            correlation: 0.0,
        }
    }

    /// Checks that every level is finite and >= 0 and the correlation in [0, 1); errors
    /// name `what` and the field (`tracking.<field>`).
    pub fn validate(&self, what: &str) -> Result<()> {
        for (field, v) in [
            ("expr_mm", self.expr_mm),
            ("rotation_deg", self.rotation_deg),
            ("neck_deg", self.neck_deg),
            ("jaw_deg", self.jaw_deg),
            ("eyes_deg", self.eyes_deg),
            ("translation_mm", self.translation_mm),
        ] {
            if !v.is_finite() || !(0.0..=1000.0).contains(&v) {
                return Err(Error::invalid(
                    what,
                    format!("tracking.{field}"),
                    format!("{v}: must be from 0 to 1000"),
                ));
            }
        }
        if !self.correlation.is_finite() || !(0.0..1.0).contains(&self.correlation) {
            return Err(Error::invalid(
                what,
                "tracking.correlation",
                format!("{}: must be in [0, 1)", self.correlation),
            ));
        }
        Ok(())
    }
}

/// The vertices expressions move: those whose largest displacement per unit coefficient,
/// over all expression components, is at least a tenth of the model's largest.
pub fn face_vertices(model: &HeadModel) -> Vec<usize> {
    let v = model.num_vertices();
    let k = model.num_shape + model.num_expr;
    let moved: Vec<f32> = (0..v)
        .map(|i| {
            (0..model.num_expr)
                .map(|j| {
                    let c = model.num_shape + j;
                    (0..3)
                        .map(|a| model.shapedirs[(i * 3 + a) * k + c].powi(2))
                        .sum::<f32>()
                        .sqrt()
                })
                .fold(0.0, f32::max)
        })
        .collect();
    let max = moved.iter().copied().fold(0.0, f32::max);
    (0..v)
        .filter(|&i| max > 0.0 && moved[i] >= 0.1 * max)
        .collect()
}

/// The standard deviation of independent noise on every expression coefficient that moves
/// the face's vertices ([`face_vertices`]) by `mm` millimetres RMS: `mm / sqrt(sum_j
/// mean_i |d_ij|^2)`, `d_ij` the displacement of vertex `i` per unit of component `j`
/// (model units taken as metres). 0 for a model without expressions.
pub fn expr_noise_std(model: &HeadModel, mm: f32) -> f32 {
    let face = face_vertices(model);
    if face.is_empty() || mm <= 0.0 {
        return 0.0;
    }
    let k = model.num_shape + model.num_expr;
    let total: f64 = (0..model.num_expr)
        .map(|j| {
            let c = model.num_shape + j;
            face.iter()
                .map(|&i| {
                    (0..3)
                        .map(|a| f64::from(model.shapedirs[(i * 3 + a) * k + c]).powi(2))
                        .sum::<f64>()
                })
                .sum::<f64>()
                / face.len() as f64
        })
        .sum();
    if total <= 0.0 {
        return 0.0;
    }
    (f64::from(mm) * 1e-3 / total.sqrt()) as f32
}

/// Mean and RMS distance between the vertices of two poses of `model` over `vertices`
/// (all when empty), in model units.
pub fn vertex_error(
    model: &HeadModel,
    a: &HeadPose,
    b: &HeadPose,
    vertices: &[usize],
) -> Result<(f64, f64)> {
    let (va, vb) = (lbs(model, a)?, lbs(model, b)?);
    let all: Vec<usize>;
    let idx = if vertices.is_empty() {
        all = (0..va.len()).collect();
        &all[..]
    } else {
        vertices
    };
    let d: Vec<f64> = idx
        .iter()
        .map(|&i| {
            (0..3)
                .map(|c| f64::from(va[i][c] - vb[i][c]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    let n = d.len().max(1) as f64;
    Ok((
        d.iter().sum::<f64>() / n,
        (d.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
    ))
}

/// First-order autoregressive Gaussian noise: `len` series of `frames` values each, unit
/// stationary variance, frame-to-frame correlation `rho`. Indexed `[frame][series]`.
fn ar1(frames: usize, len: usize, rho: f32, rng: &mut Pcg) -> Vec<Vec<f32>> {
    let innovation = (1.0 - rho * rho).max(0.0).sqrt();
    let mut state: Vec<f32> = (0..len).map(|_| rng.normal()).collect();
    let mut out = Vec::with_capacity(frames);
    for f in 0..frames {
        if f > 0 {
            for x in state.iter_mut() {
                *x = rho * *x + innovation * rng.normal();
            }
        }
        out.push(state.clone());
    }
    out
}

/// What a tracker reports for the true frames `truth` of one sequence: each expression
/// coefficient plus noise of standard deviation `expr_std` (see [`expr_noise_std`]), the
/// rotations and the translation plus noise at `noise`'s levels, all correlated over the
/// frames. Shape and static offsets are kept.
pub fn track(
    truth: &[HeadPose],
    noise: &TrackingNoise,
    expr_std: f32,
    rng: &mut Pcg,
) -> Vec<HeadPose> {
    let e = truth.first().map_or(0, |p| p.expr.len());
    let n = ar1(truth.len(), e + 18, noise.correlation, rng);
    let deg = |d: f32| d.to_radians();
    truth
        .iter()
        .zip(n)
        .map(|(p, z)| {
            let mut q = p.clone();
            for (j, x) in q.expr.iter_mut().enumerate() {
                *x += expr_std * z[j];
            }
            let z = &z[e..];
            for c in 0..3 {
                q.rotation[c] += deg(noise.rotation_deg) * z[c];
                q.neck[c] += deg(noise.neck_deg) * z[3 + c];
                q.jaw[c] += deg(noise.jaw_deg) * z[6 + c];
                q.translation[c] += noise.translation_mm * 1e-3 * z[9 + c];
            }
            for c in 0..6 {
                q.eyes[c] += deg(noise.eyes_deg) * z[12 + c];
            }
            q
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::head::HeadAsset;

    #[test]
    fn expression_noise_is_calibrated_in_millimetres() {
        let head = HeadAsset::embedded().expect("head");
        let model = &head.model;
        let face = face_vertices(model);
        assert!(face.len() > 100 && face.len() < model.num_vertices());
        let std = expr_noise_std(model, 1.0);
        eprintln!(
            "embedded head: {} face vertices, expression noise {std} per unit for 1 mm",
            face.len()
        );
        assert!(std > 0.0 && std < 0.5, "{std}");
        // Independent noise at that level moves the face by about 1 mm RMS.
        let truth = vec![HeadPose::neutral(model); 24];
        let noise = TrackingNoise {
            expr_mm: 1.0,
            ..TrackingNoise::none()
        };
        let mut rng = Pcg::new(3);
        let tracked = track(&truth, &noise, std, &mut rng);
        let mut ms = 0.0;
        for (a, b) in truth.iter().zip(&tracked) {
            let (_, rms) = vertex_error(model, a, b, &face).expect("error");
            ms += rms * rms;
        }
        let rms_mm = (ms / truth.len() as f64).sqrt() * 1e3;
        assert!((0.7..1.3).contains(&rms_mm), "{rms_mm} mm");
        // Without noise the tracker reports the truth; rotations get their levels.
        assert_eq!(track(&truth, &TrackingNoise::none(), 0.0, &mut rng), truth);
        let rot = TrackingNoise {
            rotation_deg: 1.0,
            correlation: 0.9,
            ..TrackingNoise::none()
        };
        let t = track(&vec![HeadPose::neutral(model); 400], &rot, 0.0, &mut rng);
        let r: Vec<f32> = t.iter().map(|p| p.rotation[1].to_degrees()).collect();
        let sd = (r.iter().map(|x| x * x).sum::<f32>() / r.len() as f32).sqrt();
        assert!((0.6..1.4).contains(&sd), "{sd} degrees");
        // Correlated: neighbouring frames differ much less than the level.
        let step = (r.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum::<f32>()
            / (r.len() - 1) as f32)
            .sqrt();
        assert!(step < 0.7 * sd, "{step} vs {sd}");
        assert!(t.iter().all(|p| p.expr == truth[0].expr));
    }

    #[test]
    fn bad_levels_name_the_field() {
        let mut n = TrackingNoise::default();
        assert!(n.validate("s.json").is_ok());
        n.correlation = 1.0;
        let e = n.validate("s.json").unwrap_err().to_string();
        assert!(
            e.contains("s.json") && e.contains("tracking.correlation"),
            "{e}"
        );
        n = TrackingNoise {
            eyes_deg: f32::NAN,
            ..TrackingNoise::default()
        };
        let e = n.validate("s.json").unwrap_err().to_string();
        assert!(e.contains("tracking.eyes_deg"), "{e}");
    }
}
