//! Adam (Kingma and Ba 2015) as one pass per parameter tensor, a drop-in for burn's
//! [`burn::optim::Adam`]: the same formula in the same `f32` order, the same state type
//! ([`AdamState`], so optimizer records saved with burn's Adam keep loading), and a
//! [`ModuleOptimizer`] like [`burn::optim::AdamConfig::init`]'s.
//!
//! Why: burn's Adam composes about a dozen tensor ops per parameter, each a pass over the
//! parameter with a fresh buffer (the two moments' scale and sum, the square, the root, the
//! quotient, the step). The `cpu` networks have 1.58 M parameters, most of them untied biases
//! and Exp2Code's linear weight, so those dozen passes over memory are a noticeable share of a
//! `cpu` training step. Here it is one pass that reads the gradient and updates the
//! parameter and both moments in place.
//!
//! The formula, as `burn-optim` 0.22's `AdaptiveMomentum::transform` and `Adam::step` compute
//! it, at step `t` (1 on the first call, whose moments start at zero):
//! - `m = β₁·m + (1 - β₁)·g`, `v = β₂·v + (1 - β₂)·g²`;
//! - `c₂ = √(1 - β₂ᵗ)`, `f = c₂ / (1 - β₁ᵗ)`;
//! - `p = p - lr · (f·m) / (√v + ε·c₂)`,
//!
//! which is PyTorch's `torch.optim.Adam` (`_single_tensor_adam`, `capturable=False`:
//! `step_size = lr / bias_correction1`, `denom = sqrt(v) / sqrt(bias_correction2) + eps`)
//! multiplied through by `c₂`.
//!
//! Thread mapping (CPU): the tensors are cut into runs of `CHUNK` values, one rayon task each.
//!
//! Backends: flex and ndarray run the pass here; burn's cubecl backend (wgpu) composes
//! burn's tensor ops (the trait's default body, burn's own sequence). The reference twin is
//! burn's Adam itself; the tests compare several steps with it.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::tensor::FloatTensor;
use burn::backend::{AutodiffBackend, Backend, Cube, ExtensionType, backend_extension};
use burn::optim::{AdamState, AdaptiveMomentumState, LearningRate, ModuleOptimizer, Optimizer};
use burn::tensor::{Device, Tensor};
use rayon::prelude::*;

use crate::host::HostIo;

/// Values per task (64 K floats, 256 KiB per tensor).
const CHUNK: usize = 1 << 16;

/// A parameter, its gradient and its two moments, all of one shape.
#[derive(ExtensionType, Debug, Clone)]
pub struct AdamTensors<B: Backend> {
    pub param: FloatTensor<B>,
    pub grad: FloatTensor<B>,
    pub m: FloatTensor<B>,
    pub v: FloatTensor<B>,
}

/// The updated parameter and moments.
#[derive(ExtensionType, Debug, Clone)]
pub struct AdamUpdated<B: Backend> {
    pub param: FloatTensor<B>,
    pub m: FloatTensor<B>,
    pub v: FloatTensor<B>,
}

/// The scalars of one step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamScalars {
    pub lr: f32,
    pub beta_1: f32,
    pub beta_2: f32,
    pub epsilon: f32,
    /// The step, 1 on the first.
    pub time: i32,
}

impl AdamScalars {
    /// `(c₂, f)` of the module docs, in `f32` as burn computes them.
    fn corrections(&self) -> (f32, f32) {
        let c2 = (1.0 - self.beta_2.powi(self.time)).sqrt();
        (c2, c2 / (1.0 - self.beta_1.powi(self.time)))
    }
}

/// Backends with the fused Adam step of this module.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait AdamBackend: Backend {
    /// One Adam step. Default: burn's tensor ops in burn's order.
    fn adam_step(#[extension_type] t: AdamTensors<Self>, s: AdamScalars) -> AdamUpdated<Self> {
        composed::<Self>(t, s)
    }
}

