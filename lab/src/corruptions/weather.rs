//! Weather corruptions: snow, frost, fog and spatter, ported operation by operation from
//! `imagecorruptions` 1.1.5. All four are random; they draw only from the caller's generator.
//!
//! Frost blends in photographs of frost that ship inside the reference Python package. They are
//! not redistributed with udapose: `frost` reads them at run time from the installed package.

mod cv;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use image::{Rgb, RgbImage};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::CorruptionError;
use super::kernels::{Plane, clipped_zoom, from_planes, motion_blur, skimage_gaussian, to_planes, unit_to_u8};
use cv::Gray;

const fn level(severity: u8) -> usize {
    severity as usize - 1
}

/// `np.random.normal(loc, scale, size=(h, w))`.
fn normal_plane(w: usize, h: usize, loc: f64, scale: f64, rng: &mut ChaCha8Rng) -> Plane {
    let normal = Normal::new(loc, scale).expect("positive scale");
    Plane::from_fn(w, h, |_, _| normal.sample(rng))
}

/// `np.random.uniform(low, high)`.
fn uniform(low: f64, high: f64, rng: &mut ChaCha8Rng) -> f64 {
    low + (high - low) * rng.random::<f64>()
}

// ---------------------------------------------------------------------------------------------
// snow

/// Per severity: snow mean, snow std, zoom, threshold, blur radius, blur sigma, how much of the
/// original survives the whitening.
const SNOW: [(f64, f64, f64, f64, usize, f64, f64); 5] = [
    (0.1, 0.3, 3.0, 0.5, 10, 4.0, 0.8),
    (0.2, 0.3, 2.0, 0.5, 12, 4.0, 0.7),
    (0.55, 0.3, 4.0, 0.9, 12, 8.0, 0.7),
    (0.55, 0.3, 4.5, 0.85, 12, 8.0, 0.65),
    (0.55, 0.3, 2.5, 0.85, 12, 12.0, 0.55),
];

/// The flakes: zoomed-in thresholded noise, motion-blurred at a random downward angle, rounded
/// to 8 bits and cropped to the image (the zoom can overshoot it by a few pixels).
fn snow_layer(w: usize, h: usize, severity: u8, rng: &mut ChaCha8Rng) -> Plane {
    let (loc, scale, zoom, threshold, radius, sigma, _) = SNOW[level(severity)];
    let noise = normal_plane(w, h, loc, scale, rng);
    let flakes = clipped_zoom(&noise, zoom).map(|v| if v < threshold { 0.0 } else { v.clamp(0.0, 1.0) });
    let angle = uniform(-135.0, -45.0, rng);
    let streaks = motion_blur(&flakes, radius, sigma, angle);
    streaks.crop(0, 0, w, h).map(|v| (v * 255.0).round_ties_even().clamp(0.0, 255.0) / 255.0)
}

pub fn snow(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let keep = SNOW[level(severity)].6;
    let layer = snow_layer(w, h, severity, rng);
    let rgb = to_planes(image, |v| f64::from(f32::from(v) / 255.0));
    // The scene is also whitened towards 1.5 × grey + 0.5 (cv2 RGB2GRAY weights), then the flakes
    // are added twice: as drawn and rotated by 180°.
    let grey =
        Plane::from_fn(w, h, |x, y| 0.299 * rgb[0].get(x, y) + 0.587 * rgb[1].get(x, y) + 0.114 * rgb[2].get(x, y));
    let out = rgb.map(|p| {
        Plane::from_fn(w, h, |x, y| {
            let v = p.get(x, y);
            let whitened = keep * v + (1.0 - keep) * v.max(grey.get(x, y) * 1.5 + 0.5);
            whitened + layer.get(x, y) + layer.get(w - 1 - x, h - 1 - y)
        })
    });
    from_planes(&out, unit_to_u8)
}

// ---------------------------------------------------------------------------------------------
// fog

/// The diamond-square heightmap of the reference's `plasma_fractal`, in float32 like the
/// reference's array, normalised to [0, 1]. Each midpoint gets the mean of its four neighbours
/// (wrapping around) plus `wibble · U(−wibble, wibble)`; `wibble` shrinks by `decay` per level.
fn plasma_fractal(size: usize, decay: f64, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let mut map = vec![0f32; size * size];
    let (mut step, mut wibble) = (size, 100.0);
    while step >= 2 {
        fill_squares(&mut map, size, step, wibble, rng);
        fill_diamonds(&mut map, size, step, wibble, rng);
        step /= 2;
        wibble /= decay;
    }
    let min = map.iter().copied().fold(f32::INFINITY, f32::min);
    map.iter_mut().for_each(|v| *v -= min);
    let max = map.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    map.into_iter().map(|v| v / max).collect()
}

