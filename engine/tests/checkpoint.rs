//! Model directories: save → load round trip, and clear errors for every kind of bad directory.

use std::path::{Path, PathBuf};

use tch::{Device, Kind, Tensor, nn};
use udapose_engine::Cuboid;
use udapose_engine::backbone::{Arch, Backbone};
use udapose_engine::checkpoint::{self, BACKBONE_FILE, MANIFEST, MESH_FILE, Manifest, NeuralMesh};
use udapose_engine::error::{CheckpointError, EngineError};
use udapose_engine::mesh::TARGET_VERTICES;

mod support;
use support::Scratch;

fn manifest(dtype: &str) -> Manifest {
    let cuboid = Cuboid::from_dimensions([0.434, 0.989, 0.279]).unwrap();
    Manifest {
        format_version: checkpoint::FORMAT_VERSION,
        category: "car".into(),
        version: "test-1".into(),
        vertices: cuboid.mesh(TARGET_VERTICES).vertices().len(),
        cuboid,
        backbone: Arch::ResNet18,
        input_normalization: None,
        feature_dim: 128,
        crop: [64, 160],
        clutter: 1,
        dtype: dtype.into(),
        training: serde_json::json!({"command": "test"}),
        metrics: serde_json::Value::Null,
        files: Default::default(),
        experts: Vec::new(),
        min_target_fired: None,
    }
}

fn unit_rows(rows: i64, dim: i64) -> Tensor {
    let t = Tensor::randn([rows, dim], (Kind::Float, Device::Cpu));
    &t / t.norm_scalaropt_dim(2, [1], true)
}

/// A randomly initialised model saved into `<parent>/model`.
fn saved(parent: &Path, dtype: &str) -> (PathBuf, Manifest, nn::VarStore, Tensor) {
    tch::manual_seed(3);
    let m = manifest(dtype);
    let vs = nn::VarStore::new(Device::Cpu);
    let _backbone = Backbone::new(vs.root(), m.backbone, 128);
    let r = m.vertices as i64;
    let nm = NeuralMesh {
        mesh: m.cuboid.mesh(TARGET_VERTICES),
        vertex_features: unit_rows(r, 128),
        clutter: unit_rows(1, 128),
        kappa: Tensor::full([r], 1.0 / 0.07, (Kind::Float, Device::Cpu)),
        tau: Tensor::full([r], 0.8, (Kind::Float, Device::Cpu)),
        r_bar: Tensor::full([r], 0.9, (Kind::Float, Device::Cpu)),
    };
    let dir = parent.join("model");
    checkpoint::save(&dir, &m, &vs, &nm).unwrap();
    (dir, m, vs, nm.vertex_features)
}

fn features(model: &checkpoint::Model) -> Tensor {
    tch::manual_seed(9);
    let x = Tensor::rand([1, 3, 64, 160], (Kind::Float, Device::Cpu));
    tch::no_grad(|| model.backbone.forward_t(&x, false))
}

#[test]
fn f32_round_trip_is_exact() {
    let scratch = Scratch::new("ckpt-f32");
    let parent = scratch.path();
    let (dir, m, vs, c) = saved(parent, "f32");
    let model = checkpoint::load(&dir, Device::Cpu).unwrap();
    assert_eq!(model.manifest.category, m.category);
    assert_eq!(model.manifest.files.len(), 2, "sha256 of both weight files");
    let original: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    let loaded = model.vs.variables();
    for (name, t) in original {
        assert!(loaded[&name].equal(&t), "{name}");
    }
    assert!(model.neural_mesh.vertex_features.equal(&c));
    assert_eq!(model.neural_mesh.mesh.vertices().len(), 1054);
    assert_eq!(features(&model).size(), [1, 128, 8, 20]);
    let again = checkpoint::save(&dir, &m, &vs, &model.neural_mesh);
    assert!(again.is_err(), "an existing version is never overwritten");
}

