//! Timing shared by the engine's benchmarks (a module, not a bench target).

use std::time::Instant;

/// Median and spread `(median, min, max)` of the time per call (µs) over 15 batches, each long
/// enough to time, after 0.2 s of warm-up.
pub fn time(mut call: impl FnMut(usize)) -> (f64, f64, f64) {
    let start = Instant::now();
    let mut warm = 0;
    while start.elapsed().as_secs_f64() < 0.2 {
        call(warm);
        warm += 1;
    }
    let per_batch = (warm / 4).max(1);
    let mut batches: Vec<f64> = (0..15)
        .map(|b| {
            let t = Instant::now();
            (0..per_batch).for_each(|i| call(b * per_batch + i));
            t.elapsed().as_secs_f64() * 1e6 / per_batch as f64
        })
        .collect();
    batches.sort_by(f64::total_cmp);
    (batches[7], batches[0], batches[14])
}
