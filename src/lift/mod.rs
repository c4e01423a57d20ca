//! The lifting operator: local Gaussian attributes regressed in texel space, lifted to 3D by
//! the posed mesh's per-face frames (the paper's "Quasi-Phong Jacobian field", method §4).
//!
//! - `global` mode (default): every texel is lifted with its own face's frame, then the
//!   13-channel payload [cov 6, mean 3, RGB 3, opacity logit 1] is bilinearly sampled at the
//!   kept sample points, blending frames across triangle borders.
//! - `local` mode ("w/o Global UV"): the 14 local channels are sampled first, then each
//!   sample is lifted with the one face it falls in.
//!
//! Implementations, selected by backend through [`LiftBackend`]: the fused CPU code
//! ([`cpu`], ndarray and flex), the CubeCL kernels ([`gpu`], wgpu), both with handwritten
//! backward passes, and the reference in plain burn tensor ops ([`reference`](mod@reference), any backend,
//! differentiated by burn's autodiff). All compute the same function; tests compare them in
//! values and gradients.

pub mod backend;
pub mod cpu;
pub mod gpu;
pub mod reference;
pub mod tables;
pub mod transform;

use std::sync::Arc;

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::mesh::UvMesh;
use crate::texel::{FrameKind, SampleGrid, UvLayout};

pub use crate::kernels::lift::constants;
pub use backend::LiftBackend;

/// Where frames are applied: per texel before sampling, or per sample after it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LiftMode {
    /// Quasi-Phong: lift every texel, then sample (the paper's method).
    #[default]
    Global,
    /// "w/o Global UV": sample local attributes, then lift with the sample's face.
    Local,
}

/// A topology's texel set-up, computed once: the mesh's faces, its UV layout at `R` and the
/// kept samples of the `S x S` grid.
#[derive(Clone, Debug)]
pub struct Topology {
    pub faces: Vec<[u32; 3]>,
    pub num_vertices: usize,
    pub layout: UvLayout,
    pub samples: SampleGrid,
    /// Per texel: whether some sample reads it (a bilinear tap of non-zero weight); built on
    /// first use.
    tapped: std::sync::OnceLock<Vec<bool>>,
    /// Index tables of the GPU implementation, built on first use.
    gpu_tables: std::sync::OnceLock<tables::GpuTables>,
    /// Those tables uploaded, per device (shared by clones of the topology).
    gpu_cache: Arc<gpu::BufferCache>,
}

impl Topology {
    /// Builds the layout at `res` and the `samples x samples` grid.
    pub fn new(mesh: &UvMesh, res: usize, samples: usize) -> Result<Self> {
        let layout = UvLayout::new(mesh, res)?;
        let samples = SampleGrid::new(mesh, &layout, samples)?;
        if samples.is_empty() {
            return Err(Error::invalid(
                "uv layout",
                "samples",
                "no sample is covered by the UV layout (is the mesh's UV set empty or degenerate?)",
            ));
        }
        Ok(Topology {
            faces: mesh.faces.clone(),
            num_vertices: mesh.positions.len(),
            layout,
            samples,
            tapped: std::sync::OnceLock::new(),
            gpu_tables: std::sync::OnceLock::new(),
            gpu_cache: Arc::default(),
        })
    }

    /// Per texel `[R * R]`: whether any kept sample reads it. About half of the texels of a
    /// head's layout are read (the rest lie between UV islands or under dropped samples), so
    /// the CPU lifting skips the others.
    pub fn tapped(&self) -> &[bool] {
        self.tapped.get_or_init(|| {
            let s = &self.samples;
            let mut tapped = vec![false; self.res() * self.res()];
            for (taps, weights) in s.taps.iter().zip(&s.weights) {
                for (&t, &w) in taps.iter().zip(weights) {
                    if w != 0.0 {
                        tapped[t as usize] = true;
                    }
                }
            }
            tapped
        })
    }

    /// The GPU implementation's index tables (built once).
    pub fn gpu_tables(&self) -> &tables::GpuTables {
        self.gpu_tables.get_or_init(|| tables::GpuTables::new(self))
    }

    /// Texel resolution R.
    pub fn res(&self) -> usize {
        self.layout.res
    }

    /// Number of Gaussians (kept samples).
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }
}

/// Host-side parameters of a lift.
#[derive(Clone, Debug)]
pub struct LiftParams {
    pub topology: Arc<Topology>,
    pub mode: LiftMode,
    pub frame: FrameKind,
}

/// Lifted Gaussians.
///
/// # Shapes
/// - `means`: [N, 3]; `cov6`: [N, 6] (xx, xy, xz, yy, yz, zz); `colors`: [N, 3];
///   `opacities`: `[N]` (after the sigmoid)
#[derive(Clone, Debug)]
pub struct Lifted {
    pub means: Tensor<2>,
    pub cov6: Tensor<2>,
    pub colors: Tensor<2>,
    pub opacities: Tensor<1>,
}

impl Lifted {
    /// Splits the packed [N, 13] output.
    pub fn unpack(packed: Tensor<2>) -> Self {
        use constants::*;
        Lifted {
            means: packed.clone().narrow(1, OUT_MEAN, 3),
            cov6: packed.clone().narrow(1, OUT_COV, 6),
            colors: packed.clone().narrow(1, OUT_RGB, 3),
            opacities: packed.narrow(1, OUT_OPACITY, 1).squeeze_dim::<1>(1),
        }
    }
}

fn check_shapes(local: &Tensor<3>, vertices: &Tensor<2>, params: &LiftParams) -> Result<()> {
    let t = &params.topology;
    let r = t.res();
    if local.dims() != [constants::LOCAL_CHANNELS, r, r] {
        return Err(Error::invalid(
            "lift inputs",
            "local",
            format!("expected [14, {r}, {r}], got {:?}", local.dims()),
        ));
    }
    if vertices.dims() != [t.num_vertices, 3] {
        return Err(Error::invalid(
            "lift inputs",
            "vertices",
            format!(
                "expected [{}, 3], got {:?}",
                t.num_vertices,
                vertices.dims()
            ),
        ));
    }
    Ok(())
}

/// Lifts local maps [14, R, R] with posed vertices [V, 3] through the fused operator of the
/// tensors' backend (differentiable w.r.t. both when the backend is autodiff).
pub fn lift(local: Tensor<3>, vertices: Tensor<2>, params: &LiftParams) -> Result<Lifted> {
    lift_packed(local, vertices, params).map(Lifted::unpack)
}

/// [`lift`] without the split: the operator's packed `[N, 13]` output (columns in the order
/// of [`constants`]), as [`crate::splat::render_packed`] takes it.
pub fn lift_packed(
    local: Tensor<3>,
    vertices: Tensor<2>,
    params: &LiftParams,
) -> Result<Tensor<2>> {
    check_shapes(&local, &vertices, params)?;
    let out = <burn::backend::Dispatch as LiftBackend>::lift(
        local.into_dispatch(),
        vertices.into_dispatch(),
        params.clone(),
    );
    Ok(Tensor::from_dispatch(out))
}

/// The same function in plain tensor ops ([`reference::lift`]).
pub fn lift_reference(
    local: Tensor<3>,
    vertices: Tensor<2>,
    params: &LiftParams,
) -> Result<Lifted> {
    check_shapes(&local, &vertices, params)?;
    Ok(Lifted::unpack(reference::lift(local, vertices, params)))
}
