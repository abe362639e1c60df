//! Render-and-compare pose estimation, fast form (METHOD.md §6).
//!
//! For an image with unit features `F` (D × h × w, the stride-8 grid), a neural mesh with vertex
//! features `C` (R × D) and clutter vectors `B` (N × D), the loss of a pose `g` is
//!
//! ```text
//! obj(p) = Σ_k w_k S[v_k, p]   (the face covering p, barycentrics w; 0 where no face)
//! clu(p) = max_n β_n·F(p)
//! L(g)   = 1 − (mean_p max(obj, clu) − mean_p clu),      score = 1 − L
//! ```
//!
//! with `S = C·F` computed once per image by one GEMM ([`Problem::new`]). A pose evaluation is
//! then one [`Rasterizer::render_faces`] on the feature grid and a gather over `S`, and its
//! gradient follows analytically ([`Problem::loss_and_gradient`]). [`multi_pose_init`] scores
//! the 144-pose grid, each pose at its own fit distance, and keeps the `k` best mutually distant
//! poses; [`render_and_compare`] refines each of them over `(a, e, θ, log d)` and returns the
//! lowest-loss hypothesis.
//!
//! # Optimiser choice (measured: `cargo bench -p udapose-engine --bench solver`)
//!
//! The default refines each hypothesis with Adam on the analytic gradient, METHOD's schedule
//! compressed to 150 steps: as accurate as METHOD's 300 steps on synthetic images of known pose
//! in 1.8× less time per image, and more accurate than a derivative-free pattern search on the
//! exact loss (also available, [`Optimizer::PatternSearch`]); numbers on [`Optimizer::default`]
//! and in `reports/solver-synthetic.md`. Each learning rate's phase ends once the loss stops
//! falling, and after 4 steps the hypotheses trailing the leader by more than 0.02 stop
//! ([`AdamConfig::default`], [`Prune`]): about a tenth of the evaluations, the same answers
//! on source images (`reports/solver.md`, `reports/refine-variants.md`). [`AdamConfig::fixed`] with no pruning is the fixed schedule.

mod caster;
mod dot;
mod gradient;
mod grid;
mod optimise;
mod similarity;

use std::f64::consts::{PI, TAU};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Pose, fit_distance};
use crate::error::{EngineError, Result};
use crate::mesh::Mesh;
use crate::metrics::rotation_error;
use crate::raster::Rasterizer;
use similarity::Similarity;

pub use caster::CuboidCaster;
pub use grid::GridRenders;
pub use optimise::{AdamConfig, Optimizer, PatternSearchConfig, Prune};

/// Stride of the backbone's feature grid relative to the crop (METHOD.md §2).
pub const FEATURE_STRIDE: usize = 8;

/// Solver settings. The defaults are METHOD.md §6's grid and `k`, and the measured optimiser.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SolverConfig {
    /// Number of hypotheses `k` refined from the grid (3 as in 3DUDA; 1 is NeMo).
    pub hypotheses: usize,
    /// Grid azimuths (radians): 0°, 30°, …, 330°.
    pub azimuths: Vec<f64>,
    /// Grid elevations (radians): −30°, 0°, 30°, 60°.
    pub elevations: Vec<f64>,
    /// Grid in-plane rotations (radians): −30°, 0°, 30°.
    pub thetas: Vec<f64>,
    /// Smallest geodesic angle (radians) between two kept grid poses: 45°.
    pub min_separation: f64,
    /// Fill of the crop at which each grid pose is placed (its fit distance): 0.875, the middle
    /// of the detection-crop band 0.8–0.95.
    pub fill: f64,
    /// Stride of the feature grid relative to the crop: 8.
    pub stride: usize,
    /// How each hypothesis is refined.
    pub optimizer: Optimizer,
    /// Which hypotheses stop early because another clearly leads (none in configurations
    /// written before this field existed).
    #[serde(default)]
    pub prune: Prune,
    /// Evaluate poses by ray casting where the mesh is a cuboid mesh ([`CuboidCaster`]); false
    /// rasterises every pose, as the solver did before the caster (kept for comparison).
    #[serde(default = "ray_cast_default")]
    pub ray_cast: bool,
}

