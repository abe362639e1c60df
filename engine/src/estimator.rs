//! Image in, pose out: the backbone's [`Features`], then render-and-compare against the neural
//! mesh ([`PoseSolver`]), then the answer in image coordinates ([`PoseEstimate`]). Every caller
//! (the service's workers, evaluation, the gate, adaptation, training's validation, the
//! benches) goes through this module, so the sequence is written once.

use tch::{Kind, Tensor};

use crate::backbone::{Backbone, preprocess};
use crate::camera::{Camera, Pose};
use crate::checkpoint::{Model, NeuralMesh};
use crate::error::{EngineError, Result};
use crate::input::{Crop, CropBox};
use crate::mesh::{Cuboid, Mesh};
use crate::solver::{
    CuboidCaster, Estimate, FeatureMap, GridRenders, NeuralMeshView, Problem, ScoredPose, SolverConfig, grid_losses,
    solve_from_grid,
};

/// One image's backbone features: `dim × height × width`, row-major, on the host.
#[derive(Clone, Debug, PartialEq)]
pub struct Features {
    pub data: Vec<f32>,
    pub dim: usize,
    pub height: usize,
    pub width: usize,
}

impl Features {
    /// The features as the solver reads them (checks the sizes agree).
    pub fn map(&self) -> Result<FeatureMap<'_>> {
        FeatureMap::new(&self.data, self.dim, self.height, self.width)
    }
}

/// Features of a batch of images in [0, 1] (N×3×H×W, on the backbone's device) in eval mode.
pub fn features(backbone: &Backbone, images: &Tensor) -> Result<Vec<Features>> {
    let x = preprocess(images)?;
    let f = tch::no_grad(|| backbone.features(&x, false))?;
    let [n, dim, h, w] = <[i64; 4]>::try_from(f.size()).map_err(|_| EngineError::InvalidInput("features".into()))?;
    (0..n)
        .map(|i| Ok(Features { data: to_host(&f.get(i))?, dim: dim as usize, height: h as usize, width: w as usize }))
        .collect()
}

/// The solver's side of a neural mesh: its mesh, vertex features and clutter on the host, the
/// crop camera and the solver's settings. Host data only, so it is `Sync` and crosses into
/// rayon's threads (tch tensors do not).
#[derive(Clone, Debug)]
pub struct PoseSolver {
    mesh: Mesh,
    vertex_features: Vec<f32>,
    /// The clutter vectors compared with (NeMo: the normalised bank mean, N = 1).
    clutter: Vec<f32>,
    dim: usize,
    camera: Camera,
    pub config: SolverConfig,
    /// The grid's renders for `config` (image-independent, made once); used while they fit it.
    grid: GridRenders,
    /// The mesh's ray caster, detected once (`None`: not a cuboid mesh, rasterised).
    caster: Option<CuboidCaster>,
}

impl PoseSolver {
    /// From host vectors (`R × dim` vertex features, `N × dim` clutter); checks their sizes.
    pub fn from_host(
        mesh: Mesh,
        vertex_features: Vec<f32>,
        clutter: Vec<f32>,
        dim: usize,
        camera: Camera,
        config: SolverConfig,
    ) -> Result<Self> {
        config.validate()?;
        NeuralMeshView::new(&mesh, &vertex_features, &clutter, dim)?;
        let grid = GridRenders::new(&mesh, &camera, &config)?;
        let caster = CuboidCaster::detect(&mesh);
        Ok(PoseSolver { mesh, vertex_features, clutter, dim, camera, config, grid, caster })
    }

    /// From a mesh and its tensors (`R × dim`, `N × dim`), seen through the crop camera.
    pub fn new(
        mesh: &Mesh,
        vertex_features: &Tensor,
        clutter: &Tensor,
        camera: Camera,
        config: SolverConfig,
    ) -> Result<Self> {
        let dim = vertex_features.size().last().copied().unwrap_or(0) as usize;
        PoseSolver::from_host(mesh.clone(), to_host(vertex_features)?, to_host(clutter)?, dim, camera, config)
    }

    /// A model's neural mesh, for its crops of size `crop = [H, W]`.
    pub fn for_neural_mesh(nm: &NeuralMesh, crop: [usize; 2], config: SolverConfig) -> Result<Self> {
        PoseSolver::new(&nm.mesh, &nm.vertex_features, &nm.clutter, Camera::for_crop(crop[0], crop[1])?, config)
    }

    pub fn mesh(&self) -> &Mesh {
        &self.mesh
    }

