//! Decoder for SGI images (`.rgb`, `.rgba`, `.bw`), TORCS's texture format: 8-bit channels,
//! verbatim or run-length encoded, rows stored bottom to top.

use image::{RgbImage, RgbaImage};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SgiError {
    #[error("not an SGI image (magic {0})")]
    Magic(u16),
    #[error("unsupported SGI image: {0}")]
    Unsupported(String),
    #[error("truncated or corrupt SGI data: {0}")]
    Corrupt(&'static str),
}

/// Largest accepted image side, so a corrupt header cannot make us allocate gigabytes.
const MAX_SIDE: usize = 8192;

fn be16(b: &[u8], at: usize) -> usize {
    u16::from_be_bytes([b[at], b[at + 1]]) as usize
}

fn be32(b: &[u8], at: usize) -> Option<usize> {
    Some(u32::from_be_bytes(b.get(at..at + 4)?.try_into().ok()?) as usize)
}

/// Decodes to RGB: one channel is grey, a fourth (alpha) is dropped.
pub fn decode(bytes: &[u8]) -> Result<RgbImage, SgiError> {
    Ok(image::DynamicImage::ImageRgba8(decode_rgba(bytes)?).to_rgb8())
}

/// Decodes to RGBA: one channel is grey, alpha is opaque unless a fourth channel gives it.
pub fn decode_rgba(bytes: &[u8]) -> Result<RgbaImage, SgiError> {
    if bytes.len() < 512 {
        return Err(SgiError::Corrupt("header"));
    }
    let magic = be16(bytes, 0) as u16;
    if magic != 474 {
        return Err(SgiError::Magic(magic));
    }
    let (rle, bpc) = (bytes[2], bytes[3]);
    if bpc != 1 {
        return Err(SgiError::Unsupported(format!("{bpc} bytes per channel")));
    }
    let (w, h, channels) = (be16(bytes, 6), be16(bytes, 8), be16(bytes, 10).max(1));
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE || channels > 4 {
        return Err(SgiError::Unsupported(format!("{w}x{h} with {channels} channels")));
    }
    let planes: Vec<Vec<u8>> = (0..channels)
        .map(|c| if rle == 1 { rle_plane(bytes, c, w, h, channels) } else { verbatim_plane(bytes, c, w, h) })
        .collect::<Result<_, _>>()?;
    Ok(RgbaImage::from_fn(w as u32, h as u32, |x, y| {
        let at = (h - 1 - y as usize) * w + x as usize; // bottom-up rows
        let colour = |c: usize| planes[if channels >= 3 { c } else { 0 }][at];
        let alpha = if channels == 4 || channels == 2 { planes[channels - 1][at] } else { 255 };
        image::Rgba([colour(0), colour(1), colour(2), alpha])
    }))
}

fn verbatim_plane(bytes: &[u8], c: usize, w: usize, h: usize) -> Result<Vec<u8>, SgiError> {
    let start = 512 + c * w * h;
    bytes.get(start..start + w * h).map(<[u8]>::to_vec).ok_or(SgiError::Corrupt("verbatim data"))
}

fn rle_plane(bytes: &[u8], c: usize, w: usize, h: usize, channels: usize) -> Result<Vec<u8>, SgiError> {
    let mut plane = Vec::with_capacity(w * h);
    for row in 0..h {
        let entry = 512 + 4 * (c * h + row);
        let offset = be32(bytes, entry).ok_or(SgiError::Corrupt("offset table"))?;
        let _ = be32(bytes, 512 + 4 * (channels * h + c * h + row)).ok_or(SgiError::Corrupt("length table"))?;
        let before = plane.len();
        unpack_row(bytes, offset, w, &mut plane)?;
        if plane.len() - before != w {
            return Err(SgiError::Corrupt("row length"));
        }
    }
    Ok(plane)
}

/// One RLE row: a count byte with the high bit set copies that many literal bytes, without it
/// repeats the next byte; a zero count ends the row.
fn unpack_row(bytes: &[u8], mut at: usize, w: usize, out: &mut Vec<u8>) -> Result<(), SgiError> {
    let end = out.len() + w;
    loop {
        let code = *bytes.get(at).ok_or(SgiError::Corrupt("run"))?;
        at += 1;
        let count = (code & 0x7f) as usize;
        if count == 0 {
            return Ok(());
        }
        if out.len() + count > end {
            return Err(SgiError::Corrupt("run past row end"));
        }
        if code & 0x80 != 0 {
            out.extend_from_slice(bytes.get(at..at + count).ok_or(SgiError::Corrupt("literal run"))?);
            at += count;
        } else {
            let v = *bytes.get(at).ok_or(SgiError::Corrupt("repeat run"))?;
            out.extend(std::iter::repeat_n(v, count));
            at += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(w: u16, h: u16, channels: u16, rle: u8) -> Vec<u8> {
        let mut b = vec![0u8; 512];
        b[0..2].copy_from_slice(&474u16.to_be_bytes());
        b[2] = rle;
        b[3] = 1;
        b[4..6].copy_from_slice(&3u16.to_be_bytes());
        b[6..8].copy_from_slice(&w.to_be_bytes());
        b[8..10].copy_from_slice(&h.to_be_bytes());
        b[10..12].copy_from_slice(&channels.to_be_bytes());
        b
    }

    #[test]
    fn verbatim_rows_are_bottom_up() {
        let mut b = header(2, 2, 1, 0);
        b.extend([10, 20, 30, 40]); // bottom row 10 20, top row 30 40
        let img = decode(&b).unwrap();
        assert_eq!(img.get_pixel(0, 0).0, [30, 30, 30]);
        assert_eq!(img.get_pixel(1, 1).0, [20, 20, 20]);
    }

    #[test]
    fn rle_runs_decode_and_corruption_is_an_error() {
        // 3x1, 3 channels: a repeat run, a literal run, and both mixed.
        let rows: [&[u8]; 3] = [&[3, 7, 0], &[0x83, 1, 2, 3, 0], &[2, 9, 0x81, 5, 0]];
        let mut b = header(3, 1, 3, 1);
        let mut offset = 512 + 2 * 4 * rows.len();
        let mut lengths = Vec::new();
        for r in rows {
            b.extend((offset as u32).to_be_bytes());
            lengths.extend((r.len() as u32).to_be_bytes());
            offset += r.len();
        }
        b.extend(lengths);
        rows.iter().for_each(|r| b.extend_from_slice(r));
        let img = decode(&b).unwrap();
        assert_eq!((img.get_pixel(0, 0).0, img.get_pixel(2, 0).0), ([7, 1, 9], [7, 3, 5]));
        assert!(decode(&b[..b.len() - 3]).is_err());
        assert_eq!(decode(&[0u8; 600]), Err(SgiError::Magic(0)));
    }

    #[test]
    fn decodes_a_torcs_texture() {
        let path = "/usr/share/games/torcs/cars/p406/p406.rgb";
        let bytes = std::fs::read(path).expect("TORCS textures are installed by `make assets`");
        let img = decode(&bytes).unwrap();
        assert!(img.width() >= 256 && img.height() >= 256);
        let distinct: std::collections::HashSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
        assert!(distinct.len() > 100, "a real texture has many colours");
    }
}
