//! The networks bundled: (condition, camera) -> local attribute maps for the lifting operator.

use std::path::Path;

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::constants::*;
use super::decoders::{
    AppearanceDecoder, AppearanceDecoderConfig, Exp2Code, Exp2CodeConfig, GeometryDecoder,
    GeometryDecoderConfig, ViewEncoder, ViewEncoderConfig,
};
use super::pluecker::view_input_batch;
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::kernels::lift::constants::{
    LOCAL_LOG_SCALE, LOCAL_MEAN, LOCAL_OPACITY, LOCAL_QUAT, LOCAL_RGB,
};

/// The condition vector `[expression, pose, eta]` (the data loader's order).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConditionConfig {
    /// Expression coefficients (FLAME: 100; the default head: 52).
    pub expression: usize,
    /// Pose values (15).
    pub pose: usize,
    /// Image-derived expression embedding eta (128; 0 removes it from the network).
    pub eta: usize,
    /// Ablation "w/o eta" by zeroing: the eta part of the condition is replaced by zeros
    /// before Exp2Code (the input stays `expression + pose + eta` wide). Note that with the
    /// whole-tensor weight norm the dead eta columns of Exp2Code still enter `||v||`; setting
    /// `eta` to 0 removes them instead.
    #[serde(default)]
    pub zero_eta: bool,
}

impl ConditionConfig {
    /// FLAME's condition: 100 + 15 + 128 = 243 (the paper).
    pub fn flame() -> Self {
        ConditionConfig {
            expression: FLAME_EXPRESSION_DIM,
            pose: POSE_DIM,
            eta: ETA_DIM,
            zero_eta: false,
        }
    }

    /// The shipped default head's condition: 52 + 15 + 128 = 195.
    pub fn default_head() -> Self {
        ConditionConfig {
            expression: DEFAULT_HEAD_EXPRESSION_DIM,
            ..Self::flame()
        }
    }

    /// Length of the condition vector.
    pub fn dim(&self) -> usize {
        // Saturating: sizes come from files; `NetConfig::validate` refuses a saturated sum.
        self.expression
            .saturating_add(self.pose)
            .saturating_add(self.eta)
    }
}

/// Channel plan of the appearance decoder.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AppearancePlan {
    /// Transposed convolutions before the view injection (paper: [256, 128]).
    pub before_view: Vec<usize>,
    /// 3x3 convolutions after the injection (paper: [128, 128]).
    pub mid: Vec<usize>,
    /// Transposed convolutions after those, the last one 3 wide (paper: [64, 64, 3, 3]).
    pub after_view: Vec<usize>,
}

/// The view encoder and its input.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewPlan {
    /// Stride-2 convolutions (paper: [16, 32]); the last is the embedding's width.
    pub channels: Vec<usize>,
    /// Side of the square the camera's Pluecker map is first resized to (paper: 512).
    pub square_res: usize,
}

/// All sizes of the networks (`configs/paper.json`, `cpu.json`, `tiny.json`).
///
/// `uv_res = 8 * 2^k`; both decoders have k transposed convolutions (k = 6 in the paper):
/// `geometry.len() == k` and `appearance.before_view.len() + appearance.after_view.len() == k`.
/// The view embedding is injected at side `8 * 2^len(before_view)` (32 in the paper), so
/// the view encoder's input side is that times `2^len(view.channels)` (128 in the paper).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetConfig {
    /// Side of the local attribute maps, R_uv (paper: 512).
    pub uv_res: usize,
    /// The condition vector.
    pub condition: ConditionConfig,
    /// Channels of Exp2Code's 8 x 8 code (paper: 256).
    pub code_channels: usize,
    /// Untied (per-pixel) biases on all transposed convolutions (the paper) instead of
    /// per-channel biases.
    pub untied_bias: bool,
    /// Output channels of the geometry decoder's transposed convolutions, the last 11
    /// (paper: [256, 128, 128, 64, 32, 11]).
    pub geometry: Vec<usize>,
    /// The appearance decoder.
    pub appearance: AppearancePlan,
    /// The view encoder.
    pub view: ViewPlan,
}

fn invalid(what: &str, field: &str, why: String) -> Error {
    Error::invalid(what, field, why)
}

