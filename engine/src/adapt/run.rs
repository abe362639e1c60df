//! One adaptation run: its state, the EM rounds, pseudo-poses, the selective vertex update and
//! the backbone step.

use super::resume::{Loop, Resume};
use super::*;

/// One image's best pose and the matches of each hypothesis.
pub(super) struct Solved {
    pub(super) pose: Pose,
    pub(super) score: f64,
    pub(super) hypotheses: Vec<Matches>,
    /// Whether the mirrored crop agrees ([`AdaptConfig::flip_check`]; true without the check).
    pub(super) agrees: bool,
}

/// The visible vertices at one pose, their feature cells, whether each fires and whether its
/// cell is assigned to the object.
pub(super) struct Matches {
    pub(super) visible: VisibleVertices,
    pub(super) fired: Vec<bool>,
    pub(super) object: Vec<bool>,
}

impl Matches {
    pub(super) fn ratio(&self) -> f64 {
        if self.fired.is_empty() {
            0.0
        } else {
            self.fired.iter().filter(|&&f| f).count() as f64 / self.fired.len() as f64
        }
    }
}

pub(super) struct Run<'a> {
    pub(super) config: &'a AdaptConfig,
    pub(super) images: &'a Tensor,
    pub(super) n: usize,
    pub(super) mesh: Mesh,
    pub(super) crop: Camera,
    pub(super) raster: Rasterizer,
    pub(super) vs: nn::VarStore,
    pub(super) backbone: Backbone,
    pub(super) source_mesh: &'a NeuralMesh,
    pub(super) dim: usize,
    /// `C` (R×D) and the clutter vectors (N×D) on the host, row-major.
    pub(super) c: Vec<f32>,
    pub(super) clutter: Vec<f32>,
    pub(super) tau: Vec<f32>,
    pub(super) rounds: Vec<RoundReport>,
    pub(super) steps: usize,
    /// The rounds restored from a snapshot ([`super::resume`]).
    pub(super) resumed_after: Option<usize>,
}

