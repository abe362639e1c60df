//! Noise corruptions: gaussian, shot (Poisson), impulse (salt & pepper) and speckle, as in
//! `imagecorruptions`. Every channel of every pixel draws independently, like the reference's
//! NumPy draws over the whole `H×W×3` array.

use image::RgbImage;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson, StandardNormal};

use super::kernels::unit_to_u8;

/// Maps each sample `v / 255` to a new value in unit scale; the result is clipped and truncated
/// as the reference's `np.uint8(np.clip(x, 0, 1) * 255)`.
fn per_sample(image: &RgbImage, mut f: impl FnMut(f64) -> f64) -> RgbImage {
    let mut out = image.clone();
    for v in out.iter_mut() {
        *v = unit_to_u8(f(*v as f64 / 255.0));
    }
    out
}

fn severity_index(severity: u8) -> usize {
    usize::from(severity.clamp(1, 5) - 1)
}

/// `x + N(0, c²)`.
pub fn gaussian_noise(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let c = [0.08, 0.12, 0.18, 0.26, 0.38][severity_index(severity)];
    per_sample(image, |x| x + c * rng.sample::<f64, _>(StandardNormal))
}

/// `Poisson(x · c) / c`: fewer photons (smaller `c`) at higher severity.
pub fn shot_noise(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let c = [60.0, 25.0, 12.0, 5.0, 3.0][severity_index(severity)];
    // The rate depends only on the sample value: build the 256 distributions once. A zero rate
    // always draws 0 (rand_distr rejects λ = 0).
    let dists: Vec<Option<Poisson<f64>>> = (0..=255u8).map(|v| Poisson::new(v as f64 / 255.0 * c).ok()).collect();
    let mut out = image.clone();
    for v in out.iter_mut() {
        let count = dists[usize::from(*v)].as_ref().map_or(0.0, |d| d.sample(rng));
        *v = unit_to_u8(count / c);
    }
    out
}

/// Salt and pepper (`skimage.util.random_noise(mode='s&p')`): a fraction `c` of the samples is
/// replaced, half by 1 (salt), half by 0 (pepper).
pub fn impulse_noise(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let c = [0.03, 0.06, 0.09, 0.17, 0.27][severity_index(severity)];
    per_sample(image, |x| {
        // random_noise flips where `random() <= p` and salts where `random() <= 0.5`.
        let flipped = rng.random::<f64>() <= c;
        let salted = rng.random::<f64>() <= 0.5;
        match (flipped, salted) {
            (false, _) => x,
            (true, true) => 1.0,
            (true, false) => 0.0,
        }
    })
}

/// `x + x · N(0, c²)`: noise proportional to brightness.
pub fn speckle_noise(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let c = [0.15, 0.2, 0.35, 0.45, 0.6][severity_index(severity)];
    per_sample(image, |x| x + x * (c * rng.sample::<f64, _>(StandardNormal)))
}
