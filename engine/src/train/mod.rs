//! Source training (NeMo, METHOD.md §5): a contrastive loss that pulls each visible vertex's
//! feature towards its own vertex feature and away from the other vertices (except its
//! neighbours) and from clutter, with `C` a momentum memory bank and a FIFO clutter bank.

pub mod schedule;
pub mod state;

pub use schedule::{LearningRates, Schedule};
pub use state::Progress;

use std::collections::BTreeMap;
use std::path::Path;

use rand::Rng;
use rand::seq::index::sample;
use tch::{Device, Kind, Tensor, nn};

use crate::backbone::{self, Backbone};
use crate::camera::{Camera, Pose};
use crate::checkpoint::NeuralMesh;
use crate::error::{EngineError, Result};
use crate::estimator::clutter_mean;
use crate::mesh::Mesh;
use crate::raster::Rasterizer;

/// Settings of source training; defaults are NeMo's unless noted.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainConfig {
    /// Softmax temperature T (κ = 1/T).
    pub temperature: f64,
    /// Clutter logits are down-weighted by this factor (`log` of it is added).
    pub weight_noise: f64,
    /// Vertices projected within this many pixels of a vertex (at a 256-px-high crop, scaled
    /// with the crop) are not its negatives.
    pub neighbour_px_at_256: f64,
    /// Clutter features sampled per image from cells holding no projected vertex.
    pub clutter_per_image: usize,
    /// Size of the FIFO clutter bank.
    pub clutter_bank: usize,
    /// Momentum μ of the vertex-feature memory bank.
    pub momentum: f64,
    /// Weight of the clutter regulariser `mean(x_noise · Cᵀ)`.
    pub clutter_weight: f64,
    /// Feature stride of the backbone.
    pub stride: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            temperature: 0.07,
            weight_noise: 0.005,
            neighbour_px_at_256: 48.0,
            clutter_per_image: 5,
            clutter_bank: 2560,
            momentum: 0.9,
            clutter_weight: 0.1,
            stride: 8,
        }
    }
}

/// Where one image's visible vertices fall on the feature grid.
#[derive(Clone, Debug, Default)]
pub struct VisibleVertices {
    /// Vertex indices.
    pub vertices: Vec<i64>,
    /// Flat feature-cell index `i·w + j` of each.
    pub cells: Vec<i64>,
    /// Cells that hold no projected vertex (clutter candidates).
    pub empty_cells: Vec<i64>,
    /// Every vertex's projection at crop resolution `[col, row]`, for the neighbour mask.
    pub projected: Vec<[f64; 2]>,
}

impl VisibleVertices {
    /// Drops the vertices whose projection lands on a pixel an occluder covers (`occluded`:
    /// crop pixels, row-major, `width` per row): a ground-truth pose places them, but their
    /// cells show the occluder, so training them as positives teaches the wrong feature.
    pub fn without_occluded(mut self, occluded: &[bool], width: usize) -> VisibleVertices {
        let covered = |v: i64| {
            let [x, y] = self.projected[v as usize];
            let (col, row) = (x.max(0.0) as usize, y.max(0.0) as usize);
            col < width && occluded.get(row * width + col).copied().unwrap_or(false)
        };
        let (vertices, cells) =
            self.vertices.iter().zip(&self.cells).filter(|&(&v, _)| !covered(v)).map(|(&v, &c)| (v, c)).unzip();
        (self.vertices, self.cells) = (vertices, cells);
        self
    }
}

/// Projects the mesh with a ground-truth pose and finds the visible vertices' feature cells.
pub fn visible_vertices(
    raster: &mut Rasterizer,
    mesh: &Mesh,
    crop: &Camera,
    stride: usize,
    pose: &Pose,
) -> Result<VisibleVertices> {
    let grid = crop.at_stride(stride)?;
    let frags = raster.render(mesh, &grid, pose)?;
    let s = stride as f64;
    let mut occupied = vec![false; grid.width * grid.height];
    let mut out = VisibleVertices::default();
    for (k, p) in frags.projected.iter().enumerate() {
        out.projected.push([p[0] * s, p[1] * s]);
        if p[2] > 0.0 && (0.0..grid.width as f64).contains(&p[0]) && (0.0..grid.height as f64).contains(&p[1]) {
            let cell = p[1] as usize * grid.width + p[0] as usize;
            occupied[cell] = true;
            if frags.visible[k] {
                out.vertices.push(k as i64);
                out.cells.push(cell as i64);
            }
        }
    }
    out.empty_cells = (0..occupied.len()).filter(|&c| !occupied[c]).map(|c| c as i64).collect();
    Ok(out)
}

