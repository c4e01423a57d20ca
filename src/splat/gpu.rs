//! GPU implementation of the splat operator on burn's cubecl backend (wgpu and the other
//! cubecl runtimes).
//!
//! The host side of the kernels in [`texavatars_kernels::splat`]: it allocates the buffers,
//! launches the kernels in order and wraps the results as [`CubeTensor`]s. Everything stays
//! on the device except one 12-byte read per forward: the intersection count (to size the
//! intersection buffers) and the span of the visible depth keys (to sort only the key bits
//! that differ).
//!
//! Forward: project (with the key span and intersection count, read back) → depth radix
//! sort over the differing key bits → tile counts in depth order → exclusive scan →
//! emit `(tile, Gaussian)` intersections → stable radix sort by tile → tile ranges →
//! per-tile rasterization. Backward: per-tile reverse rasterization accumulating
//! screen-space gradients (float atomics, or per-intersection slots and a deterministic
//! per-Gaussian sum when the device has no float atomics) → per-Gaussian projection
//! backward.
//!
//! Conventions: see `tests/fixtures/splat/README.md` and the kernel module docs. Float inputs
//! may be non-contiguous or of another float dtype: they are made contiguous `f32` first.
//! Integer outputs use `DType::I32` (the cube backends' default int dtype); their values are
//! non-negative and written as `u32` bit patterns, which agree with `i32` below `2^31`.

use burn::tensor::DType;
use burn_cubecl::CubeDevice;
use burn_cubecl::cubecl::client::Client;
use burn_cubecl::cubecl::features::AtomicUsage;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::cubecl::{CubeCount, CubeDim};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use texavatars_kernels::splat::bwd::project::project_backward;
use texavatars_kernels::splat::bwd::rasterize::rasterize_backward;
use texavatars_kernels::splat::bwd::sum_slots::sum_slots;
use texavatars_kernels::splat::camera::{CAMERA_LEN, pack_camera};
use texavatars_kernels::splat::constants::{GRAD2D_STRIDE, PROJECTED_STRIDE, TILE_SIZE};
use texavatars_kernels::splat::emit_intersections::emit_intersections;
use texavatars_kernels::splat::gather::gather_u32;
use texavatars_kernels::splat::iota::iota_u32;
use texavatars_kernels::splat::project::{KEY_MAX, KEY_MIN, KEY_STATS_LEN, TOTAL_TILES, project};
use texavatars_kernels::splat::radix_sort::histogram::radix_histogram;
use texavatars_kernels::splat::radix_sort::scatter::radix_scatter;
use texavatars_kernels::splat::radix_sort::{
    RADIX_BITS, RADIX_BLOCK, RADIX_BUCKETS, RADIX_THREADS,
};
use texavatars_kernels::splat::rasterize::rasterize;
use texavatars_kernels::splat::scan::add_block_offsets::scan_add_block_offsets;
use texavatars_kernels::splat::scan::blocks::scan_blocks;
use texavatars_kernels::splat::scan::{SCAN_BLOCK, SCAN_THREADS};
use texavatars_kernels::splat::tile_ranges::segment_ranges;

use crate::camera::Camera;
pub use crate::gpu::max_binding_bytes;
use crate::gpu::{Ctx, arg};

/// Blocking reads from the device issued by this module since the process started.
static HOST_READS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// How many blocking device-to-host reads the GPU splat (and its diagnostics) has issued in
/// this process: each is a round trip that stalls the host until the device has caught up.
/// For benchmarks; burn's own reads (a loss value for a log line) are not counted here.
pub fn host_reads() -> u64 {
    HOST_READS.load(std::sync::atomic::Ordering::Relaxed)
}

/// Result of [`forward`]: the image and everything [`backward`] needs.
#[derive(Clone, Debug)]
pub struct GpuForward {
    /// `[H, W, 4]` f32: RGB (background included) in channels 0..3, final transmittance in
    /// channel 3.
    pub out: CubeTensor,
    /// `[N, 8]` f32 per-Gaussian projection: `u, v, conic a, conic b, conic c, depth z,
    /// opacity, tiles touched` (all zero for culled Gaussians, whose tile count is 0).
    pub projected: CubeTensor,
    /// `[M]` int: Gaussian index of each tile intersection, tile-major, ascending depth
    /// (ties by Gaussian index) within a tile. `[1]` holding `0` when `M = 0`.
    pub isect_ids: CubeTensor,
    /// `[T, 2]` int: `[start, end)` into `isect_ids` per tile (row-major tiles of
    /// `TILE_SIZE` pixels; `T = ceil(W / 16) * ceil(H / 16)`).
    pub tile_ranges: CubeTensor,
    /// `[H, W]` int: per pixel, the end (exclusive, relative to its tile's range start) of the
    /// intersections the forward pass composited.
    pub last: CubeTensor,
}

