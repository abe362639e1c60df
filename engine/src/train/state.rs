//! A source-training run's state between epochs: the backbone's variables, the memory banks and
//! the run's progress, under `<work>/epoch-<n>/`, so a run resumes after any interruption.
//! Each epoch's directory is built under a temporary name and renamed into place (a resumed run
//! sees a whole epoch or none); the two newest are kept.

use std::collections::BTreeMap;
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tch::{Tensor, nn};

use super::SourceTraining;
use crate::error::{CheckpointError, EngineError, Result};

const STATE: &str = "state.safetensors";
const PROGRESS: &str = "progress.json";

/// What a run has done so far; saved with each epoch's weights.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Epochs completed.
    pub epoch: usize,
    /// Training seconds summed over the run's sessions.
    pub seconds: f64,
    /// One point per epoch (loss, validation metrics, seconds), as the caller records them.
    pub curve: Vec<serde_json::Value>,
}

fn state_error(dir: &Path, what: impl std::fmt::Display) -> EngineError {
    CheckpointError::Format { path: dir.display().to_string(), reason: what.to_string() }.into()
}

/// Loads the latest epoch of `work` into `vs` and `training`; a run with none starts afresh.
pub fn resume(work: &Path, vs: &mut nn::VarStore, training: &mut SourceTraining) -> Result<Progress> {
    let Some(dir) = latest_epoch(work)? else { return Ok(Progress::default()) };
    let text = fs::read_to_string(dir.join(PROGRESS))?;
    let progress: Progress = serde_json::from_str(&text).map_err(|e| state_error(&dir, e))?;
    let tensors: BTreeMap<String, Tensor> = crate::checkpoint::read_tensors(&dir.join(STATE))?;
    let get = |name: &str| tensors.get(name).ok_or_else(|| state_error(&dir, format!("no {name}")));
    tch::no_grad(|| -> Result<()> {
        for (name, mut var) in vs.variables() {
            var.f_copy_(get(&format!("backbone.{name}"))?).map_err(|e| state_error(&dir, e))?;
        }
        training.vertex_features = get("vertex_features")?.shallow_clone();
        training.clutter.f_copy_(get("clutter")?).map_err(|e| state_error(&dir, e))?;
        Ok(())
    })?;
    Ok(progress)
}

/// The directory of the newest complete epoch in `work`.
pub fn latest_epoch(work: &Path) -> Result<Option<PathBuf>> {
    if !work.is_dir() {
        return Ok(None);
    }
    let mut epochs: Vec<(usize, PathBuf)> = fs::read_dir(work)?
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let n = e.file_name().to_str()?.strip_prefix("epoch-")?.parse().ok()?;
            e.path().join(PROGRESS).is_file().then(|| (n, e.path()))
        })
        .collect();
    epochs.sort();
    Ok(epochs.pop().map(|(_, p)| p))
}

/// Writes `epoch-<n>/` (weights and banks, progress last) under a temporary name, renames it
/// into place, and keeps the two newest.
pub fn save(work: &Path, vs: &nn::VarStore, training: &SourceTraining, progress: &Progress) -> Result<()> {
    fs::create_dir_all(work)?;
    let dir = work.join(format!("epoch-{:04}", progress.epoch));
    let tmp = work.join(format!(".epoch-{:04}.tmp", progress.epoch));
    let _ = fs::remove_dir_all(&tmp);
    fs::create_dir_all(&tmp)?;
    let mut tensors: Vec<(String, Tensor)> =
        vs.variables().into_iter().map(|(n, t)| (format!("backbone.{n}"), t)).collect();
    tensors.push(("vertex_features".into(), training.vertex_features.shallow_clone()));
    tensors.push(("clutter".into(), training.clutter.shallow_clone()));
    Tensor::write_safetensors(&tensors, tmp.join(STATE)).map_err(|e| state_error(&tmp, e))?;
    File::open(tmp.join(STATE))?.sync_all()?;
    let mut f = File::create(tmp.join(PROGRESS))?;
    f.write_all(serde_json::to_string(progress).map_err(|e| state_error(&tmp, e))?.as_bytes())?;
    f.sync_all()?;
    File::open(&tmp)?.sync_all()?;
    let _ = fs::remove_dir_all(&dir);
    fs::rename(&tmp, &dir)?;
    File::open(work)?.sync_all()?;
    let mut old: Vec<PathBuf> = fs::read_dir(work)?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("epoch-")))
        .collect();
    old.sort();
    for p in old.iter().rev().skip(2) {
        fs::remove_dir_all(p)?;
    }
    Ok(())
}
