//! `S = C·F`, computed entry by entry when a pose evaluation first needs it.
//!
//! A solve reads few of the `P × R` entries: the 144 grid poses together cover 7.3% of the
//! (cell, vertex) pairs of `models/car` on its 16×40 grid, and refinement stays near three of
//! them. One dense GEMM computed all of them in 1.9 ms on one core, as much as the rest of
//! the solver; a 128-long dot product per entry actually read costs a fraction of that
//! (`reports/solver.md`). Entries are memoised in atomics so the hypotheses refined in parallel
//! share them: every thread that computes an entry computes the same value, so a race only
//! duplicates work, and the answer never depends on which thread came first.
//!
//! The memo is vertex-major (`v · P + p`): a face covers runs of neighbouring cells of a row,
//! so the entries a render reads in raster order share cache lines (pixel-major, each read was a
//! cache miss: half the refinement's time went to the loads). Its 674k entries are not
//! cleared per image either (initialising them was half the image's preparation): each entry
//! carries the number of the image that wrote it, and a memo goes back to a small pool when the
//! image is done, to serve the next image with the next number.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use super::dot::Kernels;

/// Memos kept for the next images (one per concurrent solve is all a server needs; more
/// concurrent solves allocate, and the surplus is freed when they finish).
const POOLED: usize = 4;

static POOL: Mutex<Vec<Memo>> = Mutex::new(Vec::new());

/// Memoised entries, each `epoch << 32 | value bits`: an entry whose epoch is not the memo's
/// current one is not computed for this image.
#[derive(Debug)]
struct Memo {
    entries: Box<[AtomicU64]>,
    epoch: u32,
}

impl Memo {
    /// A memo of `len` entries with an epoch no entry carries: from the pool when it has one
    /// of that size, zeroed memory (epoch 0 is never current) otherwise.
    fn take(len: usize) -> Memo {
        let pooled = POOL.lock().ok().and_then(|mut pool| {
            let i = pool.iter().position(|memo| memo.entries.len() == len)?;
            Some(pool.swap_remove(i))
        });
        match pooled {
            Some(memo) if memo.epoch < u32::MAX => Memo { epoch: memo.epoch + 1, ..memo },
            // After 4 billion images, start again from clean entries.
            _ => Memo { entries: (0..len).map(|_| AtomicU64::new(0)).collect(), epoch: 1 },
        }
    }

    fn give_back(self) {
        if let Ok(mut pool) = POOL.lock()
            && pool.len() < POOLED
        {
            pool.push(self);
        }
    }
}

#[derive(Debug)]
pub(super) struct Similarity<'a> {
    /// The image's features transposed to `P × D`, one pixel's vector contiguous.
    features: Vec<f32>,
    vertex_features: &'a [f32],
    dim: usize,
    pixels: usize,
    /// The memo's entries (empty only once dropped) and its epoch, shifted into place.
    entries: Box<[AtomicU64]>,
    tag: u64,
    kernels: Kernels,
}

impl Drop for Similarity<'_> {
    fn drop(&mut self) {
        let entries = std::mem::take(&mut self.entries);
        Memo { entries, epoch: (self.tag >> 32) as u32 }.give_back();
    }
}

impl<'a> Similarity<'a> {
    /// `features` is channel-major `D × P`; `vertex_features` is `R × D`.
    pub fn new(features: &[f32], pixels: usize, vertex_features: &'a [f32], dim: usize) -> Self {
        let vertices = vertex_features.len() / dim;
        let memo = Memo::take(pixels * vertices);
        Similarity {
            features: transpose(features, dim, pixels),
            vertex_features,
            dim,
            pixels,
            tag: u64::from(memo.epoch) << 32,
            entries: memo.entries,
            kernels: Kernels::detect(),
        }
    }

    #[inline]
    fn entry(&self, p: usize, v: usize) -> &AtomicU64 {
        &self.entries[v * self.pixels + p]
    }

    /// Memoises `S[v, p] = x`, computed elsewhere by the same dot product.
    pub fn remember(&self, p: usize, v: usize, x: f32) {
        self.entry(p, v).store(self.tag | u64::from(x.to_bits()), Ordering::Relaxed);
    }

    /// Pixel `p`'s feature vector.
    pub fn feature(&self, p: usize) -> &[f32] {
        &self.features[p * self.dim..(p + 1) * self.dim]
    }