/// Knobs of the GPU pass that do not change its result (beyond float summation order).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Accumulate the backward's per-Gaussian gradients with `Atomic<f32>` adds when the
    /// device supports them. `false` forces the deterministic per-intersection-slot path
    /// (used on devices without float atomics).
    pub allow_float_atomics: bool,
    /// Whether the float-atomic path first sums within planes (subgroups).
    pub plane_reduction: PlaneReduction,
}

impl Default for GpuOptions {
    fn default() -> Self {
        Self {
            allow_float_atomics: true,
            plane_reduction: PlaneReduction::Auto,
        }
    }
}

/// Whether the backward's float-atomic path sums each Gaussian's gradients within a plane
/// (subgroup) before its atomics.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlaneReduction {
    /// Where cubecl reports plane operations for the device ([`plane_ops_supported`]).
    Auto,
    /// Never: one set of atomics per contributing pixel.
    Off,
    /// Always. The adapter must have subgroups even where cubecl does not report them:
    /// cubecl-wgpu leaves plane operations off on CPU adapters, and lavapipe has subgroups,
    /// which is how the tests run this path without a GPU.
    Force,
}

/// How [`backward_with_options`] accumulates per-Gaussian gradients on a device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accumulation {
    /// One float atomic add per contributing pixel and gradient entry.
    Atomics,
    /// A plane (subgroup) sum per Gaussian first, then one float atomic add per plane and
    /// gradient entry.
    PlaneAtomics,
    /// Per-intersection slots and a deterministic per-Gaussian sum (no float atomics).
    Slots,
}

impl GpuOptions {
    /// The accumulation these options select on `client`'s device.
    pub fn accumulation(&self, client: &Client) -> Accumulation {
        if !(self.allow_float_atomics && float_atomics_supported(client)) {
            return Accumulation::Slots;
        }
        match self.plane_reduction {
            PlaneReduction::Auto if plane_ops_supported(client) => Accumulation::PlaneAtomics,
            PlaneReduction::Force => Accumulation::PlaneAtomics,
            _ => Accumulation::Atomics,
        }
    }
}

/// Whether cubecl reports plane (subgroup) operations for `client`'s device.
pub fn plane_ops_supported(client: &Client) -> bool {
    client
        .properties()
        .features
        .plane
        .contains(burn_cubecl::cubecl::ir::features::Plane::Ops)
}

/// Whether `client`'s device can `fetch_add` on `Atomic<f32>` in global memory.
pub fn float_atomics_supported(client: &Client) -> bool {
    let ty = Type::atomic(f32::elem_type_native());
    client
        .properties()
        .atomic_type_usage(ty)
        .contains(AtomicUsage::Add)
}

/// The sizes that set the buffers of a splat pass.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SceneSize {
    /// Gaussians (N).
    pub gaussians: usize,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Tile intersections (M), once the forward pass has counted them.
    pub intersections: Option<usize>,
    /// Whether the backward keeps per-intersection gradient slots (no float atomics).
    pub slots: bool,
}

/// Checks every scene-sized buffer of a splat pass over `scene` against `limit` bytes (see
/// [`max_binding_bytes`]) before it is allocated. The error names the scene, the buffer and
/// the limit; without this check an oversized scene ends in a panic inside wgpu.
pub fn check_buffers(scene: &SceneSize, limit: u64) -> Result<(), String> {
    let n = scene.gaussians as u64;
    let pixels = u64::from(scene.width) * u64::from(scene.height);
    let m = scene.intersections.unwrap_or(0) as u64;
    let buffers = [
        (
            "the projected Gaussians [N, 8]",
            n * u64::from(PROJECTED_STRIDE),
        ),
        (
            "the screen-space gradients [N, 9]",
            n * u64::from(GRAD2D_STRIDE),
        ),
        ("the image [H, W, 4]", pixels * 4),
        ("the tile intersections [M]", m),
        (
            "the per-intersection gradient slots [M, 9] (adapter without float atomics)",
            if scene.slots {
                m * u64::from(GRAD2D_STRIDE)
            } else {
                0
            },
        ),
    ];
    for (what, words) in buffers {
        let bytes = words * size_of::<u32>() as u64;
        if bytes > limit {
            let isects = scene
                .intersections
                .map_or(String::new(), |m| format!(" and {m} tile intersections"));
            return Err(format!(
                "a scene of {n} Gaussians at {} x {} pixels{isects} needs {bytes} bytes for \
                 {what}, above this adapter's largest storage buffer binding ({limit} bytes): \
                 render fewer Gaussians or a smaller image, or use an adapter with a larger \
                 max_storage_buffer_binding_size",
                scene.width, scene.height
            ));
        }
    }
    Ok(())
}

/// Panics with [`check_buffers`]' message when `scene` does not fit `ctx`'s adapter (a
/// burn op cannot return an error).
fn assert_fits(ctx: &Ctx, scene: &SceneSize) {
    if let Err(e) = check_buffers(scene, max_binding_bytes(&ctx.client)) {
        panic!("{e}");
    }
}