/// `side * 2^stages`, saturating at `usize::MAX` (sizes come from files).
fn doubled(side: usize, stages: usize) -> usize {
    u32::try_from(stages)
        .ok()
        .and_then(|k| 1usize.checked_shl(k))
        .and_then(|f| side.checked_mul(f))
        .unwrap_or(usize::MAX)
}

/// Most conditioning values a net config may take ([`ConditionConfig::dim`]): a bound on a
/// size read from a file, far above any real conditioning.
pub const MAX_CONDITION: usize = 1 << 16;

/// `k` with `res = 8 * 2^k`, if any (k >= 1).
fn stages_for(res: usize) -> Option<usize> {
    (res > BASE_RES && res.is_multiple_of(BASE_RES) && (res / BASE_RES).is_power_of_two())
        .then(|| (res / BASE_RES).trailing_zeros() as usize)
}

impl NetConfig {
    /// The paper's networks: R_uv 512, full channels, FLAME's 243-value condition.
    pub fn paper() -> Self {
        NetConfig {
            uv_res: BASE_RES << PAPER_GEOMETRY.len(),
            condition: ConditionConfig::flame(),
            code_channels: PAPER_CODE_CHANNELS,
            untied_bias: true,
            geometry: PAPER_GEOMETRY.to_vec(),
            appearance: AppearancePlan {
                before_view: PAPER_APPEARANCE_BEFORE_VIEW.to_vec(),
                mid: PAPER_APPEARANCE_MID.to_vec(),
                after_view: PAPER_APPEARANCE_AFTER_VIEW.to_vec(),
            },
            view: ViewPlan {
                channels: PAPER_VIEW.to_vec(),
                square_res: PLUECKER_SQUARE_RES,
            },
        }
    }

    /// A smaller variant of the paper's networks at `uv_res = 8 * 2^k` (16 to 512) with every
    /// width divided by `divisor` (rounded up, at least [`MIN_SCALED_WIDTH`]; the outputs stay
    /// 11 and 3 wide). The condition is FLAME's; change it with [`NetConfig::with_condition`].
    ///
    /// The plan is shortened by resolution: a layer keeps the width the paper gives it at the
    /// same output side, the layers beyond `uv_res` are dropped, and the last remaining
    /// transposed convolution outputs the attributes. So at `uv_res` 128 the geometry decoder
    /// is 256 -> 256 (16) -> 128 (32) -> 128 (64) -> 11 (128) before the division. The
    /// appearance decoder keeps the view injection at 32^2 when `uv_res >= 64` (at 16^2 when
    /// `uv_res` is 32, at 8^2 when 16) with the paper's 3x3 convolutions after it, and its
    /// transposed convolutions after the injection are the paper's 64, 64, 3, 3 truncated
    /// to the remaining stages, the last set to 3.
    pub fn scaled(uv_res: usize, divisor: usize) -> Result<Self> {
        let what = "scaled net config";
        let k = stages_for(uv_res)
            .filter(|&k| k <= PAPER_GEOMETRY.len())
            .ok_or_else(|| {
                invalid(
                    what,
                    "uv_res",
                    format!("must be 16, 32, ..., 512, got {uv_res}"),
                )
            })?;
        if divisor == 0 {
            return Err(invalid(what, "divisor", "must be positive".into()));
        }
        let s = |w: usize| w.div_ceil(divisor).max(MIN_SCALED_WIDTH);
        let scale_all = |ws: &[usize]| ws.iter().map(|&w| s(w)).collect::<Vec<_>>();
        // Truncated to `n` stages; the last one outputs `out` channels.
        let truncated = |ws: &[usize], n: usize, out: usize| {
            let mut v = scale_all(&ws[..n]);
            if let Some(last) = v.last_mut() {
                *last = out;
            }
            v
        };
        let before = PAPER_APPEARANCE_BEFORE_VIEW.len().min(k - 1);
        Ok(NetConfig {
            uv_res,
            condition: ConditionConfig::flame(),
            code_channels: s(PAPER_CODE_CHANNELS),
            untied_bias: true,
            geometry: truncated(&PAPER_GEOMETRY, k, GEOMETRY_CHANNELS),
            appearance: AppearancePlan {
                before_view: scale_all(&PAPER_APPEARANCE_BEFORE_VIEW[..before]),
                mid: scale_all(&PAPER_APPEARANCE_MID),
                after_view: truncated(&PAPER_APPEARANCE_AFTER_VIEW, k - before, RGB_CHANNELS),
            },
            view: ViewPlan {
                channels: scale_all(&PAPER_VIEW),
                square_res: PLUECKER_SQUARE_RES,
            },
        })
    }

