//! The texel-Jacobian lifting operator's shared constants (kernels follow in later work).

pub mod constants;
