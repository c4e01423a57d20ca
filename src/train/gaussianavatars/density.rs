//! GaussianAvatars' adaptive density control with binding inheritance, on the host.
//!
//! Follows `scene/gaussian_model.py` of GaussianAvatars (`ShenhanQian/GaussianAvatars`)
//! step by step, on the stored (triangle-local) Gaussians:
//!
//! - statistics between densifications (`add_densification_stats`, `train.py`): per visible
//!   Gaussian, the norm of the screen-space mean gradient (the rasterizer's tap,
//!   [`crate::splat::render_tapped`], NDC units as 3DGS's) is summed and counted, and the
//!   largest screen radius kept ([`Stats`]);
//! - `densify_and_prune`: the mean gradient `accum / denom` (0 where never visible) against
//!   `densify_grad_threshold`; **clone** (`densify_and_clone`) the selected Gaussians whose
//!   largest world scale is at most `percent_dense x extent`; then **split**
//!   (`densify_and_split`, N = 2) the selected ones above it: each child at `R(q_l) n + mu_l`
//!   with `n ~ N(0, diag(world scale))` (GaussianAvatars adds the world-space sample to the
//!   triangle-local position as it stands; kept as is), local scale `exp(s_l) / 1.6`, the
//!   rest copied, and the parents removed; then **prune** Gaussians with opacity below
//!   0.005 and, after the first opacity reset, those whose largest world scale exceeds 0.1 x
//!   extent or whose screen radius exceeds 20 px. The statistics are reset by the clone
//!   (`densification_postfix`) before that test, so, as in GaussianAvatars and 3DGS, the
//!   screen-radius test never removes anything; it is kept for fidelity;
//! - **binding inheritance**: every clone and child is bound to its parent's triangle; a
//!   prune never empties a triangle (`prune_points`: of the Gaussians to prune, those of a
//!   triangle that would be left with none are all kept);
//! - the optimiser's moments follow the rows: kept rows keep theirs, new rows start at zero
//!   (`cat_tensors_to_optimizer`, `_prune_optimizer`), described by
//!   [`Densified::old_from_new`];
//! - `reset_opacity`: every opacity capped at 0.01, its moments zeroed ([`reset_opacity`]).
//!
//! The world scale is `exp(s_l) k` with `k` the triangle's scale on the frame trained last
//! (`get_scaling` after `select_mesh_by_timestep`), passed as `face_scale`.

use glam::{Mat3, Quat, Vec3};

use crate::models::gaussianavatars::binding::unit;
use crate::splat::ply::PlyGaussians;
use crate::util::rng::Pcg;

/// Split children per parent (`densify_and_split(..., N=2)`).
pub const SPLIT_CHILDREN: usize = 2;
/// Children's scale divisor: `0.8 N` (`densify_and_split`).
pub const SPLIT_SCALE_DIVISOR: f32 = 0.8 * SPLIT_CHILDREN as f32;
/// World-space prune threshold as a fraction of the extent (`big_points_ws`).
pub const PRUNE_WORLD_FRACTION: f32 = 0.1;
/// The opacity `reset_opacity` caps at.
pub const RESET_OPACITY: f32 = 0.01;

/// Per-Gaussian statistics accumulated between densifications.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Stats {
    /// `[N]` sum of the screen-space gradient norms over the views that saw it.
    pub grad_accum: Vec<f32>,
    /// `[N]` views that saw it.
    pub denom: Vec<f32>,
    /// `[N]` largest screen radius (pixels) seen.
    pub max_radii: Vec<f32>,
}

impl Stats {
    /// Zeros for `n` Gaussians.
    pub fn zeros(n: usize) -> Self {
        Self {
            grad_accum: vec![0.0; n],
            denom: vec![0.0; n],
            max_radii: vec![0.0; n],
        }
    }