/// Memory banks and settings of one training run; owns no backbone.
pub struct SourceTraining {
    pub config: TrainConfig,
    pub mesh: Mesh,
    pub crop: Camera,
    /// `C`, R×D, unit rows, updated by momentum (no gradient).
    pub vertex_features: Tensor,
    /// Clutter bank, M×D.
    pub clutter: Tensor,
    clutter_next: i64,
    clutter_filled: i64,
    raster: Rasterizer,
}

/// What one step measured.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    pub loss: f64,
    pub contrastive: f64,
    pub regulariser: f64,
    pub visible: usize,
}

impl SourceTraining {
    pub fn new(config: TrainConfig, mesh: Mesh, crop: Camera, dim: i64, device: Device) -> Self {
        let r = mesh.vertices().len() as i64;
        let unit = |t: Tensor| &t / t.norm_scalaropt_dim(2, [1], true);
        SourceTraining {
            vertex_features: unit(Tensor::randn([r, dim], (Kind::Float, device))),
            clutter: unit(Tensor::randn([config.clutter_bank as i64, dim], (Kind::Float, device))),
            clutter_next: 0,
            clutter_filled: 0,
            config,
            mesh,
            crop,
            raster: Rasterizer::new(),
        }
    }

    /// A training run that starts from a trained model's vertex features and clutter vectors
    /// (the clutter bank starts with them and fills with new clutter features).
    pub fn from_model(
        config: TrainConfig,
        mesh: Mesh,
        crop: Camera,
        vertex_features: &Tensor,
        clutter: &Tensor,
    ) -> Self {
        let (r, dim) = (vertex_features.size()[0], vertex_features.size()[1]);
        let device = vertex_features.device();
        let mut training = SourceTraining::new(config, mesh, crop, dim, device);
        debug_assert_eq!(r as usize, training.mesh.vertices().len());
        training.vertex_features = vertex_features.detach().copy();
        let n = clutter.size()[0].min(training.clutter.size()[0]);
        tch::no_grad(|| training.clutter.narrow(0, 0, n).copy_(&clutter.narrow(0, 0, n)));
        (training.clutter_next, training.clutter_filled) = (n % training.clutter.size()[0], n);
        training
    }

    /// The memory banks as named tensors, for a [`crate::snapshot`]: `C`, the clutter bank and
    /// where the bank's ring stands (`[next, filled]`), so that a resumed run draws the same
    /// negatives.
    pub(crate) fn banks(&self, prefix: &str) -> Vec<(String, Tensor)> {
        vec![
            (format!("{prefix}vertex_features"), self.vertex_features.shallow_clone()),
            (format!("{prefix}clutter"), self.clutter.shallow_clone()),
            (format!("{prefix}clutter_position"), Tensor::from_slice(&[self.clutter_next, self.clutter_filled])),
        ]
    }

    /// Restores [`SourceTraining::banks`] read from the snapshot `dir`. A snapshot from before
    /// the ring's position was saved counts the bank as full.
    pub(crate) fn restore_banks(&mut self, dir: &Path, tensors: &BTreeMap<String, Tensor>, prefix: &str) -> Result<()> {
        use crate::snapshot::{format_error, get};
        let clutter = get(dir, tensors, &format!("{prefix}clutter"))?;
        if clutter.size() != self.clutter.size() {
            return Err(format_error(
                dir,
                format!("a clutter bank of {:?}, not {:?}", clutter.size(), self.clutter.size()),
            ));
        }
        self.vertex_features = get(dir, tensors, &format!("{prefix}vertex_features"))?.copy();
        tch::no_grad(|| self.clutter.copy_(clutter));
        let m = self.clutter.size()[0];
        (self.clutter_next, self.clutter_filled) = match tensors.get(&format!("{prefix}clutter_position")) {
            Some(t) => {
                let p = Vec::<i64>::try_from(t).map_err(|e| format_error(dir, e))?;
                match p[..] {
                    [next, filled] if (0..m).contains(&next) && (0..=m).contains(&filled) => (next, filled),
                    _ => return Err(format_error(dir, format!("clutter bank position {p:?}"))),
                }
            }
            None => (0, m),
        };
        Ok(())
    }

