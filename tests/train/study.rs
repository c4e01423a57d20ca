//! `texavatars study` end to end on the tiny benchmark: two variants (the full method with
//! two seeds, w/o eta), one subject, 4 iterations each. The whole study in one command
//! writes the tables, charts, curves and panels; a second call skips every finished run;
//! the same study through `--plan` (its command lines run one by one) and `--collect`
//! gives the same tables, and a partial `--collect` names what has not finished.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use super::{data, out_dir};
use texavatars::data::crop::CropSize;
use texavatars::study::{RunSpec, Variant};

fn study_config(dir: &Path) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    // train_tiny.json with the VGG term left out of the schedule (`vgg_start` 1.0), so that
    // the full method's runs need no VGG16 weights on a machine without them.
    let mut tiny: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_tiny.json"),
        )
        .unwrap(),
    )
    .unwrap();
    tiny["vgg_start"] = serde_json::json!(1.0);
    tiny["net"] =
        serde_json::json!(Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/tiny.json"));
    let train = dir.join("train_tiny.json");
    std::fs::write(&train, serde_json::to_string_pretty(&tiny).unwrap()).unwrap();
    let config = serde_json::json!({
        "subjects": [{ "name": "tiny", "data": data() }],
        "train": train,
        "iterations": 4,
        "seeds": [1, 2],
        "variants": ["full", "no-eta"],
        "eval": { "stride": 40, "lpips": false, "panels": 1 }
    });
    let path = dir.join("study.json");
    std::fs::write(&path, serde_json::to_string_pretty(&config).unwrap()).unwrap();
    path
}

