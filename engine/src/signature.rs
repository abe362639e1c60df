//! Domain signatures: what a set of images looks like in a dozen cheap statistics, so that an
//! image can be matched to the adaptation job whose images it resembles, label-free and without
//! running a model (issue 19's per-domain experts; `udapose-lab route` measures the rule,
//! `reports/route-probe.md`).
//!
//! Corruptions (blur, fog, noise, contrast) separate almost perfectly; domains that differ in
//! content rather than in image statistics (occlusion, textures, scenes) do not, so a signature
//! says where an image *may* belong; the share of a set's own images [`route`] sends back to it
//! says whether the set is distinct enough from the others for routing to be worth it.

use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

use crate::error::{EngineError, Result};

/// How many statistics an image is described by.
pub const STATS: usize = 13;

type Vector = SVector<f64, STATS>;
type Matrix = SMatrix<f64, STATS, STATS>;

/// Shrinkage of the covariance toward its diagonal: a few hundred images for 13 dimensions.
const SHRINK: f64 = 0.1;

/// The statistics of one crop (planar RGB in [0, 1], `[H, W]`), log-scaled: colour means and
/// spreads, gradient and Laplacian energy, the energy left after and taken by a 4×4 box blur
/// (what blur removes and noise adds), the dark channel (haze) and the saturation.
pub fn image_stats(pixels: &[f32], size: [usize; 2]) -> Result<[f64; STATS]> {
    let [h, w] = size;
    if h < 4 || w < 4 || pixels.len() != 3 * h * w {
        return Err(EngineError::InvalidInput(format!(
            "a signature needs a 3x{h}x{w} crop of at least 4x4 px, got {} values",
            pixels.len()
        )));
    }
    let plane = |c: usize| &pixels[c * h * w..(c + 1) * h * w];
    let (r, g, b) = (plane(0), plane(1), plane(2));
    let gray: Vec<f64> =
        (0..h * w).map(|i| 0.299 * f64::from(r[i]) + 0.587 * f64::from(g[i]) + 0.114 * f64::from(b[i])).collect();
    let at = |y: usize, x: usize| gray[y * w + x];
    let mut v = Vec::with_capacity(STATS);
    for c in [r, g, b] {
        v.push(mean(c.iter().map(|&p| f64::from(p))));
    }
    for c in [r, g, b] {
        v.push(std(c.iter().map(|&p| f64::from(p))));
    }
    v.push(mean((0..h).flat_map(|y| (1..w).map(move |x| (y, x))).map(|(y, x)| (at(y, x) - at(y, x - 1)).abs())));
    v.push(mean((1..h).flat_map(|y| (0..w).map(move |x| (y, x))).map(|(y, x)| (at(y, x) - at(y - 1, x)).abs())));
    let laplacian = (1..h - 1)
        .flat_map(|y| (1..w - 1).map(move |x| (y, x)))
        .map(|(y, x)| (4.0 * at(y, x) - at(y - 1, x) - at(y + 1, x) - at(y, x - 1) - at(y, x + 1)).abs());
    v.push(mean(laplacian));
    let (bh, bw) = (h / 4, w / 4);
    let block = |by: usize, bx: usize| (0..16).map(|k| at(4 * by + k / 4, 4 * bx + k % 4)).sum::<f64>() / 16.0;
    let low: Vec<f64> = (0..bh * bw).map(|i| block(i / bw, i % bw)).collect();
    let high =
        (0..bh * 4).flat_map(|y| (0..bw * 4).map(move |x| (y, x))).map(|(y, x)| at(y, x) - low[(y / 4) * bw + x / 4]);
    v.push(std(high));
    // The blurred image's spread over its pixels (each block counted 16 times, as upsampled).
    v.push(std(low.iter().copied()));
    let dark = (0..h * w).map(|i| r[i].min(g[i]).min(b[i]));
    v.push(mean(dark.map(f64::from)));
    let saturation = (0..h * w).map(|i| r[i].max(g[i]).max(b[i]) - r[i].min(g[i]).min(b[i]));
    v.push(mean(saturation.map(f64::from)));
    let mut out = [0.0; STATS];
    for (o, x) in out.iter_mut().zip(v) {
        *o = (x + 1e-4).ln();
    }
    Ok(out)
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n.max(1) as f64
}

/// Population standard deviation (NumPy's default), two passes' worth in one (Welford).
fn std(values: impl Iterator<Item = f64>) -> f64 {
    let (mut n, mut m, mut s) = (0.0, 0.0, 0.0);
    for v in values {
        n += 1.0;
        let d = v - m;
        m += d / n;
        s += d * (v - m);
    }
    if n > 0.0 { (s / n).sqrt() } else { 0.0 }
}

/// A Gaussian over [`image_stats`] fitted on a set of images.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Signature {
    pub mean: [f64; STATS],
    /// Row-major inverse of the shrunk covariance.
    pub precision: Vec<f64>,
    pub log_det: f64,
    pub images: usize,
}

