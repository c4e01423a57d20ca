//! Subjects of the synthetic benchmark: who is captured.
//!
//! A subject is a head shape (coefficients of the head model's shape basis) and an
//! appearance: skin tone, hair, brow, lip and iris colour, hairline height, brow
//! thickness, and the depth and placement of its wrinkles. Subject 0 is the head as the
//! benchmark always rendered it (the model's mean shape, the original colours and
//! wrinkles); subject `K > 0` is drawn from a generator seeded by `K` and the config's
//! seed. Each subject is one export folder (`texavatars synth --subject K`), as NeRSemble
//! ships one folder per subject.

use crate::head::{HeadModel, HeadPose};
use crate::synth::appearance::WRINKLES;
use crate::util::rng::Pcg;

/// Shape components a subject varies (the leading ones of the basis; FLAME orders them by
/// variance, the embedded head has 14).
pub const SHAPE_COMPONENTS: usize = 16;
/// Standard deviation of a subject's shape coefficients (clamped to +-1): mild identities
/// for a FLAME basis of unit-variance components, and within the embedded head's target
/// range of -1..1.
pub const SHAPE_STD: f32 = 0.35;
/// Base hair colours (RGB albedo) a subject draws from before jitter: black, dark brown,
/// brown, blond, red, grey.
const HAIR_COLOURS: [[f32; 3]; 6] = [
    [0.05, 0.04, 0.04],
    [0.16, 0.10, 0.07],
    [0.34, 0.22, 0.13],
    [0.68, 0.54, 0.33],
    [0.52, 0.24, 0.11],
    [0.58, 0.57, 0.55],
];
/// Base iris colours (RGB albedo): brown, dark brown, green, blue, grey.
const IRIS_COLOURS: [[f32; 3]; 5] = [
    [0.33, 0.21, 0.11],
    [0.17, 0.10, 0.06],
    [0.30, 0.40, 0.24],
    [0.26, 0.40, 0.58],
    [0.45, 0.47, 0.48],
];

/// One subject: shape and appearance.
#[derive(Clone, Debug, PartialEq)]
pub struct Subject {
    /// Its index (`--subject K`).
    pub index: usize,
    /// Shape coefficients, the model's `num_shape` of them.
    pub shape: Vec<f32>,
    /// Base skin albedo (RGB).
    pub skin: [f32; 3],
    /// Hair colour (RGB).
    pub hair: [f32; 3],
    /// Brow colour (RGB).
    pub brow: [f32; 3],
    /// Lip colour (RGB).
    pub lips: [f32; 3],
    /// Iris colour (RGB).
    pub iris: [f32; 3],
    /// Height of the hairline above the eyes, head units (eye distances).
    pub hairline: f32,
    /// Brow thickness, relative to subject 0's.
    pub brow_thickness: f32,
    /// Depth of each wrinkle kind, relative to subject 0's (multiplies the baked maps).
    pub wrinkle_depth: [f32; WRINKLES],
    /// Spacing of the line patterns (forehead, glabella, crow's feet), relative to subject
    /// 0's.
    pub wrinkle_period: f32,
    /// Offset of the line patterns, as a fraction of their period.
    pub wrinkle_phase: f32,
    /// Vertical shift of the forehead band and the nasolabial folds, head units.
    pub wrinkle_shift: f32,
}

fn lerp3(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * t)
}

fn jitter(c: [f32; 3], amount: f32, rng: &mut Pcg) -> [f32; 3] {
    let s = 1.0 + amount * (2.0 * rng.uniform() - 1.0);
    c.map(|x| (x * s * (1.0 + 0.5 * amount * (2.0 * rng.uniform() - 1.0))).clamp(0.0, 1.0))
}

fn pick<const N: usize>(palette: &[[f32; 3]; N], rng: &mut Pcg) -> [f32; 3] {
    palette[(rng.uniform() * N as f32) as usize % N]
}

