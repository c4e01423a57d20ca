//! Editing the optimiser's state when the Gaussians change ([`edit_moments`]): Adam's
//! moments follow the rows that densification clones, splits and prunes.

use burn::module::ParamId;
use burn::optim::{ModuleOptimizer, OptimizerRecord};
use burn::tensor::{DType, Shape, TensorData};

/// The optimiser with the moments of the parameters `ids` re-rowed by `old_from_new`
/// (`Some(old)`: that row's; `None`: zeros), and every moment of `zeroed` set to zero
/// (GaussianAvatars' `cat_tensors_to_optimizer`, `_prune_optimizer`,
/// `replace_tensor_to_optimizer`). Goes through the optimiser's burnpack record; a
/// parameter's step count is kept.
pub fn edit_moments(
    optim: &ModuleOptimizer,
    ids: &[ParamId],
    old_from_new: &[Option<usize>],
    zeroed: Option<ParamId>,
) -> ModuleOptimizer {
    let bytes = optim
        .to_record()
        .into_bytes()
        .expect("an optimiser record serialises");
    let reader = burn_pack::Reader::from_bytes(bytes).expect("burnpack written just now");
    let scalars = reader.scalars().clone();
    let metadata = reader.metadata().clone();
    let tensors = reader.into_tensors().expect("burnpack written just now");
    let ids: Vec<u64> = ids.iter().map(|i| i.val()).collect();
    let zeroed = zeroed.map(|i| i.val());
    let edited: Vec<burn_pack::Tensor> = tensors
        .into_iter()
        .map(|t| {
            let (name, dtype, shape, param_id, bytes) =
                t.into_parts().expect("burnpack written just now");
            let rerow = param_id.is_some_and(|p| ids.contains(&p));
            let zero = param_id.is_some() && param_id == zeroed;
            if !(rerow || zero) || dtype != DType::F32 || shape.num_dims() == 0 {
                return burn_pack::Tensor::new(name, dtype, shape, param_id, bytes);
            }
            let data = TensorData::from_bytes(bytes, shape.clone(), dtype);
            let values: Vec<f32> = data.try_to_vec().expect("f32 moments");
            let dims = shape.as_slice().to_vec();
            let row = dims[1..].iter().product::<usize>();
            let mut out = if rerow {
                let mut out = vec![0.0f32; old_from_new.len() * row];
                for (new, old) in old_from_new.iter().enumerate() {
                    if let Some(o) = old {
                        out[new * row..(new + 1) * row]
                            .copy_from_slice(&values[o * row..(o + 1) * row]);
                    }
                }
                out
            } else {
                values
            };
            if zero {
                out.iter_mut().for_each(|v| *v = 0.0);
            }
            let mut dims = dims;
            if rerow {
                dims[0] = old_from_new.len();
            }
            let data = TensorData::new(out, Shape::from(dims));
            let (bytes, shape, dtype) = data.into_parts();
            burn_pack::Tensor::new(name, dtype, shape, param_id, bytes)
        })
        .collect();
    let mut writer = burn_pack::Writer::new(edited);
    for (k, v) in &scalars {
        writer = writer.with_scalar(k, *v);
    }
    for (k, v) in &metadata {
        writer = writer.with_metadata(k, v);
    }
    let record = OptimizerRecord::from_bytes(writer.into_bytes().expect("serialises"))
        .expect("a record written just now");
    optim.clone().load_record(record)
}
