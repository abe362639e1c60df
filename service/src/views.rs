//! What the model routes answer, for any transport: a category's summary and description (the
//! contract's types; the gRPC adapter converts them, HTTP sends them as they are).

pub use udapose_api::{ModelDescription, ModelSummary};

use crate::registry::Category;

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
    let s = summary(c);
    ModelDescription {
        category: s.category,
        version: s.version.unwrap_or_default(),
        ready: s.ready,
        generation: active.as_ref().map_or(0, |a| a.generation),
        trained_as: m.map(|m| m.version.clone()).unwrap_or_default(),
        backbone: m.map(|m| m.backbone.name().to_string()).unwrap_or_default(),
        feature_dim: m.map_or(0, |m| m.feature_dim as u32),
        vertices: m.map_or(0, |m| m.vertices as u32),
        crop_height: m.map_or(0, |m| m.crop[0] as u32),
        crop_width: m.map_or(0, |m| m.crop[1] as u32),
        cuboid: m.map(|m| m.cuboid.min.iter().chain(&m.cuboid.max).copied().collect()).unwrap_or_default(),
        error: s.error.unwrap_or_default(),
        manifest: m.and_then(|m| serde_json::to_value(m).ok()).unwrap_or_default(),
    }
}
