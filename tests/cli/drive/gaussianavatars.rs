//! A GaussianAvatars output folder built by hand in GaussianAvatars' own layout, driven,
//! exported, rendered and scored by texavatars (a module of `tests/cli/drive.rs`, in the
//! `cli` test binary).
//!
//! The layout follows GaussianAvatars' code, not texavatars' writer:
//! - `point_cloud.ply`: `GaussianModel.construct_list_of_attributes` / `save_ply`
//!   (`scene/gaussian_model.py`): `x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2
//!   rot_0..3 binding_0`, every one `float` (numpy `f4`), binary little-endian; `f_rest`
//!   channel-major (`_features_rest.transpose(1, 2).flatten`), `rot` as (w, x, y, z).
//! - `flame_param.npz` beside it: `FlameGaussianModel.save_ply` / `load_meshes`
//!   (`scene/flame_gaussian_model.py`): `shape`, `static_offset` (1, V, 3), per timestep
//!   `expr` (T, 100), `rotation`, `neck_pose`, `jaw_pose` (T, 3), `eyes_pose` (T, 6),
//!   `translation` (T, 3), `dynamic_offset` (T, V, 3).
//!
//! The expected world-space Gaussians are computed here by hand with GaussianAvatars'
//! formulas: `compute_face_orientation` (`utils/graphics_utils.py`), and `get_xyz`,
//! `get_scaling`, `get_rotation` (`scene/gaussian_model.py`).

use std::path::{Path, PathBuf};

use texavatars::head::HeadAsset;
use texavatars::io::npz::NpzOut;
use texavatars::splat::ply;

use crate::{cli, tiny};

const SH_REST: usize = 45;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-ga-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// One stored Gaussian as GaussianAvatars keeps it.
struct Stored {
    xyz: [f32; 3],
    f_dc: [f32; 3],
    /// [3 channels][15 coefficients]
    f_rest: [[f32; 15]; 3],
    opacity: f32,
    scale: [f32; 3],
    rot: [f32; 4],
    binding: u32,
}

fn stored(faces: usize) -> Vec<Stored> {
    let bind = [0, 17, faces / 2, faces - 1];
    bind.iter()
        .enumerate()
        .map(|(i, &f)| {
            let t = i as f32;
            let mut f_rest = [[0.0; 15]; 3];
            for (c, ch) in f_rest.iter_mut().enumerate() {
                for (k, v) in ch.iter_mut().enumerate() {
                    *v = 0.01 * (c * 15 + k) as f32 - 0.2 + 0.03 * t;
                }
            }
            Stored {
                xyz: [0.1 * t - 0.1, 0.2, -0.05 * t],
                f_dc: [0.5, -0.3 + 0.1 * t, 0.2],
                f_rest,
                opacity: 2.0 + t,
                scale: [0.5 - 0.2 * t, 0.1, -0.3],
                rot: [1.0 + t, 0.2, -0.4 * t, 0.3],
                binding: f as u32,
            }
        })
        .collect()
}

/// `point_cloud.ply` byte for byte as GaussianAvatars' `save_ply` writes it.
fn write_point_cloud(path: &Path, gs: &[Stored]) {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..SH_REST).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names.push("binding_0".into());
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n",
        gs.len()
    )
    .into_bytes();
    for n in &names {
        bytes.extend_from_slice(format!("property float {n}\n").as_bytes());
    }
    bytes.extend_from_slice(b"end_header\n");
    for g in gs {
        let mut row: Vec<f32> = g.xyz.to_vec();
        row.extend([0.0; 3]);
        row.extend(g.f_dc);
        for ch in &g.f_rest {
            row.extend(ch);
        }
        row.push(g.opacity);
        row.extend(g.scale);
        row.extend(g.rot);
        row.push(g.binding as f32);
        assert_eq!(row.len(), names.len());
        for v in row {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).expect("write ply");
}

/// `flame_param.npz` with two timesteps: neutral, then translated by `t1`.
fn write_flame_param(path: &Path, num_shape: usize, v: usize, t1: [f32; 3]) {
    let t = 2;
    let mut z = NpzOut::default();
    z.floats("shape", &[num_shape], vec![0.0; num_shape])
        .floats("expr", &[t, 100], vec![0.0; t * 100])
        .floats("rotation", &[t, 3], vec![0.0; t * 3])
        .floats("neck_pose", &[t, 3], vec![0.0; t * 3])
        .floats("jaw_pose", &[t, 3], vec![0.0; t * 3])
        .floats("eyes_pose", &[t, 6], vec![0.0; t * 6])
        .floats(
            "translation",
            &[t, 3],
            vec![0.0, 0.0, 0.0, t1[0], t1[1], t1[2]],
        )
        .floats("static_offset", &[1, v, 3], vec![0.0; v * 3])
        .floats("dynamic_offset", &[t, v, 3], vec![0.0; t * v * 3]);
    z.write(path).expect("write npz");
}

