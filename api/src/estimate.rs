//! The answer to an estimate request (`POST /v1/pose/{category}`, `PoseService.Estimate`).

use serde::{Deserialize, Serialize};
use udapose_proto::v1 as pb;
use utoipa::ToSchema;

/// One pose. Angles follow PASCAL3D+ (radians, with degree copies).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = PoseEstimate)]
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
    /// The refined hypotheses, best first (the first is the pose above).
    pub hypotheses: Vec<HypothesisAnswer>,
    /// How ambiguous the answer is: its score lead over the best hypothesis that ends more than
    /// 30° from it (a front/back flip, say); absent when every hypothesis agrees. A lead near 0
    /// means the image supports both poses almost equally.
    pub runner_up_gap: Option<f64>,
    pub crop_box: BoxAnswer,
    /// 8 corners × (x, y) in image pixels.
    pub cuboid: Vec<f64>,
    pub model_version: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Hypothesis)]
pub struct HypothesisAnswer {
    pub azimuth: f64,
    pub elevation: f64,
    pub theta: f64,
    pub distance: f64,
    pub score: f64,
}

/// A box in image pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Box)]
pub struct BoxAnswer {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

/// Where the request's time went, milliseconds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Timings {
    pub decode_ms: f64,
    pub queue_ms: f64,
    pub crop_ms: f64,
    pub backbone_ms: f64,
    pub solver_ms: f64,
    pub total_ms: f64,
    /// Crops in the backbone batch this request's crops ran in.
    pub batch_size: u32,
}

/// One estimate per box (or one for the whole image).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = EstimateResponse)]
pub struct EstimateAnswer {
    pub estimates: Vec<PoseAnswer>,
    pub model_version: String,
    pub frame_id: String,
    pub timings: Timings,
}

impl From<HypothesisAnswer> for pb::Hypothesis {
    fn from(h: HypothesisAnswer) -> Self {
        pb::Hypothesis {
            azimuth: h.azimuth,
            elevation: h.elevation,
            theta: h.theta,
            distance: h.distance,
            score: h.score,
        }
    }
}

impl From<pb::Hypothesis> for HypothesisAnswer {
    fn from(h: pb::Hypothesis) -> Self {
        HypothesisAnswer {
            azimuth: h.azimuth,
            elevation: h.elevation,
            theta: h.theta,
            distance: h.distance,
            score: h.score,
        }
    }
}

impl From<BoxAnswer> for pb::BoundingBox {
    fn from(b: BoxAnswer) -> Self {
        pb::BoundingBox { x0: b.x0, y0: b.y0, x1: b.x1, y1: b.y1 }
    }
}

impl From<pb::BoundingBox> for BoxAnswer {
    fn from(b: pb::BoundingBox) -> Self {
        BoxAnswer { x0: b.x0, y0: b.y0, x1: b.x1, y1: b.y1 }
    }
}

impl From<PoseAnswer> for pb::PoseEstimate {
    fn from(p: PoseAnswer) -> Self {
        pb::PoseEstimate {
            azimuth: p.azimuth,
            elevation: p.elevation,
            theta: p.theta,
            azimuth_deg: p.azimuth_deg,
            elevation_deg: p.elevation_deg,
            theta_deg: p.theta_deg,
            distance: p.distance,
            rotation: p.rotation,
            score: p.score,
            hypotheses: p.hypotheses.into_iter().map(Into::into).collect(),
            runner_up_gap: p.runner_up_gap,
            crop_box: Some(p.crop_box.into()),
            cuboid: p.cuboid,
            model_version: p.model_version,
        }
    }
}

impl From<pb::PoseEstimate> for PoseAnswer {
    fn from(p: pb::PoseEstimate) -> Self {
        PoseAnswer {
            azimuth: p.azimuth,
            elevation: p.elevation,
            theta: p.theta,
            azimuth_deg: p.azimuth_deg,
            elevation_deg: p.elevation_deg,
            theta_deg: p.theta_deg,
            distance: p.distance,
            rotation: p.rotation,
            score: p.score,
            hypotheses: p.hypotheses.into_iter().map(Into::into).collect(),
            runner_up_gap: p.runner_up_gap,
            crop_box: p.crop_box.map(Into::into).unwrap_or_default(),
            cuboid: p.cuboid,
            model_version: p.model_version,
        }
    }
}

impl From<Timings> for pb::Timings {
    fn from(t: Timings) -> Self {
        pb::Timings {
            decode_ms: t.decode_ms,
            queue_ms: t.queue_ms,
            crop_ms: t.crop_ms,
            backbone_ms: t.backbone_ms,
            solver_ms: t.solver_ms,
            total_ms: t.total_ms,
            batch_size: t.batch_size,
        }
    }
}

impl From<pb::Timings> for Timings {
    fn from(t: pb::Timings) -> Self {
        Timings {
            decode_ms: t.decode_ms,
            queue_ms: t.queue_ms,
            crop_ms: t.crop_ms,
            backbone_ms: t.backbone_ms,
            solver_ms: t.solver_ms,
            total_ms: t.total_ms,
            batch_size: t.batch_size,
        }
    }
}

impl From<EstimateAnswer> for pb::EstimateResponse {
    fn from(a: EstimateAnswer) -> Self {
        pb::EstimateResponse {
            estimates: a.estimates.into_iter().map(Into::into).collect(),
            model_version: a.model_version,
            frame_id: a.frame_id,
            timings: Some(a.timings.into()),
            error: None,
        }
    }
}

impl From<pb::EstimateResponse> for EstimateAnswer {
    fn from(r: pb::EstimateResponse) -> Self {
        EstimateAnswer {
            estimates: r.estimates.into_iter().map(Into::into).collect(),
            model_version: r.model_version,
            frame_id: r.frame_id,
            timings: r.timings.map(Into::into).unwrap_or_default(),
        }
    }
}
