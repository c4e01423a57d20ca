//! OBJ input: positions, UVs and faces with separate position and UV indices.
//!
//! Parsing is done by `tobj` (quads and polygons triangulated as fans). `tobj` renumbers
//! positions in order of first use, but tracked meshes (FLAME and the like) index vertices
//! in file order, so a line-by-line pass over the file records every face corner's original
//! indices; it also reports malformed input with its file and line, which `tobj` cannot.
//! The two readings are checked against each other.
//!
//! [`PolygonMesh`] is the line scan's reading alone, for callers that need the faces as
//! written: polygons before triangulation, each with the group (`g`) it belongs to.

use std::collections::HashMap;
use std::io::BufReader;
use std::path::Path;

use crate::error::{Error, Result};

/// A triangle mesh with a UV layout. Positions and UVs have their own indices per corner.
///
/// # Shapes
/// - `positions`: `[V]` in file order
/// - `uvs`: `[T]` in file order; OBJ convention, `v` points up
/// - `faces`, `uv_faces`: `[F]` corner indices into `positions` and `uvs`
#[derive(Clone, Debug, Default, PartialEq)]
pub struct UvMesh {
    pub positions: Vec<[f32; 3]>,
    pub uvs: Vec<[f32; 2]>,
    pub faces: Vec<[u32; 3]>,
    pub uv_faces: Vec<[u32; 3]>,
}

/// An OBJ file's faces as written: polygons (not triangulated) with their groups.
///
/// Read by the line scan [`UvMesh`] checks `tobj` with, so the same input is accepted and
/// errors name the file and line; every face corner needs a UV index. A file without faces
/// reads as an empty `polygons`.
///
/// # Shapes
/// - `positions`: `[V]` in file order
/// - `uvs`: `[T]` in file order; OBJ convention, `v` points up
/// - `groups`: the group names of the file's `g` lines, each once, in file order
///   (several names on one line are one name, joined by a space); `""` when faces come
///   before any `g` line
/// - `polygons`: `[F]` in file order
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PolygonMesh {
    pub positions: Vec<[f32; 3]>,
    pub uvs: Vec<[f32; 2]>,
    pub groups: Vec<String>,
    pub polygons: Vec<Polygon>,
}

/// One face of a [`PolygonMesh`], as written (three or more corners).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Polygon {
    /// Index into [`PolygonMesh::groups`] of the group the face is in.
    pub group: usize,
    /// Corner indices into [`PolygonMesh::positions`], in file order.
    pub positions: Vec<u32>,
    /// Corner indices into [`PolygonMesh::uvs`], one per corner.
    pub uvs: Vec<u32>,
}

impl PolygonMesh {
    /// Loads an OBJ file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses OBJ text; `name` is used in error messages.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        let scan = scan(text, name)?;
        let polygons = scan
            .polygons
            .into_iter()
            .map(|f| Polygon {
                group: f.group,
                positions: f.corners.iter().map(|c| c.position as u32).collect(),
                uvs: f.corners.iter().map(|c| c.uv as u32).collect(),
            })
            .collect();
        Ok(PolygonMesh {
            positions: scan.positions,
            uvs: scan.uvs,
            groups: scan.groups,
            polygons,
        })
    }

    /// The name of `polygon`'s group.
    pub fn group_of(&self, polygon: &Polygon) -> &str {
        self.groups.get(polygon.group).map_or("", String::as_str)
    }
}

/// One face corner as written in the file.
#[derive(Clone, Copy, Debug)]
struct Corner {
    position: usize,
    uv: usize,
}

