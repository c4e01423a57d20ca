//! `eval` end to end: a tiny synthetic set, a few training iterations, then the protocol's
//! splits rendered and scored, with the files the report promises.

use std::path::PathBuf;

use texavatars::data::Split;
use texavatars::device::BackendKind;
use texavatars::eval::run::{EvalOptions, evaluate};

use crate::{cli, tiny};

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("texavatars-eval-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn trained_avatar_is_scored_on_every_split() {
    let data = dir("data");
    tiny::synth_data(&data);
    let union = data.join("union");

    let run = dir("run");
    let mut opts = EvalOptions {
        data: union.clone(),
        run: run.clone(),
        out: dir("out"),
        splits: vec![Split::Val, Split::Test, Split::Free],
        extra: Vec::new(),
        head: None,
        lpips: false,
        stride: 4,
        panels: 1,
        backend: BackendKind::Flex,
        paths: texavatars::data::PathPolicy::InsideRoot,
        tracked: false,
        renders: false,
        against: None,
    };
    // Before training: a clear error naming the missing file.
    let e = evaluate(&opts, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("avatar.json"), "{e}");

    tiny::train_tiny(&data, &run, 4, 2);

    let mut lines = Vec::new();
    let report = evaluate(&opts, &mut |l| lines.push(l.to_string())).expect("eval");
    for (split, frames) in [("val", 20usize), ("test", 32), ("free", 32)] {
        let m = report.means.get(split).expect(split);
        assert_eq!(m.images, frames.div_ceil(4), "{split}");
        assert!(m.psnr.is_finite() && m.psnr > 0.0, "{split}: {}", m.psnr);
        assert!(m.ssim > 0.0 && m.ssim <= 1.0);
        assert!(m.lpips_alex.is_none());
        let panels: Vec<_> = std::fs::read_dir(opts.out.join("images").join(split))
            .expect("panels")
            .collect();
        assert_eq!(panels.len(), 1);
    }
    // Per split: the up-front check of its files and where its eta comes from (the
    // benchmark's side files), then its scores.
    let (eta, rest): (Vec<_>, Vec<_>) = lines.iter().partition(|l| l.contains("eta ("));
    for split in ["val", "test", "free"] {
        let line = format!("eta ({split}): side files without eta/source.json");
        assert!(eta.iter().any(|l| l.contains(&line)), "{line}: {eta:?}");
    }
    let (checks, scores): (Vec<&&String>, Vec<&&String>) =
        rest.iter().partition(|l| l.contains("checked"));
    assert_eq!(
        (eta.len(), checks.len(), scores.len()),
        (3, 3, 3),
        "{lines:?}"
    );
    assert!(report.table.contains("novel view"));
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(opts.out.join("metrics.json")).expect("json"),
    )
    .expect("parse");
    assert_eq!(
        json["images"].as_array().map(Vec::len),
        Some(10 + 8 + 8 - 5)
    );
    assert!(opts.out.join("table.md").exists());
    // Pixels per visible triangle, per split: the tiny 24 x 32 frames show a few dozen of the
    // head's faces, each over a pixel or more on average.
    for split in ["val", "test", "free"] {
        let t = &report.triangles[split];
        assert_eq!(t.images as usize, report.means[split].images, "{split}");
        assert!(
            t.visible_faces >= 1.0 && t.covered_pixels <= (24 * 32) as f64,
            "{t:?}"
        );
        let ratio = t.covered_pixels / t.visible_faces;
        assert!(
            (t.pixels_per_triangle - ratio).abs() < 1e-6 * ratio.max(1.0),
            "{t:?}"
        );
        // The covered pixels' shear: ordered quantiles, a share.
        assert!(
            0.0 < t.shear_median && t.shear_median <= t.shear_p90 && t.shear_p90 <= t.shear_p99,
            "{t:?}"
        );
        assert!(
            t.shear_p99 <= 2.0 && (0.0..=1.0).contains(&t.shear_over_10pct),
            "{t:?}"
        );
    }
    // FREE's expressions shear some faces by more than 1 %.
    assert!(
        report.triangles["free"].shear_p99 > 0.01,
        "{:?}",
        report.triangles
    );
    let regions = std::fs::read_to_string(opts.out.join("regions.md")).expect("regions.md");
    assert!(regions.contains("pixels per visible triangle"), "{regions}");
    assert!(regions.contains("shear median"), "{regions}");
    // Mean ± standard deviation over the images.
    assert!(report.table.contains(" ± "), "{}", report.table);
    assert!(report.means["test"].psnr_std > 0.0);
    // A quarter of the held-out split (2 timesteps x 16 cameras) is spread over both
    // timesteps and 8 different cameras, not cameras 0, 4, 8 and 12 of a timestep-major list.
    let test: Vec<_> = report.images.iter().filter(|i| i.split == "test").collect();
    let mut cams: Vec<usize> = test.iter().map(|i| i.camera).collect();
    cams.sort_unstable();
    cams.dedup();
    assert_eq!(cams.len(), 8, "{cams:?}");
    let mut ts: Vec<usize> = test.iter().map(|i| i.timestep).collect();
    ts.dedup();
    assert_eq!(ts.len(), 2);
    // Several subjects' evaluations combine into mean ± std over the subjects.
    let combined = dir("combined");
    let (report, comb) = (opts.out.as_os_str(), combined.as_os_str());
    cli::texavatars_ok([
        "eval".as_ref(),
        "--combine".as_ref(),
        report,
        "--combine".as_ref(),
        report,
        "--out".as_ref(),
        comb,
    ]);
    let table = std::fs::read_to_string(combined.join("table.md")).expect("table");
    assert!(table.contains("over 2 subjects"), "{table}");
    assert!(combined.join("metrics.json").is_file());
    let _ = std::fs::remove_dir_all(&combined);
    // A panel is ground truth | render | error under a header row naming the columns.
    let p = std::fs::read_dir(opts.out.join("images/val"))
        .expect("dir")
        .next()
        .expect("one")
        .expect("entry")
        .path();
    let img = texavatars::io::image::read_rgb(&p).expect("png");
    let header = texavatars::eval::plot::header_height(24);
    assert!(header > 0);
    assert_eq!((img.width, img.height), (72, header + 32));
    // --against: a run compared with itself differs nowhere; with a second, shorter run it
    // differs, and the regions' shares of the difference partition it as the pixels do.
    let run2 = dir("run2");
    tiny::train_tiny(&data, &run2, 2, 2);
    let mut vs = opts.clone();
    vs.splits = vec![Split::Free];
    vs.out = dir("against");
    vs.against = Some(run.clone());
    let r = evaluate(&vs, &mut |_| {}).expect("against itself");
    let same = &r.against.as_ref().expect("against").regions["free"];
    assert!(same["all"].psnr.is_some_and(|p| p >= 100.0), "{same:?}");
    assert!(same.values().all(|x| x.error_share == 0.0), "{same:?}");
    vs.against = Some(run2.clone());
    let mut said = Vec::new();
    let r = evaluate(&vs, &mut |l| said.push(l.to_string())).expect("against run2");
    let a = r.against.as_ref().expect("against");
    assert_eq!(a.run, run2);
    let free = &a.regions["free"];
    let p = free["all"].psnr.expect("psnr");
    assert!(p.is_finite() && p < 100.0, "{free:?}");
    assert_eq!(free["all"].error_share, 1.0);
    let parts: f64 = ["background", "skin", "mouth", "eyes"]
        .iter()
        .map(|n| free[*n].error_share)
        .sum();
    assert!((parts - 1.0).abs() < 1e-9, "{free:?}");
    for (name, x) in free {
        assert_eq!(
            x.pixels, r.regions["free"][name].pixels,
            "{name}: the same labels"
        );
    }
    assert!(
        said.iter().any(|l| l.contains("against the other run")),
        "{said:?}"
    );
    let md = std::fs::read_to_string(vs.out.join("against.md")).expect("against.md");
    assert!(
        md.contains("| free | stretched |") && md.contains("concentration"),
        "{md}"
    );
    let diff: Vec<_> = std::fs::read_dir(vs.out.join("images/free"))
        .expect("panels")
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with("_against.png"))
        .collect();
    // One panel frame and the frame whose faces shear most.
    assert_eq!(diff.len(), 2);
    assert!(
        diff.iter()
            .any(|e| e.file_name().to_string_lossy().starts_with("most_sheared_")),
        "{diff:?}"
    );
    let img = texavatars::io::image::read_rgb(&diff[0].path()).expect("png");
    assert_eq!(img.width, 72);
    assert!(said.iter().any(|l| l.contains("shear most")), "{said:?}");
    for d in [&run2, &vs.out] {
        let _ = std::fs::remove_dir_all(d);
    }
    // A split without a transforms file is skipped with a message.
    std::fs::remove_file(union.join("transforms_free.json")).expect("rm");
    opts.splits = vec![Split::Free];
    let mut said = String::new();
    let r = evaluate(&opts, &mut |l| said.push_str(l)).expect("eval");
    assert!(r.means.is_empty() && said.contains("skipped"), "{said}");
    // An extra split: any export's transforms file under a name of its own, posed with the
    // avatar's subject (the run's canonical_flame_param.npz, written by train).
    assert!(run.join("canonical_flame_param.npz").is_file());
    opts.splits = Vec::new();
    opts.extra = vec![("held".into(), union.join("transforms_test.json"))];
    let r = evaluate(&opts, &mut |_| {}).expect("extra split");
    let m = r.means.get("held").expect("held");
    assert_eq!(m.images, 32usize.div_ceil(4));
    assert!(r.table.contains("| held |"), "{}", r.table);
    assert!(opts.out.join("images/held").is_dir());
    for d in [&data, &run, &opts.out] {
        let _ = std::fs::remove_dir_all(d);
    }
}
