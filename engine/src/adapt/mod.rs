//! 3DUDA (METHOD.md §7): source-free, image-only adaptation of a neural mesh model by
//! selective vertex updates and backbone fine-tuning on pseudo-poses, alternated (EM).
//!
//! The source model is never modified: [`adapt`] works on copies and returns them. The same
//! loop with ground-truth poses and all visible vertices is the supervised *oracle*
//! ([`finetune`]), so the two share their budget by construction.

use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use tch::nn::OptimizerConfig;
use tch::{Tensor, nn};

use crate::backbone::{Backbone, preprocess};
use crate::camera::{Camera, Pose};
use crate::checkpoint::{Model, NeuralMesh};
use crate::error::{EngineError, Result};
use crate::estimator::{self, Features, PoseSolver, to_host};
use crate::gate::{flip_consistent, mirror_crops};
use crate::mesh::Mesh;
use crate::metrics::rotation_error;
use crate::raster::Rasterizer;
use crate::solver::SolverConfig;
use crate::train::{SourceTraining, TrainConfig, VisibleVertices, visible_vertices};

mod fire;
mod resume;
mod run;

pub use fire::FiringTest;
use fire::*;
use resume::Resume;
use run::Run;

/// Which per-vertex cosine a feature must exceed to *fire* (METHOD.md §7.3).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", content = "value", rename_all = "snake_case")]
pub enum Threshold {
    /// τ_r from the checkpoint: a quantile of r's source cosines at ground-truth poses.
    Source,
    /// One cosine for every vertex (the paper's 0.8).
    Fixed(f64),
}

/// Which matches an image contributes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", content = "omega", rename_all = "snake_case")]
pub enum Selection {
    /// 3DUDA: every hypothesis's fired vertices, kept when at least ψ of its visible vertices
    /// fire.
    PerVertex,
    /// The ablation (the paper's §3.3): an image's pseudo-pose is used, with *all* its visible
    /// vertices, only when at least Ω of them fire.
    Global(f64),
}

/// Which visible vertices of a selected pseudo-pose the backbone step trains as positives
/// (METHOD.md §7.6). The global filter always trains all of them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Positives {
    /// R_v, every visible vertex: the paper's eq. 8.
    #[default]
    Visible,
    /// Only the vertices that fire.
    Fired,
    /// The visible vertices whose feature matches their vertex better than any clutter vector
    /// (NeMo's label-free occlusion inference: the cell is assigned to the object).
    Object,
}

/// Whose fired matches move the vertex features (METHOD.md §7.5).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VertexMatches {
    /// The fired matches of all k hypotheses (local parts match even at a wrong global pose).
    #[default]
    All,
    /// Only the best hypothesis's.
    Best,
}

/// Every knob of the adaptation. Defaults: METHOD.md §7, with the settings it leaves open
/// measured on SynCar-OOD `adapt` splits (reports/adapt-defaults.md): the paper's fixed cosine
/// 0.8 (τ_r fired for 70–90% of vertices on any image, so nothing was selected), lr 1e-5 (1e-4
/// lost precision), α 0.9 per 32 images and the source clutter kept (α 0.5 and a moving clutter
/// collapsed the vertex features on fog), 5 rounds (10 drifted further: 0.653 → 0.597
/// Acc@π/6 on `combined`; the convergence test never fired before round 10), and the target
/// images' BatchNorm statistics first (fog 0.157 → 0.900 with it; combined 0.653 → 0.683).
/// ψ 0.2, above METHOD's 5–10 %: on `occ-l1` 0.05 lets 64 % of the images teach, 28 % of those
/// with a wrong pseudo-pose, 0.2 lets 34 % teach, 8 % wrong; it gained 0.015 there over 3 seeds
/// and tied on every other domain measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdaptConfig {
    pub threshold: Threshold,
    pub selection: Selection,
    /// ψ: an image's (hypothesis's) matches count only if this share of its visible vertices fire.
    pub min_fired_ratio: f64,
    /// Images scoring below this quantile of the round are left out of the backbone update.
    pub drop_quantile: f64,
    /// EMA weight α of the old vertex feature per round: each of a round's B batches applies
    /// `C_r ← a C_r + (1 − a) mean(fired f)` with `a = α^(1/B)`, so that a round keeps α of the
    /// old feature however many batches it has (per batch, α 0.9 compounded over 50 batches
    /// replaced it).
    pub alpha: f64,
    /// Whose fired matches the vertex update takes.
    #[serde(default)]
    pub vertex_matches: VertexMatches,
    /// Only flip-consistent pseudo-poses teach: an image contributes matches and positives only
    /// when its mirrored crop's estimate is the mirror of its own (the gate's label-free check,
    /// [`crate::gate::flip_consistent`]), which costs a second backbone pass and solve per image.
    #[serde(default)]
    pub flip_check: bool,
    /// Images per vertex update (METHOD: at least 32).
    pub vertex_batch: usize,
    /// Also move the clutter vector towards the target's clutter features (same α).
    pub update_clutter: bool,
    /// Fine-tune the backbone on the pseudo-poses (false: vertex updates only).
    pub update_backbone: bool,
    /// The backbone step's positives.
    #[serde(default)]
    pub positives: Positives,
    /// Before round 1, replace the backbone's BatchNorm statistics by the target images' own
    /// (AdaBN; label-free). The fine-tuning itself keeps them frozen, as METHOD.md §7.6 says.
    #[serde(default)]
    pub target_batchnorm: bool,
    /// Adam learning rate of the backbone step.
    pub lr: f64,
    /// Images per backbone step.
    pub batch: usize,
    /// Stop after this many rounds at the latest.
    pub max_rounds: usize,
    /// Converged when, for `patience` rounds in a row, the fired ratio gains less than this ...
    pub fired_gain: f64,
    /// ... and the median pseudo-pose change is below this many degrees.
    pub pose_change_deg: f64,
    pub patience: usize,
    /// The contrastive loss of the backbone step (METHOD.md §5).
    pub train: TrainConfig,
    /// Render and compare for the pseudo-poses (k = 3 as everywhere).
    pub solver: SolverConfig,
    pub seed: u64,
}

