//! A source-training run's state: the backbone's variables, the memory banks and the run's
//! progress, under `<work>/epoch-<n>/` at the end of each epoch and `<work>/epoch-<n>-step-<m>/`
//! within one (a slow machine's epoch can last an hour: the house keeps at most 15 minutes of
//! work at risk), so a run resumes after any interruption. Each directory is built under a
//! temporary name and renamed into place (a resumed run sees a whole checkpoint or none); the two
//! newest are kept.

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

/// What a run has done so far; saved with each checkpoint's weights.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Epochs completed.
    pub epoch: usize,
    /// Batches of the next epoch completed (0 at an epoch's end).
    #[serde(default)]
    pub step: usize,
    /// The training loss summed over those batches, for the epoch's curve point.
    #[serde(default)]
    pub loss_sum: f64,
    /// Training seconds summed over the run's sessions.
    pub seconds: f64,
    /// One point per epoch (loss, validation metrics, seconds), as the caller records them.
    pub curve: Vec<serde_json::Value>,
}

fn state_error(dir: &Path, what: impl std::fmt::Display) -> EngineError {
    CheckpointError::Format { path: dir.display().to_string(), reason: what.to_string() }.into()
}

/// Loads the latest checkpoint of `work` into `vs` and `training`; a run with none starts afresh.
pub fn resume(work: &Path, vs: &mut nn::VarStore, training: &mut SourceTraining) -> Result<Progress> {
    let Some(dir) = latest_checkpoint(work)? else { return Ok(Progress::default()) };
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

/// A checkpoint directory's name: `epoch-<n>` after n epochs, `epoch-<n>-step-<m>` m batches
/// into the next.
fn dir_name(epoch: usize, step: usize) -> String {
    match step {
        0 => format!("epoch-{epoch:04}"),
        _ => format!("epoch-{epoch:04}-step-{step:06}"),
    }
}

/// (epoch, step) of a checkpoint directory's name.
fn parse_name(name: &str) -> Option<(usize, usize)> {
    let rest = name.strip_prefix("epoch-")?;
    match rest.split_once("-step-") {
        Some((epoch, step)) => Some((epoch.parse().ok()?, step.parse().ok()?)),
        None => Some((rest.parse().ok()?, 0)),
    }
}

/// The complete checkpoints in `work`, oldest first.
fn checkpoints(work: &Path) -> Result<Vec<((usize, usize), PathBuf)>> {
    if !work.is_dir() {
        return Ok(Vec::new());
    }
    let mut found: Vec<((usize, usize), PathBuf)> = fs::read_dir(work)?
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let at = parse_name(e.file_name().to_str()?)?;
            e.path().join(PROGRESS).is_file().then(|| (at, e.path()))
        })
        .collect();
    found.sort();
    Ok(found)
}

/// The directory of the newest complete checkpoint in `work`.
pub fn latest_checkpoint(work: &Path) -> Result<Option<PathBuf>> {
    Ok(checkpoints(work)?.pop().map(|(_, p)| p))
}

/// Writes the checkpoint of `progress` (weights and banks, progress last) under a temporary
/// name, renames it into place, and keeps the two newest.
pub fn save(work: &Path, vs: &nn::VarStore, training: &SourceTraining, progress: &Progress) -> Result<()> {
    fs::create_dir_all(work)?;
    let name = dir_name(progress.epoch, progress.step);
    let dir = work.join(&name);
    let tmp = work.join(format!(".{name}.tmp"));
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
    for (_, p) in checkpoints(work)?.iter().rev().skip(2) {
        fs::remove_dir_all(p)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkpoint_names_round_trip() {
        for at in [(0, 5), (3, 0), (12, 187)] {
            assert_eq!(parse_name(&dir_name(at.0, at.1)), Some(at));
        }
        assert_eq!(parse_name("epoch-0002"), Some((2, 0)));
        assert_eq!(parse_name(".epoch-0002.tmp"), None);
        assert_eq!(parse_name("epoch-x-step-3"), None);
    }

    /// The newest complete checkpoint wins: a later step of the same epoch over the epoch's
    /// start, an unfinished (no progress) or temporary directory never.
    #[test]
    fn the_latest_complete_checkpoint_is_resumed() {
        let work = std::env::temp_dir().join(format!("udapose-state-{}", std::process::id()));
        for (name, complete) in [
            ("epoch-0000-step-000010", true),
            ("epoch-0001", true),
            ("epoch-0001-step-000050", true),
            ("epoch-0001-step-000060", false),
            (".epoch-0002.tmp", true),
        ] {
            fs::create_dir_all(work.join(name)).unwrap();
            if complete {
                fs::write(work.join(name).join(PROGRESS), "{}").unwrap();
            }
        }
        assert_eq!(latest_checkpoint(&work).unwrap(), Some(work.join("epoch-0001-step-000050")));
        fs::remove_dir_all(&work).unwrap();
    }
}
