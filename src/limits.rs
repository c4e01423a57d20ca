//! Resource bounds, each with its reason, in one place: hard caps on sizes that come from
//! the command line or from files ([`Cap`]), and a memory budget that estimated
//! allocations are checked against before they are made ([`check_memory`]).
//!
//! Without them a typo (`--size 100000x100000`, `"frames": 100000000`, `"batch_size":
//! 1000`) allocates until the kernel's OOM killer ends the process, minutes later and with
//! no message. With them every such input is an error that names the flag or the file and
//! field, before any work.
//!
//! # The memory budget
//!
//! In order of precedence:
//! 1. the global flag `--max-memory SIZE` ([`set_max_memory`], applied by
//!    [`crate::cli::run`]);
//! 2. the environment variable [`ENV_MAX_MEMORY`] (`TEXAVATARS_MAX_MEMORY=SIZE`);
//! 3. [`MEMORY_FRACTION`] (3/4) of the machine's memory: `MemTotal` of `/proc/meminfo`, or
//!    the cgroup's limit when that is lower (a container);
//! 4. where neither can be read (not Linux), 3/4 of [`FALLBACK_MACHINE_MEMORY`] (8 GiB).
//!
//! `SIZE` is a number of bytes with an optional binary suffix: `K`, `M`, `G`, `T` (1024,
//! 1024², ...), optionally followed by `B` or `iB` (`512M`, `1.5G`, `24GiB`).
//!
//! Why 3/4: the rest is for the operating system, the page cache the data loader relies on
//! for reading frames, other processes, and allocator slack (burn keeps freed buffers in
//! pools; mimalloc keeps freed pages mapped). The reference machine (24 GB) has no swap, so
//! going past physical memory means the OOM killer, not a slow run; 3/4 also leaves room
//! for an estimate that is low by a third.
//!
//! # Estimates
//!
//! The estimates below count the large buffers of each path (images, per-pixel and
//! per-Gaussian renderer buffers, texel maps, network activations, frames held at once) from
//! the sizes in play. They are meant to be within a factor of 2 of the peak; they are not
//! exact, and small allocations (meshes, weights of the tiny networks) are left out. Each
//! constant says what it counts.

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::error::{Error, Result};

/// A hard cap on a size, with the reason for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cap {
    /// The largest value allowed.
    pub max: u64,
    /// Unit of the value, for messages ("pixels", "frames").
    pub unit: &'static str,
    /// Why this is the cap.
    pub reason: &'static str,
}

/// Image width and height (renders, camera files, the synthetic benchmark).
pub const IMAGE_SIDE: Cap = Cap {
    max: 16_384,
    unit: "pixels",
    reason: "20 times the paper's 802-pixel frames and the largest 2D texture of most GPUs; \
             one 16384 x 16384 avatar render already needs about 24 GiB of buffers",
};

/// Texel resolution R of the UV maps (`uv inspect --res`, a network's `uv_res`).
pub const UV_RES: Cap = Cap {
    max: 4096,
    unit: "texels",
    reason: "8 times the paper's 512; the texel maps, the decoders' untied biases and \
             activations grow with R^2, 64 times the paper's at 4096",
};

/// Side S of the sample grid (`uv inspect --samples`): S^2 samples, one Gaussian each.
pub const SAMPLE_GRID: Cap = Cap {
    max: 4096,
    unit: "samples per side",
    reason: "8 times the paper's 512, up to 16.8 million Gaussians",
};

/// Gaussians in one scene (a PLY for `splat render`, `splat demo --gaussians`).
pub const GAUSSIANS: Cap = Cap {
    max: 1 << 24,
    unit: "Gaussians",
    reason: "a full 4096 x 4096 sample grid; an avatar has a few hundred thousand, large \
             3DGS scenes about 6 million, and the rasterizer's tile lists index them with \
             32 bits",
};

