//! Parsing `.npy` bytes: the preamble, the header's dict literal, the data by dtype.

use super::*;

/// An element type as the header's `descr` names it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Kind {
    Bool,
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F32,
    F64,
    /// `U n`: n UTF-32 code units per element.
    Str(usize),
    Object,
}

#[derive(Clone, Copy, Debug)]
pub(super) struct Dtype {
    kind: Kind,
    big_endian: bool,
}

impl Dtype {
    /// Bytes per element; `None` for pickled objects.
    fn item_size(self) -> Option<usize> {
        Some(match self.kind {
            Kind::Bool | Kind::U8 | Kind::I8 => 1,
            Kind::U16 | Kind::I16 => 2,
            Kind::U32 | Kind::I32 | Kind::F32 => 4,
            Kind::U64 | Kind::I64 | Kind::F64 => 8,
            Kind::Str(n) => 4 * n,
            Kind::Object => return None,
        })
    }

    /// `<f8`, `|u1`, `>i4`, `<U13`, `|O`, …
    fn parse(descr: &str) -> Result<Self> {
        let unsupported = || NpyError::UnsupportedDtype(descr.to_owned());
        let mut chars = descr.chars();
        let order = chars.next().ok_or_else(unsupported)?;
        let big_endian = match order {
            '<' | '|' | '=' => false,
            '>' => true,
            _ => return Err(unsupported()),
        };
        let kind = match chars.as_str() {
            "b1" => Kind::Bool,
            "u1" => Kind::U8,
            "i1" => Kind::I8,
            "u2" => Kind::U16,
            "i2" => Kind::I16,
            "u4" => Kind::U32,
            "i4" => Kind::I32,
            "u8" => Kind::U64,
            "i8" => Kind::I64,
            "f4" => Kind::F32,
            "f8" => Kind::F64,
            "O" => Kind::Object,
            // `<U0` has no bytes per element, so a huge shape would cost nothing to claim.
            s => match s.strip_prefix('U').and_then(|n| n.parse::<usize>().ok()) {
                Some(n) if n > 0 && n <= 1 << 20 => Kind::Str(n),
                _ => return Err(unsupported()),
            },
        };
        Ok(Dtype { kind, big_endian })
    }
}

/// The fields of a `.npy` header dict.
pub(super) struct Header {
    dtype: Dtype,
    fortran_order: bool,
    shape: Vec<usize>,
}

pub(super) fn parse_npy(bytes: &[u8], limits: &ReadLimits) -> Result<NpyArray> {
    let (header, data_start) = parse_preamble(bytes, limits)?;
    if header.fortran_order && header.shape.len() > 1 {
        return Err(NpyError::FortranOrder(header.shape));
    }
    let count = header.shape.iter().try_fold(1u64, |n, &d| n.checked_mul(d as u64));
    let data = &bytes[data_start..];
    let needed = match header.dtype.item_size() {
        Some(size) => count.and_then(|n| n.checked_mul(size as u64)),
        None => Some(data.len() as u64),
    };
    let needed = needed.ok_or_else(|| NpyError::BadHeader(format!("shape {:?} overflows 64 bits", header.shape)))?;
    if needed > data.len() as u64 {
        return Err(NpyError::Truncated { needed, available: data.len() as u64 });
    }
    // NumPy ignores bytes after the array; so do we.
    let data = decode(header.dtype, &data[..needed as usize])?;
    NpyArray::new(header.shape, data)
}

/// Magic, version and header; returns the header and the offset of the array data.
pub(super) fn parse_preamble(bytes: &[u8], limits: &ReadLimits) -> Result<(Header, usize)> {
    let magic_len = NPY_MAGIC.len();
    if bytes.len() < magic_len || &bytes[..magic_len] != NPY_MAGIC {
        return Err(if NPY_MAGIC.starts_with(bytes) {
            truncated(magic_len + 4, bytes.len())
        } else {
            NpyError::BadMagic
        });
    }
    let (major, minor) = match bytes.get(magic_len..magic_len + 2) {
        Some(v) => (v[0], v[1]),
        None => return Err(truncated(magic_len + 4, bytes.len())),
    };
    let len_bytes = match (major, minor) {
        (1, 0) => 2,
        (2, 0) | (3, 0) => 4,
        _ => return Err(NpyError::UnsupportedVersion(major, minor)),
    };
    let start = magic_len + 2 + len_bytes;
    let raw_len = bytes.get(magic_len + 2..start).ok_or_else(|| truncated(start, bytes.len()))?;
    let header_len = raw_len.iter().rev().fold(0usize, |n, &b| (n << 8) | usize::from(b));
    if header_len > limits.max_header_bytes {
        return Err(too_large(".npy header length", header_len as u64, limits.max_header_bytes as u64));
    }
    let end = start + header_len;
    let raw = bytes.get(start..end).ok_or_else(|| truncated(end, bytes.len()))?;
    // Versions 1.0 and 2.0 encode the header in latin-1, 3.0 in UTF-8.
    let text: String = if major == 3 {
        std::str::from_utf8(raw).map_err(|_| NpyError::BadHeader("header is not UTF-8".into()))?.to_owned()
    } else {
        raw.iter().map(|&b| char::from(b)).collect()
    };
    Ok((parse_header(&text)?, end))
}

