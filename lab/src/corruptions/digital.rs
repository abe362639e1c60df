//! Digital corruptions: brightness, contrast, saturate, elastic_transform, pixelate and
//! jpeg_compression, ported operation by operation from `imagecorruptions` 1.1.5.
//!
//! The reference ends every corruption with `np.uint8(np.clip(x, 0, 1) * 255)`, which truncates;
//! `unit_to_u8` does the same, so the deterministic ones agree pixel for pixel.

use image::{Rgb, RgbImage};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::kernels::{Border, Plane, from_planes, gaussian_filter, sample_bilinear, to_planes, unit_to_u8};

mod jpeg;

const fn level(severity: u8) -> usize {
    severity as usize - 1
}

/// Applies `f` to every pixel as floats in [0, 1] (`np.array(x) / 255.`).
fn map_pixels(image: &RgbImage, f: impl Fn([f64; 3]) -> [f64; 3]) -> RgbImage {
    let mut out = image.clone();
    for p in out.pixels_mut() {
        let v = f(p.0.map(|c| f64::from(c) / 255.0));
        *p = Rgb(v.map(unit_to_u8));
    }
    out
}

/// skimage.color.rgb2hsv for one pixel, with its tie order (blue beats green beats red).
fn rgb2hsv([r, g, b]: [f64; 3]) -> [f64; 3] {
    let v = r.max(g).max(b);
    let delta = v - r.min(g).min(b);
    if delta == 0.0 {
        return [0.0, 0.0, v];
    }
    let s = delta / v;
    let h = if b == v {
        4.0 + (r - g) / delta
    } else if g == v {
        2.0 + (b - r) / delta
    } else {
        (g - b) / delta
    };
    // Python's float `%` takes the divisor's sign, as rem_euclid does for a positive divisor.
    [(h / 6.0).rem_euclid(1.0), s, v]
}