/// Renders `N` Gaussians with `camera` over `background`.
///
/// # Shapes
/// - `means`: `[N, 3]`, `cov6`: `[N, 6]` (`xx, xy, xz, yy, yz, zz`), `colors`: `[N, 3]`,
///   `opacities`: `[N]` (after the sigmoid). All on the same device.
///
/// # Panics
/// On mismatched shapes or an empty image, when the Gaussians touch more than `2^31 - 1`
/// tiles in total, or when a buffer would exceed the adapter's limit ([`check_buffers`]).
pub fn forward(
    means: CubeTensor,
    cov6: CubeTensor,
    colors: CubeTensor,
    opacities: CubeTensor,
    camera: &Camera,
    background: [f32; 3],
) -> GpuForward {
    let ctx = Ctx::new(&means);
    let means = ctx.float_input(means);
    let cov6 = ctx.float_input(cov6);
    let colors = ctx.float_input(colors);
    let opacities = ctx.float_input(opacities);
    let n = check_shapes(&means, &cov6, &colors, &opacities);
    let frame = Frame::new(camera);
    let mut scene = SceneSize {
        gaussians: n,
        width: frame.width,
        height: frame.height,
        intersections: None,
        slots: false,
    };
    assert_fits(&ctx, &scene);
    let cam = ctx.camera(camera, background);

    let projected = ctx.empty(n * PROJECTED_STRIDE as usize);
    let mut isects = 0usize;
    let mut tile_keys = None;
    let mut gaussian_from_isect = None;
    if n > 0 {
        let tile_rects = ctx.empty(n * 4);
        let tile_counts = ctx.empty(n);
        let depth_keys = ctx.empty(n);
        let key_stats = ctx
            .client
            .create_from_slice(u32::as_bytes(&[u32::MAX, 0, 0]));
        let (count, dim) = ctx.elementwise(n);
        // SAFETY: every buffer holds the lengths passed; the kernel bounds-checks `n`.
        unsafe {
            project::launch_unchecked(
                &ctx.client,
                count,
                dim,
                arg(&means.handle, n * 3),
                arg(&cov6.handle, n * 6),
                arg(&colors.handle, n * 3),
                arg(&opacities.handle, n),
                arg(&cam, CAMERA_LEN),
                arg(&projected, n * PROJECTED_STRIDE as usize),
                arg(&tile_rects, n * 4),
                arg(&tile_counts, n),
                arg(&depth_keys, n),
                arg(&key_stats, KEY_STATS_LEN),
                n as u32,
                frame.width,
                frame.height,
            );
        }

        // The tile total (project's atomics, the scan) counts in u32; the outputs index in
        // i32. Only scenes whose worst case could overflow pay for an exact host-side check.
        if n as u64 * frame.num_tiles() as u64 > i32::MAX as u64 {
            let total: u64 = ctx
                .read_words(&tile_counts, n)
                .iter()
                .map(|&c| c as u64)
                .sum();
            assert!(
                total <= i32::MAX as u64,
                "{total} tile intersections exceed the supported 2^31 - 1"
            );
        }
        // The forward's one round trip: the intersection count and the span of the
        // visible Gaussians' depth keys.
        let stats = ctx.read_words(&key_stats, KEY_STATS_LEN);
        isects = stats[TOTAL_TILES] as usize;
        scene.intersections = Some(isects);
        assert_fits(&ctx, &scene);

        // Without intersections (nothing visible) there is nothing to sort or emit.
        if isects > 0 {
            let depth_bits = depth_key_bits(stats[KEY_MIN], stats[KEY_MAX], isects);
            let order = ctx.iota(n);
            let (_, gaussian_from_depth_rank) = ctx.radix_sort(&depth_keys, &order, n, depth_bits);
            let counts_by_depth = ctx.gather(&tile_counts, &gaussian_from_depth_rank, n);
            let (isect_offsets, _) = ctx.exclusive_scan(&counts_by_depth, n);
            let keys = ctx.empty(isects);
            let gaussians = ctx.empty(isects);
            let (count, dim) = ctx.elementwise(n);
            // SAFETY: the offsets and counts sum to `isects`, the length of both outputs.
            unsafe {
                emit_intersections::launch_unchecked(
                    &ctx.client,
                    count,
                    dim,
                    arg(&gaussian_from_depth_rank, n),
                    arg(&isect_offsets, n),
                    arg(&tile_rects, n * 4),
                    arg(&tile_counts, n),
                    arg(&keys, isects),
                    arg(&gaussians, isects),
                    n as u32,
                    frame.tiles_x,
                );
            }
            let tile_bits = bit_length(frame.num_tiles() as u32 - 1);
            let (keys, gaussians) = ctx.radix_sort(&keys, &gaussians, isects, tile_bits);
            tile_keys = Some(keys);
            gaussian_from_isect = Some(gaussians);
        }
    }

    let tile_ranges = ctx.zeros(frame.num_tiles() * 2);
    if let Some(keys) = &tile_keys {
        ctx.segment_ranges(keys, &tile_ranges, isects);
    }
    let isect_len = isects.max(1);
    let gaussian_from_isect = gaussian_from_isect.unwrap_or_else(|| ctx.zeros(1));

    let pixels = frame.num_pixels();
    let out = ctx.empty(pixels * 4);
    let last = ctx.empty(pixels);
    // SAFETY: one workgroup per tile; pixels outside the image are masked in the kernel.
    unsafe {
        rasterize::launch_unchecked(
            &ctx.client,
            frame.tile_grid(),
            frame.tile_dim(),
            arg(&projected, n * PROJECTED_STRIDE as usize),
            arg(&ctx.nonempty(&colors.handle), (n * 3).max(1)),
            arg(&gaussian_from_isect, isect_len),
            arg(&tile_ranges, frame.num_tiles() * 2),
            arg(&cam, CAMERA_LEN),
            arg(&out, pixels * 4),
            arg(&last, pixels),
            frame.width,
            frame.height,
            frame.tiles_x,
        );
    }

    let (h, w) = (frame.height as usize, frame.width as usize);
    GpuForward {
        out: ctx.tensor(out, [h, w, 4], DType::F32),
        projected: ctx.tensor(projected, [n, PROJECTED_STRIDE as usize], DType::F32),
        isect_ids: ctx.tensor(gaussian_from_isect, [isect_len], DType::I32),
        tile_ranges: ctx.tensor(tile_ranges, [frame.num_tiles(), 2], DType::I32),
        last: ctx.tensor(last, [h, w], DType::I32),
    }
}