fn ray_cast_default() -> bool {
    true
}

impl Default for SolverConfig {
    fn default() -> Self {
        SolverConfig {
            hypotheses: 3,
            azimuths: (0..12).map(|i| (30.0 * i as f64).to_radians()).collect(),
            elevations: [-30.0f64, 0.0, 30.0, 60.0].map(f64::to_radians).to_vec(),
            thetas: [-30.0f64, 0.0, 30.0].map(f64::to_radians).to_vec(),
            min_separation: 45f64.to_radians(),
            fill: 0.875,
            stride: FEATURE_STRIDE,
            optimizer: Optimizer::default(),
            // Measured with the optimiser's plateau stopping (see `AdamConfig::default`); after 4
            // rather than 6, 9% fewer evaluations, the same verdicts on source (`reports/refine-variants.md`).
            prune: Prune { after: 4, margin: 0.02 },
            ray_cast: true,
        }
    }
}

impl SolverConfig {
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(EngineError::InvalidInput(m));
        if self.hypotheses == 0 {
            return bad("hypotheses must be at least 1".into());
        }
        for (name, v) in [("azimuths", &self.azimuths), ("elevations", &self.elevations), ("thetas", &self.thetas)] {
            if v.is_empty() {
                return bad(format!("the pose grid has no {name}"));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return bad(format!("non-finite grid {name}"));
            }
        }
        if !(self.min_separation.is_finite() && self.min_separation >= 0.0) {
            return bad(format!("min_separation must be finite and >= 0, got {}", self.min_separation));
        }
        if !(self.fill.is_finite() && self.fill > 0.0) {
            return bad(format!("fill must be finite and > 0, got {}", self.fill));
        }
        if self.stride == 0 {
            return bad("stride 0".into());
        }
        self.prune.validate()?;
        self.optimizer.validate()
    }

    /// The grid's `[a, e, θ]`, azimuth slowest, θ fastest.
    pub fn grid_angles(&self) -> Vec<[f64; 3]> {
        let mut out = Vec::with_capacity(self.azimuths.len() * self.elevations.len() * self.thetas.len());
        for &a in &self.azimuths {
            for &e in &self.elevations {
                out.extend(self.thetas.iter().map(|&t| [a, e, t]));
            }
        }
        out
    }
}

/// A feature map `D × h × w` (channel-major, as a backbone writes it), unit norm per pixel.
#[derive(Clone, Copy, Debug)]
pub struct FeatureMap<'a> {
    data: &'a [f32],
    dim: usize,
    height: usize,
    width: usize,
}

impl<'a> FeatureMap<'a> {
    /// Checks the size and that every value is finite (unit norm is assumed, not checked).
    pub fn new(data: &'a [f32], dim: usize, height: usize, width: usize) -> Result<Self> {
        if height == 0 || width == 0 {
            return Err(EngineError::EmptyImage { width, height });
        }
        if dim == 0 {
            return Err(EngineError::InvalidInput("feature dimension 0".into()));
        }
        let n = dim.checked_mul(height).and_then(|n| n.checked_mul(width));
        if n != Some(data.len()) {
            return Err(EngineError::InvalidInput(format!(
                "feature map of {} values is not {dim} × {height} × {width}",
                data.len()
            )));
        }
        // A branch-free pass first (it vectorises; `position` alone cost a tenth of the
        // image's preparation), the position only for the message.
        if data.iter().fold(false, |bad, v| bad | !v.is_finite())
            && let Some(i) = data.iter().position(|v| !v.is_finite())
        {
            return Err(EngineError::InvalidInput(format!("feature value {i} is not finite")));
        }
        Ok(FeatureMap { data, dim, height, width })
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn height(&self) -> usize {
        self.height
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn data(&self) -> &'a [f32] {
        self.data
    }
}

/// A neural mesh as the solver sees it: geometry, vertex features `C` (R × D, row-major, unit
/// norm) and clutter vectors `B` (N × D, N ≥ 1; NeMo uses N = 1, the normalised bank mean).
#[derive(Clone, Copy, Debug)]
pub struct NeuralMeshView<'a> {
    mesh: &'a Mesh,
    vertex_features: &'a [f32],
    clutter: &'a [f32],
    dim: usize,
}