/// skimage.color.hsv2rgb for one pixel.
fn hsv2rgb([h, s, v]: [f64; 3]) -> [f64; 3] {
    let hi = (h * 6.0).floor();
    let f = h * 6.0 - hi;
    let p = v * (1.0 - s);
    let q = v * (1.0 - f * s);
    let t = v * (1.0 - (1.0 - f) * s);
    // skimage casts to uint8 before `% 6`; hue is in [0, 1] so `hi` is 0..=6.
    match (hi as u8) % 6 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

pub fn brightness(image: &RgbImage, severity: u8) -> RgbImage {
    let c = [0.1, 0.2, 0.3, 0.4, 0.5][level(severity)];
    map_pixels(image, |rgb| {
        let [h, s, v] = rgb2hsv(rgb);
        hsv2rgb([h, s, (v + c).clamp(0.0, 1.0)])
    })
}

pub fn contrast(image: &RgbImage, severity: u8) -> RgbImage {
    let c = [0.4, 0.3, 0.2, 0.1, 0.05][level(severity)];
    let means = channel_means(image);
    map_pixels(image, |rgb| std::array::from_fn(|k| (rgb[k] - means[k]) * c + means[k]))
}

/// Per-channel mean of `x / 255.`, summed with Kahan compensation so it lands where numpy's
/// pairwise sum does (the truncation to uint8 makes the last bits matter on rare pixels).
fn channel_means(image: &RgbImage) -> [f64; 3] {
    let mut sum = [0.0f64; 3];
    let mut comp = [0.0f64; 3];
    for p in image.pixels() {
        for k in 0..3 {
            let y = f64::from(p[k]) / 255.0 - comp[k];
            let t = sum[k] + y;
            comp[k] = (t - sum[k]) - y;
            sum[k] = t;
        }
    }
    let n = f64::from(image.width()) * f64::from(image.height());
    sum.map(|s| s / n)
}

pub fn saturate(image: &RgbImage, severity: u8) -> RgbImage {
    let (scale, shift) = [(0.3, 0.0), (0.1, 0.0), (2.0, 0.0), (5.0, 0.1), (20.0, 0.2)][level(severity)];
    map_pixels(image, |rgb| {
        let [h, s, v] = rgb2hsv(rgb);
        hsv2rgb([h, (s * scale + shift).clamp(0.0, 1.0), v])
    })
}

/// One displacement field: uniform noise in ±`max_d`, blurred with a per-axis sigma
/// (1% of each side, `mode='reflect', truncate=3`), scaled by `alpha`, stored as float32.
fn displacement(w: usize, h: usize, max_d: f64, alpha: f64, rng: &mut ChaCha8Rng) -> Plane {
    let noise = Plane::from_fn(w, h, |_, _| -max_d + 2.0 * max_d * rng.random::<f64>());
    let sigma = (h as f64 * 0.01, w as f64 * 0.01);
    gaussian_filter(&noise, sigma, 3.0, Border::Reflect).map(|v| f64::from((v * alpha) as f32))
}

/// The reference's elastic_transform. This fork has no affine step (the original ImageNet-C one
/// had): every pixel is resampled at itself plus a smooth random displacement, by
/// `map_coordinates(order=1, mode='reflect')` on the float32 image.
pub fn elastic_transform(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let alpha = 250.0 * [0.05, 0.065, 0.085, 0.1, 0.12][level(severity)];
    // Both maxima scale with the height (`shape[0]`), as in the reference.
    let max_d = h as f64 * 0.005;
    let dx = displacement(w, h, max_d, alpha, rng);
    let dy = displacement(w, h, max_d, alpha, rng);
    let planes = to_planes(image, |v| f64::from(f32::from(v) / 255.0));
    let warped = planes.map(|p| {
        Plane::from_fn(w, h, |x, y| {
            let (sx, sy) = (x as f64 + dx.get(x, y), y as f64 + dy.get(x, y));
            // Reading the taps through the reflect border equals SciPy's folding of the coordinate
            // for mode='reflect' (the half-sample mirror maps the sample grid onto itself).
            // SciPy writes into a float32 output; the clip and ×255 happen in float32 too.
            f64::from((sample_bilinear(&p, sx, sy, Border::Reflect) as f32).clamp(0.0, 1.0) * 255.0)
        })
    });
    from_planes(&warped, |v| v as u8)
}

/// Fractional bits of Pillow's 8-bit resampling weights (`PRECISION_BITS`).
const PRECISION: u32 = 22;

/// Pillow's `precompute_coeffs` for the BOX filter, in its 22-bit fixed point: for each output
/// index, the first input index and the weights of the inputs it averages.
fn box_coeffs(in_size: usize, out_size: usize) -> Vec<(usize, Vec<i64>)> {
    let scale = in_size as f64 / out_size as f64;
    let filter_scale = scale.max(1.0);
    let support = 0.5 * filter_scale;
    (0..out_size)
        .map(|xx| {
            let center = (xx as f64 + 0.5) * scale;
            let xmin = ((center - support + 0.5) as isize).max(0) as usize;
            let xmax = ((center + support + 0.5) as usize).min(in_size);
            let raw: Vec<f64> = (xmin..xmax)
                .map(|x| {
                    let t = (x as f64 - center + 0.5) / filter_scale;
                    if t > -0.5 && t <= 0.5 { 1.0 } else { 0.0 }
                })
                .collect();
            let total: f64 = raw.iter().sum();
            let fixed = raw
                .iter()
                .map(|&k| {
                    let k = if total != 0.0 { k / total } else { k };
                    (0.5 + k * f64::from(1u32 << PRECISION)) as i64
                })
                .collect();
            (xmin, fixed)
        })
        .collect()
}

/// Pillow's 8-bit fixed-point accumulation: round, shift, clip.
fn fixed_to_u8(acc: i64) -> u8 {
    ((acc + (1 << (PRECISION - 1))) >> PRECISION).clamp(0, 255) as u8
}

/// `Image.resize(size, Image.BOX)`: a horizontal pass then a vertical one, each rounding to u8.
fn resize_box(image: &RgbImage, w: u32, h: u32) -> RgbImage {
    let horiz = box_coeffs(image.width() as usize, w as usize);
    let vert = box_coeffs(image.height() as usize, h as usize);
    let tmp = RgbImage::from_fn(w, image.height(), |x, y| {
        let (x0, k) = &horiz[x as usize];
        Rgb(std::array::from_fn(|c| {
            let acc = k.iter().enumerate().map(|(i, &k)| i64::from(image.get_pixel((x0 + i) as u32, y)[c]) * k);
            fixed_to_u8(acc.sum())
        }))
    });
    RgbImage::from_fn(w, h, |x, y| {
        let (y0, k) = &vert[y as usize];
        Rgb(std::array::from_fn(|c| {
            let acc = k.iter().enumerate().map(|(i, &k)| i64::from(tmp.get_pixel(x, (y0 + i) as u32)[c]) * k);
            fixed_to_u8(acc.sum())
        }))
    })
}

/// Source indices of Pillow's NEAREST resize (ImagingScaleAffine): it steps a double by the
/// scale from half a step in, so the rounding of the running sum is reproduced as is.
fn nearest_indices(in_size: u32, out_size: u32) -> Vec<u32> {
    let step = f64::from(in_size) / f64::from(out_size);
    let mut pos = step * 0.5;
    (0..out_size)
        .map(|_| {
            let i = (pos as u32).min(in_size - 1);
            pos += step;
            i
        })
        .collect()
}

pub fn pixelate(image: &RgbImage, severity: u8) -> RgbImage {
    let c = [0.6, 0.5, 0.4, 0.3, 0.25][level(severity)];
    let (w, h) = image.dimensions();
    // `int(w * c)` as Python computes it; at least 1 so tiny images stay valid.
    let small = resize_box(image, ((f64::from(w) * c) as u32).max(1), ((f64::from(h) * c) as u32).max(1));
    let xs = nearest_indices(small.width(), w);
    let ys = nearest_indices(small.height(), h);
    RgbImage::from_fn(w, h, |x, y| *small.get_pixel(xs[x as usize], ys[y as usize]))
}

/// JPEG at the reference's quality, as Pillow (libjpeg-turbo) does it: 4:2:0 chroma, the
/// integer ("islow") DCT, fancy upsampling on decode. See `jpeg` for why this is not a call
/// into an encoder.
pub fn jpeg_compression(image: &RgbImage, severity: u8) -> RgbImage {
    let quality = [25, 18, 15, 10, 7][level(severity)];
    jpeg::round_trip(image, quality)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hsv_round_trip_is_identity() {
        for rgb in [[0.2, 0.4, 0.6], [1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.9, 0.1, 0.9]] {
            let back = hsv2rgb(rgb2hsv(rgb));
            for k in 0..3 {
                assert!((back[k] - rgb[k]).abs() < 1e-12, "{rgb:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn box_downscale_by_two_averages_pairs() {
        let k = box_coeffs(4, 2);
        assert_eq!(k[0].0, 0);
        assert_eq!(k[1].0, 2);
        assert_eq!(k[0].1, vec![1 << 21, 1 << 21]);
    }
}
