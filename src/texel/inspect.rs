//! Pictures of a UV layout for people: validity, face ids in false colour, kept samples.
//!
//! Images are flipped vertically with respect to the maps (row 0 of a map is `v = 0`, the
//! bottom of the texture; see [`crate::texel::layout`]), so they look like the texture.

use crate::texel::{SampleGrid, UvLayout};

/// An RGB image in [0, 1], row-major from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Picture {
    pub name: &'static str,
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<f32>,
}

/// A stable, well-spread colour per face id.
pub fn false_colour(face: u32) -> [f32; 3] {
    let mut h = (face as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    h ^= h >> 29;
    let c = |shift: u32| 0.25 + 0.75 * ((h >> shift) & 0xff) as f32 / 255.0;
    [c(0), c(8), c(16)]
}

/// Paints an `n x n` map (row 0 = v 0) into a picture (row 0 = top).
fn picture(name: &'static str, n: usize, colour: impl Fn(usize) -> [f32; 3]) -> Picture {
    let mut rgb = Vec::with_capacity(n * n * 3);
    for y in 0..n {
        let j = n - 1 - y;
        for i in 0..n {
            rgb.extend(colour(j * n + i));
        }
    }
    Picture {
        name,
        width: n,
        height: n,
        rgb,
    }
}

/// `validity.png`, `faces.png` (texel resolution) and `samples.png` (sample resolution).
pub fn pictures(layout: &UvLayout, samples: &SampleGrid) -> Vec<Picture> {
    let r = layout.res;
    let mut kept = vec![false; samples.size * samples.size];
    for &k in &samples.grid_index {
        kept[k as usize] = true;
    }
    vec![
        picture("validity.png", r, |t| {
            [f32::from(u8::from(layout.face[t].is_some())); 3]
        }),
        picture("faces.png", r, |t| {
            layout.face[t].map_or([0.0; 3], false_colour)
        }),
        picture("samples.png", samples.size, |k| {
            [f32::from(u8::from(kept[k])); 3]
        }),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::UvMesh;

    /// A triangle in the top-left of UV space (v up) shows at the top-left of the pictures.
    #[test]
    fn pictures_show_v_up() {
        let m = UvMesh {
            uvs: vec![[0.0, 1.0], [0.0, 0.5], [0.5, 1.0]],
            positions: vec![[0.0; 3]; 3],
            faces: vec![[0, 1, 2]],
            uv_faces: vec![[0, 1, 2]],
        };
        let layout = UvLayout::new(&m, 8).expect("layout");
        let samples = SampleGrid::new(&m, &layout, 8).expect("samples");
        let p = pictures(&layout, &samples);
        let v = &p[0];
        let at = |x: usize, y: usize| v.rgb[3 * (y * 8 + x)];
        assert_eq!(at(0, 0), 1.0, "top-left is covered");
        assert_eq!(at(0, 7), 0.0, "bottom-left is not");
        assert_eq!(at(7, 0), 0.0, "top-right is not");
    }
}
