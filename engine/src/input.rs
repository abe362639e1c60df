//! Service input (ARCHITECTURE.md "Service input"): from a decoded RGB8 image and an optional
//! detection box to the model's `H×W` crop, and from the crop back to image pixels.
//!
//! With no box the image *is* the crop: it is padded symmetrically to the model's aspect ratio
//! and resized. A box is grown to the aspect ratio, then by `1 / BOX_FILL` about its centre, and
//! cut from the image. Where the crop leaves the image it is filled with the ImageNet mean, i.e.
//! zeros after normalisation. Resampling is separable with a triangle filter whose support
//! widens when downscaling (antialiased, as PIL and torchvision do), so an image that already
//! has the crop's size passes through bit for bit. Decoding image files is the caller's job.

use tch::Tensor;

use crate::backbone::IMAGENET_MEAN;
use crate::camera::{Camera, Pose, View};
use crate::error::{EngineError, Result};
use crate::mesh::Cuboid;

/// The benchmark's mean fill of a detection box within its crop (BENCHMARK.md §2).
pub const BOX_FILL: f64 = 0.875;
/// Smallest image side (pixels) an estimate can be asked of: below it there is nothing to see.
pub const MIN_IMAGE_SIDE: usize = 16;
/// Smallest box side (pixels).
pub const MIN_BOX_SIDE: f64 = 2.0;
/// Largest size reduction of a decode ([`max_reduction`]): JPEG's DCT scales by 1/2, 1/4, 1/8.
pub const MAX_REDUCTION: u32 = 8;

/// An axis-aligned box in continuous image coordinates (`x` = column, `y` = row).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CropBox {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

impl CropBox {
    pub fn width(&self) -> f64 {
        self.x1 - self.x0
    }

    pub fn height(&self) -> f64 {
        self.y1 - self.y0
    }

    /// The box about the same centre with the aspect ratio `width / height = aspect`, grown
    /// (never shrunk) along one axis, then scaled by `scale`.
    fn grown(&self, aspect: f64, scale: f64) -> CropBox {
        let (mut w, mut h) = (self.width(), self.height());
        if w / h < aspect {
            w = h * aspect;
        } else {
            h = w / aspect;
        }
        let (cx, cy) = ((self.x0 + self.x1) / 2.0, (self.y0 + self.y1) / 2.0);
        let (hw, hh) = (w * scale / 2.0, h * scale / 2.0);
        CropBox { x0: cx - hw, y0: cy - hh, x1: cx + hw, y1: cy + hh }
    }
}

/// Packed RGB8 pixels, row-major (`width * height * 3` bytes), as `image::RgbImage::as_raw`,
/// and the size of the image they were decoded from: a JPEG may be decoded at a fraction of its
/// size ([`max_reduction`]), while boxes and crop boxes stay in the encoded image's pixels.
#[derive(Clone, Copy, Debug)]
pub struct Rgb8Image<'a> {
    pixels: &'a [u8],
    width: usize,
    height: usize,
    /// `[width, height]` of the encoded image (the pixels' own size unless decoded reduced).
    encoded: [usize; 2],
}

impl<'a> Rgb8Image<'a> {
    pub fn new(pixels: &'a [u8], width: usize, height: usize) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(EngineError::EmptyImage { width, height });
        }
        let expected = width.checked_mul(height).and_then(|n| n.checked_mul(3));
        if expected != Some(pixels.len()) {
            return Err(EngineError::InvalidInput(format!(
                "{} bytes for a {width}x{height} RGB8 image (expected {})",
                pixels.len(),
                width.saturating_mul(height).saturating_mul(3)
            )));
        }
        Ok(Rgb8Image { pixels, width, height, encoded: [width, height] })
    }

    /// These pixels as a reduced decode of a `width × height` image (at most 8× larger per
    /// side, never smaller): crops are then asked for, and answered, in that image's pixels.
    pub fn decoded_from(self, width: usize, height: usize) -> Result<Self> {
        let fits = |encoded: usize, stored: usize| encoded >= stored && encoded <= stored * MAX_REDUCTION as usize;
        if !(fits(width, self.width) && fits(height, self.height)) {
            return Err(EngineError::InvalidInput(format!(
                "{}x{} pixels are not a reduced decode of a {width}x{height} image",
                self.width, self.height
            )));
        }
        Ok(Rgb8Image { encoded: [width, height], ..self })
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }
}

