//! The whole avatar: the networks ([`TexAvatarNet`]), the lifting operator's texel set-up
//! and the rasterizer, from (condition, camera, posed mesh) to rendered images.
//!
//! Data flow per frame (method §3-§5): condition and camera → decoders → local maps
//! `[14, R, R]` → lift with the frame's posed vertices (one frame at a time: [`lift`] takes
//! one frame) → 3D Gaussians → splat with the frame's camera on a white background.
//!
//! The texel set-up ([`Topology`]) is built once from the head's UV mesh at `R = R_uv` (the
//! decoders' output side) with `S = R` samples per axis, as in the paper (R = S = 512): one
//! Gaussian per kept sample, their number fixed for the whole training. It is not a
//! parameter: it is rebuilt from the mesh and the config, never saved in a checkpoint.

use std::sync::{Arc, Mutex};

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::constants::BACKGROUND;
use super::net::{LocalMaps, NetConfig, TexAvatarNet};
use crate::camera::Camera;
use crate::data::HeadBatch;
use crate::error::{Error, Result};
use crate::lift::{self, LiftMode, LiftParams, Topology};
use crate::mesh::UvMesh;
use crate::splat::{self, Gaussians, SplatParams};
use crate::texel::FrameKind;

/// Held from seeding the device to the last draw of a seeded initialisation
/// ([`AvatarConfig::init_seeded`]).
static SEEDED_INIT: Mutex<()> = Mutex::new(());

/// The paper's ablation switches (method §7). `true` everywhere is the full method.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ablations {
    /// Lift every texel, then sample (the paper's Quasi-Phong blending, [`LiftMode::Global`]);
    /// `false` is "w/o Global UV" ([`LiftMode::Local`]).
    pub global_uv: bool,
    /// Per-face frames `J_F = [e1 | e2 | n/sqrt|n|]` ([`FrameKind::Jacobian`]); `false` is
    /// "w/o Jacobian": GaussianAvatars' scaled rotation `k R` ([`FrameKind::ScaledRotation`]).
    pub jacobian: bool,
    /// Feed eta to Exp2Code; `false` is "w/o eta": the eta part of the condition is zeroed
    /// ([`super::ConditionConfig::zero_eta`]; the input keeps its width).
    pub eta: bool,
    /// The VGG perceptual loss (switched on late in training, method §6); `false` is
    /// "w/o VGG". Read by the training objective, not by the avatar.
    pub vgg: bool,
    /// FLAME refinement during training ([`crate::train::refine`], on by default as in the
    /// reference and GaussianAvatars); `false` is "w/o FLAME refinement": the tracked
    /// meshes as they are. Read by training, not by the avatar.
    pub flame_refinement: bool,
}

impl Default for Ablations {
    fn default() -> Self {
        Ablations {
            global_uv: true,
            jacobian: true,
            eta: true,
            vgg: true,
            flame_refinement: true,
        }
    }
}

impl Ablations {
    /// The lifting mode these switches select.
    pub fn lift_mode(&self) -> LiftMode {
        if self.global_uv {
            LiftMode::Global
        } else {
            LiftMode::Local
        }
    }

    /// The per-face frame these switches select.
    pub fn frame_kind(&self) -> FrameKind {
        if self.jacobian {
            FrameKind::Jacobian
        } else {
            FrameKind::ScaledRotation
        }
    }
}

/// Everything that defines an [`Avatar`] besides its UV mesh: the networks' sizes and the
/// ablation switches (which fix the lift mode and the frame kind).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvatarConfig {
    /// The networks.
    pub net: NetConfig,
    /// The ablation switches.
    #[serde(default)]
    pub ablations: Ablations,
}

impl AvatarConfig {
    /// The full method with the networks of `net`.
    pub fn new(net: NetConfig) -> Self {
        AvatarConfig {
            net,
            ablations: Ablations::default(),
        }
    }

    /// The same avatar with other ablation switches.
    pub fn with_ablations(mut self, ablations: Ablations) -> Self {
        self.ablations = ablations;
        self
    }

    /// Lifting mode ([`Ablations::lift_mode`]).
    pub fn lift_mode(&self) -> LiftMode {
        self.ablations.lift_mode()
    }

    /// Frame kind ([`Ablations::frame_kind`]).
    pub fn frame_kind(&self) -> FrameKind {
        self.ablations.frame_kind()
    }

    /// The network config actually built: `net` with eta zeroed when the eta switch is off.
    pub fn effective_net(&self) -> NetConfig {
        let mut net = self.net.clone();
        net.condition.zero_eta |= !self.ablations.eta;
        net
    }

