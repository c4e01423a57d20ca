//! Standard 3D Gaussian splatting PLY files (the INRIA layout).
//!
//! One `vertex` element with float properties `x y z`, `f_dc_0..2`, `f_rest_*` (0, 9, 24 or 45
//! of them for SH degree 0-3, stored channel-major: all R coefficients, then G, then B),
//! `opacity` (logit), `scale_0..2` (log), `rot_0..3` (quaternion w, x, y, z, not normalised).
//! Other properties (`nx ny nz`, ...) are ignored. Binary little-endian and ASCII bodies are
//! read; files are written binary little-endian.
//!
//! A file with a `binding_*` property is refused: it is a GaussianAvatars avatar, whose
//! Gaussians are stored local to the FLAME triangle each is bound to, not a world-space scene.

use std::io::Write;
use std::path::Path;

use crate::error::{Error, Result};

/// Gaussians as stored in a 3DGS PLY (host memory, row-major).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyGaussians {
    /// [N, 3]
    pub means: Vec<f32>,
    /// [N, K, 3] SH coefficients, K = (degree + 1)^2, coefficient-major per Gaussian.
    pub sh: Vec<f32>,
    /// SH degree (0..=3).
    pub sh_degree: usize,
    /// `[N]` opacity logits.
    pub opacity_logits: Vec<f32>,
    /// [N, 3] log scales.
    pub log_scales: Vec<f32>,
    /// [N, 4] quaternions (w, x, y, z), as stored.
    pub quats: Vec<f32>,
}

impl PlyGaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    /// SH coefficients per channel, K.
    pub fn sh_coeffs(&self) -> usize {
        (self.sh_degree + 1) * (self.sh_degree + 1)
    }

    /// Raises the SH degree to `degree` (at most 3), the new coefficients zero: the same
    /// colours, for loaders that insist on a degree (many want 3, i.e. 45 `f_rest_*`).
    /// Fails on a degree above 3 or below the current one (which would drop coefficients).
    pub fn pad_sh_degree(&mut self, degree: usize) -> Result<()> {
        if degree > 3 || degree < self.sh_degree {
            return Err(Error::invalid(
                "gaussians",
                "sh_degree",
                format!(
                    "cannot pad SH degree {} to {degree} (0..=3, not below the current one)",
                    self.sh_degree
                ),
            ));
        }
        let (k, k_new) = (self.sh_coeffs(), (degree + 1) * (degree + 1));
        if k_new > k {
            let mut sh = Vec::with_capacity(3 * k_new * self.len());
            for g in self.sh.chunks(3 * k) {
                sh.extend_from_slice(g);
                sh.resize(sh.len() + 3 * (k_new - k), 0.0);
            }
            self.sh = sh;
        }
        self.sh_degree = degree;
        Ok(())
    }

    /// Opacities after the sigmoid.
    pub fn opacities(&self) -> Vec<f32> {
        self.opacity_logits
            .iter()
            .map(|&l| 1.0 / (1.0 + (-l).exp()))
            .collect()
    }

    /// World covariances [N, 6] (xx, xy, xz, yy, yz, zz) from the normalised quaternion and
    /// the exponentiated scales: `R diag(s)^2 R^T`. A zero quaternion gives the identity
    /// rotation.
    pub fn cov6(&self) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.len() * 6);
        for i in 0..self.len() {
            let q = &self.quats[4 * i..4 * i + 4];
            let s = &self.log_scales[3 * i..3 * i + 3];
            out.extend_from_slice(&cov6_from_quat_scale(
                [q[0], q[1], q[2], q[3]],
                [s[0].exp(), s[1].exp(), s[2].exp()],
            ));
        }
        out
    }
}

/// `R(q) diag(s)^2 R(q)^T` as (xx, xy, xz, yy, yz, zz); `q` = (w, x, y, z), normalised here.
pub fn cov6_from_quat_scale(q: [f32; 4], s: [f32; 3]) -> [f32; 6] {
    let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let [w, x, y, z] = if norm > 0.0 && norm.is_finite() {
        q.map(|v| v / norm)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    };
    let r = crate::lift::transform::rotation(&[w, x, y, z]);
    let s2 = [s[0] * s[0], s[1] * s[1], s[2] * s[2]];
    let e = |i: usize, j: usize| (0..3).map(|k| r[i][k] * s2[k] * r[j][k]).sum::<f32>();
    [e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2)]
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Format {
    Ascii,
    BinaryLe,
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    size: usize,
    kind: ScalarKind,
}

