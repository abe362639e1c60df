//! Image decoding under limits. Runs on a blocking thread (never on the async runtime); a
//! decoder panic is caught and reported as a bad image.

use std::{io::Cursor, panic::AssertUnwindSafe};

use image::{ImageDecoder, ImageFormat, ImageReader, Limits, error::ImageError};

use udapose_engine::input::{self, Rgb8Image};

use crate::{
    api::Pixels,
    error::ApiError,
    jpeg_dc::{self, DcImage},
};

/// Bounds on what an image may decode to.
#[derive(Debug, Clone, Copy)]
pub struct DecodeLimits {
    /// Largest width or height, in pixels.
    pub max_side: u32,
    /// Largest allocation the decoder may make, in bytes.
    pub max_alloc: u64,
    /// Most bytes that the estimates' images may occupy at once, decoding or decoded and
    /// waiting for the worker ([`Header::cost`]): a small file can claim a huge image, so the
    /// number of requests bounds nothing.
    pub in_flight: u64,
}

impl Default for DecodeLimits {
    fn default() -> Self {
        // 1 GiB in flight: an 8192×8192 RGBA image costs 470 MB while it decodes.
        DecodeLimits { max_side: 8192, max_alloc: 512 * 1024 * 1024, in_flight: 1 << 30 }
    }
}

/// What an encoded image's header says, read without decoding it.
#[derive(Debug, Clone, Copy)]
pub struct Header {
    format: ImageFormat,
    pub width: u32,
    pub height: u32,
    /// Bytes per pixel of the decoder's own buffer (RGBA16: 8).
    bytes_per_pixel: u64,
}

impl Header {
    /// Checks the format, the JPEG's end and the size against `limits`.
    pub fn read(bytes: &[u8], limits: DecodeLimits) -> Result<Header, ApiError> {
        if bytes.is_empty() {
            return Err(ApiError::InvalidArgument("empty image: the request carried no bytes".into()));
        }
        guarded(|| read_header(bytes, limits))
    }

    /// Peak bytes while decoding and after: the decoder's buffer plus the RGB8 copy, unless the
    /// file is RGB8 already.
    pub fn cost(&self) -> u64 {
        let pixels = u64::from(self.width) * u64::from(self.height);
        if self.bytes_per_pixel == 3 { pixels * 3 } else { pixels * (self.bytes_per_pixel + 3) }
    }

    /// Decodes the image to RGB8.
    pub fn decode(&self, bytes: &[u8], limits: DecodeLimits) -> Result<Pixels, ApiError> {
        guarded(|| decode_checked(bytes, *self, limits))
    }

    /// Decodes the image to RGB8 at `1 / reduction` of its size (1, 2, 4 or 8, from
    /// `udapose_engine::input::max_reduction`): a JPEG by its DCT's own scaling (at 1/8 from
    /// its DC coefficients alone, [`jpeg_dc`], where the file is baseline), anything else (and
    /// JPEGs the scaling decoder does not take: CMYK, 16-bit, any it refuses) at full size, then
    /// by block means ([`reduced`]). Either way the crop then resamples an image `reduction²`
    /// times smaller.
    pub fn decode_for(&self, bytes: &[u8], limits: DecodeLimits, reduction: u32) -> Result<Pixels, ApiError> {
        if reduction <= 1 {
            return self.decode(bytes, limits);
        }
        guarded(|| {
            if self.format == ImageFormat::Jpeg
                && let Some(pixels) = decode_jpeg_reduced(bytes, *self, limits, reduction)
            {
                return Ok(pixels);
            }
            reduced(decode_checked(bytes, *self, limits)?, reduction)
        })
    }
}

/// `pixels` shrunk `r`-fold by block means (`udapose_engine::input::reduce`), still describing
/// the image they were decoded from.
pub fn reduced(pixels: Pixels, r: u32) -> Result<Pixels, ApiError> {
    if r <= 1 {
        return Ok(pixels);
    }
    let (rgb8, width, height) = input::reduce(&Rgb8Image::new(&pixels.rgb8, pixels.width, pixels.height)?, r)?;
    Ok(Pixels { rgb8, width, height, encoded: pixels.encoded })
}

/// What [`raw`] pixels of this size cost in flight (their copy).
pub fn raw_cost(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height) * 3
}

/// Decodes PNG, JPEG or WebP bytes to RGB8 within `limits`.
pub fn decode(bytes: &[u8], limits: DecodeLimits) -> Result<Pixels, ApiError> {
    Header::read(bytes, limits)?.decode(bytes, limits)
}

