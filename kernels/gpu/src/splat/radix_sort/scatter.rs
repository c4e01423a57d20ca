//! Radix sort pass, step 2: stable scatter. One workgroup of `RADIX_THREADS` threads per
//! block of `RADIX_BLOCK` pairs, `RADIX_ITEMS` consecutive pairs per thread.
//!
//! Every pair goes to `digit_offsets[digit][block] + (pairs of that digit before it in the
//! block)`, which keeps equal digits in input order.
//!
//! The rank within the block comes from sorting the block in workgroup memory: an entry
//! `digit << 16 | index in block` per pair, sorted stably by the digit in `RADIX_BITS /
//! LOCAL_BITS` steps of `LOCAL_BITS` bits, least significant first. Each step counts the
//! sub-digits of every thread's entries, scans the counts across threads and moves every
//! entry to `(entries of smaller sub-digits) + (same sub-digit, earlier threads) + (same
//! sub-digit, earlier in the thread)`. Once sorted, a pair's rank in its digit is its
//! position minus the position of its digit's first entry, and consecutive threads write
//! consecutive addresses of each digit. Keys and values are read again from the input by
//! the entry's index (the block's 8 KiB, from the cache), not carried through workgroup
//! memory: 14 KiB of it in all, within WebGPU's default 16 KiB.
//!
//! # Shapes
//! - `keys_in`, `values_in`, `keys_out`, `values_out`: `[n]` u32.
//! - `digit_offsets`: `[RADIX_BUCKETS * num_blocks]` u32, the exclusive scan of the
//!   digit-major histogram.

use cubecl::prelude::*;

use super::{
    LOCAL_BITS, LOCAL_BUCKETS, RADIX_BITS, RADIX_BLOCK, RADIX_BUCKETS, RADIX_ITEMS, RADIX_THREADS,
};

/// An entry's index in its block: its low 16 bits.
const INDEX_MASK: u32 = 0xffff;
/// Where an entry's digit starts.
const DIGIT_SHIFT: u32 = 16;

