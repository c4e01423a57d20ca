//! `benches/gpu.sh`'s training stage (stage 5) on lavapipe at a tiny size: it synthesises a
//! benchmark, trains on wgpu, evaluates the avatar, measures its frame rate and prints the
//! table rows, each with a figure (not a "failed" line). Its figures say nothing about a GPU.

use std::path::Path;
use std::process::Command;

use super::out_dir;

#[test]
fn gpu_sh_training_stage_runs_on_lavapipe() {
    let dir = out_dir("gpu-sh");
    let bin = dir.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_texavatars"), bin.join("texavatars")).unwrap();
    std::fs::write(
        dir.join("synth.json"),
        serde_json::to_string_pretty(&crate::tiny::synth_config()).unwrap(),
    )
    .unwrap();
    // No weights: the stage trains without the VGG term and scores without LPIPS.
    let weights = dir.join("no-weights");
    std::fs::create_dir_all(&weights).unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new("bash")
        .arg(root.join("benches/gpu.sh"))
        .env("GPU_SH_BIN", &bin)
        .env("GPU_SH_OUT", dir.join("out"))
        .env("GPU_SH_QUICK", "1")
        .env("GPU_SH_STAGES", "train")
        .env("GPU_SH_SYNTH", dir.join("synth.json"))
        .env("GPU_SH_SIZE", "24x32")
        .env("GPU_SH_ITERS", "6")
        .env("TEXAVATARS_WEIGHTS", &weights)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "gpu.sh failed\n{stdout}\n{stderr}");
    let row = |name: &str| -> String {
        stdout
            .lines()
            .find(|l| l.contains(name))
            .unwrap_or_else(|| panic!("no row '{name}' in\n{stdout}\n{stderr}"))
            .to_string()
    };
    // The step: a number of seconds from the progress lines.
    let step = row("training run, train_tiny.json, 6 iterations");
    let secs: f64 = step
        .split('|')
        .nth(2)
        .and_then(|c| c.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no step time in {step}"));
    assert!(secs > 0.0, "{step}");
    assert!(
        row("step with the VGG term").contains("weights not installed"),
        "{stdout}"
    );
    assert!(row("GPU memory").contains("not measured"), "{stdout}");
    assert!(row("bench fps").contains("FPS"), "{stdout}");
    let scores = row("eval (stride");
    for split in ["held-out", "FREE", "novel view"] {
        assert!(scores.contains(split), "{split} missing: {scores}");
    }
    assert!(
        scores.contains(" dB") && !scores.contains("failed"),
        "{scores}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
