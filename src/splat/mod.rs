//! Differentiable 3D Gaussian splatting.
//!
//! Three implementations with one behaviour (conventions: `tests/fixtures/splat/README.md`,
//! constants: [`constants`]):
//! - [`reference`](mod@reference): dense burn tensor ops on any backend, autodiff by burn (the oracle);
//! - [`cpu`]: the tile renderer in multi-threaded Rust, serving the ndarray and flex backends;
//! - [`gpu`]: the same tile algorithm as CubeCL kernels on burn's wgpu backend.
//!
//! [`render`] picks the fused implementation of the tensors' device through the
//! [`SplatBackend`] extension; its backward is handwritten in both fused implementations.

pub mod backend;
pub mod cpu;
pub mod demo;
pub mod gpu;
pub mod ply;
pub mod reference;
pub mod sh;

pub use backend::{SplatBackend, SplatGrads, SplatInputs, SplatParams, SplatState};
pub use texavatars_kernels::splat::constants;

use burn::backend::Dispatch;
use burn::tensor::Tensor;

use crate::error::{Error, Result};

/// A set of Gaussians as burn tensors, ready to render.
///
/// # Shapes
/// - `means`: [N, 3] world-space centres
/// - `cov6`: [N, 6] world-space covariance (xx, xy, xz, yy, yz, zz)
/// - `colors`: [N, 3] RGB
/// - `opacities`: `[N]` opacity after the sigmoid
#[derive(Clone, Debug)]
pub struct Gaussians {
    pub means: Tensor<2>,
    pub cov6: Tensor<2>,
    pub colors: Tensor<2>,
    pub opacities: Tensor<1>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacities.dims()[0]
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks that the four tensors have consistent shapes.
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        for (name, dims, width) in [
            ("means", self.means.dims(), 3),
            ("cov6", self.cov6.dims(), 6),
            ("colors", self.colors.dims(), 3),
        ] {
            if dims != [n, width] {
                return Err(Error::invalid(
                    "splat inputs",
                    name,
                    format!("expected shape [{n}, {width}], got {dims:?}"),
                ));
            }
        }
        Ok(())
    }
}

/// A rendered image.
///
/// # Shapes
/// - `image`: [H, W, 3]
/// - `transmittance`: [H, W] final transmittance (1 where nothing was drawn)
#[derive(Clone, Debug)]
pub struct Rendered {
    pub image: Tensor<3>,
    pub transmittance: Tensor<2>,
}

impl Rendered {
    /// Splits the packed [H, W, 4] output of the operators.
    pub fn from_packed(out: Tensor<3>) -> Self {
        let [h, w, _] = out.dims();
        Self {
            image: out.clone().narrow(2, 0, 3),
            transmittance: out.narrow(2, 3, 1).reshape([h, w]),
        }
    }
}

fn check(g: &Gaussians, params: &SplatParams) -> Result<()> {
    g.validate()?;
    check_params(params)
}

fn check_params(params: &SplatParams) -> Result<()> {
    params.camera.validate("camera")?;
    if params.background.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid("camera", "background", "must be finite"));
    }
    Ok(())
}

/// Renders with the fused tile rasterizer of the tensors' device (CPU for ndarray and flex,
/// GPU kernels for wgpu), differentiable through its handwritten backward.
pub fn render(g: &Gaussians, params: &SplatParams) -> Result<Rendered> {
    let screen = Tensor::<2>::zeros([g.len(), 2], &g.means.device());
    render_tapped(g, screen, params)
}

