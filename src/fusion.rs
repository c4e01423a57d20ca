//! The custom ops on burn's kernel-fusion backend (`Fusion<CubeBackend>`, cargo feature
//! `fusion`, on by default).
//!
//! With the feature, burn's cubecl backend (`burn::backend::Cube`) is `Fusion<CubeBackend>`:
//! element-wise chains of burn's own ops (the decoders' bias, LeakyReLU, weight norm, the
//! losses) are recorded lazily and compiled into fused kernels. On the GPU the transposed
//! convolution and the bias + activation epilogue are their traits' default bodies of burn
//! ops (`impl ConvTBackend for Cube {}`), which the fusion backend records and fuses like any
//! other.
//!
//! The splat cannot be a lazy fusion op (`#[backend_extension(..., Fusion)]` with
//! `#[fusion(...)]` metadata): its forward sizes the intersection buffers by a count read
//! back from the device, so its output shapes are not known before it runs. The splat and
//! lift ops therefore run *eagerly* on the fusion backend: [`resolve_float`] executes the
//! queued fused work that produces an input and hands over the inner backend's tensor, the
//! inner backend's kernels run, and [`register_float`] hands their outputs back to the
//! fusion stream as fresh tensors (the way burn-fusion's own `float_from_data` registers a
//! tensor it did not compute). The inputs and outputs are whole tensors; nothing is copied.

use burn::backend::TensorMetadata;
use burn::backend::fusion::stream::StreamId;
use burn::backend::fusion::{Fusion, FusionBackend, FusionTensor, NoOp, get_client};
use burn::backend::ir::{BackendIr, InitOperationIr, OperationIr};
use burn::backend::tensor::{FloatTensor, IntTensor};

/// The inner backend's tensor behind a fusion float tensor, after the queued operations
/// that produce it have executed.
pub fn resolve_float<B: FusionBackend>(t: FloatTensor<Fusion<B>>) -> FloatTensor<B> {
    let client = t.client.clone();
    client.resolve_tensor_float::<B>(t)
}

/// The inner backend's tensor behind a fusion int tensor (as [`resolve_float`]).
pub fn resolve_int<B: FusionBackend>(t: IntTensor<Fusion<B>>) -> IntTensor<B> {
    let client = t.client.clone();
    client.resolve_tensor_int::<B>(t)
}

/// A tensor computed by the inner backend, registered on the fusion stream of `device`.
pub fn register_float<B: FusionBackend>(
    t: FloatTensor<B>,
    device: &<B as burn::backend::BackendTypes>::Device,
) -> FloatTensor<Fusion<B>> {
    let (shape, dtype) = (t.shape(), t.dtype());
    register::<B>(B::float_tensor_handle(t), shape, dtype, device)
}

/// An int tensor computed by the inner backend (as [`register_float`]).
pub fn register_int<B: FusionBackend>(
    t: IntTensor<B>,
    device: &<B as burn::backend::BackendTypes>::Device,
) -> IntTensor<Fusion<B>> {
    let (shape, dtype) = (t.shape(), t.dtype());
    register::<B>(B::int_tensor_handle(t), shape, dtype, device)
}

/// Registers an inner backend's tensor (float or int alike) on the fusion stream.
fn register<B: FusionBackend>(
    handle: <B as BackendIr>::Handle,
    shape: burn::tensor::Shape,
    dtype: burn::tensor::DType,
    device: &<B as burn::backend::BackendTypes>::Device,
) -> FusionTensor<B::FusionRuntime> {
    let client = get_client::<B>(device);
    let desc = InitOperationIr::create(shape, dtype, || client.register_tensor_handle(handle));
    let mut outputs = client.register(
        StreamId::current(),
        OperationIr::Init(desc),
        NoOp::<B>::new(),
    );
    // An init operation has exactly one output, the registered tensor.
    outputs.remove(0)
}

/// The device of a fusion tensor, for [`register_float`].
pub fn device_of<B: FusionBackend>(
    t: &FloatTensor<Fusion<B>>,
) -> <B as burn::backend::BackendTypes>::Device {
    t.client.device().clone()
}
