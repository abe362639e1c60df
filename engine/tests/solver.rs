//! The render-and-compare solver on synthetic images whose pose is known, its building blocks
//! (fit distance, similarity, loss, gradient, multi-pose init) and its typed errors.

use udapose_engine::camera::fit_distance;
use udapose_engine::raster::NO_FACE;
use udapose_engine::solver::{
    AdamConfig, CuboidCaster, FeatureMap, GridRenders, NeuralMeshView, Optimizer, PatternSearchConfig, Problem, Prune,
    ScoredPose, Scratch, SolverConfig, grid_losses, grid_poses, multi_pose_init, render_and_compare, select_distant,
    solve,
};
use udapose_engine::{Camera, Cuboid, EngineError, Mesh, Pose, Rasterizer, View, rotation_error};
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

fn image(model: &SyntheticModel, pose: &Pose, seed: u64) -> SyntheticImage {
    render_features(model, &crop(), 8, pose, &ImageSettings::default(), &mut SplitMix64::new(seed)).unwrap()
}

fn random_image(model: &SyntheticModel, seed: u64) -> SyntheticImage {
    let mut rng = SplitMix64::new(seed);
    let pose = source_pose(&mut rng, &model.mesh, &crop()).unwrap();
    render_features(model, &crop(), 8, &pose, &ImageSettings::default(), &mut rng).unwrap()
}

fn problem<'a>(model: &'a SyntheticModel, img: &SyntheticImage) -> Problem<'a> {
    Problem::new(&model.model().unwrap(), &img.feature_map().unwrap(), &crop(), 8).unwrap()
}

fn invalid<T>(r: Result<T, EngineError>) -> bool {
    matches!(r, Err(EngineError::InvalidInput(_)))
}

fn extent(vertices: &[[f64; 3]], pose: &Pose, cam: &Camera) -> f64 {
    let view = View::new(cam, pose).unwrap();
    vertices.iter().fold(0.0f64, |m, &v| {
        let [col, row, _] = view.project(v);
        m.max(2.0 * (col - cam.principal[0]).abs() / cam.width as f64)
            .max(2.0 * (row - cam.principal[1]).abs() / cam.height as f64)
    })
}

#[test]
fn fit_distance_fills_the_crop_and_matches_bisection() {
    let m = model(1);
    let mut rng = SplitMix64::new(2);
    for (h, w) in [(128, 320), (256, 672), (200, 200)] {
        let cam = Camera::for_crop(h, w).unwrap();
        for _ in 0..50 {
            let angles = [rng.range(0.0, 6.3), rng.range(-1.4, 1.4), rng.range(-0.8, 0.8)];
            let fill = rng.range(0.3, 1.2);
            let d = fit_distance(m.mesh.vertices(), angles, &cam, fill).unwrap();
            let pose = Pose::new(angles[0], angles[1], angles[2], d);
            assert!((extent(m.mesh.vertices(), &pose, &cam) - fill).abs() < 1e-9, "{angles:?} fill {fill}");
            // The bisection on log-distance that the lab used before (60 halvings of [0.3, 1000]).
            let (mut lo, mut hi) = (0.3f64.ln(), 1000f64.ln());
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                let p = Pose::new(angles[0], angles[1], angles[2], mid.exp());
                if extent(m.mesh.vertices(), &p, &cam) > fill { lo = mid } else { hi = mid }
            }
            let reference = (0.5 * (lo + hi)).exp();
            assert!((d - reference).abs() <= 1e-12 * reference, "{d} vs bisection {reference}");
        }
    }
    // The detection-crop band: a car at fill 0.875 sits at 2.3–16 units.
    let d = fit_distance(m.mesh.vertices(), [0.0, 0.0, 0.0], &crop(), 0.875).unwrap();
    assert!(d > 2.0 && d < 16.0, "{d}");
    let v = m.mesh.vertices();
    for fill in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(matches!(fit_distance(v, [0.0; 3], &crop(), fill), Err(EngineError::InvalidInput(_))), "{fill}");
    }
    assert!(matches!(fit_distance(v, [f64::NAN, 0.0, 0.0], &crop(), 0.8), Err(EngineError::InvalidPose(_))));
    assert!(matches!(fit_distance(&[], [0.0; 3], &crop(), 0.8), Err(EngineError::InvalidMesh(_))));
    assert!(matches!(fit_distance(&[[0.0; 3]], [0.0; 3], &crop(), 0.8), Err(EngineError::InvalidInput(_))));
}