/// Frames of a motion (curves, FLAME parameter files, a dataset split) and of a synthetic
/// sequence.
pub const FRAMES: Cap = Cap {
    max: 100_000,
    unit: "frames",
    reason: "over an hour at 25 fps; a loaded motion keeps every frame's posed mesh in \
             memory (about 60 kB each for FLAME), so split longer motions into several files",
};

/// Frames per training step (`batch_size`).
pub const BATCH_SIZE: Cap = Cap {
    max: 64,
    unit: "frames",
    reason: "the paper trains at 1; every frame of a batch holds its own activations, render \
             and VGG features, about 0.5 to 2 GiB at the paper's sizes",
};

/// Cameras of the synthetic rig.
pub const CAMERAS: Cap = Cap {
    max: 256,
    unit: "cameras",
    reason: "16 times NeRSemble's 16; every timestep is rendered from every camera",
};

/// Resolution of the synthetic benchmark's baked albedo and wrinkle maps.
pub const TEXTURE_RES: Cap = Cap {
    max: 8192,
    unit: "texels",
    reason: "16 times the default 512; the baked maps take about 128 bytes per texel",
};

impl Cap {
    /// `Ok` when `value` is at most the cap; else an error naming `what` and `field`, the
    /// value, the cap and its reason.
    pub fn check(&self, what: &str, field: &str, value: u64) -> Result<()> {
        if value <= self.max {
            return Ok(());
        }
        Err(Error::invalid(
            what,
            field,
            format!(
                "{value} {} is above the cap of {} ({})",
                self.unit, self.max, self.reason
            ),
        ))
    }
}

/// [`Cap::check`] for any unsigned size: `Ok` when `value <= cap.max`.
pub fn check_size(what: &str, field: &str, value: impl TryInto<u64>, cap: &Cap) -> Result<()> {
    cap.check(what, field, value.try_into().unwrap_or(u64::MAX))
}

// ---------------------------------------------------------------------------------------
// The budget.

/// The environment variable that sets the memory budget (see the module docs).
pub const ENV_MAX_MEMORY: &str = "TEXAVATARS_MAX_MEMORY";

/// The budget's share of the machine's memory: 3/4 (see the module docs for why).
pub const MEMORY_FRACTION: (u64, u64) = (3, 4);

/// The machine's memory assumed where it cannot be read: 8 GiB, a small laptop's, so that
/// the default errs on the safe side; raise it with `--max-memory`.
pub const FALLBACK_MACHINE_MEMORY: u64 = 8 << 30;

/// The `--max-memory` value of this process; 0 when not set.
static FLAG: AtomicU64 = AtomicU64::new(0);

/// Sets the budget of this process (the `--max-memory` flag); `None` leaves the one in
/// place. It takes precedence over [`ENV_MAX_MEMORY`] from then on.
pub fn set_max_memory(bytes: Option<u64>) {
    if let Some(b) = bytes {
        FLAG.store(b.max(1), Ordering::Relaxed);
    }
}

/// Where the budget comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// The `--max-memory` flag.
    Flag,
    /// The [`ENV_MAX_MEMORY`] variable.
    Env,
    /// [`MEMORY_FRACTION`] of the machine's memory (`total` bytes).
    Machine { total: u64 },
    /// [`MEMORY_FRACTION`] of [`FALLBACK_MACHINE_MEMORY`] (the machine's could not be read).
    Fallback,
}

/// The memory budget: how many bytes a command may plan to allocate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Budget {
    /// Bytes.
    pub bytes: u64,
    /// Where the value comes from.
    pub source: Source,
}

impl fmt::Display for Budget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let b = Bytes(self.bytes);
        match self.source {
            Source::Flag => write!(f, "{b} (--max-memory)"),
            Source::Env => write!(f, "{b} ({ENV_MAX_MEMORY})"),
            Source::Machine { total } => write!(
                f,
                "{b} ({}/{} of the machine's {})",
                MEMORY_FRACTION.0,
                MEMORY_FRACTION.1,
                Bytes(total)
            ),
            Source::Fallback => write!(
                f,
                "{b} ({}/{} of an assumed {}: the machine's memory could not be read)",
                MEMORY_FRACTION.0,
                MEMORY_FRACTION.1,
                Bytes(FALLBACK_MACHINE_MEMORY)
            ),
        }
    }
}

