//! Image-processing building blocks shared by the corruptions. Each reproduces the NumPy / SciPy /
//! scikit-image / OpenCV call that the reference package (`imagecorruptions-imaug` 1.1.5) makes,
//! with the same border handling and, where it decides how a value truncates to `u8`, the same
//! order of floating-point operations.
//!
//! Everything works on [`Plane`]s (one `f64` channel); `to_planes` / `from_planes` convert.

use image::RgbImage;

/// One image channel, row-major `f64` samples.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f64>,
}

impl Plane {
    /// A plane of zeros.
    pub fn new(width: usize, height: usize) -> Self {
        Plane { width, height, data: vec![0.0; width * height] }
    }

    /// A plane whose sample at column `x`, row `y` is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> f64) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Plane { width, height, data }
    }

    pub fn get(&self, x: usize, y: usize) -> f64 {
        self.data[y * self.width + x]
    }

    pub fn set(&mut self, x: usize, y: usize, v: f64) {
        self.data[y * self.width + x] = v;
    }

    /// Applies `f` to every sample.
    pub fn map(&self, f: impl Fn(f64) -> f64) -> Plane {
        Plane { width: self.width, height: self.height, data: self.data.iter().map(|&v| f(v)).collect() }
    }

    /// Rows `y0..y0 + h`, columns `x0..x0 + w` (NumPy slicing `p[y0:y0+h, x0:x0+w]`).
    pub fn crop(&self, x0: usize, y0: usize, w: usize, h: usize) -> Plane {
        Plane::from_fn(w, h, |x, y| self.get(x0 + x, y0 + y))
    }

    fn transpose(&self) -> Plane {
        Plane::from_fn(self.height, self.width, |x, y| self.get(y, x))
    }
}

/// Splits an RGB image into its R, G, B planes, mapping each sample through `f`
/// (e.g. `|v| v as f64 / 255.0`, NumPy's `np.array(x) / 255.`).
pub fn to_planes(image: &RgbImage, f: impl Fn(u8) -> f64) -> [Plane; 3] {
    let (w, h) = (image.width() as usize, image.height() as usize);
    std::array::from_fn(|c| Plane::from_fn(w, h, |x, y| f(image.get_pixel(x as u32, y as u32)[c])))
}

/// Joins three equally sized planes into an RGB image, mapping each sample through `f`.
pub fn from_planes(planes: &[Plane; 3], f: impl Fn(f64) -> u8) -> RgbImage {
    let (w, h) = (planes[0].width, planes[0].height);
    RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let i = y as usize * w + x as usize;
        image::Rgb(std::array::from_fn(|c| f(planes[c].data[i])))
    })
}

/// `np.uint8(np.clip(v, 0, 1) * 255)`, how most corruptions end (the `corrupt()` wrapper's
/// `np.uint8` cast truncates toward zero, it does not round).
pub fn unit_to_u8(v: f64) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0) as u8
}

/// `np.uint8(np.clip(v, 0, 255))`, for corruptions that work on the 0–255 scale.
pub fn clip_to_u8(v: f64) -> u8 {
    v.clamp(0.0, 255.0) as u8
}

/// How samples beyond the edge are read. Names follow `scipy.ndimage`; OpenCV's
/// `BORDER_REFLECT_101` (its default) is `Mirror`, `BORDER_REFLECT` is `Reflect`,
/// `BORDER_REPLICATE` is `Nearest`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Border {
    /// `dcba|abcd|dcba`
    Reflect,
    /// `dcb|abcd|cba`
    Mirror,
    /// `aaa|abcd|ddd`
    Nearest,
    /// `bcd|abcd|abc`
    Wrap,
    /// `kkk|abcd|kkk`
    Constant(f64),
}

impl Border {
    /// The in-range index that index `i` of a line of `n` samples reads, or `None` for a constant
    /// border. Folds repeatedly, so kernels longer than the line work (as in SciPy and OpenCV).
    pub fn index(self, i: isize, n: usize) -> Option<usize> {
        let n = n as isize;
        if (0..n).contains(&i) {
            return Some(i as usize);
        }
        let j = match self {
            Border::Nearest => i.clamp(0, n - 1),
            Border::Wrap => i.rem_euclid(n),
            Border::Reflect => {
                let j = i.rem_euclid(2 * n);
                if j < n { j } else { 2 * n - 1 - j }
            }
            Border::Mirror if n == 1 => 0,
            Border::Mirror => {
                let j = i.rem_euclid(2 * n - 2);
                if j < n { j } else { 2 * n - 2 - j }
            }
            Border::Constant(_) => return None,
        };
        Some(j as usize)
    }