/// [`render`] with a gradient tap on the projected centres: `screen` (`[N, 2]`, zeros,
/// tracked with `require_grad`) gets the loss's gradient w.r.t. each Gaussian's projected
/// centre in normalised device coordinates, 3DGS's `viewspace_point_tensor.grad` that
/// GaussianAvatars densifies by ([`SplatInputs`]). Culled Gaussians get zeros.
pub fn render_tapped(g: &Gaussians, screen: Tensor<2>, params: &SplatParams) -> Result<Rendered> {
    check(g, params)?;
    if screen.dims() != [g.len(), 2] {
        return Err(Error::invalid(
            "splat inputs",
            "screen",
            format!("expected shape [{}, 2], got {:?}", g.len(), screen.dims()),
        ));
    }
    let inputs = SplatInputs::<Dispatch> {
        means: g.means.clone().into_dispatch(),
        cov6: g.cov6.clone().into_dispatch(),
        colors: g.colors.clone().into_dispatch(),
        opacities: g.opacities.clone().into_dispatch(),
        screen: screen.into_dispatch(),
    };
    let out = Tensor::<3>::from_dispatch(<Dispatch as SplatBackend>::splat(inputs, *params));
    Ok(Rendered::from_packed(out))
}

/// [`render`] of Gaussians packed as the lifting operator outputs them (`packed` `[N, 13]`,
/// [`crate::lift::lift_packed`]): the same image, with the gradient reaching `packed` as
/// one tensor ([`SplatBackend::splat_packed`]) instead of through four column slices.
pub fn render_packed(packed: Tensor<2>, params: &SplatParams) -> Result<Rendered> {
    use crate::lift::constants::OUT_CHANNELS;
    let [n, k] = packed.dims();
    if k != OUT_CHANNELS {
        return Err(Error::invalid(
            "splat inputs",
            "packed",
            format!("expected shape [N, {OUT_CHANNELS}], got [{n}, {k}]"),
        ));
    }
    check_params(params)?;
    let screen = Tensor::<2>::zeros([n, 2], &packed.device());
    let out = <Dispatch as SplatBackend>::splat_packed(
        packed.into_dispatch(),
        screen.into_dispatch(),
        *params,
    );
    Ok(Rendered::from_packed(Tensor::<3>::from_dispatch(out)))
}

/// Renders with the dense reference (tensor ops, autodiff by burn). Small scenes only.
pub fn render_reference(g: &Gaussians, params: &SplatParams) -> Result<Rendered> {
    check(g, params)?;
    let out = reference::render(
        g.means.clone(),
        g.cov6.clone(),
        g.colors.clone(),
        g.opacities.clone(),
        params,
    );
    Ok(Rendered::from_packed(out))
}

/// [`render_reference`] with the tap of [`render_tapped`]: the projected centres move by
/// `screen` (`[N, 2]`, normalised device coordinates), so its gradient is the oracle of the
/// fused renderers' tap.
pub fn render_reference_tapped(
    g: &Gaussians,
    screen: Tensor<2>,
    params: &SplatParams,
) -> Result<Rendered> {
    check(g, params)?;
    let out = reference::render_tapped(
        g.means.clone(),
        g.cov6.clone(),
        g.colors.clone(),
        g.opacities.clone(),
        Some(screen),
        params,
    );
    Ok(Rendered::from_packed(out))
}

impl Gaussians {
    /// Gaussians of a 3DGS PLY on `device`, with colours from its spherical harmonics
    /// evaluated for a camera at `camera_position` (burn ops, differentiable).
    pub fn from_ply(
        ply: &ply::PlyGaussians,
        camera_position: [f32; 3],
        device: &burn::tensor::Device,
    ) -> Self {
        use burn::tensor::TensorData;
        let n = ply.len();
        let k = ply.sh_coeffs();
        let means = Tensor::<2>::from_data(TensorData::new(ply.means.clone(), [n, 3]), device);
        let coeffs = Tensor::<3>::from_data(TensorData::new(ply.sh.clone(), [n, k, 3]), device);
        let colors = sh::colors(coeffs, ply.sh_degree, means.clone(), camera_position);
        Self {
            means,
            cov6: Tensor::from_data(TensorData::new(ply.cov6(), [n, 6]), device),
            colors,
            opacities: Tensor::from_data(TensorData::new(ply.opacities(), [n]), device),
        }
    }
}
