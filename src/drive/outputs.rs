//! The files `render` and `export ply` own in their output folders, and clearing them.
//!
//! A run into a folder that holds an earlier run's output first removes the files of the
//! earlier run that this command writes (by their names, below), so that frames of a longer
//! earlier run are never mixed with the new ones (nor encoded into the new MP4). Anything
//! else in the folder (other files, sub-folders, files of the other command) is left alone.
//!
//! - `render`: `OUT/frames/NNNNN.png`, `OUT/contact_sheet.png`, `OUT/render.gif`,
//!   `OUT/render.mp4`;
//! - `export ply`: `OUT/NNNNN.ply`, `OUT/NNNNN_camera.json`, `OUT/NNNNN_render.png`,
//!   `OUT/NNNNN_render.npy`;
//!
//! with `NNNNN` five or more digits, and for both the temporary files their writes go
//! through (the name with `.partial` appended, or `render.partial.mp4`), which are also
//! removed when a run fails.

use std::path::Path;

use crate::error::Result;
use crate::util::files::clear_matching;

/// Whether `s` is a frame number as the commands write them (`{i:05}`: five or more digits).
fn is_frame_number(s: &str) -> bool {
    s.len() >= 5 && s.bytes().all(|b| b.is_ascii_digit())
}

/// Whether `name` is a temporary file name (`X.partial`, `X.partial.mp4`).
pub fn is_partial(name: &str) -> bool {
    name.ends_with(".partial") || name.ends_with(".partial.mp4")
}

/// `name` without a temporary suffix (`00001.png.partial` -> `00001.png`).
fn finished_name(name: &str) -> &str {
    if let Some(s) = name.strip_suffix(".partial") {
        s
    } else if let Some(s) = name.strip_suffix(".partial.mp4") {
        // `render.mp4` is written as `render.partial.mp4`.
        if s == "render" { "render.mp4" } else { name }
    } else {
        name
    }
}

/// Files of `render` directly in `OUT`.
pub fn render_owns(name: &str) -> bool {
    matches!(
        finished_name(name),
        "contact_sheet.png" | "render.gif" | "render.mp4"
    )
}

/// Files of `render` in `OUT/frames`.
pub fn render_frame_owns(name: &str) -> bool {
    finished_name(name)
        .strip_suffix(".png")
        .is_some_and(is_frame_number)
}

/// Files of `export ply` in `OUT`.
pub fn export_owns(name: &str) -> bool {
    let n = finished_name(name);
    [".ply", "_camera.json", "_render.png", "_render.npy"]
        .iter()
        .any(|suffix| n.strip_suffix(suffix).is_some_and(is_frame_number))
}

/// Removes an earlier `render`'s files from `out` (see the module docs); returns how many.
pub fn clear_render_outputs(out: &Path) -> Result<usize> {
    Ok(clear_matching(out, &render_owns)?
        + clear_matching(&out.join("frames"), &render_frame_owns)?)
}

/// Removes an earlier `export ply`'s files from `out` (see the module docs); returns how
/// many.
pub fn clear_export_outputs(out: &Path) -> Result<usize> {
    clear_matching(out, &export_owns)
}

/// Removes `render`'s temporary files from `out` (after a failure); errors are ignored.
pub fn remove_render_partials(out: &Path) {
    let _ = clear_matching(out, &|n| is_partial(n) && render_owns(n));
    let _ = clear_matching(&out.join("frames"), &|n| {
        is_partial(n) && render_frame_owns(n)
    });
}

/// Removes `export ply`'s temporary files from `out` (after a failure); errors are ignored.
pub fn remove_export_partials(out: &Path) {
    let _ = clear_matching(out, &|n| is_partial(n) && export_owns(n));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_each_command_owns() {
        for n in [
            "contact_sheet.png",
            "render.gif",
            "render.mp4",
            "render.gif.partial",
            "contact_sheet.png.partial",
            "render.partial.mp4",
        ] {
            assert!(render_owns(n), "{n}");
        }
        for n in [
            "notes.txt",
            "render.png",
            "frames",
            "x.partial",
            "other.partial.mp4",
        ] {
            assert!(!render_owns(n), "{n}");
        }
        for n in ["00000.png", "123456.png", "00007.png.partial"] {
            assert!(render_frame_owns(n), "{n}");
        }
        for n in [
            "0000.png",
            "00000.jpg",
            "a0000.png",
            "00000_render.png",
            "00000.png.bak",
        ] {
            assert!(!render_frame_owns(n), "{n}");
        }
        for n in [
            "00000.ply",
            "00012_camera.json",
            "00012_render.png",
            "00012_render.npy",
            "00012.ply.partial",
            "00012_render.npy.partial",
            "100000.ply",
        ] {
            assert!(export_owns(n), "{n}");
        }
        for n in [
            "scene.ply",
            "00012_camera.json.bak",
            "0001.ply",
            "00012.png",
            "keep.json",
        ] {
            assert!(!export_owns(n), "{n}");
        }
        assert!(is_partial("a.partial") && is_partial("render.partial.mp4"));
        assert!(!is_partial("a.png"));
    }
}
