//! The splat operator as a burn backend extension.
//!
//! [`SplatBackend`] is implemented for the CPU backends (ndarray and flex, by the tile renderer
//! of [`crate::splat::cpu`]), for burn's cubecl backend (wgpu, by the kernels of
//! `texavatars-kernels` through [`crate::splat::gpu`]) and for `Autodiff<B>` with a
//! handwritten backward that calls the inner backend's [`SplatBackend::splat_backward`].

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::strategy::CheckpointStrategy,
    ops::{Backward, NodeGuard},
};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{
    AutodiffBackend, Backend, ExtensionType, Flex, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Shape, Slice, TensorData};

use burn_cubecl::CubeBackend;

use texavatars_cpu::autodiff;
use texavatars_cpu::host::{HostFloats, HostIo, floats, ints};

use crate::camera::Camera;
use crate::splat::{cpu, gpu};

/// Host-side parameters of one render: the camera and the background colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplatParams {
    /// The camera.
    pub camera: Camera,
    /// Background colour (RGB), composited behind the Gaussians.
    pub background: [f32; 3],
}

/// The differentiable inputs of a render.
///
/// `screen` is a gradient tap, as 3DGS's `screenspace_points` (`gaussian_renderer/
/// __init__.py`, `render`: a zero tensor passed to the rasterizer as `means2D`, whose values
/// the rasterizer never reads): the render does not depend on its values, and its gradient
/// is the loss's gradient w.r.t. each Gaussian's projected centre in normalised device
/// coordinates, the quantity 3DGS and GaussianAvatars densify by. Pass zeros; track it
/// (`require_grad`) to read that gradient.
///
/// # Shapes
/// - `means`: [N, 3] world-space centres
/// - `cov6`: [N, 6] world-space covariances (xx, xy, xz, yy, yz, zz)
/// - `colors`: [N, 3] RGB
/// - `opacities`: `[N]` opacity after the sigmoid
/// - `screen`: [N, 2] the gradient tap (values unused)
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatInputs<B: Backend> {
    pub means: FloatTensor<B>,
    pub cov6: FloatTensor<B>,
    pub colors: FloatTensor<B>,
    pub opacities: FloatTensor<B>,
    pub screen: FloatTensor<B>,
}

/// What a forward pass keeps for its backward pass.
///
/// # Shapes
/// - `out`: [H, W, 4] RGB and final transmittance
/// - `projected`: [N, P] per-Gaussian projection (layout private to each implementation)
/// - `gaussian_from_isect`: `[M]` (at least one element) the Gaussian of each tile intersection
/// - `tile_ranges`: [T, 2] `[start, end)` per tile
/// - `last`: [H, W] one past the last composited intersection per pixel, tile-relative
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatState<B: Backend> {
    pub out: FloatTensor<B>,
    pub projected: FloatTensor<B>,
    pub gaussian_from_isect: IntTensor<B>,
    pub tile_ranges: IntTensor<B>,
    pub last: IntTensor<B>,
}

/// Gradients of the loss w.r.t. the inputs (same shapes as [`SplatInputs`]); `screen` is
/// the gradient w.r.t. the projected centres (u, v) in pixels, `[N, 2]` (zero for culled
/// Gaussians).
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatGrads<B: Backend> {
    pub means: FloatTensor<B>,
    pub cov6: FloatTensor<B>,
    pub colors: FloatTensor<B>,
    pub opacities: FloatTensor<B>,
    pub screen: FloatTensor<B>,
}

/// Backends that can render Gaussians with the fused tile rasterizer.
#[backend_extension(NdArray, Flex, Cube, Autodiff)]
pub trait SplatBackend: Backend {
    /// Differentiable render: returns [H, W, 4] (RGB, final transmittance).
    fn splat(
        #[extension_type] inputs: SplatInputs<Self>,
        params: SplatParams,
    ) -> FloatTensor<Self> {
        Self::splat_forward(inputs, params).out
    }

    /// [`SplatBackend::splat`] of Gaussians packed as the lifting operator outputs them:
    /// `packed` `[N, 13]` holds means, covariances, colours and opacities in the column
    /// order of `crate::lift::constants` (`OUT_MEAN`, `OUT_COV`, `OUT_RGB`, `OUT_OPACITY`).
    /// Under autodiff the gradient reaches `packed` as one `[N, 13]` tensor: splitting it
    /// into four tracked column slices first would make autodiff build a zero-filled
    /// `[N, 13]` gradient per slice and add the four, a visible share of a `cpu` training
    /// step (docs/performance.md).
    fn splat_packed(
        packed: FloatTensor<Self>,
        screen: FloatTensor<Self>,
        params: SplatParams,
    ) -> FloatTensor<Self> {
        Self::splat(unpacked_inputs::<Self>(packed, screen), params)
    }