/// `wibbledmean`: a quarter of the float32 sum of four neighbours, plus noise, stored as f32.
fn wibbled_mean(sum: f32, wibble: f64, rng: &mut ChaCha8Rng) -> f32 {
    (f64::from(sum / 4.0) + wibble * uniform(-wibble, wibble, rng)) as f32
}

/// Centres of the squares of corners `step` apart: numpy's
/// `corner + roll(corner, -1, 0)`, then `+ roll(·, -1, 1)`.
fn fill_squares(map: &mut [f32], size: usize, step: usize, wibble: f64, rng: &mut ChaCha8Rng) {
    let n = size / step;
    let corner = |map: &[f32], i: usize, j: usize| map[(i % n) * step * size + (j % n) * step];
    for i in 0..n {
        for j in 0..n {
            let left = corner(map, i, j) + corner(map, i + 1, j);
            let right = corner(map, i, j + 1) + corner(map, i + 1, j + 1);
            let v = wibbled_mean(left + right, wibble, rng);
            map[(i * step + step / 2) * size + j * step + step / 2] = v;
        }
    }
}

/// Edge midpoints: first those on the corner rows, then those on the corner columns, each from
/// the two adjacent square centres and the two adjacent corners, with the reference's rolls.
fn fill_diamonds(map: &mut [f32], size: usize, step: usize, wibble: f64, rng: &mut ChaCha8Rng) {
    let (n, half) = (size / step, step / 2);
    let centre = |map: &[f32], i: usize, j: usize| map[((i % n) * step + half) * size + (j % n) * step + half];
    let corner = |map: &[f32], i: usize, j: usize| map[(i % n) * step * size + (j % n) * step];
    for i in 0..n {
        for j in 0..n {
            let sum = (centre(map, i, j) + centre(map, i + n - 1, j)) + (corner(map, i, j) + corner(map, i, j + 1));
            map[i * step * size + j * step + half] = wibbled_mean(sum, wibble, rng);
        }
    }
    for i in 0..n {
        for j in 0..n {
            let sum = (centre(map, i, j) + centre(map, i, j + n - 1)) + (corner(map, i, j) + corner(map, i + 1, j));
            map[(i * step + half) * size + j * step] = wibbled_mean(sum, wibble, rng);
        }
    }
}

pub fn fog(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let (amount, decay) = [(1.5, 2.0), (2.0, 2.0), (2.5, 1.7), (2.5, 1.5), (3.0, 1.4)][level(severity)];
    let (w, h) = (image.width() as usize, image.height() as usize);
    // `max(shape)` includes the channel count, so tiny images still get a 4×4 map.
    let size = w.max(h).max(3).next_power_of_two();
    let plasma = plasma_fractal(size, decay, rng);
    let max_val = image.as_raw().iter().map(|&v| f64::from(v) / 255.0).fold(0.0, f64::max);
    let rgb = to_planes(image, |v| f64::from(v) / 255.0);
    // The fog is the map's top-left h×w corner; brightness is rescaled so the original maximum
    // plus the full fog amount maps back to that maximum.
    let out = rgb.map(|p| {
        Plane::from_fn(w, h, |x, y| {
            let fogged = p.get(x, y) + f64::from(amount as f32 * plasma[y * size + x]);
            fogged * max_val / (max_val + amount)
        })
    });
    from_planes(&out, unit_to_u8)
}

// ---------------------------------------------------------------------------------------------
// frost

const FROST_FILES: [&str; 6] = ["frost1.png", "frost2.png", "frost3.png", "frost4.jpg", "frost5.jpg", "frost6.jpg"];
const FROST_INSTALL_HINT: &str = "the frost textures ship with the reference package: install it into the project venv \
     (`make venv`, or `$UDAPOSE_CACHE/venv/bin/pip install imagecorruptions-imaug==1.1.5`), or set \
     UDAPOSE_FROST_DIR to a directory holding frost1.png..frost3.png and frost4.jpg..frost6.jpg";

fn missing(what: String) -> CorruptionError {
    CorruptionError::MissingAsset(format!("{what}; {FROST_INSTALL_HINT}"))
}

