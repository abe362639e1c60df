//! The OpenCV calls that `frost` and `spatter` make in the reference, ported with OpenCV's
//! integer arithmetic and borders where they decide a value: `cv2.resize(INTER_CUBIC)`,
//! `cv2.Canny`, `cv2.distanceTransform(DIST_L2, 5)`, `cv2.blur`, `cv2.equalizeHist`,
//! `cv2.filter2D`. Single-channel 8-bit images are `Gray` (row-major `u8`).

use image::{Rgb, RgbImage};

use super::super::kernels::Border;

/// A single-channel 8-bit image.
pub struct Gray {
    pub w: usize,
    pub h: usize,
    pub data: Vec<u8>,
}

impl Gray {
    fn at(&self, x: usize, y: usize) -> u8 {
        self.data[y * self.w + x]
    }
}

/// OpenCV's `interpolateCubic` (A = −0.75), in float as OpenCV computes it, then to its 11-bit
/// fixed point (`INTER_RESIZE_COEF_SCALE`).
fn cubic_weights(t: f32) -> [i64; 4] {
    const A: f32 = -0.75;
    let c0 = ((A * (t + 1.0) - 5.0 * A) * (t + 1.0) + 8.0 * A) * (t + 1.0) - 4.0 * A;
    let c1 = ((A + 2.0) * t - (A + 3.0)) * t * t + 1.0;
    let c2 = ((A + 2.0) * (1.0 - t) - (A + 3.0)) * (1.0 - t) * (1.0 - t) + 1.0;
    let c3 = 1.0 - c0 - c1 - c2;
    [c0, c1, c2, c3].map(|c| (c * 2048.0).round_ties_even() as i64)
}

/// Source taps of one output index of a cubic resize: the four input indices (clamped to the
/// edge, OpenCV's replicate border for resize) and their fixed-point weights.
fn cubic_taps(out_index: usize, in_size: usize, out_size: usize) -> ([usize; 4], [i64; 4]) {
    let scale = 1.0 / (out_size as f64 / in_size as f64);
    let f = ((out_index as f64 + 0.5) * scale - 0.5) as f32;
    let s = f.floor();
    let idx = std::array::from_fn(|k| (s as isize - 1 + k as isize).clamp(0, in_size as isize - 1) as usize);
    (idx, cubic_weights(f - s))
}

/// The `w`×`h` window at (`x0`, `y0`) of `cv2.resize(src, (out_w, out_h), INTER_CUBIC)`.
/// Each output sample depends only on its 4×4 neighbourhood, so computing just the window the
/// caller crops gives the same pixels as resizing everything and cropping.
pub fn resize_cubic_window(src: &RgbImage, out: (usize, usize), x0: usize, y0: usize, w: usize, h: usize) -> RgbImage {
    let (sw, sh) = (src.width() as usize, src.height() as usize);
    let cols: Vec<_> = (x0..x0 + w).map(|x| cubic_taps(x, sw, out.0)).collect();
    RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let (xs, wx) = &cols[x as usize];
        let (ys, wy) = cubic_taps(y0 + y as usize, sh, out.1);
        Rgb(std::array::from_fn(|c| {
            let row = |sy: usize| -> i64 {
                xs.iter().zip(wx).map(|(&sx, &k)| i64::from(src.get_pixel(sx as u32, sy as u32)[c]) * k).sum()
            };
            let acc: i64 = ys.iter().zip(wy).map(|(&sy, k)| row(sy) * k).sum();
            ((acc + (1 << 21)) >> 22).clamp(0, 255) as u8
        }))
    })
}

/// 3×3 Sobel derivatives with `BORDER_REPLICATE`, as Canny computes them.
fn sobel(img: &Gray) -> (Vec<i32>, Vec<i32>) {
    let (w, h) = (img.w as isize, img.h as isize);
    let at = |x: isize, y: isize| i32::from(img.at(x.clamp(0, w - 1) as usize, y.clamp(0, h - 1) as usize));
    let mut dx = Vec::with_capacity(img.data.len());
    let mut dy = Vec::with_capacity(img.data.len());
    for y in 0..h {
        for x in 0..w {
            let col = |x| at(x, y - 1) + 2 * at(x, y) + at(x, y + 1);
            let row = |y| at(x - 1, y) + 2 * at(x, y) + at(x + 1, y);
            dx.push(col(x + 1) - col(x - 1));
            dy.push(row(y + 1) - row(y - 1));
        }
    }
    (dx, dy)
}

