//! Weather (snow, frost, fog, spatter) and digital (brightness, contrast, saturate,
//! elastic_transform, pixelate, jpeg_compression) corruptions. The deterministic ones are checked
//! against values the reference package computed; pixel and statistic parity on photographs is
//! `lab/scripts/corruption_parity.py`.
//!
//! Only `frost_end_to_end` calls frost or touches the environment (frost reads
//! `UDAPOSE_FROST_DIR`, and environment variables are process-wide).

use image::{Rgb, RgbImage};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use udapose_lab::corruptions::{Corruption, CorruptionError};

/// Ours, less frost (see the module comment).
const OURS: [Corruption; 9] = [
    Corruption::Snow,
    Corruption::Fog,
    Corruption::Spatter,
    Corruption::Brightness,
    Corruption::Contrast,
    Corruption::Saturate,
    Corruption::ElasticTransform,
    Corruption::Pixelate,
    Corruption::JpegCompression,
];
const RANDOM: [Corruption; 4] = [Corruption::Snow, Corruption::Fog, Corruption::Spatter, Corruption::ElasticTransform];

/// A photo-like test card: gradients, hard-edged blocks, a little noise; no sample is black or
/// white, so every corruption has something to change.
fn test_image(width: u32, height: u32) -> RgbImage {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    RgbImage::from_fn(width, height, |x, y| {
        let block = ((x / 10 + y / 7) % 2) as f64 * 70.0;
        let wave = 25.0 * (x as f64 * 0.3).sin() * (y as f64 * 0.17).cos();
        let base = 60.0 + block + wave + rng.random_range(-6.0..6.0);
        let px = |shift: f64| (base + shift + 50.0 * x as f64 / width as f64) as u8;
        Rgb([px(10.0), px(-25.0 * y as f64 / height as f64), px(30.0)])
    })
}

/// The integer test pattern the reference values below were computed on (40×34: neither side a
/// multiple of 8 or 16, so JPEG's edge padding and pixelate's rounding are exercised).
fn pattern() -> RgbImage {
    RgbImage::from_fn(40, 34, |x, y| {
        Rgb([(x * 37 + y * 11) % 256, (x * x + 3 * y * y) % 256, (x * y * 5 + 60) % 256].map(|v| v as u8))
    })
}

fn corrupt(c: Corruption, image: &RgbImage, severity: u8, seed: u64) -> RgbImage {
    c.apply(image, severity, &mut ChaCha8Rng::seed_from_u64(seed)).unwrap()
}

fn mean_abs_diff(a: &RgbImage, b: &RgbImage) -> f64 {
    let sum: f64 = a.as_raw().iter().zip(b.as_raw()).map(|(&p, &q)| (f64::from(p) - f64::from(q)).abs()).sum();
    sum / a.as_raw().len() as f64
}

fn mean(image: &RgbImage) -> f64 {
    image.as_raw().iter().map(|&v| f64::from(v)).sum::<f64>() / image.as_raw().len() as f64
}

fn std(image: &RgbImage) -> f64 {
    let m = mean(image);
    (image.as_raw().iter().map(|&v| (f64::from(v) - m).powi(2)).sum::<f64>() / image.as_raw().len() as f64).sqrt()
}

/// Mean HSV saturation, (max − min) / max per pixel.
fn mean_saturation(image: &RgbImage) -> f64 {
    let s: f64 = image
        .pixels()
        .map(|p| {
            let (max, min) = (p.0.iter().max().copied().unwrap_or(0), p.0.iter().min().copied().unwrap_or(0));
            if max == 0 { 0.0 } else { f64::from(max - min) / f64::from(max) }
        })
        .sum();
    s / f64::from(image.width() * image.height())
}

