//! What the model routes answer, for any transport: a category's summary and description.

use udapose_engine::checkpoint::Manifest;

use crate::registry::Category;

/// One served category, as `ListModels` and `GET /v1/models` list it.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelSummary {
    pub category: String,
    /// The active version; `None` before one is loaded.
    pub version: Option<String>,
    pub ready: bool,
    /// Why the category cannot serve, when it cannot.
    pub error: Option<String>,
}

/// A category's active model in full, as `DescribeModel` and `GET /v1/models/{category}`
/// describe it.
#[derive(Clone, Debug)]
pub struct ModelDescription {
    pub summary: ModelSummary,
    pub generation: u64,
    /// The version the model was trained as (its manifest's `version`).
    pub trained_as: String,
    pub backbone: String,
    pub feature_dim: usize,
    pub vertices: usize,
    /// `[H, W]`.
    pub crop: [usize; 2],
    /// The cuboid's `min` then `max` corner.
    pub cuboid: Vec<f64>,
    pub manifest: Option<Manifest>,
}

pub fn summary(c: &Category) -> ModelSummary {
    ModelSummary {
        category: c.name.clone(),
        version: c.active().map(|a| a.version.clone()),
        ready: c.ready(),
        error: c.error(),
    }
}

pub fn describe(c: &Category) -> ModelDescription {
    let active = c.active();
    let m = active.as_ref().map(|a| &a.manifest);
    ModelDescription {
        summary: summary(c),
        generation: active.as_ref().map_or(0, |a| a.generation),
        trained_as: m.map(|m| m.version.clone()).unwrap_or_default(),
        backbone: m.map(|m| m.backbone.name().to_string()).unwrap_or_default(),
        feature_dim: m.map_or(0, |m| m.feature_dim),
        vertices: m.map_or(0, |m| m.vertices),
        crop: m.map_or([0, 0], |m| m.crop),
        cuboid: m.map(|m| m.cuboid.min.iter().chain(&m.cuboid.max).copied().collect()).unwrap_or_default(),
        manifest: m.cloned(),
    }
}
