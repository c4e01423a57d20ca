//! The FLAME-compatible head model on a tiny hand-made model with known answers: blendshapes,
//! joint regression, every joint's rotation, the kinematic chain, pose correctives,
//! translation, static offsets; `.npz` round trips (both posedirs layouts); bad files.

use texavatars::head::model::HeadModel;
use texavatars::head::{HeadPose, lbs};
use texavatars::io::npz::NpzOut;

use crate::common;

const FRAC_PI_2: f32 = std::f32::consts::FRAC_PI_2;

/// The shared tiny head with one expression direction.
fn tiny() -> HeadModel {
    common::head::tiny_head(1)
}

fn close(a: &[[f32; 3]], b: &[[f32; 3]]) {
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        for c in 0..3 {
            assert!((x[c] - y[c]).abs() < 1e-5, "vertex {i}: {x:?} vs {y:?}");
        }
    }
}

#[test]
fn rest_pose_is_the_template() {
    let m = tiny();
    close(&lbs(&m, &HeadPose::default()).expect("lbs"), &m.v_template);
}

#[test]
fn blendshapes_and_translation() {
    let m = tiny();
    let pose = HeadPose {
        shape: vec![0.5],
        expr: vec![2.0],
        translation: [0.0, 0.0, 10.0],
        ..Default::default()
    };
    let mut want = m.v_template.clone();
    want[0][0] += 0.5;
    want[5][2] += 2.0;
    for v in &mut want {
        v[2] += 10.0;
    }
    close(&lbs(&m, &pose).expect("lbs"), &want);
}

#[test]
fn jaw_rotation_rotates_about_the_jaw_joint_with_correctives() {
    let m = tiny();
    // 90 degrees about x: y -> z. Vertex 5 is one unit above the jaw joint (0, 2, 0); the
    // corrective first adds (R - I)[1][1] = -1 to its y, leaving it at the joint.
    let pose = HeadPose {
        jaw: [FRAC_PI_2, 0.0, 0.0],
        ..Default::default()
    };
    let got = lbs(&m, &pose).expect("lbs");
    close(&got[..5], &m.v_template[..5]);
    close(&got[5..], &[[0.0, 2.0, 0.0]]);
    // Without the corrective the offset (0, 1, 0) turns into (0, 0, 1).
    let mut plain = m.clone();
    plain.posedirs.iter_mut().for_each(|v| *v = 0.0);
    close(&lbs(&plain, &pose).expect("lbs")[5..], &[[0.0, 2.0, 1.0]]);
}

#[test]
fn neck_rotation_carries_its_children() {
    let mut m = tiny();
    m.posedirs.iter_mut().for_each(|v| *v = 0.0);
    // 90 degrees about z at the neck (0, 1, 0): (x, y) offsets turn (x, y) -> (-y, x).
    let pose = HeadPose {
        neck: [0.0, 0.0, FRAC_PI_2],
        ..Default::default()
    };
    let got = lbs(&m, &pose).expect("lbs");
    let want = [
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [-1.0, 1.0, 0.0],
        [-2.0, 0.0, 0.0],
        [-2.0, 2.0, 0.0],
        [-2.0, 1.0, 0.0],
    ];
    close(&got, &want);
}

#[test]
fn global_rotation_and_eyes() {
    let mut m = tiny();
    m.posedirs.iter_mut().for_each(|v| *v = 0.0);
    // Global 180 degrees about y flips x and z around the root; an eye's own rotation
    // leaves its (only) vertex, the joint itself, in place.
    let pose = HeadPose {
        rotation: [0.0, std::f32::consts::PI, 0.0],
        eyes: [0.3, 0.2, 0.1, -0.4, 0.0, 0.5],
        ..Default::default()
    };
    let got = lbs(&m, &pose).expect("lbs");
    let want: Vec<[f32; 3]> = m.v_template.iter().map(|v| [-v[0], v[1], -v[2]]).collect();
    close(&got, &want);
}

#[test]
fn too_many_coefficients_are_rejected() {
    let m = tiny();
    let e = lbs(
        &m,
        &HeadPose {
            expr: vec![0.0; 2],
            ..Default::default()
        },
    )
    .expect_err("too many")
    .to_string();
    assert!(e.contains("expr"), "{e}");
    let e = lbs(
        &m,
        &HeadPose {
            static_offset: Some(vec![[0.0; 3]; 2]),
            ..Default::default()
        },
    )
    .expect_err("offsets")
    .to_string();
    assert!(e.contains("static_offset"), "{e}");
}

fn tmp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-head-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).expect("dir");
    d
}

#[test]
fn model_and_params_round_trip() {
    let d = tmp("rt");
    let m = tiny();
    m.save(&d.join("model.npz")).expect("save");
    assert_eq!(HeadModel::load(&d.join("model.npz")).expect("load"), m);

    // FLAME's PyTorch layout for posedirs: [36, 3V].
    let v = m.num_vertices();
    let mut flame = vec![0.0f32; 36 * 3 * v];
    for i in 0..3 * v {
        for q in 0..36 {
            flame[q * 3 * v + i] = m.posedirs[i * 36 + q];
        }
    }
    NpzOut::default()
        .floats("v_template", &[v, 3], m.v_template.concat())
        .floats("shapedirs", &[v, 3, 2], m.shapedirs.clone())
        .floats("posedirs", &[36, 3 * v], flame)
        .floats("J_regressor", &[5, v], m.j_regressor.clone())
        .floats("weights", &[v, 5], m.weights.clone())
        .ints(
            "kintree_table",
            &[2, 5],
            vec![4294967295, 0, 1, 1, 1, 0, 1, 2, 3, 4],
        )
        .ints(
            "f",
            &[3, 3],
            m.faces.iter().flatten().map(|&x| x as i64).collect(),
        )
        .ints("num_shape", &[], vec![1])
        .write(&d.join("flame_layout.npz"))
        .expect("write");
    assert_eq!(
        HeadModel::load(&d.join("flame_layout.npz")).expect("load"),
        m
    );

    let pose = HeadPose {
        shape: vec![0.1],
        expr: vec![0.2],
        rotation: [0.1, 0.2, 0.3],
        neck: [0.0, 0.1, 0.0],
        jaw: [0.2, 0.0, 0.0],
        eyes: [0.0, 0.1, 0.0, 0.0, -0.1, 0.0],
        translation: [1.0, 2.0, 3.0],
        static_offset: Some(vec![[0.01; 3]; v]),
    };
    pose.save_npz(&d.join("00000.npz")).expect("save");
    assert_eq!(
        HeadPose::load_npz(&d.join("00000.npz")).expect("load"),
        pose
    );
}

