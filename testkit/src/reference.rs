//! The straightforward render and compare (METHOD.md §6, "NeMo's reference solver"), written with
//! tch autograd ops: the baseline that udapose's fast form is timed against
//! (`udapose-bench solver`).
//!
//! It shares udapose's camera, grid, fit distances and `k` (it starts from [`multi_pose_init`]'s
//! poses, so both solvers refine the same hypotheses) and optimises `(a, e, θ, log d)` with
//! libtorch's Adam at METHOD's settings (lr 0.05, betas (0.4, 0.6), 300 steps, lr × 0.2 every
//! 100). What it does *not* share is the fast form: every step renders the feature map with
//! autograd ops and backpropagates through it, as NeMo does with PyTorch3D:
//!
//! 1. rotation `R = Rz(θ)·Rx(e − π/2)·Rz(−a)` and camera centre `C(a, e, d)` built from the
//!    parameter tensor; every vertex projected, `x_c = R(X − C)`, onto the stride-8 grid camera;
//! 2. the face covering each pixel from udapose's [`Rasterizer`] at the current pose values (the
//!    assignment is piecewise constant in the pose, as NeMo's hard rasteriser's), and the
//!    perspective-correct barycentrics of each covered pixel recomputed from the projected vertex
//!    tensors (edge functions, then `w_k ∝ l_k/z_k`), so that gradients flow into the pose;
//! 3. the rendered feature map `Σ_k w_k C[v_k]` (P × D, zero where no face covers the pixel),
//!    `obj = render·F` as a dot product per pixel (not through `S = C·F`), and
//!    `L = 1 − (mean_p max(obj, clu) − mean_p clu)` with `clu` computed once per image;
//! 4. `L.backward()`, an Adam step, and `log d` kept within a factor 4 of its start (as udapose).
//!
//! The pose parameters and the projection are `f64` (as udapose's rasteriser); the features are
//! `f32` (as the backbone gives them). Each refinement returns the lowest-loss pose it visited.

use rayon::prelude::*;
use tch::{Device, Kind, Tensor, nn, nn::OptimizerConfig};

use udapose_engine::camera::{Camera, Pose};
use udapose_engine::error::{EngineError, Result};
use udapose_engine::mesh::Mesh;
use udapose_engine::raster::{NO_FACE, Rasterizer};
use udapose_engine::solver::{
    AdamConfig, Estimate, FeatureMap, Hypothesis, NeuralMeshView, Problem, ScoredPose, SolverConfig, canonical,
    multi_pose_init,
};

/// How far (as a factor) the distance may move from its initial value (as udapose's refinement).
const MAX_DISTANCE_FACTOR: f64 = 4.0;

/// Settings of the reference refinement.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReferenceConfig {
    /// Adam's schedule: METHOD.md §6's 300 steps by default ([`AdamConfig::method`]).
    pub adam: AdamConfig,
    /// Refine the `k` hypotheses concurrently on rayon's pool (each with its own autograd graph
    /// and optimiser), as udapose's [`udapose_engine::solver::solve`] does; by default one after the other, as
    /// NeMo does: measured faster on the 2-core machine, whose ops are too small to share.
    pub parallel_hypotheses: bool,
}

impl Default for ReferenceConfig {
    fn default() -> Self {
        ReferenceConfig { adam: AdamConfig::method(), parallel_hypotheses: false }
    }
}

fn tch_err(e: tch::TchError) -> EngineError {
    EngineError::InvalidInput(format!("libtorch: {e}"))
}

/// One image prepared for the reference solver: the mesh and features as CPU tensors.
#[derive(Debug)]
pub struct ReferenceProblem<'a> {
    mesh: &'a Mesh,
    grid: Camera,
    /// Mesh vertices `X`, R × 3, f64.
    vertices: Tensor,
    /// Vertex features `C`, R × D, f32.
    vertex_features: Tensor,
    /// Features `F` pixel-major, P × D, f32.
    features: Tensor,
    /// `clu(p) = max_n β_n·F(p)`, P, f32.
    clutter: Tensor,
    /// Pixel centres `(col, row)` on the grid, P × 2, f64.
    centres: Tensor,
    pixels: usize,
}

