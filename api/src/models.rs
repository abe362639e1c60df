//! What the model routes answer (`GET /v1/models`, `GET /v1/models/{category}`, `ModelService`).

use serde::{Deserialize, Serialize};
use udapose_proto::v1 as pb;
use utoipa::ToSchema;

/// One served category.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Model)]
pub struct ModelSummary {
    pub category: String,
    /// The active version; `null` before one is loaded.
    pub version: Option<String>,
    pub ready: bool,
    /// Why the category cannot serve, when it cannot (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// Every configured category.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Models)]
pub struct ModelList {
    pub models: Vec<ModelSummary>,
}

/// A category's active model in full.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ModelDescription {
    pub category: String,
    /// The active version; empty before one is loaded.
    pub version: String,
    pub ready: bool,
    /// The activation generation being served.
    pub generation: u64,
    /// The version the model was trained as (its manifest's `version`).
    pub trained_as: String,
    pub backbone: String,
    pub feature_dim: u32,
    pub vertices: u32,
    pub crop_height: u32,
    pub crop_width: u32,
    /// The cuboid's `min` then `max` corner.
    pub cuboid: Vec<f64>,
    /// Why the model is not ready; empty when it is.
    pub error: String,
    /// The model's manifest (training provenance and metrics); `null` before one is loaded.
    #[schema(value_type = Object)]
    pub manifest: serde_json::Value,
}

impl From<ModelSummary> for pb::ModelInfo {
    fn from(s: ModelSummary) -> Self {
        pb::ModelInfo { category: s.category, version: s.version.unwrap_or_default(), ready: s.ready }
    }
}

impl From<pb::ModelInfo> for ModelSummary {
    fn from(m: pb::ModelInfo) -> Self {
        let version = (!m.version.is_empty()).then_some(m.version);
        ModelSummary { category: m.category, version, ready: m.ready, error: None }
    }
}

impl From<ModelDescription> for pb::ModelDescription {
    fn from(d: ModelDescription) -> Self {
        let version = (!d.version.is_empty()).then(|| d.version.clone());
        let manifest_json = if d.manifest.is_null() { String::new() } else { d.manifest.to_string() };
        pb::ModelDescription {
            info: Some(ModelSummary { category: d.category, version, ready: d.ready, error: None }.into()),
            generation: d.generation,
            trained_as: d.trained_as,
            backbone: d.backbone,
            feature_dim: d.feature_dim,
            vertices: d.vertices,
            crop_height: d.crop_height,
            crop_width: d.crop_width,
            cuboid: d.cuboid,
            error: d.error,
            manifest_json,
        }
    }
}

impl From<pb::ModelDescription> for ModelDescription {
    fn from(d: pb::ModelDescription) -> Self {
        let info = d.info.unwrap_or_default();
        ModelDescription {
            category: info.category,
            version: info.version,
            ready: info.ready,
            generation: d.generation,
            trained_as: d.trained_as,
            backbone: d.backbone,
            feature_dim: d.feature_dim,
            vertices: d.vertices,
            crop_height: d.crop_height,
            crop_width: d.crop_width,
            cuboid: d.cuboid,
            error: d.error,
            // A manifest that does not parse is shown as absent rather than failing the listing.
            manifest: serde_json::from_str(&d.manifest_json).unwrap_or(serde_json::Value::Null),
        }
    }
}
