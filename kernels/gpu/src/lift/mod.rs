//! The texel-Jacobian lifting operator's kernels. One kernel per file; `bwd/` mirrors the
//! forward ones. Host side: `src/lift/gpu.rs`.

pub mod blend;
pub mod constants;
pub mod csr_gather;
pub mod frames;
pub mod math;
pub mod opacity_grad;
pub mod transform;

pub mod bwd {
    //! Backward kernels.
    pub mod frames;
    pub mod transform;
}