#[test]
fn similarity_clutter_map_and_loss_match_their_definitions() {
    let m = model(3);
    let img = random_image(&m, 4);
    let prob = problem(&m, &img);
    let (r, p) = (m.mesh.vertices().len(), img.height * img.width);
    let f = |d: usize, px: usize| img.features[d * p + px];
    let mut worst = 0.0f32;
    for px in (0..p).step_by(7) {
        for v in (0..r).step_by(13) {
            let dot: f32 = (0..DIM).map(|d| m.vertex_features[v * DIM + d] * f(d, px)).sum();
            worst = worst.max((dot - prob.similarity(px, v)).abs());
        }
        let clu: f32 = (0..DIM).map(|d| m.clutter[d] * f(d, px)).sum();
        assert!((clu - prob.clutter_map()[px]).abs() < 1e-5);
    }
    assert!(worst < 1e-5, "S off by {worst}");

    // L = 1 − (mean max(obj, clu) − mean clu), directly from a render.
    let grid = crop().at_stride(8).unwrap();
    let mut raster = Rasterizer::new();
    let mut scratch = Scratch::default();
    let mut rng = SplitMix64::new(5);
    for k in 0..20 {
        let pose = if k == 0 { img.pose } else { source_pose(&mut rng, &m.mesh, &crop()).unwrap() };
        let frags = raster.render_faces(&m.mesh, &grid, &pose).unwrap();
        let (mut total, mut clu_sum) = (0.0f64, 0.0f64);
        for px in 0..p {
            let clu = prob.clutter_map()[px] as f64;
            let obj = match frags.face[px] {
                NO_FACE => 0.0,
                face => {
                    let idx = m.mesh.faces()[face as usize];
                    let w = frags.barycentric[px];
                    (0..3)
                        .map(|k| {
                            let v = idx[k] as usize;
                            let mix: f32 = (0..DIM).map(|d| m.vertex_features[v * DIM + d] * f(d, px)).sum();
                            (w[k] * mix) as f64
                        })
                        .sum()
                }
            };
            total += obj.max(clu);
            clu_sum += clu;
        }
        let expected = 1.0 - (total - clu_sum) / p as f64;
        let loss = prob.loss(&mut scratch, &pose).unwrap();
        assert!((loss - expected).abs() < 1e-5, "pose {k}: {loss} vs {expected}");
        let (lg, _) = prob.loss_and_gradient(&mut scratch, &pose).unwrap();
        assert!((lg - loss).abs() < 1e-9);
    }
    // Nothing in view: L = 1 − mean max(0, clu) + mean clu, and score = 1 − L in [0, 1].
    let away = Pose::new(0.0, 0.0, 0.0, 1e4);
    let l = prob.loss(&mut scratch, &away).unwrap();
    let expected = 1.0 - prob.clutter_map().iter().map(|&c| (c.max(0.0) - c) as f64).sum::<f64>() / p as f64;
    assert!((l - expected).abs() < 1e-9);
    assert!(prob.loss(&mut scratch, &img.pose).unwrap() < l);
}

/// The loss with the z-buffer's face assignment and the active pixels (`obj > clu`) of `at`
/// held fixed, in f64: the function whose gradient [`Problem::loss_and_gradient`] returns.
fn frozen_loss(m: &SyntheticModel, prob: &Problem, at: &Pose, pose: &Pose) -> f64 {
    let grid = crop().at_stride(8).unwrap();
    let mut raster = Rasterizer::new();
    let frags = raster.render_faces(&m.mesh, &grid, at).unwrap();
    let view = View::new(&grid, pose).unwrap();
    let edge = |a: [f64; 3], b: [f64; 3], q: [f64; 2]| (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0]);
    let mut sum = 0.0;
    for (px, &face) in frags.face.iter().enumerate() {
        if face == NO_FACE {
            continue;
        }
        let idx = m.mesh.faces()[face as usize].map(|v| v as usize);
        let s = idx.map(|v| prob.similarity(px, v) as f64);
        let w0 = frags.barycentric[px];
        let clu = prob.clutter_map()[px] as f64;
        let obj0: f64 = (0..3).map(|k| w0[k] as f64 * s[k]).sum();
        if obj0 <= clu {
            continue;
        }
        let q = [(px % grid.width) as f64 + 0.5, (px / grid.width) as f64 + 0.5];
        let v = idx.map(|i| view.project(m.mesh.vertices()[i]));
        let e = [edge(v[1], v[2], q), edge(v[2], v[0], q), edge(v[0], v[1], q)];
        let h: Vec<f64> = (0..3).map(|k| e[k] / v[k][2]).collect();
        let obj = (0..3).map(|k| h[k] * s[k]).sum::<f64>() / h.iter().sum::<f64>();
        sum += obj - clu;
    }
    -sum / (grid.width * grid.height) as f64
}