/// Gradients of a loss with respect to the inputs of [`forward`], given the loss gradient
/// `grad_out` (`[H, W, 4]`: dL/dRGB and dL/dT) of its output. Uses float atomics when the
/// device has them; see [`backward_with_options`].
///
/// Returns the gradients for `[means [N, 3], cov6 [N, 6], colors [N, 3], opacities [N]]`
/// and the screen-space gradient `[N, GRAD2D_STRIDE]` (its columns: d/du, d/dv in pixels,
/// then the conic's, the colour's and the opacity's). Culled Gaussians get zeros.
#[allow(clippy::too_many_arguments)]
pub fn backward(
    means: CubeTensor,
    cov6: CubeTensor,
    colors: CubeTensor,
    opacities: CubeTensor,
    camera: &Camera,
    background: [f32; 3],
    fwd: &GpuForward,
    grad_out: CubeTensor,
) -> [CubeTensor; 5] {
    backward_with_options(
        means,
        cov6,
        colors,
        opacities,
        camera,
        background,
        fwd,
        grad_out,
        GpuOptions::default(),
    )
}

/// [`backward`] with explicit [`GpuOptions`].
///
/// # Panics
/// On mismatched shapes, or, on the slot path, above `(2^32 - 1) / 9` intersections, or when
/// a buffer would exceed the adapter's limit ([`check_buffers`]).
#[allow(clippy::too_many_arguments)]
pub fn backward_with_options(
    means: CubeTensor,
    cov6: CubeTensor,
    colors: CubeTensor,
    opacities: CubeTensor,
    camera: &Camera,
    background: [f32; 3],
    fwd: &GpuForward,
    grad_out: CubeTensor,
    options: GpuOptions,
) -> [CubeTensor; 5] {
    let ctx = Ctx::new(&means);
    let means = ctx.float_input(means);
    let cov6 = ctx.float_input(cov6);
    let colors = ctx.float_input(colors);
    let opacities = ctx.float_input(opacities);
    let n = check_shapes(&means, &cov6, &colors, &opacities);
    let frame = Frame::new(camera);
    let (h, w) = (frame.height as usize, frame.width as usize);
    let grad_out = ctx.float_input(grad_out);
    assert_eq!(
        grad_out.meta.shape().as_slice(),
        &[h, w, 4],
        "grad_out must be [H, W, 4]"
    );
    if n == 0 {
        return [
            ctx.empty_tensor([0, 3]),
            ctx.empty_tensor([0, 6]),
            ctx.empty_tensor([0, 3]),
            ctx.empty_tensor([0]),
            ctx.empty_tensor([0, GRAD2D_STRIDE as usize]),
        ];
    }
    let cam = ctx.camera(camera, background);
    let projected = into_contiguous(fwd.projected.clone());
    let out = into_contiguous(fwd.out.clone());
    let last = into_contiguous(fwd.last.clone());
    let tile_ranges = into_contiguous(fwd.tile_ranges.clone());
    let isect_ids = into_contiguous(fwd.isect_ids.clone());
    // With M = 0 the buffer is a one-entry dummy holding Gaussian 0, which no tile range
    // reaches: its slot stays zero, so treating it as an intersection changes nothing.
    let isect_len = isect_ids.meta.shape().num_elements();
    let pixels = frame.num_pixels();
    let grad_len = n * GRAD2D_STRIDE as usize;

    let accumulation = options.accumulation(&ctx.client);
    let float_atomics = accumulation != Accumulation::Slots;
    assert_fits(
        &ctx,
        &SceneSize {
            gaussians: n,
            width: frame.width,
            height: frame.height,
            intersections: Some(isect_len),
            slots: !float_atomics,
        },
    );
    let grad2d = ctx.zeros(grad_len);
    assert!(
        float_atomics || isect_len * (GRAD2D_STRIDE as usize) <= u32::MAX as usize,
        "{isect_len} intersections exceed the gradient slots' u32 indexing"
    );
    let slots = if float_atomics {
        ctx.zeros(1)
    } else {
        ctx.zeros(isect_len * GRAD2D_STRIDE as usize)
    };
    let (grad2d_len, slots_len) = if float_atomics {
        (grad_len, 1)
    } else {
        (1, isect_len * GRAD2D_STRIDE as usize)
    };
    // The slot variant binds `grad2d` as plain floats (one entry, never written: its sums
    // come from `sum_slots` below), so its shader holds no float atomic (see
    // `rasterize_backward`'s module documentation).
    macro_rules! launch_backward {
        ($cell:ty) => {
            // SAFETY: one workgroup per tile; all buffers hold the lengths passed.
            unsafe {
                rasterize_backward::launch_unchecked::<$cell>(
                    &ctx.client,
                    frame.tile_grid(),
                    frame.tile_dim(),
                    arg(&projected.handle, n * PROJECTED_STRIDE as usize),
                    arg(&colors.handle, n * 3),
                    arg(&isect_ids.handle, isect_len),
                    arg(&tile_ranges.handle, frame.num_tiles() * 2),
                    arg(&cam, CAMERA_LEN),
                    arg(&out.handle, pixels * 4),
                    arg(&last.handle, pixels),
                    arg(&grad_out.handle, pixels * 4),
                    arg(&grad2d, grad2d_len),
                    arg(&slots, slots_len),
                    frame.width,
                    frame.height,
                    frame.tiles_x,
                    float_atomics,
                    accumulation == Accumulation::PlaneAtomics,
                )
            }
        };
    }
    if float_atomics {
        launch_backward!(Atomic<f32>);
    } else {
        launch_backward!(f32);
    }

    if !float_atomics {
        let order = ctx.iota(isect_len);
        let bits = bit_length(n as u32 - 1);
        let (gaussian_keys, isect_from_gaussian_rank) =
            ctx.radix_sort(&isect_ids.handle, &order, isect_len, bits);
        let gaussian_ranges = ctx.zeros(n * 2);
        ctx.segment_ranges(&gaussian_keys, &gaussian_ranges, isect_len);
        let (count, dim) = ctx.elementwise(n);
        // SAFETY: ranges index `isect_from_gaussian_rank`, whose entries index the slots.
        unsafe {
            sum_slots::launch_unchecked(
                &ctx.client,
                count,
                dim,
                arg(&slots, slots_len),
                arg(&isect_from_gaussian_rank, isect_len),
                arg(&gaussian_ranges, n * 2),
                arg(&grad2d, grad_len),
                n as u32,
            );
        }
    }

    let grad_means = ctx.empty(n * 3);
    let grad_cov6 = ctx.empty(n * 6);
    let grad_colors = ctx.empty(n * 3);
    let grad_opacities = ctx.empty(n);
    let (count, dim) = ctx.elementwise(n);
    // SAFETY: one thread per Gaussian, bounds-checked against `n`.
    unsafe {
        project_backward::launch_unchecked(
            &ctx.client,
            count,
            dim,
            arg(&means.handle, n * 3),
            arg(&cov6.handle, n * 6),
            arg(&cam, CAMERA_LEN),
            arg(&projected.handle, n * PROJECTED_STRIDE as usize),
            arg(&grad2d, grad_len),
            arg(&grad_means, n * 3),
            arg(&grad_cov6, n * 6),
            arg(&grad_colors, n * 3),
            arg(&grad_opacities, n),
            n as u32,
        );
    }
    [
        ctx.tensor(grad_means, [n, 3], DType::F32),
        ctx.tensor(grad_cov6, [n, 6], DType::F32),
        ctx.tensor(grad_colors, [n, 3], DType::F32),
        ctx.tensor(grad_opacities, [n], DType::F32),
        // The whole screen-space gradient; its first two columns are d/du, d/dv.
        ctx.tensor(grad2d, [n, GRAD2D_STRIDE as usize], DType::F32),
    ]
}

