//! The reference render and compare (tch autograd, METHOD.md §6 "NeMo's reference solver") on
//! the synthetic problems of `solver::synthetic`: same loss and gradient direction as udapose's
//! fast form, same starting poses, and it recovers known poses.

use udapose_engine::solver::{AdamConfig, FeatureMap, Problem, Scratch, SolverConfig, multi_pose_init};
use udapose_engine::{Camera, EngineError, Pose, Rasterizer, rotation_error};
use udapose_testkit::reference::{self, ReferenceConfig, ReferenceProblem};
use udapose_testkit::synthetic::{
    ImageSettings, SplitMix64, SyntheticImage, SyntheticModel, render_features, source_pose,
};

const DIM: usize = 128;

fn model(seed: u64) -> SyntheticModel {
    SyntheticModel::car(DIM, 5.0, &mut SplitMix64::new(seed)).unwrap()
}

fn crop() -> Camera {
    Camera::for_crop(128, 320).unwrap()
}

fn random_image(model: &SyntheticModel, seed: u64) -> SyntheticImage {
    let mut rng = SplitMix64::new(seed);
    let pose = source_pose(&mut rng, &model.mesh, &crop()).unwrap();
    render_features(model, &crop(), 8, &pose, &ImageSettings::default(), &mut rng).unwrap()
}

fn problems<'a>(m: &'a SyntheticModel, img: &SyntheticImage) -> (Problem<'a>, ReferenceProblem<'a>) {
    let (model, map) = (m.model().unwrap(), img.feature_map().unwrap());
    (Problem::new(&model, &map, &crop(), 8).unwrap(), ReferenceProblem::new(&model, &map, &crop(), 8).unwrap())
}

fn perturbed(pose: &Pose, rng: &mut SplitMix64) -> Pose {
    Pose::new(
        pose.azimuth + rng.range(-0.3, 0.3),
        pose.elevation + rng.range(-0.2, 0.2),
        pose.theta + rng.range(-0.2, 0.2),
        pose.distance * rng.range(0.9, 1.1),
    )
}

#[test]
fn loss_matches_the_fast_form() {
    let m = model(1);
    let config = SolverConfig::default();
    let mut worst = 0.0f64;
    for seed in 0..3 {
        let img = random_image(&m, 10 + seed);
        let (fast, slow) = problems(&m, &img);
        let (mut scratch, mut raster) = (Scratch::default(), Rasterizer::new());
        let mut rng = SplitMix64::new(20 + seed);
        let mut poses = vec![img.pose, Pose::new(0.0, 0.0, 0.0, 1e4)];
        poses.extend((0..4).map(|_| perturbed(&img.pose, &mut rng)));
        poses.extend(multi_pose_init(&fast, &config).unwrap().iter().map(|s| s.pose));
        for pose in &poses {
            let want = fast.loss(&mut scratch, pose).unwrap();
            let got = slow.loss(&mut raster, pose).unwrap();
            let (with_grad, _) = slow.loss_and_gradient(&mut raster, pose).unwrap();
            assert!((got - want).abs() < 1e-4, "seed {seed}, {pose:?}: reference {got} vs udapose {want}");
            assert!((with_grad - got).abs() < 1e-6, "the autograd pass computes the same loss");
            worst = worst.max((got - want).abs());
        }
    }
    eprintln!("largest loss difference: {worst:.2e}");
}

#[test]
fn gradient_direction_agrees_with_the_analytic_gradient() {
    let m = model(2);
    let mut cosines = Vec::new();
    for seed in 0..6 {
        let img = random_image(&m, 100 + seed);
        let (fast, slow) = problems(&m, &img);
        let (mut scratch, mut raster) = (Scratch::default(), Rasterizer::new());
        let pose = perturbed(&img.pose, &mut SplitMix64::new(200 + seed));
        let (_, analytic) = fast.loss_and_gradient(&mut scratch, &pose).unwrap();
        let (_, autograd) = slow.loss_and_gradient(&mut raster, &pose).unwrap();
        let dot: f64 = (0..4).map(|i| analytic[i] * autograd[i]).sum();
        let norm = |g: &[f64; 4]| g.iter().map(|x| x * x).sum::<f64>().sqrt();
        let cosine = dot / (norm(&analytic) * norm(&autograd));
        assert!(norm(&analytic) > 1e-4, "a pose off the truth has a gradient");
        assert!(cosine > 0.99, "seed {seed}: cosine {cosine}, analytic {analytic:?}, autograd {autograd:?}");
        cosines.push(cosine);
    }
    eprintln!("cosines between the autograd and analytic gradients: {cosines:.6?}");
}

