//! A source-training run's state: the backbone's variables, the memory banks and the run's
//! progress, under `<work>/epoch-<n>/` at the end of each epoch and `<work>/epoch-<n>-step-<m>/`
//! within one (a slow machine's epoch can last an hour: the house keeps at most 15 minutes of
//! work at risk), so a run resumes after any interruption. Each is a [`crate::snapshot`]; the two
//! newest are kept.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tch::{Tensor, nn};

use super::SourceTraining;
use crate::error::Result;
use crate::snapshot::{self, format_error, get};

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

/// Loads the latest checkpoint of `work` into `vs` and `training`; a run with none starts afresh.
pub fn resume(work: &Path, vs: &mut nn::VarStore, training: &mut SourceTraining) -> Result<Progress> {
    let Some(dir) = latest_checkpoint(work)? else { return Ok(Progress::default()) };
    let (progress, tensors): (Progress, _) = snapshot::read(&dir)?;
    tch::no_grad(|| -> Result<()> {
        for (name, mut var) in vs.variables() {
            var.f_copy_(get(&dir, &tensors, &format!("backbone.{name}"))?).map_err(|e| format_error(&dir, e))?;
        }
        Ok(())
    })?;
    training.restore_banks(&dir, &tensors, "")?;
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

/// The directory of the newest complete checkpoint in `work`.
pub fn latest_checkpoint(work: &Path) -> Result<Option<PathBuf>> {
    Ok(snapshot::complete(work, parse_name)?.pop().map(|(_, p)| p))
}

/// Writes the checkpoint of `progress` (weights and banks, progress last) and keeps the two
/// newest.
pub fn save(work: &Path, vs: &nn::VarStore, training: &SourceTraining, progress: &Progress) -> Result<()> {
    let mut tensors: Vec<(String, Tensor)> =
        vs.variables().into_iter().map(|(n, t)| (format!("backbone.{n}"), t)).collect();
    tensors.extend(training.banks(""));
    snapshot::write(work, &dir_name(progress.epoch, progress.step), &tensors, progress)?;
    snapshot::prune(work, parse_name, 2)
}

#[cfg(test)]
mod tests {
    use std::fs;

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
                fs::write(work.join(name).join("progress.json"), "{}").unwrap();
            }
        }
        assert_eq!(latest_checkpoint(&work).unwrap(), Some(work.join("epoch-0001-step-000050")));
        fs::remove_dir_all(&work).unwrap();
    }
}