    /// Bytes held on the host: mesh, features, clutter and the grid's renders.
    pub fn host_bytes(&self) -> usize {
        self.mesh.bytes()
            + std::mem::size_of_val(self.vertex_features.as_slice())
            + std::mem::size_of_val(self.clutter.as_slice())
            + self.grid.bytes()
    }

    pub fn vertex_features(&self) -> &[f32] {
        &self.vertex_features
    }

    pub fn dim(&self) -> usize {
        self.dim
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The solver's view of the mesh and its features (what the reference solver takes too).
    pub fn mesh_model(&self) -> Result<NeuralMeshView<'_>> {
        NeuralMeshView::new(&self.mesh, &self.vertex_features, &self.clutter, self.dim)
    }

    /// One image prepared for pose evaluation (`S = C·F` and the clutter map).
    pub fn problem<'a>(&'a self, features: &'a Features) -> Result<Problem<'a>> {
        // Checked by `from_host`.
        let model = NeuralMeshView::checked(&self.mesh, &self.vertex_features, &self.clutter, self.dim);
        Problem::with_caster(
            &model,
            &features.map()?,
            &self.camera,
            self.config.stride,
            self.caster.filter(|_| self.config.ray_cast),
        )
    }

    /// Render and compare (METHOD.md §6): the pose in the image whose features are `features`.
    pub fn solve(&self, features: &Features) -> Result<Estimate> {
        Ok(self.solve_with_grid(features)?.0)
    }

    /// [`PoseSolver::solve`] and the whole grid it started from (the gate's score margin
    /// reads it); the same estimate.
    pub fn solve_with_grid(&self, features: &Features) -> Result<(Estimate, Vec<ScoredPose>)> {
        if rayon::current_thread_index().is_none() {
            // Called from outside a pool, each parallel step of the solve (five) would hand its
            // work to a pool thread and sleep until woken: on one thread, 2.3-3.1 ms per solve
            // against 1.9-2.0 on the pool (100 source images, best of 8 passes, this change's
            // commit message). One hand-off for the whole solve instead.
            return rayon::scope(|_| self.solve_with_grid(features));
        }
        let problem = self.problem(features)?;
        let grid = self.grid_losses(&problem)?;
        Ok((solve_from_grid(&problem, &grid, &self.config)?, grid))
    }

    /// Every grid pose's loss on `problem`, from the renders made once when they fit the
    /// solver's camera and grid (they do unless the config was changed after construction).
    pub fn grid_losses(&self, problem: &Problem) -> Result<Vec<ScoredPose>> {
        if self.grid.fits(&self.camera, &self.config) {
            self.grid.losses(problem)
        } else {
            grid_losses(problem, &self.config)
        }
    }
}

/// The answer for one crop: the estimate, and what a user reads off it in image coordinates.
#[derive(Clone, Debug)]
pub struct PoseEstimate {
    pub estimate: Estimate,
    /// Azimuth, elevation and θ in degrees.
    pub degrees: [f64; 3],
    /// The object-to-camera rotation, row-major.
    pub rotation: [f64; 9],
    /// The image region the crop showed.
    pub crop_box: CropBox,
    /// The 8 corners of the category's cuboid in image coordinates ([`Crop::project_cuboid`]).
    pub cuboid: [[f64; 2]; 8],
}

impl PoseEstimate {
    pub fn pose(&self) -> &Pose {
        &self.estimate.pose
    }
}

/// The most crops of a CPU backbone pass whose features match any smaller pass's
/// ([`Estimator::features`]).
pub const MAX_INVARIANT_PASS: usize = 15;

/// Image in, pose out: a model (backbone + neural mesh) and its [`PoseSolver`].
pub struct Estimator {
    pub model: Model,
    solver: PoseSolver,
}