/// The budget in force (see the module docs for the order). An error when
/// [`ENV_MAX_MEMORY`] is set but not a size.
pub fn budget() -> Result<Budget> {
    let flag = FLAG.load(Ordering::Relaxed);
    if flag > 0 {
        return Ok(Budget {
            bytes: flag,
            source: Source::Flag,
        });
    }
    if let Some(v) = std::env::var_os(ENV_MAX_MEMORY) {
        let v = v.to_string_lossy();
        let bytes =
            parse_bytes(&v).map_err(|why| Error::invalid("environment", ENV_MAX_MEMORY, why))?;
        return Ok(Budget {
            bytes,
            source: Source::Env,
        });
    }
    Ok(match machine_memory() {
        Some(total) => Budget {
            bytes: fraction(total),
            source: Source::Machine { total },
        },
        None => Budget {
            bytes: fraction(FALLBACK_MACHINE_MEMORY),
            source: Source::Fallback,
        },
    })
}

fn fraction(total: u64) -> u64 {
    (total as u128 * MEMORY_FRACTION.0 as u128 / MEMORY_FRACTION.1 as u128) as u64
}

/// The machine's memory in bytes: `MemTotal` of `/proc/meminfo`, lowered to the cgroup's
/// memory limit when there is one (cgroup v2 `memory.max`, v1 `memory.limit_in_bytes`).
/// `None` where `/proc/meminfo` cannot be read.
pub fn machine_memory() -> Option<u64> {
    let total = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|t| mem_total(&t))?;
    let cgroup = [
        "/sys/fs/cgroup/memory.max",
        "/sys/fs/cgroup/memory/memory.limit_in_bytes",
    ]
    .iter()
    .filter_map(|p| std::fs::read_to_string(p).ok())
    .filter_map(|t| t.trim().parse::<u64>().ok())
    .min();
    Some(match cgroup {
        Some(c) if c > 0 => total.min(c),
        _ => total,
    })
}

/// `MemTotal` of a `/proc/meminfo` text, in bytes.
pub fn mem_total(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let mut it = line["MemTotal:".len()..].split_whitespace();
    let n: u64 = it.next()?.parse().ok()?;
    let scale = match it.next() {
        Some("kB") | Some("KB") | Some("kb") => 1024,
        None => 1,
        Some(_) => return None,
    };
    n.checked_mul(scale)
}

/// Parses a size: bytes with an optional binary suffix `K`, `M`, `G`, `T` (case does not
/// matter), optionally followed by `B` or `iB`; a fraction is allowed before a suffix
/// (`1.5G`). Zero is refused.
pub fn parse_bytes(s: &str) -> std::result::Result<u64, String> {
    let bad = || {
        format!(
            "{s:?} is not a size: expected bytes with an optional K, M, G or T suffix \
             (powers of 1024), e.g. 512M or 16G"
        )
    };
    let t = s.trim();
    let lower = t.to_ascii_lowercase();
    let num_end = lower
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(lower.len());
    let (num, unit) = lower.split_at(num_end);
    let unit = unit.trim();
    let unit = unit
        .strip_suffix("ib")
        .or_else(|| unit.strip_suffix('b'))
        .unwrap_or(unit);
    let shift = match unit {
        "" => 0,
        "k" => 10,
        "m" => 20,
        "g" => 30,
        "t" => 40,
        _ => return Err(bad()),
    };
    if num.is_empty() {
        return Err(bad());
    }
    let bytes = if let Ok(n) = num.parse::<u64>() {
        n.checked_mul(1u64 << shift).ok_or_else(bad)?
    } else {
        let x: f64 = num.parse().map_err(|_| bad())?;
        let v = x * (1u64 << shift) as f64;
        if !v.is_finite() || v >= u64::MAX as f64 {
            return Err(bad());
        }
        v.round() as u64
    };
    if bytes == 0 {
        return Err(format!("{s:?}: the memory limit must be above 0"));
    }
    Ok(bytes)
}

