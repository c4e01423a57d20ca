//! Hidden muscle tension: what the expression coefficients do not say about the wrinkles.
//!
//! The same FLAME parameters come with or without muscle activation: brows raised with a
//! furrowed forehead or a smooth one, a frown with or without glabellar lines, lines that
//! stay at a near-neutral expression. Each frame therefore carries a hidden [`Tension`]:
//! per wrinkle kind a gain on the expression's drive and a resting activation, so that
//! `activation = clamp(gain * drive + rest, 0, 1)`
//! ([`crate::synth::appearance::Appearance::activations_with`]).
//!
//! Per sequence ([`sequence_tension`]), with `s` the config's `tension` (0 switches it
//! off: gain 1, no rest), each muscle group's gain (upper face: forehead and glabella;
//! eyes: crow's feet; lower face: nasolabial folds and chin) is `0.6` (with `s > 0`) times
//!
//! - a per-sequence gain, log-normal with standard deviation `0.45 s`;
//! - a per-sequence gain of the group, log-normal with `0.3 s`;
//! - a variation within the sequence, `exp(0.5 s w(u) + 0.5 s e)` over the sequence's time
//!   `u` in [0, 1]: `w` the sum of two sines of 0.4 to 1.6 cycles with random phases, `e`
//!   a standard normal drawn per frame (the frames are sparse samples of a performance,
//!   between which tension changes);
//! - two episodes per sequence, smooth bumps over about a third of it each, one in each
//!   half (in random order): in one, a random muscle group holds lines at rest (resting
//!   activation up to `0.35..0.7 s`, also at a near-neutral expression); in the other the
//!   face relaxes (every gain drops by up to `90% * min(s, 1)`: no lines at a strong
//!   expression).
//!
//! The factor 0.6 keeps most activations below the clamp at 1. Within a sequence the
//! expression units belong to one family and each peaks in its own part of the sweep, so a
//! per-sequence gain, or one that varies only slowly, could be learnt from which units are
//! active; the per-frame variation and the episodes are what the coefficients cannot tell.

use std::f32::consts::PI;

use crate::synth::appearance::WRINKLES;
use crate::synth::sequences::bump;
use crate::util::rng::Pcg;

/// Muscle group of each wrinkle kind (upper face 0, eyes 1, lower face 2), in
/// [`crate::synth::appearance::WRINKLE_NAMES`] order.
pub const GROUP: [usize; WRINKLES] = [0, 0, 1, 1, 2, 2, 2];
/// Number of muscle groups.
pub const GROUPS: usize = 3;
/// The median gain with tension on (keeps most activations below the clamp at 1).
pub const BASE_GAIN: f32 = 0.6;

/// A frame's hidden tension: per wrinkle kind, a gain on the drive and a resting
/// activation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tension {
    pub gain: [f32; WRINKLES],
    pub rest: [f32; WRINKLES],
}

impl Tension {
    /// No hidden tension: activations follow the expression (gain 1, nothing at rest).
    pub const RELAXED: Tension = Tension {
        gain: [1.0; WRINKLES],
        rest: [0.0; WRINKLES],
    };
}

/// The hidden tension of the `n` frames of sequence number `index` (see the module docs);
/// `strength` is the config's `tension`, `seed` its seed.
pub fn sequence_tension(n: usize, index: usize, strength: f32, seed: u64) -> Vec<Tension> {
    if strength <= 0.0 {
        return vec![Tension::RELAXED; n];
    }
    let mut rng = Pcg::new(seed ^ 0x7e_5107 ^ (index as u64).wrapping_mul(0x2545_f491));
    let s = strength;
    let seq_gain = (0.45 * s * rng.normal()).exp().clamp(0.3, 3.0);
    let group_gain: [f32; GROUPS] =
        std::array::from_fn(|_| (0.3 * s * rng.normal()).exp().clamp(0.4, 2.5));
    // Two sines per group: (cycles, phase).
    let waves: [[(f32, f32); 2]; GROUPS] = std::array::from_fn(|_| {
        std::array::from_fn(|_| (0.4 + 1.2 * rng.uniform(), 2.0 * PI * rng.uniform()))
    });
    // The episodes: one in each half, in random order.
    let (a, b) = (0.15 + 0.3 * rng.uniform(), 0.55 + 0.3 * rng.uniform());
    let (rest_at, relax_at) = if rng.uniform() < 0.5 { (a, b) } else { (b, a) };
    let group = (rng.uniform() * GROUPS as f32) as usize % GROUPS;
    let level = s * (0.35 + 0.35 * rng.uniform());
    (0..n)
        .map(|f| {
            let u = if n > 1 {
                f as f32 / (n - 1) as f32
            } else {
                0.0
            };
            let slow: [f32; GROUPS] = std::array::from_fn(|g| {
                let w = waves[g]
                    .iter()
                    .map(|&(c, p)| (2.0 * PI * c * u + p).sin())
                    .sum::<f32>();
                (0.5 * s * w + 0.5 * s * rng.normal()).exp()
            });
            let relax = 1.0 - 0.9 * s.min(1.0) * bump(u, relax_at, 0.17);
            let rest = level * bump(u, rest_at, 0.17);
            Tension {
                gain: std::array::from_fn(|k| {
                    BASE_GAIN * seq_gain * group_gain[GROUP[k]] * slow[GROUP[k]] * relax
                }),
                rest: std::array::from_fn(|k| if GROUP[k] == group { rest } else { 0.0 }),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tension_varies_between_and_within_sequences_and_zero_switches_it_off() {
        assert!(
            sequence_tension(5, 0, 0.0, 7)
                .iter()
                .all(|t| *t == Tension::RELAXED)
        );
        let a = sequence_tension(40, 0, 1.0, 7);
        let b = sequence_tension(40, 1, 1.0, 7);
        assert_eq!(a, sequence_tension(40, 0, 1.0, 7), "deterministic");
        assert_eq!(a.len(), 40);
        // Within a sequence the gain changes, and differently per muscle group.
        let g: Vec<f32> = a.iter().map(|t| t.gain[0]).collect();
        let (lo, hi) = g
            .iter()
            .fold((f32::MAX, f32::MIN), |(l, h), &x| (l.min(x), h.max(x)));
        assert!(hi > 2.0 * lo, "{lo} .. {hi}");
        assert!(a.iter().any(|t| (t.gain[0] - t.gain[6]).abs() > 0.1));
        // Forehead and glabella share a group.
        assert!(a.iter().all(|t| t.gain[0] == t.gain[1]));
        // Every sequence holds lines at rest somewhere (one group only), and relaxes
        // somewhere else.
        for s in [&a, &b] {
            assert!(s.iter().any(|t| t.rest.iter().any(|&r| r > 0.2)));
            assert!(
                s.iter()
                    .all(|t| t.rest.iter().filter(|&&r| r > 0.0).count() <= 3)
            );
            let bg: Vec<f32> = s.iter().map(|t| t.gain[0]).collect();
            let bmax = bg.iter().copied().fold(0.0, f32::max);
            let bmin = bg.iter().copied().fold(f32::MAX, f32::min);
            assert!(bmin < 0.3 * bmax, "{bmin} vs {bmax}");
        }
        assert_ne!(a, b);
        assert!(a.iter().chain(&b).all(|t| {
            t.gain
                .iter()
                .chain(&t.rest)
                .all(|x| x.is_finite() && *x >= 0.0)
        }));
    }
}
