//! A study's config (`configs/study_*.json`) and the independent runs it makes.
//!
//! ```json
//! {
//!   "subjects": [{ "name": "s0", "synth": 0 }, { "name": "cap", "data": "../caps/union" }],
//!   "train": "train_cpu.json",
//!   "gaussianavatars": "train_gaussianavatars.json",
//!   "iterations": 1500,
//!   "seeds": [0, 1],
//!   "variants": ["full", "no-global-uv", "no-jacobian", "no-eta", "image-eta", "crop", "no-vgg",
//!                "no-flame-refinement", "gaussianavatars"],
//!   "every_seed": ["image-eta", "no-eta"],
//!   "eval": { "stride": 3, "lpips": true, "panels": 4 },
//!   "crop": { "width": 256, "height": 256 }
//! }
//! ```
//!
//! Paths are relative to the study config's folder. A `synth` subject is the synthetic
//! benchmark's subject of that number, generated into `OUT/data/NAME` (`synth` config:
//! `synth_config`, default the benchmark's defaults); a `data` subject is a VHAP export's
//! split folder. The full method runs once per seed, every other variant with the first
//! seed (and those of `every_seed` once per seed too). `image-eta` trains the full method on
//! a copy of the subject's data (`OUT/data/NAME.image-eta/`, files hard-linked) whose eta
//! files are computed from the images (`texavatars eta`, [`crate::eta`]). `crop` trains the
//! full method on a random window of each frame of `crop`'s size ([`TrainConfig::crop`]), to
//! compare with whole frames. `iterations`, when given, replaces both training configs' (the checkpoint interval
//! is capped to it).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::data::crop::CropSize;
use crate::error::{Error, Result};
use crate::models::texavatars::Ablations;
use crate::synth::SynthConfig;
use crate::train::TrainConfig;
use crate::train::gaussianavatars::GaTrainConfig;

/// One subject of a study.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubjectSpec {
    /// Its name in tables and folders (letters, digits, `-`, `_`).
    pub name: String,
    /// The synthetic benchmark's subject of this number.
    #[serde(default)]
    pub synth: Option<usize>,
    /// A VHAP export's split folder (`transforms_{train,val,test}.json`).
    #[serde(default)]
    pub data: Option<PathBuf>,
}

/// A row of the paper's tables: the full method, an ablation, or the baseline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Variant {
    Full,
    NoGlobalUv,
    NoJacobian,
    NoEta,
    /// The full method with eta computed from the subject's own images (`texavatars eta`)
    /// instead of the data's eta files.
    ImageEta,
    /// The full method trained on a random window of each frame (the study's `crop`).
    Crop,
    NoVgg,
    NoFlameRefinement,
    Gaussianavatars,
}

impl Variant {
    /// Every variant, in the tables' order.
    pub const ALL: [Variant; 9] = [
        Variant::Full,
        Variant::NoGlobalUv,
        Variant::NoJacobian,
        Variant::NoEta,
        Variant::ImageEta,
        Variant::Crop,
        Variant::NoVgg,
        Variant::NoFlameRefinement,
        Variant::Gaussianavatars,
    ];

    /// The config name (`no-global-uv`), also its folder name.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::NoGlobalUv => "no-global-uv",
            Variant::NoJacobian => "no-jacobian",
            Variant::NoEta => "no-eta",
            Variant::ImageEta => "image-eta",
            Variant::Crop => "crop",
            Variant::NoVgg => "no-vgg",
            Variant::NoFlameRefinement => "no-flame-refinement",
            Variant::Gaussianavatars => "gaussianavatars",
        }
    }

    /// The tables' label (the paper's).
    pub fn label(self) -> &'static str {
        match self {
            Variant::Full => "Ours (full)",
            Variant::NoGlobalUv => "w/o Global UV",
            Variant::NoJacobian => "w/o Jacobian",
            Variant::NoEta => "w/o eta",
            Variant::ImageEta => "Ours (image eta)",
            Variant::Crop => "Ours (crop)",
            Variant::NoVgg => "w/o VGG",
            Variant::NoFlameRefinement => "w/o FLAME refinement",
            Variant::Gaussianavatars => "GaussianAvatars",
        }
    }

    /// The ablation switches of a TexAvatars variant (`None` for the baseline).
    pub fn ablations(self) -> Option<Ablations> {
        let mut a = Ablations::default();
        match self {
            Variant::Full | Variant::ImageEta | Variant::Crop => {}
            Variant::NoGlobalUv => a.global_uv = false,
            Variant::NoJacobian => a.jacobian = false,
            Variant::NoEta => a.eta = false,
            Variant::NoVgg => a.vgg = false,
            Variant::NoFlameRefinement => a.flame_refinement = false,
            Variant::Gaussianavatars => return None,
        }
        Some(a)
    }
}

