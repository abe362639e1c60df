//! Dataset readers: SynCar-OOD (udapose's own benchmark, which it also writes) and the
//! NeMo-preprocessed PASCAL3D+, Occluded PASCAL3D+ and OOD-CV exports (BENCHMARK.md §4).
//!
//! Both readers return the ground truth in the pixel frame of the crop the model sees
//! ([`CropPose`]) and say where that frame came from ([`CropFrame`]). Opening a split only reads
//! its list files; annotations are loaded per sample, because a full SynCar split holds
//! thousands of H×W masks.

pub mod nemo;
pub mod syncar;

use std::fs;
use std::path::{Path, PathBuf};

use thiserror::Error;
use udapose_engine::{Camera, EngineError, Pose};

use crate::npz::{NpyError, Npz};

/// Errors from reading or writing a dataset on disk; each names the file at fault.
#[derive(Debug, Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {source}")]
    Npz { path: PathBuf, source: NpyError },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
}

pub type Result<T, E = DatasetError> = std::result::Result<T, E>;

impl DatasetError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        DatasetError::Io { path: path.to_owned(), source }
    }

    pub(crate) fn npz(path: &Path, source: NpyError) -> Self {
        DatasetError::Npz { path: path.to_owned(), source }
    }

    pub(crate) fn invalid(path: &Path, message: impl Into<String>) -> Self {
        DatasetError::Invalid { path: path.to_owned(), message: message.into() }
    }
}

/// Where a sample's [`CropPose`] comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CropFrame {
    /// Stored in the crop's own frame (SynCar-OOD): the values are used as written.
    Native,
    /// Converted from a NeMo export's *original-image* annotation: NeMo resized the image by
    /// `distance / 5` and cut a fixed box centred on the scaled principal point, so in the crop
    /// the object is at distance 5 (in the default export), the viewport is unchanged and the
    /// principal point is the crop centre. Angles are unchanged.
    NemoNormalised,
}

/// Pose and camera of the object in the pixel frame of one crop (METHOD.md §2 convention).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CropPose {
    /// Radians.
    pub azimuth: f64,
    pub elevation: f64,
    pub theta: f64,
    /// CAD units (a car is about 1 unit long).
    pub distance: f64,
    /// `[px, py]` = (column, row) in continuous pixel coordinates.
    pub principal: [f64; 2],
    /// PASCAL3D+'s viewport `M`; the focal length in pixels is `focal · viewport`.
    pub viewport: f64,
    /// PASCAL3D+'s focal, 1 in practice.
    pub focal: f64,
    /// Crop size in pixels.
    pub height: usize,
    pub width: usize,
}

impl CropPose {
    pub fn pose(&self) -> Pose {
        Pose::new(self.azimuth, self.elevation, self.theta, self.distance)
    }

    /// The engine's camera for this crop (focal length `focal · viewport` pixels).
    pub fn camera(&self) -> Result<Camera, EngineError> {
        Camera::new(self.focal * self.viewport, self.principal, self.width, self.height)
    }
}

/// A row-major `height × width` mask of 0/1 (or 0..=255) values.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mask {
    pub height: usize,
    pub width: usize,
    pub data: Vec<u8>,
}

impl Mask {
    /// Checks that `data` holds `height · width` values.
    pub fn new(height: usize, width: usize, data: Vec<u8>) -> Option<Self> {
        (height.checked_mul(width) == Some(data.len())).then_some(Mask { height, width, data })
    }

    pub fn get(&self, row: usize, col: usize) -> Option<u8> {
        if row < self.height && col < self.width { self.data.get(row * self.width + col).copied() } else { None }
    }

    /// Number of non-zero pixels.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&v| v != 0).count()
    }
}

/// Non-empty, trimmed lines of a list file (tolerates CRLF and a missing final newline).
pub(crate) fn read_list(path: &Path) -> Result<Vec<String>> {
    let text = fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
    Ok(text.lines().map(str::trim).filter(|l| !l.is_empty()).map(str::to_owned).collect())
}

/// The file name without its last extension (`a.b.png` → `a.b`).
pub(crate) fn file_stem(name: &str) -> &str {
    Path::new(name).file_stem().and_then(|s| s.to_str()).unwrap_or(name)
}

/// A 2-D `u8`/`bool` array from an npz as a [`Mask`].
pub(crate) fn mask_from(npz: &Npz, key: &str) -> Result<Mask, NpyError> {
    let (shape, data) = npz.u8_array(key)?;
    match shape[..] {
        [height, width] => Ok(Mask { height, width, data }),
        _ => {
            Err(NpyError::WrongType { key: key.to_owned(), expected: "a 2-D mask", found: format!("shape {shape:?}") })
        }
    }
}

/// A 2-element numeric array, e.g. `principal = [px, py]`.
pub(crate) fn pair(npz: &Npz, key: &str) -> Result<[f64; 2], NpyError> {
    match npz.f64_array(key)?.1[..] {
        [a, b] => Ok([a, b]),
        _ => Err(NpyError::WrongType {
            key: key.to_owned(),
            expected: "two numbers",
            found: npz.require(key)?.describe(),
        }),
    }
}

/// A non-negative integer scalar (image sizes).
pub(crate) fn size(npz: &Npz, key: &str) -> Result<usize, NpyError> {
    let value = npz.i64_scalar(key)?;
    usize::try_from(value).map_err(|_| NpyError::WrongType {
        key: key.to_owned(),
        expected: "a non-negative size",
        found: value.to_string(),
    })
}
