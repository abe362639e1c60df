//! Source training: visible vertices on the feature grid, and a contrastive step that learns.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::nn::OptimizerConfig;
use tch::{Device, Kind, Tensor, nn};
use udapose_engine::backbone::{Arch, Backbone};
use udapose_engine::mesh::TARGET_VERTICES;
use udapose_engine::train::{SourceTraining, TrainConfig, visible_vertices};
use udapose_engine::{Camera, Cuboid, Pose, Rasterizer};

fn cuboid() -> udapose_engine::Mesh {
    Cuboid::from_dimensions([0.434, 0.989, 0.279]).unwrap().mesh(TARGET_VERTICES)
}

#[test]
fn head_on_the_front_face_is_visible_in_its_cells() {
    let mesh = cuboid();
    let crop = Camera::for_crop(64, 160).unwrap();
    let vis = visible_vertices(&mut Rasterizer::new(), &mesh, &crop, 8, &Pose::new(0.0, 0.0, 0.0, 4.0)).unwrap();
    assert_eq!(vis.vertices.len(), 11 * 7 + 2 * 11 + 2 * 7);
    assert!(vis.vertices.iter().all(|&k| mesh.vertices()[k as usize][1] == mesh.vertices()[0][1].min(-0.4945)));
    let (w, h) = (20, 8);
    for (&k, &cell) in vis.vertices.iter().zip(&vis.cells) {
        let [col, row] = vis.projected[k as usize];
        assert_eq!(cell, (row / 8.0) as i64 * w + (col / 8.0) as i64, "vertex {k}");
    }
    assert!(!vis.empty_cells.is_empty() && vis.empty_cells.iter().all(|&c| c < w * h));
    assert!(vis.empty_cells.iter().all(|c| !vis.cells.contains(c)));
}

#[test]
fn training_steps_lower_the_contrastive_loss() {
    tch::manual_seed(0);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let vs = nn::VarStore::new(Device::Cpu);
    let backbone = Backbone::new(vs.root(), Arch::ResNet18, 128);
    let crop = Camera::for_crop(64, 160).unwrap();
    let mut training = SourceTraining::new(TrainConfig::default(), cuboid(), crop, 128, Device::Cpu);
    let poses: Vec<Pose> = (0..4).map(|i| Pose::new(0.4 + 1.5 * i as f64, 0.2, 0.05, 5.0)).collect();
    let images = Tensor::rand([4, 3, 64, 160], (Kind::Float, Device::Cpu));
    let mut opt = nn::Adam { wd: 1e-4, ..Default::default() }.build(&vs, 1e-3).unwrap();
    let mut losses = Vec::new();
    for _ in 0..15 {
        let features = backbone.forward_t(&images, true);
        let (loss, stats) = training.step(&features, &poses, &mut rng).unwrap();
        opt.backward_step(&loss);
        assert!(stats.visible > 100 && stats.loss.is_finite());
        losses.push(stats.contrastive);
    }
    assert!(losses[14] < 0.8 * losses[0], "contrastive loss {losses:?}");
    let norms = training.vertex_features.norm_scalaropt_dim(2, [1], false);
    let worst = f64::try_from((norms - 1.0).abs().max()).unwrap();
    assert!(worst < 1e-5, "C keeps unit rows: {worst}");
}

#[test]
fn mismatched_inputs_are_errors() {
    let crop = Camera::for_crop(64, 160).unwrap();
    let mut training = SourceTraining::new(TrainConfig::default(), cuboid(), crop, 16, Device::Cpu);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let f = Tensor::rand([2, 16, 8, 20], (Kind::Float, Device::Cpu));
    let pose = Pose::new(0.3, 0.2, 0.0, 5.0);
    assert!(training.step(&f, &[pose], &mut rng).is_err(), "one pose for two images");
    let wrong_grid = Tensor::rand([1, 16, 4, 10], (Kind::Float, Device::Cpu));
    assert!(training.step(&wrong_grid, &[pose], &mut rng).is_err());
    let wrong_dim = Tensor::rand([1, 8, 8, 20], (Kind::Float, Device::Cpu));
    assert!(training.step(&wrong_dim, &[pose], &mut rng).is_err());
    assert!(training.step(&f.narrow(0, 0, 1), &[pose], &mut rng).is_ok());
}