/// Exclusive prefix sum of `values` with the rasterizer's multi-level scan kernels, and the
/// total. A host-slice entry point for tests and diagnostics of the scan.
///
/// # Panics
/// When `values` has `2^32` or more entries or the device read fails.
pub fn exclusive_scan_u32(device: &CubeDevice, values: &[u32]) -> (Vec<u32>, u32) {
    if values.is_empty() {
        return (Vec::new(), 0);
    }
    let ctx = Ctx::on(device);
    let input = ctx.client.create_from_slice(u32::as_bytes(values));
    let (output, total) = ctx.exclusive_scan(&input, values.len());
    (ctx.read_words(&output, values.len()), ctx.read_u32(&total))
}

/// Stable sort of `(key, value)` pairs by the low `bits` bits of the keys with the
/// rasterizer's radix sort kernels. A host-slice entry point for tests and diagnostics.
///
/// # Panics
/// When the slices differ in length or the device read fails.
pub fn radix_sort_u32(
    device: &CubeDevice,
    keys: &[u32],
    values: &[u32],
    bits: u32,
) -> (Vec<u32>, Vec<u32>) {
    assert_eq!(keys.len(), values.len(), "one value per key");
    if keys.is_empty() {
        return (Vec::new(), Vec::new());
    }
    let ctx = Ctx::on(device);
    let key_buf = ctx.client.create_from_slice(u32::as_bytes(keys));
    let value_buf = ctx.client.create_from_slice(u32::as_bytes(values));
    let (sorted_keys, sorted_values) = ctx.radix_sort(&key_buf, &value_buf, keys.len(), bits);
    (
        ctx.read_words(&sorted_keys, keys.len()),
        ctx.read_words(&sorted_values, keys.len()),
    )
}

