//! The lifting operator: fused CPU vs the tensor-op reference (values and gradients, every
//! mode and frame), finite differences, rigid motion, in-plane shear (Jacobian against
//! `k R`), PSD covariances, continuity across triangle borders (global vs local),
//! degenerate triangles.

#![allow(deprecated)]

use std::sync::Arc;

use burn::tensor::{Device, Tensor, TensorData};
use texavatars::lift::{self, LiftMode, LiftParams, Lifted, Topology};
use texavatars::mesh::UvMesh;
use texavatars::texel::FrameKind;
use texavatars::util::rng::Pcg;

const COMBOS: [(LiftMode, FrameKind); 4] = [
    (LiftMode::Global, FrameKind::Jacobian),
    (LiftMode::Global, FrameKind::ScaledRotation),
    (LiftMode::Local, FrameKind::Jacobian),
    (LiftMode::Local, FrameKind::ScaledRotation),
];

fn curved_mesh(m: usize) -> UvMesh {
    UvMesh::cylinder_patch(m)
}

fn params(
    mesh: &UvMesh,
    res: usize,
    samples: usize,
    mode: LiftMode,
    frame: FrameKind,
) -> LiftParams {
    LiftParams {
        topology: Arc::new(Topology::new(mesh, res, samples).expect("valid topology")),
        mode,
        frame,
    }
}

/// Random local maps [14, R, R] with moderate values.
fn random_local(r: usize, seed: u64) -> Vec<f32> {
    let mut rng = Pcg::new(seed);
    (0..14 * r * r)
        .map(|i| {
            let c = i / (r * r);
            let u = 2.0 * rng.uniform() - 1.0;
            match c {
                0..=2 => 0.3 * u,
                3 => 1.0 + 0.3 * u,
                4..=6 => 0.5 * u,
                7..=9 => -1.0 + 0.5 * u,
                _ => u,
            }
        })
        .collect()
}

fn perturbed_vertices(mesh: &UvMesh, seed: u64, amount: f32) -> Vec<f32> {
    let mut rng = Pcg::new(seed);
    mesh.positions
        .iter()
        .flatten()
        .map(|v| v + amount * (2.0 * rng.uniform() - 1.0))
        .collect()
}

struct Outcome {
    packed: Vec<f32>,
    grad_local: Vec<f32>,
    grad_vertices: Vec<f32>,
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

fn packed(l: &Lifted) -> Tensor<2> {
    Tensor::cat(
        vec![
            l.means.clone(),
            l.cov6.clone(),
            l.colors.clone(),
            l.opacities.clone().unsqueeze_dim::<2>(1),
        ],
        1,
    )
}

/// Lifts on ndarray (fused or reference) and, when `autodiff`, back-propagates
/// loss = sum(packed * weights).
fn run(
    p: &LiftParams,
    local: &[f32],
    vertices: &[f32],
    reference: bool,
    autodiff: bool,
) -> Outcome {
    let device = &if autodiff {
        ndarray()
    } else {
        Device::ndarray()
    };
    let r = p.topology.res();
    let v = p.topology.num_vertices;
    let mut lt = Tensor::<3>::from_data(TensorData::new(local.to_vec(), [14, r, r]), device);
    let mut vt = Tensor::<2>::from_data(TensorData::new(vertices.to_vec(), [v, 3]), device);
    if autodiff {
        lt = lt.require_grad();
        vt = vt.require_grad();
    }
    let out = if reference {
        lift::lift_reference(lt.clone(), vt.clone(), p)
    } else {
        lift::lift(lt.clone(), vt.clone(), p)
    }
    .expect("valid inputs");
    let out = packed(&out);
    let n = out.dims()[0];
    let mut rng = Pcg::new(99);
    let w: Vec<f32> = (0..n * 13).map(|_| 2.0 * rng.uniform() - 1.0).collect();
    let wt = Tensor::<2>::from_data(TensorData::new(w, [n, 13]), device);
    if !autodiff {
        return Outcome {
            packed: host(out),
            grad_local: Vec::new(),
            grad_vertices: Vec::new(),
        };
    }
    let grads = (out.clone() * wt).sum().backward();
    Outcome {
        packed: host(out),
        grad_local: lt.grad(&grads).map(host).unwrap_or_default(),
        grad_vertices: vt.grad(&grads).map(host).unwrap_or_default(),
    }
}

fn max_rel(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-12);
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
        / scale
}

