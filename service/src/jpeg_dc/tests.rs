use std::io::Cursor;

use super::*;
use crate::{
    api::Pixels,
    decode::{
        DecodeLimits,
        tests::{block_error, pattern_jpeg},
    },
};

/// The scaling decoder's 1/8 image of `bytes` (libjpeg's algorithm, independently written).
fn reference(bytes: &[u8]) -> (usize, usize, Vec<u8>) {
    let mut decoder = jpeg_decoder::Decoder::new(Cursor::new(bytes));
    decoder.read_info().unwrap();
    let info = decoder.info().unwrap();
    let (w, h) = decoder.scale(info.width.div_ceil(8), info.height.div_ceil(8)).unwrap();
    let data = decoder.decode().unwrap();
    let grey = decoder.info().unwrap().pixel_format == jpeg_decoder::PixelFormat::L8;
    let rgb = if grey { data.iter().flat_map(|&v| [v, v, v]).collect() } else { data };
    (usize::from(w), usize::from(h), rgb)
}

fn size(bytes: &[u8]) -> (u32, u32) {
    let mut decoder = jpeg_decoder::Decoder::new(Cursor::new(bytes));
    decoder.read_info().unwrap();
    let info = decoder.info().unwrap();
    (u32::from(info.width), u32::from(info.height))
}

/// Mean and largest absolute difference of two equal-size images, per channel value.
fn difference(a: &[u8], b: &[u8]) -> (f64, u8) {
    assert_eq!(a.len(), b.len());
    let d = a.iter().zip(b).map(|(&x, &y)| x.abs_diff(y));
    let (sum, max) = d.fold((0u64, 0u8), |(s, m), v| (s + u64::from(v), m.max(v)));
    (sum as f64 / a.len() as f64, max)
}

/// `rgb8` at `width × height` as the reduced decode of `bytes`.
fn pixels(rgb8: Vec<u8>, width: usize, height: usize, bytes: &[u8]) -> Pixels {
    let (w, h) = size(bytes);
    Pixels { rgb8, width, height, encoded: [w as usize, h as usize] }
}

fn fixture(name: &str) -> Vec<u8> {
    std::fs::read(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("testdata").join(name)).unwrap()
}

#[test]
fn the_dc_image_is_the_scaling_decoders_eighth() {
    let mut files: Vec<(String, Vec<u8>)> = [(1601, 1203, false), (1601, 1203, true), (40, 9, false)]
        .map(|(w, h, g)| (format!("{w}x{h} grey {g}"), pattern_jpeg(w, h, g)))
        .into();
    for name in ["restart-420.jpg", "restart-422.jpg", "restart-444.jpg", "restart-grey.jpg"] {
        files.push((name.into(), fixture(name)));
    }
    for (name, bytes) in files {
        let (w, h) = size(&bytes);
        let dc = decode(&bytes, w, h).unwrap_or_else(|| panic!("{name}: not taken"));
        let (rw, rh, rgb) = reference(&bytes);
        assert_eq!((dc.width, dc.height), (rw, rh), "{name}");
        let (mean, max) = difference(&dc.rgb8, &rgb);
        // Both are 1/8 images of the decoded picture: as close to its block means as the
        // scaling decoder, and within a level of it where there is no chroma to upsample
        // (subsampled chroma is interpolated by a different filter there).
        let full = crate::decode::decode(&bytes, DecodeLimits::default()).unwrap();
        let ours = block_error(&full, &pixels(dc.rgb8.clone(), dc.width, dc.height, &bytes), 8);
        let theirs = block_error(&full, &pixels(rgb.clone(), rw, rh, &bytes), 8);
        assert!(ours <= theirs + 0.25, "{name}: {ours:.2} from the block means, the reference {theirs:.2}");
        assert!(mean < 2.0, "{name}: mean difference to the reference {mean:.2} (max {max})");
        if name.contains("grey true") || name.contains("restart-grey") {
            assert!(max <= 1, "{name}: grey differs by {max}");
        }
    }
}

#[test]
fn what_it_does_not_take_goes_to_the_general_decoder() {
    let progressive = fixture("progressive.jpg");
    let (w, h) = size(&progressive);
    assert!(decode(&progressive, w, h).is_none(), "progressive");
    let baseline = pattern_jpeg(64, 48, false);
    assert!(decode(&baseline, 64, 48).is_some());
    assert!(decode(&baseline, 64, 49).is_none(), "a size other than the header's");
    // A restart marker out of sequence: refused, not decoded shifted.
    let mut bytes = fixture("restart-420.jpg");
    let sos = bytes.windows(2).position(|w| w == [0xFF, 0xDA]).unwrap();
    let rst = sos + bytes[sos..].windows(2).position(|w| w[0] == 0xFF && (0xD0..=0xD7).contains(&w[1])).unwrap();
    bytes[rst + 1] = 0xD5;
    let (w, h) = size(&bytes);
    assert!(decode(&bytes, w, h).is_none(), "RST5 where RST0 belongs");
}

#[test]
fn corrupt_files_never_panic() {
    let good = fixture("restart-420.jpg");
    let (w, h) = size(&good);
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    for i in 0..3000 {
        let mut bytes = good.clone();
        for _ in 0..1 + i % 4 {
            let at = next() as usize % bytes.len();
            bytes[at] = next() as u8;
        }
        if i % 5 == 0 {
            bytes.truncate(next() as usize % bytes.len());
        }
        let _ = decode(&bytes, w, h);
    }
}