/// Whether pixel `i` survives non-maximum suppression, with OpenCV's fixed-point 22.5° / 67.5°
/// sector test; `mag` reads 0 outside the image.
fn is_local_max(i: usize, w: usize, dx: i32, dy: i32, mag: &dyn Fn(isize, isize) -> i32) -> bool {
    const SHIFT: u32 = 15;
    const TG22: i64 = 13573; // round(tan(22.5°) · 2^15)
    let (x, y) = ((i % w) as isize, (i / w) as isize);
    let m = mag(x, y);
    let ax = i64::from(dx.abs());
    let ay = i64::from(dy.abs()) << SHIFT;
    let tg22x = ax * TG22;
    if ay < tg22x {
        m > mag(x - 1, y) && m >= mag(x + 1, y)
    } else if ay > tg22x + (ax << (SHIFT + 1)) {
        m > mag(x, y - 1) && m >= mag(x, y + 1)
    } else {
        let s = if (dx ^ dy) < 0 { -1 } else { 1 };
        m > mag(x - s, y - 1) && m > mag(x + s, y + 1)
    }
}

/// `cv2.Canny(img, low, high)` (aperture 3, L1 gradient): 255 on edges, 0 elsewhere.
pub fn canny(img: &Gray, low: i32, high: i32) -> Gray {
    let (w, h) = (img.w, img.h);
    let (dx, dy) = sobel(img);
    let mag: Vec<i32> = dx.iter().zip(&dy).map(|(a, b)| a.abs() + b.abs()).collect();
    let mag_at = |x: isize, y: isize| {
        if x < 0 || y < 0 || x >= w as isize || y >= h as isize { 0 } else { mag[y as usize * w + x as usize] }
    };
    // 2 = edge, 1 = weak candidate, 0 = not an edge.
    let mut state = vec![0u8; w * h];
    let mut stack = Vec::new();
    for i in 0..w * h {
        if mag[i] > low && is_local_max(i, w, dx[i], dy[i], &mag_at) {
            state[i] = if mag[i] > high { 2 } else { 1 };
            if state[i] == 2 {
                stack.push(i);
            }
        }
    }
    // Hysteresis: weak candidates 8-connected to an edge become edges.
    while let Some(i) = stack.pop() {
        let (x, y) = ((i % w) as isize, (i / w) as isize);
        for (nx, ny) in (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy))) {
            if nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h {
                let j = ny as usize * w + nx as usize;
                if state[j] == 1 {
                    state[j] = 2;
                    stack.push(j);
                }
            }
        }
    }
    Gray { w, h, data: state.into_iter().map(|s| if s == 2 { 255 } else { 0 }).collect() }
}

/// `cv2.distanceTransform(img, DIST_L2, 5)`: distance from each non-zero pixel to the nearest
/// zero pixel, by OpenCV's two-pass 5×5 chamfer (steps 1, 1.4, 2.1969 in 16-bit fixed point).
/// Outside the image counts as infinitely far, so with no zero pixel everything stays huge.
pub fn distance_transform(img: &Gray) -> Vec<f32> {
    const SHIFT: u32 = 16;
    let fix = |v: f64| (v * f64::from(1u32 << SHIFT)).round_ties_even() as u64;
    let (hv, diag, long) = (fix(1.0), fix(1.4), fix(2.1969));
    // (dx, dy, cost) of the neighbours visited before the pixel in the forward scan.
    let forward = [
        (-1, -2, long),
        (1, -2, long),
        (-2, -1, long),
        (-1, -1, diag),
        (0, -1, hv),
        (1, -1, diag),
        (2, -1, long),
        (-1, 0, hv),
    ];
    let (w, h) = (img.w as isize, img.h as isize);
    let far = u64::from(u32::MAX);
    let mut d: Vec<u64> = img.data.iter().map(|&v| if v == 0 { 0 } else { far }).collect();
    let relax = |x: isize, y: isize, sign: isize, d: &mut [u64]| {
        let i = (y * w + x) as usize;
        for &(dx, dy, cost) in &forward {
            let (nx, ny) = (x + sign * dx, y + sign * dy);
            if nx >= 0 && ny >= 0 && nx < w && ny < h {
                d[i] = d[i].min(d[(ny * w + nx) as usize] + cost);
            }
        }
    };
    for y in 0..h {
        for x in 0..w {
            if img.data[(y * w + x) as usize] != 0 {
                relax(x, y, 1, &mut d);
            }
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            if d[(y * w + x) as usize] > hv {
                relax(x, y, -1, &mut d);
            }
        }
    }
    d.into_iter().map(|v| (v as f64 / f64::from(1u32 << SHIFT)) as f32).collect()
}

/// Sum of the 3×3 neighbourhood of (x, y) read through OpenCV's default `BORDER_REFLECT_101`.
fn sum3x3<T: Copy + Into<f64>>(data: &[T], w: usize, h: usize, x: usize, y: usize) -> f64 {
    let mut s = 0.0;
    for dy in -1..=1 {
        for dx in -1..=1 {
            let sx = Border::Mirror.index(x as isize + dx, w).expect("mirror border");
            let sy = Border::Mirror.index(y as isize + dy, h).expect("mirror border");
            s += data[sy * w + sx].into();
        }
    }
    s
}