/// Checks the input shapes and returns `N`.
fn check_shapes(
    means: &CubeTensor,
    cov6: &CubeTensor,
    colors: &CubeTensor,
    opacities: &CubeTensor,
) -> usize {
    let dims = |t: &CubeTensor| t.meta.shape().as_slice().to_vec();
    let n = dims(means).first().copied().unwrap_or(0);
    assert_eq!(dims(means), [n, 3], "means must be [N, 3]");
    assert_eq!(dims(cov6), [n, 6], "cov6 must be [N, 6]");
    assert_eq!(dims(colors), [n, 3], "colors must be [N, 3]");
    assert_eq!(dims(opacities), [n], "opacities must be [N]");
    assert!(
        n < (1 << 31),
        "at most 2^31 - 1 Gaussians are supported, got {n}"
    );
    n
}

/// The low key bits the depth sort must sort: those in which the smallest and the largest
/// visible key differ (all visible keys share the bits above them). Culled Gaussians, whose
/// keys may differ anywhere, touch no tile, so their place in the order does not matter;
/// without intersections nothing needs sorting.
pub fn depth_key_bits(min_key: u32, max_key: u32, intersections: usize) -> u32 {
    if intersections == 0 || min_key > max_key {
        0
    } else {
        bit_length(min_key ^ max_key)
    }
}

/// Number of bits needed to hold `max_value` (0 for 0).
fn bit_length(max_value: u32) -> u32 {
    u32::BITS - max_value.leading_zeros()
}

/// Image and tile grid sizes of a camera.
struct Frame {
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
}

impl Frame {
    fn new(camera: &Camera) -> Self {
        assert!(
            camera.width > 0 && camera.height > 0,
            "the image must not be empty, got {}x{}",
            camera.width,
            camera.height
        );
        Self {
            width: camera.width,
            height: camera.height,
            tiles_x: camera.width.div_ceil(TILE_SIZE),
            tiles_y: camera.height.div_ceil(TILE_SIZE),
        }
    }

    fn num_tiles(&self) -> usize {
        self.tiles_x as usize * self.tiles_y as usize
    }

    fn num_pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    fn tile_grid(&self) -> CubeCount {
        CubeCount::Static(self.tiles_x, self.tiles_y, 1)
    }

    fn tile_dim(&self) -> CubeDim {
        CubeDim::new_2d(TILE_SIZE, TILE_SIZE)
    }
}

impl Ctx {
    /// The camera buffer (see `texavatars_kernels::splat::camera`).
    fn camera(&self, camera: &Camera, background: [f32; 3]) -> Handle {
        let packed = pack_camera(
            [camera.width, camera.height],
            [camera.fx, camera.fy, camera.cx, camera.cy],
            &camera.world_to_camera,
            background,
        );
        self.client.create_from_slice(f32::as_bytes(&packed))
    }

    /// `handle`, or a one-element zero buffer when `handle` may be empty.
    fn nonempty(&self, handle: &Handle) -> Handle {
        if handle.size() == 0 {
            self.zeros(1)
        } else {
            handle.clone()
        }
    }

    /// `[0, 1, ..., len - 1]`.
    fn iota(&self, len: usize) -> Handle {
        let handle = self.empty(len);
        let (count, dim) = self.elementwise(len);
        // SAFETY: one thread per element, bounds-checked against `len`.
        unsafe {
            iota_u32::launch_unchecked(&self.client, count, dim, arg(&handle, len), len as u32);
        }
        handle
    }