    /// The texel set-up of `mesh` for these networks: `R = S = uv_res`.
    pub fn topology(&self, mesh: &UvMesh) -> Result<Topology> {
        Topology::new(mesh, self.net.uv_res, self.net.uv_res)
    }

    /// Builds the avatar for `mesh` (seed the device first for reproducible weights, or use
    /// [`Self::init_seeded`]).
    pub fn init(&self, mesh: &UvMesh, device: &Device) -> Result<Avatar> {
        let topology = Arc::new(self.topology(mesh)?);
        self.init_with_topology(topology, device)
    }

    /// [`Self::init`] with the device seeded by `seed`: the same weights for the same seed,
    /// even when other threads draw random tensors at the same time. burn's CPU backends keep
    /// one random generator per process (burn-flex's `backend::SEED`, a global mutex, locked
    /// per draw), so a seed followed by several draws can interleave with another thread's
    /// seed or draws; tests training in parallel threads did (a resumed run then differed from
    /// a straight one). Every seeded initialisation in this crate goes through one lock.
    pub fn init_seeded(&self, seed: u64, mesh: &UvMesh, device: &Device) -> Result<Avatar> {
        let topology = Arc::new(self.topology(mesh)?);
        let _draws = SEEDED_INIT
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        device.seed(seed);
        self.init_with_topology(topology, device)
    }

    /// Builds the avatar with an already computed texel set-up (it must be at `uv_res`).
    pub fn init_with_topology(&self, topology: Arc<Topology>, device: &Device) -> Result<Avatar> {
        if topology.res() != self.net.uv_res {
            return Err(Error::invalid(
                "avatar config",
                "topology",
                format!(
                    "built at R = {}, the networks output R_uv = {}",
                    topology.res(),
                    self.net.uv_res
                ),
            ));
        }
        Ok(Avatar {
            net: self.effective_net().init(device)?,
            lift: LiftSetup(LiftParams {
                topology,
                mode: self.lift_mode(),
                frame: self.frame_kind(),
            }),
        })
    }
}

/// The lifting set-up of an [`Avatar`] ([`LiftParams`], which it dereferences to), with a
/// one-line `Debug` (burn prints a module's non-module fields with it; the topology's tables
/// would fill pages).
#[derive(Clone)]
pub struct LiftSetup(pub LiftParams);

impl std::ops::Deref for LiftSetup {
    type Target = LiftParams;

    fn deref(&self) -> &LiftParams {
        &self.0
    }
}

impl std::fmt::Debug for LiftSetup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let t = &self.topology;
        write!(
            f,
            "LiftSetup {{ R: {}, S: {}, gaussians: {}, faces: {}, mode: {:?}, frame: {:?} }}",
            t.res(),
            t.samples.size,
            t.len(),
            t.faces.len(),
            self.mode,
            self.frame
        )
    }
}

/// The networks with the (non-parameter) lifting set-up.
#[derive(Module, Debug)]
pub struct Avatar {
    /// The four networks of method §3 (all the parameters).
    pub net: TexAvatarNet,
    /// The texel set-up, lift mode and frame kind (not a parameter; not saved).
    #[module(skip)]
    pub lift: LiftSetup,
}

/// What [`Avatar::forward`] returns.
///
/// # Shapes
/// - `renders`: [N, H, W, 3], RGB on the white background
/// - `maps`: the decoders' local maps at R = R_uv (for the regularizers)
#[derive(Clone, Debug)]
pub struct AvatarOutput {
    /// Rendered images.
    pub renders: Tensor<4>,
    /// The decoders' outputs.
    pub maps: LocalMaps,
}

impl Avatar {
    /// For rendering only: the networks with their weight norms folded
    /// ([`TexAvatarNet::fold`]).
    pub fn for_inference(self) -> Self {
        Self {
            net: self.net.fold(),
            ..self
        }
    }

