//! Segment ranges of a sorted key list: one thread per list entry.
//!
//! For sorted `keys`, writes `ranges[key] = [start, end)`, the entries holding `key`. Entry
//! `k` starts a segment when it is the first or its predecessor differs, and ends one when it
//! is the last or its successor differs. Keys absent from the list keep whatever `ranges`
//! held, so the host zero-fills it first (empty ranges).
//!
//! Used for the per-tile ranges of the tile-sorted intersections (forward) and for the
//! per-Gaussian ranges of the Gaussian-sorted intersections (backward without float
//! atomics).
//!
//! # Shapes
//! - `keys`: `[M]` u32 sorted ascending, values `< K`.
//! - `ranges`: `[K, 2]` u32.

use cubecl::prelude::*;

/// See the module documentation.
#[cube(launch_unchecked)]
pub fn segment_ranges(keys: &[u32], ranges: &mut [u32], num_entries: u32) {
    let entry = ABSOLUTE_POS as u32;
    if entry >= num_entries {
        terminate!();
    }
    let key = keys[entry as usize];
    let slot = (key * 2) as usize;
    // Neighbours are read only when they exist.
    let mut starts = entry == 0;
    if !starts {
        starts = keys[(entry - 1) as usize] != key;
    }
    let mut ends = entry + 1 == num_entries;
    if !ends {
        ends = keys[(entry + 1) as usize] != key;
    }
    if starts {
        ranges[slot] = entry;
    }
    if ends {
        ranges[slot + 1] = entry + 1;
    }
}