impl<'a> ReferenceProblem<'a> {
    /// Prepares an image whose crop camera is `crop` (`Camera::for_crop(H, W)`); `features`
    /// must be on `crop.at_stride(stride)`'s grid (checked as [`Problem::new`] does).
    pub fn new(model: &NeuralMeshView<'a>, features: &FeatureMap, crop: &Camera, stride: usize) -> Result<Self> {
        let grid = crop.at_stride(stride)?;
        if (features.height(), features.width()) != (grid.height, grid.width) {
            return Err(EngineError::InvalidInput(format!(
                "features are {}×{} but a {}×{} crop at stride {stride} gives {}×{}",
                features.height(),
                features.width(),
                crop.height,
                crop.width,
                grid.height,
                grid.width
            )));
        }
        if features.dim() != model.dim() {
            return Err(EngineError::InvalidInput(format!(
                "feature dimension {} but the mesh model has {}",
                features.dim(),
                model.dim()
            )));
        }
        let (d, r, p) = (model.dim() as i64, model.mesh().vertices().len() as i64, (grid.width * grid.height) as i64);
        let flat: Vec<f64> = model.mesh().vertices().iter().flatten().copied().collect();
        let vertices = Tensor::from_slice(&flat).view([r, 3]);
        let vertex_features = Tensor::from_slice(model.vertex_features()).view([r, d]);
        let f = Tensor::from_slice(features.data()).view([d, p]);
        let clutter_bank = Tensor::from_slice(model.clutter()).view([-1, d]);
        let clutter = clutter_bank.matmul(&f).amax([0i64].as_slice(), false);
        let centres: Vec<f64> = (0..grid.height)
            .flat_map(|i| (0..grid.width).flat_map(move |j| [j as f64 + 0.5, i as f64 + 0.5]))
            .collect();
        Ok(ReferenceProblem {
            mesh: model.mesh(),
            grid,
            vertices,
            vertex_features,
            features: f.transpose(0, 1).contiguous(),
            clutter,
            centres: Tensor::from_slice(&centres).view([p, 2]),
            pixels: p as usize,
        })
    }

