//! What models the server knows about and whether they can serve.
//!
//! No model loader exists yet: every discovered model is reported as found
//! but not loaded, and the server is not ready until a loader lands.

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
            found_categories(dir)?.into_iter().map(not_loaded).collect()
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
            (0, _) => format!(
                "no models loaded: {total} found but not loadable yet \
                 (this build has no model loader): {}",
                self.categories()
            ),
            _ => format!("{loaded} of {total} models loaded"),
        };
        Readiness { ready, reason }
    }

    /// Says at start-up what was found and that none of it serves yet.
    pub fn log_summary(&self) {
        if !self.models.is_empty() {
            tracing::warn!(
                "found {} model(s) in {}: {}; this build cannot load models yet",
                self.models.len(),
                self.dir.display(),
                self.categories()
            );
        }
        tracing::info!("{}", self.readiness().reason);
    }

    fn categories(&self) -> String {
        let names: Vec<&str> = self.models.iter().map(|m| m.category.as_str()).collect();
        names.join(", ")
    }
}

fn not_loaded(category: String) -> ModelEntry {
    ModelEntry { category, version: None, ready: false }
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
    fn manifest_dirs_are_found_but_not_ready() {
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
        assert!(catalog.models().iter().all(|m| !m.ready && m.version.is_none()));
        let readiness = catalog.readiness();
        assert!(!readiness.ready);
        assert!(readiness.reason.contains("2 found but not loadable yet"));
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