fn study(config: &Path, out: &Path, extra: &[&str]) -> Output {
    let o = Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .arg("study")
        .arg("--config")
        .arg(config)
        .arg("--out")
        .arg(out)
        .args(extra)
        .env_remove("BURN_DEVICE")
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

fn mtime(p: &Path) -> std::time::SystemTime {
    std::fs::metadata(p).unwrap().modified().unwrap()
}

#[test]
fn a_tiny_study_runs_resumes_and_collects_the_same_through_its_plan() {
    let root = out_dir("study");
    let config = study_config(&root);
    let out = root.join("all");
    let o = study(&config, &out, &[]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("3 runs, 0 finished; the 3 left take about"),
        "{stderr}"
    );
    assert!(
        stderr.contains("run 3/3 tiny/no-eta-seed1: done"),
        "{stderr}"
    );
    let report = out.join("report");
    let table1 = std::fs::read_to_string(report.join("table1.md")).unwrap();
    for row in [
        "| Ours (full) | 1 |",
        "| Ours (full) seed 1 | 1 |",
        "| Ours (full) seed 2 | 1 |",
        "| w/o eta | 1 |",
    ] {
        assert!(table1.contains(row), "{row}: {table1}");
    }
    assert!(!table1.contains("Not finished"), "{table1}");
    let table2 = std::fs::read_to_string(report.join("table2.md")).unwrap();
    assert!(
        table2.contains("| w/o eta |") && table2.contains("PSNR on FREE:"),
        "{table2}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.join("tables.json")).unwrap())
            .unwrap();
    assert_eq!(json["runs"].as_array().unwrap().len(), 3);
    assert!(json["missing"].as_array().unwrap().is_empty());
    // The full row averages its seeds: its FREE PSNR lies between theirs.
    let rows = json["rows"].as_array().unwrap();
    let free_psnr = |label: &str| {
        rows.iter().find(|r| r["label"] == label).unwrap()["splits"]["free"]["psnr"]
            .as_f64()
            .unwrap()
    };
    let (a, b) = (
        free_psnr("Ours (full) seed 1"),
        free_psnr("Ours (full) seed 2"),
    );
    let m = free_psnr("Ours (full)");
    assert!((m - 0.5 * (a + b)).abs() < 1e-9, "{a} {b} {m}");
    assert_ne!(a, b, "two seeds, two avatars");
    // --paired: each run's renders against the full method with the first seed (seed 1),
    // per face region; the reference itself is not compared; a second call keeps them.
    let o = study(&config, &out, &["--paired"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("wrote"), "{stdout}");
    let paired = std::fs::read_to_string(report.join("paired.md")).unwrap();
    for row in ["| tiny | Ours (full), seed 2 | ", "| tiny | w/o eta | "] {
        let line = paired
            .lines()
            .find(|l| l.starts_with(row))
            .unwrap_or_else(|| {
                panic!("{row}: {paired}");
            });
        assert!(line.contains(" dB |"), "{line}");
    }
    assert!(!paired.contains("seed 1 |"), "{paired}");
    let pj: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.join("paired.json")).unwrap())
            .unwrap();
    assert_eq!(pj["runs"].as_array().unwrap().len(), 2, "{pj}");
    let against = out.join("runs/tiny/no-eta-seed1/paired/against.md");
    let before = mtime(&against);
    let o = study(&config, &out, &["--paired", "--run", "2"]);
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("run 2 tiny/no-eta-seed1: compared in"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(mtime(&against), before, "kept, not rendered again");
    // The ladder reads collected studies as rungs (here the same study twice).
    let ladder_dir = root.join("ladder");
    let o = Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["study", "--ladder"])
        .arg(&out)
        .arg("--ladder")
        .arg(&out)
        .arg("--out")
        .arg(&ladder_dir)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ladder: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(ladder_dir.join("ladder.json")).unwrap())
            .unwrap();
    let rung = &ladder["rungs"][0];
    let e = &rung["effects"]["free/psnr"];
    assert!((e["full"].as_f64().unwrap() - m).abs() < 1e-9);
    let spread = (a - b).abs() / 2f64.sqrt();
    assert!(
        (e["seed_spread"].as_f64().unwrap() - spread).abs() < 1e-9,
        "{e}"
    );
    let no_eta = free_psnr("w/o eta") - m;
    assert!(
        (e["change"]["no-eta"].as_f64().unwrap() - no_eta).abs() < 1e-9,
        "{e}"
    );
    assert!(
        rung["pixels_per_triangle"]["free"].as_f64().unwrap() > 0.0,
        "{rung}"
    );
    let md = std::fs::read_to_string(ladder_dir.join("ladder.md")).unwrap();
    assert!(md.contains(&format!("{no_eta:+.2} |")), "{md}");
    assert!(
        md.contains("`study --paired`") && md.contains("| tiny | w/o eta | "),
        "{md}"
    );
    for f in ["ladder_free_psnr.png", "ladder_held-out_lpips.png"] {
        assert!(ladder_dir.join(f).is_file(), "{f}");
    }
    // A folder that was never collected is named.
    let o = Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(["study", "--ladder"])
        .arg(&root)
        .arg("--out")
        .arg(root.join("ladder2"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("tables.json"));
    for f in [
        "bars_psnr.png",
        "bars_ssim.png",
        "bars_lpips.png",
        "curves.png",
    ] {
        assert!(report.join(f).is_file(), "{f}");
    }
    // Panels: ground truth | full | w/o eta, and a zoomed row below.
    let panels: Vec<PathBuf> = std::fs::read_dir(report.join("panels"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert!(!panels.is_empty());
    let img = texavatars::io::image::read_rgb(&panels[0]).unwrap();
    assert_eq!(img.width, 3 * 24, "{}", panels[0].display());
    assert!(img.height > 32 + 24, "{}", img.height);

    // Again: every run is finished and skipped, nothing retrained.
    let marker = out.join("runs/tiny/full-seed1/run.json");
    let before = mtime(&marker);
    let o = study(&config, &out, &[]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(
        stderr.matches("finished already, skipped").count(),
        3,
        "{stderr}"
    );
    assert!(stderr.contains("3 runs, 3 finished"), "{stderr}");
    assert_eq!(mtime(&marker), before);

    // Errors per face region: every run's metrics.json has them, regions.md lists them.
    let regions = std::fs::read_to_string(report.join("regions.md")).unwrap();
    assert!(
        regions.contains("## FREE") && regions.contains("## held-out"),
        "{regions}"
    );
    let eta_row = regions
        .lines()
        .find(|l| l.starts_with("| w/o eta |"))
        .expect("w/o eta row");
    // all, background, skin, mouth, eyes, stretched, creases: "all" always has pixels.
    assert!(
        eta_row.split('|').nth(2).unwrap().contains('('),
        "{eta_row}"
    );
    assert!(
        regions.contains("| full: share of squared error |"),
        "{regions}"
    );

    // --reevaluate --run K evaluates a finished run again without training it; the
    // evaluation is deterministic, so the tables stay the same.
    let eta_run = out.join("runs/tiny/no-eta-seed1/run.json");
    let before = mtime(&eta_run);
    let train_before = mtime(&out.join("runs/tiny/no-eta-seed1/train"));
    let o = study(&config, &out, &["--reevaluate", "--run", "2"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("run 2 tiny/no-eta-seed1: evaluated again in"),
        "{stderr}"
    );
    assert!(mtime(&eta_run) > before);
    assert_eq!(
        mtime(&out.join("runs/tiny/no-eta-seed1/train")),
        train_before
    );
    study(&config, &out, &["--collect"]);
    assert_eq!(
        std::fs::read_to_string(report.join("table1.md")).unwrap(),
        table1
    );

    // The plan: one command line per run and a Slurm array over them.
    let planned = root.join("planned");
    let o = study(&config, &planned, &["--plan"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("xargs -P 2"), "{stdout}");
    let commands = std::fs::read_to_string(planned.join("plan/commands.txt")).unwrap();
    let lines: Vec<&str> = commands.lines().collect();
    assert_eq!(lines.len(), 3);
    assert!(
        lines[2].ends_with("--run 2  # tiny/no-eta-seed1"),
        "{}",
        lines[2]
    );
    let slurm = std::fs::read_to_string(planned.join("plan/slurm.sh")).unwrap();
    assert!(slurm.contains("#SBATCH --array=0-2") && slurm.contains("$SLURM_ARRAY_TASK_ID"));
    // Run the first command only: --collect names the other two as not finished.
    let sh = |line: &str| {
        let o = Command::new("sh")
            .arg("-c")
            .arg(line.split("  #").next().unwrap())
            .env_remove("BURN_DEVICE")
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{line}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    study(&config, &planned, &["--prepare"]);
    sh(lines[0]);
    study(&config, &planned, &["--collect"]);
    let partial = std::fs::read_to_string(planned.join("report/table1.md")).unwrap();
    assert!(
        partial.contains("Not finished (2 of 3 runs): tiny/full-seed2, tiny/no-eta-seed1."),
        "{partial}"
    );
    for line in &lines[1..] {
        sh(line);
    }
    study(&config, &planned, &["--collect"]);
    let collected = std::fs::read_to_string(planned.join("report/table1.md")).unwrap();
    assert_eq!(
        collected, table1,
        "the plan's runs give the one-command study's table"
    );
    assert_eq!(
        std::fs::read_to_string(planned.join("report/table2.md")).unwrap(),
        table2
    );
}

#[test]
fn a_bad_study_config_names_its_field() {
    let root = out_dir("study-bad");
    std::fs::create_dir_all(&root).unwrap();
    let train = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_tiny.json");
    for (config, field) in [
        (
            serde_json::json!({"subjects": [], "train": train, "seeds": [0], "variants": ["full"]}),
            "subjects",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a b", "synth": 0}], "train": train, "seeds": [0], "variants": ["full"]}),
            "subjects[0].name",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a", "synth": 0, "data": "x"}], "train": train, "seeds": [0], "variants": ["full"]}),
            "subjects[0]",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a", "synth": 0}], "train": train, "seeds": [0], "variants": ["gaussianavatars"]}),
            "gaussianavatars",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a", "synth": 0}], "train": train, "seeds": [], "variants": ["full"]}),
            "seeds",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a", "synth": 0}], "train": train, "seeds": [0], "variants": ["full", "crop"]}),
            "crop",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a", "synth": 0}], "train": train, "seeds": [0], "variants": ["full"], "crop": {"width": 32, "height": 32}}),
            "crop",
        ),
        (
            serde_json::json!({"subjects": [{"name": "a", "synth": 0}], "train": train, "seeds": [0], "variants": ["crop"], "crop": {"width": 8, "height": 32}}),
            "crop.width",
        ),
    ] {
        let path = root.join("bad.json");
        std::fs::write(&path, config.to_string()).unwrap();
        let e = texavatars::study::Study::load(&path)
            .unwrap_err()
            .to_string();
        assert!(e.contains(field) && e.contains("bad.json"), "{field}: {e}");
    }
}

/// The crop variant is the full method with the study's window; every other variant trains
/// on whole frames.
#[test]
fn the_crop_variant_trains_the_full_method_on_windows() {
    let root = out_dir("study-crop");
    std::fs::create_dir_all(&root).unwrap();
    let train = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/train_tiny.json");
    let path = root.join("crop.json");
    let config = serde_json::json!({"subjects": [{"name": "a", "synth": 0}], "train": train,
        "seeds": [0, 1], "variants": ["full", "crop", "no-jacobian"], "every_seed": ["crop"],
        "crop": {"width": 16, "height": 24}});
    std::fs::write(&path, config.to_string()).unwrap();
    let s = texavatars::study::Study::load(&path).unwrap();
    let runs = s.runs();
    assert_eq!(runs.len(), 5);
    for r in &runs {
        let c = s.train_config(r).unwrap();
        let want = (r.variant == Variant::Crop).then_some(CropSize {
            width: 16,
            height: 24,
        });
        assert_eq!(c.crop, want, "{}", r.id());
        assert_eq!(c.ablations.jacobian, r.variant != Variant::NoJacobian);
    }
}

#[test]
fn shipped_study_configs_load() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    for (name, iterations) in [("study_cpu", 1_000), ("study_demo_budget", 3_500)] {
        let s = texavatars::study::Study::load(&dir.join(format!("{name}.json"))).unwrap();
        // 2 subjects x (2 seeds of the full method + 6 other variants).
        assert_eq!(s.runs().len(), 16, "{name}");
        assert_eq!(s.train.iterations, iterations, "{name}");
        assert_eq!(
            s.gaussianavatars.as_ref().unwrap().iterations,
            iterations,
            "{name}"
        );
    }
    // The resolution ladder, fixed before any of its scores: the same four variants (the
    // full method with two seeds), 3,500 iterations for both models, the VGG loss for the
    // last tenth, networks scaled with the image so the Gaussians per pixel stay comparable.
    for (name, subjects, width, uv_res) in [
        ("study_ladder_200", 2, 138, 128),
        ("study_ladder_401", 2, 275, 256),
        ("study_ladder_802", 1, 550, 512),
    ] {
        let s = texavatars::study::Study::load(&dir.join(format!("{name}.json"))).unwrap();
        assert_eq!(s.runs().len(), subjects * 5, "{name}");
        assert_eq!(s.train.iterations, 3_500, "{name}");
        assert_eq!(s.train.vgg_from(), 3_150, "{name}");
        assert_eq!(s.gaussianavatars.as_ref().unwrap().iterations, 3_500);
        assert_eq!(s.train.net_config().unwrap().uv_res, uv_res, "{name}");
        assert_eq!(s.synth.width, width, "{name}");
    }
    // The crop's comparison at 550 x 802: its whole-frame runs are the ladder's (same data,
    // configs and evaluation), its crop runs differ from them only in the window.
    let crop = texavatars::study::Study::load(&dir.join("study_crop_802.json")).unwrap();
    let ladder = texavatars::study::Study::load(&dir.join("study_ladder_802.json")).unwrap();
    assert_eq!(crop.runs().len(), 4);
    assert_eq!(
        (crop.synth.clone(), crop.config.eval.clone()),
        (ladder.synth.clone(), ladder.config.eval.clone())
    );
    for r in crop.runs() {
        let c = crop.train_config(&r).unwrap();
        let mut whole = ladder
            .train_config(&RunSpec {
                variant: Variant::Full,
                ..r.clone()
            })
            .unwrap();
        if r.variant == Variant::Crop {
            whole.crop = Some(CropSize {
                width: 256,
                height: 256,
            });
        }
        assert_eq!(c, whole, "{}", r.id());
    }
}
