//! Fixtures shared by the engine's integration tests.
#![allow(dead_code)] // each test binary uses a different part

use std::path::{Path, PathBuf};

use tch::{Device, Kind, Tensor, nn};
use udapose_engine::Cuboid;
use udapose_engine::backbone::{Arch, Backbone};
use udapose_engine::checkpoint::{self, Manifest, Model, NeuralMesh};
use udapose_engine::mesh::TARGET_VERTICES;

/// A small untrained car model (ResNet-18, 128-d features, unit vertex features) on `crop`,
/// reproducible from `seed`.
pub fn random_model(seed: i64, crop: [usize; 2], version: &str) -> Model {
    tch::manual_seed(seed);
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
    let r = manifest.vertices as i64;
    let unit = |rows: i64| {
        let t = Tensor::randn([rows, 128], (Kind::Float, Device::Cpu));
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
