//! 3DUDA (METHOD.md §7): source-free, image-only adaptation of a neural mesh model by
//! selective vertex updates and backbone fine-tuning on pseudo-poses, alternated (EM).
//!
//! The source model is never modified: [`adapt`] works on copies and returns them. The same
//! loop with ground-truth poses and all visible vertices is the supervised *oracle*
//! ([`finetune`]), so the two share their budget by construction.

use std::ops::ControlFlow;
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
use crate::mesh::Mesh;
use crate::metrics::rotation_error;
use crate::raster::Rasterizer;
use crate::solver::SolverConfig;
use crate::train::{SourceTraining, TrainConfig, VisibleVertices, visible_vertices};

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

/// Every knob of the adaptation. Defaults: METHOD.md §7, with the settings it leaves open
/// measured on SynCar-OOD `adapt` splits (reports/adapt-defaults.md): the paper's fixed cosine
/// 0.8 (τ_r fired for 70–90% of vertices on any image, so nothing was selected), lr 1e-5 (1e-4
/// lost precision), α 0.9 per 32 images and the source clutter kept (α 0.5 and a moving clutter
/// collapsed the vertex features on fog), 5 rounds (10 drifted further: 0.653 → 0.597
/// Acc@π/6 on `combined`; the convergence test never fired before round 10), and the target
/// images' BatchNorm statistics first (fog 0.157 → 0.900 with it; combined 0.653 → 0.683).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdaptConfig {
    pub threshold: Threshold,
    pub selection: Selection,
    /// ψ: an image's (hypothesis's) matches count only if this share of its visible vertices fire.
    pub min_fired_ratio: f64,
    /// Images scoring below this quantile of the round are left out of the backbone update.
    pub drop_quantile: f64,
    /// EMA weight α of the old vertex feature: `C_r ← α C_r + (1 − α) mean(fired f)`.
    pub alpha: f64,
    /// Images per vertex update (METHOD: at least 32).
    pub vertex_batch: usize,
    /// Also move the clutter vector towards the target's clutter features (same α).
    pub update_clutter: bool,
    /// Fine-tune the backbone on the pseudo-poses (false: vertex updates only).
    pub update_backbone: bool,
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
    /// Re-estimate κ_r from the fired features (`κ̂ = R̄(D − R̄²)/(1 − R̄²)`) at the end.
    pub reestimate_kappa: bool,
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
            min_fired_ratio: 0.05,
            drop_quantile: 0.2,
            alpha: 0.9,
            vertex_batch: 32,
            update_clutter: false,
            update_backbone: true,
            target_batchnorm: true,
            lr: 1e-5,
            batch: 16,
            max_rounds: 5,
            fired_gain: 0.01,
            pose_change_deg: 2.0,
            patience: 2,
            reestimate_kappa: false,
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
    Step { round: usize, phase: Phase, done: usize, total: usize },
    Round(&'a RoundReport),
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
    Run::new(source, images, config)?.em(progress)
}

/// The oracle: the same loop with the ground-truth `poses` as pseudo-poses, every visible vertex
/// a positive and `C` trained by its momentum bank (METHOD.md §5), for exactly
/// `backbone_steps` optimiser steps of `config.batch` images (the adaptation's budget).
pub fn finetune(
    source: &Model,
    images: &Tensor,
    poses: &[Pose],
    backbone_steps: usize,
    config: &AdaptConfig,
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
) -> Result<Adapted> {
    let mut run = Run::new(source, images, config)?;
    run.target_batchnorm()?;
    if poses.len() != run.n {
        return Err(EngineError::InvalidInput(format!("{} poses for {} images", poses.len(), run.n)));
    }
    let targets: Vec<Option<VisibleVertices>> = poses
        .iter()
        .map(|p| visible_vertices(&mut run.raster, &run.mesh, &run.crop, config.solver.stride, p).map(Some))
        .collect::<Result<_>>()?;
    let mut training = run.training();
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut opt = nn::Adam { wd: 1e-4, ..Default::default() }.build(&run.vs, config.lr).map_err(tch_err)?;
    let (mut steps, mut round) = (0, 0);
    while steps < backbone_steps {
        round += 1;
        let started = Instant::now();
        let left = backbone_steps - steps;
        let (loss, taken) =
            run.backbone_pass(&mut training, &mut opt, &targets, true, left, &mut rng, round, progress)?;
        steps += taken;
        let report = RoundReport {
            round,
            backbone_loss: Some(loss),
            images_trained: run.n,
            seconds: started.elapsed().as_secs_f64(),
            ..Default::default()
        };
        if progress(Event::Round(&report)).is_break() {
            return Err(EngineError::Cancelled);
        }
        run.rounds.push(report);
    }
    run.c = to_host(&training.vertex_features)?;
    run.clutter = to_host(&estimator::clutter_mean(&training.clutter))?;
    run.steps = steps;
    run.finish(false, vec![None; poses.len()], vec![0.0; poses.len()])
}