impl UvMesh {
    /// Loads an OBJ file. Every face corner needs a UV index (`f p/t ...` or `f p/t/n ...`).
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses OBJ text; `name` is used in error messages.
    pub fn parse(text: &str, name: &str) -> Result<Self> {
        let scan = scan(text, name)?;
        let models = load_tobj(text, name)?;
        let triangles = scan.triangles();

        // tobj's triangles, in file order across its models, must be the scan's triangles.
        let mut tobj_corners = 0usize;
        let mut faces = Vec::with_capacity(triangles.len());
        let mut uv_faces = Vec::with_capacity(triangles.len());
        let mismatch = |why: String| Error::invalid(name, "f", why);
        for m in &models {
            let mesh = &m.mesh;
            if mesh.texcoord_indices.len() != mesh.indices.len() {
                return Err(mismatch("faces without UV indices".into()));
            }
            for (k, (&p, &t)) in mesh.indices.iter().zip(&mesh.texcoord_indices).enumerate() {
                let Some((tri, line)) = triangles.get(tobj_corners / 3) else {
                    return Err(mismatch("tobj read more faces than the file has".into()));
                };
                let c = tri[tobj_corners % 3];
                let (p, t) = (p as usize, t as usize);
                let same_position = mesh.positions.get(3 * p..3 * p + 3).is_some_and(|v| {
                    v.iter()
                        .zip(scan.positions[c.position])
                        .all(|(a, b)| *a == b)
                });
                let same_uv = mesh
                    .texcoords
                    .get(2 * t..2 * t + 2)
                    .is_some_and(|v| v.iter().zip(scan.uvs[c.uv]).all(|(a, b)| *a == b));
                if !same_position || !same_uv {
                    return Err(Error::invalid(
                        format!("{name}:{line}"),
                        "f",
                        format!("tobj and the line scan disagree on corner {}", k % 3 + 1),
                    ));
                }
                tobj_corners += 1;
            }
        }
        if tobj_corners != 3 * triangles.len() {
            return Err(mismatch(format!(
                "tobj read {} triangles, the file has {}",
                tobj_corners / 3,
                triangles.len()
            )));
        }
        for (tri, _) in &triangles {
            faces.push(tri.map(|c| c.position as u32));
            uv_faces.push(tri.map(|c| c.uv as u32));
        }
        if faces.is_empty() {
            return Err(Error::invalid(name, "f", "the mesh has no faces"));
        }
        Ok(UvMesh {
            positions: scan.positions,
            uvs: scan.uvs,
            faces,
            uv_faces,
        })
    }

    /// Writes the mesh as OBJ text (`v`, `vt`, `f p/t`), UVs as stored.
    pub fn to_obj(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        for p in &self.positions {
            let _ = writeln!(s, "v {} {} {}", p[0], p[1], p[2]);
        }
        for t in &self.uvs {
            let _ = writeln!(s, "vt {} {}", t[0], t[1]);
        }
        for (f, t) in self.faces.iter().zip(&self.uv_faces) {
            let _ = writeln!(
                s,
                "f {}/{} {}/{} {}/{}",
                f[0] + 1,
                t[0] + 1,
                f[1] + 1,
                t[1] + 1,
                f[2] + 1,
                t[2] + 1
            );
        }
        s
    }
}

fn load_tobj(text: &str, name: &str) -> Result<Vec<tobj::Model>> {
    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let mut reader = BufReader::new(text.as_bytes());
    let (models, _) = tobj::load_obj_buf(&mut reader, &options, |_| {
        Ok((Vec::new(), Default::default()))
    })
    .map_err(|e| Error::invalid(name, "obj", format!("tobj: {e}")))?;
    Ok(models)
}

/// What the line scan found.
struct Scan {
    positions: Vec<[f32; 3]>,
    uvs: Vec<[f32; 2]>,
    /// Group names (`g`), each once.
    groups: Vec<String>,
    /// Faces as written.
    polygons: Vec<ScannedFace<Corner>>,
}

/// A face of the line scan: its corners, the line it came from and its group.
struct ScannedFace<C> {
    corners: Vec<C>,
    line: usize,
    group: usize,
}

impl Scan {
    /// The faces triangulated as fans, with the line each came from.
    fn triangles(&self) -> Vec<([Corner; 3], usize)> {
        let mut triangles = Vec::new();
        for f in &self.polygons {
            let c = &f.corners;
            for k in 1..c.len() - 1 {
                triangles.push(([c[0], c[k], c[k + 1]], f.line));
            }
        }
        triangles
    }
}

