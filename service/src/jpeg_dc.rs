//! A JPEG decoded at 1/8 of its size from its DC coefficients alone.
//!
//! At 1/8 a JPEG's pixel is the mean of an 8×8 block, and that mean *is* the block's DC
//! coefficient: no inverse DCT, no full-size upsampling, no colour conversion of 64× the pixels.
//! The AC coefficients only have to be stepped over, so what remains is the entropy decoding,
//! done here with tables that step over a coefficient's code and value bits in one lookup.
//! Taken: baseline files (sequential Huffman, 8-bit) with one component, or three (YCbCr) in
//! one interleaved scan, with or without restart markers: what cameras and encoders write.
//! Anything else (progressive, arithmetic, CMYK, Adobe RGB transforms, corrupt data) gives
//! `None` and the general decoder decides, so this path never adds an error of its own.

/// An image at 1/8 scale: `ceil(w / 8) × ceil(h / 8)` RGB8 pixels.
pub struct DcImage {
    pub width: usize,
    pub height: usize,
    pub rgb8: Vec<u8>,
}

/// Decodes `bytes` at 1/8 scale; `None` for anything this decoder does not take, and for a
/// frame whose size is not `width × height` (the size the caller checked against its limits).
pub fn decode(bytes: &[u8], width: u32, height: u32) -> Option<DcImage> {
    let mut tables = Tables::default();
    let mut restart = 0;
    let mut frame = None;
    let mut pos = 2;
    if bytes.get(..2)? != [0xFF, 0xD8] {
        return None;
    }
    loop {
        if *bytes.get(pos)? != 0xFF {
            return None;
        }
        while *bytes.get(pos)? == 0xFF {
            pos += 1; // fill bytes
        }
        let marker = bytes[pos];
        pos += 1;
        if matches!(marker, 0x01 | 0xD0..=0xD9) {
            return None; // no standalone marker belongs between SOI and the scan
        }
        let len = usize::from(u16::from_be_bytes([*bytes.get(pos)?, *bytes.get(pos + 1)?]));
        if len < 2 {
            return None;
        }
        let segment = bytes.get(pos + 2..pos + len)?;
        pos += len;
        match marker {
            0xDB => tables.quantisation(segment)?,
            0xC4 => tables.huffman(segment)?,
            0xC0 | 0xC1 => {
                let f = Frame::parse(segment)?;
                if (f.width, f.height) != (width as usize, height as usize) {
                    return None;
                }
                frame = Some(f);
            }
            0xC2..=0xCF => return None, // progressive, lossless, arithmetic
            0xDD => restart = usize::from(u16::from_be_bytes([*segment.first()?, *segment.get(1)?])),
            // Adobe's APP14: its transform flag may say the three components are RGB, not YCbCr.
            0xEE if segment.starts_with(b"Adobe") => return None,
            0xDA => return scan(&frame?, &tables, restart, segment, bytes.get(pos..)?),
            _ => {} // APPn, COM
        }
    }
}

struct Component {
    id: u8,
    h: usize,
    v: usize,
    quant: usize,
}

struct Frame {
    width: usize,
    height: usize,
    components: Vec<Component>,
}

impl Frame {
    fn parse(s: &[u8]) -> Option<Frame> {
        if *s.first()? != 8 {
            return None; // 12-bit samples
        }
        let height = usize::from(u16::from_be_bytes([*s.get(1)?, *s.get(2)?]));
        let width = usize::from(u16::from_be_bytes([*s.get(3)?, *s.get(4)?]));
        let n = usize::from(*s.get(5)?);
        if width == 0 || height == 0 || !(n == 1 || n == 3) {
            return None;
        }
        let components = (0..n)
            .map(|i| {
                let c = s.get(6 + 3 * i..9 + 3 * i)?;
                let (h, v) = (usize::from(c[1] >> 4), usize::from(c[1] & 15));
                ((1..=4).contains(&h) && (1..=4).contains(&v) && c[2] < 4).then_some(Component {
                    id: c[0],
                    h,
                    v,
                    quant: usize::from(c[2]),
                })
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Frame { width, height, components })
    }
}

#[derive(Default)]
struct Tables {
    /// Each quantisation table's DC step.
    dc_step: [Option<i32>; 4],
    dc: [Option<Huffman>; 4],
    ac: [Option<Huffman>; 4],
}

impl Tables {
    fn quantisation(&mut self, mut s: &[u8]) -> Option<()> {
        while let Some(&pq_tq) = s.first() {
            let (wide, id) = (pq_tq >> 4 != 0, usize::from(pq_tq & 15));
            let size = if wide { 128 } else { 64 };
            let table = s.get(1..1 + size)?;
            let step = if wide { i32::from(u16::from_be_bytes([table[0], table[1]])) } else { i32::from(table[0]) };
            *self.dc_step.get_mut(id)? = Some(step);
            s = &s[1 + size..];
        }
        Some(())
    }

