//! The allocator's settings, for the `texavatars` binary and the benchmarks, which use
//! mimalloc as their global allocator.
//!
//! mimalloc returns freed pages to the OS ("purges" them: `MADV_DONTNEED` on Linux) once they
//! have stayed free for `purge_delay` milliseconds. A CPU training step frees and allocates
//! the same few hundred MB of activations and gradients every iteration, so purged pages come
//! back as page faults that the kernel must zero (`clear_page_erms` in a profile), a
//! noticeable share of a small `cpu` step. With purging off, freed pages stay mapped and are
//! reused, and the step is faster (`TEXAVATARS_BENCH_ROWS=step cargo bench --bench
//! cpu_vs_torch` compares, docs/performance.md). The cost is that the process keeps its peak
//! resident size until it exits, which a training run reaches anyway.

use libmimalloc_sys::{mi_option_get, mi_option_set, mi_option_t};

/// `mi_option_purge_delay` of `mi_option_e` in mimalloc's `include/mimalloc.h` (v2 and v3
/// alike). libmimalloc-sys names only some of the options, not this one; the test
/// `purge_delay_index_is_mimallocs` checks the index against mimalloc's default for it.
const PURGE_DELAY: mi_option_t = 15;

/// "-1 for no purging at all" (mimalloc.h, `mi_option_purge_delay`).
const NEVER: std::os::raw::c_long = -1;

/// Keeps freed pages mapped for reuse (see the module docs). Call it first thing in `main`;
/// it only changes a setting, so calling it again, or where mimalloc is not the global
/// allocator, does no harm.
pub fn keep_freed_pages() {
    // SAFETY: `mi_option_set` only stores an integer in mimalloc's option table; it takes no
    // pointers and may be called at any time (mimalloc.h).
    unsafe { mi_option_set(PURGE_DELAY, NEVER) }
}

/// mimalloc's current purge delay in milliseconds (-1: never).
pub fn purge_delay() -> i64 {
    // SAFETY: reads an integer from mimalloc's option table (mimalloc.h).
    unsafe { mi_option_get(PURGE_DELAY) as i64 }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Index 15 is `purge_delay`: before anything sets it, it holds the default of
    /// mimalloc v3's `src/options.c` (`{ 1000, MI_OPTION_UNINIT, MI_OPTION_LEGACY(purge_delay,
    /// reset_delay) }`) unless the environment sets `MIMALLOC_PURGE_DELAY`; the neighbouring
    /// options default to 1 (`deprecated_eager_commit_delay`) and 0 (`use_numa_nodes`). Then
    /// [`keep_freed_pages`] sets it to -1.
    #[test]
    fn purge_delay_index_is_mimallocs() {
        let from_env = std::env::var("MIMALLOC_PURGE_DELAY")
            .ok()
            .and_then(|v| v.parse::<i64>().ok());
        assert_eq!(purge_delay(), from_env.unwrap_or(1000));
        keep_freed_pages();
        assert_eq!(purge_delay(), -1);
    }
}
