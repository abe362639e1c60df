//! Contact sheets of samples with the ground-truth cuboid drawn on top: the end-to-end check of
//! the camera convention (the box must sit on the car).

use image::{Rgb, RgbImage};
use udapose_engine::{Camera, Cuboid, Pose, View};

/// Draws the 12 edges of `cuboid` seen from `pose` onto `img` (a crop with its centre as
/// principal point).
pub fn draw_cuboid(img: &mut RgbImage, cuboid: &Cuboid, pose: &Pose, colour: [u8; 3]) {
    let Some(view) = crop_view(img, pose) else { return };
    let corner =
        |i: usize| -> [f64; 3] { std::array::from_fn(|a| if i >> a & 1 == 1 { cuboid.max[a] } else { cuboid.min[a] }) };
    for i in 0..8 {
        for a in 0..3 {
            let j = i | 1 << a;
            if j != i {
                let (p, q) = (view.project(corner(i)), view.project(corner(j)));
                draw_line(img, [p[0], p[1]], [q[0], q[1]], colour);
            }
        }
    }
}

/// The segment between two object-frame points seen from `pose`.
pub fn draw_segment(img: &mut RgbImage, a: [f64; 3], b: [f64; 3], pose: &Pose, colour: [u8; 3]) {
    let Some(view) = crop_view(img, pose) else { return };
    let (p, q) = (view.project(a), view.project(b));
    draw_line(img, [p[0], p[1]], [q[0], q[1]], colour);
}

/// The view of `pose` through the crop camera of `img`'s size (none for a degenerate pose).
fn crop_view(img: &RgbImage, pose: &Pose) -> Option<View> {
    let camera = Camera::for_crop(img.height() as usize, img.width() as usize).ok()?;
    View::new(&camera, pose).ok()
}

/// A line between continuous pixel coordinates, clipped to the image.
pub fn draw_line(img: &mut RgbImage, a: [f64; 2], b: [f64; 2], colour: [u8; 3]) {
    let steps = ((b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil() as usize).clamp(1, 1 << 14);
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
        if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
            img.put_pixel(x as u32, y as u32, Rgb(colour));
        }
    }
}

/// Tiles equally sized images into a grid `columns` wide with a 2-pixel gutter.
pub fn contact_sheet(images: &[RgbImage], columns: usize) -> RgbImage {
    let Some(first) = images.first() else { return RgbImage::new(1, 1) };
    let (w, h, gap) = (first.width(), first.height(), 2);
    let columns = columns.clamp(1, images.len()) as u32;
    let rows = (images.len() as u32).div_ceil(columns);
    let mut sheet = RgbImage::from_pixel(columns * (w + gap) + gap, rows * (h + gap) + gap, Rgb([255, 255, 255]));
    for (k, img) in images.iter().enumerate() {
        let (c, r) = (k as u32 % columns, k as u32 / columns);
        image::imageops::replace(&mut sheet, img, (gap + c * (w + gap)) as i64, (gap + r * (h + gap)) as i64);
    }
    sheet
}