    fn huffman(&mut self, mut s: &[u8]) -> Option<()> {
        while let Some(&tc_th) = s.first() {
            let (class, id) = (tc_th >> 4, usize::from(tc_th & 15));
            let counts: [u8; 16] = s.get(1..17)?.try_into().ok()?;
            let n: usize = counts.iter().map(|&c| usize::from(c)).sum();
            let symbols = s.get(17..17 + n)?;
            let table = Huffman::new(&counts, symbols, class == 1)?;
            match class {
                0 => *self.dc.get_mut(id)? = Some(table),
                1 => *self.ac.get_mut(id)? = Some(table),
                _ => return None,
            }
            s = &s[17 + n..];
        }
        Some(())
    }
}

/// Codes of up to this many bits are decoded by one table lookup.
const FAST: u32 = 12;

/// A canonical Huffman table: a lookup for short codes, JPEG's MAXCODE/VALPTR for the rest.
struct Huffman {
    /// Per `FAST`-bit lookahead: `code bits | symbol << 8`, or 0 for a longer code. For an AC
    /// table whose code and value bits both fit, the entry is instead `SKIP | total bits |
    /// (run + 1) << 8`: the coefficient is stepped over in one go.
    fast: Vec<u16>,
    max_code: [i32; 17],
    /// Per code length, the index of its first symbol minus its first code.
    offset: [i32; 17],
    symbols: Vec<u8>,
}

const SKIP: u16 = 0x80;

impl Huffman {
    fn new(counts: &[u8; 16], symbols: &[u8], ac: bool) -> Option<Huffman> {
        let mut fast = vec![0u16; 1 << FAST];
        let (mut max_code, mut offset) = ([-1i32; 17], [0i32; 17]);
        let (mut code, mut k) = (0i32, 0usize);
        for len in 1..=16u32 {
            let count = i32::from(counts[len as usize - 1]);
            offset[len as usize] = k as i32 - code;
            for _ in 0..count {
                if code >= 1 << len {
                    return None; // over-subscribed: not a prefix code
                }
                if len <= FAST {
                    let symbol = symbols[k];
                    let entry = Self::entry(len, symbol, ac);
                    let first = (code as usize) << (FAST - len);
                    fast[first..first + (1 << (FAST - len))].fill(entry);
                }
                code += 1;
                k += 1;
            }
            if count > 0 {
                max_code[len as usize] = code - 1;
            }
            code <<= 1;
        }
        Some(Huffman { fast, max_code, offset, symbols: symbols.to_vec() })
    }

    /// The fast entry of a code of `len` bits for `symbol`.
    fn entry(len: u32, symbol: u8, ac: bool) -> u16 {
        let (run, size) = (u16::from(symbol >> 4), u32::from(symbol & 15));
        if ac && size > 0 && len + size <= FAST {
            SKIP | (len + size) as u16 | (run + 1) << 8
        } else {
            len as u16 | u16::from(symbol) << 8
        }
    }

    /// The next DC difference: its size category's code, then its value bits.
    fn dc_difference(&self, bits: &mut Bits) -> Option<i32> {
        let size = u32::from(self.symbol(bits)?);
        if size > 11 {
            return None;
        }
        // `symbol` refilled to ≥ 57 bits and took ≤ 16: the value's ≤ 11 bits are there.
        Some(bits.value(size))
    }

    /// The next symbol; `None` for a code in no table (corrupt data).
    fn symbol(&self, bits: &mut Bits) -> Option<u8> {
        bits.refill();
        let entry = self.fast[bits.peek(FAST) as usize];
        if entry != 0 && entry & SKIP == 0 {
            bits.consume(u32::from(entry & 0x1F));
            return Some((entry >> 8) as u8);
        }
        self.slow(bits)
    }

    fn slow(&self, bits: &mut Bits) -> Option<u8> {
        let look = bits.peek(16) as i32;
        for len in 1..=16 {
            let code = look >> (16 - len);
            if code <= self.max_code[len] {
                bits.consume(len as u32);
                return self.symbols.get((code + self.offset[len]) as usize).copied();
            }
        }
        None
    }