    /// `source[index[i]]` for `i < len`.
    fn gather(&self, source: &Handle, index: &Handle, len: usize) -> Handle {
        let output = self.empty(len);
        let (count, dim) = self.elementwise(len);
        let source_len = source.size() as usize / size_of::<u32>();
        // SAFETY: `index` holds `len` valid indices into `source`.
        unsafe {
            gather_u32::launch_unchecked(
                &self.client,
                count,
                dim,
                arg(source, source_len),
                arg(index, len),
                arg(&output, len),
                len as u32,
            );
        }
        output
    }

    /// Writes the `[start, end)` of every key of the sorted `keys` (`len` entries) into
    /// `ranges` (zero-filled by the caller).
    fn segment_ranges(&self, keys: &Handle, ranges: &Handle, len: usize) {
        let (count, dim) = self.elementwise(len);
        let ranges_len = ranges.size() as usize / size_of::<u32>();
        // SAFETY: every key indexes `ranges` (keys are tile or Gaussian ids).
        unsafe {
            segment_ranges::launch_unchecked(
                &self.client,
                count,
                dim,
                arg(keys, len),
                arg(ranges, ranges_len),
                len as u32,
            );
        }
    }

    /// Exclusive prefix sum of the `len >= 1` words of `input`, and a one-word buffer with
    /// their total.
    fn exclusive_scan(&self, input: &Handle, len: usize) -> (Handle, Handle) {
        let blocks = len.div_ceil(SCAN_BLOCK as usize);
        let output = self.empty(len);
        let block_sums = self.empty(blocks);
        let (count, dim) = self.blocks(blocks, SCAN_THREADS);
        // SAFETY: one workgroup per block, bounds-checked against `len` and `blocks`.
        unsafe {
            scan_blocks::launch_unchecked(
                &self.client,
                count,
                dim,
                arg(input, len),
                arg(&output, len),
                arg(&block_sums, blocks),
                len as u32,
                blocks as u32,
            );
        }
        if blocks == 1 {
            return (output, block_sums);
        }
        let (block_offsets, total) = self.exclusive_scan(&block_sums, blocks);
        let (count, dim) = self.blocks(blocks, SCAN_THREADS);
        // SAFETY: as above.
        unsafe {
            scan_add_block_offsets::launch_unchecked(
                &self.client,
                count,
                dim,
                arg(&output, len),
                arg(&block_offsets, blocks),
                len as u32,
                blocks as u32,
            );
        }
        (output, total)
    }

    /// Stable sort of `len` `(key, value)` pairs by the low `bits` bits of the keys. The
    /// inputs are not modified; returns new `(keys, values)` buffers (the inputs themselves
    /// when there is nothing to sort).
    fn radix_sort(
        &self,
        keys: &Handle,
        values: &Handle,
        len: usize,
        bits: u32,
    ) -> (Handle, Handle) {
        if bits == 0 || len <= 1 {
            return (keys.clone(), values.clone());
        }
        let blocks = len.div_ceil(RADIX_BLOCK as usize);
        let histogram_len = RADIX_BUCKETS as usize * blocks;
        let histogram = self.empty(histogram_len);
        let buffers = [
            (self.empty(len), self.empty(len)),
            (self.empty(len), self.empty(len)),
        ];
        let (mut cur_keys, mut cur_values) = (keys.clone(), values.clone());
        for (pass, shift) in (0..bits).step_by(RADIX_BITS as usize).enumerate() {
            let (next_keys, next_values) = buffers[pass % 2].clone();
            // The last pass may take fewer than RADIX_BITS bits: the bits above `bits` are
            // not part of the order.
            let digit_mask = ((1u64 << (bits - shift).min(RADIX_BITS)) - 1) as u32;
            let (count, dim) = self.blocks(blocks, RADIX_THREADS);
            // SAFETY: one workgroup per block, bounds-checked against `len` and `blocks`;
            // scattered positions are a permutation of `0..len`.
            unsafe {
                radix_histogram::launch_unchecked(
                    &self.client,
                    count.clone(),
                    dim,
                    arg(&cur_keys, len),
                    arg(&histogram, histogram_len),
                    len as u32,
                    shift,
                    digit_mask,
                    blocks as u32,
                );
            }
            let (digit_offsets, _) = self.exclusive_scan(&histogram, histogram_len);
            unsafe {
                radix_scatter::launch_unchecked(
                    &self.client,
                    count,
                    dim,
                    arg(&cur_keys, len),
                    arg(&cur_values, len),
                    arg(&digit_offsets, histogram_len),
                    arg(&next_keys, len),
                    arg(&next_values, len),
                    len as u32,
                    shift,
                    digit_mask,
                    blocks as u32,
                );
            }
            cur_keys = next_keys;
            cur_values = next_values;
        }
        (cur_keys, cur_values)
    }

