//! `texavatars study`: the paper's tables in one command (see [`crate::study`]).

use std::path::PathBuf;

use clap::Args;

use crate::device::BackendKind;
use crate::error::Error;
use crate::study::{Study, paired, report, run};

/// Arguments of `study`.
#[derive(Debug, Args)]
pub struct StudyArgs {
    /// The study config (configs/study_cpu.json).
    #[arg(long, required_unless_present = "ladder")]
    pub config: Option<PathBuf>,
    /// Output folder: data/, runs/, plan/, report/ (with --ladder: the ladder's tables and
    /// figures).
    #[arg(long)]
    pub out: PathBuf,
    /// Read these collected study folders as the rungs of a resolution ladder, in order
    /// (repeat the flag), and write each component's effect against pixels per triangle
    /// into --out; runs nothing.
    #[arg(long, value_name = "STUDY_OUT", conflicts_with_all = ["config", "plan", "collect", "run", "prepare", "reevaluate", "paired"])]
    pub ladder: Vec<PathBuf>,
    /// Print the independent runs as command lines, write OUT/plan/commands.txt and
    /// OUT/plan/slurm.sh, and print an `xargs -P` line; runs nothing.
    #[arg(long, conflicts_with_all = ["collect", "run", "prepare"])]
    pub plan: bool,
    /// Build the tables and figures from whatever runs have finished; runs nothing.
    #[arg(long, conflicts_with_all = ["run", "prepare"])]
    pub collect: bool,
    /// Train and evaluate run K only (0-based, the plan's order; nothing else).
    #[arg(long, value_name = "K", conflicts_with = "prepare")]
    pub run: Option<usize>,
    /// Generate the synthetic subjects' data only (before runs start in parallel).
    #[arg(long)]
    pub prepare: bool,
    /// Evaluate the finished runs again (all, or run K with --run), keeping their training,
    /// then collect: after `eval` learned a new score (the errors per face region).
    #[arg(long, conflicts_with_all = ["plan", "collect", "prepare"])]
    pub reevaluate: bool,
    /// Compare each finished run's images with its subject's full method (the first seed):
    /// both rendered at every held-out and FREE frame the study scores, where they differ
    /// per face region (`eval --against`) into RUN/paired/ (all runs, or run K with
    /// --run), then OUT/report/paired.md and paired.json. Runs already compared are kept.
    #[arg(long, conflicts_with_all = ["plan", "collect", "prepare", "reevaluate"])]
    pub paired: bool,
    /// Parallel jobs the printed `xargs` line uses (with --plan).
    #[arg(long, default_value_t = 2)]
    pub jobs: usize,
    /// Overrides the training configs' backend.
    #[arg(long, value_enum)]
    pub backend: Option<BackendKind>,
}