    /// Steps over one block's AC coefficients.
    fn skip_block(&self, bits: &mut Bits) -> Option<()> {
        let mut k = 1;
        while k < 64 {
            bits.refill();
            let entry = self.fast[bits.peek(FAST) as usize];
            if entry & SKIP != 0 {
                bits.consume(u32::from(entry & 0x1F));
                k += usize::from((entry >> 8) & 0x1F);
                continue;
            }
            let symbol = if entry != 0 {
                bits.consume(u32::from(entry & 0x1F));
                (entry >> 8) as u8
            } else {
                self.slow(bits)?
            };
            let (run, size) = (usize::from(symbol >> 4), u32::from(symbol & 15));
            if size == 0 {
                if run != 15 {
                    break; // end of block
                }
                k += 16;
            } else {
                // The refill above left ≥ 57 bits; a code took ≤ 16 of them.
                bits.consume(size);
                k += run + 1;
            }
        }
        (k <= 64).then_some(())
    }
}

/// The entropy-coded bits, most significant first, with stuffed bytes removed. At a marker it
/// feeds zeros (as decoders do for a short scan) and remembers where the marker is.
struct Bits<'a> {
    data: &'a [u8],
    pos: usize,
    buffer: u64,
    count: u32,
    at_marker: bool,
}

impl<'a> Bits<'a> {
    fn new(data: &'a [u8]) -> Bits<'a> {
        Bits { data, pos: 0, buffer: 0, count: 0, at_marker: false }
    }

    /// Fills the buffer to at least 57 bits.
    fn refill(&mut self) {
        if self.count > 56 {
            return;
        }
        // Fast path: eight bytes without an FF go in as one word.
        if !self.at_marker
            && let Some(word) = self.data.get(self.pos..self.pos + 8)
        {
            let word = u64::from_be_bytes(word.try_into().expect("8 bytes"));
            let has_ff = (!word).wrapping_sub(0x0101_0101_0101_0101) & word & 0x8080_8080_8080_8080;
            if has_ff == 0 {
                let take = (64 - self.count) / 8;
                self.buffer |= (word >> (64 - 8 * take)) << (64 - self.count - 8 * take);
                self.pos += take as usize;
                self.count += 8 * take;
                return;
            }
        }
        while self.count <= 56 {
            let byte = self.next_byte();
            self.buffer |= u64::from(byte) << (56 - self.count);
            self.count += 8;
        }
    }

    fn next_byte(&mut self) -> u8 {
        if self.at_marker {
            return 0;
        }
        match self.data.get(self.pos..).unwrap_or_default() {
            [0xFF, 0x00, ..] => {
                self.pos += 2;
                0xFF
            }
            [0xFF, ..] | [] => {
                self.at_marker = true;
                0
            }
            [b, ..] => {
                self.pos += 1;
                *b
            }
        }
    }

    fn peek(&self, n: u32) -> u64 {
        self.buffer >> (64 - n)
    }

    fn consume(&mut self, n: u32) {
        self.buffer <<= n;
        self.count = self.count.saturating_sub(n);
    }

    /// `size` bits as JPEG's signed magnitude (EXTEND); the caller has them in the buffer.
    fn value(&mut self, size: u32) -> i32 {
        if size == 0 {
            return 0;
        }
        let v = self.peek(size) as i32;
        self.consume(size);
        if v < 1 << (size - 1) { v - (1 << size) + 1 } else { v }
    }

    /// Skips the restart marker RSTn that must come next; `false` if it is not there.
    fn restart(&mut self, n: usize) -> bool {
        // Undo what the buffer read ahead: whole bytes past the padding are still in `data`.
        let marker = [0xFF, 0xD0 + (n % 8) as u8];
        if !self.at_marker {
            // The buffer holds the byte-aligned rest of the interval and nothing else: the
            // encoder pads the last byte with ones, and a marker follows.
            while !self.at_marker {
                self.next_byte();
            }
        }
        let ok = self.data.get(self.pos..self.pos + 2) == Some(&marker[..]);
        self.pos += 2;
        (self.buffer, self.count, self.at_marker) = (0, 0, false);
        ok
    }
}

/// Where a scan's component stands: its tables, its predictor and its DC per block.
struct Plane<'t> {
    h: usize,
    v: usize,
    blocks_wide: usize,
    step: i32,
    dc: &'t Huffman,
    ac: &'t Huffman,
    predictor: i32,
    /// Each block's mean sample, 0-255.
    means: Vec<u8>,
}