#[test]
fn gradient_matches_finite_differences() {
    let m = model(6);
    for seed in 0..8 {
        let img = random_image(&m, 100 + seed);
        let prob = problem(&m, &img);
        let mut scratch = Scratch::default();
        let mut rng = SplitMix64::new(200 + seed);
        // Near the truth (where the gradient matters) and farther off.
        let pose = Pose::new(
            img.pose.azimuth + rng.range(-0.3, 0.3),
            img.pose.elevation + rng.range(-0.2, 0.2),
            img.pose.theta + rng.range(-0.2, 0.2),
            img.pose.distance * rng.range(0.9, 1.1),
        );
        let (_, g) = prob.loss_and_gradient(&mut scratch, &pose).unwrap();
        let x = [pose.azimuth, pose.elevation, pose.theta, pose.distance.ln()];
        let scale = g.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        assert!(scale > 1e-4, "a pose off the truth has a gradient");
        for i in 0..4 {
            let at = |s: f64| {
                let mut y = x;
                y[i] += s;
                frozen_loss(&m, &prob, &pose, &Pose::new(y[0], y[1], y[2], y[3].exp()))
            };
            let h = 1e-6;
            let fd = (at(h) - at(-h)) / (2.0 * h);
            assert!((fd - g[i]).abs() <= 1e-5 * scale, "seed {seed}, coordinate {i}: analytic {} vs {fd}", g[i]);
        }
    }
}

#[test]
fn recovers_source_poses() {
    let m = model(7);
    let config = SolverConfig::default();
    let mut rng = SplitMix64::new(8);
    let mut errors = Vec::new();
    for i in 0..30 {
        let pose = source_pose(&mut rng, &m.mesh, &crop()).unwrap();
        let img = image(&m, &pose, 1000 + i);
        let est = render_and_compare(&m.model().unwrap(), &img.feature_map().unwrap(), &crop(), &config).unwrap();
        let err = rotation_error(&est.pose.rotation(), &pose.rotation()).to_degrees();
        errors.push(err);

        assert_eq!(est.hypotheses.len(), 3);
        assert_eq!(est.pose, est.hypotheses[0].pose);
        assert!((est.score - (1.0 - est.hypotheses[0].loss)).abs() < 1e-12);
        assert!(est.hypotheses.windows(2).all(|w| w[0].loss <= w[1].loss), "best hypothesis first");
        for (a, h) in est.hypotheses.iter().enumerate() {
            assert!(h.loss <= h.init_loss, "refinement never worsens the loss");
            for b in &est.hypotheses[a + 1..] {
                let sep = rotation_error(&h.init.rotation(), &b.init.rotation());
                assert!(sep >= 45f64.to_radians() - 1e-12, "inits {:.1}° apart", sep.to_degrees());
            }
        }
        // Score: the fraction of pixels the object explains better than clutter, weighted.
        assert!(est.score > 0.1 && est.score < 0.9, "score {}", est.score);
        if err < 5.0 {
            let rel = est.pose.distance / pose.distance;
            assert!((rel - 1.0).abs() < 0.05, "distance {} vs {}", est.pose.distance, pose.distance);
        }
    }
    let good = errors.iter().filter(|&&e| e < 5.0).count();
    let mut sorted = errors.clone();
    sorted.sort_by(f64::total_cmp);
    eprintln!("rotation errors (°): median {:.2}, worst {:.2}; {good}/30 < 5°", sorted[15], sorted[29]);
    assert!(good >= 27, "{good}/30 under 5°: {errors:?}");
}