/// Where the frost textures are: `$UDAPOSE_FROST_DIR`, else the reference package's `frost/`
/// directory in the project venv (`$UDAPOSE_CACHE`, default `~/.cache/udapose`).
pub fn frost_dir() -> Result<PathBuf, CorruptionError> {
    if let Some(dir) = std::env::var_os("UDAPOSE_FROST_DIR") {
        return Ok(PathBuf::from(dir));
    }
    let cache = match (std::env::var_os("UDAPOSE_CACHE"), std::env::var_os("HOME")) {
        (Some(cache), _) => PathBuf::from(cache),
        (None, Some(home)) => PathBuf::from(home).join(".cache/udapose"),
        (None, None) => return Err(missing("neither UDAPOSE_CACHE nor HOME is set".into())),
    };
    let lib = cache.join("venv/lib");
    let mut pythons: Vec<PathBuf> = std::fs::read_dir(&lib)
        .map(|entries| entries.filter_map(Result::ok).map(|e| e.path()).collect())
        .unwrap_or_default();
    pythons.retain(|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with("python3")));
    pythons.sort();
    pythons
        .into_iter()
        .map(|p| p.join("site-packages/imagecorruptions/frost"))
        .find(|d| d.is_dir())
        .ok_or_else(|| missing(format!("no imagecorruptions/frost under {}/python3*/site-packages", lib.display())))
}

