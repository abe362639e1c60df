//! Typed errors of the engine: every bad input maps to one of these, never to a panic.

use thiserror::Error;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum EngineError {
    #[error("invalid pose: {0}")]
    InvalidPose(String),
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    #[error("image size {width}x{height} is empty")]
    EmptyImage { width: usize, height: usize },
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    #[error("mesh file, line {line}: {message}")]
    MeshFormat { line: usize, message: String },
    #[error("mesh file I/O: {0}")]
    Io(String),
    #[error("invalid input: {0}")]
    InvalidInput(String),
    #[error("cancelled")]
    Cancelled,
    #[error("checkpoint: {0}")]
    Checkpoint(#[from] CheckpointError),
}

/// Why a weights file could not be loaded (e.g. `Backbone::load_trunk`). Nothing is
/// written into the model when any of these is returned.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum CheckpointError {
    #[error("{path}: no such file")]
    NotFound { path: String },
    #[error("{path}: not a readable safetensors file: {reason}")]
    Format { path: String, reason: String },
    #[error("{path}: missing {} key(s): {}", keys.len(), key_list(keys))]
    MissingKeys { path: String, keys: Vec<String> },
    #[error("{path}: unexpected {} key(s) (a file for another architecture?): {}", keys.len(), key_list(keys))]
    UnexpectedKeys { path: String, keys: Vec<String> },
    #[error("{path}: {key} has shape {found:?}, expected {expected:?}")]
    Shape { path: String, key: String, expected: Vec<i64>, found: Vec<i64> },
    #[error("{path}: {key} has dtype {found}, expected a floating-point tensor")]
    Dtype { path: String, key: String, found: String },
}

/// The first few keys of a sorted list, for error messages.
fn key_list(keys: &[String]) -> String {
    const SHOWN: usize = 6;
    let mut s = keys.iter().take(SHOWN).cloned().collect::<Vec<_>>().join(", ");
    if keys.len() > SHOWN {
        s.push_str(&format!(", ... and {} more", keys.len() - SHOWN));
    }
    s
}

impl From<std::io::Error> for EngineError {
    fn from(e: std::io::Error) -> Self {
        EngineError::Io(e.to_string())
    }
}

pub type Result<T> = std::result::Result<T, EngineError>;
