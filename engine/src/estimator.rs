//! Image in, pose out: the backbone's features, then render-and-compare against the neural mesh.

use tch::{Kind, Tensor};

use crate::backbone::{Backbone, preprocess};
use crate::camera::Camera;
use crate::checkpoint::NeuralMesh;
use crate::error::{EngineError, Result};
use crate::solver::{Estimate, FeatureMap, MeshModel, SolverConfig, render_and_compare};

/// The neural mesh's tensors as the solver takes them (host `f32`, row-major).
pub struct SolverMesh {
    pub vertex_features: Vec<f32>,
    /// The clutter vectors the solver compares with (NeMo: the normalised bank mean, N = 1).
    pub clutter: Vec<f32>,
    pub dim: usize,
}

impl SolverMesh {
    pub fn new(vertex_features: &Tensor, clutter: &Tensor) -> Result<Self> {
        let dim = vertex_features.size().last().copied().unwrap_or(0) as usize;
        Ok(SolverMesh { vertex_features: to_vec(vertex_features)?, clutter: to_vec(clutter)?, dim })
    }

    pub fn from_neural_mesh(nm: &NeuralMesh) -> Result<Self> {
        SolverMesh::new(&nm.vertex_features, &nm.clutter)
    }
}

/// The normalised mean of a clutter bank (M×D) as one clutter vector (1×D).
pub fn clutter_mean(bank: &Tensor) -> Tensor {
    let mean = bank.mean_dim([0i64].as_slice(), true, Kind::Float);
    &mean / mean.norm().clamp_min(1e-12)
}

fn to_vec(t: &Tensor) -> Result<Vec<f32>> {
    let flat = t.to_kind(Kind::Float).to_device(tch::Device::Cpu).contiguous().view([-1]);
    Vec::<f32>::try_from(&flat).map_err(|e| EngineError::InvalidInput(format!("tensor to host: {e}")))
}

/// Features of a batch of images in [0, 1] (N×3×H×W) in eval mode, as host vectors D×h×w.
pub fn features(backbone: &Backbone, images: &Tensor) -> Result<Vec<(Vec<f32>, usize, usize)>> {
    let x = preprocess(images)?;
    let f = tch::no_grad(|| backbone.features(&x, false))?;
    let [n, _, h, w] = <[i64; 4]>::try_from(f.size()).map_err(|_| EngineError::InvalidInput("features".into()))?;
    (0..n).map(|i| Ok((to_vec(&f.get(i))?, h as usize, w as usize))).collect()
}

/// Solves the pose of one image's features.
pub fn estimate(
    mesh: &crate::mesh::Mesh,
    solver_mesh: &SolverMesh,
    features: &(Vec<f32>, usize, usize),
    crop: &Camera,
    config: &SolverConfig,
) -> Result<Estimate> {
    let model = MeshModel::new(mesh, &solver_mesh.vertex_features, &solver_mesh.clutter, solver_mesh.dim)?;
    let map = FeatureMap::new(&features.0, solver_mesh.dim, features.1, features.2)?;
    render_and_compare(&model, &map, crop, config)
}
