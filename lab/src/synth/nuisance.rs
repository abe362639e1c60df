//! The texture and weather nuisances.

use anyhow::Result;
use image::RgbImage;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::assets::mesh::Texture;
use crate::corruptions::Corruption;

/// The car's textures with the body's (the first) recoloured — hue turned and saturation
/// scaled — or replaced by a photograph.
pub fn retexture(textures: &[Texture], photos: &[RgbImage], rng: &mut ChaCha8Rng) -> Vec<Texture> {
    let mut out = textures.to_vec();
    if rng.random_bool(0.5) {
        let (turn, scale) = (rng.random_range(60.0..300.0), rng.random_range(0.3..1.5));
        out[0].texels.iter_mut().for_each(|t| *t = recolour(*t, turn, scale));
    } else {
        out[0] = Texture::from_image(&photos[rng.random_range(0..photos.len())]);
    }
    out
}

/// Turns the hue by `turn` degrees and scales the saturation, in HSV.
fn recolour([r, g, b]: [f32; 3], turn: f32, scale: f32) -> [f32; 3] {
    let max = r.max(g).max(b);
    let min = r.min(g).min(b);
    let chroma = max - min;
    if chroma <= 1e-6 {
        return [r, g, b];
    }
    let hue = 60.0
        * if max == r {
            ((g - b) / chroma).rem_euclid(6.0)
        } else if max == g {
            (b - r) / chroma + 2.0
        } else {
            (r - g) / chroma + 4.0
        };
    let saturation = (chroma / max * scale).min(1.0);
    hsv_to_rgb((hue + turn).rem_euclid(360.0), saturation, max)
}

fn hsv_to_rgb(h: f32, s: f32, v: f32) -> [f32; 3] {
    let c = v * s;
    let x = c * (1.0 - ((h / 60.0).rem_euclid(2.0) - 1.0).abs());
    let (r, g, b) = match (h / 60.0) as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// One of fog, snow, frost (the reference corruptions at severity 2–4), rain streaks or dusk.
pub fn weather(image: &RgbImage, rng: &mut ChaCha8Rng) -> Result<RgbImage> {
    Ok(match rng.random_range(0..5) {
        0 => Corruption::Fog.apply(image, rng.random_range(2..=4), rng)?,
        1 => Corruption::Snow.apply(image, rng.random_range(2..=4), rng)?,
        2 => Corruption::Frost.apply(image, rng.random_range(2..=4), rng)?,
        3 => rain(image, rng),
        _ => dusk(image, rng),
    })
}

/// Slanted light streaks over a slightly darkened image.
fn rain(image: &RgbImage, rng: &mut ChaCha8Rng) -> RgbImage {
    let (w, h) = (image.width() as f64, image.height() as f64);
    let mut out = image.clone();
    out.pixels_mut().for_each(|p| p.0 = p.0.map(|c| (c as f32 * 0.8) as u8));
    let slant = rng.random_range(-0.3..0.3);
    let streaks = (w * h / 40.0) as usize;
    for _ in 0..streaks {
        let (x0, y0) = (rng.random_range(0.0..w), rng.random_range(0.0..h));
        let length = rng.random_range(h / 12.0..h / 5.0);
        let alpha = rng.random_range(0.15..0.4);
        for s in 0..length as usize {
            let (x, y) = (x0 + slant * s as f64, y0 + s as f64);
            if x >= 0.0 && x < w && y < h {
                let p = out.get_pixel_mut(x as u32, y as u32);
                p.0 = p.0.map(|c| (c as f64 * (1.0 - alpha) + 220.0 * alpha) as u8);
            }
        }
    }
    out
}

/// Low, warm evening light.
fn dusk(image: &RgbImage, rng: &mut ChaCha8Rng) -> RgbImage {
    let level = rng.random_range(0.3..0.55f32);
    let tint = [1.05, 0.88, 0.72];
    let mut out = image.clone();
    out.pixels_mut()
        .for_each(|p| p.0 = std::array::from_fn(|k| (p.0[k] as f32 * level * tint[k]).round().clamp(0.0, 255.0) as u8));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recolour_turns_hue_and_keeps_grey() {
        let red = [0.8, 0.1, 0.1];
        let turned = recolour(red, 120.0, 1.0);
        assert!(turned[1] > 0.7 && turned[0] < 0.2, "red turned by 120° is green: {turned:?}");
        assert_eq!(recolour([0.4; 3], 90.0, 1.4), [0.4; 3]);
    }
}