impl<'a> NeuralMeshView<'a> {
    pub fn new(mesh: &'a Mesh, vertex_features: &'a [f32], clutter: &'a [f32], dim: usize) -> Result<Self> {
        let bad = |m: String| Err(EngineError::InvalidInput(m));
        if dim == 0 {
            return bad("feature dimension 0".into());
        }
        let r = mesh.vertices().len();
        if vertex_features.len() != r * dim {
            return bad(format!("{} vertex feature values are not {r} vertices × {dim}", vertex_features.len()));
        }
        if clutter.is_empty() || !clutter.len().is_multiple_of(dim) {
            return bad(format!("{} clutter values are not N × {dim} with N >= 1", clutter.len()));
        }
        if vertex_features.iter().chain(clutter).any(|v| !v.is_finite()) {
            return bad("non-finite vertex or clutter feature".into());
        }
        Ok(NeuralMeshView { mesh, vertex_features, clutter, dim })
    }

    /// A view of parts [`NeuralMeshView::new`] has already checked (a solver's, per image:
    /// checking 135k vertex feature values again cost more than preparing the image).
    pub(crate) fn checked(mesh: &'a Mesh, vertex_features: &'a [f32], clutter: &'a [f32], dim: usize) -> Self {
        NeuralMeshView { mesh, vertex_features, clutter, dim }
    }

    pub fn mesh(&self) -> &'a Mesh {
        self.mesh
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn vertex_features(&self) -> &'a [f32] {
        self.vertex_features
    }

    pub fn clutter(&self) -> &'a [f32] {
        self.clutter
    }
}

/// Per-thread buffers of pose evaluation: the rasteriser and the per-vertex gradient, or the
/// ray caster's runs of cells.
#[derive(Debug, Default)]
pub struct Scratch {
    raster: Rasterizer,
    vertex_grad: Vec<[f64; 3]>,
    runs: Vec<[usize; 3]>,
}

/// One image prepared for pose evaluation: `S = C·F` (each entry computed when first read, see
/// [`similarity`]) and the clutter map.
#[derive(Debug)]
pub struct Problem<'a> {
    mesh: &'a Mesh,
    crop: Camera,
    grid: Camera,
    vertices: usize,
    pixels: usize,
    similarity: Similarity<'a>,
    clutter: Vec<f32>,
    /// `max(0, clu(p))`: what an uncovered pixel contributes to `mean max(obj, clu)`.
    clutter_pos: Vec<f32>,
    /// `Σ_p max(0, clu(p)) − clu(p)`: the loss sum with no pixel covered.
    base: f64,
    /// The cuboid's ray caster where the mesh is one (evaluations then skip the rasteriser).
    caster: Option<CuboidCaster>,
}

impl<'a> Problem<'a> {
    /// Prepares an image whose crop camera is `crop` (`Camera::for_crop(H, W)`); `features`
    /// must be on `crop.at_stride(stride)`'s grid. Poses are evaluated by ray casting when the
    /// mesh is a cuboid mesh ([`CuboidCaster::detect`]), by the rasteriser otherwise.
    pub fn new(model: &NeuralMeshView<'a>, features: &FeatureMap, crop: &Camera, stride: usize) -> Result<Self> {
        Problem::with_caster(model, features, crop, stride, CuboidCaster::detect(model.mesh))
    }