type V3 = [f32; 3];
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn normalize(a: V3) -> V3 {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// GaussianAvatars' `compute_face_orientation(..., return_scale=True)` and the face centre
/// (`triangles.mean(dim=-2)`): the columns a0, a1, a2, the scale and the centre.
fn ga_face(v: [V3; 3]) -> ([V3; 3], f32, V3) {
    let a0 = normalize(sub(v[1], v[0]));
    let a1 = normalize(cross(a0, sub(v[2], v[0])));
    let a2 = normalize(cross(a1, a0)).map(|x| -x);
    let s0 = dot(sub(v[1], v[0]), sub(v[1], v[0])).sqrt();
    let s1 = dot(a2, sub(v[2], v[0])).abs();
    let c = [0, 1, 2].map(|k| (v[0][k] + v[1][k] + v[2][k]) / 3.0);
    ([a0, a1, a2], (s0 + s1) / 2.0, c)
}

/// Rotation matrix (rows) of a unit quaternion (w, x, y, z).
fn rotmat(q: [f32; 4]) -> [[f32; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

fn close(a: &[f32], b: &[f32], tol: f32) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

#[test]
fn a_gaussianavatars_folder_is_driven_exported_and_rendered() {
    let head = HeadAsset::embedded().expect("head");
    let (faces, v_template) = (&head.model.faces, &head.model.v_template);
    // GaussianAvatars' model folder: point_cloud/iteration_N/, the highest N used.
    let model = tmp("model");
    let dir = model.join("point_cloud/iteration_30000");
    std::fs::create_dir_all(&dir).expect("dir");
    std::fs::create_dir_all(model.join("point_cloud/iteration_7000")).expect("dir");
    let gs = stored(faces.len());
    write_point_cloud(&dir.join("point_cloud.ply"), &gs);
    let t1 = [0.01, 0.02, -0.03];
    let motion = dir.join("flame_param.npz");
    write_flame_param(&motion, head.model.num_shape, v_template.len(), t1);

    // Timestep 1, exported as world-space 3DGS files.
    let out = tmp("export");
    let (m, o) = (motion.as_os_str(), out.as_os_str());
    cli::texavatars_ok([
        "export".as_ref(),
        "ply".as_ref(),
        "--checkpoint".as_ref(),
        model.as_os_str(),
        "--motion".as_ref(),
        m,
        "--frames".as_ref(),
        "1".as_ref(),
        "--cameras".as_ref(),
        "front".as_ref(),
        "--size".as_ref(),
        "64x96".as_ref(),
        "--out".as_ref(),
        o,
    ]);
    let world = ply::read(&out.join("00001.ply")).expect("exported ply");
    assert_eq!((world.len(), world.sh_degree), (gs.len(), 3));
    // Zero shape, expression and pose: the posed mesh is the template moved by t1.
    let posed: Vec<V3> = v_template
        .iter()
        .map(|v| [v[0] + t1[0], v[1] + t1[1], v[2] + t1[2]])
        .collect();
    for (i, g) in gs.iter().enumerate() {
        let f = faces[g.binding as usize].map(|k| posed[k as usize]);
        let ([a0, a1, a2], k, c) = ga_face(f);
        // get_xyz: k R mu + T.
        let mean: V3 =
            [0, 1, 2].map(|r| k * (a0[r] * g.xyz[0] + a1[r] * g.xyz[1] + a2[r] * g.xyz[2]) + c[r]);
        assert!(
            close(&world.means[3 * i..3 * i + 3], &mean, 1e-5),
            "mean {i}"
        );
        // get_scaling: exp(s) k, stored as a log.
        let ls = g.scale.map(|s| s + k.ln());
        assert!(
            close(&world.log_scales[3 * i..3 * i + 3], &ls, 1e-5),
            "scale {i}"
        );
        // get_rotation: R_face R(r); compared as matrices (q and -q are one rotation).
        let rl = rotmat(g.rot);
        let face = [
            [a0[0], a1[0], a2[0]],
            [a0[1], a1[1], a2[1]],
            [a0[2], a1[2], a2[2]],
        ];
        let want: Vec<f32> = (0..9)
            .map(|e| (0..3).map(|j| face[e / 3][j] * rl[j][e % 3]).sum())
            .collect();
        let q = &world.quats[4 * i..4 * i + 4];
        let got: Vec<f32> = rotmat([q[0], q[1], q[2], q[3]]).concat();
        assert!(
            close(&got, &want, 1e-5),
            "rotation {i}: {got:?} vs {want:?}"
        );
        // Opacity and colour coefficients as stored (SH is evaluated in world space).
        assert_eq!(world.opacity_logits[i], g.opacity);
        let sh = &world.sh[48 * i..48 * i + 48];
        assert_eq!(sh[..3], g.f_dc);
        for coeff in 0..15 {
            for ch in 0..3 {
                assert_eq!(sh[3 + 3 * coeff + ch], g.f_rest[ch][coeff], "sh {i}");
            }
        }
    }

    // texavatars writes the same file GaussianAvatars does: byte for byte the hand-built one.
    let (stored, binding) = ply::read_bound(&dir.join("point_cloud.ply")).expect("read");
    let again = tmp("write");
    let written =
        texavatars::models::gaussianavatars::folder::write_point_cloud(&again, &stored, &binding)
            .expect("write");
    assert_eq!(
        std::fs::read(&written).expect("written"),
        std::fs::read(dir.join("point_cloud.ply")).expect("hand-built")
    );
    let _ = std::fs::remove_dir_all(&again);

    // Rendered with texavatars' rasterizer: the Gaussians show on the white background.
    let render = tmp("render");
    cli::texavatars_ok([
        "render".as_ref(),
        "--checkpoint".as_ref(),
        dir.as_os_str(),
        "--motion".as_ref(),
        m,
        "--cameras".as_ref(),
        "front".as_ref(),
        "--size".as_ref(),
        "64x96".as_ref(),
        "--no-mp4".as_ref(),
        "--out".as_ref(),
        render.as_os_str(),
    ]);
    let img = texavatars::io::image::read_rgb(&render.join("frames/00000.png")).expect("frame");
    let drawn = img
        .rgb
        .chunks(3)
        .filter(|p| p.iter().any(|&c| c < 0.98))
        .count();
    assert!(drawn > 0, "nothing drawn");

    // Scored by `eval` like a TexAvatars run, on a tiny benchmark of the same head.
    let data = tmp("data");
    tiny::synth_data(&data);
    let opts = texavatars::eval::run::EvalOptions {
        data: data.join("union"),
        run: model.clone(),
        out: tmp("eval"),
        splits: vec![texavatars::data::Split::Test],
        extra: Vec::new(),
        head: None,
        lpips: false,
        stride: 4,
        panels: 0,
        backend: texavatars::device::BackendKind::Flex,
        paths: texavatars::data::PathPolicy::InsideRoot,
        tracked: false,
        renders: false,
        against: None,
    };
    let report = texavatars::eval::run::evaluate(&opts, &mut |_| {}).expect("eval");
    let m = &report.means["test"];
    assert_eq!(m.images, 8);
    assert!(m.psnr.is_finite() && m.psnr > 0.0, "{}", m.psnr);

    // `bench fps` on the folder: the model's own stage (binding) and the rasterizer.
    let json = tmp("fps.json");
    let text = cli::texavatars_ok([
        "bench".as_ref(),
        "fps".as_ref(),
        "--checkpoint".as_ref(),
        model.as_os_str(),
        "--renders".as_ref(),
        "2".as_ref(),
        "--rounds".as_ref(),
        "1".as_ref(),
        "--size".as_ref(),
        "24x32".as_ref(),
        "--json".as_ref(),
        json.as_os_str(),
    ]);
    assert!(
        text.contains("binding") && text.contains("rasterizer"),
        "{text}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    assert_eq!(v["model"], "GaussianAvatars");
    assert_eq!(v["gaussians"].as_u64(), Some(gs.len() as u64));
    for k in ["fps", "binding_ms", "rasterizer_ms"] {
        assert!(
            v["rounds"][0][k].as_f64().is_some_and(|x| x > 0.0),
            "{k}: {v}"
        );
    }
    let _ = std::fs::remove_file(&json);
    for d in [&model, &out, &render, &data, &opts.out] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn a_binding_beyond_the_head_model_names_the_file_and_the_fix() {
    let head = HeadAsset::embedded().expect("head");
    let dir = tmp("bad");
    std::fs::create_dir_all(&dir).expect("dir");
    let mut gs = stored(head.model.faces.len());
    gs[2].binding = head.model.faces.len() as u32 + 5;
    write_point_cloud(&dir.join("point_cloud.ply"), &gs);
    let e = texavatars::models::gaussianavatars::GaAvatar::load(
        &dir,
        &head.model.faces,
        head.model.num_vertices(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("point_cloud.ply") && e.contains("Gaussian 2") && e.contains("--head"),
        "{e}"
    );
    let e = texavatars::models::gaussianavatars::GaAvatar::load(
        &dir.join("absent"),
        &head.model.faces,
        head.model.num_vertices(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("point_cloud.ply") && e.contains("absent"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
