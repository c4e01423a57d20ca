//! Which eta a split has: its side files (`eta/TTTTT.npy`, [`crate::data::vhap::eta_path`]) and, when
//! `texavatars eta` wrote them, where they came from (`eta/source.json`, [`EtaSource`]).
//!
//! `train`, `eval` and `render` report this per split ([`EtaFiles::describe`]), so that a
//! run on a capture without eta says that its networks see zeros (the "w/o eta" condition).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::data::vhap::{VhapFrame, eta_path};
use crate::error::{Error, Result};

/// File name of the provenance record in an `eta/` folder.
pub const SOURCE_FILE: &str = "source.json";

/// What `texavatars eta` records next to the codes it writes (`eta/source.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EtaSource {
    /// How the codes were made: `"image"` (from the capture's images).
    pub kind: String,
    /// The projection file the codes were reduced with, as given.
    pub projection: PathBuf,
    /// FNV-1a 64 of the projection file's bytes, in hex: which projection, whatever its path.
    pub projection_id: String,
    /// The camera indices whose images the codes see, in order.
    pub cameras: Vec<usize>,
    /// The backbone and its taps, e.g. `vgg16 relu2_2+relu3_3+relu4_3`.
    pub network: String,
}

impl EtaSource {
    /// Reads `eta_dir/source.json`, `None` when the folder has none.
    pub fn read(eta_dir: &Path) -> Result<Option<Self>> {
        let path = eta_dir.join(SOURCE_FILE);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| Error::invalid(path.display().to_string(), "json", e.to_string()))
    }
}

