//! Up-front checks of a dataset split, so that a run fails in seconds instead of hours in.
//!
//! Two checks, both reporting every problem at once rather than the first:
//! - [`check_paths`]: every file a `transforms_*.json` names stays inside the dataset root,
//!   unless the user allows otherwise ([`PathPolicy::Anywhere`]). The root is the JSON's
//!   folder; a path may also lead into a *sibling* folder that holds a `transforms.json`,
//!   because that is how VHAP combines sequences: `vhap/combine_nerf_datasets.py`
//!   (`NeRFDatasetAssembler.combine_dbs`) writes `frame['file_path'] = str(Path('..') /
//!   Path(src_folder.name) / frame['file_path'])` and asserts that every source folder has a
//!   `transforms.json` and shares the target folder's parent. `../../etc/passwd` is refused.
//! - [`HeadDataset::check_files`]: every frame's image and mask exist and their PNG headers
//!   give the frame's `w` x `h`, and every timestep's FLAME parameters (and eta side file)
//!   read, have the model's shapes and pose the model. Headers only: pixels are decoded when
//!   a frame is trained on (the training loader stops with a checkpoint if one cannot be).

use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

use crate::data::dataset::HeadDataset;
use crate::data::vhap::VhapFrame;
use crate::error::{Error, Result};

/// Where the files of a dataset may live.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PathPolicy {
    /// Inside the dataset root or a sibling VHAP export (see the module docs); the default.
    #[default]
    InsideRoot,
    /// Anywhere (`--allow-outside-paths`).
    Anywhere,
}

/// One problem found by a check.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Problem {
    /// The field at fault, e.g. `frames[12].file_path`.
    pub field: String,
    /// What is wrong.
    pub why: String,
}

/// At most this many problems are listed in an error; the rest are counted. A broken export
/// tends to have the same problem on thousands of frames.
pub const LISTED_PROBLEMS: usize = 20;

/// One error for every problem of `what` (`None` when there is none): the first
/// [`LISTED_PROBLEMS`] each on a line, then how many more there are.
pub fn report(what: &str, problems: &[Problem]) -> Option<Error> {
    if problems.is_empty() {
        return None;
    }
    let mut why = format!("{} problem(s):", problems.len());
    for p in problems.iter().take(LISTED_PROBLEMS) {
        why.push_str(&format!("\n  {}: {}", p.field, p.why));
    }
    if problems.len() > LISTED_PROBLEMS {
        why.push_str(&format!(
            "\n  ... and {} more",
            problems.len() - LISTED_PROBLEMS
        ));
    }
    Some(Error::invalid(what, "frames", why))
}

/// `path` made absolute and without `.` or `..`, following symbolic links where the path
/// exists (so a link out of the root counts as outside).
fn resolve(path: &Path) -> PathBuf {
    if let Ok(p) = path.canonicalize() {
        return p;
    }
    let abs = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(path)
    };
    // Canonicalise the longest existing ancestor, then apply the rest lexically.
    let mut out = PathBuf::new();
    for c in abs.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            c => {
                out.push(c);
                if let Ok(p) = out.canonicalize() {
                    out = p;
                }
            }
        }
    }
    out
}

/// Whether `file` (resolved) may be read for a dataset rooted at `root` (resolved): inside
/// it, or inside a sibling folder holding a `transforms.json` (a VHAP export).
fn allowed(root: &Path, file: &Path) -> bool {
    if file.starts_with(root) {
        return true;
    }
    let Some(parent) = root.parent() else {
        return false;
    };
    let Ok(rest) = file.strip_prefix(parent) else {
        return false;
    };
    let mut parts = rest.components();
    match (parts.next(), parts.next()) {
        (Some(Component::Normal(sibling)), Some(_)) => {
            parent.join(sibling).join("transforms.json").is_file()
        }
        _ => false,
    }
}

