//! Service input: crop boxes, padding with the ImageNet mean, antialiased resizing, and the way
//! back from crop pixels to image pixels.
#![allow(clippy::needless_range_loop)] // pixel loops read best with indices

use udapose_engine::backbone::IMAGENET_MEAN;
use udapose_engine::input::{BOX_FILL, CropBox, Rgb8Image, crop, crop_box, max_reduction, reduce};
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

#[test]
fn the_reduction_keeps_every_region_at_least_the_crops_size() {
    let crop = [128, 320];
    let b = |x0: f64, y0: f64, x1: f64, y1: f64| CropBox { x0, y0, x1, y1 };
    // 4000×3000 padded to the crop's 2.5:1 is 7500×3000: 1/8 leaves 937×375.
    assert_eq!(max_reduction(4000, 3000, &[], crop), 8);
    // A 1120×448 box grows by 1/0.875 to 1280×512: 1/4 leaves exactly 320×128.
    assert_eq!(max_reduction(4000, 3000, &[b(100.0, 100.0, 1220.0, 548.0)], crop), 4);
    assert_eq!(max_reduction(4000, 3000, &[b(100.0, 100.0, 1219.0, 540.0)], crop), 2, "1278.9×511.5 after growing");
    let small = b(0.0, 0.0, 100.0, 40.0);
    assert_eq!(max_reduction(4000, 3000, &[b(0.0, 0.0, 4000.0, 3000.0), small], crop), 1, "the smallest box decides");
    assert_eq!(max_reduction(4000, 3000, &[b(0.0, 0.0, 4001.0, 100.0)], crop), 1, "a bad box: no reduction");
    assert_eq!(max_reduction(320, 128, &[], crop), 1);
}

#[test]
fn a_reduced_decode_is_cropped_in_the_encoded_images_pixels() {
    // A smooth 1280×512 image and its 2×2 block means (what a JPEG decoded at 1/2 approximates).
    let (w, h) = (1280, 512);
    let value =
        |x: usize, y: usize, c: usize| 128.0 + 100.0 * ((x as f64 / 40.0 + c as f64).sin() * (y as f64 / 30.0).cos());
    let full: Vec<u8> = (0..w * h * 3).map(|i| value(i / 3 % w, i / 3 / w, i % 3) as u8).collect();
    let half: Vec<u8> = (0..w / 2 * h / 2 * 3)
        .map(|i| {
            let (x, y, c) = (i / 3 % (w / 2), i / 3 / (w / 2), i % 3);
            let sum: u32 = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .map(|(dx, dy)| u32::from(full[((2 * y + dy) * w + 2 * x + dx) * 3 + c]))
                .sum();
            (sum as f64 / 4.0).round() as u8
        })
        .collect();
    let full_image = Rgb8Image::new(&full, w, h).unwrap();
    assert_eq!(reduce(&full_image, 2).unwrap(), (half.clone(), w / 2, h / 2), "reduce gives the rounded block means");
    let half_image = Rgb8Image::new(&half, w / 2, h / 2).unwrap().decoded_from(w, h).unwrap();
    for bbox in [None, Some(CropBox { x0: 301.0, y0: 77.0, x1: 901.0, y1: 407.5 })] {
        let a = crop(&full_image, bbox, [64, 160]).unwrap();
        let b = crop(&half_image, bbox, [64, 160]).unwrap();
        assert_eq!(a.crop_box, b.crop_box, "the crop box is in the encoded image's pixels");
        let diff = a.pixels.iter().zip(&b.pixels).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
        assert!(diff < 3.0 / 255.0, "{bbox:?}: max |full − reduced| = {:.2}/255", diff * 255.0);
    }
    // Boxes are checked against the encoded size, not the stored one.
    let err = crop(&half_image, Some(CropBox { x0: 0.0, y0: 0.0, x1: 1281.0, y1: 100.0 }), [64, 160]).unwrap_err();
    assert!(err.to_string().contains("leaves the 1280x512 image"), "{err}");
    assert!(crop(&half_image, Some(CropBox { x0: 700.0, y0: 0.0, x1: 1280.0, y1: 512.0 }), [64, 160]).is_ok());
    // Only a reduction of at most 8 per side, never an enlargement.
    assert!(Rgb8Image::new(&half, w / 2, h / 2).unwrap().decoded_from(w / 2 - 1, h / 2).is_err());
    assert!(Rgb8Image::new(&half, w / 2, h / 2).unwrap().decoded_from(8 * w, h).is_err());
}

#[test]
fn reduce_averages_partial_blocks_at_the_edges() {
    // 7×5 by 4: blocks of 4×4, 3×4, 4×1 and 3×1 pixels.
    let (w, h) = (7, 5);
    let raw: Vec<u8> = (0..w * h * 3).map(|i| (i / 3 % w * 10 + i / 3 / w * 40 + i % 3) as u8).collect();
    let (out, rw, rh) = reduce(&Rgb8Image::new(&raw, w, h).unwrap(), 4).unwrap();
    assert_eq!((rw, rh), (2, 2));
    let pixels = &raw;
    let mean = |xs: std::ops::Range<usize>, ys: std::ops::Range<usize>, c: usize| {
        let v: Vec<f64> = ys.flat_map(|y| xs.clone().map(move |x| pixels[(y * w + x) * 3 + c] as f64)).collect();
        (v.iter().sum::<f64>() / v.len() as f64).round() as u8
    };
    for c in 0..3 {
        assert_eq!(out[c], mean(0..4, 0..4, c));
        assert_eq!(out[3 + c], mean(4..7, 0..4, c));
        assert_eq!(out[6 + c], mean(0..4, 4..5, c));
        assert_eq!(out[9 + c], mean(4..7, 4..5, c));
    }
    let image = Rgb8Image::new(&raw, w, h).unwrap();
    assert_eq!(reduce(&image, 1).unwrap(), (raw.clone(), w, h));
    assert!(reduce(&image, 0).is_err() && reduce(&image, 9).is_err());
}