    /// Adds one view: `grad` `[N, 2]` the tap's gradient, `radii` `[N]` (0: not visible).
    pub fn add_view(&mut self, grad: &[f32], radii: &[f32]) {
        for (i, &r) in radii.iter().enumerate() {
            if r > 0.0 {
                let (gx, gy) = (grad[2 * i], grad[2 * i + 1]);
                self.grad_accum[i] += (gx * gx + gy * gy).sqrt();
                self.denom[i] += 1.0;
                self.max_radii[i] = self.max_radii[i].max(r);
            }
        }
    }
}

/// The settings of one `densify_and_prune` call.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensifySettings {
    /// `densify_grad_threshold`.
    pub grad_threshold: f32,
    /// Prune below this opacity (0.005 in `train.py`).
    pub min_opacity: f32,
    /// The cameras' extent (`scene.cameras_extent`, [`cameras_extent`]).
    pub extent: f32,
    /// `percent_dense`.
    pub percent_dense: f32,
    /// `size_threshold`: `Some(20)` after the first opacity reset, else `None` (no size
    /// pruning at all, world or screen).
    pub max_screen_size: Option<f32>,
}

/// The result of [`densify_and_prune`].
#[derive(Clone, Debug, PartialEq)]
pub struct Densified {
    /// The new stored Gaussians.
    pub stored: PlyGaussians,
    /// `[N']` each new Gaussian's triangle.
    pub binding: Vec<u32>,
    /// `[N']` the old row whose optimiser moments each new row keeps; `None`: a new
    /// Gaussian, zero moments.
    pub old_from_new: Vec<Option<usize>>,
    /// Gaussians cloned, split (parents) and pruned (after the split's own removals).
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
}