    /// Forward pass, keeping what the backward pass needs.
    fn splat_forward(
        #[extension_type] inputs: SplatInputs<Self>,
        params: SplatParams,
    ) -> SplatState<Self>;

    /// Backward pass: `grad_out` [H, W, 4] is dL/d(RGB, T).
    fn splat_backward(
        #[extension_type] inputs: SplatInputs<Self>,
        #[extension_type] state: SplatState<Self>,
        grad_out: FloatTensor<Self>,
        params: SplatParams,
    ) -> SplatGrads<Self>;
}

/// The four column blocks of a packed `[N, 13]` tensor as [`SplatInputs`] (views where the
/// backend slices without copying).
fn unpacked_inputs<B: Backend>(packed: FloatTensor<B>, screen: FloatTensor<B>) -> SplatInputs<B> {
    use crate::lift::constants::{OUT_CHANNELS, OUT_COV, OUT_MEAN, OUT_OPACITY, OUT_RGB};
    let n = packed.shape()[0];
    debug_assert_eq!(packed.shape()[1], OUT_CHANNELS);
    let columns = |from: usize, k: usize| {
        B::float_slice(
            packed.clone(),
            &[Slice::from(0..n), Slice::from(from..from + k)],
        )
    };
    SplatInputs {
        means: columns(OUT_MEAN, 3),
        cov6: columns(OUT_COV, 6),
        colors: columns(OUT_RGB, 3),
        opacities: B::float_reshape(columns(OUT_OPACITY, 1), Shape::from(vec![n])),
        screen,
    }
}

// ---------------------------------------------------------------------------------------------
// CPU backends: the tile renderer on host memory.

/// Floats per Gaussian in the CPU `projected` tensor.
const CPU_PROJECTED: usize = 16;

fn pack_projections(p: &[Option<cpu::Projection>]) -> Vec<f32> {
    use rayon::prelude::*;
    let mut v = vec![0.0f32; p.len() * CPU_PROJECTED];
    v.par_chunks_mut(CPU_PROJECTED)
        .zip(p)
        .with_min_len(1024)
        .for_each(|(row, p)| {
            if let Some(p) = p {
                let s = &p.splat;
                row.copy_from_slice(&[
                    s.u,
                    s.v,
                    s.a,
                    s.b,
                    s.c,
                    s.opacity,
                    s.rgb[0],
                    s.rgb[1],
                    s.rgb[2],
                    s.sigma_cut,
                    p.depth,
                    f32::from_bits(p.pixels.x0),
                    f32::from_bits(p.pixels.y0),
                    f32::from_bits(p.pixels.x1),
                    f32::from_bits(p.pixels.y1),
                    1.0,
                ]);
            }
        });
    v
}

fn unpack_projections(v: &[f32]) -> Vec<Option<cpu::Projection>> {
    v.chunks(CPU_PROJECTED)
        .map(|r| {
            (r[15] == 1.0).then(|| cpu::Projection {
                splat: cpu::Splat2d {
                    u: r[0],
                    v: r[1],
                    a: r[2],
                    b: r[3],
                    c: r[4],
                    opacity: r[5],
                    rgb: [r[6], r[7], r[8]],
                    sigma_cut: r[9],
                },
                depth: r[10],
                pixels: cpu::PixelBox {
                    x0: r[11].to_bits(),
                    y0: r[12].to_bits(),
                    x1: r[13].to_bits(),
                    y1: r[14].to_bits(),
                },
            })
        })
        .collect()
}

struct HostInputs<H: HostIo> {
    means: HostFloats<H>,
    cov6: HostFloats<H>,
    colors: HostFloats<H>,
    opacities: HostFloats<H>,
}

impl<H: HostIo> HostInputs<H> {
    fn read(i: SplatInputs<H>) -> Self {
        Self {
            means: H::read(i.means),
            cov6: H::read(i.cov6),
            colors: H::read(i.colors),
            opacities: H::read(i.opacities),
        }
    }

    fn scene(&self) -> cpu::Scene<'_> {
        cpu::Scene {
            means: &self.means,
            cov6: &self.cov6,
            colors: &self.colors,
            opacities: &self.opacities,
        }
    }
}

