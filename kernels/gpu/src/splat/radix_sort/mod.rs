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
//! the linear cube position. The scatter ranks a block by sorting it in workgroup memory
//! first, [`LOCAL_BITS`] bits at a time (see its module), so that a pass can take 8 key bits
//! within WebGPU's default 16 KiB of workgroup memory: a 32-bit key takes 4 passes, not 8.

pub mod histogram;
pub mod scatter;

/// Key bits sorted per pass. The digit of a pass is `(key >> shift) & digit_mask`, where
/// the host narrows `digit_mask` on the last pass to the bits it was asked to sort.
pub const RADIX_BITS: u32 = 8;
/// Distinct digits per pass.
pub const RADIX_BUCKETS: u32 = 1 << RADIX_BITS;
/// Threads per workgroup.
pub const RADIX_THREADS: u32 = 256;
/// Consecutive pairs per thread.
pub const RADIX_ITEMS: u32 = 4;
/// Pairs per workgroup.
pub const RADIX_BLOCK: u32 = RADIX_THREADS * RADIX_ITEMS;
/// Digit bits per step of the scatter's block-local sort (`RADIX_BITS / LOCAL_BITS` steps).
pub const LOCAL_BITS: u32 = 4;
/// Distinct sub-digits per step of the block-local sort.
pub const LOCAL_BUCKETS: u32 = 1 << LOCAL_BITS;

// Each of the histogram's threads clears and writes out one digit; the scatter keeps a
// block's local index in the low 16 bits of an entry and the digit above it; the block-local
// sort's steps cover the digit exactly.
const _: () = assert!(RADIX_THREADS >= RADIX_BUCKETS);
const _: () = assert!(RADIX_BLOCK <= 1 << 16 && RADIX_BITS <= 16);
const _: () = assert!(RADIX_BITS.is_multiple_of(LOCAL_BITS));
