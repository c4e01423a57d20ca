//! Exclusive prefix sum (scan) of `u32`, multi-level.
//!
//! [`blocks::scan_blocks()`] scans every block of [`SCAN_BLOCK`] elements and writes the block
//! totals; the host scans the totals recursively with the same kernel and adds them back with
//! [`add_block_offsets::scan_add_block_offsets()`] until a single block remains, whose total is
//! the total of the whole input.
//!
//! Blocks are numbered by the linear cube position so the grid may be two dimensional.

pub mod add_block_offsets;
pub mod blocks;

/// Threads per scan workgroup.
pub const SCAN_THREADS: u32 = 256;
/// Consecutive elements each thread scans serially.
pub const SCAN_ITEMS: u32 = 4;
/// Elements per workgroup.
pub const SCAN_BLOCK: u32 = SCAN_THREADS * SCAN_ITEMS;