pub(super) fn truncated(needed: usize, available: usize) -> NpyError {
    NpyError::Truncated { needed: needed as u64, available: available as u64 }
}

pub(super) fn decode(dtype: Dtype, bytes: &[u8]) -> Result<NpyData> {
    let big = dtype.big_endian;
    macro_rules! num {
        ($variant:ident, $t:ty) => {
            NpyData::$variant(decode_fixed(bytes, big, <$t>::from_le_bytes, <$t>::from_be_bytes))
        };
    }
    Ok(match dtype.kind {
        Kind::Bool => NpyData::Bool(bytes.iter().map(|&b| b != 0).collect()),
        Kind::U8 => NpyData::U8(bytes.to_vec()),
        Kind::I8 => num!(I8, i8),
        Kind::U16 => num!(U16, u16),
        Kind::I16 => num!(I16, i16),
        Kind::U32 => num!(U32, u32),
        Kind::I32 => num!(I32, i32),
        Kind::U64 => num!(U64, u64),
        Kind::I64 => num!(I64, i64),
        Kind::F32 => num!(F32, f32),
        Kind::F64 => num!(F64, f64),
        Kind::Str(width) => NpyData::Str(decode_strings(bytes, width, big)?),
        Kind::Object => NpyData::Object(bytes.to_vec()),
    })
}

pub(super) fn decode_fixed<const N: usize, T>(
    bytes: &[u8],
    big: bool,
    le: fn([u8; N]) -> T,
    be: fn([u8; N]) -> T,
) -> Vec<T> {
    bytes
        .chunks_exact(N)
        .map(|chunk| {
            let mut raw = [0u8; N];
            raw.copy_from_slice(chunk);
            if big { be(raw) } else { le(raw) }
        })
        .collect()
}