/// Evaluation settings of every run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StudyEval {
    /// Score `ceil(n / stride)` images of each split ([`crate::eval::run::EvalOptions`]).
    #[serde(default = "three")]
    pub stride: usize,
    /// Score LPIPS (needs `texavatars weights install`).
    #[serde(default = "yes")]
    pub lpips: bool,
    /// Frames per split shown side by side in the report.
    #[serde(default = "four")]
    pub panels: usize,
}

impl Default for StudyEval {
    fn default() -> Self {
        StudyEval {
            stride: 3,
            lpips: true,
            panels: 4,
        }
    }
}

fn three() -> usize {
    3
}
fn four() -> usize {
    4
}
fn yes() -> bool {
    true
}

/// A study: subjects × variants (× seeds for the full method).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StudyConfig {
    pub subjects: Vec<SubjectSpec>,
    /// `SynthConfig` of the `synth` subjects (default: the benchmark's defaults).
    #[serde(default)]
    pub synth_config: Option<PathBuf>,
    /// TexAvatars' training config (every TexAvatars variant starts from it).
    pub train: PathBuf,
    /// GaussianAvatars' training config.
    #[serde(default)]
    pub gaussianavatars: Option<PathBuf>,
    /// Replaces both training configs' iterations.
    #[serde(default)]
    pub iterations: Option<usize>,
    /// Seeds of the full method (the first also seeds every other variant).
    pub seeds: Vec<u64>,
    pub variants: Vec<Variant>,
    /// Variants besides the full method that also run once per seed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub every_seed: Vec<Variant>,
    #[serde(default)]
    pub eval: StudyEval,
    /// The window of the `crop` variant ([`TrainConfig::crop`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop: Option<CropSize>,
}

/// One independent run: train one variant on one subject with one seed, then evaluate it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunSpec {
    pub subject: String,
    pub variant: Variant,
    pub seed: u64,
}

impl RunSpec {
    /// `SUBJECT/VARIANT-seedS`, also its folder under `OUT/runs`.
    pub fn id(&self) -> String {
        format!("{}/{}-seed{}", self.subject, self.variant.name(), self.seed)
    }
}

/// A study config with its files read and checked.
#[derive(Clone, Debug)]
pub struct Study {
    pub config: StudyConfig,
    /// The config file (commands name it).
    pub path: PathBuf,
    pub train: TrainConfig,
    pub gaussianavatars: Option<GaTrainConfig>,
    pub synth: SynthConfig,
}