/// A decoder panic is a bad image, not a dead thread.
fn guarded<T>(f: impl FnOnce() -> Result<T, ApiError>) -> Result<T, ApiError> {
    match std::panic::catch_unwind(AssertUnwindSafe(f)) {
        Ok(result) => result,
        Err(_) => Err(ApiError::InvalidArgument("the image decoder failed on this file (corrupt image)".into())),
    }
}

fn read_header(bytes: &[u8], limits: DecodeLimits) -> Result<Header, ApiError> {
    let format = image::guess_format(bytes)
        .ok()
        .filter(|f| matches!(f, ImageFormat::Png | ImageFormat::Jpeg | ImageFormat::WebP));
    let Some(format) = format else {
        return Err(ApiError::InvalidArgument("not a PNG, JPEG or WebP image".into()));
    };
    if format == ImageFormat::Jpeg && !jpeg_is_complete(bytes) {
        // The JPEG decoder fills a cut-off scan with grey and reports success: the pose of
        // half a car would come back as if it were a whole one.
        return Err(ApiError::InvalidArgument(
            "cannot decode the JPEG image: it is truncated (no end-of-image marker after its last scan)".into(),
        ));
    }
    // The header's size first (reading it allocates nothing): a small file may claim a huge
    // image (decompression bomb), and the caller should hear which size was refused.
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    reader.no_limits();
    let decoder = reader.into_decoder().map_err(|e| describe(e, format))?;
    let ((width, height), color) = (decoder.dimensions(), decoder.color_type());
    if width > limits.max_side || height > limits.max_side {
        return Err(too_big(width, height, limits));
    }
    Ok(Header { format, width, height, bytes_per_pixel: u64::from(color.bytes_per_pixel()) })
}

fn decode_checked(bytes: &[u8], header: Header, limits: DecodeLimits) -> Result<Pixels, ApiError> {
    let format = header.format;
    let mut l = Limits::default();
    l.max_image_width = Some(limits.max_side);
    l.max_image_height = Some(limits.max_side);
    l.max_alloc = Some(limits.max_alloc);
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    reader.limits(l);
    let image = reader.decode().map_err(|e| describe(e, format))?.into_rgb8();
    let (width, height) = (image.width() as usize, image.height() as usize);
    Ok(Pixels { rgb8: image.into_raw(), width, height, encoded: [width, height] })
}

/// A JPEG decoded at `1 / reduction` of its size; `None` for pixel formats other than RGB and
/// 8-bit grey, and for files the scaling decoder refuses: the full decoder then decides.
fn decode_jpeg_reduced(bytes: &[u8], header: Header, limits: DecodeLimits, reduction: u32) -> Option<Pixels> {
    use jpeg_decoder::PixelFormat::{L8, RGB24};
    let encoded = [header.width as usize, header.height as usize];
    if reduction == 8
        && let Some(DcImage { rgb8, width, height }) = jpeg_dc::decode(bytes, header.width, header.height)
    {
        return Some(Pixels { rgb8, width, height, encoded });
    }
    let mut decoder = jpeg_decoder::Decoder::new(Cursor::new(bytes));
    decoder.set_max_decoding_buffer_size(usize::try_from(limits.max_alloc).unwrap_or(usize::MAX));
    // JPEG sides are 16-bit, and the header's were checked against `max_side`.
    let side = |n: u32| u16::try_from(n.div_ceil(reduction)).unwrap_or(u16::MAX);
    let (w, h) = decoder.scale(side(header.width), side(header.height)).ok()?;
    let format = decoder.info()?.pixel_format;
    if !matches!(format, RGB24 | L8) {
        return None;
    }
    let data = decoder.decode().ok()?;
    let rgb8 = if format == L8 { data.iter().flat_map(|&v| [v, v, v]).collect() } else { data };
    let (width, height) = (usize::from(w), usize::from(h));
    (width > 0 && height > 0 && rgb8.len() == width * height * 3).then_some(Pixels { rgb8, width, height, encoded })
}

/// Whether a JPEG's last scan (SOS, FF DA) is followed by the end-of-image marker (FF D9). Inside
/// entropy-coded data every FF byte is stuffed (FF 00) or a restart marker (FF D0-D7), so an
/// FF D9 after the last SOS can only be the real end; an embedded EXIF thumbnail comes before
/// the main image's scans, and bytes appended after the EOI are allowed.
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    let Some(last_sos) = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]) else { return false };
    bytes[last_sos..].windows(2).any(|w| w == [0xFF, 0xD9])
}

