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

mod huffman;

use huffman::{Bits, Huffman};

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
        let len = be16(bytes, pos)?;
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
            0xC2..=0xCF => return None, // progressive, lossless, arithmetic (DHT, C4, is above)
            0xDD => restart = be16(segment, 0)?,
            // Adobe's APP14: its transform flag may say the three components are RGB, not YCbCr.
            0xEE if segment.starts_with(b"Adobe") => return None,
            0xDA => return scan(&frame?, &tables, restart, segment, bytes.get(pos..)?),
            _ => {} // APPn, COM
        }
    }
}

/// The big-endian 16-bit number at `at`.
fn be16(s: &[u8], at: usize) -> Option<usize> {
    Some(usize::from(u16::from_be_bytes([*s.get(at)?, *s.get(at + 1)?])))
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
        let (height, width) = (be16(s, 1)?, be16(s, 3)?);
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
mod tests;
