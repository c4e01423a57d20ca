//! Host memory: reading a backend's tensors into host vectors and writing host vectors back
//! as tensors, for the host passes of the CPU backends (the renderer, the lifting, the layer
//! ops, the losses and Adam).

// burn-ndarray is deprecated in burn 0.22; the design keeps it alongside flex.
#![allow(deprecated)]

use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, Flex, NdArray, TensorMetadata};
use burn::tensor::{DType, Shape, TensorData};

/// Reading a backend's tensors into host vectors, for the CPU renderer and the other host
/// passes (lifting, decoder layers, losses).
pub trait HostIo: Backend {
    /// The values of a float tensor, row-major, in a vector of their own (to write in place).
    fn floats(t: FloatTensor<Self>) -> Vec<f32> {
        read_floats::<Self>(t)
    }

    /// The values of an int tensor, row-major.
    fn ints(t: IntTensor<Self>) -> Vec<u32> {
        read_ints::<Self>(t)
    }

    /// The backend's own buffer of `t` when it holds `t`'s values as contiguous row-major
    /// f32; `None` (the default) where it does not or cannot lend it.
    fn contiguous(_t: &FloatTensor<Self>) -> Option<&[f32]> {
        None
    }

    /// `t` with its values (row-major) rewritten by `f`: in the backend's own buffer where
    /// it holds `t` alone as contiguous f32 (no copy in or out), else through a copy
    /// ([`HostIo::floats`]) made into a tensor of `t`'s shape afterwards (the default).
    fn in_place(t: FloatTensor<Self>, f: impl FnOnce(&mut [f32])) -> FloatTensor<Self> {
        in_place_copy::<Self>(t, f)
    }

    /// The values of a float tensor, row-major, to read: the backend's buffer itself where
    /// [`HostIo::contiguous`] lends it, else a copy ([`HostIo::floats`]).
    fn read(t: FloatTensor<Self>) -> HostFloats<Self> {
        if Self::contiguous(&t).is_some() {
            HostFloats(Lent::Tensor(t))
        } else {
            HostFloats(Lent::Copy(Self::floats(t)))
        }
    }
}

/// A float tensor's values on the host, read-only ([`HostIo::read`]): the tensor itself when
/// its backend lends its buffer, a copy otherwise. Dereferences to `[f32]`, row-major.
pub struct HostFloats<B: HostIo>(Lent<B>);

enum Lent<B: HostIo> {
    /// A tensor whose [`HostIo::contiguous`] is `Some` (checked by [`HostIo::read`]).
    Tensor(FloatTensor<B>),
    Copy(Vec<f32>),
}

impl<B: HostIo> std::ops::Deref for HostFloats<B> {
    type Target = [f32];

    fn deref(&self) -> &[f32] {
        match &self.0 {
            Lent::Tensor(t) => {
                B::contiguous(t).expect("HostIo::read checked that the buffer is lent")
            }
            Lent::Copy(v) => v,
        }
    }
}

/// flex keeps a tensor's values in one reference-counted buffer: reading through it saves
/// the copy that `into_data` makes of a shared tensor (every tensor autodiff keeps for a
/// backward pass is shared). Those copies were most of the `memmove` in a `cpu` training
/// step's profile (docs/performance.md).
impl HostIo for Flex {
    fn contiguous(t: &FloatTensor<Self>) -> Option<&[f32]> {
        t.as_slice::<f32>()
    }

    /// A tensor no one else holds is rewritten where it lies: `into_data` and the
    /// `TensorData` round trip would copy it (for Adam's parameters and moments every step,
    /// docs/performance.md). In training the
    /// moments are unique; the parameters are not (something else holds them) and still go
    /// through the copy.
    fn in_place(mut t: FloatTensor<Self>, f: impl FnOnce(&mut [f32])) -> FloatTensor<Self> {
        if t.dtype() == DType::F32
            && let Some((start, end)) = t.layout().contiguous_offsets()
            && let Some(values) = t.try_storage_mut::<f32>()
        {
            f(&mut values[start..end]);
            return t;
        }
        in_place_copy::<Self>(t, f)
    }
}

/// [`HostIo::in_place`] through a copy: any backend.
fn in_place_copy<H: HostIo>(t: FloatTensor<H>, f: impl FnOnce(&mut [f32])) -> FloatTensor<H> {
    let (device, shape) = (t.device(), t.shape().to_vec());
    let mut v = H::floats(t);
    f(&mut v);
    floats::<H>(v, &shape, &device)
}

/// ndarray's `into_data` copies element by element through a dynamic-rank iterator when the
/// array is shared (as autodiff inputs are), tens of nanoseconds per value, which dominated
/// the CPU path.
/// Reading through a view of the contiguous storage is a plain copy.
impl HostIo for NdArray {
    fn floats(t: FloatTensor<Self>) -> Vec<f32> {
        use burn::backend::ndarray::NdArrayTensor;
        if let NdArrayTensor::F32(s) = &t
            && let Some(slice) = s.view().as_slice()
        {
            return slice.to_vec();
        }
        read_floats::<Self>(t)
    }

    fn ints(t: IntTensor<Self>) -> Vec<u32> {
        use burn::backend::ndarray::NdArrayTensor;
        match &t {
            NdArrayTensor::I64(s) => {
                if let Some(slice) = s.view().as_slice() {
                    return slice.iter().map(|&v| v as u32).collect();
                }
            }
            NdArrayTensor::I32(s) => {
                if let Some(slice) = s.view().as_slice() {
                    return slice.iter().map(|&v| v as u32).collect();
                }
            }
            _ => {}
        }
        read_ints::<Self>(t)
    }
}

