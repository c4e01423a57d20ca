//! Launching the CubeCL kernels on burn's cubecl backend: the client and device of a pass
//! (`Ctx`) with its buffer and launch helpers, and kernel arguments over buffers (`arg`).
//! The splat ([`crate::splat`]) and the lifting ([`crate::lift`]) launch through them.

use burn::tensor::{DType, Shape};
use burn_cubecl::CubeDevice;
use burn_cubecl::cubecl::client::Client;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::cubecl::{CubeCount, CubeDim, calculate_cube_count_elemwise};
use burn_cubecl::kernel::{cast, into_contiguous};
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;
use texavatars_kernels::splat::fill::fill_u32;

/// Threads per workgroup of the one-thread-per-element kernels.
pub(crate) const ELEMENTWISE_THREADS: u32 = 256;

/// The largest storage buffer one kernel may bind on `client`'s adapter, in bytes: wgpu's
/// `max_storage_buffer_binding_size`, capped by `max_buffer_size` (cubecl-wgpu reports
/// their minimum as the largest allocation).
pub fn max_binding_bytes(client: &Client) -> u64 {
    client.properties().memory.max_page_size
}

/// A kernel argument over the first `len` elements of `handle` (at least one).
pub(crate) fn arg(handle: &Handle, len: usize) -> BufferArg {
    // SAFETY: callers pass the element count the buffer was allocated with (or fewer).
    unsafe { BufferArg::from_raw_parts(handle.clone(), len.max(1)) }
}

/// The client and device every buffer of one pass lives on, with buffer helpers.
pub(crate) struct Ctx {
    pub(crate) client: Client,
    pub(crate) device: CubeDevice,
}

impl Ctx {
    pub(crate) fn new(reference: &CubeTensor) -> Self {
        Self {
            client: reference.client.clone(),
            device: reference.device.clone(),
        }
    }

    pub(crate) fn on(device: &CubeDevice) -> Self {
        Self {
            client: device.client(),
            device: device.clone(),
        }
    }

    /// `tensor` as a contiguous `f32` tensor on this context's device.
    pub(crate) fn float_input(&self, tensor: CubeTensor) -> CubeTensor {
        assert!(
            tensor.device == self.device,
            "all splat inputs must be on the same device"
        );
        let tensor = if tensor.dtype == DType::F32 {
            tensor
        } else {
            cast(tensor, DType::F32)
        };
        into_contiguous(tensor)
    }

    /// An uninitialised buffer of `len` (at least one) 32-bit words.
    ///
    /// # Panics
    /// When the buffer exceeds the adapter's largest storage binding ([`max_binding_bytes`]):
    /// the last guard for buffers no scene check covers (the lifting's), with a message
    /// instead of a panic inside wgpu.
    pub(crate) fn empty(&self, len: usize) -> Handle {
        let bytes = len.max(1) * size_of::<u32>();
        let limit = max_binding_bytes(&self.client);
        assert!(
            bytes as u64 <= limit,
            "a GPU buffer of {len} 32-bit words ({bytes} bytes) exceeds this adapter's largest \
             storage buffer binding ({limit} bytes): use fewer Gaussians (a smaller texel \
             resolution) or a smaller image, or an adapter with a larger \
             max_storage_buffer_binding_size"
        );
        self.client.empty(bytes)
    }

    /// A zero-filled buffer of `len` (at least one) 32-bit words (`0u32` and `0.0f32`).
    pub(crate) fn zeros(&self, len: usize) -> Handle {
        let handle = self.empty(len);
        let len = len.max(1);
        let (count, dim) = self.elementwise(len);
        // SAFETY: one thread per element, bounds-checked against `len`.
        unsafe {
            fill_u32::launch_unchecked(
                &self.client,
                count,
                dim,
                arg(&handle, len),
                0u32,
                len as u32,
            );
        }
        handle
    }

    /// Launch configuration for one thread per element.
    pub(crate) fn elementwise(&self, len: usize) -> (CubeCount, CubeDim) {
        let dim = CubeDim::new_1d(ELEMENTWISE_THREADS);
        let count = calculate_cube_count_elemwise(&self.client, len.max(1), dim);
        (count, dim)
    }

    /// Launch configuration for `blocks` workgroups of `threads` threads (the kernels read
    /// their block from the linear cube position and skip positions past `blocks`).
    pub(crate) fn blocks(&self, blocks: usize, threads: u32) -> (CubeCount, CubeDim) {
        let dim = CubeDim::new_1d(threads);
        let count =
            calculate_cube_count_elemwise(&self.client, blocks.max(1) * threads as usize, dim);
        (count, dim)
    }

    /// Wraps a contiguous buffer as a tensor.
    pub(crate) fn tensor<const D: usize>(
        &self,
        handle: Handle,
        shape: [usize; D],
        dtype: DType,
    ) -> CubeTensor {
        if shape.iter().product::<usize>() == 0 {
            return empty_device_dtype(
                self.client.clone(),
                self.device.clone(),
                Shape::new(shape),
                dtype,
            );
        }
        CubeTensor::new_contiguous(
            self.client.clone(),
            self.device.clone(),
            Shape::new(shape),
            handle,
            dtype,
        )
    }

    /// An empty (zero-element) `f32` tensor.
    pub(crate) fn empty_tensor<const D: usize>(&self, shape: [usize; D]) -> CubeTensor {
        empty_device_dtype(
            self.client.clone(),
            self.device.clone(),
            Shape::new(shape),
            DType::F32,
        )
    }
}
