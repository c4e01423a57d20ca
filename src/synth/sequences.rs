//! The captured performance: expression families, one sequence each, and the FREE
//! sequence. Each frame is a [`HeadPose`] (expression coefficients, joint rotations).
//!
//! Training sequences sweep one family each: its units peak one after another (smooth
//! bumps, neighbours overlapping), with gentle head motion. The held-out sequence combines
//! units from several families into an expression no training frame shows; FREE combines
//! random strong units from every family with head rotations larger than any training
//! frame's. Heads whose meta has no expression names use consecutive index blocks as
//! families.

use std::f32::consts::PI;

use crate::head::{HeadMeta, HeadModel, HeadPose};
use crate::synth::config::SynthConfig;
use crate::util::rng::Pcg;

/// Training families: (sequence name, ARKit units).
pub const TRAIN_FAMILIES: [(&str, &[&str]); 10] = [
    (
        "brows",
        &[
            "browInnerUp",
            "browOuterUpLeft",
            "browOuterUpRight",
            "browDownLeft",
            "browDownRight",
        ],
    ),
    (
        "eyes",
        &[
            "eyeBlinkLeft",
            "eyeBlinkRight",
            "eyeWideLeft",
            "eyeWideRight",
            "eyeSquintLeft",
            "eyeSquintRight",
        ],
    ),
    (
        "gaze",
        &[
            "eyeLookUpLeft",
            "eyeLookUpRight",
            "eyeLookDownLeft",
            "eyeLookDownRight",
            "eyeLookInLeft",
            "eyeLookOutRight",
        ],
    ),
    (
        "smile",
        &[
            "mouthSmileLeft",
            "mouthSmileRight",
            "cheekSquintLeft",
            "cheekSquintRight",
            "mouthDimpleLeft",
            "mouthDimpleRight",
        ],
    ),
    (
        "jaw",
        &["jawOpen", "jawLeft", "jawRight", "jawForward", "mouthClose"],
    ),
    (
        "pucker",
        &[
            "mouthPucker",
            "mouthFunnel",
            "mouthRollLower",
            "mouthRollUpper",
        ],
    ),
    (
        "frown",
        &[
            "mouthFrownLeft",
            "mouthFrownRight",
            "mouthStretchLeft",
            "mouthStretchRight",
            "mouthPressLeft",
            "mouthPressRight",
        ],
    ),
    (
        "sneer",
        &[
            "noseSneerLeft",
            "noseSneerRight",
            "mouthUpperUpLeft",
            "mouthUpperUpRight",
            "mouthShrugUpper",
            "mouthShrugLower",
        ],
    ),
    (
        "cheeks",
        &[
            "cheekPuff",
            "mouthLeft",
            "mouthRight",
            "mouthLowerDownLeft",
            "mouthLowerDownRight",
        ],
    ),
    (
        "tongue",
        &["tongueOut", "jawOpen", "eyeLookOutLeft", "eyeLookInRight"],
    ),
];
/// The held-out sequence (novel expression): anger, units seen only apart in training.
pub const TEST_FAMILY: (&str, &[&str]) = (
    "anger",
    &[
        "browDownLeft",
        "browDownRight",
        "noseSneerLeft",
        "noseSneerRight",
        "eyeSquintLeft",
        "eyeSquintRight",
        "mouthPressLeft",
        "mouthPressRight",
        "mouthFrownLeft",
        "mouthFrownRight",
    ],
);
/// The FREE sequence's name.
pub const FREE_NAME: &str = "free";

/// Which split a sequence feeds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Train,
    Test,
    Free,
}

/// One sequence: its name, role and frames.
#[derive(Clone, Debug)]
pub struct Sequence {
    pub name: String,
    pub role: Role,
    pub frames: Vec<HeadPose>,
}

/// Smooth bump on [c - w, c + w], 1 at c.
pub(super) fn bump(t: f32, c: f32, w: f32) -> f32 {
    let x = (t - c) / w;
    if x.abs() >= 1.0 {
        0.0
    } else {
        0.5 + 0.5 * (PI * x).cos()
    }
}

/// Resolves unit names to expression indices (names the head lacks are skipped).
fn units(meta: &HeadMeta, names: &[&str]) -> Vec<usize> {
    names.iter().filter_map(|n| meta.expr(n)).collect()
}

/// Gentle or strong head motion for frame `t` in [0, 1].
fn head_motion(pose: &mut HeadPose, t: f32, amp: f32, phase: f32) {
    let a = 2.0 * PI * t + phase;
    pose.rotation = [
        0.4 * amp * (1.3 * a).sin(),
        amp * a.sin(),
        0.25 * amp * (0.7 * a).cos(),
    ];
    pose.neck = [
        0.15 * amp * (0.9 * a).cos(),
        0.2 * amp * (1.1 * a).sin(),
        0.0,
    ];
}