/// FNV-1a, 64 bits, of `bytes` as 16 hex digits: the identity of a projection file.
pub fn fnv1a_hex(bytes: &[u8]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bytes {
        h ^= u64::from(*b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    format!("{h:016x}")
}

/// The eta side files of one split: how many of its timesteps have one, and the provenance
/// records of the `eta/` folders involved.
#[derive(Clone, Debug, PartialEq)]
pub struct EtaFiles {
    /// Timesteps (distinct `flame_param` files) of the split.
    pub timesteps: usize,
    /// Of those, the ones with an `eta/TTTTT.npy`.
    pub with_file: usize,
    /// Each `eta/` folder holding at least one of the split's files, with its record
    /// (`None`: files written by something else, e.g. the synthetic benchmark).
    pub folders: BTreeMap<PathBuf, Option<EtaSource>>,
}

impl EtaFiles {
    /// Looks at the eta side files of `frames`' timesteps (nothing is read but
    /// `source.json`).
    pub fn scan(frames: &[VhapFrame]) -> Result<Self> {
        let steps: BTreeSet<&PathBuf> = frames
            .iter()
            .filter_map(|f| f.flame_param.as_ref())
            .collect();
        let mut with_file = 0;
        let mut folders = BTreeMap::new();
        for p in &steps {
            let eta = eta_path(p);
            if eta.exists() {
                with_file += 1;
                let dir = eta.parent().map(Path::to_path_buf).unwrap_or_default();
                if let std::collections::btree_map::Entry::Vacant(e) = folders.entry(dir) {
                    let source = EtaSource::read(e.key())?;
                    e.insert(source);
                }
            }
        }
        Ok(EtaFiles {
            timesteps: steps.len(),
            with_file,
            folders,
        })
    }

    /// The projections the split's image codes were made with (distinct ids).
    pub fn projection_ids(&self) -> BTreeSet<&str> {
        self.folders
            .values()
            .flatten()
            .map(|s| s.projection_id.as_str())
            .collect()
    }

    /// One line for split `name`: where its eta comes from, e.g.
    /// `eta (train): image codes (projection 9c1f…, cameras [7]) for 120 of 120 timesteps`.
    pub fn describe(&self, name: &str) -> String {
        if self.with_file == 0 {
            return format!(
                "eta ({name}): no eta/ files for any of {} timesteps: zeros, the networks see \
                 the \"w/o eta\" condition (texavatars eta computes codes from the images)",
                self.timesteps
            );
        }
        let mut kinds: Vec<String> = Vec::new();
        for source in self.folders.values() {
            let k = match source {
                Some(s) => format!(
                    "{} codes (projection {}, cameras {:?}, {})",
                    s.kind, s.projection_id, s.cameras, s.network
                ),
                None => "side files without eta/source.json".to_string(),
            };
            if !kinds.contains(&k) {
                kinds.push(k);
            }
        }
        let missing = if self.with_file < self.timesteps {
            format!(
                "; {} timesteps have none and get zeros",
                self.timesteps - self.with_file
            )
        } else {
            String::new()
        };
        format!(
            "eta ({name}): {} for {} of {} timesteps{missing}",
            kinds.join(" and "),
            self.with_file,
            self.timesteps
        )
    }

    /// [`EtaFiles::describe`], prefixed `warning: ` when the split has no eta file.
    pub fn line(&self, name: &str) -> String {
        let d = self.describe(name);
        if self.is_missing() {
            format!("warning: {d}")
        } else {
            d
        }
    }

    /// Whether a warning is due: the split has timesteps and none of them has a file.
    pub fn is_missing(&self) -> bool {
        self.timesteps > 0 && self.with_file == 0
    }
}

/// Prints where split `name`'s eta comes from ([`EtaFiles::describe`], one line on stderr,
/// prefixed `warning:` when the split has no eta file at all) and returns the scan.
pub fn announce(frames: &[VhapFrame], name: &str) -> Result<EtaFiles> {
    let files = EtaFiles::scan(frames)?;
    eprintln!("{}", files.line(name));
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(param: &Path) -> VhapFrame {
        VhapFrame {
            timestep: 0,
            camera_index: 0,
            image: PathBuf::from("x.png"),
            mask: None,
            flame_param: Some(param.to_path_buf()),
            camera: crate::camera::Camera::from_fov(4, 4, 40.0, [[0.0; 4]; 4]),
        }
    }

    #[test]
    fn fnv1a_matches_the_published_test_vectors() {
        // FNV-1a 64 test vectors (Fowler, Noll, Vo; IETF draft-eastlake-fnv, appendix).
        assert_eq!(fnv1a_hex(b""), "cbf29ce484222325");
        assert_eq!(fnv1a_hex(b"a"), "af63dc4c8601ec8c");
        assert_eq!(fnv1a_hex(b"foobar"), "85944171f73967e8");
    }

    #[test]
    fn scan_counts_files_and_reads_the_record() {
        let dir = std::env::temp_dir().join(format!("texavatars-eta-scan-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let params: Vec<PathBuf> = (0..3)
            .map(|i| dir.join("seq/flame_param").join(format!("{i:05}.npz")))
            .collect();
        // Two frames of timestep 0 (two cameras), one each of 1 and 2.
        let frames: Vec<VhapFrame> = [0, 0, 1, 2].iter().map(|&i| frame(&params[i])).collect();
        let none = EtaFiles::scan(&frames).expect("scan");
        assert_eq!((none.timesteps, none.with_file), (3, 0));
        assert!(none.is_missing());
        assert!(
            none.describe("val").contains("zeros"),
            "{}",
            none.describe("val")
        );

        let eta_dir = dir.join("seq/eta");
        std::fs::create_dir_all(&eta_dir).expect("mkdir");
        for i in [0, 2] {
            crate::io::npy::write(&eta_path(&params[i]), &[2], &[0.0, 1.0]).expect("write");
        }
        let bare = EtaFiles::scan(&frames).expect("scan");
        assert_eq!((bare.timesteps, bare.with_file), (3, 2));
        assert!(!bare.is_missing());
        let d = bare.describe("train");
        assert!(
            d.contains("without eta/source.json")
                && d.contains("2 of 3")
                && d.contains("1 timesteps have none"),
            "{d}"
        );

        let source = EtaSource {
            kind: "image".into(),
            projection: PathBuf::from("p.safetensors"),
            projection_id: "0123456789abcdef".into(),
            cameras: vec![7],
            network: "vgg16 relu2_2+relu3_3+relu4_3".into(),
        };
        let json = serde_json::to_string(&source).expect("json");
        std::fs::write(eta_dir.join(SOURCE_FILE), json).expect("write");
        let image = EtaFiles::scan(&frames).expect("scan");
        assert_eq!(
            image.projection_ids().into_iter().collect::<Vec<_>>(),
            ["0123456789abcdef"]
        );
        assert!(
            image
                .describe("train")
                .contains("image codes (projection 0123456789abcdef, cameras [7]")
        );

        std::fs::write(eta_dir.join(SOURCE_FILE), "{\"kind\": 3}").expect("write");
        let e = EtaFiles::scan(&frames).expect_err("bad record").to_string();
        assert!(e.contains("source.json"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