impl Subject {
    /// Subject 0: the mean shape and the original appearance.
    pub fn original(num_shape: usize) -> Self {
        Subject {
            index: 0,
            shape: vec![0.0; num_shape],
            skin: [0.80, 0.60, 0.50],
            hair: [0.22, 0.15, 0.10],
            brow: [0.25, 0.17, 0.12],
            lips: [0.70, 0.33, 0.33],
            iris: [0.28, 0.42, 0.52],
            hairline: 1.25,
            brow_thickness: 1.0,
            wrinkle_depth: [1.0; WRINKLES],
            wrinkle_period: 1.0,
            wrinkle_phase: 0.0,
            wrinkle_shift: 0.0,
        }
    }

    /// Subject `index` of a benchmark with `seed`, for a model with `num_shape` shape
    /// components. Subject 0 is [`Subject::original`].
    pub fn new(index: usize, num_shape: usize, seed: u64) -> Self {
        if index == 0 {
            return Self::original(num_shape);
        }
        let mut rng = Pcg::new(seed ^ 0x5b_1ec7_u64 ^ (index as u64).wrapping_mul(0x9e37_79b9));
        let mut shape = vec![0.0f32; num_shape];
        for s in shape.iter_mut().take(SHAPE_COMPONENTS) {
            *s = (SHAPE_STD * rng.normal()).clamp(-1.0, 1.0);
        }
        // Skin from light to dark along a natural tone line.
        let tone = rng.uniform();
        let skin = jitter(
            lerp3([0.86, 0.68, 0.58], [0.40, 0.26, 0.19], tone),
            0.04,
            &mut rng,
        );
        let hair = jitter(pick(&HAIR_COLOURS, &mut rng), 0.08, &mut rng);
        let brow = lerp3(hair, [0.12, 0.09, 0.07], 0.3 + 0.3 * rng.uniform());
        let lips = jitter(
            [skin[0] * 0.88, skin[1] * 0.55, skin[2] * 0.66],
            0.06,
            &mut rng,
        );
        let iris = jitter(pick(&IRIS_COLOURS, &mut rng), 0.08, &mut rng);
        Subject {
            index,
            shape,
            skin,
            hair,
            brow,
            lips,
            iris,
            hairline: 1.25 + 0.24 * (rng.uniform() - 0.5),
            brow_thickness: 0.75 + 0.55 * rng.uniform(),
            wrinkle_depth: std::array::from_fn(|_| 0.5 + rng.uniform()),
            wrinkle_period: 0.85 + 0.35 * rng.uniform(),
            wrinkle_phase: rng.uniform(),
            wrinkle_shift: 0.1 * (rng.uniform() - 0.5),
        }
    }

    /// The subject's rest pose: its shape, no expression, no rotation.
    pub fn neutral(&self, model: &HeadModel) -> HeadPose {
        HeadPose {
            shape: self.shape.clone(),
            ..HeadPose::neutral(model)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subject_zero_is_the_original_head_and_others_differ() {
        let s0 = Subject::new(0, 14, 7);
        assert_eq!(s0, Subject::original(14));
        assert!(s0.shape.iter().all(|&x| x == 0.0));
        let s1 = Subject::new(1, 14, 7);
        let s2 = Subject::new(2, 14, 7);
        assert_eq!(s1, Subject::new(1, 14, 7), "deterministic");
        assert_ne!(s1.shape, s2.shape);
        assert_ne!(s1.skin, s2.skin);
        for s in [&s1, &s2] {
            assert_eq!(s.shape.len(), 14);
            assert!(s.shape.iter().any(|&x| x != 0.0));
            assert!(s.shape.iter().all(|x| x.abs() <= 1.0));
            for c in [s.skin, s.hair, s.brow, s.lips, s.iris] {
                assert!(c.iter().all(|x| (0.0..=1.0).contains(x)), "{c:?}");
            }
            assert!(s.wrinkle_depth.iter().all(|d| (0.5..=1.5).contains(d)));
        }
        // More shape components than varied: the rest stay zero.
        let flame = Subject::new(3, 300, 7);
        assert!(flame.shape[SHAPE_COMPONENTS..].iter().all(|&x| x == 0.0));
    }
}