    /// [`Problem::new`] with the caster already detected (once per solver, not per image):
    /// `caster` must be [`CuboidCaster::detect`] of `model`'s mesh.
    pub fn with_caster(
        model: &NeuralMeshView<'a>,
        features: &FeatureMap,
        crop: &Camera,
        stride: usize,
        caster: Option<CuboidCaster>,
    ) -> Result<Self> {
        let grid = crop.at_stride(stride)?;
        if grid.width == 0 || grid.height == 0 {
            return Err(EngineError::EmptyImage { width: grid.width, height: grid.height });
        }
        if (features.height, features.width) != (grid.height, grid.width) {
            return Err(EngineError::InvalidInput(format!(
                "features are {}×{} but a {}×{} crop at stride {stride} gives {}×{}",
                features.height, features.width, crop.height, crop.width, grid.height, grid.width
            )));
        }
        if features.dim != model.dim {
            return Err(EngineError::InvalidInput(format!(
                "feature dimension {} but the mesh model has {}",
                features.dim, model.dim
            )));
        }
        let r = model.mesh.vertices().len();
        let (d, p) = (model.dim, grid.width * grid.height);
        let similarity = Similarity::new(features.data, p, model.vertex_features, d);
        let clutter: Vec<f32> = (0..p)
            .map(|px| {
                let f = similarity.feature(px);
                model.clutter.chunks_exact(d).map(|b| similarity.dot(b, f)).fold(f32::NEG_INFINITY, f32::max)
            })
            .collect();
        let clutter_pos: Vec<f32> = clutter.iter().map(|&c| c.max(0.0)).collect();
        let base = clutter.iter().map(|&c| f64::from(c.max(0.0) - c)).sum();
        Ok(Problem {
            mesh: model.mesh,
            crop: *crop,
            grid,
            vertices: r,
            pixels: p,
            similarity,
            clutter,
            clutter_pos,
            base,
            caster,
        })
    }

    /// Whether poses are evaluated by ray casting.
    pub fn is_ray_cast(&self) -> bool {
        self.caster.is_some()
    }

    pub fn mesh(&self) -> &'a Mesh {
        self.mesh
    }

    /// The crop's camera (fit distances are measured on it).
    pub fn crop_camera(&self) -> &Camera {
        &self.crop
    }

    /// The feature grid's camera (poses are rendered on it).
    pub fn grid_camera(&self) -> &Camera {
        &self.grid
    }

    /// `S[v, p] = C_v·F(p)` (computed now if no pose has read it yet).
    pub fn similarity(&self, pixel: usize, vertex: usize) -> f32 {
        self.similarity.get(pixel, vertex)
    }

    /// `clu(p) = max_n β_n·F(p)`, row-major over the grid.
    pub fn clutter_map(&self) -> &[f32] {
        &self.clutter
    }

    /// `L(pose)`.
    pub fn loss(&self, scratch: &mut Scratch, pose: &Pose) -> Result<f64> {
        match &self.caster {
            Some(caster) => gradient::cast(self, caster, &mut scratch.runs, pose, false).map(|(loss, _)| loss),
            None => self.rendered_loss(scratch, pose),
        }
    }

    /// `L(pose)` from the rasteriser.
    fn rendered_loss(&self, scratch: &mut Scratch, pose: &Pose) -> Result<f64> {
        let frags = scratch.raster.render_faces(self.mesh, &self.grid, pose)?;
        Ok(self.covered_loss(grid::covered(&frags, self.mesh.faces())))
    }

    /// `L` of a render given as the cells it covers, in raster order.
    fn covered_loss(&self, covered: impl Iterator<Item = grid::Covered>) -> f64 {
        self.covered_sum(
            covered
                .map(|c| (c.pixel, c.vertices.map(|v| self.similarity.get(c.pixel as usize, v as usize)), c.weights)),
        )
    }

    /// `L` from each covered cell's index, its face's similarities and weights, in raster
    /// order: the one summation of [`Problem::loss`]'s rasteriser path and
    /// [`GridRenders::losses`], so the two agree bit for bit.
    fn covered_sum(&self, covered: impl Iterator<Item = (u32, [f32; 3], [f32; 3])>) -> f64 {
        let mut sum = 0.0f64;
        for (pixel, s, w) in covered {
            let p = pixel as usize;
            let obj = w[0] * s[0] + w[1] * s[1] + w[2] * s[2];
            sum += f64::from(obj.max(self.clutter[p]) - self.clutter_pos[p]);
        }
        1.0 - (self.base + sum) / self.pixels as f64
    }

    /// `L(pose)` and `∂L/∂(a, e, θ, log d)`. The face covering each pixel is piecewise constant
    /// in the pose, so the gradient is that of the loss with the z-buffer's assignment (and the
    /// set of pixels where `obj > clu`) held fixed: it flows through the perspective-correct
    /// barycentrics into the projected vertex positions and depths, and from them through the
    /// projection's Jacobian. It has no term for pixels entering or leaving the silhouette, as
    /// with NeMo's hard rasteriser: over steps that move the silhouette across pixel centres,
    /// the loss's own slope can differ from it.
    pub fn loss_and_gradient(&self, scratch: &mut Scratch, pose: &Pose) -> Result<(f64, [f64; 4])> {
        gradient::loss_and_gradient(self, scratch, pose)
    }
}

