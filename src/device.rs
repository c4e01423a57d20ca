//! Backend selection: one flag / config value picks where tensors live.

use burn::tensor::{Device, DeviceKind};

/// The compute backends texavatars runs on.
#[derive(
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// burn-ndarray on the CPU; the splat operator runs the multi-threaded CPU tile renderer.
    #[default]
    Cpu,
    /// burn-flex on the CPU (burn 0.22's successor of ndarray); same CPU tile renderer.
    Flex,
    /// burn-wgpu (Vulkan, Metal, DX12; lavapipe without a GPU); the splat operator runs the
    /// CubeCL kernels.
    Wgpu,
    /// burn's CUDA backend (NVIDIA GPU 0, built with `--features cuda`): the same CubeCL
    /// kernels, compiled by NVRTC at run time. burn-cubecl is one backend type for every
    /// runtime (the device says which), so every custom op registered for `Cube` runs here
    /// unchanged.
    #[cfg(feature = "cuda")]
    Cuda,
}

impl BackendKind {
    /// The device of this backend.
    #[allow(deprecated)]
    pub fn device(self) -> Device {
        match self {
            BackendKind::Cpu => Device::ndarray(),
            BackendKind::Flex => Device::flex(),
            BackendKind::Wgpu => Device::wgpu(DeviceKind::DefaultDevice),
            #[cfg(feature = "cuda")]
            BackendKind::Cuda => Device::cuda(0),
        }
    }

    /// The same device with autodiff enabled.
    pub fn autodiff_device(self) -> Device {
        self.device().autodiff()
    }
}