/// Runs `study`.
pub fn run(a: StudyArgs) -> anyhow::Result<()> {
    let Some(config) = &a.config else {
        let l = crate::study::ladder::collect(&a.ladder, &a.out)?;
        println!("{}", l.markdown);
        eprintln!(
            "study: the ladder of {} rungs is in {}",
            l.rungs.len(),
            a.out.display()
        );
        return Ok(());
    };
    let study = Study::load(config)?;
    let runs = study.runs();
    let exe = std::env::current_exe()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|_| "texavatars".into());
    let say = |l: &str| eprintln!("study: {l}");
    if a.plan {
        let commands = run::plan(&study, &a.out, &exe)?;
        for (c, r) in commands.iter().zip(&runs) {
            println!("{c}  # {}", r.id());
        }
        println!(
            "\n# wrote {0}/plan/commands.txt and {0}/plan/slurm.sh; on one machine, {1} runs at a time (--jobs):\n{2}",
            a.out.display(),
            a.jobs,
            run::xargs_line(&study, &a.out, &exe, a.jobs)
        );
        return Ok(());
    }
    if a.collect {
        return collect(&study, &a);
    }
    if a.prepare {
        run::prepare(&study, &a.out, &mut |l| say(l))?;
        return Ok(());
    }
    if a.paired {
        for (k, spec) in chosen(&runs, a.run)? {
            match paired::pair(&study, &a.out, spec, a.backend, &mut |l| say(l))? {
                Some(d) => say(&format!(
                    "run {k} {}: compared in {}",
                    spec.id(),
                    d.display()
                )),
                None => say(&format!(
                    "run {k} {}: the reference or not finished, skipped",
                    spec.id()
                )),
            }
        }
        let p = paired::report(&study, &a.out)?;
        println!("{}", p.markdown);
        if !p.missing.is_empty() {
            println!("not compared: {}", p.missing.join(", "));
        }
        println!("wrote {}/report/paired.md", a.out.display());
        return Ok(());
    }
    if a.reevaluate {
        let chosen = chosen(&runs, a.run)?;
        for (k, spec) in chosen {
            match run::reevaluate(&study, &a.out, spec, a.backend, &mut |l| say(l))? {
                Some(r) => say(&format!(
                    "run {k} {}: evaluated again in {:.0} s",
                    spec.id(),
                    r.eval_seconds
                )),
                None => say(&format!("run {k} {}: not finished, skipped", spec.id())),
            }
        }
        if a.run.is_some() {
            return Ok(());
        }
        return collect(&study, &a);
    }
    if let Some(k) = a.run {
        let Some(spec) = runs.get(k) else {
            return Err(Error::invalid(
                "study",
                "--run",
                format!("{k}: the study has {} runs (0..{})", runs.len(), runs.len()),
            )
            .into());
        };
        if run::finished(&a.out, spec).is_some() {
            say(&format!("run {k} {}: finished already, skipped", spec.id()));
            return Ok(());
        }
        say(&format!("run {k} {}", spec.id()));
        run::run_one(&study, &a.out, spec, a.backend, &mut |l| say(l))?;
        return Ok(());
    }
    run::prepare(&study, &a.out, &mut |l| say(l))?;
    let (seconds, left) = run::estimate(&study, &a.out);
    say(&format!(
        "{} runs, {} finished; the {left} left take about {} (estimate: {})",
        runs.len(),
        runs.len() - left,
        hms(seconds),
        if left < runs.len() {
            "this study's finished runs' seconds per iteration"
        } else {
            "the 2-core reference machine's step times"
        }
    ));
    let start = std::time::Instant::now();
    for (k, spec) in runs.iter().enumerate() {
        if run::finished(&a.out, spec).is_some() {
            say(&format!(
                "run {}/{} {}: finished already, skipped",
                k + 1,
                runs.len(),
                spec.id()
            ));
            continue;
        }
        say(&format!(
            "run {}/{} {}: training",
            k + 1,
            runs.len(),
            spec.id()
        ));
        let r = run::run_one(&study, &a.out, spec, a.backend, &mut |l| say(l))?;
        let (left_s, left_n) = run::estimate(&study, &a.out);
        say(&format!(
            "run {}/{} {}: done (train {:.0} s, eval {:.0} s); {} elapsed, about {} for the {left_n} left",
            k + 1,
            runs.len(),
            spec.id(),
            r.train_seconds,
            r.eval_seconds,
            hms(start.elapsed().as_secs_f64()),
            hms(left_s)
        ));
    }
    collect(&study, &a)
}

/// The runs `--run K` picks (all without it), with their indices.
fn chosen(
    runs: &[crate::study::RunSpec],
    k: Option<usize>,
) -> Result<Vec<(usize, &crate::study::RunSpec)>, Error> {
    let chosen: Vec<_> = runs
        .iter()
        .enumerate()
        .filter(|(i, _)| k.is_none_or(|k| *i == k))
        .collect();
    if chosen.is_empty() {
        return Err(Error::invalid(
            "study",
            "--run",
            format!("the study has {} runs (0..{})", runs.len(), runs.len()),
        ));
    }
    Ok(chosen)
}

fn collect(study: &Study, a: &StudyArgs) -> anyhow::Result<()> {
    let c = report::collect(study, &a.out)?;
    println!("{}\n{}", c.table1, c.table2);
    for l in &c.ordering {
        println!("- {l}");
    }
    if !c.missing.is_empty() {
        println!("\nnot finished: {}", c.missing.join(", "));
    }
    println!("wrote {}/report/", a.out.display());
    Ok(())
}

fn hms(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    format!("{}h{:02}m{:02}s", s / 3600, s / 60 % 60, s % 60)
}
