//! NumPy `.npy` / `.npz` files, read and written the way NumPy does.
//!
//! SynCar-OOD annotations must be readable by Python's `np.load`, and real NeMo exports are
//! `np.savez` archives, so this module speaks NumPy's format exactly:
//!
//! - `.npy` (format 1.0, 2.0 and 3.0 on read; 1.0, or 2.0 for huge headers, on write): the magic
//!   `\x93NUMPY`, a header that is a Python dict literal (`descr`, `fortran_order`, `shape`) padded
//!   with spaces so the data starts on a 64-byte boundary, then the raw C-order data.
//! - `.npz`: a zip of `<key>.npy` members. Reading accepts stored (`np.savez`) and deflated
//!   (`np.savez_compressed`) members. Writing stores the members in the given order with a fixed
//!   1980-01-01 timestamp, so the same arrays always give the same bytes.
//!
//! The writer reproduces NumPy's header byte for byte (including the 21-character growth padding
//! after the shape), so a `.npy` member written here is identical to the one `np.save` writes for
//! the same little-endian array.
//!
//! Reading never trusts a header: the element count is checked against the bytes actually present
//! before anything is allocated, zip members are read through a size cap (a deflate bomb stops at
//! [`ReadLimits::max_entry_bytes`]), and every failure is an [`NpyError`], never a panic.
//! Object arrays (`|O`, Python pickles such as NeMo's `occ_mask=None`) are kept as opaque bytes and
//! never unpickled.

use std::fs;
use std::io::{Cursor, Read, Seek, Write};
use std::path::Path;

use thiserror::Error;
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, DateTime, ZipArchive, ZipWriter};

mod read;
mod write;

use read::parse_npy;
use write::{encode_data, npy_header, str_width};

/// `\x93NUMPY`, the first six bytes of every `.npy` file.
pub const NPY_MAGIC: &[u8; 6] = b"\x93NUMPY";
/// NumPy aligns the start of the array data to this many bytes (numpy ≥ 1.14 header format).
pub const NPY_ALIGN: usize = 64;
/// NumPy leaves room for the first axis to grow to this many digits (`GROWTH_AXIS_MAX_DIGITS`).
const GROWTH_AXIS_MAX_DIGITS: usize = 21;