    /// The same networks with another condition vector.
    pub fn with_condition(mut self, condition: ConditionConfig) -> Self {
        self.condition = condition;
        self
    }

    /// Reads a JSON config and validates it.
    pub fn load(path: &Path) -> Result<Self> {
        let what = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let c: NetConfig = serde_json::from_str(&text).map_err(|e| {
            invalid(
                &what,
                &format!("line {} column {}", e.line(), e.column()),
                e.to_string(),
            )
        })?;
        c.validate(&what)?;
        Ok(c)
    }

    /// Pretty JSON, as in `configs/`.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a NetConfig serialises") + "\n"
    }

    /// Number of upsampling stages k (`uv_res = 8 * 2^k`).
    pub fn stages(&self) -> usize {
        stages_for(self.uv_res).unwrap_or(0)
    }

    /// Side at which the view embedding joins the appearance decoder (paper: 32).
    pub fn view_res(&self) -> usize {
        doubled(BASE_RES, self.appearance.before_view.len())
    }

    /// Side of the view encoder's input Pluecker map (paper: 128).
    pub fn view_input_res(&self) -> usize {
        doubled(self.view_res(), self.view.channels.len())
    }

    /// Checks that the sizes fit together; `what` names the source in errors.
    pub fn validate(&self, what: &str) -> Result<()> {
        let k = stages_for(self.uv_res).ok_or_else(|| {
            invalid(
                what,
                "uv_res",
                format!("must be 8 * 2^k with k >= 1, got {}", self.uv_res),
            )
        })?;
        let positive = |field: &str, ws: &[usize]| -> Result<()> {
            if ws.contains(&0) {
                return Err(invalid(what, field, format!("has a zero width: {ws:?}")));
            }
            Ok(())
        };
        positive("code_channels", &[self.code_channels])?;
        positive("geometry", &self.geometry)?;
        positive("appearance.before_view", &self.appearance.before_view)?;
        positive("appearance.mid", &self.appearance.mid)?;
        positive("appearance.after_view", &self.appearance.after_view)?;
        positive("view.channels", &self.view.channels)?;
        if self.condition.dim() == 0 {
            return Err(invalid(what, "condition", "is empty".into()));
        }
        if self.condition.dim() > MAX_CONDITION {
            return Err(invalid(
                what,
                "condition",
                format!(
                    "{} values in all, more than {MAX_CONDITION} (FLAME's 100 expression \
                     coefficients, 15 pose values and 128 eta values are 243)",
                    self.condition.dim()
                ),
            ));
        }
        if self.geometry.len() != k || self.geometry.last() != Some(&GEOMETRY_CHANNELS) {
            return Err(invalid(
                what,
                "geometry",
                format!(
                    "needs {k} entries for uv_res {} (8 * 2^{k}), the last {GEOMETRY_CHANNELS}; \
                     got {:?}",
                    self.uv_res, self.geometry
                ),
            ));
        }
        let a = &self.appearance;
        if a.before_view.len() + a.after_view.len() != k
            || a.after_view.last() != Some(&RGB_CHANNELS)
        {
            return Err(invalid(
                what,
                "appearance",
                format!(
                    "before_view and after_view need {k} entries together for uv_res {}, \
                     after_view at least one, its last {RGB_CHANNELS}; got {:?} and {:?}",
                    self.uv_res, a.before_view, a.after_view
                ),
            ));
        }
        if self.view.channels.is_empty() {
            return Err(invalid(what, "view.channels", "is empty".into()));
        }
        let (input, square) = (self.view_input_res(), self.view.square_res);
        if input > crate::limits::IMAGE_SIDE.max as usize {
            return Err(invalid(
                what,
                "view.channels",
                format!(
                    "{} stages after {} appearance stages ask for a {input}-pixel view map, \
                     more than {} (see crate::limits::IMAGE_SIDE)",
                    self.view.channels.len(),
                    self.appearance.before_view.len(),
                    crate::limits::IMAGE_SIDE.max
                ),
            ));
        }
        if square < input || !square.is_multiple_of(input) || !(square / input).is_power_of_two() {
            return Err(invalid(
                what,
                "view.square_res",
                format!(
                    "must be the view encoder's input side {input} times a power of two, got \
                     {square}"
                ),
            ));
        }
        Ok(())
    }

    /// Builds the networks (seed the device first for reproducible weights).
    pub fn init(&self, device: &Device) -> Result<TexAvatarNet> {
        self.validate("net config")?;
        let view_channels = *self.view.channels.last().expect("validated");
        Ok(TexAvatarNet {
            exp2code: Exp2CodeConfig::new(self.condition.dim(), self.code_channels).init(device),
            view_encoder: ViewEncoderConfig::new(self.view.channels.clone()).init(device),
            geometry: GeometryDecoderConfig::new(self.code_channels, self.geometry.clone())
                .with_untied_bias(self.untied_bias)
                .init(device),
            appearance: AppearanceDecoderConfig::new(
                self.code_channels,
                view_channels,
                self.appearance.before_view.clone(),
                self.appearance.mid.clone(),
                self.appearance.after_view.clone(),
            )
            .with_untied_bias(self.untied_bias)
            .init(device),
            uv_res: self.uv_res,
            cond_dim: self.condition.dim(),
            eta_dim: self.condition.eta,
            zero_eta: self.condition.zero_eta,
            view_input_res: self.view_input_res(),
            pluecker_square_res: self.view.square_res,
        })
    }
}