fn ndarray() -> Device {
    Device::ndarray().autodiff()
}

#[test]
fn fused_matches_reference_all_modes() {
    let mesh = curved_mesh(6);
    let local = random_local(16, 1);
    let verts = perturbed_vertices(&mesh, 2, 0.02);
    for (mode, frame) in COMBOS {
        let p = params(&mesh, 16, 16, mode, frame);
        let f = run(&p, &local, &verts, false, true);
        let r = run(&p, &local, &verts, true, true);
        let (ev, el, eg) = (
            max_rel(&f.packed, &r.packed),
            max_rel(&f.grad_local, &r.grad_local),
            max_rel(&f.grad_vertices, &r.grad_vertices),
        );
        println!(
            "{mode:?}/{frame:?}: N {} | values {ev:.2e} | d local {el:.2e} | d vertices {eg:.2e}",
            p.topology.len()
        );
        assert!(
            f.packed
                .iter()
                .chain(&f.grad_local)
                .chain(&f.grad_vertices)
                .all(|v| v.is_finite())
        );
        assert!(ev < 1e-5, "{mode:?}/{frame:?} values {ev}");
        assert!(el < 1e-4, "{mode:?}/{frame:?} d local {el}");
        assert!(eg < 1e-4, "{mode:?}/{frame:?} d vertices {eg}");
    }
}

