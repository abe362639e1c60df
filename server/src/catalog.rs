//! What models the server knows about and whether they can serve.
//!
//! At start every `<dir>/<category>/` with a manifest is loaded and validated by the engine
//! (weights, checksums, shapes); a model that fails stays listed, not ready, with the reason.
//! Serving estimates from them (workers, batching, hot swap) is the inference-service issue.

use std::{
    fs,
    path::{Path, PathBuf},
};

use anyhow::{Context, Result, bail};
use serde::Serialize;

/// The file that marks a directory under `--models` as a model.
const MANIFEST: &str = "manifest.json";

/// One category's model as the server sees it (mirrors `udapose.v1.ModelInfo`).
#[derive(Debug, Clone, Serialize, PartialEq, Eq)]
pub struct ModelEntry {
    pub category: String,
    /// The version being served; `None` while nothing is loaded.
    pub version: Option<String>,
    pub ready: bool,
    /// Why the model could not be loaded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The models configured under one directory.
#[derive(Debug)]
pub struct Catalog {
    dir: PathBuf,
    models: Vec<ModelEntry>,
}

/// Whether every configured model is loaded, and why not.
#[derive(Debug, PartialEq, Eq)]
pub struct Readiness {
    pub ready: bool,
    pub reason: String,
}

impl Catalog {
    /// Finds `<dir>/<category>/manifest.json`; a missing `dir` means no models.
    pub fn scan(dir: &Path) -> Result<Self> {
        let models = if dir.exists() {
            found_categories(dir)?.into_iter().map(|c| load(dir, c)).collect()
        } else {
            tracing::warn!("models directory {} does not exist", dir.display());
            Vec::new()
        };
        Ok(Self { dir: dir.to_path_buf(), models })
    }

    /// Every configured model, ordered by category.
    pub fn models(&self) -> &[ModelEntry] {
        &self.models
    }

    /// Ready only when at least one model is configured and all are loaded.
    pub fn readiness(&self) -> Readiness {
        let total = self.models.len();
        let loaded = self.models.iter().filter(|m| m.ready).count();
        let ready = total > 0 && loaded == total;
        let reason = match (loaded, total) {
            (_, 0) => {
                format!("no models loaded: none configured (no <category>/{MANIFEST} under {})", self.dir.display())
            }
            _ if loaded == total => format!("{loaded} of {total} models loaded"),
            _ => {
                let failed: Vec<String> = self
                    .models
                    .iter()
                    .filter_map(|m| m.error.as_ref().map(|e| format!("{}: {e}", m.category)))
                    .collect();
                format!("{loaded} of {total} models loaded; failed: {}", failed.join("; "))
            }
        };
        Readiness { ready, reason }
    }

    /// Says at start-up what was loaded and what failed.
    pub fn log_summary(&self) {
        for m in &self.models {
            match (&m.version, &m.error) {
                (Some(v), _) => tracing::info!(category = %m.category, version = %v, "model loaded"),
                (_, Some(e)) => tracing::warn!(category = %m.category, "model not loaded: {e}"),
                _ => {}
            }
        }
        tracing::info!("{}", self.readiness().reason);
    }
}

/// Loads and validates one model directory (the tensors are not kept yet: nothing serves them).
fn load(dir: &Path, category: String) -> ModelEntry {
    let device = udapose_engine::runtime::RuntimeInfo::detect().device();
    match udapose_engine::checkpoint::load(&dir.join(&category), device) {
        Ok(model) => ModelEntry { category, version: Some(model.manifest.version), ready: true, error: None },
        Err(e) => ModelEntry { category, version: None, ready: false, error: Some(e.to_string()) },
    }
}

/// Sorted names of the subdirectories of `dir` that hold a manifest.
fn found_categories(dir: &Path) -> Result<Vec<String>> {
    if !dir.is_dir() {
        bail!("models path {} is not a directory", dir.display());
    }
    let entries = fs::read_dir(dir).with_context(|| format!("reading models directory {}", dir.display()))?;
    let mut categories = Vec::new();
    for entry in entries {
        let path = entry.with_context(|| format!("listing {}", dir.display()))?.path();
        if !path.join(MANIFEST).is_file() {
            continue;
        }
        match path.file_name().and_then(|n| n.to_str()) {
            Some(name) => categories.push(name.to_owned()),
            None => tracing::warn!("skipping model directory with a non-UTF-8 name: {path:?}"),
        }
    }
    categories.sort();
    Ok(categories)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("udapose-catalog-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn missing_dir_means_no_models_and_not_ready() {
        let catalog = Catalog::scan(Path::new("/nonexistent/udapose/models")).unwrap();
        assert!(catalog.models().is_empty());
        let readiness = catalog.readiness();
        assert!(!readiness.ready);
        assert!(readiness.reason.starts_with("no models loaded: none configured"));
    }

    #[test]
    fn broken_models_are_listed_not_ready_with_their_reason() {
        let dir = temp_dir("found");
        for category in ["car", "bus"] {
            fs::create_dir(dir.join(category)).unwrap();
            fs::write(dir.join(category).join(MANIFEST), "{}").unwrap();
        }
        fs::create_dir(dir.join("no-manifest")).unwrap();
        let catalog = Catalog::scan(&dir).unwrap();
        fs::remove_dir_all(&dir).unwrap();

        let names: Vec<_> = catalog.models().iter().map(|m| m.category.as_str()).collect();
        assert_eq!(names, ["bus", "car"]);
        assert!(catalog.models().iter().all(|m| !m.ready && m.version.is_none() && m.error.is_some()));
        let readiness = catalog.readiness();
        assert!(!readiness.ready);
        assert!(readiness.reason.contains("0 of 2 models loaded; failed: bus:"), "{}", readiness.reason);
    }

    #[test]
    fn the_shipped_model_loads_and_makes_the_server_ready() {
        let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models");
        let catalog = Catalog::scan(&shipped).unwrap();
        let car = catalog.models().iter().find(|m| m.category == "car").expect("models/car is shipped");
        assert!(car.ready, "{:?}", car.error);
        assert!(car.version.as_deref().is_some_and(|v| v.starts_with("source-")));
        assert!(catalog.readiness().ready);
    }

    #[test]
    fn a_file_is_not_a_models_dir() {
        let dir = temp_dir("file");
        let file = dir.join("models");
        fs::write(&file, "").unwrap();
        let err = Catalog::scan(&file).unwrap_err();
        fs::remove_dir_all(&dir).unwrap();
        assert!(err.to_string().contains("not a directory"));
    }
}
