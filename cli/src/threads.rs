//! The thread count a user asks for covers the BVH builds too.
//!
//! BVHs are built on rayon's global pool (the two sides of each cut near the top of the
//! tree in parallel), outside any render pool. Left alone, that pool takes every core,
//! so `--threads 1` would still build on all of them: a run would not use what it was
//! given, and a one-thread benchmark would not be one.

/// Size rayon's global pool to `threads` (0: leave it at one thread per core). Call
/// before anything uses the pool; a pool already running keeps its size.
pub fn limit_build_threads(threads: usize) {
    if threads == 0 {
        return;
    }
    if let Err(e) = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("dray-build-{i}"))
        .build_global()
    {
        tracing::debug!("the build pool was already running: {e}");
    }
}