    /// Fails naming the first parameter (by module path) with a NaN or infinite entry: an
    /// avatar saved from a diverged run renders blank frames without a word otherwise.
    pub fn check_finite(&self, what: &str) -> Result<()> {
        use burn::module::{ModuleVisitor, Param};
        #[derive(Default)]
        struct Finite {
            path: Vec<String>,
            bad: Option<(String, usize, usize)>,
        }
        impl ModuleVisitor for Finite {
            fn enter_module(&mut self, name: &str, _container_type: &str) {
                self.path.push(name.to_string());
            }
            fn exit_module(&mut self, _name: &str, _container_type: &str) {
                self.path.pop();
            }
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                if self.bad.is_some() {
                    return;
                }
                let data = param.val().into_data();
                let values = data.iter::<f32>();
                let (mut bad, mut total) = (0, 0);
                for v in values {
                    total += 1;
                    bad += usize::from(!v.is_finite());
                }
                if bad > 0 {
                    self.bad = Some((self.path.join("."), bad, total));
                }
            }
        }
        let mut f = Finite::default();
        self.visit(&mut f);
        match f.bad {
            None => Ok(()),
            Some((path, bad, total)) => Err(Error::invalid(
                what,
                path,
                format!(
                    "{bad} of {total} values are NaN or infinite: the avatar was saved from a \
                     diverged run; retrain it (lower learning rates) or use an earlier checkpoint"
                ),
            )),
        }
    }

    /// Number of Gaussians (kept samples of the texel set-up).
    pub fn num_gaussians(&self) -> usize {
        self.lift.topology.len()
    }

    /// Number of mesh vertices the avatar is rigged to.
    pub fn num_vertices(&self) -> usize {
        self.lift.topology.num_vertices
    }

    /// Renders a batch of the data loader ([`HeadBatch`]): its conditions, cameras and posed
    /// vertices. All its images must have one size.
    ///
    /// # Shapes
    /// - `batch.condition`: [N, C]; `batch.vertices`: [N, V, 3]; N cameras
    /// - returns renders [N, H, W, 3]
    pub fn forward(&self, batch: &HeadBatch) -> Result<AvatarOutput> {
        self.render(
            batch.condition.clone(),
            &batch.cameras,
            batch.vertices.clone(),
        )
    }

    /// The Gaussians of frame `i` of the decoders' output `maps` on the posed `vertices`.
    ///
    /// # Shapes
    /// - `vertices`: [V, 3]
    pub fn gaussians(&self, maps: &LocalMaps, i: usize, vertices: Tensor<2>) -> Result<Gaussians> {
        let lifted = lift::lift(maps.frame(i), vertices, &self.lift.0)?;
        Ok(Gaussians {
            means: lifted.means,
            cov6: lifted.cov6,
            colors: lifted.colors,
            opacities: lifted.opacities,
        })
    }

    /// Decoders → lift (frame by frame) → splat, for conditions seen from `cameras` on posed
    /// meshes.
    ///
    /// # Shapes
    /// - `condition`: [N, C]
    /// - `cameras`: N cameras with one image size H x W
    /// - `vertices`: [N, V, 3]
    /// - returns renders [N, H, W, 3]
    pub fn render(
        &self,
        condition: Tensor<2>,
        cameras: &[Camera],
        vertices: Tensor<3>,
    ) -> Result<AvatarOutput> {
        let what = "avatar inputs";
        let n = condition.dims()[0];
        let [nv, v, three] = vertices.dims();
        if cameras.len() != n || nv != n {
            return Err(Error::invalid(
                what,
                "cameras",
                format!(
                    "{} cameras and {nv} vertex sets for {n} conditions",
                    cameras.len()
                ),
            ));
        }
        if v != self.num_vertices() || three != 3 {
            return Err(Error::invalid(
                what,
                "vertices",
                format!(
                    "expected [{n}, {}, 3], got {:?}",
                    self.num_vertices(),
                    vertices.dims()
                ),
            ));
        }
        if let Some(c) = cameras
            .iter()
            .find(|c| (c.width, c.height) != (cameras[0].width, cameras[0].height))
        {
            return Err(Error::invalid(
                what,
                "cameras",
                format!(
                    "images of one batch need one size: {}x{} and {}x{}",
                    cameras[0].width, cameras[0].height, c.width, c.height
                ),
            ));
        }
        let maps = self.net.forward_cameras(condition, cameras)?;
        let mut renders = Vec::with_capacity(n);
        for (i, camera) in cameras.iter().enumerate() {
            let verts = vertices.clone().narrow(0, i, 1).squeeze_dim::<2>(0);
            let packed = lift::lift_packed(maps.frame(i), verts, &self.lift.0)?;
            let params = SplatParams {
                camera: *camera,
                background: BACKGROUND,
            };
            renders.push(
                splat::render_packed(packed, &params)?
                    .image
                    .unsqueeze_dim::<4>(0),
            );
        }
        Ok(AvatarOutput {
            renders: Tensor::cat(renders, 0),
            maps,
        })
    }
}
