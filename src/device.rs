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

/// Kernel launches counted on every cubecl device (wgpu, CUDA) while a [`LaunchCount`] is
/// alive: cubecl's process-wide launch observer, which sees every kernel burn, burn's
/// fusion and texavatars' own ops issue, on any thread. For benchmarks (launches per render
/// or per training step); CPU backends launch nothing.
pub struct LaunchCount {
    counts: std::sync::Arc<LaunchTally>,
    _observation: burn_cubecl::cubecl::logging::LaunchObservation,
}

#[derive(Default)]
struct LaunchTally(std::sync::Mutex<std::collections::BTreeMap<&'static str, u64>>);

impl burn_cubecl::cubecl::logging::LaunchObserver for LaunchTally {
    fn launched(&self, kernel: &'static str) {
        if let Ok(mut counts) = self.0.lock() {
            *counts.entry(kernel).or_default() += 1;
        }
    }
}

impl LaunchCount {
    /// Starts counting (replacing any other observer until this is dropped).
    pub fn start() -> Self {
        let counts = std::sync::Arc::new(LaunchTally::default());
        let observation = burn_cubecl::cubecl::logging::LaunchObservation::new(counts.clone());
        Self {
            counts,
            _observation: observation,
        }
    }

    /// Launches so far, by kernel name (shortened to the kernel's own name, without module
    /// paths and generic arguments), most frequent first.
    pub fn by_kernel(&self) -> Vec<(String, u64)> {
        let mut merged = std::collections::BTreeMap::<String, u64>::new();
        if let Ok(counts) = self.counts.0.lock() {
            for (name, n) in counts.iter() {
                *merged.entry(short_kernel_name(name)).or_default() += n;
            }
        }
        let mut v: Vec<(String, u64)> = merged.into_iter().collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v
    }

    /// Launches so far.
    pub fn total(&self) -> u64 {
        self.counts.0.lock().map_or(0, |c| c.values().sum())
    }
}

/// `a::b::Kernel<x::Y>` → `Kernel`.
fn short_kernel_name(name: &str) -> String {
    let base = name.split('<').next().unwrap_or(name);
    base.rsplit("::").next().unwrap_or(base).to_string()
}
