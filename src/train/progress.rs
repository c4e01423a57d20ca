//! A line-oriented burn metrics renderer: every `log_every` iterations one line on stderr
//! with the global iteration, the metrics averaged since the previous line, the time per
//! iteration and the estimated time left; after each validation pass one line with its
//! means. (burn's own renderers are a terminal UI, not built here, and a plain renderer that
//! prints no metric values.)

use std::collections::HashMap;
use std::time::Instant;

use burn::train::logger::{EvaluationProgressLogger, TrainingProgressLogger};
use burn::train::metric::{MetricDefinition, MetricId, NumericEntry};
use burn::train::renderer::{
    EvaluationName, MetricState, MetricsRenderer, MetricsRendererEvaluation,
    MetricsRendererTraining,
};

use super::loader::Schedule;
use super::metrics::Term;
use super::stop::StopControl;

/// Running sums of one metric since the last printed line.
#[derive(Clone, Copy, Debug, Default)]
struct Window {
    sum: f64,
    count: usize,
}

/// The renderer of [`super::train`].
pub struct ProgressPrinter {
    schedule: Schedule,
    log_every: usize,
    names: HashMap<MetricId, String>,
    train: HashMap<String, Window>,
    valid_final: HashMap<String, f64>,
    /// Frames of the current validation pass (none: no line).
    valid_items: usize,
    split: &'static str,
    /// 1-based burn epoch of the current split.
    epoch: usize,
    /// Global iterations done when this process started.
    start_iteration: usize,
    started: Option<Instant>,
    window_start: Option<(Instant, usize)>,
    /// Where the run stopped early, for the checkpoint line.
    stop: Option<StopControl>,
}

impl ProgressPrinter {
    /// A printer for `schedule` writing every `log_every` iterations (0: only validation
    /// and checkpoint lines).
    pub fn new(schedule: Schedule, log_every: usize) -> Self {
        ProgressPrinter {
            schedule,
            log_every,
            names: HashMap::new(),
            train: HashMap::new(),
            valid_final: HashMap::new(),
            valid_items: 0,
            split: "train",
            epoch: 1,
            start_iteration: 0,
            started: None,
            window_start: None,
            stop: None,
        }
    }

    /// Names the iteration a stopped run's last checkpoint holds ([`StopControl`]).
    pub fn with_stop(mut self, stop: StopControl) -> Self {
        self.stop = Some(stop);
        self
    }

    /// Global iterations done after `items` items of the current epoch.
    fn iteration(&self, items: usize) -> usize {
        self.schedule.iterations_of(self.epoch - 1).start + items / self.schedule.batch_size
    }

    fn values_line(values: &[(String, f64)]) -> String {
        let mut s = String::new();
        for term in Term::ALL {
            if let Some((_, v)) = values.iter().find(|(n, _)| n == term.name()) {
                let unit = if term == Term::Psnr { " dB" } else { "" };
                s += &format!("  {} {}{unit}", term.name(), fmt(*v));
            }
        }
        s
    }

    fn print_train(&mut self, iteration: usize) {
        let values: Vec<(String, f64)> = self
            .train
            .iter()
            .filter(|(_, w)| w.count > 0)
            .map(|(n, w)| (n.clone(), w.sum / w.count as f64))
            .collect();
        let now = Instant::now();
        let per_it = self.window_start.and_then(|(t, it0)| {
            (iteration > it0)
                .then(|| now.duration_since(t).as_secs_f64() / (iteration - it0) as f64)
        });
        let timing = match per_it {
            Some(s) => format!(
                "  {:.3} s/it  ~{} left at this rate",
                s,
                duration(s * (self.schedule.total - iteration) as f64)
            ),
            None => String::new(),
        };
        eprintln!(
            "train  it {iteration}/{}{}{timing}",
            self.schedule.total,
            Self::values_line(&values)
        );
        self.train.clear();
        self.window_start = Some((now, iteration));
    }
}

fn fmt(v: f64) -> String {
    if v == 0.0 || (v.abs() >= 1e-3 && v.abs() < 1e4) {
        format!("{v:.4}")
    } else {
        format!("{v:.3e}")
    }
}

fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{}h{:02}m", s / 3600, (s % 3600) / 60)
    } else if s >= 60 {
        format!("{}m{:02}s", s / 60, s % 60)
    } else {
        format!("{s}s")
    }
}

impl MetricsRendererTraining for ProgressPrinter {
    fn update_train(&mut self, state: MetricState) {
        if let MetricState::Numeric(entry, Some(value)) = state
            && let Some(name) = self.names.get(&entry.metric_id)
            && !matches!(value, NumericEntry::Final(_))
        {
            let w = self.train.entry(name.clone()).or_default();
            w.sum += value.current();
            w.count += 1;
        }
    }

    fn update_valid(&mut self, state: MetricState) {
        if let MetricState::Numeric(entry, Some(NumericEntry::Final(v))) = state
            && let Some(name) = self.names.get(&entry.metric_id)
        {
            self.valid_final.insert(name.clone(), v);
        }
    }
}

impl TrainingProgressLogger for ProgressPrinter {
    fn start(
        &mut self,
        total_epochs: usize,
        starting_epoch: usize,
        _total_items: Option<usize>,
        _label: Option<&str>,
    ) {
        self.epoch = starting_epoch;
        self.start_iteration = self.schedule.iterations_of(starting_epoch - 1).start;
        self.started = Some(Instant::now());
        self.window_start = Some((Instant::now(), self.start_iteration));
        eprintln!(
            "train: iterations {}..{} of {} ({} per checkpoint, burn epochs {starting_epoch}..={total_epochs})",
            self.start_iteration, self.schedule.total, self.schedule.total, self.schedule.per_epoch
        );
    }

    fn update_epoch(&mut self, epoch: usize) {
        let end = self.schedule.iterations_of(epoch - 1).end;
        let it = self
            .stop
            .as_ref()
            .and_then(|s| s.stopped_at())
            .map_or(end, |s| s.min(end));
        eprintln!("train: iteration {it}: checkpoint {epoch}");
        self.epoch = epoch + 1;
    }

    fn start_split(&mut self, split: &str, _total_items: usize) {
        self.split = if split == "valid" { "valid" } else { "train" };
        if self.split == "valid" {
            self.valid_final.clear();
            self.valid_items = 0;
        }
    }

    fn update_split(&mut self, items_processed: usize) {
        if self.split == "valid" {
            self.valid_items = items_processed;
        }
        if self.split != "train" || self.log_every == 0 {
            return;
        }
        let it = self.iteration(items_processed);
        if it.is_multiple_of(self.log_every) || it == self.schedule.total {
            self.print_train(it);
        }
    }

    fn end_split(&mut self) {
        if self.split == "valid" && self.valid_items > 0 && !self.valid_final.is_empty() {
            let values: Vec<(String, f64)> = self
                .valid_final
                .iter()
                .map(|(n, v)| (n.clone(), *v))
                .collect();
            let it = self.schedule.iterations_of(self.epoch - 1).end;
            eprintln!("valid  it {it}{}", Self::values_line(&values));
        }
    }

    fn end(&mut self) {
        if let Some(t) = self.started {
            eprintln!(
                "train: stopped after {} in this process",
                duration(t.elapsed().as_secs_f64())
            );
        }
    }

    fn log_event_training(&mut self, _event: String) {}
}

impl EvaluationProgressLogger for ProgressPrinter {
    fn start_global_progress(&mut self, _total_tests: usize) {}
    fn start_test(&mut self, _name: &str, _total_items: usize) {}
    fn update_test_progress(&mut self, _items_processed: usize) {}
    fn end_test(&mut self) {}
    fn end_global_progress(&mut self) {}
    fn log_event_evaluation(&mut self, _event: String) {}
}

impl MetricsRendererEvaluation for ProgressPrinter {
    fn update_test(&mut self, _name: EvaluationName, _state: MetricState) {}
}

impl MetricsRenderer for ProgressPrinter {
    fn manual_close(&mut self) {}

    fn register_metric(&mut self, definition: MetricDefinition) {
        self.names
            .insert(definition.metric_id.clone(), definition.name.to_string());
    }
}