/// Central differences of loss = sum(out * w) on the fused operator (no autodiff involved).
#[test]
fn fused_gradients_match_finite_differences() {
    let mesh = curved_mesh(3);
    let r = 8;
    let local = random_local(r, 5);
    let verts = perturbed_vertices(&mesh, 6, 0.02);
    for (mode, frame) in COMBOS {
        let p = params(&mesh, r, 8, mode, frame);
        let loss = |l: &[f32], v: &[f32]| -> f64 {
            let o = run(&p, l, v, false, false).packed;
            let mut rng = Pcg::new(99);
            o.iter()
                .map(|x| *x as f64 * (2.0 * rng.uniform() - 1.0) as f64)
                .sum()
        };
        let g = run(&p, &local, &verts, false, true);
        let mut rng = Pcg::new(7);
        let mut worst = 0.0f64;
        for _ in 0..12 {
            let i = (rng.uniform() * local.len() as f32) as usize % local.len();
            let h = 1e-2f32;
            let (mut a, mut b) = (local.clone(), local.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (loss(&a, &verts) - loss(&b, &verts)) / (2.0 * h as f64);
            worst = worst.max((fd - g.grad_local[i] as f64).abs() / (1.0 + fd.abs()));
        }
        for _ in 0..12 {
            let i = (rng.uniform() * verts.len() as f32) as usize % verts.len();
            let h = 1e-3f32;
            let (mut a, mut b) = (verts.clone(), verts.clone());
            a[i] += h;
            b[i] -= h;
            let fd = (loss(&local, &a) - loss(&local, &b)) / (2.0 * h as f64);
            worst = worst.max((fd - g.grad_vertices[i] as f64).abs() / (1.0 + fd.abs()));
        }
        println!("{mode:?}/{frame:?}: worst finite-difference error {worst:.2e}");
        assert!(worst < 2e-2, "{mode:?}/{frame:?}: {worst}");
    }
}

fn lifted_host(p: &LiftParams, local: &[f32], verts: &[f32]) -> Vec<[f32; 13]> {
    run(p, local, verts, false, false)
        .packed
        .chunks(13)
        .map(|c| std::array::from_fn(|k| c[k]))
        .collect()
}

#[test]
fn rigid_motion_moves_gaussians_rigidly() {
    let mesh = curved_mesh(5);
    let local = random_local(16, 11);
    let verts = perturbed_vertices(&mesh, 12, 0.01);
    // Rotation about (1, 2, 3) by 0.7 rad, then a translation.
    let (axis, angle) = ([1.0f32, 2.0, 3.0], 0.7f32);
    let n = (axis.iter().map(|a| a * a).sum::<f32>()).sqrt();
    let [x, y, z] = axis.map(|a| a / n);
    let (s, c) = angle.sin_cos();
    let rot = [
        [
            c + x * x * (1.0 - c),
            x * y * (1.0 - c) - z * s,
            x * z * (1.0 - c) + y * s,
        ],
        [
            y * x * (1.0 - c) + z * s,
            c + y * y * (1.0 - c),
            y * z * (1.0 - c) - x * s,
        ],
        [
            z * x * (1.0 - c) - y * s,
            z * y * (1.0 - c) + x * s,
            c + z * z * (1.0 - c),
        ],
    ];
    let t = [0.3f32, -0.2, 1.5];
    let apply = |v: [f32; 3]| -> [f32; 3] {
        std::array::from_fn(|i| (0..3).map(|k| rot[i][k] * v[k]).sum::<f32>() + t[i])
    };
    let moved: Vec<f32> = verts
        .chunks(3)
        .flat_map(|v| apply([v[0], v[1], v[2]]))
        .collect();
    for (mode, frame) in COMBOS {
        let p = params(&mesh, 16, 16, mode, frame);
        let a = lifted_host(&p, &local, &verts);
        let b = lifted_host(&p, &local, &moved);
        let mut worst = 0.0f32;
        for (ga, gb) in a.iter().zip(&b) {
            let m = apply([ga[0], ga[1], ga[2]]);
            for i in 0..3 {
                worst = worst.max((m[i] - gb[i]).abs());
            }
            let sym = |c: &[f32]| -> [[f32; 3]; 3] {
                [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
            };
            let (ca, cb) = (sym(&ga[3..9]), sym(&gb[3..9]));
            for i in 0..3 {
                for j in 0..3 {
                    let want: f32 = (0..3)
                        .flat_map(|k| (0..3).map(move |l| (k, l)))
                        .map(|(k, l)| rot[i][k] * ca[k][l] * rot[j][l])
                        .sum();
                    worst = worst.max((want - cb[i][j]).abs());
                }
            }
            for k in 9..13 {
                worst = worst.max((ga[k] - gb[k]).abs());
            }
        }
        println!("{mode:?}/{frame:?}: rigid motion max error {worst:.2e}");
        assert!(worst < 1e-4, "{mode:?}/{frame:?}: {worst}");
    }
}

/// Where "w/o Jacobian" and the full method differ: an in-plane affine map `A` (a stretch
/// and a shear) of a flat mesh. The Jacobian frames `[e1 | e2 | n / sqrt|n|]` carry every
/// Gaussian's in-plane position and covariance through `A` exactly (the in-plane block of
/// the covariance becomes `A Σ Aᵀ`), in both lift modes; GaussianAvatars' `k R` carries a
/// similarity per face only, so (lifted per face) each covariance keeps its in-plane aspect
/// ratio. The component the study removes is live in the lifting.
#[test]
fn in_plane_shear_is_followed_by_the_jacobian_only() {
    let mesh = curved_mesh(5);
    let local = random_local(16, 13);
    // The patch unrolled into the plane z = 0.
    let flat: Vec<f32> = mesh
        .positions
        .iter()
        .flat_map(|p| [p[0].atan2(p[2]), p[1], 0.0])
        .collect();
    let a = [[1.5f32, 0.4], [0.0, 0.8]];
    let t = [0.2f32, -0.1];
    let moved: Vec<f32> = flat
        .chunks(3)
        .flat_map(|v| {
            [
                a[0][0] * v[0] + a[0][1] * v[1] + t[0],
                a[1][0] * v[0] + a[1][1] * v[1] + t[1],
                0.0,
            ]
        })
        .collect();
    // The in-plane block [xx, xy, yy] of a lifted Gaussian's covariance, and its aspect
    // ratio (the eigenvalues' ratio).
    let block = |g: &[f32; 13]| [g[3], g[4], g[6]];
    let aspect = |[xx, xy, yy]: [f32; 3]| {
        let (m, d) = (
            0.5 * (xx + yy),
            (0.25 * (xx - yy) * (xx - yy) + xy * xy).sqrt(),
        );
        (m + d) / (m - d).max(1e-12)
    };
    for mode in [LiftMode::Global, LiftMode::Local] {
        let p = params(&mesh, 16, 16, mode, FrameKind::Jacobian);
        let (rest, def) = (
            lifted_host(&p, &local, &flat),
            lifted_host(&p, &local, &moved),
        );
        let (mut worst, mut most_changed) = (0.0f32, 1.0f32);
        for (g, h) in rest.iter().zip(&def) {
            for i in 0..2 {
                let want = a[i][0] * g[0] + a[i][1] * g[1] + t[i];
                worst = worst.max((want - h[i]).abs());
            }
            let [xx, xy, yy] = block(g);
            let s = [[xx, xy], [xy, yy]];
            let asa = |i: usize, j: usize| -> f32 {
                (0..2)
                    .flat_map(|k| (0..2).map(move |l| (k, l)))
                    .map(|(k, l)| a[i][k] * s[k][l] * a[j][l])
                    .sum()
            };
            let want = [asa(0, 0), asa(0, 1), asa(1, 1)];
            let scale = want.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
            for (w, got) in want.iter().zip(block(h)) {
                worst = worst.max((w - got).abs() / scale);
            }
            let r = aspect(block(h)) / aspect(block(g));
            most_changed = most_changed.max(r.max(1.0 / r));
        }
        println!(
            "{mode:?}/Jacobian: A Σ Aᵀ within {worst:.2e}, aspect changed up to {most_changed:.2}x"
        );
        assert!(worst < 1e-4, "{mode:?}: {worst}");
        assert!(most_changed > 1.5, "{mode:?}: {most_changed}");

        // Per face, `k R` is a similarity; Global UV's blend of neighbouring faces' frames
        // (which turn by different angles under `A`) is not one, so the aspect test is the
        // local mode's.
        if mode == LiftMode::Global {
            continue;
        }
        let p = params(&mesh, 16, 16, mode, FrameKind::ScaledRotation);
        let (rest, def) = (
            lifted_host(&p, &local, &flat),
            lifted_host(&p, &local, &moved),
        );
        let mut worst = 0.0f32;
        for (g, h) in rest.iter().zip(&def) {
            let r = aspect(block(h)) / aspect(block(g));
            worst = worst.max((r - 1.0).abs());
        }
        println!("{mode:?}/ScaledRotation: aspect kept within {worst:.2e}");
        assert!(worst < 1e-3, "{mode:?}: {worst}");
    }
}

#[test]
fn covariances_are_positive_semidefinite() {
    let mesh = curved_mesh(4);
    for seed in 0..4 {
        let mut local = random_local(16, 20 + seed);
        // Wilder log-scales and quaternions than the other tests.
        let mut rng = Pcg::new(seed);
        for v in &mut local[3 * 256..10 * 256] {
            *v = 3.0 * (2.0 * rng.uniform() - 1.0);
        }
        let verts = perturbed_vertices(&mesh, 30 + seed, 0.05);
        for (mode, frame) in COMBOS {
            let p = params(&mesh, 16, 16, mode, frame);
            for g in lifted_host(&p, &local, &verts) {
                let c = &g[3..9];
                let (xx, xy, xz, yy, yz, zz) = (c[0], c[1], c[2], c[3], c[4], c[5]);
                let scale = xx.abs() + yy.abs() + zz.abs() + 1e-20;
                let m2 = xx * yy - xy * xy;
                let det =
                    xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz);
                assert!(
                    xx >= 0.0 && yy >= 0.0 && zz >= 0.0,
                    "{mode:?}/{frame:?} {c:?}"
                );
                assert!(m2 >= -1e-5 * scale * scale, "{mode:?}/{frame:?} {c:?}");
                assert!(
                    det >= -1e-5 * scale * scale * scale,
                    "{mode:?}/{frame:?} {c:?}"
                );
            }
        }
    }
}

/// On a finely tessellated curved mesh with constant local attributes, neighbouring samples
/// in different faces differ in covariance: piecewise frames (local mode) jump by the full
/// frame change between two samples, blended frames (global mode) spread it over the texel
/// spacing. Samples are twice as dense as texels so that the spread is visible between
/// neighbours (at S = R the blend spans one sample step and the two maxima nearly coincide).
#[test]
fn global_mode_is_smoother_across_borders_than_local() {
    let mesh = curved_mesh(12);
    let (r, s) = (64, 128);
    let mut local = vec![0.0f32; 14 * r * r];
    let constant = [
        0.0, 0.0, 0.2, 0.9, 0.3, -0.2, 0.1, -2.0, -1.5, -3.0, 0.0, 0.5, 0.5, 0.5,
    ];
    for (c, v) in constant.iter().enumerate() {
        local[c * r * r..(c + 1) * r * r].fill(*v);
    }
    let verts: Vec<f32> = mesh.positions.iter().flatten().copied().collect();
    let mut jumps = Vec::new();
    for mode in [LiftMode::Global, LiftMode::Local] {
        let p = params(&mesh, r, s, mode, FrameKind::Jacobian);
        let g = lifted_host(&p, &local, &verts);
        let samples = &p.topology.samples;
        let at: std::collections::HashMap<u32, usize> = samples
            .grid_index
            .iter()
            .enumerate()
            .map(|(k, &i)| (i, k))
            .collect();
        let mut worst = 0.0f32;
        for (k, &gi) in samples.grid_index.iter().enumerate() {
            for nb in [gi + 1, gi + s as u32] {
                let Some(&k2) = at.get(&nb) else { continue };
                if nb == gi + 1 && (gi as usize + 1).is_multiple_of(s) {
                    continue;
                }
                if samples.face[k] == samples.face[k2] {
                    continue;
                }
                let d: f32 = (3..9)
                    .map(|c| (g[k][c] - g[k2][c]).powi(2))
                    .sum::<f32>()
                    .sqrt();
                let norm: f32 = (3..9).map(|c| g[k][c].powi(2)).sum::<f32>().sqrt();
                worst = worst.max(d / norm);
            }
        }
        jumps.push(worst);
    }
    println!(
        "largest relative covariance jump between neighbouring samples across borders: global {:.4e}, local {:.4e}",
        jumps[0], jumps[1]
    );
    assert!(
        jumps[0] < jumps[1],
        "global {} vs local {}",
        jumps[0],
        jumps[1]
    );
}

#[test]
fn zero_area_triangles_give_finite_outputs_and_gradients() {
    let mut mesh = curved_mesh(4);
    let r = 16;
    let local = random_local(r, 40);
    let mut verts: Vec<f32> = mesh.positions.iter().flatten().copied().collect();
    // Collapse face 3 to a point and make face 8 a sliver on a line.
    let f3 = mesh.faces[3];
    for k in 1..3 {
        for c in 0..3 {
            verts[3 * f3[k] as usize + c] = verts[3 * f3[0] as usize + c];
        }
    }
    let f8 = mesh.faces[8];
    for c in 0..3 {
        let (a, b) = (verts[3 * f8[0] as usize + c], verts[3 * f8[1] as usize + c]);
        verts[3 * f8[2] as usize + c] = 0.5 * (a + b);
    }
    mesh.positions = verts.chunks(3).map(|v| [v[0], v[1], v[2]]).collect();
    for (mode, frame) in COMBOS {
        let p = params(&mesh, r, 16, mode, frame);
        for reference in [false, true] {
            let o = run(&p, &local, &verts, reference, true);
            assert!(
                o.packed
                    .iter()
                    .chain(&o.grad_local)
                    .chain(&o.grad_vertices)
                    .all(|v| v.is_finite()),
                "{mode:?}/{frame:?} reference={reference}"
            );
        }
    }
}

#[test]
fn wrong_shapes_are_rejected() {
    let mesh = curved_mesh(2);
    let p = params(&mesh, 8, 8, LiftMode::Global, FrameKind::Jacobian);
    let d = Device::ndarray();
    let local = Tensor::<3>::zeros([14, 8, 7], &d);
    let verts = Tensor::<2>::zeros([9, 3], &d);
    let e = lift::lift(local, verts.clone(), &p)
        .expect_err("bad local")
        .to_string();
    assert!(e.contains("local"), "{e}");
    let e = lift::lift(
        Tensor::<3>::zeros([14, 8, 8], &d),
        Tensor::<2>::zeros([8, 3], &d),
        &p,
    )
    .expect_err("bad vertices")
    .to_string();
    assert!(e.contains("vertices"), "{e}");
}

/// The CubeCL kernels on wgpu (lavapipe here) against the fused CPU code and the reference
/// on ndarray (every mode and frame, values and gradients, also with one zero-area face) and,
/// for one combination, against the reference on wgpu.
#[test]
fn wgpu_matches_cpu_and_reference() {
    let wgpu = Device::wgpu(burn::tensor::DeviceKind::DefaultDevice).autodiff();
    let mesh = curved_mesh(4);
    let local = random_local(16, 50);
    let smooth = perturbed_vertices(&mesh, 51, 0.02);
    // The same with one zero-area face, so the kernels' guards are exercised too.
    let mut collapsed = smooth.clone();
    let f3 = mesh.faces[3];
    for k in 1..3 {
        for c in 0..3 {
            collapsed[3 * f3[k] as usize + c] = collapsed[3 * f3[0] as usize + c];
        }
    }
    for (label, verts) in [("smooth", &smooth), ("zero-area face", &collapsed)] {
        let get = |p: &LiftParams, device: &Device, reference: bool| {
            let r = p.topology.res();
            let lt = Tensor::<3>::from_data(TensorData::new(local.clone(), [14, r, r]), device)
                .require_grad();
            let vt = Tensor::<2>::from_data(
                TensorData::new(verts.clone(), [p.topology.num_vertices, 3]),
                device,
            )
            .require_grad();
            let out = if reference {
                lift::lift_reference(lt.clone(), vt.clone(), p)
            } else {
                lift::lift(lt.clone(), vt.clone(), p)
            }
            .expect("valid inputs");
            let packed = packed(&out);
            let grads = (packed.clone() * packed.clone()).sum().backward();
            (
                host(packed),
                lt.grad(&grads).map(host).unwrap_or_default(),
                vt.grad(&grads).map(host).unwrap_or_default(),
            )
        };
        for (i, (mode, frame)) in COMBOS.into_iter().enumerate() {
            let p = params(&mesh, 16, 16, mode, frame);
            let g = get(&p, &wgpu, false);
            let mut against = vec![
                ("cpu", get(&p, &ndarray(), false)),
                ("reference on ndarray", get(&p, &ndarray(), true)),
            ];
            if i == 0 {
                against.push(("reference on wgpu", get(&p, &wgpu, true)));
            }
            for (name, w) in against {
                let (ev, el, eg) = (
                    max_rel(&g.0, &w.0),
                    max_rel(&g.1, &w.1),
                    max_rel(&g.2, &w.2),
                );
                println!(
                    "{label}: wgpu vs {name} {mode:?}/{frame:?}: values {ev:.2e} | d local {el:.2e} | d vertices {eg:.2e}"
                );
                assert!(g.0.iter().chain(&g.1).chain(&g.2).all(|v| v.is_finite()));
                assert!(
                    ev < 1e-5 && el < 1e-4 && eg < 1e-4,
                    "{name}: {ev} {el} {eg}"
                );
            }
        }
    }
}