    /// One optimiser step on a batch of images (`N×3×H×W` in [0, 1]) at their ground-truth
    /// poses: the backbone's features in training mode, the loss, its backward pass, and the
    /// memory banks' updates.
    pub fn backward_step(
        &mut self,
        backbone: &Backbone,
        opt: &mut nn::Optimizer,
        images: &Tensor,
        poses: &[Pose],
        rng: &mut impl Rng,
    ) -> Result<StepStats> {
        let features = backbone.forward_t(&backbone::preprocess(images)?, true);
        let (loss, stats) = self.step(&features, poses, rng)?;
        opt.backward_step(&loss);
        Ok(stats)
    }

    /// The neural mesh the run has learned: `C`, the clutter bank's mean, κ = 1/T, and the
    /// vertex statistics measured after training.
    pub fn neural_mesh(&self, tau: Tensor, r_bar: Tensor) -> NeuralMesh {
        let vertices = self.mesh.vertices().len() as i64;
        let device = self.vertex_features.device();
        NeuralMesh {
            mesh: self.mesh.clone(),
            vertex_features: self.vertex_features.shallow_clone(),
            clutter: clutter_mean(&self.clutter),
            kappa: Tensor::full([vertices], 1.0 / self.config.temperature, (Kind::Float, device)),
            tau,
            r_bar,
        }
    }

    /// The loss of a batch of unit-norm features `N×D×h×w` at their ground-truth poses (to be
    /// back-propagated by the caller), and the memory-bank updates, applied at once since
    /// they use detached features.
    pub fn step(&mut self, features: &Tensor, poses: &[Pose], rng: &mut impl Rng) -> Result<(Tensor, StepStats)> {
        let visible = poses
            .iter()
            .map(|p| visible_vertices(&mut self.raster, &self.mesh, &self.crop, self.config.stride, p))
            .collect::<Result<Vec<_>>>()?;
        self.step_visible(features, &visible, rng, true)
    }