impl Signature {
    /// Fits on the statistics of at least `STATS + 2` images (fewer leave the covariance
    /// singular even after shrinkage on some axes).
    pub fn fit(stats: &[[f64; STATS]]) -> Result<Signature> {
        let n = stats.len();
        if n < STATS + 2 {
            return Err(EngineError::InvalidInput(format!("a signature needs at least {} images, got {n}", STATS + 2)));
        }
        let xs: Vec<Vector> = stats.iter().map(|s| Vector::from_column_slice(s)).collect();
        let mean = xs.iter().sum::<Vector>() / n as f64;
        // Sample covariance (n − 1), as NumPy's np.cov.
        let cov = xs.iter().map(|x| (x - mean) * (x - mean).transpose()).sum::<Matrix>() / (n - 1) as f64;
        let cov = cov * (1.0 - SHRINK) + Matrix::from_diagonal(&cov.diagonal()) * SHRINK;
        let cholesky = cov.cholesky().ok_or_else(|| {
            EngineError::InvalidInput("the images' statistics are degenerate (identical images?)".into())
        })?;
        let log_det = 2.0 * cholesky.l().diagonal().iter().map(|d| d.ln()).sum::<f64>();
        let precision = cholesky.inverse();
        Ok(Signature {
            mean: mean.into(),
            precision: precision.transpose().iter().copied().collect(),
            log_det,
            images: n,
        })
    }

    /// Gaussian log-likelihood of one image's statistics, up to the constant every signature
    /// shares.
    pub fn log_likelihood(&self, stats: &[f64; STATS]) -> f64 {
        self.log_likelihood_at(self.distance2(stats))
    }

    fn log_likelihood_at(&self, distance2: f64) -> f64 {
        -0.5 * (distance2 + self.log_det)
    }

    /// Squared Mahalanobis distance of one image's statistics to the mean.
    pub fn distance2(&self, stats: &[f64; STATS]) -> f64 {
        let d = Vector::from_column_slice(stats) - Vector::from_column_slice(&self.mean);
        let precision = Matrix::from_row_slice(&self.precision);
        (d.transpose() * precision * d)[(0, 0)]
    }
}

/// The index of the signature most likely to have produced `stats` (the first on ties); `None`
/// for no signatures.
pub fn route(signatures: &[&Signature], stats: &[f64; STATS]) -> Option<usize> {
    most_likely(signatures.iter().map(|s| s.log_likelihood(stats)).enumerate())
}

/// A signature with an acceptance bound: an image belongs to the domain when its Mahalanobis
/// distance is within what a `coverage` share of *unseen* images of the domain reach. Unlike
/// [`route`], which always picks one of the signatures it is given, a domain can refuse an
/// image, so an expert needs no signature of the images it must *not* take (the service has no
/// source images: it is source-free).
///
/// A domain fitted on a wide variety of images (clear scenes) also takes some images of a
/// narrow one (fog) within its bound; a `rival`, fitted on images the domain must leave alone,
/// keeps those: an image the rival finds more likely is refused.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Domain {
    pub signature: Signature,
    /// The largest squared Mahalanobis distance taken.
    pub max_distance2: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rival: Option<Signature>,
}

/// Folds of the cross-fit that sets a domain's bound.
const FOLDS: usize = 5;

impl Domain {
    /// Fits the signature on `stats`; the bound is the `coverage` quantile of each image's
    /// distance to a signature fitted without its fold. In-sample distances would set it too
    /// tight: with 60 images in 13 dimensions a bound at 95% of the fitted images took about
    /// 80% of fresh ones (`engine/tests/signature.rs`).
    pub fn fit(stats: &[[f64; STATS]], coverage: f64) -> Result<Domain> {
        if !(coverage > 0.0 && coverage <= 1.0) {
            return Err(EngineError::InvalidInput(format!("coverage {coverage} is not in (0, 1]")));
        }
        let signature = Signature::fit(stats)?;
        let mut unseen = Vec::with_capacity(stats.len());
        for fold in 0..FOLDS {
            let rest: Vec<[f64; STATS]> =
                stats.iter().enumerate().filter(|(i, _)| i % FOLDS != fold).map(|(_, s)| *s).collect();
            let fitted = Signature::fit(&rest)?;
            unseen.extend(stats.iter().skip(fold).step_by(FOLDS).map(|s| fitted.distance2(s)));
        }
        unseen.sort_by(f64::total_cmp);
        let at = ((coverage * unseen.len() as f64).ceil() as usize).clamp(1, unseen.len()) - 1;
        Ok(Domain { signature, max_distance2: unseen[at], rival: None })
    }

    /// The image's log-likelihood when the domain takes it.
    pub fn accepts(&self, stats: &[f64; STATS]) -> Option<f64> {
        let d2 = self.signature.distance2(stats);
        if d2 > self.max_distance2 {
            return None;
        }
        let l = self.signature.log_likelihood_at(d2);
        match &self.rival {
            Some(rival) if rival.log_likelihood(stats) >= l => None,
            _ => Some(l),
        }
    }
}

/// The domain that takes `stats` with the highest likelihood (the first on ties); `None` when
/// none takes it.
pub fn pick(domains: &[&Domain], stats: &[f64; STATS]) -> Option<usize> {
    most_likely(domains.iter().enumerate().filter_map(|(i, d)| d.accepts(stats).map(|l| (i, l))))
}

/// The index with the highest log-likelihood (the first on ties).
fn most_likely(scores: impl Iterator<Item = (usize, f64)>) -> Option<usize> {
    scores
        .fold(None, |best: Option<(usize, f64)>, (i, l)| match best {
            Some((_, b)) if b >= l => best,
            _ => Some((i, l)),
        })
        .map(|(i, _)| i)
}
