//! What a transport hands the service for an estimate, and the answer's types (from
//! `udapose-api`: HTTP serialises them, gRPC converts them, the CLI prints them).

pub use udapose_api::{BoxAnswer, EstimateAnswer, HypothesisAnswer, PoseAnswer, Timings};

/// A decoded image: packed RGB8.
#[derive(Debug)]
pub struct Pixels {
    pub rgb8: Vec<u8>,
    pub width: usize,
    pub height: usize,
    /// `[width, height]` of the encoded image: `[width, height]` unless the image was kept at a
    /// reduced size ([`crate::decode::Header::decode_for`]); boxes and answers are in its pixels.
    pub encoded: [usize; 2],
}

/// What a transport hands the service.
#[derive(Debug)]
pub enum ImageInput {
    /// PNG, JPEG or WebP bytes.
    Encoded(bytes::Bytes),
    /// Raw RGB8 with its size.
    Raw { width: u32, height: u32, rgb8: bytes::Bytes },
}

#[derive(Debug)]
pub struct EstimateInput {
    pub category: String,
    pub image: ImageInput,
    /// `(x0, y0, x1, y1)` in image pixels; empty: the image is the crop.
    pub boxes: Vec<[f64; 4]>,
    pub frame_id: String,
    /// The caller's deadline, if any (gRPC timeout or `timeout_ms`).
    pub timeout: Option<std::time::Duration>,
}