impl Estimator {
    pub fn new(model: Model, config: SolverConfig) -> Result<Self> {
        let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, model.manifest.crop, config)?;
        Ok(Estimator { model, solver })
    }

    pub fn solver(&self) -> &PoseSolver {
        &self.solver
    }

    /// What this estimator keeps in memory: the model's tensors and the solver's host data.
    pub fn resident_bytes(&self) -> usize {
        self.model.tensor_bytes() + self.solver.host_bytes()
    }

    /// Features of a batch of crops (N×3×H×W in [0, 1], any device) in one backbone pass.
    pub fn batch_features(&self, images: &Tensor) -> Result<Vec<Features>> {
        features(&self.model.backbone, &images.to_device(self.model.vs.device()))
    }

    /// Features of each crop, in backbone passes of at most `max_batch` crops (at most
    /// [`MAX_INVARIANT_PASS`] on the CPU), so that a crop's features, and its answer, never
    /// depend on what else was in the queue: measured by `bench/examples/batch_invariance.rs`
    /// (libtorch 2.13 on the CPU), a crop's features are bit-identical whatever shares its pass,
    /// its place in it and the pass's size, once the backbone runs a batch of one's small
    /// convolutions as a batch of two (`backbone::invariant`). The one exception left is ATen's
    /// rule for 1×1 convolutions with one torch thread: oneDNN only from 16 images on, hence the cap.
    pub fn features(&self, crops: &[&Crop], max_batch: usize) -> Result<Vec<Features>> {
        let cpu = self.model.vs.device() == tch::Device::Cpu;
        let pass = if cpu { max_batch.clamp(1, MAX_INVARIANT_PASS) } else { max_batch.max(1) };
        let mut out = Vec::with_capacity(crops.len());
        for chunk in crops.chunks(pass) {
            let rows: Vec<Tensor> = chunk.iter().map(|c| c.tensor()).collect();
            out.extend(self.batch_features(&Tensor::cat(&rows, 0))?);
        }
        Ok(out)
    }

    /// The answer for a crop whose features are `features`.
    pub fn estimate_features(&self, crop: &Crop, features: &Features) -> Result<PoseEstimate> {
        answer(&self.model.manifest.cuboid, crop, self.solver.solve(features)?)
    }

    /// The answers for crops whose features are `features`, with each solve's milliseconds. The
    /// crops are solved in parallel (rayon): a solve keeps one core busy once its hypotheses
    /// are pruned to one, so a batch's solves, or a request's boxes, would otherwise leave the
    /// other cores idle. Each answer is the same as [`Estimator::estimate_features`]'s.
    pub fn estimate_all(&self, crops: &[&Crop], features: &[Features]) -> Vec<Result<(PoseEstimate, f64)>> {
        self.estimate_all_in(None, crops, features)
    }

    /// [`Estimator::estimate_all`] with the solves on `pool` (the global pool where `None`).
    pub fn estimate_all_in(
        &self,
        pool: Option<&rayon::ThreadPool>,
        crops: &[&Crop],
        features: &[Features],
    ) -> Vec<Result<(PoseEstimate, f64)>> {
        use rayon::prelude::*;
        if crops.len() != features.len() {
            let e = || EngineError::InvalidInput(format!("{} crops but {} feature maps", crops.len(), features.len()));
            return crops.iter().map(|_| Err(e())).collect();
        }
        // The tch model is not Sync; the solver and the cuboid are all a solve needs.
        let (solver, cuboid) = (&self.solver, &self.model.manifest.cuboid);
        let solve = || {
            crops
                .par_iter()
                .zip(features)
                .map(|(crop, f)| {
                    let started = std::time::Instant::now();
                    let estimate = answer(cuboid, crop, solver.solve(f)?)?;
                    Ok((estimate, started.elapsed().as_secs_f64() * 1e3))
                })
                .collect()
        };
        match pool {
            Some(pool) => pool.install(solve),
            None => solve(),
        }
    }

    /// Image in, pose out, for one crop.
    pub fn estimate(&self, crop: &Crop) -> Result<PoseEstimate> {
        let features = self.features(&[crop], 1)?;
        self.estimate_features(crop, &features[0])
    }
}

/// A solver's estimate as the answer for `crop`: angles in degrees, the rotation matrix, the
/// cuboid's corners in image pixels.
fn answer(cuboid: &Cuboid, crop: &Crop, estimate: Estimate) -> Result<PoseEstimate> {
    let p = estimate.pose;
    let r = p.rotation();
    Ok(PoseEstimate {
        degrees: [p.azimuth.to_degrees(), p.elevation.to_degrees(), p.theta.to_degrees()],
        rotation: std::array::from_fn(|i| r[(i / 3, i % 3)]),
        crop_box: crop.crop_box,
        cuboid: crop.project_cuboid(cuboid, &p)?,
        estimate,
    })
}

/// The normalised mean of a clutter bank (M×D) as one clutter vector (1×D).
pub fn clutter_mean(bank: &Tensor) -> Tensor {
    let mean = bank.mean_dim([0i64].as_slice(), true, Kind::Float);
    &mean / mean.norm().clamp_min(1e-12)
}

pub(crate) fn to_host(t: &Tensor) -> Result<Vec<f32>> {
    let flat = t.to_kind(Kind::Float).to_device(tch::Device::Cpu).contiguous().view([-1]);
    Vec::<f32>::try_from(&flat).map_err(|e| EngineError::InvalidInput(format!("tensor to host: {e}")))
}