/// A pose and its loss.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoredPose {
    pub pose: Pose,
    pub loss: f64,
}

/// One refined hypothesis: where it started (a grid pose) and where it ended.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hypothesis {
    pub pose: Pose,
    pub loss: f64,
    pub init: Pose,
    pub init_loss: f64,
    /// Loss evaluations the refinement spent.
    pub evaluations: usize,
}

/// The solver's answer: the lowest-loss hypothesis, its score `1 − L`, and every hypothesis in
/// order of loss (best first).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub pose: Pose,
    pub score: f64,
    pub hypotheses: Vec<Hypothesis>,
}

impl Estimate {
    /// How far the answer's loss leads that of the best hypothesis ending more than
    /// `separation` (radians) from it; `None` when every hypothesis ends within it. A small gap
    /// is an ambiguous image (both poses explain it almost equally well).
    pub fn runner_up_gap(&self, separation: f64) -> Option<f64> {
        let (best, rest) = self.hypotheses.split_first()?;
        let r = best.pose.rotation();
        rest.iter().find(|h| rotation_error(&h.pose.rotation(), &r) > separation).map(|h| h.loss - best.loss)
    }
}

/// The grid poses, each at the distance where the mesh fills `config.fill` of the crop.
pub fn grid_poses(mesh: &Mesh, crop: &Camera, config: &SolverConfig) -> Result<Vec<Pose>> {
    config.validate()?;
    config
        .grid_angles()
        .into_par_iter()
        .map(|[a, e, t]| Ok(Pose::new(a, e, t, fit_distance(mesh.vertices(), [a, e, t], crop, config.fill)?)))
        .collect()
}

/// Multi-pose initialisation (METHOD.md §6.4–5): scores every grid pose at its own fit distance
/// (in parallel, one rasteriser per thread) and keeps the `k` best poses that are mutually at
/// least `min_separation` apart (greedy in loss order). Returns them best first; fewer than `k`
/// when the grid has no more such poses.
pub fn multi_pose_init(problem: &Problem, config: &SolverConfig) -> Result<Vec<ScoredPose>> {
    let scored = grid_losses(problem, config)?;
    Ok(select_distant(&scored, config.hypotheses, config.min_separation))
}

/// Every grid pose (in [`SolverConfig::grid_angles`] order, 144 by default) at its own fit
/// distance, with its loss: what [`multi_pose_init`] selects from. Scored in parallel, one
/// rasteriser per thread.
pub fn grid_losses(problem: &Problem, config: &SolverConfig) -> Result<Vec<ScoredPose>> {
    config.validate()?;
    config
        .grid_angles()
        .into_par_iter()
        .map_init(Scratch::default, |scratch, [a, e, t]| {
            let distance = fit_distance(problem.mesh.vertices(), [a, e, t], &problem.crop, config.fill)?;
            let pose = Pose::new(a, e, t, distance);
            Ok(ScoredPose { pose, loss: problem.rendered_loss(scratch, &pose)? })
        })
        .collect()
}