/// The four networks of method §3.
#[derive(Module, Debug)]
pub struct TexAvatarNet {
    /// Condition -> 8 x 8 code, shared by both decoders.
    pub exp2code: Exp2Code,
    /// Pluecker map -> view embedding.
    pub view_encoder: ViewEncoder,
    /// Code -> local geometry maps.
    pub geometry: GeometryDecoder,
    /// Code + view embedding -> local RGB maps.
    pub appearance: AppearanceDecoder,
    /// R_uv.
    pub uv_res: usize,
    /// Length of the condition vector.
    pub cond_dim: usize,
    /// Length of its eta part (the last entries).
    pub eta_dim: usize,
    /// Whether eta is zeroed (ablation).
    pub zero_eta: bool,
    /// Side of the view encoder's input.
    pub view_input_res: usize,
    /// Side of the square the camera's Pluecker map is first resized to.
    pub pluecker_square_res: usize,
}

/// The decoders' outputs: local attribute maps in texel space, ready for the lifting
/// operator ([`crate::lift`]). Texel `(i, j)` is pixel column `i`, row `j` (row 0 at v = 0,
/// see [`crate::texel::layout`]).
///
/// # Shapes
/// - `geometry`: [N, 11, R, R]: offset 3, quaternion 4 (w, x, y, z; unnormalised), log-scale
///   3, opacity logit 1
/// - `rgb`: [N, 3, R, R]
#[derive(Clone, Debug)]
pub struct LocalMaps {
    /// Geometry maps.
    pub geometry: Tensor<4>,
    /// Colour maps.
    pub rgb: Tensor<4>,
}

impl LocalMaps {
    /// Position offsets mu^l, [N, 3, R, R].
    pub fn offset(&self) -> Tensor<4> {
        self.geometry.clone().narrow(1, LOCAL_MEAN, 3)
    }

    /// Rotation quaternions q^l (w, x, y, z; unnormalised), [N, 4, R, R].
    pub fn rotation(&self) -> Tensor<4> {
        self.geometry.clone().narrow(1, LOCAL_QUAT, 4)
    }

    /// Log-scales s^l, [N, 3, R, R].
    pub fn log_scale(&self) -> Tensor<4> {
        self.geometry.clone().narrow(1, LOCAL_LOG_SCALE, 3)
    }

    /// Opacity logits, [N, 1, R, R].
    pub fn opacity_logit(&self) -> Tensor<4> {
        self.geometry.clone().narrow(1, LOCAL_OPACITY, 1)
    }

    /// All 14 channels in the lifting operator's order, [N, 14, R, R].
    pub fn packed(&self) -> Tensor<4> {
        debug_assert_eq!(self.geometry.dims()[1], LOCAL_RGB);
        Tensor::cat(vec![self.geometry.clone(), self.rgb.clone()], 1)
    }

