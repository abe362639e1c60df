//! The entropy-coded data: canonical Huffman tables and the bit reader.

/// Codes of up to this many bits are decoded by one table lookup.
const FAST: u32 = 12;

/// A canonical Huffman table: a lookup for short codes, JPEG's MAXCODE/VALPTR for the rest.
pub(super) struct Huffman {
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
    pub(super) fn new(counts: &[u8; 16], symbols: &[u8], ac: bool) -> Option<Huffman> {
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
    pub(super) fn dc_difference(&self, bits: &mut Bits) -> Option<i32> {
        let size = u32::from(self.symbol(bits)?);
        if size > 11 {
            return None;
        }
        // `symbol` refilled to ≥ 57 bits and took ≤ 16: the value's ≤ 11 bits are there.
        Some(bits.value(size))
    }

    /// The next symbol of a DC table (which has no `SKIP` entries); `None` for a code in no
    /// table (corrupt data).
    fn symbol(&self, bits: &mut Bits) -> Option<u8> {
        bits.refill();
        self.decode(self.fast[bits.peek(FAST) as usize], bits)
    }

    /// The symbol of a plain `fast` entry, or of a code too long for it.
    fn decode(&self, entry: u16, bits: &mut Bits) -> Option<u8> {
        if entry == 0 {
            return self.slow(bits);
        }
        bits.consume(u32::from(entry & 0x1F));
        Some((entry >> 8) as u8)
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
    pub(super) fn skip_block(&self, bits: &mut Bits) -> Option<()> {
        let mut k = 1;
        while k < 64 {
            bits.refill();
            let entry = self.fast[bits.peek(FAST) as usize];
            if entry & SKIP != 0 {
                bits.consume(u32::from(entry & 0x1F));
                k += usize::from((entry >> 8) & 0x1F);
                continue;
            }
            let symbol = self.decode(entry, bits)?;
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
pub(super) struct Bits<'a> {
    data: &'a [u8],
    pos: usize,
    buffer: u64,
    count: u32,
    at_marker: bool,
}

impl<'a> Bits<'a> {
    pub(super) fn new(data: &'a [u8]) -> Bits<'a> {
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
    pub(super) fn restart(&mut self, n: usize) -> bool {
        // All that is left of the interval is its last byte's padding bits (in the buffer or
        // not yet read); the marker follows it. Never-read bytes before it mean corrupt data,
        // which the marker test below then refuses.
        while !self.at_marker {
            self.next_byte();
        }
        let marker = [0xFF, 0xD0 + (n % 8) as u8];
        let ok = self.data.get(self.pos..self.pos + 2) == Some(&marker[..]);
        self.pos += 2;
        (self.buffer, self.count, self.at_marker) = (0, 0, false);
        ok
    }
}