/// The six textures of `dir`, decoded once per directory and process.
pub fn frost_textures(dir: &Path) -> Result<Arc<Vec<RgbImage>>, CorruptionError> {
    static CACHE: OnceLock<Mutex<HashMap<PathBuf, Arc<Vec<RgbImage>>>>> = OnceLock::new();
    let cache = CACHE.get_or_init(Default::default);
    if let Some(textures) = cache.lock().expect("frost cache poisoned").get(dir) {
        return Ok(textures.clone());
    }
    let textures = FROST_FILES
        .iter()
        .map(|name| {
            let path = dir.join(name);
            image::open(&path)
                .map(|img| img.to_rgb8())
                .map_err(|e| missing(format!("cannot read frost texture {}: {e}", path.display())))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let textures = Arc::new(textures);
    cache.lock().expect("frost cache poisoned").insert(dir.to_path_buf(), textures.clone());
    Ok(textures)
}

/// The reference's texture size: scaled up until it covers the image, then by 1.1 more so a
/// random crop has room to move.
fn frost_size(tex_w: usize, tex_h: usize, w: usize, h: usize) -> (usize, usize) {
    let (tw, th) = (tex_w as f64, tex_h as f64);
    let fits = (th >= h as f64, tw >= w as f64);
    let factor = match fits {
        (true, true) => 1.0,
        (false, true) => h as f64 / th,
        (true, false) => w as f64 / tw,
        (false, false) => (h as f64 / th).max(w as f64 / tw),
    } * 1.1;
    ((tw * factor).ceil() as usize, (th * factor).ceil() as usize)
}

pub fn frost(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> Result<RgbImage, CorruptionError> {
    frost_from(&frost_dir()?, image, severity, rng)
}

/// `frost` with the texture directory given explicitly.
pub fn frost_from(
    dir: &Path,
    image: &RgbImage,
    severity: u8,
    rng: &mut ChaCha8Rng,
) -> Result<RgbImage, CorruptionError> {
    let textures = frost_textures(dir)?;
    let (keep, add) = [(1.0, 0.4), (0.8, 0.6), (0.7, 0.7), (0.65, 0.7), (0.6, 0.75)][level(severity)];
    let (w, h) = (image.width() as usize, image.height() as usize);
    let texture = &textures[rng.random_range(0..FROST_FILES.len())];
    let (tw, th) = frost_size(texture.width() as usize, texture.height() as usize, w, h);
    // frost_size makes the texture strictly larger, so both ranges are non-empty.
    let top = rng.random_range(0..th - h);
    let left = rng.random_range(0..tw - w);
    let crop = cv::resize_cubic_window(texture, (tw, th), left, top, w, h);
    Ok(RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let (p, f) = (image.get_pixel(x, y), crop.get_pixel(x, y));
        Rgb(std::array::from_fn(|c| (keep * f64::from(p[c]) + add * f64::from(f[c])).clamp(0.0, 255.0) as u8))
    }))
}

// ---------------------------------------------------------------------------------------------
// spatter

/// Per severity: liquid mean, liquid std, liquid blur sigma, threshold, water intensity or mud
/// blur sigma, and whether it is mud (1) or water (0).
const SPATTER: [(f64, f64, f64, f64, f64, bool); 5] = [
    (0.65, 0.3, 4.0, 0.69, 0.6, false),
    (0.65, 0.3, 3.0, 0.68, 0.6, false),
    (0.65, 0.3, 2.0, 0.68, 0.5, false),
    (0.65, 0.3, 1.0, 0.65, 1.5, true),
    (0.67, 0.4, 1.0, 0.65, 1.5, true),
];

pub fn spatter(image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> RgbImage {
    let (loc, scale, sigma, threshold, strength, mud) = SPATTER[level(severity)];
    let (w, h) = (image.width() as usize, image.height() as usize);
    let liquid = skimage_gaussian(&normal_plane(w, h, loc, scale, rng), sigma);
    let liquid = liquid.map(|v| if v < threshold { 0.0 } else { v });
    if mud { mud_spatter(image, &liquid, threshold, strength) } else { water_spatter(image, &liquid, strength) }
}

/// Water drops: the liquid blobs shaded by an embossed, equalised distance-to-edge map, tinted
/// pale turquoise and added to the image.
fn water_spatter(image: &RgbImage, liquid: &Plane, strength: f64) -> RgbImage {
    let (w, h) = (liquid.width, liquid.height);
    let layer = Gray { w, h, data: liquid.data.iter().map(|&v| (v * 255.0) as u8).collect() };
    let shade = drop_shading(&layer);
    let m: Vec<f32> = layer.data.iter().zip(&shade.data).map(|(&l, &s)| f32::from(l) * f32::from(s)).collect();
    let max = m.iter().copied().fold(0.0f32, f32::max);
    // With no drop at all the reference divides 0 by 0 and its uint8 cast of NaN gives black;
    // leaving the image untouched is the sensible reading of "no spatter".
    let m: Vec<f64> = m.iter().map(|&v| if max > 0.0 { f64::from(v / max) * strength } else { 0.0 }).collect();
    // Channel order as the reference applies it to an RGB array (it calls the tint BGR).
    let tint = [175.0 / 255.0, 238.0 / 255.0, 238.0 / 255.0];
    let rgb = to_planes(image, |v| f64::from(f32::from(v) / 255.0));
    let out: [Plane; 3] =
        std::array::from_fn(|c| Plane::from_fn(w, h, |x, y| rgb[c].get(x, y) + m[y * w + x] * tint[c]));
    from_planes(&out, unit_to_u8)
}

/// The reference's OpenCV chain: Canny edges of the blobs, distance to them capped at 20,
/// blurred, equalised, embossed, blurred again.
fn drop_shading(layer: &Gray) -> Gray {
    let (w, h) = (layer.w, layer.h);
    let edges = cv::canny(layer, 50, 150);
    let not_edges = Gray { w, h, data: edges.data.iter().map(|&e| 255 - e).collect() };
    let dist: Vec<f32> = cv::distance_transform(&not_edges).into_iter().map(|d| d.min(20.0)).collect();
    let dist = Gray { w, h, data: cv::blur3_f32(&dist, w, h).into_iter().map(|d| d as u8).collect() };
    let embossed = cv::filter3x3_u8(&cv::equalize_hist(&dist), [[-2, -1, 0], [-1, 1, 1], [0, 1, 2]]);
    cv::blur3_u8(&embossed)
}

/// Mud: where the blurred blob mask is at least 0.8 the image is replaced (in proportion) by
/// mud brown.
fn mud_spatter(image: &RgbImage, liquid: &Plane, threshold: f64, sigma: f64) -> RgbImage {
    let mask = liquid.map(|v| if v > threshold { 1.0 } else { 0.0 });
    let m = skimage_gaussian(&mask, sigma).map(|v| {
        let v = f64::from(v as f32);
        if v < 0.8 { 0.0 } else { v }
    });
    let brown = [63.0 / 255.0, 42.0 / 255.0, 20.0 / 255.0];
    let rgb = to_planes(image, |v| f64::from(f32::from(v) / 255.0));
    let out: [Plane; 3] = std::array::from_fn(|c| {
        Plane::from_fn(liquid.width, liquid.height, |x, y| {
            let m = m.get(x, y);
            rgb[c].get(x, y) * (1.0 - m) + brown[c] * m
        })
    });
    from_planes(&out, unit_to_u8)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn plasma_is_normalised_and_seeded() {
        let a = plasma_fractal(64, 2.0, &mut ChaCha8Rng::seed_from_u64(1));
        let b = plasma_fractal(64, 2.0, &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(a, b);
        assert_eq!(a.iter().copied().fold(f32::INFINITY, f32::min), 0.0);
        assert_eq!(a.iter().copied().fold(f32::NEG_INFINITY, f32::max), 1.0);
    }

    #[test]
    fn frost_texture_covers_the_image() {
        // 900 · 1.1 is 990.0000000000001 in binary floating point; np.ceil makes it 991 too.
        assert_eq!(frost_size(900, 600, 320, 128), (991, 660));
        let (w, h) = frost_size(560, 315, 672, 256);
        assert!(w > 672 && h > 256, "{w}x{h}");
    }

    #[test]
    fn frost_from_an_empty_dir_is_a_missing_asset() {
        let dir = std::env::temp_dir().join(format!("udapose-no-frost-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let img = RgbImage::new(16, 16);
        let err = frost_from(&dir, &img, 3, &mut ChaCha8Rng::seed_from_u64(0)).unwrap_err();
        assert!(
            matches!(&err, CorruptionError::MissingAsset(m) if m.contains("frost1.png") && m.contains("pip install"))
        );
        std::fs::remove_dir(&dir).unwrap();
    }
}