/// A byte count for messages: `1.5 GiB`, `200.0 MiB`, `512 B`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bytes(pub u64);

impl fmt::Display for Bytes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let b = self.0 as f64;
        for (shift, unit) in [(40, "TiB"), (30, "GiB"), (20, "MiB"), (10, "KiB")] {
            let s = (1u64 << shift) as f64;
            if b >= s {
                return write!(f, "{:.1} {unit}", b / s);
            }
        }
        write!(f, "{} B", self.0)
    }
}

/// A memory estimate made of named parts (for the message when it is over the budget).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Estimate {
    parts: Vec<(String, u64)>,
}

impl Estimate {
    /// An empty estimate.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds `bytes` for `part` (zero parts are left out of the message).
    pub fn add(mut self, part: impl Into<String>, bytes: u64) -> Self {
        if bytes > 0 {
            self.parts.push((part.into(), bytes));
        }
        self
    }

    /// The sum of the parts (saturating).
    pub fn total(&self) -> u64 {
        self.parts
            .iter()
            .fold(0u64, |s, (_, b)| s.saturating_add(*b))
    }

    /// The parts, largest first, as `name size, ...`.
    pub fn breakdown(&self) -> String {
        let mut p = self.parts.clone();
        p.sort_by_key(|x| std::cmp::Reverse(x.1));
        p.iter()
            .map(|(n, b)| format!("{n} {}", Bytes(*b)))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// `Ok` when `estimated_bytes` fits the [`budget`]; else an error naming `what` and
/// `field`, the estimate, the budget and how to raise it.
pub fn check_memory(what: &str, field: &str, estimated_bytes: u64) -> Result<()> {
    check_estimate(
        what,
        field,
        &Estimate::new().add("buffers", estimated_bytes),
    )
}

/// [`check_memory`] for an estimate made of parts (named in the message).
pub fn check_estimate(what: &str, field: &str, estimate: &Estimate) -> Result<()> {
    let budget = budget()?;
    check_estimate_against(what, field, estimate, &budget)
}

/// [`check_estimate`] against a given budget (no global state: for tests and callers that
/// hold a budget).
pub fn check_estimate_against(
    what: &str,
    field: &str,
    estimate: &Estimate,
    budget: &Budget,
) -> Result<()> {
    let total = estimate.total();
    if total <= budget.bytes {
        return Ok(());
    }
    Err(Error::invalid(
        what,
        field,
        format!(
            "needs about {} of memory (an estimate, good to within 2x: {}), above the limit \
             of {budget}; make it smaller, or raise the limit with --max-memory SIZE or \
             {ENV_MAX_MEMORY}=SIZE (e.g. 32G)",
            Bytes(total),
            estimate.breakdown()
        ),
    ))
}

// ---------------------------------------------------------------------------------------
// What things take.

/// Saturating product.
pub fn product(factors: &[u64]) -> u64 {
    factors.iter().fold(1u64, |p, &f| p.saturating_mul(f))
}

/// Host bytes per pixel of one avatar frame (`render`, `export ply`): the Pluecker map of
/// the full image (6 floats, 24 B), the rasterizer's packed output and last-contributor
/// index (20 B), its copy out of the tensor and the image narrowed from it (28 B), the host
/// RGB (12 B), 8-bit copies for the PNG, the thumbnails and the GIF (6 B), and the tile
/// lists (a few B at typical depth complexity): 96 B.
pub const RENDER_BYTES_PER_PIXEL: u64 = 96;

/// Host bytes per pixel of `splat render` (no Pluecker map): 64 B (see
/// [`RENDER_BYTES_PER_PIXEL`]).
pub const SPLAT_BYTES_PER_PIXEL: u64 = 64;

/// Bytes per Gaussian while rendering and exporting: the four input tensors (13 floats),
/// the renderer's projected record (16 floats), spherical-harmonic coefficients up to
/// degree 3 (48 floats), host copies and the PLY rows (about 50 floats): 512 B.
pub const GAUSSIAN_BYTES: u64 = 512;

/// Bytes per texel (of R^2) of an avatar's inference pass: the decoders' last layers (the
/// paper's networks produce about 36 floats per output texel over all layers), the packed
/// 14-channel local maps, the lifted per-texel attributes, and the texel set-up (layout,
/// sample taps): 320 B.
pub const INFERENCE_BYTES_PER_TEXEL: u64 = 320;

/// Bytes per texel of a UV layout (`uv inspect`): coverage rasterization (face, barycentrics:
/// 20 B), the layout (32 B), its validity map, and two 12 B/texel float pictures: 96 B.
pub const LAYOUT_BYTES_PER_TEXEL: u64 = 96;

/// Bytes per sample of the S^2 sample grid (`uv inspect`, the avatar's Gaussians): coverage
/// at the samples (20 B), the kept samples' taps, weights, faces and barycentrics (60 B),
/// the samples picture (12 B) and slack: 128 B.
pub const SAMPLE_BYTES: u64 = 128;

/// Bytes per synthetic-benchmark supersample: the z-buffer's depth, face and barycentrics
/// (24 B) and slack: 32 B. Each output pixel adds the same again (RGB, mask, PNG bytes).
pub const SYNTH_BYTES_PER_SAMPLE: u64 = 32;

/// Bytes per texel of the synthetic benchmark's baked maps (albedo, specular, 7 wrinkle
/// maps: 44 B) with the baking's coverage and the written pictures: 128 B.
pub const SYNTH_BYTES_PER_TEXEL: u64 = 128;

/// Bytes per image record of the synthetic benchmark's `transforms_*.json` (the record, its
/// JSON value and text): 2 KiB.
pub const SYNTH_BYTES_PER_IMAGE_RECORD: u64 = 2048;

/// Bytes of one rendered avatar frame of `width x height` pixels.
pub fn render_bytes(width: u64, height: u64) -> u64 {
    product(&[width, height, RENDER_BYTES_PER_PIXEL])
}

/// Bytes of a loaded motion frame for a head of `vertices` vertices and a condition of
/// `condition` values: the posed vertices, the condition, and the parameters the frame is
/// built from (a second copy of the vertices' size: static offsets, skinning temporaries).
pub fn motion_frame_bytes(vertices: usize, condition: usize) -> u64 {
    let floats = (vertices as u64)
        .saturating_mul(6)
        .saturating_add(condition as u64);
    floats.saturating_mul(4).saturating_add(256)
}

/// Bytes of an avatar's inference at `uv_res` with `gaussians` Gaussians (networks, lift,
/// Gaussians; the image is [`render_bytes`]).
pub fn avatar_bytes(uv_res: usize, gaussians: usize) -> u64 {
    let r = uv_res as u64;
    product(&[r, r, INFERENCE_BYTES_PER_TEXEL])
        .saturating_add(product(&[gaussians as u64, GAUSSIAN_BYTES]))
}

/// Checks an image size against [`IMAGE_SIDE`]; `field` prefixes the `width` / `height`
/// field names (e.g. `""` or `"camera."`).
pub fn check_image_size(what: &str, field: &str, width: u64, height: u64) -> Result<()> {
    IMAGE_SIDE.check(what, &format!("{field}width"), width)?;
    IMAGE_SIDE.check(what, &format!("{field}height"), height)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_suffixes() {
        assert_eq!(parse_bytes("123"), Ok(123));
        assert_eq!(parse_bytes("1K"), Ok(1024));
        assert_eq!(parse_bytes("1k"), Ok(1024));
        assert_eq!(parse_bytes("512M"), Ok(512 << 20));
        assert_eq!(parse_bytes("16G"), Ok(16 << 30));
        assert_eq!(parse_bytes("16GiB"), Ok(16 << 30));
        assert_eq!(parse_bytes("16gb"), Ok(16 << 30));
        assert_eq!(parse_bytes(" 2 T "), Ok(2 << 40));
        assert_eq!(parse_bytes("1.5G"), Ok(3 << 29));
        for bad in [
            "",
            "G",
            "-1G",
            "1X",
            "1.2.3M",
            "0",
            "0G",
            "99999999999T",
            "nan",
            "1e9",
        ] {
            assert!(parse_bytes(bad).is_err(), "{bad:?}");
        }
        assert!(parse_bytes("x").unwrap_err().contains("\"x\""));
    }

    #[test]
    fn meminfo_total_is_read_in_bytes() {
        let t = "MemTotal:       24684084 kB\nMemFree:        1000 kB\n";
        assert_eq!(mem_total(t), Some(24684084 * 1024));
        assert_eq!(mem_total("MemFree: 1 kB\n"), None);
        assert_eq!(mem_total("MemTotal: lots kB\n"), None);
        assert_eq!(mem_total("MemTotal: 5 pages\n"), None);
    }

    #[test]
    fn the_machine_budget_is_three_quarters() {
        assert_eq!(fraction(4 << 30), 3 << 30);
        assert_eq!(fraction(u64::MAX), u64::MAX / 4 * 3 + 2);
        if let Some(total) = machine_memory() {
            assert!(total > 0);
        }
    }

    #[test]
    fn caps_name_the_field_value_and_reason() {
        assert!(FRAMES.check("m.json", "frames", FRAMES.max).is_ok());
        let e = FRAMES
            .check("m.json", "frames", FRAMES.max + 1)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("m.json")
                && e.contains("`frames`")
                && e.contains("100001 frames")
                && e.contains("cap of 100000")
                && e.contains("hour"),
            "{e}"
        );
        let e = check_size("x", "n", u128::MAX, &GAUSSIANS)
            .unwrap_err()
            .to_string();
        assert!(e.contains(&u64::MAX.to_string()), "{e}");
        let e = check_image_size("cam.json", "", 100, 100_000)
            .unwrap_err()
            .to_string();
        assert!(e.contains("`height`") && e.contains("16384"), "{e}");
    }

    #[test]
    fn estimates_over_the_budget_say_how_to_raise_it() {
        let budget = Budget {
            bytes: 1 << 30,
            source: Source::Flag,
        };
        let small = Estimate::new().add("frames", 1 << 20);
        assert!(check_estimate_against("render", "--size", &small, &budget).is_ok());
        let big = Estimate::new()
            .add("render buffers", render_bytes(8000, 8000))
            .add("motion", 3 << 20)
            .add("nothing", 0);
        let e = check_estimate_against("render", "--size", &big, &budget)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("render: field `--size`: needs about 5.7 GiB")
                && e.contains("render buffers 5.7 GiB, motion 3.0 MiB")
                && !e.contains("nothing")
                && e.contains("limit of 1.0 GiB (--max-memory)")
                && e.contains("--max-memory SIZE")
                && e.contains(ENV_MAX_MEMORY),
            "{e}"
        );
        let machine = Budget {
            bytes: 3 << 30,
            source: Source::Machine { total: 4 << 30 },
        };
        assert_eq!(
            machine.to_string(),
            "3.0 GiB (3/4 of the machine's 4.0 GiB)"
        );
    }

    #[test]
    fn estimates_saturate_instead_of_overflowing() {
        assert_eq!(render_bytes(u64::MAX, 2), u64::MAX);
        assert_eq!(avatar_bytes(usize::MAX, usize::MAX), u64::MAX);
        assert_eq!(motion_frame_bytes(usize::MAX, 1), u64::MAX);
        let e = Estimate::new().add("a", u64::MAX).add("b", 5);
        assert_eq!(e.total(), u64::MAX);
        assert_eq!(Bytes(512).to_string(), "512 B");
        assert_eq!(Bytes(3 << 29).to_string(), "1.5 GiB");
    }
}
