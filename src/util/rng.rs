//! The project's random numbers: a small seeded generator, so that the synthetic benchmark,
//! the demo scene and the training frame order are functions of their seeds alone.

/// A small deterministic generator (PCG-XSH-RR 32).
#[derive(Clone, Debug)]
pub struct Pcg(u64);

impl Pcg {
    /// Seeds the generator.
    pub fn new(seed: u64) -> Self {
        let mut p = Pcg(seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407));
        p.next_u32();
        p
    }

    /// Next 32 random bits.
    pub fn next_u32(&mut self) -> u32 {
        let old = self.0;
        self.0 = old
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 / (1u32 << 24) as f32
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f32 {
        let u1 = self.uniform().max(1e-7);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}