/// One image's best pose and the matches of each hypothesis.
struct Solved {
    pose: Pose,
    score: f64,
    hypotheses: Vec<Matches>,
}

/// The visible vertices at one pose, their feature cells and whether each fires.
struct Matches {
    visible: VisibleVertices,
    fired: Vec<bool>,
}

impl Matches {
    fn ratio(&self) -> f64 {
        if self.fired.is_empty() {
            0.0
        } else {
            self.fired.iter().filter(|&&f| f).count() as f64 / self.fired.len() as f64
        }
    }
}

struct Run<'a> {
    config: &'a AdaptConfig,
    images: &'a Tensor,
    n: usize,
    mesh: Mesh,
    crop: Camera,
    raster: Rasterizer,
    vs: nn::VarStore,
    backbone: Backbone,
    source_mesh: &'a NeuralMesh,
    dim: usize,
    /// `C` (R×D) and the clutter vectors (N×D) on the host, row-major.
    c: Vec<f32>,
    clutter: Vec<f32>,
    tau: Vec<f32>,
    rounds: Vec<RoundReport>,
    steps: usize,
    /// Per vertex, the sum and count of the fired features of the last vertex-update pass (κ̂).
    resultant: (Vec<f32>, Vec<usize>),
}

impl<'a> Run<'a> {
    fn new(source: &'a Model, images: &'a Tensor, config: &'a AdaptConfig) -> Result<Self> {
        config.validate()?;
        let [h, w] = source.manifest.crop;
        let size = images.size();
        if size.len() != 4 || size[1] != 3 || size[2] != h as i64 || size[3] != w as i64 || size[0] == 0 {
            return Err(EngineError::InvalidInput(format!("images must be N×3×{h}×{w}, got {size:?}")));
        }
        let mut vs = nn::VarStore::new(source.vs.device());
        let backbone = Backbone::new(vs.root(), source.manifest.backbone, source.manifest.feature_dim as i64);
        vs.copy(&source.vs).map_err(|e| EngineError::InvalidInput(format!("copying the backbone: {e}")))?;
        let nm = &source.neural_mesh;
        let r = nm.mesh.vertices().len();
        let tau = match config.threshold {
            Threshold::Source => to_host(&nm.tau)?,
            Threshold::Fixed(t) => vec![t as f32; r],
        };
        Ok(Run {
            config,
            images,
            n: size[0] as usize,
            mesh: nm.mesh.clone(),
            crop: Camera::for_crop(h, w)?,
            raster: Rasterizer::new(),
            vs,
            backbone,
            source_mesh: nm,
            dim: source.manifest.feature_dim,
            c: to_host(&nm.vertex_features)?,
            clutter: to_host(&nm.clutter)?,
            tau,
            rounds: Vec::new(),
            steps: 0,
            resultant: (Vec::new(), Vec::new()),
        })
    }

