//! `S = C·F`, computed entry by entry when a pose evaluation first needs it.
//!
//! A solve reads few of the `P × R` entries: the 144 grid poses together cover 7.3% of the
//! (cell, vertex) pairs of `models/car` on its 16×40 grid, and refinement stays near three of
//! them. One dense GEMM computed all of them in 1.9 ms on one core, as much as the rest of
//! the solver; a 128-long dot product per entry actually read costs a fraction of that
//! (`reports/solver.md`). Entries are memoised in atomics so the hypotheses refined in parallel
//! share them: every thread that computes an entry computes the same value, so a race only
//! duplicates work, and the answer never depends on which thread came first.

use std::sync::atomic::{AtomicU32, Ordering};

/// An entry not computed yet (a dot product of finite unit vectors is never NaN).
const PENDING: u32 = f32::NAN.to_bits();

/// Two dot products with a shared second vector.
type Dot2 = fn(&[f32], &[f32], &[f32]) -> [f32; 2];

#[derive(Debug)]
pub(super) struct Similarity<'a> {
    /// The image's features transposed to `P × D`, one pixel's vector contiguous.
    features: Vec<f32>,
    vertex_features: &'a [f32],
    dim: usize,
    vertices: usize,
    values: Vec<AtomicU32>,
    dot: fn(&[f32], &[f32]) -> f32,
    /// Two of `dot` sharing their second vector.
    dot2: Dot2,
}

impl<'a> Similarity<'a> {
    /// `features` is channel-major `D × P`; `vertex_features` is `R × D`.
    pub fn new(features: &[f32], pixels: usize, vertex_features: &'a [f32], dim: usize) -> Self {
        let mut transposed = vec![0.0f32; pixels * dim];
        for (d, channel) in features.chunks_exact(pixels).enumerate() {
            for (p, &x) in channel.iter().enumerate() {
                transposed[p * dim + d] = x;
            }
        }
        let vertices = vertex_features.len() / dim;
        Similarity {
            features: transposed,
            vertex_features,
            dim,
            vertices,
            values: (0..pixels * vertices).map(|_| AtomicU32::new(PENDING)).collect(),
            dot: dot_fn(),
            dot2: dot2_fn(),
        }
    }

    /// Pixel `p`'s feature vector.
    pub fn feature(&self, p: usize) -> &[f32] {
        &self.features[p * self.dim..(p + 1) * self.dim]
    }

    /// `S[v, p] = C_v·F(p)`.
    #[inline]
    pub fn get(&self, p: usize, v: usize) -> f32 {
        let cell = &self.values[p * self.vertices + v];
        let x = f32::from_bits(cell.load(Ordering::Relaxed));
        if !x.is_nan() {
            return x;
        }
        let x = (self.dot)(self.feature(p), &self.vertex_features[v * self.dim..(v + 1) * self.dim]);
        cell.store(x.to_bits(), Ordering::Relaxed);
        x
    }

    /// Computes `S[v, p]` for every cell `p` of `cells` (a vertex's cells, in one go: the
    /// vertex's feature is loaded once per two cells). The values are bit for bit those
    /// [`Similarity::get`] computes.
    pub fn fill(&self, v: usize, cells: &[u32]) {
        let c = &self.vertex_features[v * self.dim..(v + 1) * self.dim];
        let store = |p: u32, x: f32| self.values[p as usize * self.vertices + v].store(x.to_bits(), Ordering::Relaxed);
        let pairs = cells.chunks_exact(2);
        if let [p] = pairs.remainder() {
            store(*p, (self.dot)(self.feature(*p as usize), c));
        }
        for pair in pairs {
            let [x, y] = (self.dot2)(self.feature(pair[0] as usize), self.feature(pair[1] as usize), c);
            store(pair[0], x);
            store(pair[1], y);
        }
    }

    /// The dot product this machine uses (the same for every entry).
    pub fn dot(&self, a: &[f32], b: &[f32]) -> f32 {
        (self.dot)(a, b)
    }
}