/// Reads `v`, `vt`, `f`, `l` and `g` lines (and counts `vn` lines), checking syntax,
/// finiteness and index ranges of everything tobj reads.
fn scan(text: &str, name: &str) -> Result<Scan> {
    let mut positions = Vec::new();
    let mut uvs = Vec::new();
    let mut groups: Vec<String> = Vec::new();
    let mut group_index: HashMap<String, usize> = HashMap::new();
    // The group of the faces that follow (`None`: before any `g` line).
    let mut group: Option<usize> = None;
    let mut index_of = |name: String, groups: &mut Vec<String>| {
        *group_index.entry(name).or_insert_with_key(|name| {
            groups.push(name.clone());
            groups.len() - 1
        })
    };
    // Corners as written (1-based or negative).
    let mut polygons: Vec<ScannedFace<(i64, i64)>> = Vec::new();
    // Normal indices of faces and the indices of polylines, with their line.
    let mut others: Vec<(Other, i64, usize, &str)> = Vec::new();
    let mut normals = 0usize;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let at = || format!("{name}:{line}");
        let content = raw.split('#').next().unwrap_or("");
        let mut tokens = content.split_whitespace();
        let Some(keyword) = tokens.next() else {
            continue;
        };
        match keyword {
            "v" | "vt" => {
                let need = if keyword == "v" { 3 } else { 2 };
                let values: Vec<&str> = tokens.collect();
                if values.len() < need {
                    return Err(Error::invalid(
                        at(),
                        keyword,
                        format!("needs {need} numbers, found {}", values.len()),
                    ));
                }
                let mut v = [0.0f32; 3];
                for (k, s) in values.iter().take(need).enumerate() {
                    v[k] = match s.parse::<f32>() {
                        Ok(x) if x.is_finite() => x,
                        Ok(_) => {
                            return Err(Error::invalid(
                                at(),
                                keyword,
                                format!("`{s}` is not finite"),
                            ));
                        }
                        Err(_) => {
                            return Err(Error::invalid(
                                at(),
                                keyword,
                                format!("`{s}` is not a number"),
                            ));
                        }
                    };
                }
                if keyword == "v" {
                    positions.push(v);
                } else {
                    uvs.push([v[0], v[1]]);
                }
            }
            "vn" => normals += 1,
            "g" => {
                let name = tokens.collect::<Vec<_>>().join(" ");
                group = Some(index_of(name, &mut groups));
            }
            // tobj reads the indices of polylines too (and makes faces of those with three
            // or more corners): they are checked like the faces' ones.
            "l" => {
                for tok in tokens {
                    for (k, s) in tok.split('/').enumerate() {
                        let (kind, len) = match k {
                            0 => (Other::Position, positions.len()),
                            1 => (Other::Uv, uvs.len()),
                            _ => (Other::Normal, normals),
                        };
                        if k > 0 && s.is_empty() {
                            continue;
                        }
                        let v = parse_index(s, kind.name(), tok, &at)?;
                        others.push((kind, resolve(v, len), line, "l"));
                    }
                }
            }
            "f" => {
                let mut corners = Vec::new();
                for tok in tokens {
                    let mut parts = tok.split('/');
                    let p = parts.next().unwrap_or("");
                    let t = parts.next().unwrap_or("");
                    let p = parse_index(p, "position", tok, &at)?;
                    let t = parse_index(t, "UV", tok, &at)?;
                    // Negative indices count back from the current end.
                    corners.push((resolve(p, positions.len()), resolve(t, uvs.len())));
                    // The normal index is not kept, but tobj reads it (and multiplies it
                    // unchecked): it is checked like the others.
                    if let Some(n) = parts.next().filter(|n| !n.is_empty()) {
                        let n = parse_index(n, "normal", tok, &at)?;
                        others.push((Other::Normal, resolve(n, normals), line, "f"));
                    }
                }
                if corners.len() < 3 {
                    return Err(Error::invalid(
                        at(),
                        "f",
                        format!("a face needs 3 corners, found {}", corners.len()),
                    ));
                }
                let g = match group {
                    Some(g) => g,
                    None => *group.insert(index_of(String::new(), &mut groups)),
                };
                polygons.push(ScannedFace {
                    corners,
                    line,
                    group: g,
                });
            }
            _ => {}
        }
    }
    // As tobj checks them: UVs and normals only when the file has some.
    for (kind, v, line, field) in others {
        let len = match kind {
            Other::Position => positions.len(),
            Other::Uv if uvs.is_empty() => continue,
            Other::Uv => uvs.len(),
            Other::Normal if normals == 0 => continue,
            Other::Normal => normals,
        };
        if v < 1 || v as usize > len {
            return Err(Error::invalid(
                format!("{name}:{line}"),
                field,
                format!(
                    "{} index {v} out of range (the file has {len})",
                    kind.name()
                ),
            ));
        }
    }
    let mut resolved_polygons = Vec::with_capacity(polygons.len());
    for ScannedFace {
        corners,
        line,
        group,
    } in polygons
    {
        let mut resolved = Vec::with_capacity(corners.len());
        for (p, t) in corners {
            let bad = |what: &str, v: i64, len: usize| {
                Error::invalid(
                    format!("{name}:{line}"),
                    "f",
                    format!("{what} index {v} out of range (the file has {len})"),
                )
            };
            if p < 1 || p as usize > positions.len() {
                return Err(bad("position", p, positions.len()));
            }
            if t < 1 || t as usize > uvs.len() {
                return Err(bad("UV", t, uvs.len()));
            }
            resolved.push(Corner {
                position: p as usize - 1,
                uv: t as usize - 1,
            });
        }
        resolved_polygons.push(ScannedFace {
            corners: resolved,
            line,
            group,
        });
    }
    Ok(Scan {
        positions,
        uvs,
        groups,
        polygons: resolved_polygons,
    })
}