/// Forward of the CPU tile renderer for any host backend.
pub fn cpu_forward<H: HostIo>(inputs: SplatInputs<H>, params: SplatParams) -> SplatState<H> {
    let device = inputs.means.device();
    let host = HostInputs::read(inputs);
    let fwd = cpu::forward(&host.scene(), &params.camera, params.background);
    let (w, h) = (params.camera.width as usize, params.camera.height as usize);
    let n = host.opacities.len();
    let m = fwd.bins.gaussian_from_isect.len();
    let t = fwd.bins.tile_ranges.len();
    let mut isects = fwd.bins.gaussian_from_isect;
    if isects.is_empty() {
        isects.push(0);
    }
    SplatState {
        out: floats::<H>(fwd.out, &[h, w, 4], &device),
        projected: floats::<H>(
            pack_projections(&fwd.projections),
            &[n, CPU_PROJECTED],
            &device,
        ),
        gaussian_from_isect: ints::<H>(isects, &[m.max(1)], &device),
        tile_ranges: ints::<H>(fwd.bins.tile_ranges.concat(), &[t, 2], &device),
        last: ints::<H>(fwd.last, &[h, w], &device),
    }
}

/// Backward of the CPU tile renderer for any host backend.
pub fn cpu_backward<H: HostIo>(
    inputs: SplatInputs<H>,
    state: SplatState<H>,
    grad_out: FloatTensor<H>,
    params: SplatParams,
) -> SplatGrads<H> {
    let device = inputs.means.device();
    let host = HostInputs::read(inputs);
    let n = host.opacities.len();
    let tile_ranges: Vec<[u32; 2]> = H::ints(state.tile_ranges)
        .chunks(2)
        .map(|c| [c[0], c[1]])
        .collect();
    let m = tile_ranges.last().map_or(0, |r| r[1] as usize);
    let mut gaussian_from_isect = H::ints(state.gaussian_from_isect);
    gaussian_from_isect.truncate(m);
    let fwd = cpu::Forward {
        out: H::floats(state.out),
        projections: unpack_projections(&H::read(state.projected)),
        bins: cpu::Bins {
            gaussian_from_isect,
            tile_ranges,
        },
        last: H::ints(state.last),
    };
    let grad_out = H::read(grad_out);
    let g = cpu::backward(
        &host.scene(),
        &params.camera,
        params.background,
        &fwd,
        &grad_out,
    );
    SplatGrads {
        means: floats::<H>(g.means, &[n, 3], &device),
        cov6: floats::<H>(g.cov6, &[n, 6], &device),
        colors: floats::<H>(g.colors, &[n, 3], &device),
        opacities: floats::<H>(g.opacities, &[n], &device),
        screen: floats::<H>(g.screen, &[n, 2], &device),
    }
}

/// The CPU backends share one implementation: the tile renderer on host memory.
macro_rules! cpu_splat_backend {
    ($($backend:ty),*) => {$(
        impl SplatBackend for $backend {
            fn splat_forward(inputs: SplatInputs<Self>, params: SplatParams) -> SplatState<Self> {
                cpu_forward::<Self>(inputs, params)
            }

            fn splat_backward(
                inputs: SplatInputs<Self>,
                state: SplatState<Self>,
                grad_out: FloatTensor<Self>,
                params: SplatParams,
            ) -> SplatGrads<Self> {
                cpu_backward::<Self>(inputs, state, grad_out, params)
            }
        }
    )*};
}

cpu_splat_backend!(NdArray, Flex);

// ---------------------------------------------------------------------------------------------
// cubecl (wgpu): the CubeCL kernels of `texavatars-kernels`.

impl SplatBackend for CubeBackend {
    fn splat_forward(inputs: SplatInputs<Self>, params: SplatParams) -> SplatState<Self> {
        let f = gpu::forward(
            inputs.means,
            inputs.cov6,
            inputs.colors,
            inputs.opacities,
            &params.camera,
            params.background,
        );
        SplatState {
            out: f.out,
            projected: f.projected,
            gaussian_from_isect: f.isect_ids,
            tile_ranges: f.tile_ranges,
            last: f.last,
        }
    }

    fn splat_backward(
        inputs: SplatInputs<Self>,
        state: SplatState<Self>,
        grad_out: FloatTensor<Self>,
        params: SplatParams,
    ) -> SplatGrads<Self> {
        let fwd = gpu::GpuForward {
            out: state.out,
            projected: state.projected,
            isect_ids: state.gaussian_from_isect,
            tile_ranges: state.tile_ranges,
            last: state.last,
        };
        let [means, cov6, colors, opacities, grad2d] = gpu::backward(
            inputs.means,
            inputs.cov6,
            inputs.colors,
            inputs.opacities,
            &params.camera,
            params.background,
            &fwd,
            grad_out,
        );
        let n = grad2d.shape()[0];
        SplatGrads {
            means,
            cov6,
            colors,
            opacities,
            screen: first_columns::<Self>(grad2d, n, 2),
        }
    }
}

