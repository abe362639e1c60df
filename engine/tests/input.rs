//! Service input: crop boxes, padding with the ImageNet mean, antialiased resizing, and the way
//! back from crop pixels to image pixels.
#![allow(clippy::needless_range_loop)] // pixel loops read best with indices

use udapose_engine::backbone::IMAGENET_MEAN;
use udapose_engine::input::{BOX_FILL, CropBox, Rgb8Image, crop, crop_box};
use udapose_engine::mesh::Cuboid;
use udapose_engine::{Camera, Pose, View};

fn pattern(width: usize, height: usize) -> Vec<u8> {
    (0..width * height * 3).map(|i| (i * 37 % 251) as u8).collect()
}

fn at(pixels: &[f32], size: [usize; 2], c: usize, row: usize, col: usize) -> f32 {
    pixels[c * size[0] * size[1] + row * size[1] + col]
}

#[test]
fn an_image_of_the_crop_size_passes_through_bit_for_bit() {
    let (w, h) = (160, 64);
    let raw = pattern(w, h);
    let out = crop(&Rgb8Image::new(&raw, w, h).unwrap(), None, [h, w]).unwrap();
    assert_eq!(out.crop_box, CropBox { x0: 0.0, y0: 0.0, x1: 160.0, y1: 64.0 });
    for (i, p) in raw.chunks(3).enumerate() {
        for c in 0..3 {
            // Exactly what the training and eval loaders compute.
            assert_eq!(at(&out.pixels, [h, w], c, i / w, i % w), p[c] as f32 / 255.0);
        }
    }
    assert_eq!(out.tensor().size(), [1, 3, 64, 160]);
}

#[test]
fn a_square_image_is_padded_symmetrically_with_the_imagenet_mean() {
    // 100×100 into 64×160 (aspect 2.5): the region is 250×100, 75 px of padding each side,
    // i.e. 48 crop columns of 1.5625 image px.
    let raw = vec![200u8; 100 * 100 * 3];
    let out = crop(&Rgb8Image::new(&raw, 100, 100).unwrap(), None, [64, 160]).unwrap();
    assert_eq!(out.crop_box, CropBox { x0: -75.0, y0: 0.0, x1: 175.0, y1: 100.0 });
    for row in [0, 31, 63] {
        for c in 0..3 {
            for col in (0..46).chain(114..160) {
                let v = at(&out.pixels, [64, 160], c, row, col);
                assert!((f64::from(v) - IMAGENET_MEAN[c]).abs() < 1e-6, "pad at ({row}, {col}): {v}");
            }
            for col in 50..110 {
                assert_eq!(at(&out.pixels, [64, 160], c, row, col), 200.0 / 255.0, "image at ({row}, {col})");
            }
        }
    }
    // Symmetric: the left and right borders mirror each other.
    for col in 40..56 {
        let (l, r) = (at(&out.pixels, [64, 160], 0, 10, col), at(&out.pixels, [64, 160], 0, 10, 159 - col));
        assert!((l - r).abs() < 1e-6, "column {col}: {l} vs {r}");
    }
}

#[test]
fn a_box_is_grown_to_the_aspect_ratio_and_the_benchmark_fill() {
    // 20×16 box, centre (30, 18): grown to 40×16 (aspect 2.5), then by 1/0.875.
    let b = CropBox { x0: 20.0, y0: 10.0, x1: 40.0, y1: 26.0 };
    let region = crop_box(200, 100, Some(b), [64, 160]).unwrap();
    let (w, h) = (40.0 / BOX_FILL, 16.0 / BOX_FILL);
    let expected = CropBox { x0: 30.0 - w / 2.0, y0: 18.0 - h / 2.0, x1: 30.0 + w / 2.0, y1: 18.0 + h / 2.0 };
    for (got, want) in
        [region.x0, region.y0, region.x1, region.y1].iter().zip([expected.x0, expected.y0, expected.x1, expected.y1])
    {
        assert!((got - want).abs() < 1e-12, "{region:?} vs {expected:?}");
    }
    // A tall box grows in width.
    let tall = crop_box(200, 100, Some(CropBox { x0: 90.0, y0: 0.0, x1: 110.0, y1: 100.0 }), [64, 160]).unwrap();
    assert!((tall.width() - 250.0 / BOX_FILL).abs() < 1e-9 && (tall.height() - 100.0 / BOX_FILL).abs() < 1e-9);
}

