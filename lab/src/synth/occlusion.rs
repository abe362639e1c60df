//! Occluders: textured shapes and patches of other photographs, added until the measured share
//! of the object mask they cover falls inside the level's band.

use anyhow::{Result, bail};
use image::RgbImage;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::assets::backgrounds::random_crop;

const MAX_TRIES: usize = 2000;
/// Rejections in a row after which a fraction already inside the band is accepted: near the
/// top of the band no occluder is small enough to reach a target just below it.
const STALL: usize = 50;

/// What the occluders did: the covered fraction of the object mask, in `[band.0, band.1]`, and
/// every pixel they cover (1), object or not.
pub struct Occlusion {
    pub fraction: f64,
    pub covered: Vec<u8>,
}

/// Paints occluders over `image`, covering a fraction of `mask` within `band`.
pub fn occlude(
    image: &mut RgbImage,
    mask: &[u8],
    band: (f64, f64),
    photos: &[RgbImage],
    rng: &mut ChaCha8Rng,
) -> Result<Occlusion> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let area = mask.iter().filter(|&&m| m != 0).count();
    let Some(bbox) = bounding_box(mask, w) else { bail!("no object pixels to occlude") };
    let target = rng.random_range(band.0..band.1);
    let mut covered = vec![false; w * h];
    let mut hits = 0usize;
    let mut scale = 0.6;
    let mut rejected = 0;
    for _ in 0..MAX_TRIES {
        let shape = Shape::random(bbox, scale, rng);
        let pixels: Vec<usize> = shape.pixels(w, h).filter(|&p| !covered[p]).collect();
        let new_hits = pixels.iter().filter(|&&p| mask[p] != 0).count();
        if (hits + new_hits) as f64 > band.1 * area as f64 {
            scale = (scale * 0.9).max(0.05); // too big for what is left of the band
            rejected += 1;
            if rejected >= STALL && hits as f64 >= band.0 * area as f64 {
                return Ok(Occlusion::of(hits, area, &covered));
            }
            continue;
        }
        if new_hits > 0 {
            rejected = 0;
        }
        paint(image, &shape, &pixels, photos, rng);
        pixels.iter().for_each(|&p| covered[p] = true);
        hits += new_hits;
        if hits as f64 >= target * area as f64 {
            return Ok(Occlusion::of(hits, area, &covered));
        }
    }
    bail!("could not place occluders covering {:.0}–{:.0}% of the object", band.0 * 100.0, band.1 * 100.0)
}

impl Occlusion {
    fn of(hits: usize, area: usize, covered: &[bool]) -> Occlusion {
        Occlusion { fraction: hits as f64 / area as f64, covered: covered.iter().map(|&c| u8::from(c)).collect() }
    }
}

/// `(x0, y0, x1, y1)` of the non-zero pixels, exclusive ends.
fn bounding_box(mask: &[u8], w: usize) -> Option<(usize, usize, usize, usize)> {
    let mut b: Option<(usize, usize, usize, usize)> = None;
    for (i, _) in mask.iter().enumerate().filter(|(_, m)| **m != 0) {
        let (x, y) = (i % w, i / w);
        b = Some(match b {
            None => (x, y, x + 1, y + 1),
            Some((x0, y0, x1, y1)) => (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1)),
        });
    }
    b
}

enum Kind {
    Ellipse,
    Rectangle,
    Triangle([[f64; 2]; 3]),
}

struct Shape {
    kind: Kind,
    centre: [f64; 2],
    half: [f64; 2],
}