#[derive(Clone, Copy, Debug)]
enum ScalarKind {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarKind {
    fn parse(s: &str) -> Option<(Self, usize)> {
        Some(match s {
            "char" | "int8" => (Self::I8, 1),
            "uchar" | "uint8" => (Self::U8, 1),
            "short" | "int16" => (Self::I16, 2),
            "ushort" | "uint16" => (Self::U16, 2),
            "int" | "int32" => (Self::I32, 4),
            "uint" | "uint32" => (Self::U32, 4),
            "float" | "float32" => (Self::F32, 4),
            "double" | "float64" => (Self::F64, 8),
            _ => return None,
        })
    }

    fn read(self, b: &[u8]) -> f32 {
        match self {
            Self::I8 => b[0] as i8 as f32,
            Self::U8 => b[0] as f32,
            Self::I16 => i16::from_le_bytes([b[0], b[1]]) as f32,
            Self::U16 => u16::from_le_bytes([b[0], b[1]]) as f32,
            Self::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Self::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Self::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            Self::F64 => {
                f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
            }
        }
    }
}

/// Reads a 3DGS PLY file.
pub fn read(path: &Path) -> Result<PlyGaussians> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse(&bytes, &path.display().to_string())
}

/// Parses a 3DGS PLY from memory; `what` names the source in errors.
pub fn parse(bytes: &[u8], what: &str) -> Result<PlyGaussians> {
    Ok(parse_any(bytes, what, false)?.0)
}

/// Reads a GaussianAvatars `point_cloud.ply`: the Gaussians as stored (local to their
/// triangles) and `binding_0`, each Gaussian's triangle. GaussianAvatars' `save_ply`
/// (`scene/gaussian_model.py`, `construct_list_of_attributes`) writes every property,
/// the binding included, as `float`; an index that is negative, fractional or not finite
/// is an error naming the vertex.
pub fn read_bound(path: &Path) -> Result<(PlyGaussians, Vec<u32>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let what = path.display().to_string();
    match parse_any(&bytes, &what, true)? {
        (g, Some(b)) => Ok((g, b)),
        (_, None) => Err(Error::invalid(
            what,
            "binding_0",
            "missing: a GaussianAvatars point_cloud.ply binds every Gaussian to a FLAME \
             triangle; this is a world-space 3DGS scene",
        )),
    }
}

