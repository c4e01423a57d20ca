//! The WGSL that CubeCL generates for every custom kernel, validated with naga (the validator
//! wgpu runs before it creates a pipeline) against the capabilities of an adapter *without*
//! float atomics (DX12, browsers' WebGPU, older Apple GPUs). No device is needed: the kernel
//! definitions go through CubeCL's WGSL compiler (`cubecl::wgpu::WgslCompiler`, the one
//! `cubecl-wgpu` uses on every backend this crate builds), and the text is what wgpu would
//! receive.
//!
//! The float-atomic variant of the backward rasterizer must *fail* the same validation (it
//! declares `array<atomic<f32>>`) and pass with the capability: that shows the check can see
//! the difference, so the slot variant's pass means something.

use std::sync::Arc;

use burn_cubecl::cubecl::Compiler as _;
use burn_cubecl::cubecl::ir::features::Features;
use burn_cubecl::cubecl::ir::{DeviceIdentity, HardwareProperties, MemoryDeviceProperties};
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::wgpu::WgslCompiler;
use burn_cubecl::cubecl::{WgpuCompilationOptions, profile::TimingMethod};
use naga::valid::{Capabilities, ValidationFlags, Validator};
use texavatars_kernels::lift::blend::blend;
use texavatars_kernels::lift::bwd::frames::face_frames_backward;
use texavatars_kernels::lift::bwd::transform::lift_rows_backward;
use texavatars_kernels::lift::csr_gather::csr_gather;
use texavatars_kernels::lift::frames::face_frames;
use texavatars_kernels::lift::opacity_grad::opacity_grad;
use texavatars_kernels::lift::transform::lift_rows;
use texavatars_kernels::splat::bwd::project::project_backward;
use texavatars_kernels::splat::bwd::rasterize::rasterize_backward;
use texavatars_kernels::splat::bwd::sum_slots::sum_slots;
use texavatars_kernels::splat::emit_intersections::emit_intersections;
use texavatars_kernels::splat::fill::fill_u32;
use texavatars_kernels::splat::gather::gather_u32;
use texavatars_kernels::splat::iota::iota_u32;
use texavatars_kernels::splat::project::project;
use texavatars_kernels::splat::radix_sort::histogram::radix_histogram;
use texavatars_kernels::splat::radix_sort::scatter::radix_scatter;
use texavatars_kernels::splat::rasterize::rasterize;
use texavatars_kernels::splat::scan::add_block_offsets::scan_add_block_offsets;
use texavatars_kernels::splat::scan::blocks::scan_blocks;
use texavatars_kernels::splat::tile_ranges::segment_ranges;

/// A device description for compiling offline: the limits of a common desktop adapter (the
/// WGSL compiler only reads them for features this crate's kernels do not use).
fn props() -> Arc<DeviceProperties> {
    Arc::new(DeviceProperties::new(
        Features::default(),
        MemoryDeviceProperties::new(u64::MAX, 256),
        HardwareProperties {
            load_width: 128,
            vector_register_count: None,
            plane_size_min: 32,
            plane_size_max: 32,
            max_bindings: 32,
            max_shared_memory_size: 32768,
            max_cube_count: (65535, 65535, 65535),
            max_units_per_cube: 256,
            max_cube_dim: (256, 256, 64),
            num_streaming_multiprocessors: None,
            num_tensor_cores: None,
            min_tensor_cores_dim: None,
            num_cpu_cores: None,
            last_level_cache_size: None,
            max_vector_size: VectorSize::MAX,
            cube_mma_reserved_shared_memory: 0,
        },
        TimingMethod::System,
        DeviceIdentity {
            name: "offline".into(),
            fingerprint: "offline".into(),
            physical: None,
        },
    ))
}

fn settings(dim: CubeDim) -> KernelSettings {
    KernelSettings::new(*dim, ExecutionMode::Unchecked, AddressType::U32)
}

fn tile() -> KernelSettings {
    settings(CubeDim::new_2d(16, 16))
}

fn line() -> KernelSettings {
    settings(CubeDim::new_1d(256))
}

