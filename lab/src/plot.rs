//! Two small PNG charts for the reports, drawn pixel by pixel (no font, no plotting stack):
//! the captions live in the Markdown next to them.

use std::f64::consts::PI;
use std::path::Path;

use anyhow::Result;
use image::{Rgb, RgbImage};

const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const GREY: Rgb<u8> = Rgb([200, 200, 200]);
pub const BLUE: Rgb<u8> = Rgb([66, 110, 200]);
pub const ORANGE: Rgb<u8> = Rgb([230, 130, 40]);

/// Side-by-side polar histograms, one per series: for each of `bins` azimuth sectors (0° at
/// the top, clockwise), a wedge whose radius is the mean of the values (in [0, 1]) that fall
/// in it; grey rings at 0.25, 0.5, 0.75 and 1.
pub fn polar_histograms(path: &Path, series: &[(&[f64], &[f64], Rgb<u8>)], bins: usize) -> Result<()> {
    let size = 240u32;
    let mut img = RgbImage::from_pixel(size * series.len() as u32, size, WHITE);
    for (panel, (azimuths_deg, values, colour)) in series.iter().enumerate() {
        let mut sums = vec![(0.0, 0usize); bins];
        for (a, v) in azimuths_deg.iter().zip(values.iter()) {
            let b = ((a.rem_euclid(360.0) / 360.0 * bins as f64) as usize).min(bins - 1);
            sums[b] = (sums[b].0 + v, sums[b].1 + 1);
        }
        let means: Vec<f64> = sums.iter().map(|&(s, n)| if n > 0 { s / n as f64 } else { 0.0 }).collect();
        let (cx, cy, radius) = (size as f64 / 2.0, size as f64 / 2.0, size as f64 / 2.0 - 8.0);
        for y in 0..size {
            for x in 0..size {
                let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
                let r = (dx * dx + dy * dy).sqrt() / radius;
                let angle = dx.atan2(-dy).rem_euclid(2.0 * PI);
                let b = ((angle / (2.0 * PI) * bins as f64) as usize).min(bins - 1);
                let px = img.get_pixel_mut(panel as u32 * size + x, y);
                if r <= means[b] {
                    *px = *colour;
                }
                if [0.25, 0.5, 0.75, 1.0].iter().any(|ring| (r - ring).abs() * radius < 0.6) {
                    *px = if r <= means[b] { Rgb([40, 40, 40]) } else { GREY };
                }
            }
        }
    }
    img.save(path)?;
    Ok(())
}

/// Histograms of values in `[0, max]` with `bins` bins, the series' bars side by side within
/// each bin, heights relative to the tallest bar; grey lines at each quarter of that height.
pub fn histograms(path: &Path, series: &[(&[f64], Rgb<u8>)], max: f64, bins: usize) -> Result<()> {
    let (width, height, margin) = (bins as u32 * 24, 200u32, 8u32);
    let mut img = RgbImage::from_pixel(width + 2 * margin, height + 2 * margin, WHITE);
    let counts: Vec<Vec<usize>> = series
        .iter()
        .map(|(values, _)| {
            let mut c = vec![0usize; bins];
            for v in values.iter().filter(|v| v.is_finite()) {
                c[((v / max * bins as f64) as usize).min(bins - 1)] += 1;
            }
            c
        })
        .collect();
    let tallest = counts.iter().flatten().copied().max().unwrap_or(1).max(1) as f64;
    for q in 1..=4 {
        let y = margin + height - (height as f64 * q as f64 / 4.0) as u32;
        for x in margin..margin + width {
            img.put_pixel(x, y, GREY);
        }
    }
    // A 4-px gap between bins keeps each bin's bars together.
    let bar = 20 / series.len().max(1) as u32;
    for (s, (c, (_, colour))) in counts.iter().zip(series).enumerate() {
        for (b, &n) in c.iter().enumerate() {
            let h = (n as f64 / tallest * height as f64).round() as u32;
            let x0 = margin + 2 + b as u32 * 24 + s as u32 * bar;
            for x in x0..x0 + bar {
                for y in (margin + height - h)..(margin + height) {
                    img.put_pixel(x, y, *colour);
                }
            }
        }
    }
    img.save(path)?;
    Ok(())
}
