//! The per-tile compositing loops, written lane-wise so that LLVM vectorizes them.
//!
//! Thread mapping: one call handles one 16x16 tile (one rayon task). Inside, a tile is held
//! as 32 spans of 8 pixels (two per row). For every Gaussian of the tile, every span its pixel
//! box touches and that still has a live pixel is processed as one 8-lane step with no
//! branches (masks and selects instead), so the loop over lanes becomes one AVX2 vector (two
//! SSE ones). Lanes outside the Gaussian's box, pixels that have terminated and pixels the
//! Gaussian does not reach are masked out; spans whose pixels have all terminated (forward)
//! or that the Gaussian never reached (backward) are skipped whole.
//!
//! `exp` is the one transcendental; [`exp_neg`] is a branch-free polynomial version that
//! vectorizes (libm's `expf` does not).
//!
//! On x86-64 the tile functions are compiled twice: a baseline (SSE2) version and an AVX2
//! version chosen at run time when the CPU has it.

use crate::splat::constants::{ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN};

use super::project::{Projection, Splat2d, Splat2dGrad};

/// Pixels per span: one AVX2 vector of f32.
pub const LANES: usize = 8;
/// Spans per tile row.
const SPANS_PER_ROW: usize = TILE_SIZE as usize / LANES;
/// Spans per tile (row-major: span `2 y + h` holds pixels `8 h .. 8 h + 8` of row `y`).
pub const SPANS: usize = TILE_SIZE as usize * SPANS_PER_ROW;

/// Slack on the cheap `sigma > sigma_cut` rejection: `exp(-0.01) < 1`, so a pixel rejected
/// this way has alpha below the threshold whatever the rounding of `exp`.
pub const SIGMA_CUT_SLACK: f32 = 0.01;

/// Largest `sigma` handed to the polynomial: `exp(-87)` is still a normal f32, so the
/// exponent assembled from bits never underflows.
const EXP_SIGMA_MAX: f32 = 87.0;