    /// A copy sharing the tensors' storage, for another thread (tensors are `Send`, not `Sync`).
    pub fn shallow_clone(&self) -> ReferenceProblem<'a> {
        ReferenceProblem {
            mesh: self.mesh,
            grid: self.grid,
            vertices: self.vertices.shallow_clone(),
            vertex_features: self.vertex_features.shallow_clone(),
            features: self.features.shallow_clone(),
            clutter: self.clutter.shallow_clone(),
            centres: self.centres.shallow_clone(),
            pixels: self.pixels,
        }
    }

    /// The feature grid's camera.
    pub fn grid_camera(&self) -> &Camera {
        &self.grid
    }

    /// The loss at `x = [a, e, θ, log d]` (a 4-vector of f64, usually requiring grad) as a 0-d
    /// f32 tensor in the autograd graph of `x`.
    pub fn forward(&self, raster: &mut Rasterizer, x: &Tensor) -> Result<Tensor> {
        let values = Vec::<f64>::try_from(&x.detach()).map_err(tch_err)?;
        let &[a0, e0, t0, ld0] = values.as_slice() else {
            return Err(EngineError::InvalidInput(format!("pose parameters {values:?} are not [a, e, θ, log d]")));
        };
        // The piecewise-constant part: which face covers which pixel at the current pose.
        let frags = raster.render_faces(self.mesh, &self.grid, &Pose::new(a0, e0, t0, ld0.exp()))?;
        let faces = self.mesh.faces();
        let (mut covered, mut corners) = (Vec::new(), Vec::new());
        for (p, &f) in frags.face.iter().enumerate() {
            if f != NO_FACE {
                covered.push(p as i64);
                corners.extend(faces[f as usize].map(i64::from));
            }
        }
        let covered = Tensor::from_slice(&covered);
        let corners = Tensor::from_slice(&corners);
        let n = covered.size()[0];

        // Projection with autograd ops.
        let (a, e, t, d) = (x.get(0), x.get(1), x.get(2), x.get(3).exp());
        let rotation = rot_z(&t).matmul(&rot_x(&(&e - std::f64::consts::FRAC_PI_2))).matmul(&rot_z(&(-&a)));
        let centre = Tensor::stack(&[e.cos() * a.sin(), -(e.cos() * a.cos()), e.sin()], 0) * &d;
        let camera = (&self.vertices - centre.unsqueeze(0)).matmul(&rotation.transpose(0, 1)); // R × 3
        let depth = -camera.select(1, 2);
        let m = self.grid.viewport;
        let col = (camera.select(1, 0) / &depth) * m + self.grid.principal[0];
        let row = (camera.select(1, 1) / &depth) * (-m) + self.grid.principal[1];

        // Perspective-correct barycentrics of every covered pixel, from the projected corners.
        let gather = |v: &Tensor| v.index_select(0, &corners).view([n, 3]);
        let (pc, pr, pz) = (gather(&col), gather(&row), gather(&depth));
        let q = self.centres.index_select(0, &covered);
        let (qc, qr) = (q.select(1, 0).unsqueeze(1), q.select(1, 1).unsqueeze(1));
        let next = |v: &Tensor, k: i64| v.roll([-k].as_slice(), [1i64].as_slice());
        // Edge function opposite corner k: edge(p_{k+1}, p_{k+2}, q).
        let (ac, ar, bc, br) = (next(&pc, 1), next(&pr, 1), next(&pc, 2), next(&pr, 2));
        let edges = (&bc - &ac) * (&qr - &ar) - (&br - &ar) * (&qc - &ac);
        let screen = &edges / edges.sum_dim_intlist([1i64].as_slice(), true, Kind::Double);
        let h = screen / pz;
        let weights = (&h / h.sum_dim_intlist([1i64].as_slice(), true, Kind::Double)).to_kind(Kind::Float);

        // The rendered feature map and the loss.
        let dim = self.vertex_features.size()[1];
        let mixed = (self.vertex_features.index_select(0, &corners).view([n, 3, dim]) * weights.unsqueeze(2))
            .sum_dim_intlist([1i64].as_slice(), false, Kind::Float);
        let render =
            Tensor::zeros([self.pixels as i64, dim], (Kind::Float, Device::Cpu)).index_add(0, &covered, &mixed);
        let obj = (render * &self.features).sum_dim_intlist([1i64].as_slice(), false, Kind::Float);
        let score = obj.maximum(&self.clutter).mean(Kind::Float) - self.clutter.mean(Kind::Float);
        Ok(1.0 - score)
    }

    /// `L(pose)`.
    pub fn loss(&self, raster: &mut Rasterizer, pose: &Pose) -> Result<f64> {
        let x = pose_tensor(pose);
        let loss = tch::no_grad(|| self.forward(raster, &x))?;
        f64::try_from(&loss).map_err(tch_err)
    }

    /// `L(pose)` and its autograd gradient with respect to `(a, e, θ, log d)`.
    pub fn loss_and_gradient(&self, raster: &mut Rasterizer, pose: &Pose) -> Result<(f64, [f64; 4])> {
        let x = pose_tensor(pose).set_requires_grad(true);
        let loss = self.forward(raster, &x)?;
        loss.backward();
        let g = Vec::<f64>::try_from(&x.grad()).map_err(tch_err)?;
        Ok((f64::try_from(&loss).map_err(tch_err)?, [g[0], g[1], g[2], g[3]]))
    }

    /// Refines one hypothesis with libtorch's Adam; returns the lowest-loss pose visited.
    pub fn refine(&self, init: &ScoredPose, config: &AdamConfig) -> Result<Hypothesis> {
        let p = init.pose;
        p.validate()?;
        let ld0 = p.distance.ln();
        let log_d = [ld0 - MAX_DISTANCE_FACTOR.ln(), ld0 + MAX_DISTANCE_FACTOR.ln()];
        let vs = nn::VarStore::new(Device::Cpu);
        let x = vs.root().var_copy("pose", &pose_tensor(&p));
        let adam = nn::Adam { beta1: config.beta1, beta2: config.beta2, wd: 0.0, eps: config.eps, amsgrad: false };
        let mut opt = adam.build(&vs, config.lr).map_err(tch_err)?;
        let mut raster = Rasterizer::new();
        let mut best = (p, f64::INFINITY);
        let mut evaluations = 0;
        for step in 0..config.steps {
            opt.set_lr(config.lr * config.decay.powi((step / config.decay_every) as i32));
            let at = tensor_pose(&x)?;
            let loss = self.forward(&mut raster, &x)?;
            evaluations += 1;
            let value = f64::try_from(&loss).map_err(tch_err)?;
            if value < best.1 {
                best = (at, value);
            }
            opt.zero_grad();
            loss.backward();
            opt.step();
            tch::no_grad(|| {
                let mut log_distance = x.get(3);
                let _ = log_distance.clamp_(log_d[0], log_d[1]);
            });
        }
        let last = tensor_pose(&x)?;
        let value = self.loss(&mut raster, &last)?;
        evaluations += 1;
        if value < best.1 {
            best = (last, value);
        }
        Ok(Hypothesis { pose: canonical(&best.0), loss: best.1, init: p, init_loss: init.loss, evaluations })
    }
}