#[test]
fn truth_scores_better_than_every_grid_pose() {
    let m = model(9);
    let config = SolverConfig::default();
    let mut scratch = Scratch::default();
    for seed in 0..10 {
        let img = random_image(&m, 300 + seed);
        let prob = problem(&m, &img);
        let truth = prob.loss(&mut scratch, &img.pose).unwrap();
        let grid = grid_poses(&m.mesh, &crop(), &config).unwrap();
        assert_eq!(grid.len(), 144);
        for g in &grid {
            let l = prob.loss(&mut scratch, g).unwrap();
            assert!(truth <= l, "image {seed}: truth {truth} > grid pose {g:?} at {l}");
        }
        let est = solve(&prob, &config).unwrap();
        assert!(est.hypotheses[0].loss <= truth + 0.01, "solver {} vs truth {truth}", est.hypotheses[0].loss);
    }
}

#[test]
fn multi_pose_init_keeps_the_best_distant_grid_poses() {
    let m = model(10);
    let img = random_image(&m, 11);
    let prob = problem(&m, &img);
    let config = SolverConfig::default();
    let grid = grid_poses(&m.mesh, &crop(), &config).unwrap();
    for g in &grid {
        let e = extent(m.mesh.vertices(), g, &crop());
        assert!((e - 0.875).abs() < 1e-9, "grid pose at fill {e}");
    }
    let mut scratch = Scratch::default();
    let losses: Vec<f64> = grid.iter().map(|g| prob.loss(&mut scratch, g).unwrap()).collect();
    let best = losses.iter().copied().fold(f64::INFINITY, f64::min);
    for k in [1, 3, 5] {
        let init = multi_pose_init(&prob, &SolverConfig { hypotheses: k, ..config.clone() }).unwrap();
        assert_eq!(init.len(), k);
        assert_eq!(init[0].loss, best, "the grid's best pose comes first");
        assert!(init.windows(2).all(|w| w[0].loss <= w[1].loss));
        for (i, a) in init.iter().enumerate() {
            for b in &init[i + 1..] {
                assert!(rotation_error(&a.pose.rotation(), &b.pose.rotation()) >= 45f64.to_radians() - 1e-12);
            }
        }
    }
    // Greedy selection: ties keep the earlier pose; k beyond what the separation allows gives
    // fewer poses.
    let p = |a: f64, l: f64| ScoredPose { pose: Pose::new(a.to_radians(), 0.0, 0.0, 5.0), loss: l };
    let scored = [p(0.0, 0.5), p(10.0, 0.1), p(50.0, 0.2), p(100.0, 0.3), p(200.0, 0.1)];
    let kept: Vec<f64> =
        select_distant(&scored, 10, 45f64.to_radians()).iter().map(|s| s.pose.azimuth.to_degrees()).collect();
    // 50° is better than 100° but only 40° from the kept 10°.
    assert_eq!(kept.len(), 3, "{kept:?}");
    assert!((kept[0] - 10.0).abs() < 1e-9 && (kept[1] - 200.0).abs() < 1e-9 && (kept[2] - 100.0).abs() < 1e-9);
}

#[test]
fn every_optimiser_improves_on_the_grid() {
    let m = model(12);
    let img = random_image(&m, 13);
    let prob = problem(&m, &img);
    let grid_only = solve(&prob, &SolverConfig { optimizer: Optimizer::None, ..SolverConfig::default() }).unwrap();
    for h in &grid_only.hypotheses {
        assert_eq!(h.loss, h.init_loss);
        assert_eq!(h.evaluations, 0);
    }
    let method = Optimizer::Adam(AdamConfig::method());
    let search = Optimizer::PatternSearch(PatternSearchConfig::default());
    for optimizer in [Optimizer::default(), method, search] {
        let est = solve(&prob, &SolverConfig { optimizer: optimizer.clone(), ..SolverConfig::default() }).unwrap();
        assert!(est.hypotheses[0].loss < grid_only.hypotheses[0].loss, "{optimizer:?}");
        let err = rotation_error(&est.pose.rotation(), &img.pose.rotation()).to_degrees();
        assert!(err < 5.0, "{optimizer:?}: {err}°");
        assert!(est.hypotheses.iter().all(|h| h.evaluations > 0));
        assert!((0.0..std::f64::consts::TAU).contains(&est.pose.azimuth));
    }
}