/// Poses driven by expression unit `e` that the skeleton should also show.
fn joints_for_units(pose: &mut HeadPose, meta: &HeadMeta) {
    let get = |n: &str| meta.expr(n).map_or(0.0, |i| pose.expr[i]);
    pose.jaw = [
        0.25 * get("jawOpen"),
        0.06 * (get("jawLeft") - get("jawRight")),
        0.0,
    ];
    let look_y = 0.3 * (get("eyeLookOutLeft") - get("eyeLookInLeft"));
    let look_x = 0.25 * (get("eyeLookDownLeft") - get("eyeLookUpLeft"));
    let look_y_r = 0.3 * (get("eyeLookInRight") - get("eyeLookOutRight"));
    let look_x_r = 0.25 * (get("eyeLookDownRight") - get("eyeLookUpRight"));
    pose.eyes = [look_x, look_y, 0.0, look_x_r, look_y_r, 0.0];
}

/// Frames of one family sweep.
fn sweep(
    model: &HeadModel,
    meta: &HeadMeta,
    members: &[usize],
    n: usize,
    rng: &mut Pcg,
    amp: f32,
) -> Vec<HeadPose> {
    let k = members.len().max(1);
    let peaks: Vec<f32> = (0..k).map(|_| 0.7 + 0.3 * rng.uniform()).collect();
    let phase = 2.0 * PI * rng.uniform();
    (0..n)
        .map(|f| {
            let t = f as f32 / (n - 1) as f32;
            let mut pose = HeadPose::neutral(model);
            for (i, &m) in members.iter().enumerate() {
                let c = (i as f32 + 0.5) / k as f32;
                pose.expr[m] = peaks[i] * bump(t, c, 1.5 / k as f32);
            }
            head_motion(&mut pose, t, amp, phase);
            joints_for_units(&mut pose, meta);
            pose
        })
        .collect()
}

/// All sequences: ten training families, the held-out one, FREE.
pub fn sequences(config: &SynthConfig, model: &HeadModel, meta: &HeadMeta) -> Vec<Sequence> {
    let mut rng = Pcg::new(config.seed ^ 0x5e9_u64);
    let e = model.num_expr;
    let named = !meta.expr_names.is_empty();
    let block = |i: usize, of: usize| -> Vec<usize> { (i * e / of..(i + 1) * e / of).collect() };
    let mut out = Vec::new();
    for (i, (name, names)) in TRAIN_FAMILIES.iter().enumerate() {
        let members = if named {
            units(meta, names)
        } else {
            block(i, TRAIN_FAMILIES.len())
        };
        out.push(Sequence {
            name: (*name).to_string(),
            role: Role::Train,
            frames: sweep(
                model,
                meta,
                &members,
                config.frames_per_sequence,
                &mut rng,
                config.train_rotation,
            ),
        });
    }
    // Held-out: the anger units all rise together (pairs in step).
    let members = if named {
        units(meta, TEST_FAMILY.1)
    } else {
        (0..e).step_by(3).collect()
    };
    let n = config.frames_per_sequence;
    let phase = 2.0 * PI * rng.uniform();
    let test = (0..n)
        .map(|f| {
            let t = f as f32 / (n - 1) as f32;
            let mut pose = HeadPose::neutral(model);
            // max(0): sin(pi) is slightly negative in f32, and a negative base has no power.
            let a = (PI * t).sin().max(0.0).powf(0.7);
            for &m in &members {
                pose.expr[m] = 0.85 * a;
            }
            head_motion(&mut pose, t, config.train_rotation, phase);
            joints_for_units(&mut pose, meta);
            pose
        })
        .collect();
    out.push(Sequence {
        name: TEST_FAMILY.0.to_string(),
        role: Role::Test,
        frames: test,
    });
    // FREE: random strong combinations, changing every few frames, big head motion.
    let n = config.free_frames;
    let keys = n.div_ceil(4) + 1;
    let key_poses: Vec<Vec<f32>> = (0..keys)
        .map(|_| {
            let mut x = vec![0.0f32; e];
            for _ in 0..4 {
                let fam =
                    (rng.uniform() * TRAIN_FAMILIES.len() as f32) as usize % TRAIN_FAMILIES.len();
                let members = if named {
                    units(meta, TRAIN_FAMILIES[fam].1)
                } else {
                    block(fam, TRAIN_FAMILIES.len())
                };
                if members.is_empty() {
                    continue;
                }
                let m = members[(rng.uniform() * members.len() as f32) as usize % members.len()];
                x[m] = (x[m] + 0.8 + 0.4 * rng.uniform()).min(1.2);
            }
            x
        })
        .collect();
    let phase = 2.0 * PI * rng.uniform();
    let free = (0..n)
        .map(|f| {
            let s = f as f32 / 4.0;
            let (k0, w) = (s.floor() as usize, s.fract());
            let w = w * w * (3.0 - 2.0 * w);
            let mut pose = HeadPose::neutral(model);
            let (a, b) = (&key_poses[k0], &key_poses[(k0 + 1).min(keys - 1)]);
            for (i, x) in pose.expr.iter_mut().enumerate() {
                *x = (1.0 - w) * a[i] + w * b[i];
            }
            head_motion(
                &mut pose,
                f as f32 / (n - 1) as f32,
                config.free_rotation,
                phase,
            );
            joints_for_units(&mut pose, meta);
            pose
        })
        .collect();
    out.push(Sequence {
        name: FREE_NAME.to_string(),
        role: Role::Free,
        frames: free,
    });
    out
}