    fn vertex(&self, v: usize) -> &[f32] {
        &self.vertex_features[v * self.dim..(v + 1) * self.dim]
    }

    /// `S[v, p] = C_v·F(p)`.
    #[inline]
    pub fn get(&self, p: usize, v: usize) -> f32 {
        let e = self.entry(p, v).load(Ordering::Relaxed);
        if e >> 32 == self.tag >> 32 {
            return f32::from_bits(e as u32);
        }
        let x = (self.kernels.dot)(self.feature(p), self.vertex(v));
        self.remember(p, v, x);
        x
    }

    /// `out[i] = S[vertices[i], cells[i]]`, not memoised; two at a time where neighbouring
    /// entries share their vertex (its feature is then loaded once per two cells). The values
    /// are bit for bit those [`Similarity::get`] computes.
    pub fn compute(&self, vertices: &[u32], cells: &[u32], out: &mut [f32]) {
        let mut i = 0;
        while i < out.len() {
            let (v, p) = (vertices[i] as usize, cells[i] as usize);
            if i + 1 < out.len() && vertices[i + 1] as usize == v {
                let q = cells[i + 1] as usize;
                [out[i], out[i + 1]] = (self.kernels.dot2)(self.feature(p), self.feature(q), self.vertex(v));
                i += 2;
            } else {
                out[i] = (self.kernels.dot)(self.feature(p), self.vertex(v));
                i += 1;
            }
        }
    }

    /// The dot product this machine uses (the same for every entry).
    pub fn dot(&self, a: &[f32], b: &[f32]) -> f32 {
        (self.kernels.dot)(a, b)
    }
}

/// Channel-major `D × P` to pixel-major `P × D`, a block of pixels at a time: one cache line
/// of each channel is read while the block's rows stay in L1 (a pixel at a time, every write
/// was to another line).
fn transpose(features: &[f32], dim: usize, pixels: usize) -> Vec<f32> {
    const BLOCK: usize = 16;
    let mut out = vec![0.0f32; pixels * dim];
    for p0 in (0..pixels).step_by(BLOCK) {
        let p1 = (p0 + BLOCK).min(pixels);
        for (d, channel) in features.chunks_exact(pixels).enumerate() {
            for (p, &x) in (p0..p1).zip(&channel[p0..p1]) {
                out[p * dim + d] = x;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Channel-major features `D × P` that differ with `seed`.
    fn features(dim: usize, pixels: usize, seed: f32) -> Vec<f32> {
        (0..dim * pixels).map(|i| (i as f32 * 0.37 + seed).sin()).collect()
    }

    /// A memo handed on to the next image (same size, so from the pool) answers that image's
    /// entries, never the last image's, whether an entry is computed, memoised or computed in
    /// a pair.
    #[test]
    fn a_pooled_memo_forgets_the_last_image() {
        let (dim, pixels, vertices) = (130, 37, 5);
        let vertex_features: Vec<f32> = (0..vertices * dim).map(|i| (i as f32 * 0.11).cos()).collect();
        let expected = |f: &[f32], p: usize, v: usize| {
            let pixel: Vec<f32> = (0..dim).map(|d| f[d * pixels + p]).collect();
            (Kernels::detect().dot)(&pixel, &vertex_features[v * dim..(v + 1) * dim])
        };
        for seed in [0.0, 1.0, 2.0] {
            let f = features(dim, pixels, seed);
            let s = Similarity::new(&f, pixels, &vertex_features, dim);
            for p in 0..pixels {
                for v in 0..vertices {
                    let x = expected(&f, p, v);
                    assert_eq!(s.get(p, v).to_bits(), x.to_bits(), "seed {seed}, pixel {p}, vertex {v}");
                    assert_eq!(s.get(p, v).to_bits(), x.to_bits(), "memoised: seed {seed}");
                }
            }
            let mut out = vec![0.0; 3];
            s.compute(&[1, 1, 4], &[0, 9, 36], &mut out);
            let pairs = [expected(&f, 0, 1), expected(&f, 9, 1), expected(&f, 36, 4)];
            assert_eq!(
                out.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                pairs.map(f32::to_bits),
                "computed: seed {seed}"
            );
        }
    }
}