/// Plateau stopping and pruning spend fewer evaluations than the fixed schedule and end at the
/// same pose; with neither, the schedule is the fixed one, step for step.
#[test]
fn early_stopping_and_pruning_save_evaluations_not_accuracy() {
    let m = model(16);
    let fixed = SolverConfig {
        optimizer: Optimizer::Adam(AdamConfig::fixed()),
        prune: Prune::default(),
        ..SolverConfig::default()
    };
    let plateau = AdamConfig { patience: 10, min_improvement: 1e-4, ..AdamConfig::fixed() };
    let early = SolverConfig { optimizer: Optimizer::Adam(plateau), ..fixed.clone() };
    let pruned = SolverConfig { prune: Prune { after: 20, margin: 0.02 }, ..early.clone() };
    let evaluations = |e: &udapose_engine::solver::Estimate| e.hypotheses.iter().map(|h| h.evaluations).sum::<usize>();
    for seed in 0..4 {
        let img = random_image(&m, 100 + seed);
        let prob = problem(&m, &img);
        let [f, e, p] = [&fixed, &early, &pruned].map(|c| solve(&prob, c).unwrap());
        // The fixed schedule: 150 steps and the final point per hypothesis.
        assert!(f.hypotheses.iter().all(|h| h.evaluations == 151), "{:?}", f.hypotheses);
        assert!(evaluations(&e) < evaluations(&f), "plateau {} vs fixed {}", evaluations(&e), evaluations(&f));
        assert!(evaluations(&p) <= evaluations(&e), "pruned {} vs plateau {}", evaluations(&p), evaluations(&e));
        for (name, est) in [("plateau", &e), ("pruned", &p)] {
            let err = rotation_error(&est.pose.rotation(), &img.pose.rotation()).to_degrees();
            assert!(err < 5.0, "{name}: {err}°");
            let apart = rotation_error(&est.pose.rotation(), &f.pose.rotation()).to_degrees();
            assert!(apart < 2.0, "{name}: {apart}° from the fixed schedule's pose");
            assert!(est.hypotheses[0].loss < f.hypotheses[0].loss + 2e-3, "{name}");
        }
    }
    // A margin nothing trails by prunes nothing: the same answer as without pruning.
    let img = random_image(&m, 100);
    let prob = problem(&m, &img);
    let wide = SolverConfig { prune: Prune { after: 20, margin: 10.0 }, ..early.clone() };
    assert_eq!(solve(&prob, &wide).unwrap(), solve(&prob, &early).unwrap());
    // A zero margin stops every hypothesis but the leader after 20 steps (plus its last point).
    let tight = SolverConfig { prune: Prune { after: 20, margin: 0.0 }, ..early.clone() };
    let t = solve(&prob, &tight).unwrap();
    assert_eq!(
        t.hypotheses.iter().filter(|h| h.evaluations == 21).count(),
        t.hypotheses.len() - 1,
        "{:?}",
        t.hypotheses
    );
}