/// The problems of `frames` (read from `transforms`) under `policy`: every file named that
/// lies outside the dataset root (see the module docs).
pub fn check_paths(transforms: &Path, frames: &[VhapFrame], policy: PathPolicy) -> Vec<Problem> {
    if policy == PathPolicy::Anywhere {
        return Vec::new();
    }
    let root = resolve(transforms.parent().unwrap_or(Path::new(".")));
    let mut seen: HashMap<PathBuf, bool> = HashMap::new();
    let mut problems = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        let files = [
            ("file_path", Some(&f.image)),
            ("fg_mask_path", f.mask.as_ref()),
            ("flame_param_path", f.flame_param.as_ref()),
        ];
        for (field, path) in files {
            let Some(path) = path else { continue };
            let ok = *seen
                .entry(path.clone())
                .or_insert_with(|| allowed(&root, &resolve(path)));
            if !ok {
                problems.push(Problem {
                    field: format!("frames[{i}].{field}"),
                    why: format!(
                        "{} resolves to {}, outside the dataset root {} (and not in a sibling \
                         VHAP export); pass --allow-outside-paths to read it anyway",
                        path.display(),
                        resolve(path).display(),
                        root.display()
                    ),
                });
            }
        }
    }
    problems
}

/// What [`HeadDataset::check_files`] looked at.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Checked {
    /// Frames whose image (and mask) headers were read.
    pub frames: usize,
    /// Distinct FLAME parameter files read and posed.
    pub timesteps: usize,
}

impl HeadDataset {
    /// Checks every frame's files before any training (see the module docs); the error lists
    /// every problem found ([`report`]). Fills the per-timestep cache when it is on.
    pub fn check_files(&self) -> Result<Checked> {
        let json = self.transforms_path().display().to_string();
        let mut problems = Vec::new();
        let header = |path: &Path, field: String, w: u32, h: u32, problems: &mut Vec<Problem>| {
            match image::image_dimensions(path) {
                Ok((pw, ph)) if (pw, ph) == (w, h) => {}
                Ok((pw, ph)) => problems.push(Problem {
                    field,
                    why: format!(
                        "{} is {pw}x{ph} pixels, the frame's w x h is {w}x{h}",
                        path.display()
                    ),
                }),
                Err(e) => problems.push(Problem {
                    field,
                    why: format!("{}: {e}", path.display()),
                }),
            }
        };
        let mut timesteps: HashMap<&Path, ()> = HashMap::new();
        for (i, f) in self.frames().iter().enumerate() {
            let (w, h) = (f.camera.width, f.camera.height);
            header(
                &f.image,
                format!("frames[{i}].file_path"),
                w,
                h,
                &mut problems,
            );
            if let Some(mask) = f.mask.as_ref().filter(|m| m.exists()) {
                header(
                    mask,
                    format!("frames[{i}].fg_mask_path"),
                    w,
                    h,
                    &mut problems,
                );
            }
            if let Some(p) = &f.flame_param
                && timesteps.insert(p, ()).is_none()
                && let Err(e) = self.conditioning(i)
            {
                problems.push(Problem {
                    field: format!("frames[{i}].flame_param_path"),
                    why: e.to_string(),
                });
            }
        }
        match report(&json, &problems) {
            Some(e) => Err(e),
            None => Ok(Checked {
                frames: self.len(),
                timesteps: timesteps.len(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parent_dirs_are_resolved_lexically_when_missing() {
        let dir = std::env::temp_dir().join(format!("texavatars-validate-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("root")).unwrap();
        let root = resolve(&dir.join("root"));
        assert!(allowed(&root, &resolve(&dir.join("root/a/../b.png"))));
        assert!(!allowed(
            &root,
            &resolve(&dir.join("root/../../etc/passwd"))
        ));
        // A sibling without transforms.json is outside; with one it is a VHAP export.
        assert!(!allowed(
            &root,
            &resolve(&dir.join("root/../seq/images/0.png"))
        ));
        std::fs::create_dir_all(dir.join("seq")).unwrap();
        std::fs::write(dir.join("seq/transforms.json"), "{}").unwrap();
        assert!(allowed(
            &root,
            &resolve(&dir.join("root/../seq/images/0.png"))
        ));
        // The sibling folder itself (no file inside it) is not.
        assert!(!allowed(&root, &resolve(&dir.join("root/../seq"))));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn reports_list_every_problem_up_to_a_cap() {
        assert!(report("x", &[]).is_none());
        let many: Vec<_> = (0..25)
            .map(|i| Problem {
                field: format!("frames[{i}].file_path"),
                why: "missing".into(),
            })
            .collect();
        let e = report("t.json", &many).unwrap().to_string();
        assert!(e.contains("25 problem(s)"), "{e}");
        assert!(e.contains("frames[0].file_path") && e.contains("frames[19].file_path"));
        assert!(!e.contains("frames[20].file_path"), "{e}");
        assert!(e.contains("and 5 more"), "{e}");
    }
}
