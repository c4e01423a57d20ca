//! Where the work runs: on a thread of rayon's pool rather than on the process's main thread.
//!
//! Every parallel loop of a CPU step (burn-flex's element-wise ops, gemm's products, this
//! crate's host passes) is a rayon job. Called from a thread outside the pool, rayon takes its
//! cold path (`Registry::in_worker_cold` in rayon-core): it injects the job into the pool,
//! wakes the workers, and puts the caller to sleep on a latch until the job is done, so each
//! loop costs a futex wake-up of the workers and a sleep and wake-up of the caller. A `cpu`
//! decoder step runs a few hundred such loops, and in a profile of `cargo bench --bench
//! cpu_vs_torch` (decoders, `cpu`) the wake-ups (`try_to_wake_up` under
//! `Sleep::wake_specific_thread`, `finish_task_switch`) are a large share of the time. Called
//! from one of the pool's own threads, a loop pushes its halves onto that thread's queue and
//! starts on them at once; only an idle worker needs waking, and the caller never sleeps, so
//! the small decoders' forward and backward run faster (docs/performance.md).
//!
//! [`on_pool`] therefore runs a whole command on a pool thread (the app's `cli::run`, every
//! command but `view`, whose calling thread waits on its server for the whole session and
//! would hold a worker away from the renders), and the app's library entry points that run
//! parallel work take the pool themselves (`train::train`, `train::gaussianavatars::train`,
//! `eval::run::evaluate`, `synth::generate_with`; the criterion benches' `main`), so a
//! library caller gets the binary's speed without knowing about the pool. The pool is rayon's global one (its size follows
//! `RAYON_NUM_THREADS`, as before), built here with the main thread's stack size so that deep
//! call chains behave as they did on the main thread.
//!
//! Code that waits on another thread must not run inside [`on_pool`] if that thread's work
//! needs the pool: the waiting worker is not free for it, and with one worker nothing is.

/// The stack of each pool thread: the size Rust gives the main thread on Linux (8 MiB)
/// rather than the 2 MiB of other threads, since [`on_pool`] moves the whole command there.
const STACK_BYTES: usize = 8 << 20;

/// Runs `f` on a thread of rayon's global pool and returns its result; the calling thread
/// waits. On a pool thread already (a nested call), `f` runs where it is.
///
/// The first call builds the global pool with an 8 MiB stack per thread; if something
/// built it before, that pool is used as it is.
pub fn on_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    // Fails only when the global pool already exists, which is fine (see the docs).
    let _ = rayon::ThreadPoolBuilder::new()
        .stack_size(STACK_BYTES)
        .build_global();
    rayon::scope(|_| f())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `f` runs on a pool thread, returns its value, and a nested call stays on that thread.
    #[test]
    fn runs_on_a_pool_thread_and_nests_in_place() {
        assert!(
            rayon::current_thread_index().is_none(),
            "tests run outside the pool"
        );
        let (outer, inner, sum) = on_pool(|| {
            let outer = std::thread::current().id();
            let inner = on_pool(|| std::thread::current().id());
            let sum: u64 = {
                use rayon::prelude::*;
                (0..1000u64).into_par_iter().sum()
            };
            ((outer, rayon::current_thread_index().is_some()), inner, sum)
        });
        assert!(outer.1, "on_pool ran its closure outside the pool");
        assert_eq!(outer.0, inner, "a nested on_pool moved to another thread");
        assert_eq!(sum, 499_500);
    }
}