/// [`parse`]; with `bound`, a `binding_0` property is read (GaussianAvatars) instead of
/// refused.
fn parse_any(bytes: &[u8], what: &str, bound: bool) -> Result<(PlyGaussians, Option<Vec<u32>>)> {
    let err = |field: &str, why: String| Error::invalid(what, field, why);
    let end_marker = b"end_header";
    let header_end = bytes
        .windows(end_marker.len())
        .position(|w| w == end_marker)
        .ok_or_else(|| err("header", "no `end_header` line".into()))?;
    let mut body_start = header_end + end_marker.len();
    if bytes.get(body_start) == Some(&b'\r') {
        body_start += 1;
    }
    if bytes.get(body_start) == Some(&b'\n') {
        body_start += 1;
    }
    let header = std::str::from_utf8(&bytes[..header_end])
        .map_err(|_| err("header", "not valid text".into()))?;
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err(err("magic", "file does not start with `ply`".into()));
    }
    let mut format = None;
    let mut count = None;
    let mut props: Vec<Property> = Vec::new();
    let mut in_vertex = false;
    let mut elements_before_vertex = false;
    for line in lines {
        let tok: Vec<&str> = line.split_whitespace().collect();
        match tok.as_slice() {
            ["format", "ascii", _] => format = Some(Format::Ascii),
            ["format", "binary_little_endian", _] => format = Some(Format::BinaryLe),
            ["format", other, ..] => {
                return Err(err("format", format!("unsupported format `{other}`")));
            }
            ["element", name, n] => {
                in_vertex = *name == "vertex";
                if in_vertex {
                    count = Some(
                        n.parse::<usize>()
                            .map_err(|_| err("element vertex", format!("bad count `{n}`")))?,
                    );
                } else if count.is_none() {
                    elements_before_vertex = true;
                }
            }
            ["property", "list", ..] if in_vertex => {
                return Err(err("property", "list properties are not supported".into()));
            }
            ["property", ty, name] if in_vertex => {
                let (kind, size) = ScalarKind::parse(ty)
                    .ok_or_else(|| err(name, format!("unknown property type `{ty}`")))?;
                props.push(Property {
                    name: name.to_string(),
                    size,
                    kind,
                });
            }
            _ => {}
        }
    }
    if elements_before_vertex {
        return Err(err("element", "the vertex element must come first".into()));
    }
    if let Some(p) = props
        .iter()
        .find(|p| p.name.starts_with("binding_"))
        .filter(|_| !bound)
    {
        return Err(err(
            &p.name,
            "this is a GaussianAvatars avatar (`point_cloud.ply`): each Gaussian's position, \
             rotation and scale are local to the FLAME triangle it is bound to, and placing \
             them needs the tracked mesh (`flame_param.npz`); it is not a world-space 3DGS \
             scene. Drive it with `texavatars render --checkpoint FOLDER --motion \
             FOLDER/flame_param.npz --head FLAME_WITH_TEETH.npz`"
                .into(),
        ));
    }
    let format = format.ok_or_else(|| err("format", "missing".into()))?;
    let n = count.ok_or_else(|| err("element vertex", "missing".into()))?;
    let index = |name: &str| props.iter().position(|p| p.name == name);
    let need = |name: &str| index(name).ok_or_else(|| err(name, "missing property".into()));
    let xyz = [need("x")?, need("y")?, need("z")?];
    let dc = [need("f_dc_0")?, need("f_dc_1")?, need("f_dc_2")?];
    let opacity = need("opacity")?;
    let scales = [need("scale_0")?, need("scale_1")?, need("scale_2")?];
    let rots = [
        need("rot_0")?,
        need("rot_1")?,
        need("rot_2")?,
        need("rot_3")?,
    ];
    let binding = if bound { index("binding_0") } else { None };
    if let Some(p) = props
        .iter()
        .find(|p| p.name.starts_with("binding_") && p.name != "binding_0")
        .filter(|_| bound)
    {
        return Err(err(
            &p.name,
            "GaussianAvatars binds each Gaussian to one triangle (`binding_0` only)".into(),
        ));
    }
    let mut rest = Vec::new();
    while let Some(i) = index(&format!("f_rest_{}", rest.len())) {
        rest.push(i);
    }
    let sh_degree = match rest.len() {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        r => {
            return Err(err(
                "f_rest_*",
                format!("{r} coefficients; expected 0, 9, 24 or 45 (SH degree 0-3)"),
            ));
        }
    };
    let rows = read_rows(&bytes[body_start..], format, &props, n, &err)?;
    let k = (sh_degree + 1) * (sh_degree + 1);
    let mut g = PlyGaussians {
        sh_degree,
        means: Vec::with_capacity(3 * n),
        sh: Vec::with_capacity(3 * k * n),
        opacity_logits: Vec::with_capacity(n),
        log_scales: Vec::with_capacity(3 * n),
        quats: Vec::with_capacity(4 * n),
    };
    let per = k - 1;
    let mut faces = binding.map(|_| Vec::with_capacity(n));
    for (r, row) in rows.chunks(props.len().max(1)).enumerate() {
        if let (Some(i), Some(faces)) = (binding, faces.as_mut()) {
            let f = row[i];
            if !(f.is_finite() && f >= 0.0 && f.fract() == 0.0 && f < u32::MAX as f32) {
                return Err(err(
                    "binding_0",
                    format!("vertex {r}: {f} is not a triangle index"),
                ));
            }
            faces.push(f as u32);
        }
        g.means.extend(xyz.map(|i| row[i]));
        g.sh.extend(dc.map(|i| row[i]));
        for coeff in 0..per {
            for ch in 0..3 {
                g.sh.push(row[rest[ch * per + coeff]]);
            }
        }
        g.opacity_logits.push(row[opacity]);
        g.log_scales.extend(scales.map(|i| row[i]));
        g.quats.extend(rots.map(|i| row[i]));
    }
    Ok((g, faces))
}

