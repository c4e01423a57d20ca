//! Stable LSD radix sort of `(u32 key, u32 value)` pairs, [`RADIX_BITS`] bits of the key per
//! pass.
//!
//! A pass is three launches: [`histogram::radix_histogram()`] counts the digits of every block,
//! the host scans the histogram (exclusive, digit-major, see `scan`) into global digit
//! offsets, and [`scatter::radix_scatter()`] moves every pair to
//! `offset[digit][block] + rank`, where the rank counts the pairs of the same digit before it
//! in its block. Ranks preserve the input order, so every pass is stable and repeated passes
//! from the least significant digit up sort by the whole key with ties kept in input order.
//!
//! Both kernels give a workgroup of [`RADIX_THREADS`] threads a block of [`RADIX_BLOCK`]
//! consecutive pairs, [`RADIX_ITEMS`] consecutive pairs per thread. Blocks are numbered by
//! the linear cube position.

pub mod histogram;
pub mod scatter;

/// Key bits sorted per pass.
pub const RADIX_BITS: u32 = 4;
/// Distinct digits per pass.
pub const RADIX_BUCKETS: u32 = 1 << RADIX_BITS;
/// Threads per workgroup.
pub const RADIX_THREADS: u32 = 256;
/// Consecutive pairs per thread.
pub const RADIX_ITEMS: u32 = 4;
/// Pairs per workgroup.
pub const RADIX_BLOCK: u32 = RADIX_THREADS * RADIX_ITEMS;