    /// The EM loop (METHOD.md §7.1–7).
    fn em(mut self, progress: &mut dyn FnMut(Event) -> ControlFlow<()>) -> Result<Adapted> {
        let config = self.config;
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let mut opt = nn::Adam { wd: 1e-4, ..Default::default() }.build(&self.vs, config.lr).map_err(tch_err)?;
        let mut previous: Option<Vec<Pose>> = None;
        let (mut calm, mut converged) = (0, false);
        let mut last = (Vec::new(), Vec::new());
        let source_fired = if config.target_batchnorm {
            let features = self.features(self.n.min(SOURCE_CHECK_IMAGES), 1, progress)?;
            let solved = self.solve_batch(&features)?;
            self.target_batchnorm()?;
            Some(mean(&solved.iter().map(|s| s.hypotheses[0].ratio()).collect::<Vec<_>>()))
        } else {
            None
        };
        for round in 1..=config.max_rounds {
            let started = Instant::now();
            let features = self.features(self.n, round, progress)?;
            let (before, updated) = self.vertex_update(&features, round, progress)?;
            let solved = self.solve_all(&features, round, Phase::PseudoPoses, progress)?;
            let poses: Vec<Pose> = solved.iter().map(|s| s.pose).collect();
            let ratios: Vec<f64> = solved.iter().map(|s| s.hypotheses[0].ratio()).collect();
            let targets = self.backbone_targets(&solved);
            let change = previous.as_ref().map(|p| pose_changes(p, &poses));
            let mut report = RoundReport {
                round,
                source_fired_ratio: source_fired.filter(|_| round == 1),
                fired_ratio_before: before,
                fired_ratio: mean(&ratios),
                vertices_updated: updated,
                images_selected: solved.iter().filter(|s| self.selected(&s.hypotheses[0])).count(),
                images_trained: targets.iter().filter(|t| t.is_some()).count(),
                pose_change_median_deg: change.as_ref().map(|c| quantile(c, 0.5)),
                pose_change_p90_deg: change.as_ref().map(|c| quantile(c, 0.9)),
                mean_score: mean(&solved.iter().map(|s| s.score).collect::<Vec<_>>()),
                ..Default::default()
            };
            let gain = report.fired_ratio - self.rounds.last().map_or(f64::NEG_INFINITY, |r| r.fired_ratio);
            let still = report.pose_change_median_deg.is_some_and(|c| c < config.pose_change_deg);
            calm = if gain < config.fired_gain && still { calm + 1 } else { 0 };
            converged = calm >= config.patience;
            previous = Some(poses.clone());
            last = (poses.into_iter().map(Some).collect(), ratios);
            if config.update_backbone && !converged && round < config.max_rounds {
                let mut training = self.training();
                let (loss, steps) = self.backbone_pass(
                    &mut training,
                    &mut opt,
                    &targets,
                    false,
                    usize::MAX,
                    &mut rng,
                    round,
                    progress,
                )?;
                report.backbone_loss = Some(loss);
                self.steps += steps;
            }
            report.seconds = started.elapsed().as_secs_f64();
            if progress(Event::Round(&report)).is_break() {
                return Err(EngineError::Cancelled);
            }
            self.rounds.push(report);
            if converged {
                break;
            }
        }
        self.finish(converged, last.0, last.1)
    }

    fn finish(self, converged: bool, pseudo_poses: Vec<Option<Pose>>, fired_ratios: Vec<f64>) -> Result<Adapted> {
        let device = self.vs.device();
        let (r, d) = (self.mesh.vertices().len() as i64, self.dim as i64);
        let vertex_features = Tensor::from_slice(&self.c).reshape([r, d]).to_device(device);
        let clutter = Tensor::from_slice(&self.clutter).reshape([-1, d]).to_device(device);
        let kappa = if self.config.reestimate_kappa && !self.resultant.1.is_empty() {
            let kappa = self.kappa_estimate();
            Tensor::from_slice(&kappa).to_device(device)
        } else {
            self.source_mesh.kappa.copy()
        };
        let neural_mesh = NeuralMesh {
            mesh: self.mesh,
            vertex_features,
            clutter,
            kappa,
            tau: self.source_mesh.tau.copy(),
            r_bar: self.source_mesh.r_bar.copy(),
        };
        Ok(Adapted {
            vs: self.vs,
            backbone: self.backbone,
            neural_mesh,
            rounds: self.rounds,
            converged,
            backbone_steps: self.steps,
            pseudo_poses,
            fired_ratios,
        })
    }

    /// `κ̂_r = R̄(D − R̄²)/(1 − R̄²)` from the last pass's fired features; the source κ_r where a
    /// vertex fired fewer than 2 times.
    fn kappa_estimate(&self) -> Vec<f32> {
        let d = self.dim;
        let source = to_host(&self.source_mesh.kappa).unwrap_or_else(|_| vec![0.0; self.resultant.1.len()]);
        (0..self.resultant.1.len())
            .map(|v| {
                let n = self.resultant.1[v];
                if n < 2 {
                    return source[v];
                }
                let sum = &self.resultant.0[v * d..][..d];
                let r = (sum.iter().map(|x| x * x).sum::<f32>().sqrt() / n as f32).min(0.999);
                r * (d as f32 - r * r) / (1.0 - r * r)
            })
            .collect()
    }