/// On burn's fusion backend the splat runs eagerly on the inner backend (see
/// [`crate::fusion`]): the forward sizes its intersection buffers from a count it reads back,
/// so its outputs' shapes cannot be declared before it runs, as a lazy fusion op requires.
#[cfg(feature = "fusion")]
impl<B: burn::backend::fusion::FusionBackend + SplatBackend> SplatBackend
    for burn::backend::fusion::Fusion<B>
{
    fn splat_forward(inputs: SplatInputs<Self>, params: SplatParams) -> SplatState<Self> {
        use crate::fusion::{device_of, register_float, register_int};
        let device = device_of::<B>(&inputs.means);
        let s = B::splat_forward(resolve_inputs::<B>(inputs), params);
        SplatState {
            out: register_float::<B>(s.out, &device),
            projected: register_float::<B>(s.projected, &device),
            gaussian_from_isect: register_int::<B>(s.gaussian_from_isect, &device),
            tile_ranges: register_int::<B>(s.tile_ranges, &device),
            last: register_int::<B>(s.last, &device),
        }
    }

    fn splat_backward(
        inputs: SplatInputs<Self>,
        state: SplatState<Self>,
        grad_out: FloatTensor<Self>,
        params: SplatParams,
    ) -> SplatGrads<Self> {
        use crate::fusion::{device_of, register_float, resolve_float, resolve_int};
        let device = device_of::<B>(&inputs.means);
        let state = SplatState {
            out: resolve_float::<B>(state.out),
            projected: resolve_float::<B>(state.projected),
            gaussian_from_isect: resolve_int::<B>(state.gaussian_from_isect),
            tile_ranges: resolve_int::<B>(state.tile_ranges),
            last: resolve_int::<B>(state.last),
        };
        let g = B::splat_backward(
            resolve_inputs::<B>(inputs),
            state,
            resolve_float::<B>(grad_out),
            params,
        );
        SplatGrads {
            means: register_float::<B>(g.means, &device),
            cov6: register_float::<B>(g.cov6, &device),
            colors: register_float::<B>(g.colors, &device),
            opacities: register_float::<B>(g.opacities, &device),
            screen: register_float::<B>(g.screen, &device),
        }
    }
}

/// The inner backend's tensors behind fusion splat inputs.
#[cfg(feature = "fusion")]
fn resolve_inputs<B: burn::backend::fusion::FusionBackend>(
    inputs: SplatInputs<burn::backend::fusion::Fusion<B>>,
) -> SplatInputs<B> {
    use crate::fusion::resolve_float;
    SplatInputs {
        means: resolve_float::<B>(inputs.means),
        cov6: resolve_float::<B>(inputs.cov6),
        colors: resolve_float::<B>(inputs.colors),
        opacities: resolve_float::<B>(inputs.opacities),
        screen: resolve_float::<B>(inputs.screen),
    }
}

/// The first `k` columns of an `[n, _]` tensor.
fn first_columns<B: Backend>(t: FloatTensor<B>, n: usize, k: usize) -> FloatTensor<B> {
    B::float_slice(t, &[Slice::from(0..n), Slice::from(0..k)])
}

// ---------------------------------------------------------------------------------------------
// Autodiff: the handwritten backward.

texavatars_cpu::backward_op!(
    SplatBackward<5>: SplatBackend,
    (SplatInputs<B>, SplatState<B>, SplatParams),
    |(inputs, state, params), grad| {
        let g = B::splat_backward(inputs, state, grad, params);
        let screen = screen_in_ndc::<B>(&g.screen, &params);
        [g.means, g.cov6, g.colors, g.opacities, screen]
    }
);

/// The tap's gradient in 3DGS's units: d/d(NDC) = d/d(pixel) * (W/2, H/2)
/// (diff-gaussian-rasterization, `cuda_rasterizer/backward.cu`, `renderCUDA`:
/// `ddelx_dx = 0.5 * W`, `ddely_dy = 0.5 * H`).
fn screen_in_ndc<B: Backend>(pixels: &FloatTensor<B>, params: &SplatParams) -> FloatTensor<B> {
    let (w, h) = (params.camera.width as f32, params.camera.height as f32);
    let device = pixels.device();
    let half = B::float_from_data(TensorData::new(vec![0.5 * w, 0.5 * h], [1, 2]), &device);
    B::float_mul(pixels.clone(), half)
}