#[test]
fn bad_inputs_are_typed_errors() {
    let m = model(14);
    let img = random_image(&m, 15);
    let (h, w) = (img.height, img.width);

    // Feature maps.
    assert!(invalid(FeatureMap::new(&img.features[1..], DIM, h, w)));
    assert!(invalid(FeatureMap::new(&img.features, 0, h, w)));
    assert!(matches!(FeatureMap::new(&[], DIM, 0, w), Err(EngineError::EmptyImage { .. })));
    assert!(matches!(FeatureMap::new(&[], DIM, h, 0), Err(EngineError::EmptyImage { .. })));
    let mut nan = img.features.clone();
    nan[77] = f32::NAN;
    assert!(invalid(FeatureMap::new(&nan, DIM, h, w)));
    nan[77] = f32::INFINITY;
    assert!(invalid(FeatureMap::new(&nan, DIM, h, w)));

    // Mesh models.
    let vf = &m.vertex_features;
    assert!(invalid(NeuralMeshView::new(&m.mesh, &vf[DIM..], &m.clutter, DIM)));
    assert!(invalid(NeuralMeshView::new(&m.mesh, vf, &[], DIM)));
    assert!(invalid(NeuralMeshView::new(&m.mesh, vf, &m.clutter[1..], DIM)));
    assert!(invalid(NeuralMeshView::new(&m.mesh, vf, &m.clutter, 0)));
    let mut bad_c = vf.clone();
    bad_c[5] = f32::NAN;
    assert!(invalid(NeuralMeshView::new(&m.mesh, &bad_c, &m.clutter, DIM)));
    let mut bad_b = m.clutter.clone();
    bad_b[0] = f32::NEG_INFINITY;
    assert!(invalid(NeuralMeshView::new(&m.mesh, vf, &bad_b, DIM)));
    let two = [m.clutter.clone(), m.clutter.clone()].concat();
    assert!(NeuralMeshView::new(&m.mesh, vf, &two, DIM).is_ok(), "N = 2 clutter vectors");

    // Features that do not fit the crop, the stride or the model.
    let model = m.model().unwrap();
    let fm = img.feature_map().unwrap();
    assert!(invalid(Problem::new(&model, &fm, &Camera::for_crop(256, 672).unwrap(), 8)));
    assert!(invalid(Problem::new(&model, &fm, &crop(), 4)));
    assert!(matches!(Problem::new(&model, &fm, &crop(), 0), Err(EngineError::InvalidCamera(_))));
    assert!(matches!(
        Problem::new(&model, &fm, &Camera::for_crop(4, 4).unwrap(), 8),
        Err(EngineError::EmptyImage { .. })
    ));
    let small = &img.features[..64 * h * w];
    let fm64 = FeatureMap::new(small, 64, h, w).unwrap();
    assert!(invalid(Problem::new(&model, &fm64, &crop(), 8)));

    // Solver settings.
    let run = |c: SolverConfig| render_and_compare(&model, &fm, &crop(), &c);
    let base = SolverConfig::default;
    assert!(invalid(run(SolverConfig { hypotheses: 0, ..base() })));
    assert!(invalid(run(SolverConfig { azimuths: vec![], ..base() })));
    assert!(invalid(run(SolverConfig { elevations: vec![], ..base() })));
    assert!(invalid(run(SolverConfig { thetas: vec![f64::NAN], ..base() })));
    assert!(invalid(run(SolverConfig { fill: 0.0, ..base() })));
    assert!(invalid(run(SolverConfig { fill: f64::NAN, ..base() })));
    assert!(invalid(run(SolverConfig { min_separation: -1.0, ..base() })));
    assert!(invalid(run(SolverConfig { stride: 0, ..base() })));
    let adam = |c: AdamConfig| SolverConfig { optimizer: Optimizer::Adam(c), ..base() };
    assert!(invalid(run(adam(AdamConfig { lr: -0.1, ..AdamConfig::default() }))));
    assert!(invalid(run(adam(AdamConfig { beta1: 1.0, ..AdamConfig::default() }))));
    assert!(invalid(run(adam(AdamConfig { decay_every: 0, ..AdamConfig::default() }))));
    assert!(invalid(run(adam(AdamConfig { min_improvement: -1e-3, ..AdamConfig::default() }))));
    assert!(invalid(run(SolverConfig { prune: Prune { after: 10, margin: f64::NAN }, ..base() })));
    let search = |c: PatternSearchConfig| SolverConfig { optimizer: Optimizer::PatternSearch(c), ..base() };
    assert!(invalid(run(search(PatternSearchConfig { shrink: 1.0, ..PatternSearchConfig::default() }))));
    assert!(invalid(run(search(PatternSearchConfig { tolerance: 0.0, ..PatternSearchConfig::default() }))));
    let mut scratch = Scratch::default();
    let prob = Problem::new(&model, &fm, &crop(), 8).unwrap();
    assert!(matches!(prob.loss(&mut scratch, &Pose::new(0.0, f64::NAN, 0.0, 5.0)), Err(EngineError::InvalidPose(_))));
    assert!(matches!(
        prob.loss_and_gradient(&mut scratch, &Pose::new(0.0, 0.0, 0.0, -5.0)),
        Err(EngineError::InvalidPose(_))
    ));

    // A one-pose grid with k = 3 gives one hypothesis.
    let one = SolverConfig { azimuths: vec![0.0], elevations: vec![0.0], thetas: vec![0.0], ..base() };
    assert_eq!(run(one).unwrap().hypotheses.len(), 1);
}

#[test]
fn grid_renders_give_the_per_image_grid_losses_bit_for_bit() {
    let m = model(12);
    let config = SolverConfig::default();
    let renders = GridRenders::new(&m.mesh, &crop(), &config).unwrap();
    for seed in [13, 14, 15] {
        let img = random_image(&m, seed);
        // Two problems: S computed entry by entry as the renders read it, and prefilled vertex
        // by vertex by the cached renders — the same bits either way.
        let rendered = grid_losses(&problem(&m, &img), &config).unwrap();
        let gathered = renders.losses(&problem(&m, &img)).unwrap();
        assert_eq!(rendered.len(), 144);
        for (r, g) in rendered.iter().zip(&gathered) {
            assert_eq!(r.pose, g.pose);
            assert_eq!(r.loss.to_bits(), g.loss.to_bits(), "pose {:?}", r.pose);
        }
    }
    // Renders of another grid or crop are refused, not used.
    let coarse = SolverConfig { azimuths: vec![0.0, 1.0], ..config.clone() };
    assert!(!renders.fits(&crop(), &coarse));
    assert!(renders.fits(&crop(), &SolverConfig { hypotheses: 1, ..config.clone() }));
    let other = GridRenders::new(&m.mesh, &Camera::for_crop(64, 160).unwrap(), &config).unwrap();
    let img = random_image(&m, 16);
    assert!(invalid(other.losses(&problem(&m, &img))));
}