/// An index checked besides the faces' positions and UVs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Other {
    Position,
    Uv,
    Normal,
}

impl Other {
    fn name(self) -> &'static str {
        match self {
            Other::Position => "position",
            Other::Uv => "UV",
            Other::Normal => "normal",
        }
    }
}

/// A 1-based or negative OBJ index `s` of corner `tok`; `at` names the file and line.
fn parse_index(s: &str, what: &str, tok: &str, at: &dyn Fn() -> String) -> Result<i64> {
    match s.parse::<i64>() {
        Ok(0) => Err(Error::invalid(
            at(),
            "f",
            format!("{what} index 0 in `{tok}` (OBJ indices start at 1)"),
        )),
        Ok(v) => Ok(v),
        Err(_) if s.is_empty() && what == "UV" => Err(Error::invalid(
            at(),
            "f",
            format!("corner `{tok}` has no UV index (write p/t)"),
        )),
        Err(_) => Err(Error::invalid(
            at(),
            "f",
            format!("bad {what} index in `{tok}`"),
        )),
    }
}

/// A negative index counts back from the current end (`len` elements so far).
fn resolve(v: i64, len: usize) -> i64 {
    if v < 0 { len as i64 + v + 1 } else { v }
}

#[cfg(test)]
mod tests {
    use super::*;

    const QUAD: &str = "# a unit quad, two triangles after triangulation\n\
        v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 5 5 5\n\
        vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n\
        f 3/3 4/4 1/1 2/2\n";

    #[test]
    fn quads_are_triangulated_in_file_order() {
        let m = UvMesh::parse(QUAD, "quad.obj").expect("valid OBJ");
        // The unused vertex 5 keeps its place; tobj alone would drop and renumber.
        assert_eq!(m.positions.len(), 5);
        assert_eq!(m.faces, vec![[2, 3, 0], [2, 0, 1]]);
        assert_eq!(m.uv_faces, vec![[2, 3, 0], [2, 0, 1]]);
        let again = UvMesh::parse(&m.to_obj(), "again.obj").expect("round trip");
        assert_eq!(again.faces, m.faces);
        assert_eq!(again.positions[..4], m.positions[..4]);
    }

