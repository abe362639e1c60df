//! Fixtures shared by the engine's integration tests.
#![allow(dead_code)] // each test binary uses a different part

use std::path::{Path, PathBuf};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor, nn};
use udapose_engine::Cuboid;
use udapose_engine::backbone::{Arch, Backbone};
use udapose_engine::checkpoint::{self, Manifest, Model, NeuralMesh};
use udapose_engine::mesh::TARGET_VERTICES;

/// Uniform draws on the host from a ChaCha generator, as tensors. Not torch's global generator:
/// a test binary runs its tests on parallel threads, and any model load there (a fresh backbone
/// draws its initial weights) would interleave with another test's seeded draws.
pub struct Draws(ChaCha8Rng);

impl Draws {
    pub fn new(seed: u64) -> Draws {
        Draws(ChaCha8Rng::seed_from_u64(seed))
    }

    /// Uniform in `[-bound, bound)`.
    pub fn uniform(&mut self, shape: &[i64], bound: f64) -> Tensor {
        let n = shape.iter().product::<i64>() as usize;
        let values: Vec<f32> = (0..n).map(|_| self.0.random_range(-bound..bound) as f32).collect();
        Tensor::from_slice(&values).reshape(shape)
    }

    /// Uniform in `[0, 1)`, as `Tensor::rand`.
    pub fn rand(&mut self, shape: &[i64]) -> Tensor {
        (self.uniform(shape, 0.5) + 0.5).clamp(0.0, 1.0)
    }

    /// Every weight of `vs` with two dimensions or more (convolutions) redrawn, Kaiming-uniform
    /// for its fan-in; one-dimensional ones (BatchNorm, biases) are constants already.
    pub fn reinit(&mut self, vs: &nn::VarStore) {
        let mut variables: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
        variables.sort_by(|a, b| a.0.cmp(&b.0));
        tch::no_grad(|| {
            for (_, mut v) in variables.into_iter().filter(|(_, v)| v.dim() >= 2) {
                let shape = v.size();
                let fan_in = shape[1..].iter().product::<i64>() as f64;
                v.copy_(&self.uniform(&shape, (6.0 / fan_in).sqrt()));
            }
        });
    }
}

/// A small untrained car model (ResNet-18, 128-d features, unit vertex features) on `crop`,
/// the same for the same `seed` whatever else the process draws.
pub fn random_model(seed: i64, crop: [usize; 2], version: &str) -> Model {
    let mut draws = Draws::new(seed as u64);
    let cuboid = Cuboid::from_dimensions([0.434, 0.989, 0.279]).unwrap();
    let manifest = Manifest {
        format_version: checkpoint::FORMAT_VERSION,
        category: "car".into(),
        version: version.into(),
        vertices: cuboid.mesh(TARGET_VERTICES).vertices().len(),
        cuboid,
        backbone: Arch::ResNet18,
        input_normalization: None,
        feature_dim: 128,
        crop,
        clutter: 1,
        dtype: "f32".into(),
        training: serde_json::json!({"command": "test"}),
        metrics: serde_json::Value::Null,
        files: Default::default(),
        experts: Vec::new(),
        min_target_fired: None,
    };
    let vs = nn::VarStore::new(Device::Cpu);
    let backbone = Backbone::new(vs.root(), manifest.backbone, 128);
    draws.reinit(&vs);
    let r = manifest.vertices as i64;
    let mut unit = |rows: i64| {
        let t = draws.uniform(&[rows, 128], 1.0);
        &t / t.norm_scalaropt_dim(2, [1], true)
    };
    let neural_mesh = NeuralMesh {
        mesh: manifest.cuboid.mesh(TARGET_VERTICES),
        vertex_features: unit(r),
        clutter: unit(1),
        kappa: Tensor::full([r], 1.0 / 0.07, (Kind::Float, Device::Cpu)),
        tau: Tensor::full([r], 0.8, (Kind::Float, Device::Cpu)),
        r_bar: Tensor::full([r], 0.9, (Kind::Float, Device::Cpu)),
    };
    Model { manifest, vs, backbone, neural_mesh }
}

/// A scratch directory under cargo's per-target tmp dir, removed on drop (a failed test's too:
/// models are tens of MB, and every run would otherwise leave them behind).
pub struct Scratch(PathBuf);

impl Scratch {
    pub fn new(tag: &str) -> Scratch {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().subsec_nanos();
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("{tag}-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Scratch(dir)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
