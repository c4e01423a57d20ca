//! Radix sort pass, step 2: stable scatter. One workgroup of `RADIX_THREADS` threads per
//! block of `RADIX_BLOCK` pairs, `RADIX_ITEMS` consecutive pairs per thread.
//!
//! Every pair goes to `digit_offsets[digit][block] + (pairs of that digit before it in the
//! block)`, which keeps equal digits in input order.
//!
//! # Shapes
//! - `keys_in`, `values_in`, `keys_out`, `values_out`: `[n]` u32.
//! - `digit_offsets`: `[RADIX_BUCKETS * num_blocks]` u32, the exclusive scan of the
//!   digit-major histogram.

use cubecl::prelude::*;

use super::{RADIX_BLOCK, RADIX_BUCKETS, RADIX_ITEMS, RADIX_THREADS};

/// See the module documentation.
///
/// Per-thread digit counts are packed two digits per `u32` (16 bits each; a block holds at
/// most `RADIX_BLOCK` < 2^16 pairs, so the halves never carry into each other) and scanned
/// across threads per digit pair: each of the 8 rows of 256 counts is split into 32 segments
/// of 8 threads, one segment per thread.
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
    num_blocks: u32,
) {
    let block = CUBE_POS as u32;
    if block >= num_blocks {
        terminate!();
    }
    let tid = UNIT_POS;
    let pair_rows = RADIX_BUCKETS / 2;
    let threads_per_row = RADIX_THREADS / pair_rows;
    let segment_len = RADIX_THREADS / threads_per_row;

    // Own items; digit RADIX_BUCKETS marks a missing item past the end.
    let base = block * RADIX_BLOCK + tid * RADIX_ITEMS;
    let mut keys = Array::<u32>::new(RADIX_ITEMS as usize);
    let mut values = Array::<u32>::new(RADIX_ITEMS as usize);
    let mut digits = Array::<u32>::new(RADIX_ITEMS as usize);
    for j in 0..RADIX_ITEMS {
        let idx = base + j;
        let present = idx < n;
        let mut key = 0u32;
        let mut value = 0u32;
        if present {
            key = keys_in[idx as usize];
            value = values_in[idx as usize];
        }
        let digit = select(present, (key >> shift) & (RADIX_BUCKETS - 1), RADIX_BUCKETS);
        keys[j as usize] = key;
        values[j as usize] = value;
        digits[j as usize] = digit;
    }

    // packed[row * RADIX_THREADS + thread]: counts of digits 2 row (low half) and
    // 2 row + 1 (high half) among the thread's items.
    let mut packed = Shared::<[u32]>::new_slice((pair_rows * RADIX_THREADS) as usize);
    for row in 0..pair_rows {
        packed[(row * RADIX_THREADS + tid) as usize] = 0u32;
    }
    for j in 0..RADIX_ITEMS {
        let digit = digits[j as usize];
        if digit < RADIX_BUCKETS {
            let slot = ((digit / 2) * RADIX_THREADS + tid) as usize;
            packed[slot] += 1u32 << ((digit % 2) * 16);
        }
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
    let mut seg_totals = Shared::<[u32]>::new_slice(RADIX_THREADS as usize);
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
    sync_cube();

    for j in 0..RADIX_ITEMS {
        let digit = digits[j as usize];
        if digit < RADIX_BUCKETS {
            let before_in_block = (packed[((digit / 2) * RADIX_THREADS + tid) as usize]
                >> ((digit % 2) * 16))
                & 0xffffu32;
            let mut before_in_thread = 0u32;
            for k in 0..j {
                if digits[k as usize] == digit {
                    before_in_thread += 1u32;
                }
            }
            let dst = digit_offsets[(digit * num_blocks + block) as usize]
                + before_in_block
                + before_in_thread;
            keys_out[dst as usize] = keys[j as usize];
            values_out[dst as usize] = values[j as usize];
        }
    }
}