impl Study {
    /// Reads and checks `path` and the configs it names.
    pub fn load(path: &Path) -> Result<Self> {
        let what = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let config: StudyConfig = serde_json::from_str(&text).map_err(|e| {
            Error::invalid(
                &what,
                format!("line {} column {}", e.line(), e.column()),
                e.to_string(),
            )
        })?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let rel = |p: &Path| {
            if p.is_relative() {
                dir.join(p)
            } else {
                p.to_path_buf()
            }
        };
        if config.subjects.is_empty() {
            return Err(Error::invalid(&what, "subjects", "none"));
        }
        for (i, s) in config.subjects.iter().enumerate() {
            let ok_name = !s.name.is_empty()
                && s.name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_".contains(c));
            if !ok_name {
                return Err(Error::invalid(
                    &what,
                    format!("subjects[{i}].name"),
                    format!("{:?}: letters, digits, '-' and '_' only", s.name),
                ));
            }
            if config.subjects[..i].iter().any(|o| o.name == s.name) {
                return Err(Error::invalid(
                    &what,
                    format!("subjects[{i}].name"),
                    format!("{:?} is used twice", s.name),
                ));
            }
            if s.synth.is_some() == s.data.is_some() {
                return Err(Error::invalid(
                    &what,
                    format!("subjects[{i}]"),
                    "give exactly one of synth (a benchmark subject) and data (a VHAP export)",
                ));
            }
        }
        if config.seeds.is_empty() {
            return Err(Error::invalid(&what, "seeds", "none"));
        }
        if config.variants.is_empty() {
            return Err(Error::invalid(&what, "variants", "none"));
        }
        if config.iterations == Some(0) {
            return Err(Error::invalid(&what, "iterations", "must be at least 1"));
        }
        if config.eval.stride == 0 {
            return Err(Error::invalid(&what, "eval.stride", "must be at least 1"));
        }
        let mut train = TrainConfig::load(&rel(&config.train))?;
        match (&config.crop, config.variants.contains(&Variant::Crop)) {
            (Some(c), true) => c.validate(&what)?,
            (None, true) => {
                return Err(Error::invalid(
                    &what,
                    "crop",
                    "the crop variant needs the window's size: \"crop\": {\"width\": W, \"height\": H}",
                ));
            }
            (Some(_), false) => {
                return Err(Error::invalid(
                    &what,
                    "crop",
                    "only the crop variant uses it; add \"crop\" to variants",
                ));
            }
            (None, false) => {}
        }
        if train.crop.is_some() && config.variants.contains(&Variant::Crop) {
            return Err(Error::invalid(
                rel(&config.train).display().to_string(),
                "crop",
                "the crop variant is compared with whole frames: the training config must not crop",
            ));
        }
        let gaussianavatars = match &config.gaussianavatars {
            Some(p) => Some(GaTrainConfig::load(&rel(p))?),
            None if config.variants.contains(&Variant::Gaussianavatars) => {
                return Err(Error::invalid(
                    &what,
                    "gaussianavatars",
                    "the gaussianavatars variant needs its training config",
                ));
            }
            None => None,
        };
        let mut gaussianavatars = gaussianavatars;
        if let Some(n) = config.iterations {
            train.iterations = n;
            train.checkpoint_every = train.checkpoint_every.min(n);
            if let Some(g) = &mut gaussianavatars {
                g.iterations = n;
                g.checkpoint_every = g.checkpoint_every.min(n);
            }
        }
        let synth = match &config.synth_config {
            Some(p) => {
                let p = rel(p);
                let text = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
                serde_json::from_str(&text)
                    .map_err(|e| Error::invalid(p.display().to_string(), "json", e.to_string()))?
            }
            None => SynthConfig::default(),
        };
        let mut config = config;
        for s in &mut config.subjects {
            if let Some(d) = &s.data {
                s.data = Some(rel(d));
            }
        }
        Ok(Study {
            config,
            path: path.to_path_buf(),
            train,
            gaussianavatars,
            synth,
        })
    }

    /// Every run, subject by subject in the config's variant order; the full method once
    /// per seed.
    pub fn runs(&self) -> Vec<RunSpec> {
        let c = &self.config;
        let mut runs = Vec::new();
        for s in &c.subjects {
            for &v in &c.variants {
                let seeds: &[u64] = if v == Variant::Full || c.every_seed.contains(&v) {
                    &c.seeds
                } else {
                    &c.seeds[..1]
                };
                for &seed in seeds {
                    runs.push(RunSpec {
                        subject: s.name.clone(),
                        variant: v,
                        seed,
                    });
                }
            }
        }
        runs
    }

    /// The TexAvatars training config of `run` (`None` for the baseline).
    pub fn train_config(&self, run: &RunSpec) -> Option<TrainConfig> {
        let ablations = run.variant.ablations()?;
        let mut c = self.train.clone();
        c.ablations = ablations;
        c.seed = run.seed;
        if run.variant == Variant::Crop {
            c.crop = self.config.crop;
        }
        Some(c)
    }

    /// The baseline's training config of `run`.
    pub fn ga_config(&self, run: &RunSpec) -> Option<GaTrainConfig> {
        if run.variant != Variant::Gaussianavatars {
            return None;
        }
        let mut c = self.gaussianavatars.clone()?;
        c.seed = run.seed;
        Some(c)
    }

    /// The subject `name`'s spec.
    pub fn subject(&self, name: &str) -> Option<&SubjectSpec> {
        self.config.subjects.iter().find(|s| s.name == name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn variants_round_trip_their_names_and_switch_one_thing_each() {
        for v in Variant::ALL {
            let json = serde_json::to_string(&v).unwrap();
            assert_eq!(json, format!("\"{}\"", v.name()));
            assert_eq!(serde_json::from_str::<Variant>(&json).unwrap(), v);
            let full = Ablations::default();
            match v.ablations() {
                Some(a) => {
                    let differs = [
                        a.global_uv != full.global_uv,
                        a.jacobian != full.jacobian,
                        a.eta != full.eta,
                        a.vgg != full.vgg,
                        a.flame_refinement != full.flame_refinement,
                    ];
                    let n = differs.iter().filter(|d| **d).count();
                    let same = matches!(v, Variant::Full | Variant::ImageEta | Variant::Crop);
                    assert_eq!(n, usize::from(!same), "{v:?}");
                }
                None => assert_eq!(v, Variant::Gaussianavatars),
            }
        }
    }
}