fn read_rows(
    body: &[u8],
    format: Format,
    props: &[Property],
    n: usize,
    err: &dyn Fn(&str, String) -> Error,
) -> Result<Vec<f32>> {
    let np = props.len();
    // Every value takes at least one byte of the body (binary: its size; ASCII: one
    // character), so a count the body cannot hold is refused before anything is allocated.
    let stride: usize = match format {
        Format::BinaryLe => props.iter().map(|p| p.size).sum(),
        Format::Ascii => np,
    };
    let need = stride.checked_mul(n).ok_or_else(|| {
        err(
            "element vertex",
            format!("count {n} is too large for any file"),
        )
    })?;
    if body.len() < need {
        return Err(err(
            "body",
            format!(
                "truncated: {n} vertices need at least {need} bytes, found {}",
                body.len()
            ),
        ));
    }
    let mut out = Vec::with_capacity(n * np);
    match format {
        Format::BinaryLe => {
            for r in 0..n {
                let mut off = r * stride;
                for p in props {
                    out.push(p.kind.read(&body[off..off + p.size]));
                    off += p.size;
                }
            }
        }
        Format::Ascii => {
            let text = std::str::from_utf8(body).map_err(|_| err("body", "not text".into()))?;
            let mut values = text.split_whitespace();
            for r in 0..n {
                for p in props {
                    let tok = values.next().ok_or_else(|| {
                        err(
                            "body",
                            format!("truncated at vertex {r}, property {}", p.name),
                        )
                    })?;
                    let v: f32 = tok.parse().map_err(|_| {
                        err(&p.name, format!("vertex {r}: `{tok}` is not a number"))
                    })?;
                    out.push(v);
                }
            }
        }
    }
    Ok(out)
}

/// Writes Gaussians as a binary little-endian 3DGS PLY (with `nx ny nz` = 0 as the INRIA
/// code does, so every viewer accepts it). The file is written to a temporary name first and
/// renamed, so an existing file is never left half-written.
pub fn write(path: &Path, g: &PlyGaussians) -> Result<()> {
    write_any(path, g, None)
}

/// Writes a GaussianAvatars `point_cloud.ply`: [`write()`]'s layout followed by `binding_0`,
/// each Gaussian's triangle, as a `float` (GaussianAvatars' `save_ply` writes every
/// attribute as numpy `f4`, `construct_list_of_attributes` appends `binding_0` last).
pub fn write_bound(path: &Path, g: &PlyGaussians, binding: &[u32]) -> Result<()> {
    if binding.len() != g.len() {
        return Err(Error::invalid(
            path.display().to_string(),
            "binding_0",
            format!("{} bindings for {} Gaussians", binding.len(), g.len()),
        ));
    }
    write_any(path, g, Some(binding))
}

