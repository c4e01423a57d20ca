//! A tiny trained avatar for end-to-end tests: the synthetic benchmark at 24 x 32 pixels with
//! two frames per sequence, and `configs/train_tiny.json` run for a few iterations on flex.

use std::path::Path;

use texavatars::device::BackendKind;
use texavatars::head::HeadAsset;
use texavatars::synth::{self, SynthConfig};
use texavatars::train::{TrainConfig, TrainOptions, train};

/// The tiny synthetic set's config: 24 x 32 pixels, two frames per sequence.
pub fn synth_config() -> SynthConfig {
    SynthConfig {
        width: 24,
        height: 32,
        supersample: 1,
        frames_per_sequence: 2,
        free_frames: 2,
        texture_res: 64,
        ..SynthConfig::default()
    }
}

/// Renders the tiny synthetic set of the embedded head into `data` (`data/union` is the
/// training export).
#[allow(dead_code)] // not every test binary that includes this module renders the set
pub fn synth_data(data: &Path) {
    let head = HeadAsset::embedded().expect("head");
    synth::generate(&synth_config(), &head, data, &mut |_| {}).expect("synth");
}

/// Trains the tiny networks on `data/union` into `run` for `iterations`, a checkpoint every
/// `checkpoint_every`.
#[allow(dead_code)] // not every test that renders the tiny set trains on it
pub fn train_tiny(data: &Path, run: &Path, iterations: usize, checkpoint_every: usize) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_tiny.json");
    let mut c = TrainConfig::load(&path).expect("tiny config");
    c.iterations = iterations;
    c.checkpoint_every = checkpoint_every;
    c.log_every = 0;
    let mut t = TrainOptions::new(data.join("union"), run);
    t.backend = Some(BackendKind::Flex);
    t.head = Some(HeadAsset::embedded().expect("head"));
    t.app_log = false;
    train(&c, &t).expect("train");
}
