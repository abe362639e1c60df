//! How many threads each kind of work gets: libtorch's count per thread, and the inference
//! workers' solver pools.
//!
//! OpenMP keeps its thread count per thread, and libtorch gives a thread its count lazily, from
//! the process-wide value, the first time that thread runs a parallel operator; oneDNN's batched
//! convolutions read the calling thread's count. So a count set in `main` did not reach the
//! workers' convolutions (each ran an OpenMP team over every core), and a count set in a thread
//! before its lazy initialisation was overwritten by whatever process-wide value another thread
//! had set since. [`pin_torch_threads`] runs the initialisation first, then sets the count.

/// Gives the calling thread `n` libtorch threads (at least 1), for the rest of its life.
pub fn pin_torch_threads(n: usize) {
    let _ = tch::get_num_threads(); // libtorch's lazy per-thread initialisation, now
    tch::set_num_threads(n.max(1) as i32);
}

/// The solver pool of one inference worker: `None` (the global pool, every core) for a
/// category's only worker; with several, each gets its share of the cores, so that one worker's
/// solves never queue behind, or spin against, another's backbone pass.
pub fn solver_pool(workers: usize, name: &str) -> Option<rayon::ThreadPool> {
    if workers <= 1 {
        return None;
    }
    let cores = udapose_engine::runtime::cores();
    let prefix = name.to_owned();
    rayon::ThreadPoolBuilder::new()
        .num_threads((cores / workers).max(1))
        .thread_name(move |i| format!("{prefix}-solve-{i}"))
        .build()
        .inspect_err(|e| tracing::warn!("no solver pool of its own for {name} ({e}): the global pool serves"))
        .ok()
}