/// burn-optim's sequence of ops (the trait's default body).
fn composed<B: Backend>(
    AdamTensors { param, grad, m, v }: AdamTensors<B>,
    s: AdamScalars,
) -> AdamUpdated<B> {
    let m = B::float_add(
        B::float_mul_scalar(m, s.beta_1.into()),
        B::float_mul_scalar(grad.clone(), (1.0 - s.beta_1).into()),
    );
    let v = B::float_add(
        B::float_mul_scalar(v, s.beta_2.into()),
        B::float_mul_scalar(B::float_mul(grad.clone(), grad), (1.0 - s.beta_2).into()),
    );
    let (c2, f) = s.corrections();
    let step = B::float_div(
        B::float_mul_scalar(m.clone(), f.into()),
        B::float_add_scalar(B::float_sqrt(v.clone()), (s.epsilon * c2).into()),
    );
    let param = B::float_sub(param, B::float_mul_scalar(step, s.lr.into()));
    AdamUpdated { param, m, v }
}

/// The pass on host memory: `p`, `m` and `v` in place.
fn host_step(p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32], s: AdamScalars) {
    let (c2, f) = s.corrections();
    let (b1, b2) = (s.beta_1, s.beta_2);
    let (a1, a2) = (1.0 - b1, 1.0 - b2);
    let eps = s.epsilon * c2;
    p.par_chunks_mut(CHUNK)
        .zip(g.par_chunks(CHUNK))
        .zip(m.par_chunks_mut(CHUNK).zip(v.par_chunks_mut(CHUNK)))
        .for_each(|((p, g), (m, v))| {
            for (((p, g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
                *m = *m * b1 + *g * a1;
                *v = *v * b2 + (*g * *g) * a2;
                *p -= ((*m * f) / (v.sqrt() + eps)) * s.lr;
            }
        });
}

impl<H: HostIo> AdamBackend for H {
    fn adam_step(
        AdamTensors { param, grad, m, v }: AdamTensors<Self>,
        s: AdamScalars,
    ) -> AdamUpdated<Self> {
        // The three state tensors are rewritten where they lie when the backend lets us
        // (`HostIo::in_place`); nesting the closures keeps all three borrowed at once.
        let g = H::read(grad);
        let (mut m_out, mut v_out) = (None, None);
        let param = H::in_place(param, |p| {
            m_out = Some(H::in_place(m, |mv| {
                v_out = Some(H::in_place(v, |vv| host_step(p, &g, mv, vv, s)));
            }));
        });
        AdamUpdated {
            param,
            m: m_out.expect("the closures ran"),
            v: v_out.expect("the closures ran"),
        }
    }
}

/// The GPU backend composes burn's tensor ops (the trait's default body).
impl AdamBackend for Cube {}

/// Optimizers step untracked tensors; under autodiff the step runs on the inner backend.
impl<B: Backend + AdamBackend, C: CheckpointStrategy> AdamBackend for Autodiff<B, C> {
    fn adam_step(t: AdamTensors<Self>, s: AdamScalars) -> AdamUpdated<Self> {
        let inner = AdamTensors {
            param: t.param.into_primitive(),
            grad: t.grad.into_primitive(),
            m: t.m.into_primitive(),
            v: t.v.into_primitive(),
        };
        let out = B::adam_step(inner, s);
        AdamUpdated {
            param: Self::from_inner(out.param),
            m: Self::from_inner(out.m),
            v: Self::from_inner(out.v),
        }
    }
}

/// Adam with burn's formula and state in one pass per tensor (see the module docs). No
/// weight decay, no AMSGrad: what the TexAvatars and GaussianAvatars recipes use.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FusedAdam {
    pub beta_1: f32,
    pub beta_2: f32,
    pub epsilon: f32,
}

impl FusedAdam {
    /// The whole-module optimizer, as [`burn::optim::AdamConfig::init`] (without gradient
    /// clipping, which the recipes do not use).
    pub fn init(self) -> ModuleOptimizer {
        ModuleOptimizer::from(self)
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        let (m, v, time) = match state {
            Some(AdamState { momentum }) => (momentum.moment_1, momentum.moment_2, momentum.time),
            None => (grad.zeros_like(), grad.zeros_like(), 0),
        };
        let time = time + 1;
        let s = AdamScalars {
            lr: lr as f32,
            beta_1: self.beta_1,
            beta_2: self.beta_2,
            epsilon: self.epsilon,
            time: i32::try_from(time).unwrap_or(i32::MAX),
        };
        let t = AdamTensors {
            param: tensor.into_dispatch(),
            grad: grad.into_dispatch(),
            m: m.into_dispatch(),
            v: v.into_dispatch(),
        };
        let out = <burn::backend::Dispatch as AdamBackend>::adam_step(t, s);
        let momentum = AdaptiveMomentumState::new(
            time,
            Tensor::from_dispatch(out.m),
            Tensor::from_dispatch(out.v),
        );
        (
            Tensor::from_dispatch(out.param),
            Some(AdamState::new(momentum)),
        )
    }

    fn to_device<const D: usize>(mut state: Self::State<D>, device: &Device) -> Self::State<D> {
        state.momentum = state.momentum.to_device(device);
        state
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::optim::AdamConfig;
    use burn::tensor::TensorData;

    const BETAS: (f32, f32, f32) = (0.9, 0.99, 1e-8);

    fn values(n: usize, phase: f32) -> Vec<f32> {
        (0..n).map(|i| ((i as f32 + phase) * 0.73).sin()).collect()
    }

    fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    fn max_rel(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / y.abs().max(1e-3))
            .fold(0.0, f32::max)
    }

    /// Three steps of [`FusedAdam`] against burn's own `Adam` (the reference twin, from
    /// `AdamConfig::build`): parameters, both moments and the step count. The tensor is
    /// larger than one `CHUNK`, and the first step starts from no state.
    fn matches_burn(device: Device) {
        let (b1, b2, eps) = BETAS;
        let burn_adam = AdamConfig::new()
            .with_beta_1(b1)
            .with_beta_2(b2)
            .with_epsilon(eps)
            .build();
        let fused = FusedAdam {
            beta_1: b1,
            beta_2: b2,
            epsilon: eps,
        };
        let shape = [3, CHUNK / 2 + 5];
        let n = shape[0] * shape[1];
        let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, shape), &device);
        let (mut p_ref, mut p) = (t(values(n, 0.0)), t(values(n, 0.0)));
        let (mut s_ref, mut s) = (None, None);
        for step in 0..3 {
            let g = t(values(n, 1.5 + step as f32));
            let lr = 1e-2 / (step + 1) as f64;
            (p_ref, s_ref) = burn_adam.step(lr, p_ref, g.clone(), s_ref);
            (p, s) = fused.step(lr, p, g, s);
        }
        assert!(max_rel(&host(p.clone()), &host(p_ref.clone())) < 1e-6);
        let (a, b) = (s.expect("state").momentum, s_ref.expect("state").momentum);
        assert_eq!(a.time, b.time);
        assert!(max_rel(&host(a.moment_1), &host(b.moment_1)) < 1e-6);
        assert!(max_rel(&host(a.moment_2), &host(b.moment_2)) < 1e-6);
    }

    #[test]
    fn matches_burns_adam_on_flex() {
        matches_burn(Device::flex());
    }

    #[test]
    fn matches_burns_adam_on_ndarray() {
        matches_burn(Device::ndarray());
    }

    /// An optimizer record written by burn's Adam (checkpoints from before this optimizer)
    /// loads into [`FusedAdam`], and the next step equals burn's Adam continuing from its
    /// own state: whole-module optimizers, a `Linear` layer, under autodiff on flex.
    #[test]
    fn loads_a_record_of_burns_adam_and_continues_like_it() {
        use burn::nn::{Linear, LinearConfig};
        use burn::optim::GradientsParams;

        let device = Device::flex().autodiff();
        let (b1, b2, eps) = BETAS;
        let burn_adam = || {
            AdamConfig::new()
                .with_beta_1(b1)
                .with_beta_2(b2)
                .with_epsilon(eps)
                .init()
        };
        let input =
            |phase| Tensor::<2>::from_data(TensorData::new(values(12, phase), [3, 4]), &device);
        let grads = |layer: &Linear, phase| {
            let loss = layer.forward(input(phase)).powf_scalar(2.0).mean();
            GradientsParams::from_grads(loss.backward(), layer)
        };
        let mut layer = LinearConfig::new(4, 5).init(&device);
        let mut reference = burn_adam();
        for step in 0..2 {
            layer = reference.step(1e-2, layer.clone(), grads(&layer, step as f32));
        }
        let mut fused = FusedAdam {
            beta_1: b1,
            beta_2: b2,
            epsilon: eps,
        }
        .init()
        .load_record(reference.to_record());
        let a = reference.step(1e-2, layer.clone(), grads(&layer, 5.0));
        let b = fused.step(1e-2, layer.clone(), grads(&layer, 5.0));
        let params = |l: Linear| {
            let mut v = host(l.weight.val());
            v.extend(host(l.bias.expect("bias").val()));
            v
        };
        let before = params(layer.clone());
        let (a, b) = (params(a), params(b));
        assert!(
            a.iter().zip(&before).any(|(x, y)| x != y),
            "the step moved nothing"
        );
        assert!(max_rel(&b, &a) < 1e-6);
    }

    /// The trait's default body (what wgpu runs) against the host pass, on flex, at step 4.
    #[test]
    fn default_body_matches_the_host_pass() {
        use burn::backend::Flex as F;
        use burn::backend::ops::FloatTensorOps;
        let n = 1000;
        let x =
            |phase| F::float_from_data(TensorData::new(values(n, phase), [n]), &Default::default());
        let v_pos = || F::float_abs(x(3.0));
        let t = || AdamTensors {
            param: x(0.0),
            grad: x(1.0),
            m: x(2.0),
            v: v_pos(),
        };
        let s = AdamScalars {
            lr: 1e-3,
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-8,
            time: 4,
        };
        let (a, b) = (<F as AdamBackend>::adam_step(t(), s), composed::<F>(t(), s));
        for (a, b) in [(a.param, b.param), (a.m, b.m), (a.v, b.v)] {
            assert!(max_rel(&F::floats(a), &F::floats(b)) < 1e-6);
        }
    }

    /// Against PyTorch's form of the update (`torch/optim/adam.py`, `_single_tensor_adam`
    /// with `capturable=False`): `p -= (lr / bc1) · m / (sqrt(v) / sqrt(bc2) + eps)`, with
    /// `bc_i = 1 - β_iᵗ`, here in `f64` from the same moments.
    #[test]
    fn equals_pytorchs_form_of_the_update() {
        let (b1, b2, eps) = BETAS;
        let n = 257;
        let (p0, g, m0, v0) = (
            values(n, 0.0),
            values(n, 1.0),
            values(n, 2.0),
            values(n, 3.0),
        );
        let v0: Vec<f32> = v0.iter().map(|v| v.abs()).collect();
        let s = AdamScalars {
            lr: 3e-3,
            beta_1: b1,
            beta_2: b2,
            epsilon: eps,
            time: 7,
        };
        let (mut p, mut m, mut v) = (p0.clone(), m0.clone(), v0.clone());
        host_step(&mut p, &g, &mut m, &mut v, s);
        let t = s.time;
        let (bc1, bc2) = (1.0 - (b1 as f64).powi(t), 1.0 - (b2 as f64).powi(t));
        for i in 0..n {
            let g = g[i] as f64;
            let m = b1 as f64 * m0[i] as f64 + (1.0 - b1 as f64) * g;
            let v = b2 as f64 * v0[i] as f64 + (1.0 - b2 as f64) * g * g;
            let denom = v.sqrt() / bc2.sqrt() + eps as f64;
            let torch = p0[i] as f64 - (s.lr as f64 / bc1) * m / denom;
            assert!(
                (p[i] as f64 - torch).abs() < 1e-6,
                "{i}: {} vs {torch}",
                p[i]
            );
        }
    }
}