    /// Reads the first `len` words of `handle`.
    fn read_words(&self, handle: &Handle, len: usize) -> Vec<u32> {
        HOST_READS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let bytes = self
            .client
            .read_one(handle.clone())
            .expect("reading a buffer back from the device failed");
        bytes
            .chunks_exact(size_of::<u32>())
            .take(len)
            .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
            .collect()
    }

    /// Reads the first word of `handle`.
    fn read_u32(&self, handle: &Handle) -> u32 {
        HOST_READS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let bytes = self
            .client
            .read_one(handle.clone())
            .expect("reading a value back from the device failed");
        u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// wgpu's default `max_storage_buffer_binding_size` (128 MiB), what browsers' WebGPU
    /// grants without asking for more.
    const WEBGPU_DEFAULT: u64 = 128 << 20;

    fn scene(m: Option<usize>, slots: bool) -> SceneSize {
        SceneSize {
            gaussians: 124_535,
            width: 550,
            height: 802,
            intersections: m,
            slots,
        }
    }

    #[test]
    fn depth_sort_keeps_only_the_differing_key_bits() {
        let key = |z: f32| z.to_bits();
        // A head about a metre away: depths 0.8 to 1.2 share the top 8 key bits.
        assert_eq!(depth_key_bits(key(0.8), key(1.2), 10), 24);
        // Within one binade only the mantissa bits can differ.
        assert_eq!(depth_key_bits(key(1.0), key(1.5), 10), 23);
        // One depth: nothing to sort; no intersections: nothing to sort.
        assert_eq!(depth_key_bits(key(2.0), key(2.0), 10), 0);
        assert_eq!(depth_key_bits(u32::MAX, 0, 0), 0);
        // A scene from the near plane to far away still needs the exponent bits.
        assert_eq!(depth_key_bits(key(0.011), key(1.0e4), 10), 31);
        // Sorting by the low bits orders every key of the span as the full key does.
        let keys: Vec<u32> = [0.8f32, 1.2, 0.95, 1.0, 1.19, 0.81].map(key).to_vec();
        let bits = depth_key_bits(key(0.8), key(1.2), keys.len());
        let mask = (1u64 << bits) as u32 - 1;
        let mut by_low: Vec<usize> = (0..keys.len()).collect();
        by_low.sort_by_key(|&i| keys[i] & mask);
        let mut by_full: Vec<usize> = (0..keys.len()).collect();
        by_full.sort_by_key(|&i| keys[i]);
        assert_eq!(by_low, by_full);
    }

    #[test]
    fn paper_scale_scene_fits_the_webgpu_default() {
        // The `paper` avatar's 508k intersections (performance.md), on both paths.
        for slots in [false, true] {
            assert_eq!(
                check_buffers(&scene(Some(508_000), slots), WEBGPU_DEFAULT),
                Ok(())
            );
        }
    }

    #[test]
    fn oversized_slots_name_the_scene_and_the_limit() {
        // 5M intersections: 20 MB of ids fit, 180 MB of slots do not.
        let s = scene(Some(5_000_000), true);
        let e = check_buffers(&s, WEBGPU_DEFAULT).expect_err("slots over the limit");
        for part in [
            "124535 Gaussians",
            "550 x 802 pixels",
            "5000000 tile intersections",
            "180000000 bytes",
            "gradient slots",
            "134217728 bytes",
        ] {
            assert!(e.contains(part), "{part:?} missing from: {e}");
        }
        // With float atomics there are no slots.
        assert_eq!(
            check_buffers(&scene(Some(5_000_000), false), WEBGPU_DEFAULT),
            Ok(())
        );
    }

    #[test]
    fn allocation_above_the_limit_is_refused_with_its_size() {
        use burn_cubecl::cubecl::device::WgpuDeviceKind;
        let device = CubeDevice::wgpu(WgpuDeviceKind::DefaultDevice).expect("a wgpu device");
        let ctx = Ctx {
            client: device.client(),
            device,
        };
        let limit = max_binding_bytes(&ctx.client);
        let words = (limit / 4 + 1) as usize;
        let err = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| ctx.empty(words)))
            .expect_err("refused");
        let msg = err.downcast_ref::<String>().cloned().unwrap_or_default();
        assert!(
            msg.contains(&format!("{words} 32-bit words"))
                && msg.contains(&format!("({limit} bytes)")),
            "{msg}"
        );
        // Below the limit buffers are still made.
        let _ = ctx.empty(1024);
    }

    #[test]
    fn before_counting_only_gaussians_and_pixels_are_checked() {
        let s = SceneSize {
            gaussians: 10,
            width: 8192,
            height: 8192,
            intersections: None,
            slots: true,
        };
        let e = check_buffers(&s, WEBGPU_DEFAULT).expect_err("a 1 GiB image");
        assert!(
            e.contains("the image [H, W, 4]") && !e.contains("intersections"),
            "{e}"
        );
        assert_eq!(check_buffers(&s, 2 << 30), Ok(()));
    }
}