texavatars_cpu::backward_op!(
    /// The backward of [`SplatBackend::splat_packed`]: the inner backend's gradients of the
    /// four column blocks, joined into one `[N, 13]` gradient of `packed`.
    SplatPackedBackward<2>: SplatBackend,
    (SplatInputs<B>, SplatState<B>, SplatParams),
    |(inputs, state, params), grad| {
        let g = B::splat_backward(inputs, state, grad, params);
        let n = g.opacities.shape()[0];
        let opacities = B::float_reshape(g.opacities, Shape::from(vec![n, 1]));
        // The order of `crate::lift::constants`: OUT_MEAN, OUT_COV, OUT_RGB, OUT_OPACITY.
        let packed = B::float_cat(vec![g.means, g.cov6, g.colors, opacities], 1);
        [packed, screen_in_ndc::<B>(&g.screen, &params)]
    }
);

fn inner_inputs<B: Backend, C: CheckpointStrategy>(
    i: SplatInputs<Autodiff<B, C>>,
) -> SplatInputs<B> {
    SplatInputs {
        means: i.means.into_primitive(),
        cov6: i.cov6.into_primitive(),
        colors: i.colors.into_primitive(),
        opacities: i.opacities.into_primitive(),
        screen: i.screen.into_primitive(),
    }
}

/// The forward pass of one of the autodiff splat ops (`op`, whose parents are `nodes`): the
/// renderer's whole state is kept for the backward pass when a parent is tracked, only the
/// image otherwise.
fn splat_op<B, C, Op, const N: usize>(
    op: Op,
    nodes: [NodeGuard; N],
    inner: SplatInputs<B>,
    params: SplatParams,
) -> FloatTensor<Autodiff<B, C>>
where
    B: Backend + SplatBackend,
    C: CheckpointStrategy,
    Op: Backward<B, N, State = (SplatInputs<B>, SplatState<B>, SplatParams)>,
{
    let run = |i| B::splat_forward(i, params);
    let keep = |i, state: SplatState<B>| {
        let out = state.out.clone();
        ((i, state, params), out)
    };
    autodiff::forward_with::<B, C, _, _, _, N>(op, nodes, inner, run, keep, |state| state.out)
}

impl<B: Backend + SplatBackend, C: CheckpointStrategy> SplatBackend for Autodiff<B, C> {
    fn splat(inputs: SplatInputs<Self>, params: SplatParams) -> FloatTensor<Self> {
        let nodes = [
            inputs.means.node(),
            inputs.cov6.node(),
            inputs.colors.node(),
            inputs.opacities.node(),
            inputs.screen.node(),
        ];
        splat_op::<B, C, _, 5>(SplatBackward, nodes, inner_inputs(inputs), params)
    }

    fn splat_packed(
        packed: FloatTensor<Self>,
        screen: FloatTensor<Self>,
        params: SplatParams,
    ) -> FloatTensor<Self> {
        let nodes = [packed.node(), screen.node()];
        let inner = unpacked_inputs::<B>(packed.into_primitive(), screen.into_primitive());
        splat_op::<B, C, _, 2>(SplatPackedBackward, nodes, inner, params)
    }

    fn splat_forward(inputs: SplatInputs<Self>, params: SplatParams) -> SplatState<Self> {
        let s = B::splat_forward(inner_inputs(inputs), params);
        SplatState {
            out: Self::from_inner(s.out),
            projected: Self::from_inner(s.projected),
            gaussian_from_isect: s.gaussian_from_isect,
            tile_ranges: s.tile_ranges,
            last: s.last,
        }
    }

    fn splat_backward(
        inputs: SplatInputs<Self>,
        state: SplatState<Self>,
        grad_out: FloatTensor<Self>,
        params: SplatParams,
    ) -> SplatGrads<Self> {
        let state = SplatState {
            out: state.out.into_primitive(),
            projected: state.projected.into_primitive(),
            gaussian_from_isect: state.gaussian_from_isect,
            tile_ranges: state.tile_ranges,
            last: state.last,
        };
        let g = B::splat_backward(
            inner_inputs(inputs),
            state,
            grad_out.into_primitive(),
            params,
        );
        SplatGrads {
            means: Self::from_inner(g.means),
            cov6: Self::from_inner(g.cov6),
            colors: Self::from_inner(g.colors),
            opacities: Self::from_inner(g.opacities),
            screen: Self::from_inner(g.screen),
        }
    }
}
