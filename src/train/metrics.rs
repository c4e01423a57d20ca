//! The live training metrics as burn metrics: the objective, each of its terms, and PSNR.
//! burn's metric system logs them (`OUT/train/epoch-N/*.log`, `OUT/valid/epoch-N/*.log`) and
//! hands them to the renderer ([`super::progress::ProgressPrinter`]).

use std::sync::Arc;

use burn::tensor::TensorReadError;
use burn::train::metric::state::{FormatOptions, NumericMetricState};
use burn::train::metric::{
    Metric, MetricAttributes, MetricMetadata, MetricName, Numeric, NumericAttributes, NumericEntry,
    SerializedEntry,
};

/// The numbers a step reports, in the order of [`super::step::StepOutput`]'s values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Term {
    /// The weighted objective.
    Loss = 0,
    /// L1.
    L1,
    /// `1 - SSIM`.
    DSsim,
    /// The VGG perceptual loss (0 while it is off; always 0 in validation).
    Vgg,
    /// L_pos.
    Position,
    /// L_scale.
    Scale,
    /// PSNR in dB (images clamped to [0, 1]).
    Psnr,
}

impl Term {
    /// Number of terms.
    pub const COUNT: usize = 7;

    /// Every term, in order.
    pub const ALL: [Term; Term::COUNT] = [
        Term::Loss,
        Term::L1,
        Term::DSsim,
        Term::Vgg,
        Term::Position,
        Term::Scale,
        Term::Psnr,
    ];

    /// The metric's name (also its log file's name).
    pub fn name(self) -> &'static str {
        match self {
            Term::Loss => "Loss",
            Term::L1 => "L1",
            Term::DSsim => "D-SSIM",
            Term::Vgg => "VGG",
            Term::Position => "L_pos",
            Term::Scale => "L_scale",
            Term::Psnr => "PSNR",
        }
    }
}

/// What [`TermMetric`] reads: a step's values on the host.
#[derive(Clone, Debug)]
pub struct TermsInput {
    /// [`Term::COUNT`] values.
    pub values: Vec<f64>,
    /// Frames the values average over.
    pub batch_size: usize,
}

/// One [`Term`] as a numeric burn metric (running mean over the epoch).
#[derive(Clone)]
pub struct TermMetric {
    term: Term,
    name: MetricName,
    state: NumericMetricState,
}

impl TermMetric {
    /// The metric of `term`.
    pub fn new(term: Term) -> Self {
        TermMetric {
            term,
            name: Arc::new(term.name().to_string()),
            state: NumericMetricState::default(),
        }
    }

    fn format(&self) -> FormatOptions {
        let f = FormatOptions::new(self.name.clone()).precision(4);
        if self.term == Term::Psnr {
            f.unit("dB")
        } else {
            f
        }
    }
}

impl Metric for TermMetric {
    type Input = TermsInput;

    fn name(&self) -> MetricName {
        self.name.clone()
    }

    fn attributes(&self) -> MetricAttributes {
        NumericAttributes {
            unit: (self.term == Term::Psnr).then(|| "dB".to_string()),
            higher_is_better: self.term == Term::Psnr,
        }
        .into()
    }

    fn update(
        &mut self,
        item: &TermsInput,
        _metadata: &MetricMetadata,
    ) -> Result<SerializedEntry, TensorReadError> {
        let v = item.values[self.term as usize];
        self.state.update(v, item.batch_size);
        Ok(self.state.compute_update(self.format()))
    }

    fn compute(&mut self) -> Result<SerializedEntry, TensorReadError> {
        Ok(self.state.compute_final(self.format()))
    }

    fn clear(&mut self) {
        self.state.reset()
    }
}

impl Numeric for TermMetric {
    fn value(&self) -> Option<NumericEntry> {
        Some(self.state.current_value())
    }

    fn running_value(&self) -> Option<NumericEntry> {
        Some(self.state.running_value())
    }

    fn final_value(&self) -> NumericEntry {
        self.state.final_value()
    }
}
