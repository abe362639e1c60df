//! Blur corruptions: defocus, glass, motion, zoom and gaussian, following `imagecorruptions`
//! step by step (same kernels, borders, precision and final truncation to `u8`).

use image::RgbImage;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::kernels::{
    self, Border, Plane, clip_to_u8, cv_gaussian_blur, filter2d, from_planes, skimage_gaussian, to_planes, unit_to_u8,
};

fn severity_index(severity: u8) -> usize {
    usize::from(severity.clamp(1, 5) - 1)
}

/// `x / 255.` per channel, as the reference's `np.array(x) / 255.`.
fn unit_planes(image: &RgbImage) -> [Plane; 3] {
    to_planes(image, |v| v as f64 / 255.0)
}

/// Convolution with an anti-aliased disk (`cv2.filter2D`, `BORDER_REFLECT_101`).
pub fn defocus_blur(image: &RgbImage, severity: u8) -> RgbImage {
    let (radius, alias_blur) = [(3, 0.1), (4, 0.5), (6, 0.5), (8, 0.5), (10, 0.5)][severity_index(severity)];
    let kernel = disk(radius, alias_blur);
    let planes = unit_planes(image).map(|p| filter2d(&p, &kernel, Border::Mirror));
    from_planes(&planes, unit_to_u8)
}

/// The reference's `disk()`: a normalised binary disk, smoothed by a small `cv2.GaussianBlur`,
/// all in `float32`. Radii up to 8 sit in a 17×17 grid.
fn disk(radius: i64, alias_blur: f64) -> Plane {
    let (half, ksize) = if radius <= 8 { (8, 3) } else { (radius, 5) };
    let side = (2 * half + 1) as usize;
    let inside = |x: usize, y: usize| {
        let (dx, dy) = (x as i64 - half, y as i64 - half);
        dx * dx + dy * dy <= radius * radius
    };
    let count = (0..side * side).filter(|i| inside(i % side, i / side)).count() as f32;
    let aliased = Plane::from_fn(side, side, |x, y| if inside(x, y) { (1.0f32 / count) as f64 } else { 0.0 });
    cv_gaussian_blur(&aliased, ksize, alias_blur).map(|v| v as f32 as f64)
}

/// Gaussian blur, then local pixel shuffling, then blur again.
pub fn glass_blur(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    // sigma, max_delta, iterations
    let (sigma, delta, iterations) =
        [(0.7, 1, 2), (0.9, 2, 1), (1.0, 2, 3), (1.1, 3, 2), (1.5, 4, 2)][severity_index(severity)];
    // The first blur is stored as uint8 without clipping: `np.uint8(gaussian(x / 255.) * 255)`.
    let blurred = unit_planes(image).map(|p| skimage_gaussian(&p, sigma));
    let mut pixels = from_planes(&blurred, |v| (v * 255.0) as u8);
    shuffle_pixels(&mut pixels, delta, iterations, rng);
    let planes = unit_planes(&pixels).map(|p| skimage_gaussian(&p, sigma));
    from_planes(&planes, unit_to_u8)
}

/// The reference's `_shuffle_pixels_njit_glass_blur`. Its tuple "swap" of NumPy views
/// (`x[h, w], x[h', w'] = x[h', w'], x[h, w]`) only copies `x[h', w']` into `x[h, w]` (checked
/// against the numba original), so this copies too. Offsets are drawn in `[-delta, delta)`; the
/// loop bounds keep every source pixel inside the image.
fn shuffle_pixels(pixels: &mut RgbImage, delta: i64, iterations: usize, rng: &mut ChaCha8Rng) {
    let (w, h) = (i64::from(pixels.width()), i64::from(pixels.height()));
    for _ in 0..iterations {
        for y in (delta + 1..=h - delta).rev() {
            for x in (delta + 1..=w - delta).rev() {
                let dx = rng.random_range(-delta..delta);
                let dy = rng.random_range(-delta..delta);
                let src = *pixels.get_pixel((x + dx) as u32, (y + dy) as u32);
                pixels.put_pixel(x as u32, y as u32, src);
            }
        }
    }
}

/// A one-sided Gaussian streak in a random direction, angle uniform in [−45°, 45°).
pub fn motion_blur(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let (radius, sigma) = [(10, 3.0), (15, 5.0), (15, 8.0), (15, 12.0), (20, 15.0)][severity_index(severity)];
    let angle = rng.random_range(-45.0..45.0);
    // The reference blurs the 0–255 uint8 values directly and ends with np.clip(x, 0, 255).
    let planes = to_planes(image, f64::from).map(|p| kernels::motion_blur(&p, radius, sigma, angle));
    from_planes(&planes, clip_to_u8)
}

/// Average of the image and centre crops zoomed by factors `1, 1 + step, …` (in `float32`,
/// like the reference).
pub fn zoom_blur(image: &RgbImage, severity: u8) -> RgbImage {
    let s = severity_index(severity);
    // `np.arange(1, stop, step)` lengths for the reference's stops 1.11, 1.16, 1.21, 1.26, 1.31
    // (1.11 is included by rounding, hence 12 factors at severity 1).
    let (count, step) = [(12, 0.01), (16, 0.01), (11, 0.02), (13, 0.02), (11, 0.03)][s];
    // arange fills `start + i * (a[1] - a[0])`.
    let delta = (1.0 + step) - 1.0;
    let factors = (0..count).map(|i| 1.0 + i as f64 * delta);
    let x = to_planes(image, |v| (v as f64 / 255.0) as f32 as f64);
    let (w, h) = (x[0].width, x[0].height);
    let mut out: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0.0f32; w * h]);
    for factor in factors {
        for (plane, acc) in x.iter().zip(out.iter_mut()) {
            let layer = kernels::clipped_zoom(plane, factor);
            // A layer smaller than the image only adds to its top-left part (the reference's
            // ValueError fallback); a larger one is cropped to `[:h, :w]`.
            for yy in 0..h.min(layer.height) {
                for xx in 0..w.min(layer.width) {
                    acc[yy * w + xx] += layer.get(xx, yy) as f32;
                }
            }
        }
    }
    let n = (count + 1) as f32;
    let planes: [Plane; 3] = std::array::from_fn(|c| {
        Plane::from_fn(w, h, |xx, yy| {
            let i = yy * w + xx;
            ((x[c].data[i] as f32 + out[c][i]) / n) as f64
        })
    });
    // np.clip(x, 0, 1) * 255 stays float32 before the uint8 cast.
    from_planes(&planes, |v| ((v as f32).clamp(0.0, 1.0) * 255.0) as u8)
}

/// `skimage.filters.gaussian` with sigma 1–6 (`mode='nearest'`, `truncate=4`).
pub fn gaussian_blur(image: &RgbImage, severity: u8) -> RgbImage {
    let sigma = [1.0, 2.0, 3.0, 4.0, 6.0][severity_index(severity)];
    let planes = unit_planes(image).map(|p| skimage_gaussian(&p, sigma));
    from_planes(&planes, unit_to_u8)
}