fn pose_tensor(p: &Pose) -> Tensor {
    Tensor::from_slice(&[p.azimuth, p.elevation, p.theta, p.distance.ln()])
}

fn tensor_pose(x: &Tensor) -> Result<Pose> {
    let v = Vec::<f64>::try_from(&x.detach()).map_err(tch_err)?;
    let pose = Pose::new(v[0], v[1], v[2], v[3].exp());
    pose.validate()?;
    Ok(pose)
}

fn rot_z(t: &Tensor) -> Tensor {
    let (c, s) = (t.cos(), t.sin());
    let (zero, one) = (Tensor::from(0.0f64), Tensor::from(1.0f64));
    Tensor::stack(&[&c, &(-&s), &zero, &s, &c, &zero, &zero, &zero, &one], 0).view([3, 3])
}

fn rot_x(t: &Tensor) -> Tensor {
    let (c, s) = (t.cos(), t.sin());
    let (zero, one) = (Tensor::from(0.0f64), Tensor::from(1.0f64));
    Tensor::stack(&[&one, &zero, &zero, &zero, &c, &(-&s), &zero, &s, &c], 0).view([3, 3])
}

/// Refines each of `inits` (udapose's [`multi_pose_init`] output) with the reference solver and
/// returns the lowest-loss hypothesis, as [`udapose_engine::solver::solve`] does.
pub fn solve(problem: &ReferenceProblem, inits: &[ScoredPose], config: &ReferenceConfig) -> Result<Estimate> {
    udapose_engine::solver::Optimizer::Adam(config.adam).validate()?;
    let hypotheses: Vec<Hypothesis> = if config.parallel_hypotheses {
        let copies: Vec<(ReferenceProblem, ScoredPose)> = inits.iter().map(|i| (problem.shallow_clone(), *i)).collect();
        copies.into_par_iter().map(|(p, init)| p.refine(&init, &config.adam)).collect::<Result<_>>()?
    } else {
        inits.iter().map(|init| problem.refine(init, &config.adam)).collect::<Result<_>>()?
    };
    Estimate::from_hypotheses(hypotheses)
}

/// The reference render and compare: udapose's [`multi_pose_init`] (same grid, fit distances and
/// `k` as `solver`), then [`solve`] from those poses.
pub fn render_and_compare(
    model: &NeuralMeshView,
    features: &FeatureMap,
    crop: &Camera,
    solver: &SolverConfig,
    config: &ReferenceConfig,
) -> Result<Estimate> {
    solver.validate()?;
    let inits = multi_pose_init(&Problem::new(model, features, crop, solver.stride)?, solver)?;
    let problem = ReferenceProblem::new(model, features, crop, solver.stride)?;
    solve(&problem, &inits, config)
}