impl Shape {
    /// A shape centred inside the object's box, its size `scale` of the box (± half).
    fn random((x0, y0, x1, y1): (usize, usize, usize, usize), scale: f64, rng: &mut ChaCha8Rng) -> Shape {
        let (bw, bh) = ((x1 - x0) as f64, (y1 - y0) as f64);
        let centre = [rng.random_range(x0 as f64..x1 as f64), rng.random_range(y0 as f64..y1 as f64)];
        let half = [bw * scale * rng.random_range(0.5..1.5) / 2.0, bh * scale * rng.random_range(0.5..1.5) / 2.0];
        let kind = match rng.random_range(0..3) {
            0 => Kind::Ellipse,
            1 => Kind::Rectangle,
            _ => Kind::Triangle(std::array::from_fn(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])),
        };
        Shape { kind, centre, half }
    }

    fn contains(&self, x: f64, y: f64) -> bool {
        let u = (x - self.centre[0]) / self.half[0].max(0.5);
        let v = (y - self.centre[1]) / self.half[1].max(0.5);
        match &self.kind {
            Kind::Ellipse => u * u + v * v <= 1.0,
            Kind::Rectangle => u.abs() <= 1.0 && v.abs() <= 1.0,
            Kind::Triangle([a, b, c]) => {
                let side = |p: [f64; 2], q: [f64; 2]| (q[0] - p[0]) * (v - p[1]) - (q[1] - p[1]) * (u - p[0]);
                let s = [side(*a, *b), side(*b, *c), side(*c, *a)];
                s.iter().all(|&d| d >= 0.0) || s.iter().all(|&d| d <= 0.0)
            }
        }
    }

    /// Indices of the pixels whose centres the shape contains.
    fn pixels(&self, w: usize, h: usize) -> impl Iterator<Item = usize> + '_ {
        let span =
            |c: f64, r: f64, n: usize| ((c - r).floor().max(0.0) as usize, ((c + r).ceil().max(0.0) as usize).min(n));
        let (xs, ys) = (span(self.centre[0], self.half[0], w), span(self.centre[1], self.half[1], h));
        (ys.0..ys.1)
            .flat_map(move |y| (xs.0..xs.1).map(move |x| (x, y)))
            .filter(|&(x, y)| self.contains(x as f64 + 0.5, y as f64 + 0.5))
            .map(move |(x, y)| y * w + x)
    }
}

/// Fills the pixels with a patch of a photograph, or a flat colour with a little noise.
fn paint(image: &mut RgbImage, shape: &Shape, pixels: &[usize], photos: &[RgbImage], rng: &mut ChaCha8Rng) {
    let w = image.width() as usize;
    let (pw, ph) = ((2.0 * shape.half[0]).ceil().max(1.0) as u32, (2.0 * shape.half[1]).ceil().max(1.0) as u32);
    let origin = [shape.centre[0] - shape.half[0], shape.centre[1] - shape.half[1]];
    if rng.random_bool(0.6) {
        let patch = random_crop(&photos[rng.random_range(0..photos.len())], pw, ph, rng);
        for &p in pixels {
            let (x, y) = ((p % w) as f64 - origin[0], (p / w) as f64 - origin[1]);
            let (px, py) = ((x.max(0.0) as u32).min(pw - 1), (y.max(0.0) as u32).min(ph - 1));
            image.put_pixel((p % w) as u32, (p / w) as u32, *patch.get_pixel(px, py));
        }
    } else {
        let base: [f64; 3] = std::array::from_fn(|_| rng.random_range(0.0..255.0));
        for &p in pixels {
            let noise = rng.random_range(-12.0..12.0);
            let c = base.map(|b| (b + noise).clamp(0.0, 255.0) as u8);
            image.put_pixel((p % w) as u32, (p / w) as u32, image::Rgb(c));
        }
    }
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;

    use super::*;

    #[test]
    fn covered_fraction_lands_in_every_band() {
        let (w, h) = (160usize, 64usize);
        // An object ellipse in the middle of the crop.
        let mask: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64 - 80.0, (i / w) as f64 - 32.0);
                u8::from((x / 60.0).powi(2) + (y / 20.0).powi(2) <= 1.0)
            })
            .collect();
        let photo = RgbImage::from_fn(300, 300, |x, y| image::Rgb([x as u8, y as u8, 90]));
        for (k, band) in [(0.2, 0.4), (0.4, 0.6), (0.6, 0.8)].into_iter().enumerate() {
            for seed in 0..20 {
                let mut rng = ChaCha8Rng::seed_from_u64(seed * 10 + k as u64);
                let mut img = RgbImage::new(w as u32, h as u32);
                let o = occlude(&mut img, &mask, band, std::slice::from_ref(&photo), &mut rng).unwrap();
                let f = o.fraction;
                assert!(f >= band.0 && f <= band.1, "band {band:?}: {f}");
                // The occluder mask is exactly the pixels painted, and its share of the object f.
                let shown: Vec<bool> = img.as_raw().chunks(3).map(|p| p != [0, 0, 0]).collect();
                assert!(o.covered.iter().zip(&shown).all(|(&c, &s)| c == 1 || !s), "painted outside the mask");
                let on_object = o.covered.iter().zip(&mask).filter(|&(&c, &m)| c == 1 && m != 0).count();
                // The stored figure is what the image shows: painted object pixels / object area.
                let painted = mask
                    .iter()
                    .enumerate()
                    .filter(|(i, m)| **m != 0 && img.as_raw()[3 * i..3 * i + 3] != [0, 0, 0])
                    .count();
                let area = mask.iter().filter(|m| **m != 0).count();
                assert_eq!(on_object as f64 / area as f64, f);
                assert!((painted as f64 / area as f64 - f).abs() < 0.02, "measured {painted}/{area} vs {f}");
            }
        }
    }
}
