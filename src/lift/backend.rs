//! The lifting operator as a burn backend extension.
//!
//! [`LiftBackend`] is implemented for the CPU backends (ndarray and flex) by the fused code of
//! [`crate::lift::cpu`], and for `Autodiff<B>` with a handwritten backward that calls the
//! inner backend's [`LiftBackend::lift_backward`]. On burn's cubecl backend (wgpu) the CubeCL
//! kernels are not written yet: wgpu tensors go through the same fused CPU code with a host
//! round trip, so the operator works (slowly) on every backend meanwhile.

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, ExtensionType, Flex, NdArray, TensorMetadata, backend_extension,
};
use burn_cubecl::CubeBackend;

use crate::kernels::lift::constants::{LOCAL_CHANNELS, OUT_CHANNELS};
use crate::lift::{LiftParams, cpu, gpu};
use texavatars_cpu::autodiff;
use texavatars_cpu::host::{HostIo, floats};

/// Gradients of a lift's two inputs.
///
/// # Shapes
/// - `local`: [14, R, R]; `vertices`: [V, 3]
#[derive(ExtensionType, Debug, Clone)]
pub struct LiftGradients<B: Backend> {
    pub local: FloatTensor<B>,
    pub vertices: FloatTensor<B>,
}

/// Backends with the fused lifting operator.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait LiftBackend: Backend {
    /// Local maps [14, R, R] and posed vertices [V, 3] → packed Gaussians [N, 13]
    /// (mean 3, cov 6, RGB 3, opacity 1).
    fn lift(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        params: LiftParams,
    ) -> FloatTensor<Self>;

    /// Backward: `grad_out` [N, 13] → gradients of the local maps and the vertices.
    fn lift_backward(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        grad_out: FloatTensor<Self>,
        params: LiftParams,
    ) -> LiftGradients<Self>;
}

fn host_lift<H: HostIo>(
    local: FloatTensor<H>,
    vertices: FloatTensor<H>,
    params: LiftParams,
) -> FloatTensor<H> {
    let device = local.device();
    let out = cpu::forward(
        &params.topology,
        params.mode,
        params.frame,
        &H::read(local),
        &H::read(vertices),
    );
    floats::<H>(out, &[params.topology.len(), OUT_CHANNELS], &device)
}

fn host_lift_backward<H: HostIo>(
    local: FloatTensor<H>,
    vertices: FloatTensor<H>,
    grad_out: FloatTensor<H>,
    params: LiftParams,
) -> LiftGradients<H> {
    let device = local.device();
    let t = &params.topology;
    let (dl, dv) = cpu::backward(
        t,
        params.mode,
        params.frame,
        &H::read(local),
        &H::read(vertices),
        &H::read(grad_out),
    );
    LiftGradients {
        local: floats::<H>(dl, &[LOCAL_CHANNELS, t.res(), t.res()], &device),
        vertices: floats::<H>(dv, &[t.num_vertices, 3], &device),
    }
}

macro_rules! host_lift_backend {
    ($($b:ty),*) => {$(
        impl LiftBackend for $b {
            fn lift(
                local: FloatTensor<Self>,
                vertices: FloatTensor<Self>,
                params: LiftParams,
            ) -> FloatTensor<Self> {
                host_lift::<Self>(local, vertices, params)
            }

            fn lift_backward(
                local: FloatTensor<Self>,
                vertices: FloatTensor<Self>,
                grad_out: FloatTensor<Self>,
                params: LiftParams,
            ) -> LiftGradients<Self> {
                host_lift_backward::<Self>(local, vertices, grad_out, params)
            }
        }
    )*};
}

host_lift_backend!(NdArray, Flex);

impl LiftBackend for CubeBackend {
    fn lift(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        params: LiftParams,
    ) -> FloatTensor<Self> {
        gpu::forward(local, vertices, &params)
    }

    fn lift_backward(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        grad_out: FloatTensor<Self>,
        params: LiftParams,
    ) -> LiftGradients<Self> {
        let (local, vertices) = gpu::backward(local, vertices, grad_out, &params);
        LiftGradients { local, vertices }
    }
}

/// On burn's fusion backend the lift runs eagerly on the inner backend (see
/// [`crate::fusion`]): its inputs are the decoders' outputs, which fusion hands over once
/// computed, and its output feeds the splat, which must run eagerly anyway.
#[cfg(feature = "fusion")]
impl<B: burn::backend::fusion::FusionBackend + LiftBackend> LiftBackend
    for burn::backend::fusion::Fusion<B>
{
    fn lift(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        params: LiftParams,
    ) -> FloatTensor<Self> {
        use crate::fusion::{device_of, register_float, resolve_float};
        let device = device_of::<B>(&local);
        let out = B::lift(
            resolve_float::<B>(local),
            resolve_float::<B>(vertices),
            params,
        );
        register_float::<B>(out, &device)
    }

    fn lift_backward(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        grad_out: FloatTensor<Self>,
        params: LiftParams,
    ) -> LiftGradients<Self> {
        use crate::fusion::{device_of, register_float, resolve_float};
        let device = device_of::<B>(&local);
        let g = B::lift_backward(
            resolve_float::<B>(local),
            resolve_float::<B>(vertices),
            resolve_float::<B>(grad_out),
            params,
        );
        LiftGradients {
            local: register_float::<B>(g.local, &device),
            vertices: register_float::<B>(g.vertices, &device),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

texavatars_cpu::backward_op!(
    LiftBackwardOp<2>: LiftBackend,
    (FloatTensor<B>, FloatTensor<B>, LiftParams),
    |(local, vertices, params), grad| {
        let g = B::lift_backward(local, vertices, grad, params);
        [g.local, g.vertices]
    }
);

impl<B: Backend + LiftBackend, C: CheckpointStrategy> LiftBackend for Autodiff<B, C> {
    fn lift(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        params: LiftParams,
    ) -> FloatTensor<Self> {
        let nodes = [local.node(), vertices.node()];
        let inner = (local.into_primitive(), vertices.into_primitive());
        let run = |(l, v)| B::lift(l, v, params.clone());
        let keep = |(l, v), _: &FloatTensor<B>| (l, v, params.clone());
        autodiff::forward::<B, C, _, _, 2>(LiftBackwardOp, nodes, inner, run, keep)
    }

    fn lift_backward(
        local: FloatTensor<Self>,
        vertices: FloatTensor<Self>,
        grad_out: FloatTensor<Self>,
        params: LiftParams,
    ) -> LiftGradients<Self> {
        let g = B::lift_backward(
            local.into_primitive(),
            vertices.into_primitive(),
            grad_out.into_primitive(),
            params,
        );
        LiftGradients {
            local: Self::from_inner(g.local),
            vertices: Self::from_inner(g.vertices),
        }
    }
}