#[test]
fn the_crop_shows_the_box_content() {
    // Left half dark, right half bright; a box on the bright half gives a bright crop centre.
    let (w, h) = (400, 200);
    let raw: Vec<u8> = (0..w * h).flat_map(|i| if i % w < 200 { [10u8; 3] } else { [250u8; 3] }).collect();
    let image = Rgb8Image::new(&raw, w, h).unwrap();
    let out = crop(&image, Some(CropBox { x0: 260.0, y0: 60.0, x1: 340.0, y1: 140.0 }), [64, 160]).unwrap();
    assert_eq!(at(&out.pixels, [64, 160], 1, 32, 80), 250.0 / 255.0);
    let out = crop(&image, Some(CropBox { x0: 20.0, y0: 60.0, x1: 100.0, y1: 140.0 }), [64, 160]).unwrap();
    assert_eq!(at(&out.pixels, [64, 160], 1, 32, 80), 10.0 / 255.0);
}

#[test]
fn downscaling_is_antialiased() {
    // A one-pixel checkerboard shrunk 4× averages to grey instead of aliasing to black or white.
    let (w, h) = (640, 256);
    let raw: Vec<u8> = (0..w * h).flat_map(|i| if (i % w + i / w) % 2 == 0 { [0u8; 3] } else { [255u8; 3] }).collect();
    let out = crop(&Rgb8Image::new(&raw, w, h).unwrap(), None, [64, 160]).unwrap();
    for row in 2..62 {
        for col in 2..158 {
            let v = at(&out.pixels, [64, 160], 0, row, col);
            assert!((v - 0.5).abs() < 0.02, "({row}, {col}): {v}");
        }
    }
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let raw = pattern(1, 1);
    let err = crop(&Rgb8Image::new(&raw, 1, 1).unwrap(), None, [64, 160]).unwrap_err();
    assert!(err.to_string().contains("image is 1x1 px"), "{err}");
    assert!(Rgb8Image::new(&[0u8; 10], 2, 2).is_err());
    assert!(Rgb8Image::new(&[], 0, 5).is_err());
    let raw = pattern(100, 50);
    let image = Rgb8Image::new(&raw, 100, 50).unwrap();
    for (b, what) in [
        (CropBox { x0: -1.0, y0: 0.0, x1: 10.0, y1: 10.0 }, "leaves"),
        (CropBox { x0: 0.0, y0: 0.0, x1: 101.0, y1: 10.0 }, "leaves"),
        (CropBox { x0: f64::NAN, y0: 0.0, x1: 10.0, y1: 10.0 }, "non-finite"),
        (CropBox { x0: 5.0, y0: 5.0, x1: 6.0, y1: 40.0 }, "smaller"),
        (CropBox { x0: 20.0, y0: 5.0, x1: 10.0, y1: 40.0 }, "smaller"),
    ] {
        let err = crop(&image, Some(b), [64, 160]).unwrap_err();
        assert!(err.to_string().contains(what), "{b:?}: {err}");
    }
}

#[test]
fn cuboid_corners_map_back_through_the_crop() {
    let cuboid = Cuboid { min: [-0.2, -0.5, -0.15], max: [0.2, 0.5, 0.12] };
    let pose = Pose::new(0.7, 0.2, -0.1, 6.0);
    let view = View::new(&Camera::for_crop(64, 160).unwrap(), &pose).unwrap();
    let corner = |i: usize| {
        [
            if i & 1 == 1 { 0.2 } else { -0.2 },
            if i & 2 == 2 { 0.5 } else { -0.5 },
            if i & 4 == 4 { 0.12 } else { -0.15 },
        ]
    };
    // Identity crop: image pixels are crop pixels.
    let raw = pattern(160, 64);
    let same = crop(&Rgb8Image::new(&raw, 160, 64).unwrap(), None, [64, 160]).unwrap();
    let corners = same.project_cuboid(&cuboid, &pose).unwrap();
    for (i, c) in corners.iter().enumerate() {
        let [col, row, _] = view.project(corner(i));
        assert!((c[0] - col).abs() < 1e-9 && (c[1] - row).abs() < 1e-9, "corner {i}: {c:?} vs {col}, {row}");
    }
    // A 2× larger image: every corner lands at twice the coordinates.
    let raw = pattern(320, 128);
    let double = crop(&Rgb8Image::new(&raw, 320, 128).unwrap(), None, [64, 160]).unwrap();
    for (a, b) in double.project_cuboid(&cuboid, &pose).unwrap().iter().zip(&corners) {
        assert!((a[0] - 2.0 * b[0]).abs() < 1e-9 && (a[1] - 2.0 * b[1]).abs() < 1e-9);
    }
}