    /// `line` extended by `before` samples on the left and `after` on the right.
    fn pad(self, line: &[f64], before: usize, after: usize) -> Vec<f64> {
        let n = line.len();
        (-(before as isize)..(n + after) as isize)
            .map(|i| match self.index(i, n) {
                Some(j) => line[j],
                None => {
                    if let Border::Constant(k) = self {
                        k
                    } else {
                        unreachable!()
                    }
                }
            })
            .collect()
    }
}

/// NumPy's `np.sum` of a contiguous 1-D float64 array: pairwise summation with 8 accumulators per
/// block of ≤ 128 (sequential below 8). Kernels normalised this way match the reference to the
/// last bit, which matters where flat image regions truncate to `u8`.
pub fn numpy_sum(a: &[f64]) -> f64 {
    let n = a.len();
    if n < 8 {
        return a.iter().fold(0.0, |s, &v| s + v);
    }
    if n <= 128 {
        let mut r: [f64; 8] = a[..8].try_into().unwrap();
        let full = n - n % 8;
        for block in a[8..full].chunks_exact(8) {
            for (acc, v) in r.iter_mut().zip(block) {
                *acc += v;
            }
        }
        let head = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        return a[full..].iter().fold(head, |s, &v| s + v);
    }
    let half = n / 2 - (n / 2) % 8;
    numpy_sum(&a[..half]) + numpy_sum(&a[half..])
}

/// `scipy.ndimage` Gaussian weights: radius `int(truncate * sigma + 0.5)`, normalised to sum 1.
pub fn gaussian_kernel1d(sigma: f64, truncate: f64) -> Vec<f64> {
    let radius = (truncate * sigma + 0.5) as i64;
    let scale = -0.5 / (sigma * sigma);
    let phi: Vec<f64> = (-radius..=radius).map(|x| (scale * (x * x) as f64).exp()).collect();
    let sum = numpy_sum(&phi);
    phi.iter().map(|v| v / sum).collect()
}

/// Which axis a 1-D filter runs along.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Axis {
    /// Down the columns (NumPy axis 0).
    Rows,
    /// Along each row (NumPy axis 1).
    Cols,
}

/// `scipy.ndimage.correlate1d`: `out[i] = Σ_j w[j] · in[i + j − len/2]`. An odd symmetric kernel
/// is summed as SciPy does, centre first and then the pairs from the outside in.
pub fn correlate1d(plane: &Plane, weights: &[f64], axis: Axis, border: Border) -> Plane {
    match axis {
        Axis::Cols => correlate_rows(plane, weights, border),
        Axis::Rows => correlate_rows(&plane.transpose(), weights, border).transpose(),
    }
}

fn correlate_rows(plane: &Plane, weights: &[f64], border: Border) -> Plane {
    let size = weights.len();
    let (before, after) = (size / 2, size - size / 2 - 1);
    let symmetric = size % 2 == 1 && (0..size).all(|j| weights[j] == weights[size - 1 - j]);
    let mut out = Plane::new(plane.width, plane.height);
    for (row, dst) in plane.data.chunks_exact(plane.width).zip(out.data.chunks_exact_mut(plane.width)) {
        let line = border.pad(row, before, after);
        for (i, d) in dst.iter_mut().enumerate() {
            let win = &line[i..i + size];
            *d = if symmetric {
                let c = before;
                (1..=c).rev().fold(win[c] * weights[c], |acc, k| acc + (win[c - k] + win[c + k]) * weights[c - k])
            } else {
                let last = win[size - 1] * weights[size - 1];
                (0..size - 1).fold(last, |acc, j| acc + win[j] * weights[j])
            };
        }
    }
    out
}

/// `scipy.ndimage.gaussian_filter` with per-axis sigmas `(sigma_rows, sigma_cols)` (axis 0 is
/// filtered first; a zero sigma skips its axis).
pub fn gaussian_filter(plane: &Plane, sigma: (f64, f64), truncate: f64, border: Border) -> Plane {
    let mut out = plane.clone();
    for (s, axis) in [(sigma.0, Axis::Rows), (sigma.1, Axis::Cols)] {
        if s > 1e-15 {
            out = correlate1d(&out, &gaussian_kernel1d(s, truncate), axis, border);
        }
    }
    out
}