/// See the module documentation. `digit_mask < RADIX_BUCKETS`.
///
/// Per-thread sub-digit counts are packed two sub-digits per `u32` (16 bits each; a block
/// holds at most `RADIX_BLOCK` < 2^16 pairs, so the halves never carry into each other) and
/// scanned across threads per sub-digit pair: each of the 8 rows of 256 counts is split
/// into 32 segments of 8 threads, one segment per thread.
#[allow(clippy::too_many_arguments)]
#[cube(launch_unchecked)]
pub fn radix_scatter(
    keys_in: &[u32],
    values_in: &[u32],
    digit_offsets: &[u32],
    keys_out: &mut [u32],
    values_out: &mut [u32],
    n: u32,
    shift: u32,
    digit_mask: u32,
    num_blocks: u32,
) {
    let block = CUBE_POS as u32;
    if block >= num_blocks {
        terminate!();
    }
    let tid = UNIT_POS;
    let pair_rows = LOCAL_BUCKETS / 2;
    let threads_per_row = RADIX_THREADS / pair_rows;
    let segment_len = RADIX_THREADS / threads_per_row;
    let block_start = block * RADIX_BLOCK;

    // The thread's entries. A pair past the end gets the largest digit: it sorts after every
    // pair of the block (it comes last in the input, and every step is stable) and is never
    // written.
    let mut entries = Array::<u32>::new(RADIX_ITEMS as usize);
    for j in 0..RADIX_ITEMS {
        let local = tid * RADIX_ITEMS + j;
        let idx = block_start + local;
        let present = idx < n;
        let mut key = 0u32;
        if present {
            key = keys_in[idx as usize];
        }
        let digit = select(present, (key >> shift) & digit_mask, RADIX_BUCKETS - 1);
        entries[j as usize] = (digit << DIGIT_SHIFT) | local;
    }

    // packed[row * RADIX_THREADS + thread]: counts of sub-digits 2 row (low half) and
    // 2 row + 1 (high half) among the thread's entries; then their exclusive scan.
    let mut packed = Shared::<[u32]>::new_slice((pair_rows * RADIX_THREADS) as usize);
    let mut seg_totals = Shared::<[u32]>::new_slice(RADIX_THREADS as usize);
    // row_totals[row]: the block's counts of sub-digits 2 row and 2 row + 1, packed.
    let mut row_totals = Shared::<[u32]>::new_slice(pair_rows as usize);
    // The block's entries in the order of the last step.
    let mut sorted = Shared::<[u32]>::new_slice(RADIX_BLOCK as usize);
    let mut positions = Array::<u32>::new(RADIX_ITEMS as usize);

    for step in 0..RADIX_BITS / LOCAL_BITS {
        let sub_shift = DIGIT_SHIFT + step * LOCAL_BITS;
        for row in 0..pair_rows {
            packed[(row * RADIX_THREADS + tid) as usize] = 0u32;
        }
        for j in 0..RADIX_ITEMS {
            let sub = (entries[j as usize] >> sub_shift) & (LOCAL_BUCKETS - 1);
            let slot = ((sub / 2) * RADIX_THREADS + tid) as usize;
            packed[slot] += 1u32 << ((sub % 2) * 16);
        }
        sync_cube();

        // Exclusive scan of every row across threads: thread -> (row, segment).
        let row = tid / threads_per_row;
        let segment = tid % threads_per_row;
        let seg_start = row * RADIX_THREADS + segment * segment_len;
        let mut seg_total = 0u32;
        for i in 0..segment_len {
            seg_total += packed[(seg_start + i) as usize];
        }
        seg_totals[tid as usize] = seg_total;
        sync_cube();
        let mut running = 0u32;
        for s in 0..segment {
            running += seg_totals[(row * threads_per_row + s) as usize];
        }
        for i in 0..segment_len {
            let slot = (seg_start + i) as usize;
            let count = packed[slot];
            packed[slot] = running;
            running += count;
        }
        if segment == threads_per_row - 1 {
            row_totals[row as usize] = running;
        }
        sync_cube();

        for j in 0..RADIX_ITEMS {
            let sub = (entries[j as usize] >> sub_shift) & (LOCAL_BUCKETS - 1);
            let mut smaller = 0u32;
            for d in 0..sub {
                smaller += (row_totals[(d / 2) as usize] >> ((d % 2) * 16)) & INDEX_MASK;
            }
            let earlier_threads = (packed[((sub / 2) * RADIX_THREADS + tid) as usize]
                >> ((sub % 2) * 16))
                & INDEX_MASK;
            let mut earlier_in_thread = 0u32;
            for k in 0..j {
                let other = (entries[k as usize] >> sub_shift) & (LOCAL_BUCKETS - 1);
                if other == sub {
                    earlier_in_thread += 1u32;
                }
            }
            positions[j as usize] = smaller + earlier_threads + earlier_in_thread;
        }
        // Every read of `sorted` of the step before happened before this step's first
        // barrier, so it can be overwritten now.
        for j in 0..RADIX_ITEMS {
            sorted[positions[j as usize] as usize] = entries[j as usize];
        }
        sync_cube();
        for j in 0..RADIX_ITEMS {
            entries[j as usize] = sorted[(tid * RADIX_ITEMS + j) as usize];
        }
    }

    // digit_start[d]: the position of digit d's first entry (set for the digits present).
    let mut digit_start = Shared::<[u32]>::new_slice(RADIX_BUCKETS as usize);
    for j in 0..RADIX_ITEMS {
        let position = tid * RADIX_ITEMS + j;
        let digit = entries[j as usize] >> DIGIT_SHIFT;
        let mut first = position == 0;
        if position > 0 {
            first = (sorted[(position - 1) as usize] >> DIGIT_SHIFT) != digit;
        }
        if first {
            digit_start[digit as usize] = position;
        }
    }
    sync_cube();

    for j in 0..RADIX_ITEMS {
        let position = tid * RADIX_ITEMS + j;
        let entry = entries[j as usize];
        let idx = block_start + (entry & INDEX_MASK);
        if idx < n {
            let digit = entry >> DIGIT_SHIFT;
            let dst = digit_offsets[(digit * num_blocks + block) as usize] + position
                - digit_start[digit as usize];
            keys_out[dst as usize] = keys_in[idx as usize];
            values_out[dst as usize] = values_in[idx as usize];
        }
    }
}