#[test]
fn deterministic_ones_match_reference_values() {
    // corrupt(pattern, name, severity) from imagecorruptions-imaug 1.1.5: (sum of all bytes,
    // pixel (7, 5), pixel (39, 33)) for severities 1 to 5.
    type Expected = [(u64, [u8; 3], [u8; 3]); 5];
    let table: [(Corruption, Expected); 5] = [
        (
            Corruption::Brightness,
            [
                (573934, [62, 134, 255], [15, 205, 108]),
                (618422, [62, 134, 255], [17, 231, 121]),
                (648580, [62, 134, 255], [19, 255, 134]),
                (669353, [62, 134, 255], [19, 255, 134]),
                (682105, [62, 134, 255], [19, 255, 134]),
            ],
        ),
        (
            Corruption::Contrast,
            [
                (513963, [99, 124, 170], [81, 146, 114]),
                (513723, [106, 124, 159], [93, 141, 117]),
                (513921, [113, 124, 149], [104, 135, 121]),
                (513851, [120, 124, 138], [115, 129, 124]),
                (513842, [123, 124, 133], [121, 127, 126]),
            ],
        ),
        (
            Corruption::Saturate,
            [
                (692463, [181, 201, 235], [130, 180, 154]),
                (743273, [217, 223, 235], [163, 180, 171]),
                (418775, [0, 87, 235], [0, 180, 87]),
                (388867, [0, 87, 235], [0, 180, 87]),
                (385307, [0, 87, 235], [0, 180, 87]),
            ],
        ),
        (
            Corruption::Pixelate,
            [
                (517288, [64, 141, 125], [119, 173, 173]),
                (519672, [35, 105, 207], [119, 173, 173]),
                (518605, [89, 147, 155], [156, 162, 162]),
                (517442, [90, 130, 133], [165, 138, 138]),
                (519704, [116, 146, 148], [167, 133, 127]),
            ],
        ),
        (
            Corruption::JpegCompression,
            [
                (516966, [106, 101, 124], [97, 132, 90]),
                (516839, [118, 99, 127], [100, 143, 115]),
                (516041, [118, 95, 105], [112, 167, 127]),
                (516838, [103, 97, 101], [143, 186, 177]),
                (515277, [118, 114, 115], [94, 115, 116]),
            ],
        ),
    ];
    let input = pattern();
    for (c, expected) in table {
        for (severity, (sum, a, b)) in (1..=5).zip(expected) {
            let out = corrupt(c, &input, severity, 0);
            let got = (
                out.as_raw().iter().map(|&v| u64::from(v)).sum::<u64>(),
                out.get_pixel(7, 5).0,
                out.get_pixel(39, 33).0,
            );
            assert_eq!(got, (sum, a, b), "{c} severity {severity}");
        }
    }
}

#[test]
fn output_has_input_size_for_any_shape() {
    for (w, h) in [(8, 8), (160, 64), (37, 21), (9, 40)] {
        let input = test_image(w, h);
        for c in OURS {
            for severity in [1, 5] {
                let out = corrupt(c, &input, severity, 3);
                assert_eq!(out.dimensions(), (w, h), "{c} severity {severity} on {w}x{h}");
            }
        }
    }
}

#[test]
fn random_ones_are_deterministic_per_seed() {
    let input = test_image(160, 64);
    for c in RANDOM {
        let a = corrupt(c, &input, 3, 42);
        assert_eq!(a, corrupt(c, &input, 3, 42), "{c}: same seed, different output");
        assert_ne!(a, corrupt(c, &input, 3, 43), "{c}: different seeds, same output");
    }
}

#[test]
fn every_severity_changes_the_image() {
    let input = test_image(160, 64);
    for c in OURS {
        for severity in 1..=5 {
            let out = corrupt(c, &input, severity, 5);
            assert!(mean_abs_diff(&out, &input) > 0.5, "{c} severity {severity} barely changes the image");
        }
    }
}