#[test]
fn bad_model_files_name_file_and_field() {
    let d = tmp("bad");
    let m = tiny();
    let v = m.num_vertices();
    let base = |skip: &str, wrong: &str, faces: Vec<i64>| {
        let mut o = NpzOut::default();
        let mut add_f = |name: &str, shape: &[usize], data: Vec<f32>| {
            if name == skip {
                return;
            }
            if name == wrong {
                o.floats(name, &[data.len()], data);
            } else {
                o.floats(name, shape, data);
            }
        };
        add_f("v_template", &[v, 3], m.v_template.concat());
        add_f("shapedirs", &[v, 3, 2], m.shapedirs.clone());
        add_f("posedirs", &[v, 3, 36], m.posedirs.clone());
        add_f("J_regressor", &[5, v], m.j_regressor.clone());
        add_f("weights", &[v, 5], m.weights.clone());
        o.ints(
            "kintree_table",
            &[2, 5],
            vec![-1, 0, 1, 1, 1, 0, 1, 2, 3, 4],
        )
        .ints("f", &[faces.len() / 3, 3], faces)
        .ints("num_shape", &[1], vec![1]);
        o
    };
    let ok_faces: Vec<i64> = vec![0, 1, 2, 2, 5, 3, 2, 5, 4];
    for field in [
        "v_template",
        "shapedirs",
        "posedirs",
        "J_regressor",
        "weights",
    ] {
        let p = d.join(format!("missing_{field}.npz"));
        base(field, "", ok_faces.clone()).write(&p).expect("write");
        let e = HeadModel::load(&p).expect_err(field).to_string();
        assert!(
            e.contains(&format!("missing_{field}.npz")) && e.contains(field),
            "{e}"
        );
        let p = d.join(format!("wrong_{field}.npz"));
        base("", field, ok_faces.clone()).write(&p).expect("write");
        let e = HeadModel::load(&p).expect_err(field).to_string();
        assert!(
            e.contains(&format!("wrong_{field}.npz")) && e.contains(field),
            "{e}"
        );
    }
    // A face indexing past the vertices, and a truncated file.
    let p = d.join("bad_face.npz");
    base("", "", vec![0, 1, 99]).write(&p).expect("write");
    let e = HeadModel::load(&p).expect_err("face").to_string();
    assert!(e.contains("bad_face.npz") && e.contains("`f`"), "{e}");
    let good = d.join("good.npz");
    m.save(&good).expect("save");
    let bytes = std::fs::read(&good).expect("read");
    let cut = d.join("cut.npz");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).expect("write");
    let e = HeadModel::load(&cut).expect_err("truncated").to_string();
    assert!(e.contains("cut.npz"), "{e}");
    let e = HeadModel::load(&d.join("absent.npz"))
        .expect_err("absent")
        .to_string();
    assert!(e.contains("absent.npz"), "{e}");
}

#[test]
fn non_finite_parameters_name_the_file_and_field() {
    let dir = std::env::temp_dir().join(format!("texavatars-nan-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let p = dir.join("00000.npz");
    let mut pose = HeadPose {
        expr: vec![0.0, f32::NAN],
        ..Default::default()
    };
    let e = pose.save_npz(&p).unwrap_err().to_string();
    assert!(e.contains("expr") && e.contains("00000.npz"), "{e}");
    assert!(!p.exists(), "nothing written");
    // A file written by someone else with an infinite rotation.
    pose.expr = vec![0.0, 0.0];
    pose.save_npz(&p).expect("save");
    texavatars::io::npz::NpzOut::default()
        .floats("translation", &[1, 3], vec![0.0; 3])
        .floats("rotation", &[1, 3], vec![0.0, f32::INFINITY, 0.0])
        .floats("neck_pose", &[1, 3], vec![0.0; 3])
        .floats("jaw_pose", &[1, 3], vec![0.0; 3])
        .floats("eyes_pose", &[1, 6], vec![0.0; 6])
        .floats("expr", &[1, 2], vec![0.0; 2])
        .floats("shape", &[0], vec![])
        .write(&p)
        .expect("write");
    let e = HeadPose::load_npz(&p).unwrap_err().to_string();
    assert!(e.contains("rotation") && e.contains("00000.npz"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn non_finite_model_arrays_are_rejected() {
    let mut m = tiny();
    m.v_template[1][2] = f32::NAN;
    let e = m.validate("m.npz").unwrap_err().to_string();
    assert!(e.contains("m.npz") && e.contains("v_template"), "{e}");
    let mut m = tiny();
    m.weights[0] = f32::INFINITY;
    let e = m.validate("m.npz").unwrap_err().to_string();
    assert!(e.contains("weights"), "{e}");
}