    #[test]
    fn malformed_input_names_file_and_line() {
        let cases = [
            ("v 0 0\n", "m.obj:1", "needs 3 numbers"),
            ("v 0 0 nan\n", "m.obj:1", "not finite"),
            ("v 0 0 0\nvt 0 x\n", "m.obj:2", "not a number"),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1 2 3\n",
                "m.obj:5",
                "no UV index",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 4/1\n",
                "m.obj:5",
                "out of range",
            ),
            (
                "v 0 0 0\nv 1 0 0\nvt 0 0\nf 1/1 2/1\n",
                "m.obj:4",
                "3 corners",
            ),
            ("v 0 0 0\n", "m.obj", "no faces"),
        ];
        for (text, at, why) in cases {
            let e = UvMesh::parse(text, "m.obj").expect_err(text).to_string();
            assert!(e.contains(at) && e.contains(why), "{text:?}: {e}");
        }
    }

    /// Polygons keep their corners and groups as written; the same checks as [`UvMesh`].
    #[test]
    fn polygons_keep_their_corners_and_groups() {
        let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 1\n\
            f 1/1 2/1 3/2\ng skin  face # the rest of the line\nf 4/1 3/2 2/2 1/1\n\
            g eye\nf -1/-1 -2/-2 -3/-1\ng skin face\nf 1/1 2/2 4/2\n";
        let m = PolygonMesh::parse(text, "p.obj").expect("valid OBJ");
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.uvs.len(), 2);
        assert_eq!(m.groups, vec!["", "skin face", "eye"]);
        let faces: Vec<(&str, &[u32], &[u32])> = m
            .polygons
            .iter()
            .map(|f| (m.group_of(f), &f.positions[..], &f.uvs[..]))
            .collect();
        assert_eq!(
            faces,
            vec![
                ("", &[0, 1, 2][..], &[0, 0, 1][..]),
                ("skin face", &[3, 2, 1, 0][..], &[0, 1, 1, 0][..]),
                ("eye", &[3, 2, 1][..], &[1, 0, 1][..]),
                ("skin face", &[0, 1, 3][..], &[0, 1, 1][..]),
            ]
        );
        // The triangle mesh of the same text is its fans.
        let t = UvMesh::parse(text, "p.obj").expect("valid OBJ");
        assert_eq!(
            t.faces,
            vec![[0, 1, 2], [3, 2, 1], [3, 1, 0], [3, 2, 1], [0, 1, 3]]
        );
        for (text, why) in [
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 4/1\n",
                "out of range",
            ),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "no UV index"),
        ] {
            let e = PolygonMesh::parse(text, "p.obj")
                .expect_err(text)
                .to_string();
            assert!(e.contains("p.obj:") && e.contains(why), "{text:?}: {e}");
        }
        assert!(PolygonMesh::parse("v 0 0 0\n", "p.obj").is_ok_and(|m| m.polygons.is_empty()));
    }

    /// Normal indices (which tobj multiplies unchecked) and polyline indices are checked.
    #[test]
    fn hostile_normal_and_polyline_indices_are_errors() {
        let head = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n";
        for (tail, why) in [
            ("f 1/1/1 2/1/1 3/1/-9223372036854775808\n", "normal index"),
            ("f 1/1/1 2/1/1 3/1/9223372036854775807\n", "normal index"),
            ("f 1/1/1 2/1/1 3/1/0\n", "normal index 0"),
            ("f 1/1/1 2/1/1 3/1/x\n", "bad normal index"),
            ("l 1/1/1 2/9223372036854775807 3/1\n", "UV index"),
            ("l 1 2 9\n", "position index"),
        ] {
            let text = format!("{head}{tail}");
            let e = UvMesh::parse(&text, "n.obj").expect_err(&text).to_string();
            assert!(e.contains("n.obj:6") && e.contains(why), "{text:?}: {e}");
        }
        // In range, with and without normals in the file.
        let m = UvMesh::parse(&format!("{head}f 1/1/1 2/1/-1 3/1/1\n"), "n.obj").unwrap();
        assert_eq!(m.faces, vec![[0, 1, 2]]);
        let m = UvMesh::parse(
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1/7 2/1/7 3/1/7\n",
            "n.obj",
        );
        assert!(m.is_ok(), "{m:?}");
    }
}