impl Default for AdaptConfig {
    fn default() -> Self {
        AdaptConfig {
            threshold: Threshold::Fixed(0.8),
            selection: Selection::PerVertex,
            min_fired_ratio: 0.2,
            drop_quantile: 0.2,
            alpha: 0.9,
            vertex_matches: VertexMatches::All,
            flip_check: false,
            vertex_batch: 32,
            update_clutter: false,
            update_backbone: true,
            positives: Positives::Visible,
            target_batchnorm: true,
            lr: 1e-5,
            batch: 16,
            max_rounds: 5,
            fired_gain: 0.01,
            pose_change_deg: 2.0,
            patience: 2,
            train: TrainConfig::default(),
            solver: SolverConfig::default(),
            seed: 0,
        }
    }
}

impl AdaptConfig {
    /// The global pseudo-label filter of the ablation, Ω = 0.5 (the paper's setting).
    pub fn global_filter() -> Self {
        AdaptConfig { selection: Selection::Global(0.5), ..AdaptConfig::default() }
    }

    /// Whether the EM can change nothing but what AdaBN does: α = 1 keeps every vertex
    /// feature, the clutter stays, and no round trains the backbone (the last round never does).
    /// Such a run (the report's *BN only*) skips the rounds' render-and-compare, whose results
    /// it could not use.
    pub fn batchnorm_only(&self) -> bool {
        self.alpha >= 1.0 && !self.update_clutter && (!self.update_backbone || self.max_rounds <= 1)
    }

    pub fn validate(&self) -> Result<()> {
        let unit = |x: f64| x.is_finite() && (0.0..=1.0).contains(&x);
        let ok = unit(self.min_fired_ratio)
            && unit(self.drop_quantile)
            && unit(self.alpha)
            && self.vertex_batch > 0
            && self.batch > 0
            && self.max_rounds > 0
            && self.patience > 0
            && self.lr.is_finite()
            && self.lr > 0.0
            && self.fired_gain.is_finite()
            && self.pose_change_deg.is_finite()
            && match self.threshold {
                Threshold::Source => true,
                Threshold::Fixed(t) => t.is_finite() && (-1.0..=1.0).contains(&t),
            }
            && match self.selection {
                Selection::PerVertex => true,
                Selection::Global(omega) => unit(omega),
            };
        if !ok {
            return Err(EngineError::InvalidInput(format!("invalid adaptation settings {self:?}")));
        }
        self.solver.validate()
    }
}

/// How many images [`RoundReport::source_fired_ratio`] looks at.
pub const SOURCE_CHECK_IMAGES: usize = 64;

/// What happens now, for progress bars.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Features,
    VertexUpdate,
    PseudoPoses,
    Backbone,
}