/// The WGSL text of a kernel definition.
fn wgsl(def: KernelDefinition) -> String {
    WgslCompiler
        .compile(def, &WgpuCompilationOptions::default())
        .expect("CubeCL compiles the kernel to WGSL")
        .to_string()
}

/// Parses and validates WGSL as wgpu does, with `caps`; the error names the line.
fn validate(src: &str, caps: Capabilities) -> Result<(), String> {
    let module = naga::front::wgsl::parse_str(src).map_err(|e| e.emit_to_string(src))?;
    Validator::new(ValidationFlags::all(), caps)
        .validate(&module)
        .map(|_| ())
        .map_err(|e| e.emit_to_string(src))
}

/// Everything an adapter may offer except float atomics.
fn without_float_atomics() -> Capabilities {
    Capabilities::all() - Capabilities::SHADER_FLOAT32_ATOMIC
}

/// The WGSL of kernel type `$kernel` (the type `#[cube]` generates) with `$settings` and
/// its compilation arguments in parameter order: `B` for a buffer, `S` for a scalar, then
/// the comptime values.
macro_rules! shader {
    ($kernel:ty, $settings:expr; $($arg:expr),* $(,)?) => {
        wgsl(
            <$kernel>::new($settings, props(), Arc::new(TargetProperties::default()), $($arg),*)
                .define(),
        )
    };
}

/// A buffer argument of `shader!`.
const B: BufferCompilationArg = BufferCompilationArg { inplace: None };
/// A scalar argument of `shader!`.
const S: () = ();

/// Every kernel a training step launches on an adapter without float atomics, by name.
#[rustfmt::skip]
fn kernels_without_float_atomics() -> Vec<(&'static str, String)> {
    vec![
        ("project", shader!(project::Project, line(); B, B, B, B, B, B, B, B, B, B, S, S, S)),
        ("emit_intersections", shader!(emit_intersections::EmitIntersections, line(); B, B, B, B, B, B, S, S)),
        ("radix_histogram", shader!(radix_histogram::RadixHistogram, line(); B, B, S, S, S, S)),
        ("radix_scatter", shader!(radix_scatter::RadixScatter, line(); B, B, B, B, B, S, S, S, S)),
        ("fill_u32", shader!(fill_u32::FillU32, line(); B, S, S)),
        ("gather_u32", shader!(gather_u32::GatherU32, line(); B, B, B, S)),
        ("iota_u32", shader!(iota_u32::IotaU32, line(); B, S)),
        ("segment_ranges", shader!(segment_ranges::SegmentRanges, line(); B, B, S)),
        ("scan_blocks", shader!(scan_blocks::ScanBlocks, line(); B, B, B, S, S)),
        ("scan_add_block_offsets", shader!(scan_add_block_offsets::ScanAddBlockOffsets, line(); B, B, S, S)),
        ("rasterize", shader!(rasterize::Rasterize, tile(); B, B, B, B, B, B, B, S, S, S)),
        (
            "rasterize_backward (slots)",
            shader!(rasterize_backward::RasterizeBackward<f32>, tile(); B, B, B, B, B, B, B, B, B, B, S, S, S, false, false),
        ),
        ("sum_slots", shader!(sum_slots::SumSlots, line(); B, B, B, B, S)),
        ("project_backward", shader!(project_backward::ProjectBackward, line(); B, B, B, B, B, B, B, B, B, S)),
        ("face_frames", shader!(face_frames::FaceFrames, line(); B, B, B, S, true)),
        ("face_frames_backward", shader!(face_frames_backward::FaceFramesBackward, line(); B, B, B, B, S, true)),
        ("lift_rows", shader!(lift_rows::LiftRows, line(); B, S, S, B, B, B, B, B, B, S, true)),
        ("lift_rows_backward", shader!(lift_rows_backward::LiftRowsBackward, line(); B, S, S, B, B, B, B, S, S, B, S, true)),
        ("csr_gather", shader!(csr_gather::CsrGather, line(); B, S, S, B, B, B, B, S, S, S, S, true)),
        ("blend", shader!(blend::Blend, line(); B, S, S, B, B, B, S, S, true)),
        ("opacity_grad", shader!(opacity_grad::OpacityGrad, line(); B, B, B, S)),
    ]
}