/// `cv2.blur(x, (3, 3))` on float32.
pub fn blur3_f32(data: &[f32], w: usize, h: usize) -> Vec<f32> {
    (0..w * h).map(|i| (sum3x3(data, w, h, i % w, i / w) * (1.0 / 9.0)) as f32).collect()
}

/// `cv2.blur(x, (3, 3))` on uint8 (rounded to nearest).
pub fn blur3_u8(img: &Gray) -> Gray {
    let data = (0..img.w * img.h)
        .map(|i| (sum3x3(&img.data, img.w, img.h, i % img.w, i / img.w) * (1.0 / 9.0)).round_ties_even() as u8)
        .collect();
    Gray { w: img.w, h: img.h, data }
}

/// `cv2.equalizeHist`: the cumulative histogram, from the first occupied bin, stretched to 0–255.
pub fn equalize_hist(img: &Gray) -> Gray {
    let mut hist = [0u32; 256];
    for &v in &img.data {
        hist[usize::from(v)] += 1;
    }
    let first = hist.iter().position(|&c| c > 0).unwrap_or(0);
    let total = img.data.len() as u32;
    if hist[first] == total {
        return Gray { w: img.w, h: img.h, data: vec![first as u8; img.data.len()] };
    }
    let scale = 255.0f32 / (total - hist[first]) as f32;
    let mut lut = [0u8; 256];
    let mut sum = 0u32;
    for i in first + 1..256 {
        sum += hist[i];
        lut[i] = (sum as f32 * scale).round_ties_even().clamp(0.0, 255.0) as u8;
    }
    Gray { w: img.w, h: img.h, data: img.data.iter().map(|&v| lut[usize::from(v)]).collect() }
}

/// `cv2.filter2D(img, cv2.CV_8U, kernel)` for a 3×3 integer kernel: correlation anchored at the
/// centre, `BORDER_REFLECT_101`, saturated to 0–255.
pub fn filter3x3_u8(img: &Gray, kernel: [[i32; 3]; 3]) -> Gray {
    let (w, h) = (img.w, img.h);
    let data = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut s = 0;
            for (ky, row) in kernel.iter().enumerate() {
                for (kx, k) in row.iter().enumerate() {
                    let sx = Border::Mirror.index(x as isize + kx as isize - 1, w).expect("mirror border");
                    let sy = Border::Mirror.index(y as isize + ky as isize - 1, h).expect("mirror border");
                    s += k * i32::from(img.at(sx, sy));
                }
            }
            s.clamp(0, 255) as u8
        })
        .collect();
    Gray { w, h, data }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cubic_weights_sum_to_one() {
        for t in [0.0, 0.25, 0.5, 0.9] {
            let s: i64 = cubic_weights(t).iter().sum();
            assert!((s - 2048).abs() <= 1, "{t}: {s}");
        }
        assert_eq!(cubic_weights(0.0), [0, 2048, 0, 0]);
    }

    #[test]
    fn distance_to_single_zero() {
        let mut data = vec![255u8; 25];
        data[12] = 0;
        let d = distance_transform(&Gray { w: 5, h: 5, data });
        assert_eq!(d[12], 0.0);
        assert_eq!(d[13], 1.0);
        assert!((d[18] - 1.4).abs() < 1e-4);
        assert!((d[19] - 2.1969).abs() < 1e-4);
        assert!((d[0] - 2.8).abs() < 1e-4);
    }

    #[test]
    fn canny_finds_a_square_outline() {
        let data = (0..400)
            .map(|i| if (5..15).contains(&(i % 20)) && (5..15).contains(&(i / 20)) { 200 } else { 0 })
            .collect();
        let edges = canny(&Gray { w: 20, h: 20, data }, 50, 150);
        // cv2.Canny on the same square: 36 edge pixels, just outside the top edge, corners cut.
        assert_eq!(edges.data.iter().filter(|&&v| v == 255).count(), 36);
        assert_eq!((edges.at(5, 5), edges.at(10, 5), edges.at(10, 4), edges.at(10, 10)), (255, 0, 255, 0));
        let top: Vec<usize> = (0..20).filter(|&x| edges.at(x, 4) == 255).collect();
        assert_eq!(top, (6..14).collect::<Vec<_>>());
    }

    #[test]
    fn equalize_spreads_two_levels() {
        let img = Gray { w: 2, h: 1, data: vec![3, 9] };
        assert_eq!(equalize_hist(&img).data, vec![0, 255]);
    }
}