/// The model's input for one box: planar RGB in [0, 1] (3×H×W) and where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct Crop {
    pub pixels: Vec<f32>,
    /// `[H, W]`, the model's crop size.
    pub size: [usize; 2],
    /// The region of the image the crop shows (may extend past the image).
    pub crop_box: CropBox,
}

impl Crop {
    /// The crop as the backbone takes it: 1×3×H×W, values in [0, 1], on the CPU.
    pub fn tensor(&self) -> Tensor {
        let [h, w] = self.size;
        Tensor::from_slice(&self.pixels).view([1, 3, h as i64, w as i64])
    }

    /// Image coordinates `(x, y)` of a crop pixel position `(col, row)`.
    pub fn to_image(&self, col: f64, row: f64) -> [f64; 2] {
        let [h, w] = self.size;
        let b = &self.crop_box;
        [b.x0 + col * b.width() / w as f64, b.y0 + row * b.height() / h as f64]
    }

    /// The 8 corners of `cuboid` seen from `pose` through the crop's camera (METHOD.md §2),
    /// in image coordinates `(x, y)`. Corner `i` has `x = max` if bit 0 of `i` is set, `y = max`
    /// if bit 1, `z = max` if bit 2 (so edges join corners that differ in one bit).
    pub fn project_cuboid(&self, cuboid: &Cuboid, pose: &Pose) -> Result<[[f64; 2]; 8]> {
        let [h, w] = self.size;
        let view = View::new(&Camera::for_crop(h, w)?, pose)?;
        let corner = |i: usize| {
            let pick = |bit: usize, axis: usize| if i >> bit & 1 == 1 { cuboid.max[axis] } else { cuboid.min[axis] };
            [pick(0, 0), pick(1, 1), pick(2, 2)]
        };
        Ok(std::array::from_fn(|i| {
            let [col, row, _] = view.project(corner(i));
            self.to_image(col, row)
        }))
    }
}

/// The region of a `width × height` image that becomes the crop of size `crop = [H, W]`:
/// the whole image padded to the aspect ratio when `bbox` is `None`, else the box grown to the
/// aspect ratio and by `1 / BOX_FILL`. A box must lie within the image and be at least
/// [`MIN_BOX_SIDE`] on each side.
pub fn crop_box(width: usize, height: usize, bbox: Option<CropBox>, crop: [usize; 2]) -> Result<CropBox> {
    let [ch, cw] = crop;
    if ch == 0 || cw == 0 {
        return Err(EngineError::EmptyImage { width: cw, height: ch });
    }
    let aspect = cw as f64 / ch as f64;
    let (w, h) = (width as f64, height as f64);
    match bbox {
        None => Ok(CropBox { x0: 0.0, y0: 0.0, x1: w, y1: h }.grown(aspect, 1.0)),
        Some(b) => {
            let coords = [b.x0, b.y0, b.x1, b.y1];
            if coords.iter().any(|c| !c.is_finite()) {
                return Err(EngineError::InvalidInput(format!("box {coords:?} has a non-finite coordinate")));
            }
            if b.x0 < 0.0 || b.y0 < 0.0 || b.x1 > w || b.y1 > h {
                return Err(EngineError::InvalidInput(format!(
                    // Debug: 1e300 prints as such, not as 301 digits.
                    "box ({:?}, {:?}, {:?}, {:?}) leaves the {width}x{height} image",
                    b.x0, b.y0, b.x1, b.y1
                )));
            }
            if b.width() < MIN_BOX_SIDE || b.height() < MIN_BOX_SIDE {
                return Err(EngineError::InvalidInput(format!(
                    "box ({:?}, {:?}, {:?}, {:?}) is smaller than {MIN_BOX_SIDE} px on a side",
                    b.x0, b.y0, b.x1, b.y1
                )));
            }
            Ok(b.grown(aspect, 1.0 / BOX_FILL))
        }
    }
}

/// The largest reduction `r` (8, 4 or 2; else 1) at which a `width × height` image may be
/// decoded for crops of `boxes` (none: the whole image) at the model's `crop = [H, W]`: every
/// region those crops show keeps at least `H × W` pixels after shrinking `r`-fold, so the crop
/// still downsamples and loses nothing it would have kept. 1 when a box is invalid: [`crop`]
/// then reports it in the image's own pixels.
pub fn max_reduction(width: usize, height: usize, boxes: &[CropBox], crop: [usize; 2]) -> u32 {
    let regions: Result<Vec<CropBox>> = if boxes.is_empty() {
        crop_box(width, height, None, crop).map(|r| vec![r])
    } else {
        boxes.iter().map(|&b| crop_box(width, height, Some(b), crop)).collect()
    };
    let Ok(regions) = regions else { return 1 };
    let [ch, cw] = crop.map(|c| c as f64);
    let fits = |r: f64| regions.iter().all(|b| b.width() / r >= cw && b.height() / r >= ch);
    [MAX_REDUCTION, 4, 2].into_iter().find(|&r| fits(f64::from(r))).unwrap_or(1)
}