fn write_any(path: &Path, g: &PlyGaussians, binding: Option<&[u32]>) -> Result<()> {
    let bytes = encode(g, binding);
    let tmp = path.with_extension("ply.partial");
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    f.write_all(&bytes)
        .and_then(|_| f.sync_all())
        .map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// The bytes [`write()`] puts in a file (e.g. for a download in `texavatars view`).
pub fn to_bytes(g: &PlyGaussians) -> Vec<u8> {
    encode(g, None)
}

fn encode(g: &PlyGaussians, binding: Option<&[u32]>) -> Vec<u8> {
    let n = g.len();
    let k = g.sh_coeffs();
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    header.push_str(&format!("element vertex {n}\n"));
    let mut names: Vec<String> = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    names.extend((0..3 * (k - 1)).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    if binding.is_some() {
        names.push("binding_0".into());
    }
    for name in &names {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    let mut body = Vec::with_capacity(n * names.len() * 4);
    let mut put = |v: f32| body.extend_from_slice(&v.to_le_bytes());
    for i in 0..n {
        g.means[3 * i..3 * i + 3].iter().for_each(|&v| put(v));
        (0..3).for_each(|_| put(0.0));
        let sh = &g.sh[3 * k * i..3 * k * (i + 1)];
        (0..3).for_each(|ch| put(sh[ch]));
        for ch in 0..3 {
            for coeff in 1..k {
                put(sh[3 * coeff + ch]);
            }
        }
        put(g.opacity_logits[i]);
        g.log_scales[3 * i..3 * i + 3].iter().for_each(|&v| put(v));
        g.quats[4 * i..4 * i + 4].iter().for_each(|&v| put(v));
        if let Some(b) = binding {
            put(b[i] as f32);
        }
    }
    let mut bytes = header.into_bytes();
    bytes.extend_from_slice(&body);
    bytes
}

/// Test helper: the property names and the rows of a binary little-endian PLY whose vertex
/// properties are all `float` (what [`write`] produces), read without [`parse`].
#[cfg(test)]
pub(crate) fn raw_float_rows(bytes: &[u8]) -> (Vec<String>, Vec<Vec<f32>>) {
    let h = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap();
    let header = std::str::from_utf8(&bytes[..h]).unwrap();
    let mut n = 0;
    let mut names = Vec::new();
    for line in header.lines() {
        let tok: Vec<&str> = line.split_whitespace().collect();
        match tok.as_slice() {
            ["element", "vertex", c] => n = c.parse().unwrap(),
            ["property", "float", name] => names.push(name.to_string()),
            ["property", ..] => panic!("not a float property: {line}"),
            _ => {}
        }
    }
    let body = &bytes[h + 11..];
    assert_eq!(body.len(), 4 * n * names.len());
    let values: Vec<f32> = body
        .chunks(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let rows = values.chunks(names.len()).map(<[f32]>::to_vec).collect();
    (names, rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(degree: usize) -> PlyGaussians {
        let k = (degree + 1) * (degree + 1);
        let n = 3;
        PlyGaussians {
            means: (0..3 * n).map(|i| i as f32 * 0.1).collect(),
            sh: (0..3 * k * n).map(|i| (i as f32 * 0.37).sin()).collect(),
            sh_degree: degree,
            opacity_logits: vec![0.5, -1.0, 2.0],
            log_scales: (0..3 * n).map(|i| -(i as f32) * 0.2).collect(),
            quats: vec![1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0],
        }
    }

    #[test]
    fn write_read_round_trip_all_degrees() {
        let dir = std::env::temp_dir().join(format!("texavatars-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for d in 0..=3 {
            let g = sample(d);
            let p = dir.join(format!("g{d}.ply"));
            write(&p, &g).unwrap();
            assert_eq!(read(&p).unwrap(), g);
        }
    }

    #[test]
    fn ascii_body_is_read() {
        let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
            property float z\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n\
            property float opacity\nproperty float scale_0\nproperty float scale_1\n\
            property float scale_2\nproperty float rot_0\nproperty float rot_1\n\
            property float rot_2\nproperty float rot_3\nend_header\n1 2 3 0.1 0.2 0.3 0 0 0 0 1 0 0 0\n";
        let g = parse(text.as_bytes(), "t.ply").unwrap();
        assert_eq!(g.means, vec![1.0, 2.0, 3.0]);
        assert_eq!(g.sh, vec![0.1, 0.2, 0.3]);
        assert_eq!(g.opacities(), vec![0.5]);
    }

    #[test]
    fn malformed_files_name_the_field() {
        let dir = std::env::temp_dir().join(format!("texavatars-plybad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("g.ply");
        write(&p, &sample(1)).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let e = parse(&bytes[..bytes.len() - 10], "g.ply")
            .unwrap_err()
            .to_string();
        assert!(e.contains("g.ply") && e.contains("truncated"), "{e}");
        let h = bytes.windows(10).position(|w| w == b"end_header").unwrap();
        let text = String::from_utf8_lossy(&bytes[..h])
            .replace("property float opacity", "property float opacityX");
        let mut b2 = text.into_bytes();
        b2.extend_from_slice(&bytes[h..]);
        let e = parse(&b2, "g.ply").unwrap_err().to_string();
        assert!(e.contains("opacity"), "{e}");
        let e = parse(b"not a ply", "x.ply").unwrap_err().to_string();
        assert!(e.contains("x.ply"), "{e}");
        let e = read(&dir.join("absent.ply")).unwrap_err().to_string();
        assert!(e.contains("absent.ply"), "{e}");
    }

    /// GaussianAvatars' `scene/gaussian_model.py`, `GaussianModel.construct_list_of_attributes`
    /// and `save_ply`: the 3DGS attributes (here SH degree 0, so no `f_rest_*`) followed by
    /// `binding_0` (the FLAME triangle of each Gaussian) when `self.binding` is set, every
    /// attribute written as `f4`, i.e. `property float`. `FlameGaussianModel.save_ply`
    /// (`scene/flame_gaussian_model.py`) puts `flame_param.npz` next to it.
    #[test]
    fn gaussian_avatars_ply_is_refused() {
        let names = [
            "x",
            "y",
            "z",
            "nx",
            "ny",
            "nz",
            "f_dc_0",
            "f_dc_1",
            "f_dc_2",
            "opacity",
            "scale_0",
            "scale_1",
            "scale_2",
            "rot_0",
            "rot_1",
            "rot_2",
            "rot_3",
            "binding_0",
        ];
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\n".to_vec();
        for name in names {
            bytes.extend_from_slice(format!("property float {name}\n").as_bytes());
        }
        bytes.extend_from_slice(b"end_header\n");
        for face in [0.0f32, 7.0] {
            for (j, name) in names.iter().enumerate() {
                let v = match *name {
                    "binding_0" => face,
                    "rot_0" => 1.0,
                    _ => j as f32 * 0.01,
                };
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        let dir = std::env::temp_dir().join(format!("texavatars-plyga-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("point_cloud.ply");
        std::fs::write(&p, &bytes).unwrap();
        let e = read(&p).unwrap_err().to_string();
        for needle in [
            "point_cloud.ply",
            "binding_0",
            "GaussianAvatars",
            "FLAME",
            "world-space",
        ] {
            assert!(e.contains(needle), "`{needle}` not in: {e}");
        }
        // The same file without the binding is a plain (world-space) 3DGS scene.
        let plain = String::from_utf8_lossy(&bytes[..bytes.len() - 2 * 4 * names.len()])
            .replace("property float binding_0\n", "");
        let mut plain = plain.into_bytes();
        for _ in 0..2 {
            for (j, name) in names[..names.len() - 1].iter().enumerate() {
                let v = if *name == "rot_0" {
                    1.0
                } else {
                    j as f32 * 0.01
                };
                plain.extend_from_slice(&v.to_le_bytes());
            }
        }
        assert_eq!(parse(&plain, "plain.ply").unwrap().len(), 2);
        // Read as what it is: the Gaussians as stored and each one's triangle.
        let (g, faces) = read_bound(&p).unwrap();
        assert_eq!(faces, vec![0, 7]);
        assert_eq!((g.len(), g.sh_degree), (2, 0));
        // Written as `j as f32 * 0.01` for property j.
        assert_eq!(g.means[..3], [0.0, 0.01, 2.0 * 0.01]);
        assert_eq!(g.quats[..4], [1.0, 14.0 * 0.01, 15.0 * 0.01, 16.0 * 0.01]);
        // A binding that is no triangle index names the vertex; a plain scene has none.
        let at = bytes.len() - 4;
        for bad in [-1.0f32, 2.5, f32::NAN] {
            let mut b = bytes.clone();
            b[at..].copy_from_slice(&bad.to_le_bytes());
            std::fs::write(&p, &b).unwrap();
            let e = read_bound(&p).unwrap_err().to_string();
            assert!(e.contains("binding_0") && e.contains("vertex 1"), "{e}");
        }
        std::fs::write(&p, &plain).unwrap();
        let e = read_bound(&p).unwrap_err().to_string();
        assert!(e.contains("binding_0") && e.contains("missing"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A vertex count the body cannot hold is an error naming the file, never a panic or a
    /// huge allocation ("capacity overflow").
    #[test]
    fn huge_vertex_counts_are_errors() {
        let props = "property float x\nproperty float y\nproperty float z\n\
            property float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n\
            property float opacity\nproperty float scale_0\nproperty float scale_1\n\
            property float scale_2\nproperty float rot_0\nproperty float rot_1\n\
            property float rot_2\nproperty float rot_3\n";
        let counts = [
            u64::MAX.to_string(),
            (1u64 << 62).to_string(),
            (1u64 << 58).to_string(),
            "1000000".into(),
            "99999999999999999999999".into(),
        ];
        for format in ["binary_little_endian", "ascii"] {
            for n in &counts {
                let text = format!(
                    "ply\nformat {format} 1.0\nelement vertex {n}\n{props}end_header\n\
                     1 2 3 0.1 0.2 0.3 0 0 0 0 1 0 0 0\n"
                );
                let e = parse(text.as_bytes(), "big.ply").unwrap_err().to_string();
                assert!(
                    e.contains("big.ply") && (e.contains("vertex") || e.contains("truncated")),
                    "{format} {n}: {e}"
                );
            }
        }
    }

    /// 3DGS's `GaussianModel.save_ply` (the same in GaussianAvatars' `scene/gaussian_model.py`)
    /// writes `f_rest` as `_features_rest.transpose(1, 2).flatten(start_dim=1)` with
    /// `_features_rest` of shape [N, K - 1, 3]: channel-major, all R coefficients, then G,
    /// then B.
    #[test]
    fn f_rest_is_channel_major_like_inria_save_ply() {
        let dir = std::env::temp_dir().join(format!("texavatars-plycm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let g = sample(2);
        let p = dir.join("g.ply");
        write(&p, &g).unwrap();
        let (names, rows) = raw_float_rows(&std::fs::read(&p).unwrap());
        let col = |name: &str| names.iter().position(|n| n == name).unwrap();
        assert_eq!(col("f_rest_0"), col("f_dc_2") + 1);
        assert_eq!(col("opacity"), col("f_rest_23") + 1);
        let k = 9;
        for (i, row) in rows.iter().enumerate() {
            let sh = &g.sh[3 * k * i..3 * k * (i + 1)];
            for ch in 0..3 {
                assert_eq!(row[col(&format!("f_dc_{ch}"))], sh[ch]);
                for coeff in 1..k {
                    let j = ch * (k - 1) + coeff - 1;
                    assert_eq!(row[col(&format!("f_rest_{j}"))], sh[3 * coeff + ch]);
                }
            }
        }
    }

    #[test]
    fn padding_keeps_coefficients_and_adds_zeros() {
        let g1 = sample(1);
        let mut g = g1.clone();
        g.pad_sh_degree(3).unwrap();
        assert_eq!((g.sh_degree, g.sh_coeffs()), (3, 16));
        assert_eq!(g.sh.len(), 3 * 16 * g.len());
        for i in 0..g.len() {
            assert_eq!(&g.sh[48 * i..48 * i + 12], &g1.sh[12 * i..12 * i + 12]);
            assert!(g.sh[48 * i + 12..48 * (i + 1)].iter().all(|&v| v == 0.0));
        }
        assert_eq!((&g.means, &g.quats), (&g1.means, &g1.quats));
        let mut same = g1.clone();
        same.pad_sh_degree(1).unwrap();
        assert_eq!(same, g1);
        assert!(g.clone().pad_sh_degree(4).is_err());
        assert!(g.pad_sh_degree(2).is_err());
    }

    #[test]
    fn covariance_of_rotated_scales() {
        // 90 degrees about z swaps the x and y variances.
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let c = cov6_from_quat_scale([h, 0.0, 0.0, h], [1.0, 2.0, 3.0]);
        let want = [4.0, 0.0, 0.0, 1.0, 0.0, 9.0];
        for (a, b) in c.iter().zip(want) {
            assert!((a - b).abs() < 1e-5, "{c:?}");
        }
    }
}