#[test]
fn severity_orders_where_the_reference_is_monotone() {
    let input = test_image(160, 64);
    let by_severity = |c: Corruption, stat: &dyn Fn(&RgbImage) -> f64| -> Vec<f64> {
        (1..=5).map(|s| stat(&corrupt(c, &input, s, 9))).collect()
    };
    let increasing = |v: &[f64]| v.windows(2).all(|w| w[0] < w[1]);
    let distance = |out: &RgbImage| mean_abs_diff(out, &input);
    // Brightness adds 0.1..0.5 to V; contrast scales deviations by 0.4..0.05.
    assert!(increasing(&by_severity(Corruption::Brightness, &mean)));
    let contrast = by_severity(Corruption::Contrast, &std);
    assert!(contrast.windows(2).all(|w| w[0] > w[1]), "{contrast:?}");
    // Saturation factors are 0.3, 0.1, 2, 5 (+0.1), 20 (+0.2): severity 2 is the greyest.
    let sat = by_severity(Corruption::Saturate, &mean_saturation);
    assert!(increasing(&[sat[1], sat[0], sat[2], sat[3], sat[4]]), "{sat:?}");
    // Coarser blocks, lower JPEG quality, a stronger warp (same seed, so the same field scaled
    // up): each moves further from the input.
    for c in [Corruption::Pixelate, Corruption::JpegCompression, Corruption::ElasticTransform] {
        let d = by_severity(c, &distance);
        assert!(increasing(&d), "{c}: {d:?}");
    }
}

#[test]
fn bad_severity_is_an_error() {
    let input = test_image(32, 32);
    for c in OURS.into_iter().chain([Corruption::Frost]) {
        for severity in [0, 6] {
            let got = c.apply(&input, severity, &mut ChaCha8Rng::seed_from_u64(0));
            assert_eq!(got, Err(CorruptionError::Severity(severity)), "{c}");
        }
    }
}

/// Frost, in one test because it reads the environment: a directory without the textures is a
/// `MissingAsset` error naming the fix; with the reference package installed in the project venv
/// (as `make venv` does), it behaves like the other random corruptions.
#[test]
fn frost_end_to_end() {
    let input = test_image(160, 64);
    let empty = std::env::temp_dir().join(format!("udapose-frost-test-{}", std::process::id()));
    std::fs::create_dir_all(&empty).unwrap();
    let saved = std::env::var_os("UDAPOSE_FROST_DIR");
    // SAFETY: this is the only test in this binary that reads or writes the environment.
    unsafe { std::env::set_var("UDAPOSE_FROST_DIR", &empty) };
    let got = Corruption::Frost.apply(&input, 3, &mut ChaCha8Rng::seed_from_u64(0));
    // SAFETY: as above.
    unsafe {
        match &saved {
            Some(v) => std::env::set_var("UDAPOSE_FROST_DIR", v),
            None => std::env::remove_var("UDAPOSE_FROST_DIR"),
        }
    }
    std::fs::remove_dir(&empty).unwrap();
    match got {
        Err(CorruptionError::MissingAsset(msg)) => {
            assert!(msg.contains("imagecorruptions-imaug") && msg.contains("UDAPOSE_FROST_DIR"), "{msg}")
        }
        other => panic!("expected MissingAsset, got {other:?}"),
    }

    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let first = match Corruption::Frost.apply(&input, 3, &mut rng) {
        Ok(out) => out,
        Err(CorruptionError::MissingAsset(msg)) => {
            eprintln!("skipping the rest of frost_end_to_end: {msg}");
            return;
        }
        Err(e) => panic!("{e}"),
    };
    assert_eq!(first, corrupt(Corruption::Frost, &input, 3, 1));
    assert!(mean_abs_diff(&first, &input) > 0.5);
    let seeds: Vec<RgbImage> = (2..6).map(|seed| corrupt(Corruption::Frost, &input, 3, seed)).collect();
    assert!(seeds.iter().any(|o| *o != first), "five seeds, one frost");
    for (w, h) in [(8, 8), (37, 21), (1000, 40), (40, 700)] {
        let small = test_image(w, h);
        for severity in 1..=5 {
            assert_eq!(corrupt(Corruption::Frost, &small, severity, 4).dimensions(), (w, h));
        }
    }
}