    /// Frame `i` of [`LocalMaps::packed`]: the [14, R, R] input of [`crate::lift::lift`].
    pub fn frame(&self, i: usize) -> Tensor<3> {
        let packed = self.packed();
        if packed.dims()[0] == 1 && i == 0 {
            // A narrow over the whole batch would still be a tracked slice, whose gradient
            // autodiff builds as a zero-filled copy of the whole map.
            return packed.squeeze_dim::<3>(0);
        }
        packed.narrow(0, i, 1).squeeze_dim::<3>(0)
    }
}

impl TexAvatarNet {
    /// The condition with its eta part zeroed when the ablation is on.
    fn condition_used(&self, condition: Tensor<2>) -> Tensor<2> {
        if !self.zero_eta || self.eta_dim == 0 {
            return condition;
        }
        let [n, c] = condition.dims();
        let device = condition.device();
        Tensor::cat(
            vec![
                condition.narrow(1, 0, c - self.eta_dim),
                Tensor::zeros([n, self.eta_dim], &device),
            ],
            1,
        )
    }

    /// The view encoder's input for `cameras` ([`super::pluecker::view_input_batch`]).
    ///
    /// # Shapes
    /// - returns [N, 6, S, S] with N = `cameras.len()`, S the view encoder's input side
    pub fn view_input(&self, cameras: &[Camera], device: &Device) -> Result<Tensor<4>> {
        view_input_batch(
            cameras,
            self.pluecker_square_res,
            self.view_input_res,
            device,
        )
    }

    /// Runs the networks on conditions and precomputed Pluecker maps.
    ///
    /// # Shapes
    /// - `condition`: [N, cond_dim], the order `[expression, pose, eta]`
    /// - `pluecker`: [N, 6, S, S] ([`TexAvatarNet::view_input`])
    /// - returns maps at R = R_uv
    pub fn forward(&self, condition: Tensor<2>, pluecker: Tensor<4>) -> Result<LocalMaps> {
        let [n, c] = condition.dims();
        let what = "net inputs";
        if c != self.cond_dim || n == 0 {
            return Err(Error::invalid(
                what,
                "condition",
                format!("expected [N >= 1, {}], got {:?}", self.cond_dim, [n, c]),
            ));
        }
        let s = self.view_input_res;
        if pluecker.dims() != [n, PLUECKER_CHANNELS, s, s] {
            return Err(Error::invalid(
                what,
                "pluecker",
                format!(
                    "expected [{n}, {PLUECKER_CHANNELS}, {s}, {s}], got {:?}",
                    pluecker.dims()
                ),
            ));
        }
        let code = self.exp2code.forward(self.condition_used(condition));
        let view = self.view_encoder.forward(pluecker);
        Ok(LocalMaps {
            geometry: self.geometry.forward(code.clone()),
            rgb: self.appearance.forward(code, view),
        })
    }

    /// For inference: every layer's weight norm folded into its weight, so forward passes
    /// skip the norms (a sizeable part of the `paper` decoders' forward on the CPU). The folded net
    /// computes the same function and saves as an ordinary one; it is not for training.
    pub fn fold(self) -> Self {
        Self {
            exp2code: self.exp2code.fold(),
            view_encoder: self.view_encoder.fold(),
            geometry: self.geometry.fold(),
            appearance: self.appearance.fold(),
            ..self
        }
    }

    /// Runs the networks for conditions seen from `cameras` (one per row of `condition`).
    pub fn forward_cameras(&self, condition: Tensor<2>, cameras: &[Camera]) -> Result<LocalMaps> {
        let pluecker = self.view_input(cameras, &condition.device())?;
        self.forward(condition, pluecker)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sizes read from a file that would overflow are errors, not panics (found by
    /// tests/cpu/fuzz.rs: `ConditionConfig::dim` and `view_input_res` used to overflow).
    #[test]
    fn overflowing_sizes_are_errors() {
        let mut c = NetConfig::paper();
        c.condition.eta = usize::MAX;
        let e = c.validate("n.json").unwrap_err().to_string();
        assert!(e.contains("condition"), "{e}");
        let mut c = NetConfig::paper();
        c.view.channels = vec![4; 200];
        let e = c.validate("n.json").unwrap_err().to_string();
        assert!(e.contains("view.channels"), "{e}");
        assert_eq!(doubled(8, 70), usize::MAX);
        assert_eq!(doubled(8, 4), 128);
    }
}
