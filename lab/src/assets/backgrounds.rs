//! Background photographs from the TORCS tracks (BENCHMARK.md §3): `road/` and `oval/` for the
//! source domain, `dirt/` for `context`, disjoint by content.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use image::{RgbImage, RgbaImage, imageops};
use rayon::prelude::*;
use sha2::{Digest, Sha256};

use super::sgi;

/// Which backgrounds a sample draws from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Group {
    Source,
    Context,
}

/// Decoded backgrounds, shrunk so their short side is at most `max_short_side` (enough for the
/// crops we cut).
pub struct Backgrounds {
    pub source: Vec<RgbImage>,
    pub context: Vec<RgbImage>,
}

impl Backgrounds {
    pub fn load(torcs: &Path, max_short_side: u32) -> Result<Self> {
        let tracks = torcs.join("tracks");
        let source = usable(&["road", "oval"].map(|g| tracks.join(g)))?;
        let source_hashes: HashSet<[u8; 32]> = source.iter().map(|c| c.sha256).collect();
        let context: Vec<Candidate> =
            usable(&[tracks.join("dirt")])?.into_iter().filter(|c| !source_hashes.contains(&c.sha256)).collect();
        if source.is_empty() || context.is_empty() {
            bail!("no usable backgrounds under {}", tracks.display());
        }
        let shrink = |c: Candidate| shrink(c.image, max_short_side);
        Ok(Backgrounds {
            source: source.into_par_iter().map(shrink).collect(),
            context: context.into_par_iter().map(shrink).collect(),
        })
    }

    pub fn group(&self, group: Group) -> &[RgbImage] {
        match group {
            Group::Source => &self.source,
            Group::Context => &self.context,
        }
    }
}

struct Candidate {
    image: RgbImage,
    sha256: [u8; 32],
}

/// Images at least 256 px on the short side, at most 1% non-opaque, not shadows, logos or
/// track maps; sorted by path so the pool is the same on every machine.
fn usable(dirs: &[PathBuf]) -> Result<Vec<Candidate>> {
    let mut files = Vec::new();
    for dir in dirs {
        for track in std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
            let track = track?.path();
            let track_name = track.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            for f in std::fs::read_dir(&track).into_iter().flatten().flatten() {
                let path = f.path();
                let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                let image_file = name.ends_with(".png") || name.ends_with(".rgb");
                let excluded =
                    name.starts_with("shadow") || name.starts_with("logo") || name == format!("{track_name}.png");
                if image_file && !excluded {
                    files.push(path);
                }
            }
        }
    }
    files.sort();
    Ok(files.par_iter().filter_map(|p| candidate(p)).collect())
}

fn candidate(path: &Path) -> Option<Candidate> {
    let bytes = std::fs::read(path).ok()?;
    let rgba: RgbaImage = match sgi::decode_rgba(&bytes) {
        Ok(img) => img,
        Err(_) => image::load_from_memory(&bytes).ok()?.to_rgba8(),
    };
    let translucent = rgba.pixels().filter(|p| p.0[3] < 255).count();
    let big_enough = rgba.width().min(rgba.height()) >= 256;
    (big_enough && translucent * 100 <= rgba.pixels().len()).then(|| Candidate {
        sha256: Sha256::digest(&bytes).into(),
        image: image::DynamicImage::ImageRgba8(rgba).to_rgb8(),
    })
}

fn shrink(img: RgbImage, max_short_side: u32) -> RgbImage {
    let short = img.width().min(img.height());
    if short <= max_short_side {
        return img;
    }
    let scale = max_short_side as f64 / short as f64;
    let (w, h) = ((img.width() as f64 * scale).round() as u32, (img.height() as f64 * scale).round() as u32);
    imageops::resize(&img, w.max(1), h.max(1), imageops::FilterType::Triangle)
}

/// A crop with the aspect of `width × height` at a random scale and place, resized to that
/// size and flipped horizontally at random.
pub fn random_crop(src: &RgbImage, width: u32, height: u32, rng: &mut impl rand::Rng) -> RgbImage {
    let aspect = width as f64 / height as f64;
    let max_h = (src.height() as f64).min(src.width() as f64 / aspect);
    let h = (max_h * rng.random_range(0.5..=1.0)).max(1.0);
    let w = (h * aspect).min(src.width() as f64);
    let x = rng.random_range(0.0..=(src.width() as f64 - w).max(0.0)) as u32;
    let y = rng.random_range(0.0..=(src.height() as f64 - h).max(0.0)) as u32;
    let view = imageops::crop_imm(src, x, y, (w as u32).max(1), (h as u32).max(1)).to_image();
    let out = imageops::resize(&view, width, height, imageops::FilterType::Triangle);
    if rng.random_bool(0.5) { imageops::flip_horizontal(&out) } else { out }
}