/// Partial sums in eight lanes, added in a fixed order: the result is a fixed function of the
/// inputs on a given machine.
fn dot_portable(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        acc[i % 8] += x * y;
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// Four independent 8-wide FMA chains (one chain made a 128-long dot product latency-bound,
/// and the compiler's own vectorisation of lane arrays used 2-wide loads), then the portable
/// form for a tail shorter than 32.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dot_avx2_fma(a: &[f32], b: &[f32]) -> f32 {
    use std::arch::x86_64::*;
    let n = a.len().min(b.len());
    let body = n - n % 32;
    let mut acc = [_mm256_setzero_ps(); 4];
    let mut i = 0;
    while i < body {
        for (k, acc) in acc.iter_mut().enumerate() {
            // SAFETY: i + 8k + 8 <= body <= both lengths.
            let (x, y) =
                unsafe { (_mm256_loadu_ps(a.as_ptr().add(i + 8 * k)), _mm256_loadu_ps(b.as_ptr().add(i + 8 * k))) };
            *acc = _mm256_fmadd_ps(x, y, *acc);
        }
        i += 32;
    }
    let sum = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
    let mut lanes = [0.0f32; 8];
    // SAFETY: lanes holds 8 floats.
    unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), sum) };
    let head = ((lanes[0] + lanes[4]) + (lanes[1] + lanes[5])) + ((lanes[2] + lanes[6]) + (lanes[3] + lanes[7]));
    head + dot_portable(&a[body..n], &b[body..n])
}

fn dot2_portable(a0: &[f32], a1: &[f32], b: &[f32]) -> [f32; 2] {
    [dot_portable(a0, b), dot_portable(a1, b)]
}

/// [`dot_avx2_fma`] of `a0` and of `a1` with `b`, the same operations per pair in the same
/// order (so the same bits), with `b`'s loads shared.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dot2_avx2_fma(a0: &[f32], a1: &[f32], b: &[f32]) -> [f32; 2] {
    use std::arch::x86_64::*;
    let n = a0.len().min(a1.len()).min(b.len());
    if n != a0.len() || n != a1.len() {
        return [dot_avx2_fma(a0, b), dot_avx2_fma(a1, b)];
    }
    let body = n - n % 32;
    let mut acc0 = [_mm256_setzero_ps(); 4];
    let mut acc1 = [_mm256_setzero_ps(); 4];
    let mut i = 0;
    while i < body {
        for k in 0..4 {
            // SAFETY: i + 8k + 8 <= body <= every length.
            let (x0, x1, y) = unsafe {
                (
                    _mm256_loadu_ps(a0.as_ptr().add(i + 8 * k)),
                    _mm256_loadu_ps(a1.as_ptr().add(i + 8 * k)),
                    _mm256_loadu_ps(b.as_ptr().add(i + 8 * k)),
                )
            };
            acc0[k] = _mm256_fmadd_ps(x0, y, acc0[k]);
            acc1[k] = _mm256_fmadd_ps(x1, y, acc1[k]);
        }
        i += 32;
    }
    let finish = |acc: [__m256; 4], a: &[f32]| {
        let sum = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
        let mut lanes = [0.0f32; 8];
        // SAFETY: lanes holds 8 floats.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), sum) };
        let head = ((lanes[0] + lanes[4]) + (lanes[1] + lanes[5])) + ((lanes[2] + lanes[6]) + (lanes[3] + lanes[7]));
        head + dot_portable(&a[body..n], &b[body..n])
    };
    [finish(acc0, a0), finish(acc1, a1)]
}

fn dot2_fn() -> Dot2 {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
        // SAFETY: the features the function is compiled for were just detected.
        return |a0, a1, b| unsafe { dot2_avx2_fma(a0, a1, b) };
    }
    dot2_portable
}

/// AVX2 + FMA where the CPU has them (detected once per problem), portable otherwise.
fn dot_fn() -> fn(&[f32], &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
        // SAFETY: the features the function is compiled for were just detected.
        return |a, b| unsafe { dot_avx2_fma(a, b) };
    }
    dot_portable
}
