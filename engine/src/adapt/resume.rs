//! An adaptation's (or the oracle's) state after each round (each pass), so that an interrupted
//! run resumes where it stopped ([`super::adapt_resumable`], [`super::finetune_resumable`]): a
//! round of a large target set can take ten minutes on a laptop's CPU, a whole run an hour.
//!
//! Saved, as a [`crate::snapshot`] `round-<n>` (the two newest kept): the backbone's variables
//! (BatchNorm statistics included), `C` and the clutter vectors, the oracle's memory banks, the
//! rounds so far, the loop's convergence state and the random generator's position. Not saved:
//! Adam's moments, which tch cannot read out, so the backbone step restarts Adam at the next
//! round, as a resumed source training does; a resumed run that trains the backbone again is
//! then not bit-identical to an uninterrupted one, and [`super::Adapted::resumed_after`] says it
//! was resumed. A snapshot is keyed by its run (source model, images, labels, settings): another
//! run's is an error, never resumed.

use std::path::Path;

use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tch::Tensor;

use super::run::Run;
use super::{AdaptConfig, Label, RoundReport};
use crate::camera::Pose;
use crate::checkpoint::Model;
use crate::error::{EngineError, Result};
use crate::snapshot::{self, format_error, get};
use crate::train::SourceTraining;

/// Where a run keeps its snapshots, and the key of the run.
pub(super) struct Resume<'p> {
    pub(super) dir: &'p Path,
    pub(super) key: String,
}

impl<'p> Resume<'p> {
    /// `kind` tells the EM from the oracle; `labels` are the oracle's.
    pub(super) fn new(
        dir: &'p Path,
        kind: &str,
        source: &Model,
        images: &Tensor,
        config: &AdaptConfig,
        labels: &[Label],
    ) -> Result<Self> {
        let mut h = Sha256::new();
        let settings = serde_json::to_string(config).map_err(|e| EngineError::InvalidInput(e.to_string()))?;
        h.update(format!("{kind}\n{}\n{settings}\n{:?}\n", source.manifest.version, images.size()));
        for i in 0..images.size()[0] {
            let pixels = Vec::<f32>::try_from(images.get(i).flatten(0, -1)).map_err(|e| format_error(dir, e))?;
            h.update(pixels.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>());
        }
        for label in labels {
            h.update(format!("{:?}", label.pose));
            if let Some(o) = &label.occluded {
                h.update(o.iter().map(|&b| b as u8).collect::<Vec<u8>>());
            }
        }
        let key = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
        Ok(Resume { dir, key })
    }
}

/// The loop's own state between rounds.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub(super) struct Loop {
    /// The EM's calm rounds in a row, whether it converged, and the last round's pseudo-poses
    /// (empty before the first; the next round measures its pose change against them) and
    /// fired ratios (the result's).
    pub(super) calm: usize,
    pub(super) converged: bool,
    pub(super) poses: Vec<Pose>,
    pub(super) ratios: Vec<f64>,
    /// The oracle's mean loss per pass.
    pub(super) losses: Vec<f64>,
}

#[derive(Serialize, Deserialize)]
struct Record {
    key: String,
    rounds: Vec<RoundReport>,
    steps: usize,
    /// `ChaCha8Rng::get_word_pos` (a u128, as text: JSON numbers stop at 2^53 in many readers).
    rng_word_pos: String,
    state: Loop,
}

fn parse_name(name: &str) -> Option<usize> {
    name.strip_prefix("round-")?.parse().ok()
}

impl Run<'_> {
    /// Snapshots the run after its latest round; `banks` are the oracle's memory banks.
    pub(super) fn save(
        &self,
        resume: &Resume,
        rng: &ChaCha8Rng,
        state: &Loop,
        banks: Option<&SourceTraining>,
    ) -> Result<()> {
        let mut tensors: Vec<(String, Tensor)> =
            self.vs.variables().into_iter().map(|(n, t)| (format!("backbone.{n}"), t)).collect();
        tensors.push(("c".into(), Tensor::from_slice(&self.c)));
        tensors.push(("clutter".into(), Tensor::from_slice(&self.clutter)));
        if let Some(b) = banks {
            tensors.extend(b.banks("bank."));
        }
        let record = Record {
            key: resume.key.clone(),
            rounds: self.rounds.clone(),
            steps: self.steps,
            rng_word_pos: rng.get_word_pos().to_string(),
            state: state.clone(),
        };
        snapshot::write(resume.dir, &format!("round-{:04}", self.rounds.len()), &tensors, &record)?;
        snapshot::prune(resume.dir, parse_name, 2)
    }

    /// Restores the newest snapshot of `resume.dir`, if any, into the run, `rng` and `banks`;
    /// returns the loop's state, or `None` for a fresh run.
    pub(super) fn restore(
        &mut self,
        resume: &Resume,
        rng: &mut ChaCha8Rng,
        banks: Option<&mut SourceTraining>,
    ) -> Result<Option<Loop>> {
        let Some((_, dir)) = snapshot::complete(resume.dir, parse_name)?.pop() else { return Ok(None) };
        let (record, tensors): (Record, _) = snapshot::read(&dir)?;
        if record.key != resume.key {
            return Err(EngineError::InvalidInput(format!(
                "{} holds the state of another run (another model, other images or settings): remove it to start afresh",
                resume.dir.display()
            )));
        }
        let host = |name: &str, len: usize| -> Result<Vec<f32>> {
            let v = Vec::<f32>::try_from(get(&dir, &tensors, name)?).map_err(|e| format_error(&dir, e))?;
            if v.len() != len {
                return Err(format_error(&dir, format!("{name} has {} values, not {len}", v.len())));
            }
            Ok(v)
        };
        let (c, clutter) = (host("c", self.c.len())?, host("clutter", self.clutter.len())?);
        tch::no_grad(|| -> Result<()> {
            for (name, mut var) in self.vs.variables() {
                var.f_copy_(get(&dir, &tensors, &format!("backbone.{name}"))?).map_err(|e| format_error(&dir, e))?;
            }
            Ok(())
        })?;
        if let Some(b) = banks {
            b.restore_banks(&dir, &tensors, "bank.")?;
        }
        let pos: u128 = record.rng_word_pos.parse().map_err(|e| format_error(&dir, e))?;
        rng.set_word_pos(pos);
        (self.c, self.clutter, self.rounds, self.steps) = (c, clutter, record.rounds, record.steps);
        self.resumed_after = Some(self.rounds.len());
        Ok(Some(record.state))
    }
}