#[test]
fn recovers_synthetic_poses_from_the_same_inits() {
    let m = model(7);
    let config = SolverConfig::default();
    let reference_config = ReferenceConfig::default();
    assert_eq!(reference_config.adam, AdamConfig::method());
    let mut errors = Vec::new();
    for seed in 0..4 {
        let img = random_image(&m, 1000 + seed);
        let (model, map) = (m.model().unwrap(), img.feature_map().unwrap());
        let est = reference::render_and_compare(&model, &map, &crop(), &config, &reference_config).unwrap();
        let err = rotation_error(&est.pose.rotation(), &img.pose.rotation()).to_degrees();
        errors.push(err);

        let (fast, _) = problems(&m, &img);
        let inits = multi_pose_init(&fast, &config).unwrap();
        assert_eq!(est.hypotheses.len(), config.hypotheses);
        let mut started: Vec<Pose> = est.hypotheses.iter().map(|h| h.init).collect();
        let mut expected: Vec<Pose> = inits.iter().map(|s| s.pose).collect();
        let key = |p: &Pose| (p.azimuth, p.elevation, p.theta);
        started.sort_by(|a, b| key(a).partial_cmp(&key(b)).unwrap());
        expected.sort_by(|a, b| key(a).partial_cmp(&key(b)).unwrap());
        assert_eq!(started, expected, "the reference refines udapose's grid poses");
        assert!(est.hypotheses.windows(2).all(|w| w[0].loss <= w[1].loss), "best hypothesis first");
        assert_eq!(est.pose, est.hypotheses[0].pose);
        for h in &est.hypotheses {
            assert!(h.loss <= h.init_loss + 1e-4, "refinement never worsens the loss: {h:?}");
            assert_eq!(h.evaluations, AdamConfig::method().steps + 1);
        }
        // The returned loss is the loss at the returned pose.
        let at = fast.loss(&mut Scratch::default(), &est.pose).unwrap();
        assert!((at - est.hypotheses[0].loss).abs() < 1e-4);
        assert!(err < 5.0, "image {seed}: {err:.2}° ({:?} vs {:?})", est.pose, img.pose);
        if err < 5.0 {
            let rel = est.pose.distance / img.pose.distance;
            assert!((rel - 1.0).abs() < 0.05, "distance {} vs {}", est.pose.distance, img.pose.distance);
        }
    }
    eprintln!("reference rotation errors (°): {errors:.2?}");
}

#[test]
fn sequential_and_parallel_hypotheses_agree() {
    let m = model(3);
    let img = random_image(&m, 50);
    let (fast, slow) = problems(&m, &img);
    let config = SolverConfig::default();
    let inits = multi_pose_init(&fast, &config).unwrap();
    let short = AdamConfig { steps: 20, ..AdamConfig::method() };
    let run = |parallel| {
        reference::solve(&slow, &inits, &ReferenceConfig { adam: short, parallel_hypotheses: parallel }).unwrap()
    };
    assert_eq!(run(true), run(false));
}

#[test]
fn bad_inputs_are_typed_errors() {
    let m = model(4);
    let img = random_image(&m, 60);
    let model = m.model().unwrap();
    let map = img.feature_map().unwrap();
    let invalid = |r: Result<ReferenceProblem, EngineError>| matches!(r, Err(EngineError::InvalidInput(_)));
    // Features of a 16×40 grid against a 256×672 crop, and against another feature dimension.
    assert!(invalid(ReferenceProblem::new(&model, &map, &Camera::for_crop(256, 672).unwrap(), 8)));
    let other = vec![0.0f32; 64 * 16 * 40];
    let narrow = FeatureMap::new(&other, 64, 16, 40).unwrap();
    assert!(invalid(ReferenceProblem::new(&model, &narrow, &crop(), 8)));
    let slow = ReferenceProblem::new(&model, &map, &crop(), 8).unwrap();
    let bad = ReferenceConfig { adam: AdamConfig { lr: -1.0, ..AdamConfig::method() }, parallel_hypotheses: false };
    let inits = multi_pose_init(&problems(&m, &img).0, &SolverConfig::default()).unwrap();
    assert!(matches!(reference::solve(&slow, &inits, &bad), Err(EngineError::InvalidInput(_))));
    assert!(matches!(reference::solve(&slow, &[], &ReferenceConfig::default()), Err(EngineError::InvalidInput(_))));
    let nan = Pose::new(f64::NAN, 0.0, 0.0, 5.0);
    assert!(slow.loss(&mut Rasterizer::new(), &nan).is_err());
}