#[test]
fn f16_storage_loads_as_f32_close_to_the_original() {
    let scratch = Scratch::new("ckpt-f16");
    let parent = scratch.path();
    let (dir, _, vs, c) = saved(parent, "f16");
    let size = |f: &str| std::fs::metadata(dir.join(f)).unwrap().len();
    let (f32_dir, ..) = saved(&parent.join("f32"), "f32");
    assert!(size(BACKBONE_FILE) * 10 < std::fs::metadata(f32_dir.join(BACKBONE_FILE)).unwrap().len() * 6);
    let model = checkpoint::load(&dir, Device::Cpu).unwrap();
    assert_eq!(model.neural_mesh.vertex_features.kind(), Kind::Float);
    let diff = f64::try_from((&model.neural_mesh.vertex_features - &c).abs().max()).unwrap();
    assert!(diff < 1e-3, "f16 rounding only: {diff}");
    let w = &vs.variables()["conv1.weight"];
    let diff = f64::try_from((&model.vs.variables()["conv1.weight"] - w).abs().max()).unwrap();
    assert!(diff < 1e-3);
}

fn load_err(dir: &Path) -> EngineError {
    match checkpoint::load(dir, Device::Cpu) {
        Ok(_) => panic!("{} loaded", dir.display()),
        Err(e) => e,
    }
}

#[test]
fn bad_directories_give_clear_errors() {
    let scratch = Scratch::new("ckpt-bad");
    let parent = scratch.path();
    let (dir, ..) = saved(parent, "f32");
    let copy = |name: &str| {
        let to = parent.join(name);
        std::fs::create_dir_all(&to).unwrap();
        for f in [MANIFEST, BACKBONE_FILE, MESH_FILE] {
            std::fs::copy(dir.join(f), to.join(f)).unwrap();
        }
        to
    };

    let missing = copy("missing");
    std::fs::remove_file(missing.join(MESH_FILE)).unwrap();
    assert!(matches!(load_err(&missing), EngineError::Checkpoint(CheckpointError::NotFound { .. })));
    assert!(matches!(
        load_err(&parent.join("nothing-here")),
        EngineError::Checkpoint(CheckpointError::NotFound { .. })
    ));

    let truncated = copy("truncated");
    let bytes = std::fs::read(truncated.join(BACKBONE_FILE)).unwrap();
    std::fs::write(truncated.join(BACKBONE_FILE), &bytes[..bytes.len() / 2]).unwrap();
    assert!(load_err(&truncated).to_string().contains("sha256"), "truncation is caught by the checksum");

    let rewrite_manifest = |name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let d = copy(name);
        let mut v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d.join(MANIFEST)).unwrap()).unwrap();
        edit(&mut v);
        std::fs::write(d.join(MANIFEST), serde_json::to_string(&v).unwrap()).unwrap();
        d
    };
    let version = rewrite_manifest("version", &|v| v["format_version"] = 99.into());
    assert!(load_err(&version).to_string().contains("format version 99"));
    let arch = rewrite_manifest("arch", &|v| v["backbone"] = "resnet34".into());
    assert!(matches!(load_err(&arch), EngineError::Checkpoint(CheckpointError::MissingKeys { .. })));
    let dim = rewrite_manifest("dim", &|v| v["feature_dim"] = 64.into());
    assert!(matches!(load_err(&dim), EngineError::Checkpoint(CheckpointError::Shape { .. })));
    let vertices = rewrite_manifest("vertices", &|v| v["vertices"] = 1000.into());
    assert!(load_err(&vertices).to_string().contains("1054 vertices"));
    let garbage = copy("garbage");
    std::fs::write(garbage.join(MANIFEST), "{not json").unwrap();
    assert!(load_err(&garbage).to_string().contains(MANIFEST));

    // A consistent directory whose mesh file has a wrong shape: re-hashed so only the shape is wrong.
    let shape = copy("shape");
    let r = 1054;
    let bad = vec![
        ("vertex_features".to_string(), unit_rows(r, 64)),
        ("clutter".to_string(), unit_rows(1, 128)),
        ("kappa".to_string(), Tensor::ones([r], (Kind::Float, Device::Cpu))),
        ("tau".to_string(), Tensor::ones([r], (Kind::Float, Device::Cpu))),
        ("r_bar".to_string(), Tensor::ones([r], (Kind::Float, Device::Cpu))),
    ];
    Tensor::write_safetensors(&bad, shape.join(MESH_FILE)).unwrap();
    let sha = checkpoint::sha256_file(&shape.join(MESH_FILE)).unwrap();
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(shape.join(MANIFEST)).unwrap()).unwrap();
    v["files"][MESH_FILE] = sha.into();
    std::fs::write(shape.join(MANIFEST), serde_json::to_string(&v).unwrap()).unwrap();
    match load_err(&shape) {
        EngineError::Checkpoint(CheckpointError::Shape { key, .. }) => assert_eq!(key, "vertex_features"),
        e => panic!("{e}"),
    }
}