/// The cameras' extent as 3DGS computes it (`scene/dataset_readers.py`, `getNerfppNorm`):
/// 1.1 x the largest distance of a camera centre from their mean.
pub fn cameras_extent(centers: &[[f32; 3]]) -> f32 {
    if centers.is_empty() {
        return 0.0;
    }
    let n = centers.len() as f32;
    let mean = centers.iter().fold(Vec3::ZERO, |a, c| a + Vec3::from(*c)) / n;
    let diagonal = centers
        .iter()
        .map(|c| (Vec3::from(*c) - mean).length())
        .fold(0.0f32, f32::max);
    1.1 * diagonal
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn inverse_sigmoid(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// Rows of stored Gaussians, appended and filtered together.
struct Rows<'a> {
    src: &'a PlyGaussians,
    out: PlyGaussians,
    binding: Vec<u32>,
    origin: Vec<Option<usize>>,
}

impl<'a> Rows<'a> {
    fn new(src: &'a PlyGaussians, binding: &[u32]) -> Self {
        Self {
            src,
            out: src.clone(),
            binding: binding.to_vec(),
            origin: (0..src.len()).map(Some).collect(),
        }
    }

    fn len(&self) -> usize {
        self.binding.len()
    }

    /// Appends a copy of current row `i`, with a new origin (zero moments).
    fn push_copy(&mut self, i: usize) -> usize {
        let k = self.src.sh_coeffs() * 3;
        let o = &mut self.out;
        o.means.extend_from_within(3 * i..3 * i + 3);
        o.sh.extend_from_within(k * i..k * (i + 1));
        o.opacity_logits.push(o.opacity_logits[i]);
        o.log_scales.extend_from_within(3 * i..3 * i + 3);
        o.quats.extend_from_within(4 * i..4 * i + 4);
        self.binding.push(self.binding[i]);
        self.origin.push(None);
        self.len() - 1
    }

    /// Keeps the rows where `keep` is true.
    fn retain(&mut self, keep: &[bool]) {
        let k = self.src.sh_coeffs() * 3;
        fn filter<T: Copy>(v: &[T], width: usize, keep: &[bool]) -> Vec<T> {
            v.chunks(width)
                .zip(keep)
                .filter(|(_, k)| **k)
                .flat_map(|(c, _)| c.iter().copied())
                .collect()
        }
        let o = &mut self.out;
        o.means = filter(&o.means, 3, keep);
        o.sh = filter(&o.sh, k, keep);
        o.opacity_logits = filter(&o.opacity_logits, 1, keep);
        o.log_scales = filter(&o.log_scales, 3, keep);
        o.quats = filter(&o.quats, 4, keep);
        self.binding = filter(&self.binding, 1, keep);
        self.origin = filter(&self.origin, 1, keep);
    }

    /// Largest world scale of row `i`: `max exp(s_l) k`.
    fn world_max_scale(&self, i: usize, face_scale: &[f32]) -> f32 {
        let k = face_scale[self.binding[i] as usize];
        self.out.log_scales[3 * i..3 * i + 3]
            .iter()
            .map(|s| s.exp() * k)
            .fold(f32::NEG_INFINITY, f32::max)
    }

    /// `prune_points` with GaussianAvatars' guard: of the rows in `mask`, those of a
    /// triangle that would be left with none are kept. Returns the rows removed.
    fn prune(&mut self, mask: &[bool], num_faces: usize) -> usize {
        let mut counter = vec![0usize; num_faces];
        let mut to_prune = vec![0usize; num_faces];
        for (i, &f) in self.binding.iter().enumerate() {
            counter[f as usize] += 1;
            if mask[i] {
                to_prune[f as usize] += 1;
            }
        }
        let keep: Vec<bool> = mask
            .iter()
            .zip(&self.binding)
            .map(|(&m, &f)| !(m && counter[f as usize] > to_prune[f as usize]))
            .collect();
        let removed = keep.iter().filter(|k| !**k).count();
        self.retain(&keep);
        removed
    }
}

/// GaussianAvatars' `densify_and_prune` (see the module documentation).
///
/// # Shapes
/// - `stored`: N Gaussians; `binding`, `stats.*`: `[N]`; `face_scale`: `[F]`
///
/// # Panics
/// When the lengths disagree or a binding is not below `face_scale.len()`.
pub fn densify_and_prune(
    stored: &PlyGaussians,
    binding: &[u32],
    face_scale: &[f32],
    stats: &Stats,
    settings: &DensifySettings,
    rng: &mut Pcg,
) -> Densified {
    let n = stored.len();
    assert_eq!(binding.len(), n, "one binding per Gaussian");
    assert_eq!(stats.denom.len(), n, "statistics per Gaussian");
    let num_faces = face_scale.len();
    assert!(
        binding.iter().all(|&f| (f as usize) < num_faces),
        "bindings below the face count"
    );
    // grads = accum / denom, NaN (never seen) -> 0.
    let grads: Vec<f32> = (0..n)
        .map(|i| {
            let g = stats.grad_accum[i] / stats.denom[i];
            if g.is_nan() { 0.0 } else { g }
        })
        .collect();
    let dense = settings.percent_dense * settings.extent;
    let mut rows = Rows::new(stored, binding);

    // Clone: small Gaussians with a large mean gradient.
    let mut cloned = 0;
    for (i, &g) in grads.iter().enumerate() {
        if g >= settings.grad_threshold && rows.world_max_scale(i, face_scale) <= dense {
            rows.push_copy(i);
            cloned += 1;
        }
    }

    // Split: large ones (clones have no gradient: `padded_grad`).
    let selected: Vec<usize> = (0..n)
        .filter(|&i| {
            grads[i] >= settings.grad_threshold && rows.world_max_scale(i, face_scale) > dense
        })
        .collect();
    // `repeat(N, 1)`: all selected once, then all again.
    for _ in 0..SPLIT_CHILDREN {
        for &i in &selected {
            let k = face_scale[rows.binding[i] as usize];
            let s = &stored.log_scales[3 * i..3 * i + 3];
            let std = Vec3::new(s[0].exp() * k, s[1].exp() * k, s[2].exp() * k);
            let sample = Vec3::new(rng.normal(), rng.normal(), rng.normal()) * std;
            let q = &stored.quats[4 * i..4 * i + 4];
            let rot = Mat3::from_quat(unit(Quat::from_xyzw(q[1], q[2], q[3], q[0])));
            let mu = Vec3::from_slice(&stored.means[3 * i..3 * i + 3]);
            let child = rows.push_copy(i);
            let p = rot * sample + mu;
            rows.out.means[3 * child..3 * child + 3].copy_from_slice(&p.to_array());
            // scaling_inverse_activation((world / face) / (0.8 N)).
            for (c, s) in s.iter().enumerate() {
                let world = s.exp() * k;
                rows.out.log_scales[3 * child + c] = (world / k / SPLIT_SCALE_DIVISOR).ln();
            }
        }
    }
    let mut parents = vec![false; rows.len()];
    for &i in &selected {
        parents[i] = true;
    }
    rows.prune(&parents, num_faces);

    // Prune: transparent, and (after the first reset) too large. The statistics were reset
    // by the clone's `densification_postfix`: the screen radii are all 0 here.
    let m = rows.len();
    let mut mask: Vec<bool> = rows
        .out
        .opacity_logits
        .iter()
        .map(|&o| sigmoid(o) < settings.min_opacity)
        .collect();
    if let Some(max_screen) = settings.max_screen_size {
        let screen_radii = vec![0.0f32; m];
        for (i, flag) in mask.iter_mut().enumerate() {
            let big_vs = screen_radii[i] > max_screen;
            let big_ws =
                rows.world_max_scale(i, face_scale) > PRUNE_WORLD_FRACTION * settings.extent;
            *flag = *flag || big_vs || big_ws;
        }
    }
    let pruned = rows.prune(&mask, num_faces);
    Densified {
        stored: rows.out,
        binding: rows.binding,
        old_from_new: rows.origin,
        cloned,
        split: selected.len(),
        pruned,
    }
}

/// `reset_opacity`: every opacity logit replaced by `inverse_sigmoid(min(sigmoid(o), 0.01))`
/// (the optimiser's opacity moments are zeroed by the caller).
pub fn reset_opacity(opacity_logits: &mut [f32]) {
    for o in opacity_logits {
        *o = inverse_sigmoid(sigmoid(*o).min(RESET_OPACITY));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four Gaussians on three triangles (scales 1, 2, 0.5), SH degree 1.
    fn stored() -> (PlyGaussians, Vec<u32>, Vec<f32>) {
        let n = 4;
        let k = 4;
        let sh: Vec<f32> = (0..n * k * 3).map(|i| i as f32 * 0.01).collect();
        let g = PlyGaussians {
            means: vec![
                0.1, 0.2, 0.3, //
                -0.1, 0.0, 0.2, //
                0.0, 0.5, 0.0, //
                0.3, 0.3, 0.3,
            ],
            sh,
            sh_degree: 1,
            opacity_logits: vec![0.0, 1.0, -2.0, 0.5],
            log_scales: vec![
                -5.0, -5.0, -5.0, // small: 0.0067 x 1
                -0.5, -1.0, -1.5, // large: 0.61 x 2
                -5.0, -6.0, -7.0, // small
                -1.0, -1.0, -1.0, // large: 0.37 x 0.5 = 0.18
            ],
            quats: vec![
                1.0, 0.0, 0.0, 0.0, //
                0.0, 0.0, 0.0, 2.0, // 180 degrees about z (unnormalised)
                1.0, 0.0, 0.0, 0.0, //
                0.0, 1.0, 0.0, 0.0,
            ],
        };
        (g, vec![0, 1, 1, 2], vec![1.0, 2.0, 0.5])
    }

    fn settings() -> DensifySettings {
        DensifySettings {
            grad_threshold: 2e-4,
            min_opacity: 0.005,
            extent: 1.0,
            percent_dense: 0.01,
            max_screen_size: None,
        }
    }

    fn row(g: &PlyGaussians, i: usize) -> (Vec<f32>, Vec<f32>, f32, Vec<f32>, Vec<f32>) {
        let k = g.sh_coeffs() * 3;
        (
            g.means[3 * i..3 * i + 3].to_vec(),
            g.sh[k * i..k * (i + 1)].to_vec(),
            g.opacity_logits[i],
            g.log_scales[3 * i..3 * i + 3].to_vec(),
            g.quats[4 * i..4 * i + 4].to_vec(),
        )
    }

    #[test]
    fn stats_follow_add_densification_stats() {
        let mut s = Stats::zeros(3);
        s.add_view(&[3.0, 4.0, 1.0, 0.0, 9.0, 9.0], &[2.0, 5.0, 0.0]);
        s.add_view(&[0.0, 1.0, 0.0, 0.0, 9.0, 9.0], &[7.0, 0.0, 0.0]);
        assert_eq!(s.grad_accum, vec![6.0, 1.0, 0.0]);
        assert_eq!(s.denom, vec![2.0, 1.0, 0.0]);
        assert_eq!(s.max_radii, vec![7.0, 5.0, 0.0]);
    }

    /// Clone selects small Gaussians, split large ones; children inherit their parent's
    /// triangle and every other attribute but position and scale; new rows have no
    /// optimiser moments; the parents of splits are gone.
    #[test]
    fn clone_and_split_inherit_the_binding_exactly() {
        let (g, binding, face_scale) = stored();
        let stats = Stats {
            grad_accum: vec![1e-3, 1e-3, 1e-5, 3e-3],
            denom: vec![1.0, 2.0, 1.0, 3.0],
            max_radii: vec![0.0; 4],
        };
        let mut rng = Pcg::new(3);
        let d = densify_and_prune(&g, &binding, &face_scale, &stats, &settings(), &mut rng);
        // Gaussian 0 cloned (small, 1e-3 >= 2e-4); 1 and 3 split (large); 2 untouched.
        assert_eq!((d.cloned, d.split, d.pruned), (1, 2, 0));
        // Rows: 0, 2 (kept), clone of 0, children of 1, 3, 1, 3.
        assert_eq!(
            d.old_from_new,
            vec![Some(0), Some(2), None, None, None, None, None]
        );
        assert_eq!(d.binding, vec![0, 1, 0, 1, 2, 1, 2]);
        assert_eq!(row(&d.stored, 0), row(&g, 0));
        assert_eq!(row(&d.stored, 1), row(&g, 2));
        assert_eq!(row(&d.stored, 2), row(&g, 0));
        for (child, parent) in [(3, 1), (4, 3), (5, 1), (6, 3)] {
            let (_, sh, op, ls, q) = row(&d.stored, child);
            let (mu_p, sh_p, op_p, ls_p, q_p) = row(&g, parent);
            assert_eq!((sh, op, q), (sh_p, op_p, q_p), "child {child}");
            for c in 0..3 {
                let want = ls_p[c] - 1.6f32.ln();
                assert!((ls[c] - want).abs() < 1e-5, "child {child} scale {c}");
            }
            // Within a few standard deviations (world scale) of the parent's local position.
            let mu = &d.stored.means[3 * child..3 * child + 3];
            let k = face_scale[binding[parent] as usize];
            let max_std = ls_p.iter().map(|s| s.exp() * k).fold(0.0, f32::max);
            let dist: f32 = mu
                .iter()
                .zip(&mu_p)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f32>()
                .sqrt();
            assert!(dist < 6.0 * max_std, "child {child} at {dist}");
            assert!(dist > 0.0);
        }
    }

    /// The split sample is rotated by the stored rotation: for a scale with one non-zero
    /// axis, the child lies on the rotated axis through the parent.
    #[test]
    fn split_samples_along_the_rotated_axes() {
        let g = PlyGaussians {
            means: vec![1.0, 2.0, 3.0],
            sh: vec![0.0; 3],
            sh_degree: 0,
            opacity_logits: vec![0.0],
            // x axis 1 (k = 1), the others negligible.
            log_scales: vec![0.0, -30.0, -30.0],
            // 90 degrees about z: the x axis goes to y.
            quats: vec![
                std::f32::consts::FRAC_1_SQRT_2,
                0.0,
                0.0,
                std::f32::consts::FRAC_1_SQRT_2,
            ],
        };
        let stats = Stats {
            grad_accum: vec![1.0],
            denom: vec![1.0],
            max_radii: vec![0.0],
        };
        let d = densify_and_prune(&g, &[0], &[1.0], &stats, &settings(), &mut Pcg::new(9));
        assert_eq!((d.cloned, d.split), (0, 1));
        assert_eq!(d.stored.len(), 2);
        for c in 0..2 {
            let mu = &d.stored.means[3 * c..3 * c + 3];
            assert!((mu[0] - 1.0).abs() < 1e-5, "{mu:?}");
            assert!((mu[2] - 3.0).abs() < 1e-5, "{mu:?}");
        }
    }

    /// Pruning: transparent Gaussians go unless they are their triangle's last; large ones
    /// only with a size threshold.
    #[test]
    fn prune_never_empties_a_triangle() {
        let (mut g, binding, face_scale) = stored();
        // 0 (alone on triangle 0) and 2 (shares triangle 1 with 1) transparent.
        g.opacity_logits = vec![-9.0, 1.0, -9.0, 0.5];
        let stats = Stats::zeros(4);
        let d = densify_and_prune(
            &g,
            &binding,
            &face_scale,
            &stats,
            &settings(),
            &mut Pcg::new(1),
        );
        assert_eq!(d.old_from_new, vec![Some(0), Some(1), Some(3)]);
        assert_eq!(d.binding, vec![0, 1, 2]);
        assert_eq!(d.pruned, 1);
        // Both of triangle 1 transparent: both kept.
        g.opacity_logits = vec![1.0, -9.0, -9.0, 0.5];
        let d = densify_and_prune(
            &g,
            &binding,
            &face_scale,
            &stats,
            &settings(),
            &mut Pcg::new(1),
        );
        assert_eq!(d.pruned, 0);
        // With the size threshold: Gaussian 1's world scale 0.61 x 2 > 0.1 x extent; it
        // shares triangle 1 with 2, which stays.
        g.opacity_logits = vec![1.0, 1.0, 1.0, 0.5];
        let s = DensifySettings {
            max_screen_size: Some(20.0),
            ..settings()
        };
        let d = densify_and_prune(&g, &binding, &face_scale, &stats, &s, &mut Pcg::new(1));
        // 3 (0.18 > 0.1) is its triangle's last: kept.
        assert_eq!(d.old_from_new, vec![Some(0), Some(2), Some(3)]);
    }

    #[test]
    fn reset_caps_opacity_at_one_percent() {
        let mut o = vec![3.0, -6.0, inverse_sigmoid(0.01)];
        reset_opacity(&mut o);
        assert!((sigmoid(o[0]) - 0.01).abs() < 1e-6);
        assert!((o[1] + 6.0).abs() < 1e-6);
        assert!((sigmoid(o[2]) - 0.01).abs() < 1e-6);
    }

    /// `getNerfppNorm`: centres at +-1 on x: mean 0, diagonal 1, radius 1.1.
    #[test]
    fn extent_is_nerfpp_radius() {
        let e = cameras_extent(&[[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.5, 0.0]]);
        // mean (0, 1/6, 0); farthest |(1, -1/6, 0)| = 1.01379.
        assert!((e - 1.1 * (1.0f32 + 1.0 / 36.0).sqrt()).abs() < 1e-5);
    }
}
