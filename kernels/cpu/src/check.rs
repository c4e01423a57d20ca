//! Test support for the layers' fused ops ([`super::bias_act`], [`super::weight_norm`],
//! the convolutions): run an op of two (or three) inputs under autodiff and read its output
//! and the input gradients, so a test compares the op with its reference twin in one line
//! per side.

use burn::backend::Flex;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{Tensor, TensorData};

/// The values of a tensor, row-major.
pub fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

/// The largest difference relative to the largest magnitude of `b` (at least `floor`).
pub fn max_rel(a: &[f32], b: &[f32], floor: f32) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(floor, |m, v| m.max(v.abs()));
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() / scale)
        .fold(0.0, f32::max)
}

/// `op(a, b)`, and the gradients of `sum(op(a, b) · upstream)` with respect to `a` and
/// `b`, as host values `[output, d a, d b]`.
pub fn output_and_gradients<const DA: usize, const DB: usize, const DO: usize>(
    a: &Tensor<DA>,
    b: &Tensor<DB>,
    upstream: &Tensor<DO>,
    op: impl Fn(Tensor<DA>, Tensor<DB>) -> Tensor<DO>,
) -> [Vec<f32>; 3] {
    let (a, b) = (a.clone().require_grad(), b.clone().require_grad());
    let out = op(a.clone(), b.clone());
    let grads = (out.clone() * upstream.clone()).sum().backward();
    [
        host(out),
        host(a.grad(&grads).expect("gradient of the first input")),
        host(b.grad(&grads).expect("gradient of the second input")),
    ]
}

/// Central finite differences of `f(a, b)` against the analytic gradients `[d a, d b]`,
/// every entry of both inputs, within `tol` absolute.
pub fn check_finite_differences(
    inputs: [&[f32]; 2],
    analytic: [&[f32]; 2],
    f: impl Fn(&[f32], &[f32]) -> f64,
    eps: f32,
    tol: f64,
) {
    for (which, grad) in analytic.iter().enumerate() {
        for (i, a) in grad.iter().enumerate() {
            let (mut plus, mut minus) = (inputs.map(<[f32]>::to_vec), inputs.map(<[f32]>::to_vec));
            plus[which][i] += eps;
            minus[which][i] -= eps;
            let fd = (f(&plus[0], &plus[1]) - f(&minus[0], &minus[1])) / (2.0 * eps as f64);
            assert!(
                (fd - *a as f64).abs() < tol,
                "input {which} [{i}]: {fd} vs {a}"
            );
        }
    }
}

/// A layer op of an input, a weight and a bias (or [`super::wn_linear`]'s magnitudes `g`):
/// its output and the gradients of `sum(f(x, w, b) · up)` with respect to all three, as host
/// values `[output, d x, d w, d b]`.
pub fn layer_output_and_gradients<const R: usize, const D: usize>(
    [x, w]: [&Tensor<R>; 2],
    b: &Tensor<D>,
    up: &Tensor<R>,
    f: impl Fn(Tensor<R>, Tensor<R>, Tensor<D>) -> Tensor<R>,
) -> [Vec<f32>; 4] {
    let (x, w, b) = (
        x.clone().require_grad(),
        w.clone().require_grad(),
        b.clone().require_grad(),
    );
    let out = f(x.clone(), w.clone(), b.clone());
    let grads = (out.clone() * up.clone()).sum().backward();
    [
        host(out),
        host(x.grad(&grads).expect("x grad")),
        host(w.grad(&grads).expect("weight grad")),
        host(b.grad(&grads).expect("bias grad")),
    ]
}

/// [`layer_output_and_gradients`] of an op against its reference twin: every one of the
/// four within 1e-5 of the reference's largest magnitude (at least 1e-3).
pub fn compare_outputs(ours: &[Vec<f32>; 4], want: &[Vec<f32>; 4], what: &str) {
    for ((name, a), b) in ["forward", "grad x", "grad weight", "grad bias"]
        .iter()
        .zip(ours)
        .zip(want)
    {
        let e = max_rel(a, b, 1e-3);
        assert!(e < 1e-5, "{what}: {name} differs by {e}");
    }
}

/// A flex tensor (no autodiff) of `shape` holding a fixed pattern of values in about
/// [-1.6, 1.6], shifted by `off` places, plus `add`: the inputs of the tests that compare an
/// op's default bodies (what wgpu runs) with its host passes.
pub fn flex_pattern(shape: &[usize], off: usize, add: f32) -> FloatTensor<Flex> {
    let len = shape.iter().product::<usize>();
    let data: Vec<f32> = (0..len)
        .map(|i| ((((i + off) * 37) % 23) as f32 - 11.0) / 7.0 + add)
        .collect();
    Flex::float_from_data(TensorData::new(data, shape.to_vec()), &Default::default())
}

/// `len` test values `((i·a mod m) - m/2) / d` for `i = 0, 1, …`: a fixed, varied pattern in
/// about `[-m/2d, m/2d]` (integer `m/2`), the inputs of the finite-difference checks.
pub fn pattern(len: usize, a: usize, m: usize, d: f32) -> Vec<f32> {
    (0..len)
        .map(|i| ((i * a % m) as f32 - (m / 2) as f32) / d)
        .collect()
}

/// Two tests of a check over a device, on each CPU backend under autodiff: `$flex` runs
/// `$check(Device::flex().autodiff())`, `$ndarray` runs it on ndarray.
macro_rules! on_cpu_backends {
    ($check:ident: $flex:ident, $ndarray:ident) => {
        #[test]
        fn $flex() {
            $check(burn::tensor::Device::flex().autodiff());
        }

        #[test]
        #[allow(deprecated)]
        fn $ndarray() {
            $check(burn::tensor::Device::ndarray().autodiff());
        }
    };
}
pub(crate) use on_cpu_backends;