/// `image` shrunk `r`-fold by block means (`r × r` pixels each, fewer at the right and bottom
/// edges; rounded): what a JPEG's DCT scaling approximates, for images decoded at full size.
/// Returns the pixels and their width and height, `ceil(w / r) × ceil(h / r)`; the result is a
/// reduced decode of `image` ([`Rgb8Image::decoded_from`] with its size).
pub fn reduce(image: &Rgb8Image, r: u32) -> Result<(Vec<u8>, usize, usize)> {
    if !(1..=MAX_REDUCTION).contains(&r) {
        return Err(EngineError::InvalidInput(format!("reduction {r} is not 1 to {MAX_REDUCTION}")));
    }
    let r = r as usize;
    let (w, h) = (image.width.div_ceil(r), image.height.div_ceil(r));
    let mut out = Vec::with_capacity(w * h * 3);
    let mut sums = vec![0u32; w * 3];
    for rows in image.pixels.chunks(image.width * 3 * r) {
        sums.iter_mut().for_each(|s| *s = 0);
        for row in rows.chunks_exact(image.width * 3) {
            for (sum, pixels) in sums.chunks_exact_mut(3).zip(row.chunks(3 * r)) {
                for px in pixels.chunks_exact(3) {
                    sum[0] += u32::from(px[0]);
                    sum[1] += u32::from(px[1]);
                    sum[2] += u32::from(px[2]);
                }
            }
        }
        let height = (rows.len() / (image.width * 3)) as u32;
        for (block, sum) in sums.chunks_exact(3).enumerate() {
            let n = height * (image.width - block * r).min(r) as u32;
            out.extend(sum.iter().map(|&s| ((s + n / 2) / n) as u8));
        }
    }
    Ok((out, w, h))
}

/// Cuts, pads and resizes `image` to the model's `crop = [H, W]` (see the module docs).
/// `bbox` and the crop's box are in the encoded image's pixels ([`Rgb8Image::decoded_from`]).
pub fn crop(image: &Rgb8Image, bbox: Option<CropBox>, crop: [usize; 2]) -> Result<Crop> {
    let [width, height] = image.encoded;
    if width < MIN_IMAGE_SIDE || height < MIN_IMAGE_SIDE {
        return Err(EngineError::InvalidInput(format!(
            "image is {width}x{height} px; at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} is needed"
        )));
    }
    let region = crop_box(width, height, bbox, crop)?;
    let [ch, cw] = crop;
    // Encoded to stored pixels: exactly 1 unless the image was decoded reduced.
    let (sx, sy) = (width as f64 / image.width as f64, height as f64 / image.height as f64);
    let cols = taps(region.x0 / sx, region.width() / sx, cw);
    let rows = taps(region.y0 / sy, region.height() / sy, ch);
    // Byte units until the end, so that an identity resize reproduces `p as f32 / 255.0`.
    let pad: [f64; 3] = std::array::from_fn(|c| IMAGENET_MEAN[c] * 255.0);
    let horizontal = resample_rows(image, &cols, &rows, pad);
    let plane = ch * cw;
    let mut pixels = vec![0f32; 3 * plane];
    let mut sums = vec![0f64; cw * 3];
    for (i, row_taps) in rows.iter().enumerate() {
        // Rows whose taps are all inside the image are summed a whole row at a time (each sum
        // gets the same terms in the same order as the general path below, so the same bits).
        if let Some(values) = horizontal.rows(row_taps.start, row_taps.weights.len()) {
            sums.fill(0.0);
            for (&wt, row) in row_taps.weights.iter().zip(values.chunks_exact(cw * 3)) {
                sums.iter_mut().zip(row).for_each(|(s, &v)| *s += wt * v);
            }
            for (j, sum) in sums.chunks_exact(3).enumerate() {
                for c in 0..3 {
                    pixels[c * plane + i * cw + j] = sum[c] as f32 / 255.0;
                }
            }
            continue;
        }
        for j in 0..cw {
            for (c, channel) in pad.iter().enumerate() {
                let mut v = 0.0;
                for (k, &wt) in row_taps.weights.iter().enumerate() {
                    let y = row_taps.start + k as isize;
                    v += wt * horizontal.get(y, j, c).unwrap_or(*channel);
                }
                pixels[c * plane + i * cw + j] = v as f32 / 255.0;
            }
        }
    }
    Ok(Crop { pixels, size: crop, crop_box: region })
}