    /// The current backbone's features of the first `n` images (eval mode), on the host.
    fn features(
        &self,
        n: usize,
        round: usize,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<Vec<Features>> {
        let mut out = Vec::with_capacity(n);
        for start in (0..n).step_by(self.config.batch) {
            let len = self.config.batch.min(n - start);
            let batch = self.images.narrow(0, start as i64, len as i64).to_device(self.vs.device());
            out.extend(estimator::features(&self.backbone, &batch)?);
            step(progress, round, Phase::Features, out.len(), n)?;
        }
        Ok(out)
    }

    /// AdaBN (`config.target_batchnorm`): the target images' BatchNorm statistics replace the
    /// source's.
    fn target_batchnorm(&self) -> Result<()> {
        if self.config.target_batchnorm {
            self.backbone.reestimate_batchnorm(&self.vs, self.images, self.config.batch)?;
        }
        Ok(())
    }

    /// Render and compare on every image with the current `C`, and each hypothesis's matches.
    fn solve_all(
        &self,
        features: &[Features],
        round: usize,
        phase: Phase,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<Vec<Solved>> {
        let mut out = Vec::with_capacity(features.len());
        for chunk in features.chunks(self.config.vertex_batch) {
            out.extend(self.solve_batch(chunk)?);
            step(progress, round, phase, out.len(), features.len())?;
        }
        Ok(out)
    }

    fn solve_batch(&self, features: &[Features]) -> Result<Vec<Solved>> {
        let solver = PoseSolver::from_host(
            self.mesh.clone(),
            self.c.clone(),
            self.clutter.clone(),
            self.dim,
            self.crop,
            self.config.solver.clone(),
        )?;
        // Only host data crosses into the worker threads (tch tensors are not Sync).
        let (mesh, crop, config, tau) = (&self.mesh, &self.crop, self.config, &self.tau);
        features
            .par_iter()
            .map_init(Rasterizer::new, |raster, f| {
                let estimate = solver.solve(f)?;
                let hypotheses = estimate
                    .hypotheses
                    .iter()
                    .map(|h| {
                        let visible = visible_vertices(raster, mesh, crop, config.solver.stride, &h.pose)?;
                        let fired = fires(&visible, f, solver.vertex_features(), tau, solver.dim());
                        Ok(Matches { visible, fired })
                    })
                    .collect::<Result<Vec<_>>>()?;
                Ok(Solved { pose: estimate.pose, score: estimate.score, hypotheses })
            })
            .collect()
    }

    fn selected(&self, m: &Matches) -> bool {
        match self.config.selection {
            Selection::PerVertex => m.ratio() >= self.config.min_fired_ratio && m.ratio() > 0.0,
            Selection::Global(omega) => m.ratio() >= omega,
        }
    }

    /// The matches an image's hypotheses contribute: `(vertex, cell)` pairs.
    fn contributions<'m>(&self, solved: &'m Solved) -> impl Iterator<Item = (i64, i64)> + 'm {
        let global = matches!(self.config.selection, Selection::Global(_));
        let hypotheses = if global { &solved.hypotheses[..1] } else { &solved.hypotheses[..] };
        let keep: Vec<bool> = hypotheses.iter().map(|m| self.selected(m)).collect();
        hypotheses.iter().zip(keep).filter(|(_, k)| *k).flat_map(move |(m, _)| {
            m.visible
                .vertices
                .iter()
                .zip(&m.visible.cells)
                .zip(&m.fired)
                .filter(move |(_, fired)| global || **fired)
                .map(|((&v, &c), _)| (v, c))
        })
    }