fn scan(frame: &Frame, tables: &Tables, restart: usize, header: &[u8], data: &[u8]) -> Option<DcImage> {
    let n = usize::from(*header.first()?);
    if n != frame.components.len() {
        return None; // one component per scan (non-interleaved colour): not taken
    }
    // One component is never interleaved: its MCU is one block, whatever its factors say.
    let single = n == 1;
    let (h_max, v_max) = if single {
        (1, 1)
    } else {
        (frame.components.iter().map(|c| c.h).max()?, frame.components.iter().map(|c| c.v).max()?)
    };
    let (mcu_w, mcu_h) = (8 * h_max, 8 * v_max);
    let (mcus_wide, mcus_high) = (frame.width.div_ceil(mcu_w), frame.height.div_ceil(mcu_h));
    let mut planes = Vec::with_capacity(n);
    for i in 0..n {
        let selector = header.get(1 + 2 * i..3 + 2 * i)?;
        let c = frame.components.iter().find(|c| c.id == selector[0])?;
        if !single && (h_max % c.h != 0 || v_max % c.v != 0) {
            return None;
        }
        let (h, v) = if single { (1, 1) } else { (c.h, c.v) };
        let (wide, high) = (mcus_wide * h, mcus_high * v);
        planes.push(Plane {
            h,
            v,
            blocks_wide: wide,
            step: tables.dc_step[c.quant]?,
            dc: tables.dc.get(usize::from(selector[1] >> 4))?.as_ref()?,
            ac: tables.ac.get(usize::from(selector[1] & 15))?.as_ref()?,
            predictor: 0,
            means: vec![0; wide.checked_mul(high)?],
        });
    }
    // Luma at the full factors (as every encoder writes it) is read without interpolation.
    if !single && (planes[0].h, planes[0].v) != (h_max, v_max) {
        return None;
    }
    let mut bits = Bits::new(data);
    let mut next_restart = 0;
    for m in 0..mcus_wide * mcus_high {
        if restart > 0 && m > 0 && m % restart == 0 {
            if !bits.restart(next_restart) {
                return None;
            }
            next_restart += 1;
            planes.iter_mut().for_each(|p| p.predictor = 0);
        }
        let (mx, my) = (m % mcus_wide, m / mcus_wide);
        for p in &mut planes {
            for by in my * p.v..(my + 1) * p.v {
                for bx in mx * p.h..(mx + 1) * p.h {
                    // Wrapping: corrupt data may sum past i32, and must not panic.
                    p.predictor = p.predictor.wrapping_add(p.dc.dc_difference(&mut bits)?);
                    p.ac.skip_block(&mut bits)?;
                    // libjpeg's 1×1 inverse DCT: the DC over 8, rounded, shifted to 0-255.
                    let mean = ((i64::from(p.predictor) * i64::from(p.step) + 4) >> 3) + 128;
                    p.means[by * p.blocks_wide + bx] = mean.clamp(0, 255) as u8;
                }
            }
        }
    }
    Some(to_rgb(frame, &planes, h_max, v_max))
}

/// Each output pixel from its blocks, YCbCr to RGB as JFIF defines it. A subsampled plane is
/// interpolated bilinearly between its block centres (libjpeg's "fancy" upsampling is this
/// triangle filter for factors of two), clamped at the edges.
fn to_rgb(frame: &Frame, planes: &[Plane], h_max: usize, v_max: usize) -> DcImage {
    let (width, height) = (frame.width.div_ceil(8), frame.height.div_ceil(8));
    let mut rgb8 = Vec::with_capacity(width * height * 3);
    if let [grey] = planes {
        for y in 0..height {
            let row = &grey.means[y * grey.blocks_wide..][..width];
            rgb8.extend(row.iter().flat_map(|&l| [l, l, l]));
        }
        return DcImage { width, height, rgb8 };
    }
    let (luma, cb, cr) = (&planes[0], &planes[1], &planes[2]);
    let (cb_at, cr_at) = (Sampler::new(cb, h_max, v_max, width, height), Sampler::new(cr, h_max, v_max, width, height));
    // Rounds half up without libm's `roundf` call (a third of this function's time).
    let to_u8 = |v: f32| (v + 0.5).clamp(0.0, 255.0) as u8;
    for y in 0..height {
        let luma_row = &luma.means[y * luma.blocks_wide..][..width];
        for (x, &luma) in luma_row.iter().enumerate() {
            let luma = f32::from(luma);
            let (cb, cr) = (cb_at.at(cb, x, y) - 128.0, cr_at.at(cr, x, y) - 128.0);
            rgb8.extend_from_slice(&[
                to_u8(luma + 1.402 * cr),
                to_u8(luma - 0.344_136 * cb - 0.714_136 * cr),
                to_u8(luma + 1.772 * cb),
            ]);
        }
    }
    DcImage { width, height, rgb8 }
}