/// Errors from reading or writing `.npy` / `.npz` data.
#[derive(Debug, Error)]
pub enum NpyError {
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
    #[error("zip archive error: {0}")]
    Zip(#[from] zip::result::ZipError),
    #[error("not a .npy file (bad magic bytes)")]
    BadMagic,
    #[error("unsupported .npy format version {0}.{1}")]
    UnsupportedVersion(u8, u8),
    #[error("malformed .npy header: {0}")]
    BadHeader(String),
    #[error("unsupported dtype {0:?}")]
    UnsupportedDtype(String),
    #[error("Fortran-order arrays are not supported (shape {0:?})")]
    FortranOrder(Vec<usize>),
    #[error("truncated data: the header needs {needed} bytes, only {available} are present")]
    Truncated { needed: u64, available: u64 },
    #[error("{what} of {size} exceeds the limit of {limit}")]
    TooLarge { what: &'static str, size: u64, limit: u64 },
    #[error("invalid unicode code point {0:#x} in a string array")]
    BadString(u32),
    #[error("shape {shape:?} holds {expected} elements but {actual} were given")]
    ShapeMismatch { shape: Vec<usize>, expected: usize, actual: usize },
    #[error("npz member {0:?} is not a .npy file")]
    NotNpy(String),
    #[error("npz holds {0:?} twice")]
    DuplicateKey(String),
    #[error("npz has no array {0:?}")]
    MissingKey(String),
    #[error("array {key:?}: expected {expected}, found {found}")]
    WrongType { key: String, expected: &'static str, found: String },
    #[error("npz member {key:?}: {source}")]
    Entry { key: String, source: Box<NpyError> },
}

pub type Result<T, E = NpyError> = std::result::Result<T, E>;

/// Caps applied while reading, so a hostile or corrupt file cannot make us allocate without bound.
#[derive(Clone, Copy, Debug)]
pub struct ReadLimits {
    /// Largest uncompressed `.npy` member (or standalone file) accepted, in bytes.
    pub max_entry_bytes: u64,
    /// Most members accepted in one `.npz`.
    pub max_entries: usize,
    /// Longest header accepted; NumPy itself refuses headers over 10 000 bytes by default.
    pub max_header_bytes: usize,
}

impl Default for ReadLimits {
    fn default() -> Self {
        ReadLimits { max_entry_bytes: 1 << 30, max_entries: 4096, max_header_bytes: 10_000 }
    }
}

/// The elements of an array, flattened in C order, one variant per supported dtype.
#[derive(Clone, Debug, PartialEq)]
pub enum NpyData {
    Bool(Vec<bool>),
    U8(Vec<u8>),
    I8(Vec<i8>),
    U16(Vec<u16>),
    I16(Vec<i16>),
    U32(Vec<u32>),
    I32(Vec<i32>),
    U64(Vec<u64>),
    I64(Vec<i64>),
    F32(Vec<f32>),
    F64(Vec<f64>),
    /// `<U n` strings, trailing NULs removed (as NumPy does). Written with `n` = the longest one.
    Str(Vec<String>),
    /// `|O`: the pickle NumPy wrote, kept verbatim and never unpickled.
    Object(Vec<u8>),
}

impl NpyData {
    /// Element count (for `Object`, the count is only known from the shape).
    fn len(&self) -> Option<usize> {
        Some(match self {
            NpyData::Bool(v) => v.len(),
            NpyData::U8(v) => v.len(),
            NpyData::I8(v) => v.len(),
            NpyData::U16(v) => v.len(),
            NpyData::I16(v) => v.len(),
            NpyData::U32(v) => v.len(),
            NpyData::I32(v) => v.len(),
            NpyData::U64(v) => v.len(),
            NpyData::I64(v) => v.len(),
            NpyData::F32(v) => v.len(),
            NpyData::F64(v) => v.len(),
            NpyData::Str(v) => v.len(),
            NpyData::Object(_) => return None,
        })
    }

    /// The NumPy `descr` this data is written with (always little-endian).
    pub fn descr(&self) -> String {
        match self {
            NpyData::Bool(_) => "|b1".into(),
            NpyData::U8(_) => "|u1".into(),
            NpyData::I8(_) => "|i1".into(),
            NpyData::U16(_) => "<u2".into(),
            NpyData::I16(_) => "<i2".into(),
            NpyData::U32(_) => "<u4".into(),
            NpyData::I32(_) => "<i4".into(),
            NpyData::U64(_) => "<u8".into(),
            NpyData::I64(_) => "<i8".into(),
            NpyData::F32(_) => "<f4".into(),
            NpyData::F64(_) => "<f8".into(),
            NpyData::Str(v) => format!("<U{}", str_width(v)),
            NpyData::Object(_) => "|O".into(),
        }
    }
}

/// An N-d array: a shape (empty for a 0-d scalar) and its C-order elements.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    shape: Vec<usize>,
    data: NpyData,
}

impl NpyArray {
    /// Checks that the shape holds exactly as many elements as `data`.
    pub fn new(shape: Vec<usize>, data: NpyData) -> Result<Self> {
        if let Some(actual) = data.len() {
            let expected = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
            if expected != Some(actual) {
                return Err(NpyError::ShapeMismatch { shape, expected: expected.unwrap_or(usize::MAX), actual });
            }
        }
        Ok(NpyArray { shape, data })
    }

    /// A 0-d array.
    pub fn scalar(data: NpyData) -> Result<Self> {
        Self::new(Vec::new(), data)
    }

    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    pub fn data(&self) -> &NpyData {
        &self.data
    }

    pub fn into_parts(self) -> (Vec<usize>, NpyData) {
        (self.shape, self.data)
    }

    /// Number of elements (the product of the shape; 1 for a 0-d array).
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `descr` and shape, for error messages.
    pub fn describe(&self) -> String {
        format!("dtype {} shape {:?}", self.data.descr(), self.shape)
    }

    /// Every element as `f64` (any integer, float or bool dtype), like `arr.astype(float)`.
    pub fn to_f64_vec(&self) -> Option<Vec<f64>> {
        Some(match &self.data {
            NpyData::Bool(v) => v.iter().map(|&b| f64::from(u8::from(b))).collect(),
            NpyData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::I8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::U16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::I16(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::U32(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::I32(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::U64(v) => v.iter().map(|&x| x as f64).collect(),
            NpyData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            NpyData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
            NpyData::F64(v) => v.clone(),
            NpyData::Str(_) | NpyData::Object(_) => return None,
        })
    }

    /// Every element as `i64`. Floats are accepted when integral, because MATLAB-derived
    /// annotations (PASCAL3D+ `.mat` files) store indices and sizes as doubles.
    pub fn to_i64_vec(&self) -> Option<Vec<i64>> {
        match &self.data {
            NpyData::U64(v) => v.iter().map(|&x| i64::try_from(x).ok()).collect(),
            NpyData::I64(v) => Some(v.clone()),
            NpyData::F32(_) | NpyData::F64(_) => self
                .to_f64_vec()?
                .into_iter()
                .map(|x| (x.fract() == 0.0 && x.abs() < 9.0e15).then_some(x as i64))
                .collect(),
            // All remaining numeric dtypes convert exactly through f64.
            _ => self.to_f64_vec().map(|v| v.into_iter().map(|x| x as i64).collect()),
        }
    }

    /// Every element as `u8`, for masks: `u8` and `bool` arrays, or integers within 0..=255.
    pub fn to_u8_vec(&self) -> Option<Vec<u8>> {
        match &self.data {
            NpyData::U8(v) => Some(v.clone()),
            NpyData::Bool(v) => Some(v.iter().map(|&b| u8::from(b)).collect()),
            NpyData::F32(_) | NpyData::F64(_) | NpyData::Str(_) | NpyData::Object(_) => None,
            _ => self.to_i64_vec()?.into_iter().map(|x| u8::try_from(x).ok()).collect(),
        }
    }

    /// The string of a one-element string array (`np.array("car")`).
    pub fn as_str(&self) -> Option<&str> {
        match &self.data {
            NpyData::Str(v) if v.len() == 1 => Some(&v[0]),
            _ => None,
        }
    }
}

macro_rules! scalar_from {
    ($($t:ty => $variant:ident),*) => {$(
        impl From<$t> for NpyArray {
            /// A 0-d array, as `np.savez(key=value)` stores a Python/NumPy scalar.
            fn from(v: $t) -> Self {
                NpyArray { shape: Vec::new(), data: NpyData::$variant(vec![v]) }
            }
        }
        impl From<Vec<$t>> for NpyArray {
            /// A 1-d array.
            fn from(v: Vec<$t>) -> Self {
                NpyArray { shape: vec![v.len()], data: NpyData::$variant(v) }
            }
        }
    )*};
}

scalar_from!(bool => Bool, u8 => U8, i8 => I8, u16 => U16, i16 => I16, u32 => U32, i32 => I32, u64 => U64,
    i64 => I64, f32 => F32, f64 => F64, String => Str);

impl From<&str> for NpyArray {
    fn from(v: &str) -> Self {
        NpyArray::from(v.to_owned())
    }
}

impl<const N: usize> From<[f64; N]> for NpyArray {
    fn from(v: [f64; N]) -> Self {
        NpyArray::from(v.to_vec())
    }
}

/// A `.npz` archive: named arrays in archive order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Npz {
    entries: Vec<(String, NpyArray)>,
}

impl Npz {
    pub fn new() -> Self {
        Npz::default()
    }

    /// Adds `key`, or replaces its array in place (keeping its position).
    pub fn insert(&mut self, key: impl Into<String>, array: impl Into<NpyArray>) {
        let (key, array) = (key.into(), array.into());
        match self.entries.iter_mut().find(|(k, _)| *k == key) {
            Some(slot) => slot.1 = array,
            None => self.entries.push((key, array)),
        }
    }

    pub fn get(&self, key: &str) -> Option<&NpyArray> {
        self.entries.iter().find(|(k, _)| k == key).map(|(_, a)| a)
    }

    pub fn require(&self, key: &str) -> Result<&NpyArray> {
        self.get(key).ok_or_else(|| NpyError::MissingKey(key.to_owned()))
    }

    pub fn contains(&self, key: &str) -> bool {
        self.get(key).is_some()
    }

    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.entries.iter().map(|(k, _)| k.as_str())
    }

    pub fn iter(&self) -> impl Iterator<Item = (&str, &NpyArray)> {
        self.entries.iter().map(|(k, a)| (k.as_str(), a))
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// A one-element numeric array as `f64` (like Python's `float(npz[key])`).
    pub fn f64_scalar(&self, key: &str) -> Result<f64> {
        let array = self.require(key)?;
        one(array.to_f64_vec()).ok_or_else(|| wrong_type(key, "one number", array))
    }

    /// A one-element integer (or integral float) array as `i64` (like Python's `int(npz[key])`).
    pub fn i64_scalar(&self, key: &str) -> Result<i64> {
        let array = self.require(key)?;
        one(array.to_i64_vec()).ok_or_else(|| wrong_type(key, "one integer", array))
    }

    /// A one-element string array.
    pub fn str_scalar(&self, key: &str) -> Result<&str> {
        let array = self.require(key)?;
        array.as_str().ok_or_else(|| wrong_type(key, "one string", array))
    }

    /// Shape and elements of a numeric array, converted to `f64`.
    pub fn f64_array(&self, key: &str) -> Result<(Vec<usize>, Vec<f64>)> {
        let array = self.require(key)?;
        let data = array.to_f64_vec().ok_or_else(|| wrong_type(key, "a numeric array", array))?;
        Ok((array.shape.clone(), data))
    }

    /// Shape and elements of a `u8` or `bool` array (masks).
    pub fn u8_array(&self, key: &str) -> Result<(Vec<usize>, Vec<u8>)> {
        let array = self.require(key)?;
        let data = array.to_u8_vec().ok_or_else(|| wrong_type(key, "a uint8 or bool array", array))?;
        Ok((array.shape.clone(), data))
    }

    /// Reads an archive held in memory, with the default [`ReadLimits`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        Self::read_from(Cursor::new(bytes), &ReadLimits::default())
    }

    /// Reads an archive from disk, with the default [`ReadLimits`].
    pub fn read_path(path: impl AsRef<Path>) -> Result<Self> {
        Self::read_from(fs::File::open(path)?, &ReadLimits::default())
    }

    /// Reads every member of an archive (stored or deflated) within `limits`.
    pub fn read_from<R: Read + Seek>(reader: R, limits: &ReadLimits) -> Result<Self> {
        let mut archive = ZipArchive::new(reader)?;
        if archive.len() > limits.max_entries {
            return Err(too_large("npz member count", archive.len() as u64, limits.max_entries as u64));
        }
        let mut npz = Npz::new();
        for index in 0..archive.len() {
            let (key, bytes) = read_member(&mut archive, index, limits)?;
            if npz.contains(&key) {
                return Err(NpyError::DuplicateKey(key));
            }
            let array =
                parse_npy(&bytes, limits).map_err(|e| NpyError::Entry { key: key.clone(), source: e.into() })?;
            npz.entries.push((key, array));
        }
        Ok(npz)
    }

    /// The archive as `np.savez` lays it out: stored `<key>.npy` members in insertion order.
    /// Timestamps are fixed at 1980-01-01 00:00 so equal arrays give byte-identical archives.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let options = SimpleFileOptions::default()
            .compression_method(CompressionMethod::Stored)
            .last_modified_time(DateTime::default())
            .unix_permissions(0o644);
        let mut zip = ZipWriter::new(Cursor::new(Vec::new()));
        for (key, array) in &self.entries {
            zip.start_file(format!("{key}.npy"), options)?;
            zip.write_all(&npy_bytes(array))?;
        }
        Ok(zip.finish()?.into_inner())
    }

    /// Writes [`Npz::to_bytes`] to `path` through a temporary file and a rename, so a crash never
    /// leaves a half-written annotation that a resumed run would take for a finished one.
    pub fn write_path(&self, path: impl AsRef<Path>) -> Result<()> {
        crate::atomic::write_atomic(path.as_ref(), &self.to_bytes()?)?;
        Ok(())
    }
}

fn one<T>(values: Option<Vec<T>>) -> Option<T> {
    let mut values = values?;
    if values.len() == 1 { values.pop() } else { None }
}

fn wrong_type(key: &str, expected: &'static str, array: &NpyArray) -> NpyError {
    NpyError::WrongType { key: key.to_owned(), expected, found: array.describe() }
}

fn too_large(what: &'static str, size: u64, limit: u64) -> NpyError {
    NpyError::TooLarge { what, size, limit }
}

/// Name (without `.npy`) and bytes of one member, read through the size cap.
fn read_member<R: Read + Seek>(
    archive: &mut ZipArchive<R>,
    index: usize,
    limits: &ReadLimits,
) -> Result<(String, Vec<u8>)> {
    let mut member = archive.by_index(index)?;
    let name = member.name().to_owned();
    let key = name.strip_suffix(".npy").ok_or_else(|| NpyError::NotNpy(name.clone()))?.to_owned();
    let cap = limits.max_entry_bytes;
    if member.size() > cap {
        return Err(too_large("npz member size", member.size(), cap));
    }
    // The declared size may lie: read at most cap + 1 bytes; the buffer only grows with real data.
    let mut bytes = Vec::new();
    member.by_ref().take(cap.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > cap {
        return Err(too_large("npz member size", bytes.len() as u64, cap));
    }
    Ok((key, bytes))
}

// ---------------------------------------------------------------------------------------------
// .npy

/// Parses a standalone `.npy` file held in memory, with the default [`ReadLimits`].
pub fn read_npy(bytes: &[u8]) -> Result<NpyArray> {
    parse_npy(bytes, &ReadLimits::default())
}

/// Reads a `.npy` file from disk.
pub fn read_npy_path(path: impl AsRef<Path>) -> Result<NpyArray> {
    let limits = ReadLimits::default();
    let file = fs::File::open(path)?;
    let size = file.metadata()?.len();
    if size > limits.max_entry_bytes {
        return Err(too_large(".npy file size", size, limits.max_entry_bytes));
    }
    let mut bytes = Vec::new();
    file.take(limits.max_entry_bytes).read_to_end(&mut bytes)?;
    parse_npy(&bytes, &limits)
}

/// The `.npy` bytes NumPy's `np.save` writes for this array.
pub fn npy_bytes(array: &NpyArray) -> Vec<u8> {
    let mut out = npy_header(&array.data.descr(), &array.shape);
    encode_data(&array.data, &mut out);
    out
}

/// Writes a `.npy` file.
pub fn write_npy_path(path: impl AsRef<Path>, array: &NpyArray) -> Result<()> {
    fs::write(path, npy_bytes(array))?;
    Ok(())
}