/// WebGPU's default `maxComputeWorkgroupStorageSize` (<https://www.w3.org/TR/webgpu/#limits>),
/// the workgroup memory every adapter grants without asking for more.
const WEBGPU_WORKGROUP_STORAGE: u32 = 16384;

/// Bytes of workgroup memory the WGSL declares (naga's layout of its `var<workgroup>`s).
fn workgroup_bytes(src: &str) -> u32 {
    let module = naga::front::wgsl::parse_str(src).expect("the WGSL parses");
    let mut layouter = naga::proc::Layouter::default();
    layouter
        .update(module.to_ctx())
        .expect("naga lays the types out");
    module
        .global_variables
        .iter()
        .filter(|(_, var)| var.space == naga::AddressSpace::WorkGroup)
        .map(|(_, var)| layouter[var.ty].size)
        .sum()
}

#[test]
fn every_kernel_fits_webgpu_default_workgroup_memory() {
    for (name, src) in kernels_without_float_atomics() {
        let bytes = workgroup_bytes(&src);
        assert!(
            bytes <= WEBGPU_WORKGROUP_STORAGE,
            "{name}: {bytes} bytes of workgroup memory, over WebGPU's default {WEBGPU_WORKGROUP_STORAGE}"
        );
        if name == "radix_scatter" {
            // The 8-bit pass's block-local sort (kernels/gpu/src/splat/radix_sort/scatter.rs)
            // declares about 14 KiB: counts, segment totals, sorted entries, digit starts.
            // Fewer counted bytes would mean the measure misses declarations.
            assert!(
                bytes > 12 * 1024,
                "radix_scatter: only {bytes} bytes counted"
            );
        }
    }
}

#[test]
fn every_kernel_validates_without_float_atomics() {
    for (name, src) in kernels_without_float_atomics() {
        assert!(
            !src.contains("atomic<f32>"),
            "{name}: the shader declares a float atomic"
        );
        if let Err(e) = validate(&src, without_float_atomics()) {
            panic!("{name}: naga rejects the WGSL without float atomics:\n{e}");
        }
    }
}

#[test]
fn float_atomic_backward_needs_the_capability_and_has_it_checked() {
    #[rustfmt::skip]
    let src = shader!(
        rasterize_backward::RasterizeBackward<Atomic<f32>>, tile();
        B, B, B, B, B, B, B, B, B, B, S, S, S, true, false
    );
    assert!(
        src.contains("atomic<f32>"),
        "the float-atomic variant binds float atomics"
    );
    assert_eq!(
        src.matches("atomicAdd(").count(),
        9,
        "nine gradient entries per pair"
    );
    let err = validate(&src, without_float_atomics()).expect_err("rejected without the capability");
    assert!(err.contains("SHADER_FLOAT32_ATOMIC"), "{err}");
    validate(&src, Capabilities::all()).expect("valid with float atomics");
}

/// The subgroup-reduced backward (`plane_reduce`, chosen on adapters with subgroups): nine
/// `subgroupAdd`s and one set of nine atomics for the plane's first unit; naga accepts it
/// with subgroup operations and float atomics and rejects it without subgroups, which is
/// why the host picks it only where cubecl reports plane operations.
#[test]
fn plane_reduced_backward_needs_subgroups() {
    #[rustfmt::skip]
    let src = shader!(
        rasterize_backward::RasterizeBackward<Atomic<f32>>, tile();
        B, B, B, B, B, B, B, B, B, B, S, S, S, true, true
    );
    assert_eq!(src.matches("subgroupAdd(").count(), 9, "nine plane sums");
    assert_eq!(src.matches("atomicAdd(").count(), 9, "one set of atomics");
    validate(&src, Capabilities::all()).expect("valid with subgroups and float atomics");
    let without = Capabilities::all()
        - Capabilities::SUBGROUP
        - Capabilities::SUBGROUP_BARRIER
        - Capabilities::SUBGROUP_VERTEX_STAGE;
    let err = validate(&src, without).expect_err("rejected without subgroups");
    assert!(err.to_lowercase().contains("subgroup"), "{err}");
}