/// `skimage.filters.gaussian(x, sigma)` with its defaults (`mode='nearest'`, `truncate=4.0`), per
/// channel as with `channel_axis=-1`.
pub fn skimage_gaussian(plane: &Plane, sigma: f64) -> Plane {
    gaussian_filter(plane, (sigma, sigma), 4.0, Border::Nearest)
}

/// `cv2.filter2D(x, -1, kernel)`: correlation with the kernel anchored at its centre. OpenCV's
/// default border is `Border::Mirror` (`BORDER_REFLECT_101`).
pub fn filter2d(plane: &Plane, kernel: &Plane, border: Border) -> Plane {
    let (kw, kh) = (kernel.width, kernel.height);
    let (ax, ay) = (kw / 2, kh / 2);
    let padded = pad2d(plane, (ax, kw - ax - 1), (ay, kh - ay - 1), border);
    // Only non-zero taps: disk kernels are mostly zeros at small radii.
    let taps: Vec<(usize, usize, f64)> = (0..kh)
        .flat_map(|y| (0..kw).map(move |x| (x, y)))
        .map(|(x, y)| (x, y, kernel.get(x, y)))
        .filter(|t| t.2 != 0.0)
        .collect();
    let mut out = Plane::new(plane.width, plane.height);
    // Tap-major over whole rows so the inner loop vectorises; each output sample still adds the
    // taps in kernel order.
    for (y, dst) in out.data.chunks_exact_mut(plane.width).enumerate() {
        for &(kx, ky, w) in &taps {
            let start = (y + ky) * padded.width + kx;
            for (d, &v) in dst.iter_mut().zip(&padded.data[start..start + plane.width]) {
                *d += v * w;
            }
        }
    }
    out
}

/// `plane` extended by `(left, right)` columns and `(top, bottom)` rows read through `border`.
fn pad2d(plane: &Plane, cols: (usize, usize), rows: (usize, usize), border: Border) -> Plane {
    let wide = Plane::from_fn(plane.width + cols.0 + cols.1, plane.height, |x, y| {
        fetch(plane, x as isize - cols.0 as isize, y as isize, border)
    });
    Plane::from_fn(wide.width, plane.height + rows.0 + rows.1, |x, y| {
        fetch(&wide, x as isize, y as isize - rows.0 as isize, border)
    })
}

/// The sample at (x, y), read through `border` when outside.
pub fn fetch(plane: &Plane, x: isize, y: isize, border: Border) -> f64 {
    match (border.index(x, plane.width), border.index(y, plane.height)) {
        (Some(x), Some(y)) => plane.get(x, y),
        _ => {
            if let Border::Constant(k) = border {
                k
            } else {
                unreachable!()
            }
        }
    }
}

/// `cv2.getGaussianKernel(ksize, sigma)` for `sigma > 0`, as the `f32` OpenCV stores it.
pub fn cv_gaussian_kernel(ksize: usize, sigma: f64) -> Vec<f64> {
    let scale = -0.5 / (sigma * sigma);
    let mid = (ksize as f64 - 1.0) * 0.5;
    let t: Vec<f64> = (0..ksize).map(|i| (scale * (i as f64 - mid).powi(2)).exp()).collect();
    let sum: f64 = t.iter().sum();
    t.iter().map(|v| (v / sum) as f32 as f64).collect()
}

/// `cv2.GaussianBlur(x, (ksize, ksize), sigma)`: separable, `BORDER_REFLECT_101`.
pub fn cv_gaussian_blur(plane: &Plane, ksize: usize, sigma: f64) -> Plane {
    let k = cv_gaussian_kernel(ksize, sigma);
    let horizontal = correlate1d(plane, &k, Axis::Cols, Border::Mirror);
    correlate1d(&horizontal, &k, Axis::Rows, Border::Mirror)
}

/// `scipy.ndimage.zoom(x, ..., order=1)` to an explicit output size: output sample `o` reads
/// input coordinate `o · (n_in − 1) / (n_out − 1)` (SciPy's default `grid_mode=False`), linearly
/// interpolated.
pub fn zoom_linear(plane: &Plane, out_width: usize, out_height: usize) -> Plane {
    let xs = linear_taps(plane.width, out_width);
    let ys = linear_taps(plane.height, out_height);
    Plane::from_fn(out_width, out_height, |x, y| {
        let (x0, wx) = xs[x];
        let (y0, wy) = ys[y];
        let mut acc = 0.0;
        for (dy, wy) in wy.iter().enumerate() {
            for (dx, wx) in wx.iter().enumerate() {
                let v = plane.get((x0 + dx).min(plane.width - 1), (y0 + dy).min(plane.height - 1));
                acc += v * wy * wx;
            }
        }
        acc
    })
}