/// Bilinear weights from output pixels to a plane's blocks, per column and per row.
struct Sampler {
    columns: Vec<(usize, usize, f32)>,
    rows: Vec<(usize, usize, f32)>,
}

impl Sampler {
    fn new(p: &Plane, h_max: usize, v_max: usize, width: usize, height: usize) -> Sampler {
        // The plane's blocks that hold image data (the rest is MCU padding).
        let used = |n: usize, f: usize, max: usize| (n * f).div_ceil(max).max(1);
        let axis = |n: usize, f: usize, max: usize| -> Vec<(usize, usize, f32)> {
            let last = used(n, f, max) - 1;
            (0..n)
                .map(|i| {
                    let u = ((i as f32 + 0.5) * f as f32 / max as f32 - 0.5).clamp(0.0, last as f32);
                    let lo = u.floor() as usize;
                    (lo, (lo + 1).min(last), u - lo as f32)
                })
                .collect()
        };
        Sampler { columns: axis(width, p.h, h_max), rows: axis(height, p.v, v_max) }
    }

    fn at(&self, p: &Plane, x: usize, y: usize) -> f32 {
        let ((x0, x1, fx), (y0, y1, fy)) = (self.columns[x], self.rows[y]);
        let v = |bx: usize, by: usize| f32::from(p.means[by * p.blocks_wide + bx]);
        let top = v(x0, y0) + fx * (v(x1, y0) - v(x0, y0));
        let bottom = v(x0, y1) + fx * (v(x1, y1) - v(x0, y1));
        top + fy * (bottom - top)
    }
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;

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

    fn encoded(width: u32, height: u32, grey: bool) -> Vec<u8> {
        let value = |x: u32, y: u32, c: u32| {
            (128.0 + 100.0 * ((x as f64 / 37.0 + c as f64).sin() * (y as f64 / 23.0).cos())) as u8
        };
        let mut out = Vec::new();
        let format = image::ImageFormat::Jpeg;
        if grey {
            let img = image::GrayImage::from_fn(width, height, |x, y| image::Luma([value(x, y, 0)]));
            img.write_to(&mut Cursor::new(&mut out), format).unwrap();
        } else {
            let img = image::RgbImage::from_fn(width, height, |x, y| image::Rgb([0, 1, 2].map(|c| value(x, y, c))));
            img.write_to(&mut Cursor::new(&mut out), format).unwrap();
        }
        out
    }

    /// The full decode's (image's decoder) means over the 8×8 blocks.
    fn block_means(bytes: &[u8], width: usize, height: usize) -> Vec<u8> {
        let full = image::load_from_memory(bytes).unwrap().to_rgb8();
        let (w, h) = (full.width() as usize, full.height() as usize);
        let mut means = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            for x in 0..width {
                for c in 0..3 {
                    let (mut sum, mut n) = (0.0, 0.0);
                    for yy in y * 8..((y + 1) * 8).min(h) {
                        for xx in x * 8..((x + 1) * 8).min(w) {
                            sum += f64::from(full.get_pixel(xx as u32, yy as u32)[c]);
                            n += 1.0;
                        }
                    }
                    means.push((sum / n).round() as u8);
                }
            }
        }
        means
    }

    fn fixture(name: &str) -> Vec<u8> {
        std::fs::read(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("testdata").join(name)).unwrap()
    }

    #[test]
    fn the_dc_image_is_the_scaling_decoders_eighth() {
        let mut files: Vec<(String, Vec<u8>)> = [(1601, 1203, false), (1601, 1203, true), (40, 9, false)]
            .map(|(w, h, g)| (format!("{w}x{h} grey {g}"), encoded(w, h, g)))
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
            // Luma is the same block mean; chroma is replicated here where the reference
            // interpolates, so colour images differ a little along chroma edges.
            // Both are 1/8 images of the decoded picture: as close to its block means as the
            // scaling decoder, and within a level of it where there is no chroma to upsample.
            let truth = block_means(&bytes, rw, rh);
            let (ours, theirs) = (difference(&dc.rgb8, &truth).0, difference(&rgb, &truth).0);
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
        let baseline = encoded(64, 48, false);
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
}