pub(super) fn decode_strings(bytes: &[u8], width: usize, big: bool) -> Result<Vec<String>> {
    let units = decode_fixed(bytes, big, u32::from_le_bytes, u32::from_be_bytes);
    units
        .chunks_exact(width)
        .map(|element| {
            let used = element.iter().rposition(|&u| u != 0).map_or(0, |i| i + 1);
            element[..used].iter().map(|&u| char::from_u32(u).ok_or(NpyError::BadString(u))).collect()
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Header dict: the Python literal `{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }`.

/// The subset of Python literals a `.npy` header uses.
#[derive(Debug)]
pub(super) enum Literal {
    Str(String),
    Bool(bool),
    Int(u64),
    Tuple(Vec<Literal>),
    /// A list (a structured dtype's descr): parsed only to be reported as unsupported.
    List,
}

pub(super) fn parse_header(text: &str) -> Result<Header> {
    let mut parser = LiteralParser { text: text.as_bytes(), pos: 0 };
    let dict = parser.dict()?;
    parser.skip_space();
    if parser.pos != parser.text.len() {
        return Err(NpyError::BadHeader(format!("unexpected text after the dict in {text:?}")));
    }
    let field = |name: &str| {
        dict.iter().find(|(k, _)| k == name).map(|(_, v)| v).ok_or_else(|| NpyError::BadHeader(format!("no {name:?}")))
    };
    let dtype = match field("descr")? {
        Literal::Str(descr) => Dtype::parse(descr)?,
        Literal::List => return Err(NpyError::UnsupportedDtype("structured dtype".into())),
        other => return Err(NpyError::BadHeader(format!("descr is {other:?}"))),
    };
    let fortran_order = match field("fortran_order")? {
        Literal::Bool(b) => *b,
        other => return Err(NpyError::BadHeader(format!("fortran_order is {other:?}"))),
    };
    let shape = match field("shape")? {
        Literal::Tuple(dims) => dims.iter().map(dim).collect::<Result<Vec<_>>>()?,
        other => return Err(NpyError::BadHeader(format!("shape is {other:?}"))),
    };
    Ok(Header { dtype, fortran_order, shape })
}

pub(super) fn dim(literal: &Literal) -> Result<usize> {
    match literal {
        Literal::Int(n) => usize::try_from(*n).map_err(|_| NpyError::BadHeader(format!("dimension {n} too large"))),
        other => Err(NpyError::BadHeader(format!("dimension {other:?}"))),
    }
}

pub(super) struct LiteralParser<'a> {
    text: &'a [u8],
    pos: usize,
}

impl LiteralParser<'_> {
    fn error(&self, what: &str) -> NpyError {
        NpyError::BadHeader(format!("{what} at byte {} of the header", self.pos))
    }

    fn skip_space(&mut self) {
        while self.text.get(self.pos).is_some_and(u8::is_ascii_whitespace) {
            self.pos += 1;
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_space();
        self.text.get(self.pos).copied()
    }

    fn expect(&mut self, byte: u8) -> Result<()> {
        if self.peek() != Some(byte) {
            return Err(self.error(&format!("expected {:?}", char::from(byte))));
        }
        self.pos += 1;
        Ok(())
    }

    /// `{ key: value, ... }` with string keys and an optional trailing comma.
    fn dict(&mut self) -> Result<Vec<(String, Literal)>> {
        self.expect(b'{')?;
        let mut fields = Vec::new();
        while self.peek() != Some(b'}') {
            let key = match self.value()? {
                Literal::Str(key) => key,
                _ => return Err(self.error("dict key is not a string")),
            };
            self.expect(b':')?;
            fields.push((key, self.value()?));
            if self.peek() == Some(b',') {
                self.pos += 1;
            } else if self.peek() != Some(b'}') {
                return Err(self.error("expected ',' or '}'"));
            }
        }
        self.pos += 1;
        Ok(fields)
    }

    fn value(&mut self) -> Result<Literal> {
        match self.peek() {
            Some(quote @ (b'\'' | b'"')) => self.string(quote),
            Some(b'(') => self.sequence(b')').map(Literal::Tuple),
            Some(b'[') => self.sequence(b']').map(|_| Literal::List),
            Some(b'0'..=b'9') => self.integer(),
            Some(_) if self.text[self.pos..].starts_with(b"True") => self.word(4, Literal::Bool(true)),
            Some(_) if self.text[self.pos..].starts_with(b"False") => self.word(5, Literal::Bool(false)),
            _ => Err(self.error("expected a value")),
        }
    }

    fn word(&mut self, len: usize, literal: Literal) -> Result<Literal> {
        self.pos += len;
        Ok(literal)
    }

    /// A quoted string without escapes (NumPy's descr and keys never contain any).
    fn string(&mut self, quote: u8) -> Result<Literal> {
        let start = self.pos + 1;
        let len =
            self.text[start..].iter().position(|&b| b == quote).ok_or_else(|| self.error("unterminated string"))?;
        let raw = &self.text[start..start + len];
        if raw.contains(&b'\\') {
            return Err(self.error("escaped string"));
        }
        self.pos = start + len + 1;
        let s = std::str::from_utf8(raw).map_err(|_| self.error("non-UTF-8 string"))?;
        Ok(Literal::Str(s.to_owned()))
    }

    /// A non-negative integer; Python 2 headers may carry an `L` suffix.
    fn integer(&mut self) -> Result<Literal> {
        let start = self.pos;
        while self.text.get(self.pos).is_some_and(u8::is_ascii_digit) {
            self.pos += 1;
        }
        let digits = std::str::from_utf8(&self.text[start..self.pos]).map_err(|_| self.error("bad integer"))?;
        let n = digits.parse::<u64>().map_err(|_| self.error("integer out of range"))?;
        if self.text.get(self.pos) == Some(&b'L') {
            self.pos += 1;
        }
        Ok(Literal::Int(n))
    }

    /// `(a, b, ...)` or `[a, b, ...]`, trailing comma allowed.
    fn sequence(&mut self, close: u8) -> Result<Vec<Literal>> {
        self.pos += 1;
        let mut items = Vec::new();
        while self.peek() != Some(close) {
            items.push(self.value()?);
            if self.peek() == Some(b',') {
                self.pos += 1;
            } else if self.peek() != Some(close) {
                return Err(self.error("expected ',' or the closing bracket"));
            }
        }
        self.pos += 1;
        Ok(items)
    }
}