/// One output sample's source taps: weights for source indices `start, start + 1, ...`
/// (indices may fall outside the image), summing to 1.
struct Taps {
    start: isize,
    weights: Vec<f64>,
}

/// Triangle-filter taps for resampling `[origin, origin + length)` of a source axis to `out`
/// samples; the filter's radius is the scale factor when downscaling, one pixel otherwise.
/// Taps stay within the region (as when cropping first, then resizing), so the padding never
/// bleeds into an image edge that is also the region's edge.
fn taps(origin: f64, length: f64, out: usize) -> Vec<Taps> {
    let scale = length / out as f64;
    let support = scale.max(1.0);
    let (first, last) = (origin.floor() as isize, (origin + length).ceil() as isize - 1);
    (0..out)
        .map(|j| {
            let centre = origin + (j as f64 + 0.5) * scale;
            let lo = ((centre - support - 0.5).floor() as isize).max(first);
            let hi = ((centre + support - 0.5).ceil() as isize).min(last);
            let mut weights: Vec<f64> =
                (lo..=hi).map(|k| (1.0 - ((k as f64 + 0.5 - centre) / support).abs()).max(0.0)).collect();
            let sum: f64 = weights.iter().sum();
            weights.iter_mut().for_each(|w| *w /= sum);
            Taps { start: lo, weights }
        })
        .collect()
}

/// The horizontal pass over the image rows that some output row reads: `rows[y][j][c]`.
struct Horizontal {
    first_row: isize,
    width: usize,
    values: Vec<f64>,
}

impl Horizontal {
    /// Rows `y .. y + n` of the pass, if all are inside the image.
    fn rows(&self, y: isize, n: usize) -> Option<&[f64]> {
        let r = usize::try_from(y - self.first_row).ok()?;
        self.values.get(r * self.width * 3..(r + n) * self.width * 3)
    }

    /// The resampled value at source row `y`, output column `j`; `None` outside the image.
    fn get(&self, y: isize, j: usize, c: usize) -> Option<f64> {
        let r = usize::try_from(y - self.first_row).ok()?;
        self.values.get((r * self.width + j) * 3 + c).copied()
    }
}

fn resample_rows(image: &Rgb8Image, cols: &[Taps], rows: &[Taps], pad: [f64; 3]) -> Horizontal {
    let height = image.height as isize;
    let needed = |t: &Taps| (t.start, t.start + t.weights.len() as isize);
    let first = rows.iter().map(|t| needed(t).0).min().unwrap_or(0).clamp(0, height);
    let last = rows.iter().map(|t| needed(t).1).max().unwrap_or(0).clamp(first, height);
    let width = cols.len();
    let mut values = Vec::with_capacity((last - first) as usize * width * 3);
    for y in first..last {
        let row = &image.pixels[y as usize * image.width * 3..(y as usize + 1) * image.width * 3];
        for t in cols {
            let mut v = [0.0f64; 3];
            // Taps inside the row (all but a padded edge's) skip the per-tap bounds test; the
            // sums are the same, term by term, as the general path's.
            let inside = usize::try_from(t.start).ok().filter(|&x| x + t.weights.len() <= image.width);
            if let Some(x) = inside {
                for (&wt, p) in t.weights.iter().zip(row[x * 3..].chunks_exact(3)) {
                    for c in 0..3 {
                        v[c] += wt * f64::from(p[c]);
                    }
                }
            } else {
                for (k, &wt) in t.weights.iter().enumerate() {
                    let x = t.start + k as isize;
                    let px = usize::try_from(x).ok().filter(|&x| x < image.width).map(|x| &row[x * 3..x * 3 + 3]);
                    for c in 0..3 {
                        v[c] += wt * px.map_or(pad[c], |p| f64::from(p[c]));
                    }
                }
            }
            values.extend_from_slice(&v);
        }
    }
    Horizontal { first_row: first, width, values }
}