/// The statistics of one EM round.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RoundReport {
    pub round: usize,
    /// Round 1 with target BatchNorm statistics: the mean fired ratio of up to
    /// [`SOURCE_CHECK_IMAGES`] of the images to the unchanged source model, i.e. how much the
    /// images look like the category before anything adapts (AdaBN makes almost anything fire).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_fired_ratio: Option<f64>,
    /// Mean share of visible vertices that fire at each image's best pose, with the vertex
    /// features the round started with (round 1: the source model's).
    pub fired_ratio_before: f64,
    /// The same after this round's vertex update, at the new pseudo-poses.
    pub fired_ratio: f64,
    /// Share of the mesh's vertices that received at least one fired feature.
    pub vertices_updated: f64,
    /// Images whose pseudo-pose passed the selection (ψ or Ω) at this round.
    pub images_selected: usize,
    /// Images used by the backbone step (selected and above the score quantile).
    pub images_trained: usize,
    /// With [`AdaptConfig::flip_check`]: images whose pseudo-pose is flip-consistent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flip_consistent: Option<usize>,
    /// Mean share of a trained image's visible vertices that are its positives ([`Positives`]).
    #[serde(default)]
    pub positive_share: f64,
    /// Median / 90th percentile of the pseudo-pose change from the previous round (degrees).
    pub pose_change_median_deg: Option<f64>,
    pub pose_change_p90_deg: Option<f64>,
    /// Mean render-and-compare score at the pseudo-poses.
    pub mean_score: f64,
    /// Mean contrastive loss of the backbone step (none in the last round).
    pub backbone_loss: Option<f64>,
    pub seconds: f64,
}

/// Progress of a run: phases within a round, and each finished round.
#[derive(Clone, Debug)]
pub enum Event<'a> {
    Step {
        round: usize,
        phase: Phase,
        done: usize,
        total: usize,
    },
    /// The target check's reading, before round 1 of a run with target BatchNorm statistics:
    /// the mean fired ratio of up to [`SOURCE_CHECK_IMAGES`] of the images to the unchanged
    /// model (round 1's [`RoundReport::source_fired_ratio`]). A caller that breaks here stops
    /// the run before any round, so images that do not look like the category cost one pass
    /// over 64 images (see [`crate::gate::target_fired`]).
    TargetCheck {
        fired: f64,
    },
    Round(&'a RoundReport),
    /// The run goes on from a snapshot taken after this many rounds ([`adapt_resumable`]).
    Resumed {
        rounds: usize,
    },
}

/// The adapted (or fine-tuned) model: a new backbone and neural mesh, and how it got there.
pub struct Adapted {
    pub vs: nn::VarStore,
    pub backbone: Backbone,
    pub neural_mesh: NeuralMesh,
    pub rounds: Vec<RoundReport>,
    /// Stopped by the convergence criterion (not by `max_rounds`).
    pub converged: bool,
    /// Backbone optimiser steps taken (the budget the oracle matches).
    pub backbone_steps: usize,
    /// Rounds (passes) restored from a snapshot, when the run was resumed.
    pub resumed_after: Option<usize>,
    /// Per image, the pseudo-pose of the last round and its fired-vertex ratio.
    pub pseudo_poses: Vec<Option<Pose>>,
    pub fired_ratios: Vec<f64>,
}