/// Per output index: the first input index and the two linear (order-1 spline) weights, computed
/// as SciPy's `spline_coefficients` does.
fn linear_taps(n_in: usize, n_out: usize) -> Vec<(usize, [f64; 2])> {
    let zoom = if n_out > 1 { (n_in as f64 - 1.0) / (n_out as f64 - 1.0) } else { 0.0 };
    (0..n_out)
        .map(|o| {
            let c = (o as f64 * zoom).min(n_in as f64 - 1.0);
            let start = c.floor();
            let w = |h: f64| {
                let y = (start - c + h).abs();
                if y > 1.0 { 0.0 } else { 1.0 - y }
            };
            (start as usize, [w(0.0), w(1.0)])
        })
        .collect()
}

/// `scipy.ndimage.zoom(x, factor, order=1)`: output size `round(n · factor)` (Python's
/// round-half-even).
pub fn scipy_zoom(plane: &Plane, factor: f64) -> Plane {
    let size = |n: usize| (n as f64 * factor).round_ties_even() as usize;
    zoom_linear(plane, size(plane.width), size(plane.height))
}

/// The reference's `clipped_zoom`: crop the centre `ceil(n / factor)` samples of each axis and
/// zoom them by `factor`. The result can be a little larger or smaller than the input; callers
/// crop it (`[:h, :w]`) as the reference does.
pub fn clipped_zoom(plane: &Plane, factor: f64) -> Plane {
    let side = |n: usize| {
        let c = (n as f64 / factor).ceil() as usize;
        ((n - c) / 2, c)
    };
    let (x0, w) = side(plane.width);
    let (y0, h) = side(plane.height);
    scipy_zoom(&plane.crop(x0, y0, w, h), factor)
}

/// Bilinear sample at fractional (x, y); the four neighbours are read through `border`.
/// Matches `scipy.ndimage.map_coordinates(order=1)` inside the image; outside it, SciPy folds the
/// coordinate itself before interpolating, which this does not.
pub fn sample_bilinear(plane: &Plane, x: f64, y: f64, border: Border) -> f64 {
    let (x0, y0) = (x.floor(), y.floor());
    let (tx, ty) = (x - x0, y - y0);
    let (x0, y0) = (x0 as isize, y0 as isize);
    let at = |dx: isize, dy: isize| fetch(plane, x0 + dx, y0 + dy, border);
    let top = at(0, 0) * (1.0 - tx) + at(1, 0) * tx;
    let bottom = at(0, 1) * (1.0 - tx) + at(1, 1) * tx;
    top * (1.0 - ty) + bottom * ty
}

/// The reference's `_motion_blur(x, radius, sigma, angle)`: a one-sided Gaussian of
/// `2·radius + 1` taps along direction `angle_deg`, each tap a copy of the image shifted with
/// edge replication. Taps stop once a shift would leave the image, as in the reference.
pub fn motion_blur(plane: &Plane, radius: usize, sigma: f64, angle_deg: f64) -> Plane {
    let width = 2 * radius + 1;
    let kernel = motion_kernel(width, sigma);
    let angle = angle_deg.to_radians();
    let point = (width as f64 * angle.sin(), width as f64 * angle.cos());
    let hypot = point.0.hypot(point.1);
    let (w, h) = (plane.width as isize, plane.height as isize);
    let mut out = Plane::new(plane.width, plane.height);
    for (i, k) in kernel.iter().enumerate() {
        let dy = -((i as f64 * point.0) / hypot - 0.5).ceil() as isize;
        let dx = -((i as f64 * point.1) / hypot - 0.5).ceil() as isize;
        if dy.abs() >= h || dx.abs() >= w {
            break;
        }
        for y in 0..h {
            let sy = (y - dy).clamp(0, h - 1) as usize;
            for x in 0..w {
                let sx = (x - dx).clamp(0, w - 1) as usize;
                out.data[(y * w + x) as usize] += k * plane.get(sx, sy);
            }
        }
    }
    out
}

/// `gauss_function(arange(width), 0, sigma)` normalised to sum 1.
fn motion_kernel(width: usize, sigma: f64) -> Vec<f64> {
    let norm = (2.0 * std::f64::consts::PI).sqrt() * sigma;
    let k: Vec<f64> = (0..width).map(|x| (-((x * x) as f64) / (2.0 * sigma * sigma)).exp() / norm).collect();
    let sum = numpy_sum(&k);
    k.iter().map(|v| v / sum).collect()
}