fn too_big(w: u32, h: u32, limits: DecodeLimits) -> ApiError {
    ApiError::InvalidArgument(format!("image is {w}x{h} px, over the limit of {m}x{m}", m = limits.max_side))
}

fn describe(e: ImageError, format: ImageFormat) -> ApiError {
    let name = format!("{format:?}").to_uppercase();
    match e {
        ImageError::Limits(l) => ApiError::InvalidArgument(format!("{name} image exceeds the decoding limits: {l}")),
        other => ApiError::InvalidArgument(format!("cannot decode the {name} image: {other}")),
    }
}

/// Checks raw RGB8 pixels and copies them into a `Pixels`.
pub fn raw(width: u32, height: u32, rgb8: &[u8], limits: DecodeLimits) -> Result<Pixels, ApiError> {
    if width == 0 || height == 0 {
        return Err(ApiError::InvalidArgument(format!("raw image is {width}x{height} px")));
    }
    if width > limits.max_side || height > limits.max_side {
        return Err(too_big(width, height, limits));
    }
    let expected = width as usize * height as usize * 3;
    if rgb8.len() != expected {
        return Err(ApiError::InvalidArgument(format!(
            "raw image: {} bytes for {width}x{height} RGB8 (expected {expected})",
            rgb8.len()
        )));
    }
    let (width, height) = (width as usize, height as usize);
    Ok(Pixels { rgb8: rgb8.to_vec(), width, height, encoded: [width, height] })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    fn jpeg() -> Vec<u8> {
        let img = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, 90]));
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Jpeg).unwrap();
        out
    }

    pub(crate) fn pattern_jpeg(width: u32, height: u32, grey: bool) -> Vec<u8> {
        let value = |x: u32, y: u32, c: u32| {
            (128.0 + 100.0 * ((x as f64 / 37.0 + c as f64).sin() * (y as f64 / 23.0).cos())) as u8
        };
        let mut out = Vec::new();
        if grey {
            let img = image::GrayImage::from_fn(width, height, |x, y| image::Luma([value(x, y, 0)]));
            img.write_to(&mut Cursor::new(&mut out), ImageFormat::Jpeg).unwrap();
        } else {
            let img = image::RgbImage::from_fn(width, height, |x, y| image::Rgb([0, 1, 2].map(|c| value(x, y, c))));
            img.write_to(&mut Cursor::new(&mut out), ImageFormat::Jpeg).unwrap();
        }
        out
    }

    /// Mean absolute difference between a reduced decode and the full decode averaged over the
    /// same `r × r` blocks (what the DCT's scaling approximates).
    pub(crate) fn block_error(full: &Pixels, reduced: &Pixels, r: usize) -> f64 {
        let mut total = 0.0;
        for y in 0..reduced.height {
            for x in 0..reduced.width {
                for c in 0..3 {
                    let (mut sum, mut n) = (0.0, 0.0);
                    for yy in y * r..((y + 1) * r).min(full.height) {
                        for xx in x * r..((x + 1) * r).min(full.width) {
                            sum += f64::from(full.rgb8[(yy * full.width + xx) * 3 + c]);
                            n += 1.0;
                        }
                    }
                    total += (sum / n - f64::from(reduced.rgb8[(y * reduced.width + x) * 3 + c])).abs();
                }
            }
        }
        total / (reduced.width * reduced.height * 3) as f64
    }

    #[test]
    fn a_jpeg_decodes_reduced_to_its_block_averages() {
        let limits = DecodeLimits::default();
        for grey in [false, true] {
            let bytes = pattern_jpeg(1601, 1203, grey);
            let header = Header::read(&bytes, limits).unwrap();
            let full = header.decode(&bytes, limits).unwrap();
            assert_eq!(full.encoded, [1601, 1203]);
            for r in [2usize, 4, 8] {
                let reduced = header.decode_for(&bytes, limits, r as u32).unwrap();
                assert_eq!((reduced.width, reduced.height), (1601usize.div_ceil(r), 1203usize.div_ceil(r)));
                assert_eq!(reduced.encoded, [1601, 1203]);
                let error = block_error(&full, &reduced, r);
                assert!(error < 3.0, "grey {grey}, 1/{r}: mean |reduced - block mean| = {error:.2} (of 255)");
            }
        }
        // Not a JPEG: decoded at full size, then block means.
        let png = png(40, 30);
        let header = Header::read(&png, limits).unwrap();
        let full = header.decode(&png, limits).unwrap();
        let pixels = header.decode_for(&png, limits, 8).unwrap();
        assert_eq!((pixels.width, pixels.height, pixels.encoded), (5, 4, [40, 30]));
        assert!(block_error(&full, &pixels, 8) <= 0.5, "rounded block means");
    }

    #[test]
    fn a_truncated_jpeg_is_refused_and_a_whole_one_decodes() {
        let whole = jpeg();
        assert!(decode(&whole, DecodeLimits::default()).is_ok());
        let mut appended = whole.clone();
        appended.extend_from_slice(b"trailing bytes after the end-of-image marker");
        assert!(decode(&appended, DecodeLimits::default()).is_ok());
        for cut in [whole.len() - 2, whole.len() * 3 / 4, whole.len() / 2] {
            match decode(&whole[..cut], DecodeLimits::default()) {
                Err(ApiError::InvalidArgument(m)) => assert!(m.contains("truncated"), "{m}"),
                other => panic!("a JPEG cut at {cut} of {} bytes decoded: {:?}", whole.len(), other.is_ok()),
            }
        }
    }

    fn png(width: u32, height: u32) -> Vec<u8> {
        let mut out = Vec::new();
        let img = image::RgbImage::from_fn(width, height, |x, y| image::Rgb([x as u8, y as u8, 7]));
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png).unwrap();
        out
    }

    /// A valid 1×1 PNG whose IHDR (CRC fixed) claims `width`×`height`: a decompression bomb's header.
    fn png_header(width: u32, height: u32) -> Vec<u8> {
        let mut out = png(1, 1);
        out[16..20].copy_from_slice(&width.to_be_bytes());
        out[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32(&out[12..29]); // the IHDR chunk's type and data
        out[29..33].copy_from_slice(&crc.to_be_bytes());
        out
    }

    /// CRC-32 (ISO-HDLC), as PNG chunks carry it.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
            }
        }
        !crc
    }

    #[test]
    fn the_header_prices_an_image_before_it_decodes() {
        // A bomb's header: 30000×7000 RGB8 claimed by a 1×1 file, refused by its size only
        // past the side limit.
        let limits = DecodeLimits { max_side: 30000, ..DecodeLimits::default() };
        let header = Header::read(&png_header(30000, 7000), limits).unwrap();
        assert_eq!((header.width, header.height, header.cost()), (30000, 7000, 30000 * 7000 * 3));
        let mut gray = Vec::new();
        image::GrayImage::new(40, 10).write_to(&mut Cursor::new(&mut gray), ImageFormat::Png).unwrap();
        assert_eq!(Header::read(&gray, limits).unwrap().cost(), 40 * 10 * 4, "L8 buffer + RGB8 copy");
    }

    #[test]
    fn a_png_decodes_to_its_pixels() {
        let p = decode(&png(20, 10), DecodeLimits::default()).unwrap();
        assert_eq!((p.width, p.height, p.rgb8.len()), (20, 10, 600));
        assert_eq!(&p.rgb8[3 * 21..3 * 22], &[1, 1, 7]);
    }

    #[test]
    fn bad_files_are_invalid_arguments_with_a_reason() {
        let limits = DecodeLimits::default();
        let cases: [(&[u8], &str); 4] = [
            (&[], "empty image"),
            (b"not an image at all", "not a PNG, JPEG or WebP"),
            (&png(20, 10)[..60], "cannot decode the PNG"),
            (&png_header(30000, 30000), "30000x30000"),
        ];
        for (bytes, want) in cases {
            let err = decode(bytes, limits).unwrap_err();
            assert!(matches!(err, ApiError::InvalidArgument(_)), "{err:?}");
            assert!(err.to_string().contains(want), "{want}: {err}");
        }
    }

    #[test]
    fn raw_pixels_must_match_their_size() {
        let limits = DecodeLimits::default();
        assert!(raw(2, 2, &[0; 12], limits).is_ok());
        assert!(raw(2, 2, &[0; 11], limits).unwrap_err().to_string().contains("expected 12"));
        assert!(raw(0, 2, &[], limits).is_err());
        assert!(raw(9000, 1, &[], limits).unwrap_err().to_string().contains("over the limit"));
    }
}