/// Greedy in loss order: keep a pose when it is at least `min_separation` (geodesic) from every
/// pose already kept, until `k` are kept. Ties keep the earlier pose.
pub fn select_distant(scored: &[ScoredPose], k: usize, min_separation: f64) -> Vec<ScoredPose> {
    let mut order: Vec<usize> = (0..scored.len()).collect();
    order.sort_by(|&i, &j| scored[i].loss.total_cmp(&scored[j].loss).then(i.cmp(&j)));
    let mut kept: Vec<(ScoredPose, nalgebra::Matrix3<f64>)> = Vec::with_capacity(k);
    for i in order {
        if kept.len() == k {
            break;
        }
        let r = scored[i].pose.rotation();
        if kept.iter().all(|(_, q)| rotation_error(q, &r) >= min_separation) {
            kept.push((scored[i], r));
        }
    }
    kept.into_iter().map(|(s, _)| s).collect()
}

/// Render and compare (METHOD.md §6) on a prepared image: [`multi_pose_init`], then each of the
/// `k` initial poses refined by `config.optimizer` (in parallel).
pub fn solve(problem: &Problem, config: &SolverConfig) -> Result<Estimate> {
    let grid = grid_losses(problem, config)?;
    solve_from_grid(problem, &grid, config)
}

/// [`solve`] from grid losses already computed by [`grid_losses`] (for callers that also need
/// the whole grid, such as the validation gate's score margin): selects the `k` best mutually
/// distant poses and refines each of them. Gives exactly [`solve`]'s estimate.
pub fn solve_from_grid(problem: &Problem, grid: &[ScoredPose], config: &SolverConfig) -> Result<Estimate> {
    config.validate()?;
    let inits = select_distant(grid, config.hypotheses, config.min_separation);
    let refined = optimise::refine_all(problem, &inits, &config.optimizer, &config.prune)?;
    let hypotheses: Vec<Hypothesis> = inits
        .iter()
        .zip(refined)
        .map(|(init, refined)| Hypothesis {
            pose: canonical(&refined.pose),
            loss: refined.loss,
            init: init.pose,
            init_loss: init.loss,
            evaluations: refined.evaluations,
        })
        .collect();
    Estimate::from_hypotheses(hypotheses)
}

impl Estimate {
    /// Ranks refined hypotheses by loss; the best one is the estimate.
    pub fn from_hypotheses(mut hypotheses: Vec<Hypothesis>) -> Result<Estimate> {
        hypotheses.sort_by(|a, b| a.loss.total_cmp(&b.loss));
        let best = hypotheses.first().ok_or_else(|| EngineError::InvalidInput("no grid pose to start from".into()))?;
        Ok(Estimate { pose: best.pose, score: 1.0 - best.loss, hypotheses })
    }
}

/// Render and compare (METHOD.md §6): the pose of `model` in the image whose features are
/// `features`, seen through the crop camera `crop` (`Camera::for_crop(H, W)`).
pub fn render_and_compare(
    model: &NeuralMeshView,
    features: &FeatureMap,
    crop: &Camera,
    config: &SolverConfig,
) -> Result<Estimate> {
    config.validate()?;
    let caster = if config.ray_cast { CuboidCaster::detect(model.mesh) } else { None };
    let problem = Problem::with_caster(model, features, crop, config.stride, caster)?;
    solve(&problem, config)
}

/// The same rotation and distance with azimuth in `[0, 2π)` and elevation, θ in `[−π, π)`.
pub fn canonical(p: &Pose) -> Pose {
    let wrap = |x: f64| (x + PI).rem_euclid(TAU) - PI;
    Pose::new(p.azimuth.rem_euclid(TAU), wrap(p.elevation), wrap(p.theta), p.distance)
}
