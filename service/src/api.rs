//! The answer to an estimate request, once, for both transports: HTTP serialises these structs
//! as JSON and gRPC converts them field by field, so the two agree exactly.

use serde::Serialize;

/// One pose (see `udapose.v1.PoseEstimate` for every field's meaning).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PoseAnswer {
    pub azimuth: f64,
    pub elevation: f64,
    pub theta: f64,
    pub azimuth_deg: f64,
    pub elevation_deg: f64,
    pub theta_deg: f64,
    pub distance: f64,
    /// Row-major R(a, e, θ).
    pub rotation: Vec<f64>,
    pub score: f64,
    pub hypotheses: Vec<HypothesisAnswer>,
    pub crop_box: BoxAnswer,
    /// 8 corners × (x, y) in image pixels.
    pub cuboid: Vec<f64>,
    pub model_version: String,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct HypothesisAnswer {
    pub azimuth: f64,
    pub elevation: f64,
    pub theta: f64,
    pub distance: f64,
    pub score: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct BoxAnswer {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Timings {
    pub decode_ms: f64,
    pub queue_ms: f64,
    pub crop_ms: f64,
    pub backbone_ms: f64,
    pub solver_ms: f64,
    pub total_ms: f64,
    pub batch_size: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EstimateAnswer {
    pub estimates: Vec<PoseAnswer>,
    pub model_version: String,
    pub frame_id: String,
    pub timings: Timings,
}

/// A decoded image: packed RGB8.
#[derive(Debug)]
pub struct Pixels {
    pub rgb8: Vec<u8>,
    pub width: usize,
    pub height: usize,
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