/// `exp(-s)` for `s >= 0` (negative or NaN `s` count as 0; `s > 87` as 87), with a relative
/// error below 2e-7: Cody–Waite range reduction `-s = n ln2 + r`, `|r| <= ln2 / 2`, then a
/// degree-6 polynomial for `e^r` (Cephes' `expf` coefficients) scaled by `2^n` built from
/// bits. Branch-free, so it vectorizes.
#[inline(always)]
pub fn exp_neg(s: f32) -> f32 {
    // 1.5 * 2^23: adding it rounds to the nearest integer, kept in the low mantissa bits.
    const SHIFTER: f32 = 12_582_912.0;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Not `clamp`: `max` maps NaN to 0 here, `clamp` would keep it.
    #[allow(clippy::manual_clamp)]
    let x = -s.max(0.0).min(EXP_SIGMA_MAX);
    let t = x * std::f32::consts::LOG2_E + SHIFTER;
    let n = t - SHIFTER;
    let r = x - n * LN2_HI - n * LN2_LO;
    let r2 = r * r;
    let p = ((((1.987_569_2e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let e = p * r2 + r + 1.0;
    // The integer n sits in the low mantissa bits of t; n is in [-126, 0].
    let n_int = t.to_bits() as i32 - SHIFTER.to_bits() as i32;
    e * f32::from_bits(((n_int + 127) as u32) << 23)
}

/// A Gaussian's constants for one row of pixels.
#[derive(Clone, Copy)]
struct RowSplat {
    u: f32,
    half_a: f32,
    /// `b * dy`.
    b_dy: f32,
    /// `c * dy^2 / 2`.
    c_dy2: f32,
    opacity: f32,
    cut: f32,
}

impl RowSplat {
    #[inline(always)]
    fn new(s: &Splat2d, dy: f32) -> Self {
        RowSplat {
            u: s.u,
            half_a: 0.5 * s.a,
            b_dy: s.b * dy,
            c_dy2: 0.5 * s.c * dy * dy,
            opacity: s.opacity,
            cut: s.sigma_cut + SIGMA_CUT_SLACK,
        }
    }

    /// `(dx, exp(-sigma), raw alpha, alpha, reaches)` at pixel centre `x` (reaches ignores
    /// the pixel box).
    #[inline(always)]
    fn eval(&self, x: f32) -> (f32, f32, f32, f32, bool) {
        let dx = x - self.u;
        let sigma = dx * (self.half_a * dx + self.b_dy) + self.c_dy2;
        let g = exp_neg(sigma);
        let raw = self.opacity * g;
        let alpha = raw.min(ALPHA_MAX);
        let reaches = (sigma >= 0.0) & (sigma <= self.cut) & (alpha >= ALPHA_MIN);
        (dx, g, raw, alpha, reaches)
    }
}

/// The rectangle of a tile (absolute pixel coordinates).
#[derive(Clone, Copy)]
pub struct TileRect {
    pub x0: u32,
    pub y0: u32,
    /// Exclusive.
    pub x1: u32,
    pub y1: u32,
}

impl TileRect {
    /// Pixel centres' x per span column and lane.
    #[inline(always)]
    fn xs(&self) -> [[f32; LANES]; SPANS_PER_ROW] {
        std::array::from_fn(|h| {
            std::array::from_fn(|l| (self.x0 + (h * LANES + l) as u32) as f32 + 0.5)
        })
    }

    /// The Gaussian's pixel box clipped to this tile, tile-relative and inclusive.
    #[inline(always)]
    fn clip(&self, p: &Projection) -> Option<(u32, u32, u32, u32)> {
        let b = &p.pixels;
        let x0 = b.x0.max(self.x0);
        let y0 = b.y0.max(self.y0);
        let x1 = b.x1.min(self.x1 - 1);
        let y1 = b.y1.min(self.y1 - 1);
        // Lazily: the subtraction would underflow for a box outside the tile.
        (x0 <= x1 && y0 <= y1).then(|| (x0 - self.x0, y0 - self.y0, x1 - self.x0, y1 - self.y0))
    }

    fn pixels(&self) -> u32 {
        (self.x1 - self.x0) * (self.y1 - self.y0)
    }

    /// Whether each lane of each span column is a pixel of the image.
    fn inside(&self) -> [[bool; LANES]; SPANS_PER_ROW] {
        let w = self.x1 - self.x0;
        std::array::from_fn(|h| std::array::from_fn(|l| ((h * LANES + l) as u32) < w))
    }
}

/// Box mask (1 inside) per span column for tile-relative inclusive x range `[lx0, lx1]`.
#[inline(always)]
fn box_masks(lx0: u32, lx1: u32) -> [[u32; LANES]; SPANS_PER_ROW] {
    let mut m = [[0u32; LANES]; SPANS_PER_ROW];
    for (h, row) in m.iter_mut().enumerate() {
        for (l, v) in row.iter_mut().enumerate() {
            let x = (h * LANES + l) as u32;
            *v = u32::from((x >= lx0) & (x <= lx1));
        }
    }
    m
}

/// Forward compositing state of one tile, by span (see the module doc).
pub struct TileForward {
    pub trans: [[f32; LANES]; SPANS],
    pub color: [[[f32; LANES]; SPANS]; 3],
    /// Per pixel, one past the last composited intersection (tile-relative).
    pub last: [[u32; LANES]; SPANS],
    /// 1 where the pixel has terminated (or lies outside the image).
    done: [[u32; LANES]; SPANS],
    /// Pixels of the span still compositing.
    live: [u32; SPANS],
}

/// Span and lane of tile-relative pixel `(lx, ly)`.
#[inline(always)]
pub fn span_lane(lx: usize, ly: usize) -> (usize, usize) {
    (ly * SPANS_PER_ROW + lx / LANES, lx % LANES)
}

/// One span of one Gaussian, forward. Returns the number of pixels that terminated.
///
/// Works on local copies of the span's state so that LLVM sees no aliasing and vectorizes.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn span_forward(
    rs: &RowSplat,
    rgb: [f32; 3],
    xs: &[f32; LANES],
    in_box: &[u32; LANES],
    k1: u32,
    st: &mut TileForward,
    sp: usize,
) -> u32 {
    let mut trans = st.trans[sp];
    let mut last = st.last[sp];
    let mut done = st.done[sp];
    let mut cr = st.color[0][sp];
    let mut cg = st.color[1][sp];
    let mut cb = st.color[2][sp];
    let mut term_lanes = [0u32; LANES];
    for l in 0..LANES {
        let (_, _, _, alpha, reaches) = rs.eval(xs[l]);
        let valid = reaches & (in_box[l] != 0) & (done[l] == 0);
        let t = trans[l];
        let next = t * (1.0 - alpha);
        let term = valid & (next < TRANSMITTANCE_MIN);
        let comp = valid & !term;
        let w = alpha * t * (comp as u32 as f32);
        cr[l] += w * rgb[0];
        cg[l] += w * rgb[1];
        cb[l] += w * rgb[2];
        trans[l] = select(comp, next, t);
        let mask = (comp as u32).wrapping_neg();
        last[l] = (k1 & mask) | (last[l] & !mask);
        term_lanes[l] = term as u32;
        done[l] |= term as u32;
    }
    st.trans[sp] = trans;
    st.last[sp] = last;
    st.done[sp] = done;
    st.color[0][sp] = cr;
    st.color[1][sp] = cg;
    st.color[2][sp] = cb;
    term_lanes.iter().sum()
}

/// How many intersections ahead the tile loops prefetch a Gaussian's projection: the
/// projections are read in an order unrelated to memory (tile lists follow depth), and
/// without prefetching the tile loop spends much of its time waiting on these loads.
const PREFETCH_AHEAD: usize = 12;

/// Hints the CPU to bring `*p` into cache (both ends: a value may straddle two lines).
#[inline(always)]
fn prefetch<T>(p: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let first = (p as *const T).cast::<i8>();
        let end = first.wrapping_add(std::mem::size_of::<T>().saturating_sub(1));
        // SAFETY: prefetching never faults and dereferences nothing.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(first);
            _mm_prefetch::<_MM_HINT_T0>(end);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// `if m { a } else { b }` on the bits, which LLVM keeps as a blend instead of turning a
/// conditional update of an array into a (slow) masked store.
#[inline(always)]
fn select(m: bool, a: f32, b: f32) -> f32 {
    let mask = (m as u32).wrapping_neg();
    f32::from_bits((a.to_bits() & mask) | (b.to_bits() & !mask))
}

/// Composites one tile front to back.
///
/// `isects` lists the tile's Gaussians in depth order, indices into `projections` (`None`
/// for culled ones). Lanes outside `rect` stay at T = 1.
#[inline(always)]
pub fn tile_forward_generic(
    rect: TileRect,
    projections: &[Option<Projection>],
    isects: &[u32],
) -> TileForward {
    let inside = rect.inside();
    let mut st = TileForward {
        trans: [[1.0; LANES]; SPANS],
        color: [[[0.0; LANES]; SPANS]; 3],
        last: [[0; LANES]; SPANS],
        done: std::array::from_fn(|sp| inside[sp % SPANS_PER_ROW].map(|i| u32::from(!i))),
        live: std::array::from_fn(|sp| {
            let rows = rect.y1 - rect.y0;
            let n = inside[sp % SPANS_PER_ROW].iter().filter(|&&i| i).count() as u32;
            if ((sp / SPANS_PER_ROW) as u32) < rows {
                n
            } else {
                0
            }
        }),
    };
    let xs = rect.xs();
    let mut remaining = rect.pixels();
    for (k, &g) in isects.iter().enumerate() {
        if remaining == 0 {
            break;
        }
        if let Some(&ahead) = isects.get(k + PREFETCH_AHEAD) {
            prefetch(&projections[ahead as usize]);
        }
        let Some(p) = &projections[g as usize] else {
            continue;
        };
        let Some((lx0, ly0, lx1, ly1)) = rect.clip(p) else {
            continue;
        };
        let s = &p.splat;
        let masks = box_masks(lx0, lx1);
        let (h0, h1) = (lx0 as usize / LANES, lx1 as usize / LANES);
        for ly in ly0 as usize..=ly1 as usize {
            let rs = RowSplat::new(s, (rect.y0 + ly as u32) as f32 + 0.5 - s.v);
            for h in h0..=h1 {
                let sp = ly * SPANS_PER_ROW + h;
                if st.live[sp] == 0 {
                    continue;
                }
                let n = span_forward(&rs, s.rgb, &xs[h], &masks[h], k as u32 + 1, &mut st, sp);
                st.live[sp] -= n;
                remaining -= n;
            }
        }
    }
    st
}

/// Backward state of one tile, by span: per pixel, what the forward left and the output
/// gradient.
pub struct TileBackward {
    /// Transmittance in front of the Gaussian being processed (starts at the final T).
    pub trans: [[f32; LANES]; SPANS],
    /// Sum over the Gaussians behind (and the background / T output) of their contribution
    /// to `dL/d alpha`, before division by `1 - alpha`.
    pub after: [[f32; LANES]; SPANS],
    /// dL/d RGB.
    pub grad: [[[f32; LANES]; SPANS]; 3],
    /// One past the last composited intersection; 0 outside the image.
    pub last: [[u32; LANES]; SPANS],
}

impl TileBackward {
    /// All-zero state; lanes outside the tile keep `last = 0` and so never contribute.
    pub fn new() -> Self {
        TileBackward {
            trans: [[0.0; LANES]; SPANS],
            after: [[0.0; LANES]; SPANS],
            grad: [[[0.0; LANES]; SPANS]; 3],
            last: [[0; LANES]; SPANS],
        }
    }
}

impl Default for TileBackward {
    fn default() -> Self {
        Self::new()
    }
}

/// Per-lane gradient accumulators of one Gaussian over one tile.
#[derive(Default)]
struct LaneGrads {
    u: [f32; LANES],
    v: [f32; LANES],
    a: [f32; LANES],
    b: [f32; LANES],
    c: [f32; LANES],
    opacity: [f32; LANES],
    rgb: [[f32; LANES]; 3],
}

impl LaneGrads {
    #[inline(always)]
    fn add(&mut self, o: &LaneGrads) {
        for l in 0..LANES {
            self.u[l] += o.u[l];
            self.v[l] += o.v[l];
            self.a[l] += o.a[l];
            self.b[l] += o.b[l];
            self.c[l] += o.c[l];
            self.opacity[l] += o.opacity[l];
            for ch in 0..3 {
                self.rgb[ch][l] += o.rgb[ch][l];
            }
        }
    }

    fn sum(&self) -> Splat2dGrad {
        let s = |v: &[f32; LANES]| v.iter().sum::<f32>();
        Splat2dGrad {
            u: s(&self.u),
            v: s(&self.v),
            a: s(&self.a),
            b: s(&self.b),
            c: s(&self.c),
            opacity: s(&self.opacity),
            rgb: [s(&self.rgb[0]), s(&self.rgb[1]), s(&self.rgb[2])],
        }
    }
}

/// One span of one Gaussian, backward (local copies, as in [`span_forward`]).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn span_backward(
    rs: &RowSplat,
    s: &Splat2d,
    dy: f32,
    xs: &[f32; LANES],
    in_box: &[u32; LANES],
    k: u32,
    st: &mut TileBackward,
    sp: usize,
    acc: &mut LaneGrads,
) {
    let mut trans = st.trans[sp];
    let mut after = st.after[sp];
    let last = st.last[sp];
    let grad = [st.grad[0][sp], st.grad[1][sp], st.grad[2][sp]];
    let mut a = LaneGrads::default();
    for l in 0..LANES {
        let (dx, g, raw, alpha, reaches) = rs.eval(xs[l]);
        let m = reaches & (in_box[l] != 0) & (k < last[l]);
        let one_minus = 1.0 - alpha;
        let t_i = trans[l] / one_minus;
        let gl = [grad[0][l], grad[1][l], grad[2][l]];
        let gc = gl[0] * s.rgb[0] + gl[1] * s.rgb[1] + gl[2] * s.rgb[2];
        let w = alpha * t_i;
        let d_alpha = t_i * gc - after[l] / one_minus;
        after[l] = select(m, after[l] + gc * w, after[l]);
        trans[l] = select(m, t_i, trans[l]);
        let wm = w * (m as u32 as f32);
        a.rgb[0][l] = gl[0] * wm;
        a.rgb[1][l] = gl[1] * wm;
        a.rgb[2][l] = gl[2] * wm;
        // Where alpha was clamped it does not depend on opacity or sigma.
        let m2 = m & (raw <= ALPHA_MAX);
        let d_alpha = select(m2, d_alpha, 0.0);
        let d_sigma = -d_alpha * alpha;
        a.opacity[l] = d_alpha * g;
        a.a[l] = d_sigma * 0.5 * dx * dx;
        a.b[l] = d_sigma * dx * dy;
        a.c[l] = d_sigma * 0.5 * dy * dy;
        // d = pixel - mean, so d sigma / d u = -(a dx + b dy).
        a.u[l] = -d_sigma * (s.a * dx + s.b * dy);
        a.v[l] = -d_sigma * (s.b * dx + s.c * dy);
    }
    st.trans[sp] = trans;
    st.after[sp] = after;
    acc.add(&a);
}

/// Composites one tile back to front, writing each intersection's gradient into `slots`
/// (tile-relative index). `isects` as in [`tile_forward_generic`].
#[inline(always)]
pub fn tile_backward_generic(
    rect: TileRect,
    st: &mut TileBackward,
    projections: &[Option<Projection>],
    isects: &[u32],
    slots: &mut [Splat2dGrad],
) {
    let xs = rect.xs();
    let span_last: [u32; SPANS] =
        std::array::from_fn(|sp| st.last[sp].iter().copied().max().unwrap_or(0));
    let max_last = span_last.iter().copied().max().unwrap_or(0);
    for k in (0..max_last).rev() {
        if let Some(ahead) = (k as usize).checked_sub(PREFETCH_AHEAD) {
            prefetch(&projections[isects[ahead] as usize]);
        }
        let Some(p) = &projections[isects[k as usize] as usize] else {
            continue;
        };
        let Some((lx0, ly0, lx1, ly1)) = rect.clip(p) else {
            continue;
        };
        let s = &p.splat;
        let masks = box_masks(lx0, lx1);
        let (h0, h1) = (lx0 as usize / LANES, lx1 as usize / LANES);
        let mut acc = LaneGrads::default();
        for ly in ly0 as usize..=ly1 as usize {
            let dy = (rect.y0 + ly as u32) as f32 + 0.5 - s.v;
            let rs = RowSplat::new(s, dy);
            for h in h0..=h1 {
                let sp = ly * SPANS_PER_ROW + h;
                if k >= span_last[sp] {
                    continue;
                }
                span_backward(&rs, s, dy, &xs[h], &masks[h], k, st, sp, &mut acc);
            }
        }
        slots[k as usize] = acc.sum();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_neg_matches_libm() {
        let mut worst = 0.0f32;
        for i in 0..200_000 {
            let s = i as f32 * 87.0 / 200_000.0;
            let want = (-s).exp();
            let got = exp_neg(s);
            worst = worst.max(((got - want) / want).abs());
        }
        assert!(worst < 4e-7, "worst relative error {worst}");
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(-3.0), 1.0);
        assert_eq!(exp_neg(f32::NAN), 1.0);
        assert!(exp_neg(1e9) > 0.0 && exp_neg(1e9) < 1e-37);
    }
}