impl<'a> Run<'a> {
    pub(super) fn new(source: &'a Model, images: &'a Tensor, config: &'a AdaptConfig) -> Result<Self> {
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
            resumed_after: None,
        })
    }

    /// The EM loop (METHOD.md §7.1–7); with `resume`, from the newest snapshot there, and
    /// snapshotted after each round.
    pub(super) fn em(
        mut self,
        resume: Option<&Resume>,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<Adapted> {
        let config = self.config;
        if config.batchnorm_only() {
            self.target_batchnorm()?;
            let n = self.n;
            return self.finish(false, vec![None; n], Vec::new());
        }
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let restored = match resume {
            Some(r) => self.restore(r, &mut rng, None)?,
            None => None,
        };
        let resumed = restored.is_some();
        let mut state = restored.unwrap_or_default();
        if resumed && progress(Event::Resumed { rounds: self.rounds.len() }).is_break() {
            return Err(EngineError::Cancelled);
        }
        // A resumed run's snapshot already has the target's BatchNorm statistics.
        let source_fired = if config.target_batchnorm && !resumed {
            let fired = mean(&self.source_fired(progress)?);
            if progress(Event::TargetCheck { fired }).is_break() {
                return Err(EngineError::Cancelled);
            }
            self.target_batchnorm()?;
            Some(fired)
        } else {
            None
        };
        let mut opt = nn::Adam { wd: 1e-4, ..Default::default() }.build(&self.vs, config.lr).map_err(tch_err)?;
        for round in self.rounds.len() + 1..=config.max_rounds {
            if state.converged {
                break;
            }
            let started = Instant::now();
            let features = self.features(self.n, false, round, progress)?;
            let mirrors = if config.flip_check { Some(self.features(self.n, true, round, progress)?) } else { None };
            let (before, updated) = self.vertex_update(&features, mirrors.as_deref(), round, progress)?;
            let solved = self.solve_all(&features, mirrors.as_deref(), round, Phase::PseudoPoses, progress)?;
            let poses: Vec<Pose> = solved.iter().map(|s| s.pose).collect();
            let ratios: Vec<f64> = solved.iter().map(|s| s.hypotheses[0].ratio()).collect();
            let targets = self.backbone_targets(&solved);
            let change = (!state.poses.is_empty()).then(|| pose_changes(&state.poses, &poses));
            let mut report = RoundReport {
                round,
                source_fired_ratio: source_fired.filter(|_| round == 1),
                fired_ratio_before: before,
                fired_ratio: mean(&ratios),
                vertices_updated: updated,
                images_selected: solved.iter().filter(|s| self.selected(&s.hypotheses[0])).count(),
                images_trained: targets.iter().filter(|t| t.is_some()).count(),
                flip_consistent: config.flip_check.then(|| solved.iter().filter(|s| s.agrees).count()),
                positive_share: positive_share(&solved, &targets),
                pose_change_median_deg: change.as_ref().map(|c| quantile(c, 0.5)),
                pose_change_p90_deg: change.as_ref().map(|c| quantile(c, 0.9)),
                mean_score: mean(&solved.iter().map(|s| s.score).collect::<Vec<_>>()),
                ..Default::default()
            };
            let gain = report.fired_ratio - self.rounds.last().map_or(f64::NEG_INFINITY, |r| r.fired_ratio);
            let still = report.pose_change_median_deg.is_some_and(|c| c < config.pose_change_deg);
            state.calm = if gain < config.fired_gain && still { state.calm + 1 } else { 0 };
            state.converged = state.calm >= config.patience;
            (state.poses, state.ratios) = (poses, ratios);
            if config.update_backbone && !state.converged && round < config.max_rounds {
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
            self.end_round(report, resume, &rng, &state, None, progress)?;
        }
        self.finish(state.converged, state.poses.into_iter().map(Some).collect(), state.ratios)
    }

    /// The fired ratio of each of up to [`SOURCE_CHECK_IMAGES`] of the images to the model as
    /// it is (before any BatchNorm step); their mean is [`RoundReport::source_fired_ratio`].
    pub(super) fn source_fired(&self, progress: &mut dyn FnMut(Event) -> ControlFlow<()>) -> Result<Vec<f64>> {
        let features = self.features(self.n.min(SOURCE_CHECK_IMAGES), false, 1, progress)?;
        let solved = self.solve_batch(&features, None)?;
        Ok(solved.iter().map(|s| s.hypotheses[0].ratio()).collect())
    }

    /// Records a finished round, snapshots the run (with `resume`) and reports the round.
    pub(super) fn end_round(
        &mut self,
        report: RoundReport,
        resume: Option<&Resume>,
        rng: &ChaCha8Rng,
        state: &Loop,
        banks: Option<&SourceTraining>,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<()> {
        self.rounds.push(report.clone());
        if let Some(r) = resume {
            self.save(r, rng, state, banks)?;
        }
        if progress(Event::Round(&report)).is_break() {
            return Err(EngineError::Cancelled);
        }
        Ok(())
    }

    pub(super) fn finish(
        self,
        converged: bool,
        pseudo_poses: Vec<Option<Pose>>,
        fired_ratios: Vec<f64>,
    ) -> Result<Adapted> {
        let device = self.vs.device();
        let (r, d) = (self.mesh.vertices().len() as i64, self.dim as i64);
        let vertex_features = Tensor::from_slice(&self.c).reshape([r, d]).to_device(device);
        let clutter = Tensor::from_slice(&self.clutter).reshape([-1, d]).to_device(device);
        let neural_mesh = NeuralMesh {
            mesh: self.mesh,
            vertex_features,
            clutter,
            kappa: self.source_mesh.kappa.copy(),
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
            resumed_after: self.resumed_after,
            pseudo_poses,
            fired_ratios,
        })
    }

    /// The current backbone's features of the first `n` images (eval mode), on the host; of
    /// their mirrored crops when `mirrored`.
    pub(super) fn features(
        &self,
        n: usize,
        mirrored: bool,
        round: usize,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<Vec<Features>> {
        let mut out = Vec::with_capacity(n);
        for start in (0..n).step_by(self.config.batch) {
            let len = self.config.batch.min(n - start);
            let batch = self.images.narrow(0, start as i64, len as i64).to_device(self.vs.device());
            let batch = if mirrored { mirror_crops(&batch) } else { batch };
            out.extend(estimator::features(&self.backbone, &batch)?);
            step(progress, round, Phase::Features, out.len(), n)?;
        }
        Ok(out)
    }

    /// AdaBN (`config.target_batchnorm`): the target images' BatchNorm statistics replace the
    /// source's.
    pub(super) fn target_batchnorm(&self) -> Result<()> {
        if self.config.target_batchnorm {
            self.backbone.reestimate_batchnorm(&self.vs, self.images, self.config.batch)?;
        }
        Ok(())
    }

    /// Render and compare on every image with the current `C`, and each hypothesis's matches;
    /// with `mirrors` (the mirrored crops' features), whether each image is flip-consistent.
    pub(super) fn solve_all(
        &self,
        features: &[Features],
        mirrors: Option<&[Features]>,
        round: usize,
        phase: Phase,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<Vec<Solved>> {
        let mut out = Vec::with_capacity(features.len());
        for range in ranges(features.len(), self.config.vertex_batch) {
            out.extend(self.solve_batch(&features[range.clone()], mirrors.map(|m| &m[range]))?);
            step(progress, round, phase, out.len(), features.len())?;
        }
        Ok(out)
    }

    pub(super) fn solve_batch(&self, features: &[Features], mirrors: Option<&[Features]>) -> Result<Vec<Solved>> {
        let solver = PoseSolver::from_host(
            self.mesh.clone(),
            self.c.clone(),
            self.clutter.clone(),
            self.dim,
            self.crop,
            self.config.solver.clone(),
        )?;
        // Only host data crosses into the worker threads (tch tensors are not Sync).
        let (mesh, crop, config, tau, clutter) = (&self.mesh, &self.crop, self.config, &self.tau, &self.clutter);
        (0..features.len())
            .into_par_iter()
            .map_init(Rasterizer::new, |raster, i| {
                let (f, mirror) = (&features[i], mirrors.map(|m| &m[i]));
                let estimate = solver.solve(f)?;
                let agrees = match mirror {
                    Some(g) => flip_consistent(&estimate.pose, &solver.solve(g)?.pose),
                    None => true,
                };
                let hypotheses = estimate
                    .hypotheses
                    .iter()
                    .map(|h| {
                        let visible = visible_vertices(raster, mesh, crop, config.solver.stride, &h.pose)?;
                        let (c, dim) = (solver.vertex_features(), solver.dim());
                        let fired = fires(&visible, f, c, tau, dim);
                        let object = on_object(&visible, f, c, clutter, dim);
                        Ok(Matches { visible, fired, object })
                    })
                    .collect::<Result<Vec<_>>>()?;
                Ok(Solved { pose: estimate.pose, score: estimate.score, hypotheses, agrees })
            })
            .collect()
    }

    pub(super) fn selected(&self, m: &Matches) -> bool {
        match self.config.selection {
            Selection::PerVertex => m.ratio() >= self.config.min_fired_ratio && m.ratio() > 0.0,
            Selection::Global(omega) => m.ratio() >= omega,
        }
    }

    /// The matches an image's hypotheses contribute: `(vertex, cell)` pairs.
    pub(super) fn contributions<'m>(&self, solved: &'m Solved) -> impl Iterator<Item = (i64, i64)> + 'm {
        let global = matches!(self.config.selection, Selection::Global(_));
        let best = global || self.config.vertex_matches == VertexMatches::Best;
        // An image whose mirror disagrees (AdaptConfig::flip_check) contributes nothing.
        let used = match (solved.agrees, best) {
            (false, _) => 0,
            (true, true) => 1,
            (true, false) => solved.hypotheses.len(),
        };
        let hypotheses = &solved.hypotheses[..used];
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
    pub(super) fn vertex_update(
        &mut self,
        features: &[Features],
        mirrors: Option<&[Features]>,
        round: usize,
        progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    ) -> Result<(f64, f64)> {
        let (r, d) = (self.mesh.vertices().len(), self.dim);
        let mut ratios = Vec::with_capacity(features.len());
        let mut touched = vec![false; r];
        // α per round, whatever the number of batches (AdaptConfig::alpha).
        let batches = features.len().div_ceil(self.config.vertex_batch).max(1);
        let alpha = (self.config.alpha as f32).powf(1.0 / batches as f32);
        for range in ranges(features.len(), self.config.vertex_batch) {
            let (chunk, end) = (&features[range.clone()], range.end);
            let solved = self.solve_batch(chunk, mirrors.map(|m| &m[range]))?;
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
            step(progress, round, Phase::VertexUpdate, end, features.len())?;
        }
        Ok((mean(&ratios), touched.iter().filter(|&&t| t).count() as f64 / r as f64))
    }

    /// Step 6's targets: per image, its pseudo-pose's positives ([`Positives`]; all visible
    /// vertices under the global filter), or none when it failed the selection or scored below
    /// the round's `drop_quantile`.
    pub(super) fn backbone_targets(&self, solved: &[Solved]) -> Vec<Option<VisibleVertices>> {
        let scores: Vec<f64> = solved.iter().map(|s| s.score).collect();
        let floor = quantile(&scores, self.config.drop_quantile);
        let global = matches!(self.config.selection, Selection::Global(_));
        solved
            .iter()
            .map(|s| {
                let best = &s.hypotheses[0];
                if s.score < floor || !self.selected(best) || !s.agrees {
                    return None;
                }
                let mut v = best.visible.clone();
                let keep = match self.config.positives {
                    _ if global => return Some(v),
                    Positives::Visible => return Some(v),
                    Positives::Fired => &best.fired,
                    Positives::Object => &best.object,
                };
                // The neighbour mask still uses every vertex's projection (`projected`).
                let kept = |list: &[i64]| list.iter().zip(keep).filter(|(_, k)| **k).map(|(x, _)| *x).collect();
                (v.vertices, v.cells) = (kept(&best.visible.vertices), kept(&best.visible.cells));
                Some(v)
            })
            .collect()
    }

    /// The contrastive loss of METHOD.md §5 around the current `C` and clutter.
    pub(super) fn training(&self) -> SourceTraining {
        let device = self.vs.device();
        let (r, d) = (self.mesh.vertices().len() as i64, self.dim as i64);
        let c = Tensor::from_slice(&self.c).reshape([r, d]).to_device(device);
        let clutter = Tensor::from_slice(&self.clutter).reshape([-1, d]).to_device(device);
        SourceTraining::from_model(self.config.train.clone(), self.mesh.clone(), self.crop, &c, &clutter)
    }

    /// One pass over the images with targets, at most `max_steps` optimiser steps, BatchNorm
    /// statistics frozen. Returns the mean loss and the steps taken.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn backbone_pass(
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

/// `0..n` in consecutive ranges of `size`.
fn ranges(n: usize, size: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    (0..n).step_by(size.max(1)).map(move |start| start..(start + size).min(n))
}

/// Mean over the trained images of their positives' share of their visible vertices.
fn positive_share(solved: &[Solved], targets: &[Option<VisibleVertices>]) -> f64 {
    let shares: Vec<f64> = solved
        .iter()
        .zip(targets)
        .filter_map(|(s, t)| {
            Some(t.as_ref()?.vertices.len() as f64 / s.hypotheses[0].visible.vertices.len().max(1) as f64)
        })
        .collect();
    mean(&shares)
}