    /// The loss of a batch whose positives are given per image (`vertices`/`cells`; the
    /// neighbour mask uses every vertex's projection). `update_vertices: false` keeps `C`
    /// frozen (3DUDA's backbone step); the clutter bank is always fed.
    pub fn step_visible(
        &mut self,
        features: &Tensor,
        visible: &[VisibleVertices],
        rng: &mut impl Rng,
        update_vertices: bool,
    ) -> Result<(Tensor, StepStats)> {
        let [n, d, h, w] = <[i64; 4]>::try_from(features.size())
            .map_err(|_| EngineError::InvalidInput(format!("features must be N×D×h×w, got {:?}", features.size())))?;
        if n as usize != visible.len() || d != self.vertex_features.size()[1] {
            return Err(EngineError::InvalidInput(format!(
                "{} images' targets for features {:?}",
                visible.len(),
                features.size()
            )));
        }
        let grid = self.crop.at_stride(self.config.stride)?;
        if (grid.height as i64, grid.width as i64) != (h, w) {
            return Err(EngineError::InvalidInput(format!(
                "feature grid {h}×{w}, camera grid {}×{}",
                grid.height, grid.width
            )));
        }
        let flat = features.permute([0, 2, 3, 1]).reshape([n * h * w, d]);
        let (mut rows, mut targets, mut masks, mut noise) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let radius = self.config.neighbour_px_at_256 * self.crop.height as f64 / 256.0;
        for (b, vis) in visible.iter().enumerate() {
            let base = b as i64 * h * w;
            rows.extend(vis.cells.iter().map(|c| base + c));
            targets.extend(vis.vertices.iter().copied());
            masks.push(neighbour_mask(vis, radius));
            let k = self.config.clutter_per_image.min(vis.empty_cells.len());
            noise.extend(sample(rng, vis.empty_cells.len(), k).into_iter().map(|i| base + vis.empty_cells[i]));
        }
        if rows.is_empty() {
            return Err(EngineError::InvalidInput("no vertex is visible in this batch".into()));
        }
        let device = features.device();
        let index = |v: &[i64]| Tensor::from_slice(v).to_device(device);
        let f = flat.index_select(0, &index(&rows)); // V×D
        let x_noise = flat.index_select(0, &index(&noise));
        // A copy: the banks change in place after this step, while autograd still needs them.
        let bank = self.clutter.narrow(0, 0, self.clutter_filled.max(1)).copy();
        let mask = Tensor::from_slice(&masks.concat())
            .reshape([rows.len() as i64, self.vertex_features.size()[0]])
            .to_device(device);

        let vertex_logits = f.matmul(&self.vertex_features.tr()) / self.config.temperature;
        let vertex_logits = vertex_logits.masked_fill(&mask, -1e4);
        let clutter_logits = f.matmul(&bank.tr()) / self.config.temperature + self.config.weight_noise.ln();
        let logits = Tensor::cat(&[vertex_logits, clutter_logits], 1);
        let contrastive = logits.cross_entropy_for_logits(&index(&targets));
        let regulariser = x_noise.matmul(&self.vertex_features.tr()).mean(Kind::Float);
        let loss = &contrastive + self.config.clutter_weight * &regulariser;

        tch::no_grad(|| self.update_banks(&f.detach(), &targets, n, &x_noise.detach(), update_vertices));
        let stats = StepStats {
            loss: f64::try_from(&loss).unwrap_or(f64::NAN),
            contrastive: f64::try_from(&contrastive).unwrap_or(f64::NAN),
            regulariser: f64::try_from(&regulariser).unwrap_or(f64::NAN),
            visible: rows.len(),
        };
        Ok((loss, stats))
    }

    /// `C_k ← normalise(μ C_k + (1 − μ)/B · Σ_b f_bk)` over the batch's visible occurrences
    /// (NeMo divides by the batch size, not the visible count); clutter into the FIFO.
    fn update_banks(&mut self, f: &Tensor, targets: &[i64], batch: i64, x_noise: &Tensor, update_vertices: bool) {
        self.push_clutter(x_noise);
        if !update_vertices {
            return;
        }
        let mu = self.config.momentum;
        let sums = Tensor::zeros_like(&self.vertex_features).index_add(
            0,
            &Tensor::from_slice(targets).to_device(f.device()),
            f,
        );
        let touched = sums.abs().sum_dim_intlist([1i64].as_slice(), true, Kind::Float).gt(0.0);
        let updated = &self.vertex_features * mu + sums * ((1.0 - mu) / batch as f64);
        let updated = &updated / updated.norm_scalaropt_dim(2, [1], true).clamp_min(1e-12);
        self.vertex_features = updated.where_self(&touched, &self.vertex_features);
    }

    fn push_clutter(&mut self, x_noise: &Tensor) {
        let m = self.clutter.size()[0];
        for i in 0..x_noise.size()[0] {
            self.clutter.get(self.clutter_next).copy_(&x_noise.get(i));
            self.clutter_next = (self.clutter_next + 1) % m;
            self.clutter_filled = (self.clutter_filled + 1).min(m);
        }
    }
}

/// Row per visible vertex, column per mesh vertex: true where the column vertex projects within
/// `radius` pixels of the row's (its own column excepted), i.e. is not a negative.
fn neighbour_mask(vis: &VisibleVertices, radius: f64) -> Vec<bool> {
    let r2 = radius * radius;
    let all = &vis.projected;
    vis.vertices
        .iter()
        .flat_map(|&k| {
            let p = all[k as usize];
            all.iter().enumerate().map(move |(j, q)| {
                let (dx, dy) = (p[0] - q[0], p[1] - q[1]);
                j as i64 != k && dx * dx + dy * dy < r2
            })
        })
        .collect()
}