pub fn read_floats<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    let data = burn::tensor::try_read_sync(B::float_into_data(t))
        .expect("synchronous read-back is supported on CPU backends")
        .expect("reading a CPU tensor cannot fail");
    // `into_vec` moves the buffer when the dtype matches; `iter` converts element by element
    // (tens of ns each), which dominated the CPU path's time before.
    match data.dtype() {
        DType::F32 => data.into_vec::<f32>().expect("dtype checked"),
        _ => data.iter::<f32>().collect(),
    }
}

pub fn read_ints<B: Backend>(t: IntTensor<B>) -> Vec<u32> {
    let data = burn::tensor::try_read_sync(B::int_into_data(t))
        .expect("synchronous read-back is supported on CPU backends")
        .expect("reading a CPU tensor cannot fail");
    match data.dtype() {
        DType::I32 => data
            .into_vec::<i32>()
            .expect("dtype checked")
            .into_iter()
            .map(|v| v as u32)
            .collect(),
        DType::I64 => data
            .into_vec::<i64>()
            .expect("dtype checked")
            .into_iter()
            .map(|v| v as u32)
            .collect(),
        _ => data.iter::<i64>().map(|v| v as u32).collect(),
    }
}

/// A host vector as a float tensor of `shape` on `device`.
pub fn floats<B: Backend>(v: Vec<f32>, shape: &[usize], device: &B::Device) -> FloatTensor<B> {
    B::float_from_data(TensorData::new(v, Shape::from(shape.to_vec())), device)
}

pub fn ints<B: Backend>(v: Vec<u32>, shape: &[usize], device: &B::Device) -> IntTensor<B> {
    let v: Vec<i32> = v.into_iter().map(|x| x as i32).collect();
    B::int_from_data(TensorData::new(v, Shape::from(shape.to_vec())), device)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::ops::FloatTensorOps;

    /// [`HostIo::read`] lends flex's own buffer for a contiguous tensor, also a shared one
    /// (a clone), and copies a strided one (a transpose) into row-major order; the values
    /// are [`HostIo::floats`]'s in every case.
    #[test]
    fn read_lends_contiguous_flex_buffers_and_copies_strided_ones() {
        type F = Flex;
        let v: Vec<f32> = (0..6).map(|i| i as f32 * 0.5 - 1.0).collect();
        let t = F::float_from_data(TensorData::new(v.clone(), [2, 3]), &Default::default());
        let shared = t.clone();
        assert!(F::contiguous(&t).is_some());
        let lent = F::read(t);
        assert!(matches!(lent.0, Lent::Tensor(_)));
        assert_eq!(&*lent, v.as_slice());
        drop(lent);

        let transposed = F::float_swap_dims(shared, 0, 1);
        assert!(F::contiguous(&transposed).is_none());
        let copied = F::read(transposed.clone());
        assert!(matches!(copied.0, Lent::Copy(_)));
        assert_eq!(&*copied, [-1.0, 0.5, -0.5, 1.0, 0.0, 1.5].as_slice());
        assert_eq!(&*copied, F::floats(transposed).as_slice());
    }

    /// `in_place` rewrites a flex tensor no one else holds in its own buffer, and goes
    /// through a copy for a shared one (whose other holder keeps the old values) or a
    /// strided one (rewritten in row-major order of its shape); the default body (ndarray)
    /// gives the same values.
    #[test]
    fn in_place_rewrites_unique_flex_buffers_and_copies_the_rest() {
        type F = Flex;
        let v: Vec<f32> = (0..6).map(|i| i as f32 * 0.5 - 1.0).collect();
        let plus_index = |x: &mut [f32]| {
            x.iter_mut()
                .enumerate()
                .for_each(|(i, x)| *x += i as f32 * 10.0)
        };
        let want: Vec<f32> = v
            .iter()
            .enumerate()
            .map(|(i, x)| x + i as f32 * 10.0)
            .collect();

        let unique = F::float_from_data(TensorData::new(v.clone(), [2, 3]), &Default::default());
        let before = F::contiguous(&unique).expect("contiguous").as_ptr();
        let out = F::in_place(unique, plus_index);
        assert_eq!(F::contiguous(&out).expect("contiguous").as_ptr(), before);
        assert_eq!(F::floats(out), want);

        let t = F::float_from_data(TensorData::new(v.clone(), [2, 3]), &Default::default());
        let kept = t.clone();
        let out = F::in_place(t, plus_index);
        assert_eq!(F::floats(out), want);
        assert_eq!(F::floats(kept), v, "the other holder's values");

        let t = F::float_from_data(TensorData::new(v.clone(), [2, 3]), &Default::default());
        let transposed = F::float_swap_dims(t, 0, 1);
        let out = F::in_place(transposed, plus_index);
        assert_eq!(out.shape().to_vec(), vec![3, 2]);
        let row_major = [-1.0f32, 0.5, -0.5, 1.0, 0.0, 1.5];
        let want_t: Vec<f32> = row_major
            .iter()
            .enumerate()
            .map(|(i, x)| x + i as f32 * 10.0)
            .collect();
        assert_eq!(F::floats(out), want_t);

        type N = NdArray;
        let t = N::float_from_data(TensorData::new(v.clone(), [2, 3]), &Default::default());
        assert_eq!(N::floats(N::in_place(t, plus_index)), want);
    }
}