#[test]
fn the_ray_caster_is_used_only_for_exact_cuboid_meshes() {
    for (dims, target) in [([0.43, 1.0, 0.28], 1000), ([1.0, 1.0, 1.0], 200), ([2.0, 0.5, 0.1], 60)] {
        let mesh = Cuboid::from_dimensions(dims).unwrap().mesh(target);
        assert!(CuboidCaster::detect(&mesh).is_some(), "{dims:?} / {target}");
    }
    let mesh = model(30).mesh;
    assert!(CuboidCaster::detect(&mesh).is_some());
    // Any other mesh is rasterised: a moved vertex, reordered faces, a non-box shape.
    let mut moved = mesh.vertices().to_vec();
    moved[7][2] += 1e-3;
    assert!(CuboidCaster::detect(&Mesh::new(moved, mesh.faces().to_vec()).unwrap()).is_none());
    let mut faces = mesh.faces().to_vec();
    faces.swap(0, 1);
    assert!(CuboidCaster::detect(&Mesh::new(mesh.vertices().to_vec(), faces).unwrap()).is_none());
    let tetra = Mesh::new(
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    )
    .unwrap();
    assert!(CuboidCaster::detect(&tetra).is_none());
}

#[test]
fn ray_casting_gives_the_rasterisers_loss_gradient_and_estimate() {
    let m = model(31);
    for seed in [32, 33, 34] {
        let img = random_image(&m, seed);
        let cast = problem(&m, &img);
        let raster = Problem::with_caster(&m.model().unwrap(), &img.feature_map().unwrap(), &crop(), 8, None).unwrap();
        assert!(cast.is_ray_cast() && !raster.is_ray_cast());
        let (mut sc, mut sr) = (Scratch::default(), Scratch::default());
        let mut rng = SplitMix64::new(seed + 100);
        for k in 0..40 {
            let base = if k == 0 { img.pose } else { source_pose(&mut rng, &m.mesh, &crop()).unwrap() };
            // From near the fit distance to well inside and outside it.
            let pose = Pose { distance: base.distance * rng.range(0.7, 1.5), ..base };
            let (lc, gc) = cast.loss_and_gradient(&mut sc, &pose).unwrap();
            let (lr, gr) = raster.loss_and_gradient(&mut sr, &pose).unwrap();
            assert!((lc - lr).abs() < 1e-6, "seed {seed}, pose {k}: loss {lc} cast vs {lr} rasterised");
            assert_eq!(cast.loss(&mut sc, &pose).unwrap().to_bits(), lc.to_bits());
            let scale = gr.iter().fold(1e-3f64, |m, g| m.max(g.abs()));
            for i in 0..4 {
                assert!(
                    (gc[i] - gr[i]).abs() < 1e-6 * scale,
                    "seed {seed}, pose {k}, coordinate {i}: {gc:?} vs {gr:?}"
                );
            }
        }
        // The whole solve: the same answer to well under a degree.
        let fast =
            render_and_compare(&m.model().unwrap(), &img.feature_map().unwrap(), &crop(), &SolverConfig::default())
                .unwrap();
        let slow_config = SolverConfig { ray_cast: false, ..SolverConfig::default() };
        let slow = render_and_compare(&m.model().unwrap(), &img.feature_map().unwrap(), &crop(), &slow_config).unwrap();
        let apart = rotation_error(&fast.pose.rotation(), &slow.pose.rotation()).to_degrees();
        assert!(apart < 0.5, "seed {seed}: the two solvers' answers are {apart}° apart");
    }
    // Configurations written before the switch existed ray cast.
    let mut json = serde_json::to_value(SolverConfig::default()).unwrap();
    json.as_object_mut().unwrap().remove("ray_cast");
    assert!(serde_json::from_value::<SolverConfig>(json).unwrap().ray_cast);
}