    /// Step 5: solve each batch with the current `C`, then move every vertex that received
    /// fired features towards their mean. Returns the mean fired ratio before the updates and
    /// the share of vertices updated at least once.
    fn vertex_update(
        &mut self,
        features: &[Features],
        round: usize,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<(f64, f64)> {
        let (r, d) = (self.mesh.vertices().len(), self.dim);
        let mut ratios = Vec::with_capacity(features.len());
        let mut touched = vec![false; r];
        let alpha = self.config.alpha as f32;
        self.resultant = (vec![0f32; r * d], vec![0usize; r]);
        for (b, chunk) in features.chunks(self.config.vertex_batch).enumerate() {
            let solved = self.solve_batch(chunk)?;
            ratios.extend(solved.iter().map(|s| s.hypotheses[0].ratio()));
            let mut sums = vec![0f32; r * d];
            let mut counts = vec![0usize; r];
            let (mut clutter_sum, mut clutter_count) = (vec![0f32; d], 0usize);
            for (s, f) in solved.iter().zip(chunk) {
                for (v, cell) in self.contributions(s) {
                    add_feature(&mut sums[v as usize * d..][..d], f, cell as usize);
                    counts[v as usize] += 1;
                }
                for &cell in &s.hypotheses[0].visible.empty_cells {
                    add_feature(&mut clutter_sum, f, cell as usize);
                    clutter_count += 1;
                }
            }
            for v in (0..r).filter(|&v| counts[v] > 0) {
                touched[v] = true;
                self.resultant.1[v] += counts[v];
                self.resultant.0[v * d..][..d].iter_mut().zip(&sums[v * d..][..d]).for_each(|(a, s)| *a += s);
                let row = &mut self.c[v * d..][..d];
                let sum = &sums[v * d..][..d];
                let k = counts[v] as f32;
                row.iter_mut().zip(sum).for_each(|(c, s)| *c = alpha * *c + (1.0 - alpha) * s / k);
                normalise(row);
            }
            if self.config.update_clutter && clutter_count > 0 {
                for row in self.clutter.chunks_mut(d) {
                    row.iter_mut()
                        .zip(&clutter_sum)
                        .for_each(|(c, s)| *c = alpha * *c + (1.0 - alpha) * s / clutter_count as f32);
                    normalise(row);
                }
            }
            step(
                progress,
                round,
                Phase::VertexUpdate,
                (b * self.config.vertex_batch + chunk.len()).min(self.n),
                self.n,
            )?;
        }
        Ok((mean(&ratios), touched.iter().filter(|&&t| t).count() as f64 / r as f64))
    }

    /// Step 6's targets: per image, its pseudo-pose's positives (fired vertices; all visible
    /// ones under the global filter), or none when it failed the selection or scored below the
    /// round's `drop_quantile`.
    fn backbone_targets(&self, solved: &[Solved]) -> Vec<Option<VisibleVertices>> {
        let scores: Vec<f64> = solved.iter().map(|s| s.score).collect();
        let floor = quantile(&scores, self.config.drop_quantile);
        let global = matches!(self.config.selection, Selection::Global(_));
        solved
            .iter()
            .map(|s| {
                let best = &s.hypotheses[0];
                if s.score < floor || !self.selected(best) {
                    return None;
                }
                let mut v = best.visible.clone();
                if !global {
                    let keep = |i: &usize| best.fired[*i];
                    v.vertices = (0..best.fired.len()).filter(keep).map(|i| best.visible.vertices[i]).collect();
                    v.cells = (0..best.fired.len()).filter(keep).map(|i| best.visible.cells[i]).collect();
                }
                Some(v)
            })
            .collect()
    }

    /// The contrastive loss of METHOD.md §5 around the current `C` and clutter.
    fn training(&self) -> SourceTraining {
        let device = self.vs.device();
        let (r, d) = (self.mesh.vertices().len() as i64, self.dim as i64);
        let c = Tensor::from_slice(&self.c).reshape([r, d]).to_device(device);
        let clutter = Tensor::from_slice(&self.clutter).reshape([-1, d]).to_device(device);
        SourceTraining::from_model(self.config.train.clone(), self.mesh.clone(), self.crop, &c, &clutter)
    }

    /// One pass over the images with targets, at most `max_steps` optimiser steps, BatchNorm
    /// statistics frozen. Returns the mean loss and the steps taken.
    #[allow(clippy::too_many_arguments)]
    fn backbone_pass(
        &mut self,
        training: &mut SourceTraining,
        opt: &mut nn::Optimizer,
        targets: &[Option<VisibleVertices>],
        update_vertices: bool,
        max_steps: usize,
        rng: &mut ChaCha8Rng,
        round: usize,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<(f64, usize)> {
        use rand::seq::SliceRandom;
        let mut order: Vec<usize> =
            (0..self.n).filter(|&i| targets[i].as_ref().is_some_and(|t| !t.vertices.is_empty())).collect();
        order.shuffle(rng);
        let (mut sum, mut steps) = (0.0, 0);
        let device = self.vs.device();
        for (b, chunk) in order.chunks(self.config.batch).enumerate() {
            if steps == max_steps {
                break;
            }
            let index = Tensor::from_slice(&chunk.iter().map(|&i| i as i64).collect::<Vec<_>>());
            let images = self.images.index_select(0, &index).to_device(device);
            let features = self.backbone.forward_t(&preprocess(&images)?, false);
            let visible: Vec<VisibleVertices> = chunk.iter().map(|&i| targets[i].clone().unwrap_or_default()).collect();
            let (loss, stats) = training.step_visible(&features, &visible, rng, update_vertices)?;
            opt.backward_step(&loss);
            sum += stats.loss;
            steps += 1;
            step(progress, round, Phase::Backbone, ((b + 1) * self.config.batch).min(order.len()), order.len())?;
        }
        Ok((sum / steps.max(1) as f64, steps))
    }
}

/// The share of an image's visible vertices (at `pose`) whose feature fires against `model`'s
/// vertex features and thresholds: the diagnostic the paper plots by azimuth.
pub fn fired_ratio(
    neural_mesh: &NeuralMesh,
    features: &Features,
    crop: &Camera,
    stride: usize,
    pose: &Pose,
    threshold: Threshold,
) -> Result<f64> {
    let mut raster = Rasterizer::new();
    let visible = visible_vertices(&mut raster, &neural_mesh.mesh, crop, stride, pose)?;
    let dim = neural_mesh.vertex_features.size()[1] as usize;
    let c = to_host(&neural_mesh.vertex_features)?;
    let tau = to_host(&neural_mesh.tau)?;
    if visible.vertices.is_empty() {
        return Ok(0.0);
    }
    let tau = match threshold {
        Threshold::Source => tau,
        Threshold::Fixed(t) => vec![t as f32; tau.len()],
    };
    let fired = fires(&visible, features, &c, &tau, dim).into_iter().filter(|&f| f).count();
    Ok(fired as f64 / visible.vertices.len() as f64)
}

/// Which visible vertices fire: `f·C_r > τ_r` (METHOD.md §7.3).
fn fires(visible: &VisibleVertices, f: &Features, c: &[f32], tau: &[f32], dim: usize) -> Vec<bool> {
    visible
        .vertices
        .iter()
        .zip(&visible.cells)
        .map(|(&v, &cell)| cosine(f, cell as usize, &c[v as usize * dim..][..dim]) > tau[v as usize])
        .collect()
}

fn tch_err(e: tch::TchError) -> EngineError {
    EngineError::InvalidInput(format!("libtorch: {e}"))
}

fn step(
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    round: usize,
    phase: Phase,
    done: usize,
    total: usize,
) -> Result<()> {
    match progress(Event::Step { round, phase, done, total }) {
        ControlFlow::Continue(()) => Ok(()),
        ControlFlow::Break(()) => Err(EngineError::Cancelled),
    }
}

/// `f(cell) · c` for a channel-major feature map.
fn cosine(f: &Features, cell: usize, c: &[f32]) -> f32 {
    let hw = f.height * f.width;
    c.iter().enumerate().map(|(k, ck)| f.data[k * hw + cell] * ck).sum()
}

fn add_feature(sum: &mut [f32], f: &Features, cell: usize) {
    let hw = f.height * f.width;
    sum.iter_mut().enumerate().for_each(|(k, s)| *s += f.data[k * hw + cell]);
}

fn normalise(row: &mut [f32]) {
    let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    row.iter_mut().for_each(|x| *x /= norm);
}

fn pose_changes(a: &[Pose], b: &[Pose]) -> Vec<f64> {
    a.iter().zip(b).map(|(p, q)| rotation_error(&p.rotation(), &q.rotation()).to_degrees()).collect()
}

fn mean(v: &[f64]) -> f64 {
    if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 }
}

/// The `q` quantile (nearest rank) of `v`; 0 for an empty `v`.
fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(((s.len().max(1) - 1) as f64 * q).round() as usize).copied().unwrap_or(0.0)
}
