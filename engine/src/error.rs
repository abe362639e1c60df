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
}

impl From<std::io::Error> for EngineError {
    fn from(e: std::io::Error) -> Self {
        EngineError::Io(e.to_string())
    }
}

pub type Result<T> = std::result::Result<T, EngineError>;