/// Adapts `source` to the domain of `images` (N×3×H×W RGB in [0, 1], the model's crop size),
/// without labels. `progress` may stop the run (`ControlFlow::Break`), which returns
/// [`EngineError::Cancelled`].
pub fn adapt(
    source: &Model,
    images: &Tensor,
    config: &AdaptConfig,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Adapted> {
    Run::new(source, images, config)?.em(None, progress)
}

/// What the service's target check reads before a job adapts
/// ([`crate::gate::GateConfig::min_target_fired`]): the share of visible vertices that fire on
/// each of up to [`SOURCE_CHECK_IMAGES`] of `images` to `source` as it is. Their mean is the
/// round-1 [`RoundReport::source_fired_ratio`] of [`adapt`] on the same images and settings,
/// without the round. `config` gives the threshold τ and the solver.
pub fn source_fired(
    source: &Model,
    images: &Tensor,
    config: &AdaptConfig,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Vec<f64>> {
    Run::new(source, images, config)?.source_fired(progress)
}

/// [`adapt`], snapshotted after each round into `work` and resumed from the newest snapshot
/// there: the backbone, `C`, the clutter, the rounds, the loop's state and the generator's
/// position, not Adam's moments (tch cannot read them out; [`Adapted::resumed_after`] says the
/// run was resumed). `work` is the caller's to remove once the model is saved.
pub fn adapt_resumable(
    source: &Model,
    images: &Tensor,
    config: &AdaptConfig,
    work: &Path,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Adapted> {
    let run = Run::new(source, images, config)?;
    let resume = Resume::new(work, "adapt", source, images, config, &[])?;
    run.em(Some(&resume), progress)
}

/// A labelled image of the oracle: its ground-truth pose and, where the data knows it, which
/// crop pixels an occluder covers (`H·W`, row-major), so that occluded vertices are not trained
/// as positives.
#[derive(Clone, Debug)]
pub struct Label {
    pub pose: Pose,
    pub occluded: Option<Vec<bool>>,
}

/// How long the oracle trains.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Budget {
    /// Exactly this many optimiser steps: the adaptation's own budget (the same-budget oracle).
    Steps(usize),
    /// Passes over the images until the pass's mean loss stops falling (the strong oracle): at
    /// least `min_passes`, at most `max_passes`; after `min_passes`, a pass whose loss is not
    /// below `(1 − tolerance)` times the best earlier pass's ends the run.
    Plateau { min_passes: usize, max_passes: usize, tolerance: f64 },
}

impl Budget {
    /// Whether the run stops after a pass, given every pass's mean loss so far.
    fn done(&self, steps: usize, losses: &[f64]) -> bool {
        match *self {
            Budget::Steps(n) => steps >= n,
            Budget::Plateau { min_passes, max_passes, tolerance } => {
                let Some((last, earlier)) = losses.split_last() else { return false };
                let best = earlier.iter().copied().fold(f64::INFINITY, f64::min);
                losses.len() >= max_passes || (losses.len() >= min_passes && *last >= (1.0 - tolerance) * best)
            }
        }
    }
}

/// The oracle: the same loop with the ground-truth poses as pseudo-poses, every visible and
/// unoccluded vertex a positive and `C` trained by its momentum bank (METHOD.md §5), for the
/// `budget` in optimiser steps of `config.batch` images.
pub fn finetune(
    source: &Model,
    images: &Tensor,
    labels: &[Label],
    budget: Budget,
    config: &AdaptConfig,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Adapted> {
    finetune_in(source, images, labels, budget, config, None, progress)
}

/// [`finetune`], snapshotted after each pass into `work` and resumed from there, as
/// [`adapt_resumable`].
pub fn finetune_resumable(
    source: &Model,
    images: &Tensor,
    labels: &[Label],
    budget: Budget,
    config: &AdaptConfig,
    work: &Path,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Adapted> {
    finetune_in(source, images, labels, budget, config, Some(work), progress)
}

fn finetune_in(
    source: &Model,
    images: &Tensor,
    labels: &[Label],
    budget: Budget,
    config: &AdaptConfig,
    work: Option<&Path>,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Adapted> {
    let mut run = Run::new(source, images, config)?;
    if labels.len() != run.n {
        return Err(EngineError::InvalidInput(format!("{} poses for {} images", labels.len(), run.n)));
    }
    let (height, width) = (run.crop.height, run.crop.width);
    if let Some(o) = labels.iter().filter_map(|l| l.occluded.as_ref()).find(|o| o.len() != height * width) {
        let n = o.len();
        return Err(EngineError::InvalidInput(format!("an occluder mask of {n} pixels for a {height}×{width} crop")));
    }
    let resume = work.map(|w| Resume::new(w, "oracle", source, images, config, labels)).transpose()?;
    let mut training = run.training();
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let restored = match &resume {
        Some(r) => run.restore(r, &mut rng, Some(&mut training))?,
        None => None,
    };
    let mut state = match restored {
        Some(state) => {
            if progress(Event::Resumed { rounds: run.rounds.len() }).is_break() {
                return Err(EngineError::Cancelled);
            }
            state
        }
        None => {
            run.target_batchnorm()?;
            Default::default()
        }
    };
    let targets: Vec<Option<VisibleVertices>> = labels
        .iter()
        .map(|label| {
            let visible = visible_vertices(&mut run.raster, &run.mesh, &run.crop, config.solver.stride, &label.pose)?;
            Ok(Some(match &label.occluded {
                Some(o) => visible.without_occluded(o, width),
                None => visible,
            }))
        })
        .collect::<Result<_>>()?;
    let mut opt = nn::Adam { wd: 1e-4, ..Default::default() }.build(&run.vs, config.lr).map_err(tch_err)?;
    while !budget.done(run.steps, &state.losses) {
        let round = state.losses.len() + 1;
        let started = Instant::now();
        let left = match budget {
            Budget::Steps(n) => n - run.steps,
            Budget::Plateau { .. } => usize::MAX,
        };
        let (loss, taken) =
            run.backbone_pass(&mut training, &mut opt, &targets, true, left, &mut rng, round, progress)?;
        if taken == 0 {
            return Err(EngineError::InvalidInput("no labelled image shows a visible vertex".into()));
        }
        run.steps += taken;
        state.losses.push(loss);
        let report = RoundReport {
            round,
            backbone_loss: Some(loss),
            images_trained: run.n,
            seconds: started.elapsed().as_secs_f64(),
            ..Default::default()
        };
        run.end_round(report, resume.as_ref(), &rng, &state, Some(&training), progress)?;
    }
    run.c = to_host(&training.vertex_features)?;
    run.clutter = to_host(&estimator::clutter_mean(&training.clutter))?;
    run.finish(false, vec![None; labels.len()], vec![0.0; labels.len()])
}