/// Per-vertex statistics of the source features at ground-truth poses, stored with the model
/// for adaptation (METHOD.md §7): the `quantile` of each vertex's cosines to its feature (τ_r)
/// and the mean resultant length of its features (R̄_r).
pub struct VertexStatistics {
    cosines: Vec<Vec<f32>>,
    sums: Tensor,
    counts: Vec<usize>,
    raster: Rasterizer,
}

/// τ for a vertex never seen visible (METHOD.md §7's fallback, the paper's 0.8 as a cosine).
pub const FALLBACK_TAU: f64 = 0.8;

impl VertexStatistics {
    pub fn new(vertices: usize, dim: i64, device: Device) -> Self {
        VertexStatistics {
            cosines: vec![Vec::new(); vertices],
            sums: Tensor::zeros([vertices as i64, dim], (Kind::Float, device)),
            counts: vec![0; vertices],
            raster: Rasterizer::new(),
        }
    }

    /// Adds a batch of images (`N×3×H×W` in [0, 1]) at their ground-truth poses, the
    /// backbone in eval mode.
    pub fn add_images(
        &mut self,
        training: &SourceTraining,
        backbone: &Backbone,
        images: &Tensor,
        poses: &[Pose],
    ) -> Result<()> {
        let x = backbone::preprocess(images)?;
        let features = tch::no_grad(|| backbone.forward_t(&x, false));
        self.add(training, &features, poses)
    }

    /// Adds a batch of unit-norm features `N×D×h×w` at their ground-truth poses.
    pub fn add(&mut self, training: &SourceTraining, features: &Tensor, poses: &[Pose]) -> Result<()> {
        let [n, d, h, w] = <[i64; 4]>::try_from(features.size())
            .map_err(|_| EngineError::InvalidInput(format!("features must be N×D×h×w, got {:?}", features.size())))?;
        let flat = features.detach().permute([0, 2, 3, 1]).reshape([n * h * w, d]);
        let (mut rows, mut targets) = (Vec::new(), Vec::new());
        for (b, pose) in poses.iter().enumerate() {
            let vis = visible_vertices(&mut self.raster, &training.mesh, &training.crop, training.config.stride, pose)?;
            rows.extend(vis.cells.iter().map(|c| b as i64 * h * w + c));
            targets.extend(vis.vertices);
        }
        if rows.is_empty() {
            return Ok(());
        }
        let device = features.device();
        let f = flat.index_select(0, &Tensor::from_slice(&rows).to_device(device));
        let t = Tensor::from_slice(&targets).to_device(device);
        let cos =
            (&f * training.vertex_features.index_select(0, &t)).sum_dim_intlist([1i64].as_slice(), false, Kind::Float);
        let cos =
            Vec::<f32>::try_from(&cos.to_device(Device::Cpu)).map_err(|e| EngineError::InvalidInput(e.to_string()))?;
        for (&k, c) in targets.iter().zip(cos) {
            self.cosines[k as usize].push(c);
            self.counts[k as usize] += 1;
        }
        self.sums = self.sums.index_add(0, &t, &f);
        Ok(())
    }

    /// `(τ, R̄)`, each of length R.
    pub fn finish(mut self, quantile: f64) -> (Tensor, Tensor) {
        let tau: Vec<f32> = self
            .cosines
            .iter_mut()
            .map(|c| {
                if c.is_empty() {
                    return FALLBACK_TAU as f32;
                }
                c.sort_by(f32::total_cmp);
                c[((c.len() - 1) as f64 * quantile).round() as usize]
            })
            .collect();
        let counts: Vec<f32> = self.counts.iter().map(|&c| c.max(1) as f32).collect();
        let device = self.sums.device();
        let r_bar = self.sums.norm_scalaropt_dim(2, [1], false) / Tensor::from_slice(&counts).to_device(device);
        (Tensor::from_slice(&tau).to_device(device), r_bar)
    }
}
