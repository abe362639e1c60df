//! The validation gate: the mirror convention against the camera, each criterion's rule on
//! synthetic checks (a gate that is broken in one rule fails one of these), the held-out bucket,
//! and `measure` on a random model and, when `make test` provides it (`UDAPOSE_QUICK_MODEL`,
//! `UDAPOSE_QUICK_DATA`), on the quick model and real crops.

mod support;

use std::f64::consts::{PI, TAU};
use std::ops::ControlFlow;
use std::path::PathBuf;

use sha2::{Digest, Sha256};
use tch::{Device, Kind, Tensor};
use udapose_engine::adapt::{Event, Phase, RoundReport};
use udapose_engine::checkpoint::{self, Model};
use udapose_engine::error::EngineError;
use udapose_engine::gate::{
    self, Decision, GateConfig, GateStats, ImageCheck, decide, flip_consistent, guard, held_out, measure, mirror_crops,
    mirrored,
};
use udapose_engine::solver::{AdamConfig, Optimizer, SolverConfig};
use udapose_engine::{Camera, Pose, View};

// ---------------------------------------------------------------------------------------------
// The mirror convention

/// A left-right (x ↦ −x) symmetric point set: the cuboid's corners and a scatter of points,
/// each with its mirror.
fn symmetric_points() -> Vec<[f64; 3]> {
    let mut pts = Vec::new();
    for i in 0..40 {
        let t = i as f64;
        let p = [0.05 + 0.17 * (t * 0.37).sin().abs(), 0.5 * (t * 0.73).cos(), 0.14 * (t * 1.31).sin()];
        pts.push(p);
        pts.push([-p[0], p[1], p[2]]);
    }
    for sx in [-0.217, 0.217] {
        for sy in [-0.49, 0.5] {
            for sz in [-0.16, 0.118] {
                pts.push([sx, sy, sz]);
            }
        }
    }
    pts
}

/// Projecting a symmetric point set at `(a, e, θ)` and mirroring each pixel about the crop's
/// centre (`col ↦ W − col`) gives the projection at `(−a, e, −θ)` of the mirrored points, to
/// 1e-12 px: the convention the flip-consistency criterion relies on.
#[test]
fn mirrored_crop_shows_the_mirrored_pose() {
    let camera = Camera::for_crop(128, 320).unwrap();
    let w = camera.width as f64;
    let pts = symmetric_points();
    let mut worst: f64 = 0.0;
    for &(a, e, t, d) in &[
        (0.0, 0.0, 0.0, 5.0),
        (0.7, 0.3, 0.2, 6.0),
        (2.9, -0.4, -0.5, 4.0),
        (4.4, 1.0, 0.9, 9.0),
        (-1.3, 0.2, 3.0, 12.0),
    ] {
        let pose = Pose::new(a, e, t, d);
        let view = View::new(&camera, &pose).unwrap();
        let mirror_view = View::new(&camera, &mirrored(&pose)).unwrap();
        for p in &pts {
            let [col, row, depth] = view.project(*p);
            let [mcol, mrow, mdepth] = mirror_view.project([-p[0], p[1], p[2]]);
            worst = worst.max((w - col - mcol).abs()).max((row - mrow).abs()).max((depth - mdepth).abs());
        }
    }
    assert!(worst < 1e-12, "mirror convention off by {worst:e} px");
}

/// The *wrong* mirror conventions do not pass the same check (so the test above has teeth).
#[test]
fn other_mirror_conventions_fail() {
    let camera = Camera::for_crop(128, 320).unwrap();
    let pts = symmetric_points();
    let pose = Pose::new(0.7, 0.3, 0.2, 6.0);
    let view = View::new(&camera, &pose).unwrap();
    for wrong in
        [Pose::new(-0.7, 0.3, 0.2, 6.0), Pose::new(PI - 0.7, 0.3, -0.2, 6.0), Pose::new(0.7 + PI, 0.3, -0.2, 6.0)]
    {
        let mirror_view = View::new(&camera, &wrong).unwrap();
        let worst = pts
            .iter()
            .map(|p| {
                let [col, row, _] = view.project(*p);
                let [mcol, mrow, _] = mirror_view.project([-p[0], p[1], p[2]]);
                (320.0 - col - mcol).abs().max((row - mrow).abs())
            })
            .fold(0.0, f64::max);
        assert!(worst > 1.0, "{wrong:?} should not be the mirror (off by {worst})");
    }
}

/// `mirror_crops` maps pixel column j to W − 1 − j, i.e. continuous x to W − x about the centre.
#[test]
fn mirror_crops_flips_about_the_centre() {
    let x = Tensor::arange(2 * 3 * 2 * 5, (Kind::Float, Device::Cpu)).reshape([2, 3, 2, 5]);
    let m = mirror_crops(&x);
    for j in 0..5i64 {
        let a = x.get(1).get(2).get(1).double_value(&[j]);
        let b = m.get(1).get(2).get(1).double_value(&[4 - j]);
        assert_eq!(a, b);
    }
    assert!(mirror_crops(&m).equal(&x));
}

#[test]
fn flip_consistency_is_judged_against_the_mirrored_pose() {
    let p = Pose::new(0.6, 0.2, 0.1, 5.0);
    assert!(flip_consistent(&p, &Pose::new(-0.6, 0.2, -0.1, 5.0)));
    assert!(flip_consistent(&p, &Pose::new(TAU - 0.6 + 0.3, 0.2, -0.1, 7.0)));
    assert!(!flip_consistent(&p, &Pose::new(-0.6 + 0.6, 0.2, -0.1, 5.0)));
    // The same pose (not mirrored) is not consistent unless the pose is its own mirror.
    assert!(!flip_consistent(&p, &p));
    let frontal = Pose::new(0.0, 0.3, 0.0, 5.0);
    assert!(flip_consistent(&frontal, &frontal));
}

// ---------------------------------------------------------------------------------------------
// decide() on synthetic checks

/// Evenly spread azimuths (one per bin, cycling), the given margins and flip outcomes.
fn stats(margins: &[f64], flips: &[bool]) -> GateStats {
    assert_eq!(margins.len(), flips.len());
    GateStats {
        images: margins
            .iter()
            .zip(flips)
            .enumerate()
            .map(|(i, (&margin, &flip_consistent))| ImageCheck {
                azimuth: (30.0 * (i % 12) as f64).to_radians(),
                score: 0.3 + margin,
                margin,
                flip_consistent,
            })
            .collect(),
    }
}

fn with_azimuths(mut s: GateStats, azimuths_deg: &[f64]) -> GateStats {
    for (c, a) in s.images.iter_mut().zip(azimuths_deg) {
        c.azimuth = a.to_radians();
    }
    s
}

fn criterion<'a>(d: &'a Decision, name: &str) -> &'a gate::Criterion {
    d.criteria.iter().find(|c| c.name == name).unwrap_or_else(|| panic!("no criterion {name}"))
}

fn healthy(n: usize) -> GateStats {
    let margins: Vec<f64> = (0..n).map(|i| 0.02 + 0.002 * (i % 7) as f64).collect();
    let flips: Vec<bool> = (0..n).map(|i| i % 4 != 0).collect();
    stats(&margins, &flips)
}

#[test]
fn criteria_are_named_and_ordered() {
    let a = healthy(24);
    let d = decide(&a, &a, &GateConfig { margin_gain: 0.0, ..GateConfig::default() }).unwrap();
    let names: Vec<&str> = d.criteria.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["flip_consistency", "score_margin", "pose_diversity"]);
    assert!(d.passed, "{}", d.reason());
    assert_eq!(d.reason(), "passed");
    for c in &d.criteria {
        assert!(c.passed && c.candidate >= c.threshold && !c.detail.is_empty(), "{c:?}");
    }
}

#[test]
fn a_collapsed_candidate_is_rejected() {
    let n = 24;
    let active = healthy(n);
    // Every pose scores alike: margins ~0, and the estimates pile up in one azimuth bin.
    let collapsed = with_azimuths(stats(&vec![1e-5; n], &vec![true; n]), &vec![0.0; n]);
    let d = decide(&active, &collapsed, &GateConfig::default()).unwrap();
    assert!(!d.passed);
    assert!(!criterion(&d, "score_margin").passed);
    assert!(!criterion(&d, "pose_diversity").passed);
    // Its flips are perfect (a collapsed model answers the same pose for an image and its
    // mirror, and a head-on pose is its own mirror), but the margin rejects it.
    assert!(criterion(&d, "flip_consistency").passed);
    let reason = d.reason();
    assert!(reason.contains("score_margin: 0.000 < ") && reason.contains("pose_diversity: 0.000 < "), "{reason}");
    // Even with no margin gain required.
    let d = decide(&active, &collapsed, &GateConfig { margin_gain: 0.0, ..GateConfig::default() }).unwrap();
    assert!(!d.passed && !criterion(&d, "score_margin").passed);
}

#[test]
fn an_identical_candidate_fails_a_positive_margin_gain() {
    // The default demands a rise: a no-op adaptation (the source's weights unchanged) is not
    // activated.
    const { assert!(gate::DEFAULT_MARGIN_GAIN > 0.0) };
    let a = healthy(20);
    let d = decide(&a, &a, &GateConfig::default()).unwrap();
    assert!(!d.passed && !criterion(&d, "score_margin").passed, "{}", d.reason());
    assert!(criterion(&d, "flip_consistency").passed && criterion(&d, "pose_diversity").passed);
    let config = GateConfig { margin_gain: 0.01, ..GateConfig::default() };
    let d = decide(&a, &a, &config).unwrap();
    assert!(!d.passed);
    let m = criterion(&d, "score_margin");
    assert!(!m.passed);
    assert_eq!(m.active, m.candidate);
    assert!((m.threshold - (a.median_margin() + 0.01)).abs() < 1e-15);
    assert!(criterion(&d, "flip_consistency").passed && criterion(&d, "pose_diversity").passed);
    assert!(d.reason().starts_with("score_margin: ") && !d.reason().contains(';'), "{}", d.reason());
    // Margins raised by more than the gain pass.
    let mut better = a.clone();
    better.images.iter_mut().for_each(|c| c.margin += 0.0101);
    assert!(decide(&a, &better, &config).unwrap().passed);
    let mut short = a.clone();
    short.images.iter_mut().for_each(|c| c.margin += 0.0099);
    assert!(!decide(&a, &short, &config).unwrap().passed);
}

#[test]
fn median_margin_is_the_median() {
    assert_eq!(stats(&[0.3, 0.1, 0.2], &[true; 3]).median_margin(), 0.2);
    assert_eq!(stats(&[0.4, 0.1, 0.2, 0.3], &[true; 4]).median_margin(), 0.25);
    // One outlier does not move it.
    assert_eq!(stats(&[0.1, 0.2, 0.3, 0.4, 9.0], &[true; 5]).median_margin(), 0.3);
}

#[test]
fn entropy_rule() {
    let n = 24;
    let uniform = healthy(n);
    assert!((uniform.azimuth_entropy() - 12f64.ln()).abs() < 1e-12);
    let config = GateConfig::default();
    let in_bins = |bins: &[f64]| {
        let az: Vec<f64> = (0..n).map(|i| bins[i % bins.len()]).collect();
        with_azimuths(healthy(n), &az)
    };
    // Three equal bins: ln 3 ≈ 1.0986 ≥ min(ln 12 − 0.25, 1.0) = 1.0 passes (a domain seen from
    // few directions is allowed); two: ln 2 < 1.0 fails.
    let three = in_bins(&[0.0, 120.0, 240.0]);
    assert!((three.azimuth_entropy() - 3f64.ln()).abs() < 1e-12);
    let d = decide(&uniform, &three, &config).unwrap();
    let c = criterion(&d, "pose_diversity");
    assert!(c.passed && (c.threshold - 1.0).abs() < 1e-15, "{c:?}");
    let two = in_bins(&[0.0, 180.0]);
    assert!(!criterion(&decide(&uniform, &two, &config).unwrap(), "pose_diversity").passed);
    // Azimuths within ±15° of a grid azimuth share its bin (bins are centred on the grid).
    let jittered = in_bins(&[-14.0, 14.0, 345.5, 15.5, 44.0]);
    // bins 0, 0, 0, 1, 1 cycling over 24 images: 15 in bin 0, 9 in bin 1.
    let p: [f64; 2] = [15.0 / 24.0, 9.0 / 24.0];
    assert!((jittered.azimuth_entropy() + p.iter().map(|p| p * p.ln()).sum::<f64>()).abs() < 1e-12);
    // Below the floor, the candidate may drop by entropy_drop and no more.
    let active = in_bins(&[0.0, 0.0, 0.0, 180.0]); // 3/4, 1/4: 0.562 nats
    let h = active.azimuth_entropy();
    let slightly_less = in_bins(&[0.0, 0.0, 0.0, 0.0, 0.0, 180.0]); // 5/6, 1/6: 0.451 nats
    assert!(slightly_less.azimuth_entropy() >= h - 0.25 && slightly_less.azimuth_entropy() < h);
    let d = decide(&active, &slightly_less, &config).unwrap();
    assert!(criterion(&d, "pose_diversity").passed);
    assert!((criterion(&d, "pose_diversity").threshold - (h - 0.25)).abs() < 1e-15);
    let one_bin = in_bins(&[60.0]);
    assert_eq!(one_bin.azimuth_entropy(), 0.0);
    assert!(!criterion(&decide(&active, &one_bin, &config).unwrap(), "pose_diversity").passed);
}

#[test]
fn flip_rule_allows_two_paired_standard_errors() {
    let n = 12;
    let margins = vec![0.05; n];
    let active = stats(&margins, &vec![true; n]);
    let config = GateConfig { margin_gain: 0.0, ..GateConfig::default() };
    let losing = |k: usize| stats(&margins, &(0..n).map(|i| i >= k).collect::<Vec<_>>());
    // Losing k of 12: d has k values −1. SE = sd(d)/√n; passes iff k/n ≤ 2·SE.
    for k in 0..=n {
        let d = decide(&active, &losing(k), &config).unwrap();
        let c = criterion(&d, "flip_consistency");
        let mean = -(k as f64) / n as f64;
        let var = (k as f64 * (-1.0 - mean).powi(2) + (n - k) as f64 * mean.powi(2)) / (n - 1) as f64;
        let se = (var / n as f64).sqrt();
        assert!((c.threshold - (1.0 - 2.0 * se)).abs() < 1e-12, "k = {k}: {c:?}");
        assert_eq!(c.active, 1.0);
        assert!((c.candidate - (1.0 + mean)).abs() < 1e-15);
        assert_eq!(c.passed, k <= 3, "k = {k}: {c:?}");
        assert_eq!(d.passed, c.passed);
    }
    // A stricter setting rejects a single loss; a candidate that gains always passes.
    let strict = GateConfig { flip_se: 0.0, ..config.clone() };
    assert!(!decide(&active, &losing(1), &strict).unwrap().passed);
    assert!(decide(&losing(6), &active, &strict).unwrap().passed);
    // Swaps cancel: as many gained as lost leaves the rate unchanged.
    let a = stats(&margins, &(0..n).map(|i| i % 2 == 0).collect::<Vec<_>>());
    let c = stats(&margins, &(0..n).map(|i| i % 2 == 1).collect::<Vec<_>>());
    assert!(decide(&a, &c, &strict).unwrap().passed);
}

#[test]
fn the_regression_rule_tolerates_noise_but_not_a_fall() {
    // On an earlier domain's images the candidate need not improve: the active model itself
    // passes (where decide() demands a rising margin), and so does a small, noisy change.
    let config = GateConfig::default();
    let n = 24;
    let active = healthy(n);
    let d = guard(&active, &active, &config).unwrap();
    let names: Vec<&str> = d.criteria.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["flip_consistency", "score_margin", "pose_diversity"]);
    assert!(d.passed, "{}", d.reason());
    assert!(!decide(&active, &active, &config).unwrap().passed);
    let mut jittered = active.clone();
    jittered.images.iter_mut().enumerate().for_each(|(i, c)| c.margin += if i % 2 == 0 { 0.004 } else { -0.0045 });
    assert!(guard(&active, &jittered, &config).unwrap().passed);
    // Forgetting: every margin falls by more than the noise allows.
    let mut forgot = active.clone();
    forgot.images.iter_mut().enumerate().for_each(|(i, c)| c.margin -= 0.01 + 0.001 * (i % 3) as f64);
    let d = guard(&active, &forgot, &config).unwrap();
    let m = criterion(&d, "score_margin");
    assert!(!d.passed && !m.passed && m.candidate < m.threshold, "{m:?}");
    assert!(criterion(&d, "flip_consistency").passed && d.reason().starts_with("score_margin: "), "{}", d.reason());
    // The threshold is the active mean less regression_se paired standard errors: with
    // regression_se 0, any fall of the mean fails.
    let mean = |s: &GateStats| s.images.iter().map(|c| c.margin).sum::<f64>() / n as f64;
    let strict = GateConfig { regression_se: 0.0, ..config.clone() };
    let m = criterion(&guard(&active, &jittered, &strict).unwrap(), "score_margin").clone();
    assert!((m.threshold - mean(&active)).abs() < 1e-15 && !m.passed, "{m:?}");
    // Flip consistency follows the flip rule with regression_se: 4 of 12 lost fail at 2 SE.
    let flips = |k: usize| stats(&[0.05; 12], &(0..12).map(|i| i >= k).collect::<Vec<_>>());
    assert!(guard(&flips(0), &flips(3), &config).unwrap().passed);
    assert!(!criterion(&guard(&flips(0), &flips(4), &config).unwrap(), "flip_consistency").passed);
    assert!(GateConfig { regression_se: -1.0, ..config }.validate().is_err());
}

#[test]
fn too_few_or_mismatched_images_are_errors() {
    let config = GateConfig::default();
    let four = healthy(4);
    assert!(decide(&four, &four, &GateConfig { margin_gain: 0.0, ..config.clone() }).is_ok());
    let three = healthy(3);
    assert!(matches!(decide(&three, &three, &config), Err(EngineError::InvalidInput(_))));
    assert!(matches!(decide(&GateStats::default(), &GateStats::default(), &config), Err(EngineError::InvalidInput(_))));
    assert!(matches!(decide(&four, &healthy(5), &config), Err(EngineError::InvalidInput(_))));
    let mut nan = four.clone();
    nan.images[2].margin = f64::NAN;
    assert!(matches!(decide(&four, &nan, &config), Err(EngineError::InvalidInput(_))));
    let bad = GateConfig { flip_se: -1.0, ..config.clone() };
    assert!(matches!(decide(&four, &four, &bad), Err(EngineError::InvalidInput(_))));
    let six = GateConfig { min_images: 6, ..config };
    assert!(matches!(decide(&healthy(5), &healthy(5), &six), Err(EngineError::InvalidInput(_))));
}

#[test]
fn config_defaults_and_serde() {
    let c = GateConfig::default();
    assert_eq!(c.margin_gain, gate::DEFAULT_MARGIN_GAIN);
    assert_eq!((c.flip_se, c.entropy_drop, c.entropy_floor, c.min_images), (2.0, 0.25, 1.0, 4));
    assert_eq!(c.solver, SolverConfig::default());
    let back: GateConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
    assert_eq!(back, c, "exact: the workspace parses floats with float_roundtrip");
    // Missing fields take their defaults.
    let partial: GateConfig = serde_json::from_str(r#"{"margin_gain": 0.5, "min_images": 10}"#).unwrap();
    assert_eq!(partial, GateConfig { margin_gain: 0.5, min_images: 10, ..GateConfig::default() });
    let d = decide(&healthy(8), &healthy(8), &GateConfig { margin_gain: 0.0, ..c }).unwrap();
    let back: Decision = serde_json::from_str(&serde_json::to_string(&d).unwrap()).unwrap();
    assert_eq!(back, d);
}

/// The target check's threshold: the operator's for every model, else the model's own
/// (measured by `udapose-lab target-check`), else the default.
#[test]
fn the_target_threshold_is_the_operators_then_the_models_then_the_default() {
    let mut model = support::random_model(1, [64, 160], "target").manifest;
    let config = GateConfig::default();
    assert_eq!(config.min_target_fired_for(&model), gate::DEFAULT_MIN_TARGET_FIRED);
    model.min_target_fired = Some(0.1);
    assert_eq!(config.min_target_fired_for(&model), 0.1);
    let operator = GateConfig { min_target_fired: Some(0.05), ..config.clone() };
    assert_eq!(operator.min_target_fired_for(&model), 0.05);
    assert!(GateConfig { min_target_fired: Some(1.5), ..config }.validate().is_err());
}

/// The target check judges a run once: at its TargetCheck event or, without a BatchNorm step
/// (no separate check), at round 1.
#[test]
fn the_target_check_reads_one_event_per_run() {
    assert_eq!(gate::target_fired(&Event::TargetCheck { fired: 0.08 }), Some(0.08));
    let round = |round, source_fired_ratio| RoundReport {
        round,
        source_fired_ratio,
        fired_ratio_before: 0.3,
        ..Default::default()
    };
    assert_eq!(gate::target_fired(&Event::Round(&round(1, None))), Some(0.3), "no BatchNorm step");
    assert_eq!(gate::target_fired(&Event::Round(&round(1, Some(0.08)))), None, "checked before round 1");
    assert_eq!(gate::target_fired(&Event::Round(&round(2, None))), None, "later rounds are not judged");
    let step = Event::Step { round: 1, phase: Phase::Features, done: 1, total: 2 };
    assert_eq!(gate::target_fired(&step), None);
}

// ---------------------------------------------------------------------------------------------
// The held-out bucket

#[test]
fn held_out_bucket() {
    assert!(held_out(&[0, 0, 7]));
    assert!(!held_out(&[0, 1]));
    assert!(held_out(&[0, 5]));
    assert!(!held_out(&[1, 0])); // 256 % 5 = 1
    assert!(held_out(&[0xff, 0xff])); // 65535 % 5 = 0
    assert!(!held_out(&[0]) && !held_out(&[]));
    let held = (0u32..5000).filter(|i| held_out(&Sha256::digest(i.to_le_bytes()))).count();
    assert!((900..1100).contains(&held), "{held} of 5000 held out");
    // sha256("") = e3b0…: 0xe3b0 = 58288, % 5 = 3.
    assert!(!held_out(&Sha256::digest(b"")));
}

// ---------------------------------------------------------------------------------------------
// measure()

fn fast_config() -> GateConfig {
    let solver = SolverConfig {
        optimizer: Optimizer::Adam(AdamConfig { steps: 15, ..AdamConfig::default() }),
        ..SolverConfig::default()
    };
    GateConfig { solver, ..GateConfig::default() }
}

fn random_model() -> Model {
    support::random_model(3, [32, 80], "gate-test")
}

#[test]
fn measure_reports_every_image_and_can_be_cancelled() {
    let model = random_model();
    tch::manual_seed(7);
    let n = 18; // two backbone batches
    let images = Tensor::rand([n, 3, 32, 80], (Kind::Float, Device::Cpu));
    let config = fast_config();
    let mut calls = Vec::new();
    let s = measure(&model, &images, &config, &mut |done, total| {
        calls.push((done, total));
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(calls, [(0, n as usize), (16, n as usize), (n as usize, n as usize)]);
    assert_eq!(s.images.len(), n as usize);
    for c in &s.images {
        assert!((0.0..TAU).contains(&c.azimuth) && c.score.is_finite(), "{c:?}");
        // The estimate is refined from the best grid pose, so no far grid pose beats it.
        assert!(c.margin >= 0.0 && c.margin.is_finite(), "{c:?}");
    }
    // Deterministic for the same images in the same order.
    let again = measure(&model, &images, &config, &mut |_, _| ControlFlow::Continue(())).unwrap();
    assert_eq!(again, s);
    // The model against itself passes with no gain required.
    assert!(decide(&s, &again, &GateConfig { margin_gain: 0.0, ..config.clone() }).unwrap().passed);

    let mut seen = 0;
    let cancelled = measure(&model, &images, &config, &mut |done, _| {
        seen += 1;
        if done > 0 { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
    });
    assert_eq!(cancelled, Err(EngineError::Cancelled));
    assert_eq!(seen, 2);
    let stop_at_once = measure(&model, &images, &config, &mut |_, _| ControlFlow::Break(()));
    assert_eq!(stop_at_once, Err(EngineError::Cancelled));
}

#[test]
fn measure_rejects_wrong_inputs() {
    let model = random_model();
    let config = fast_config();
    let go = &mut |_: usize, _: usize| ControlFlow::Continue(());
    for bad in [
        Tensor::rand([2, 3, 32, 64], (Kind::Float, Device::Cpu)),
        Tensor::rand([2, 1, 32, 80], (Kind::Float, Device::Cpu)),
        Tensor::rand([3, 32, 80], (Kind::Float, Device::Cpu)),
        Tensor::zeros([2, 3, 32, 80], (Kind::Uint8, Device::Cpu)),
    ] {
        assert!(matches!(measure(&model, &bad, &config, go), Err(EngineError::InvalidInput(_))), "{bad:?}");
    }
    let empty = Tensor::zeros([0, 3, 32, 80], (Kind::Float, Device::Cpu));
    assert!(measure(&model, &empty, &config, go).unwrap().images.is_empty());
}

fn env_path(name: &str) -> Option<PathBuf> {
    std::env::var_os(name).map(PathBuf::from)
}

/// The first `n` crops of the quick combined adapt split, as N×3×H×W in [0, 1].
fn quick_images(data: &std::path::Path, n: usize) -> Tensor {
    let split = data.join("combined/adapt");
    let list = std::fs::read_to_string(split.join("lists/car/list.txt")).unwrap();
    let crops: Vec<Tensor> = list
        .lines()
        .take(n)
        .map(|name| tch::vision::image::load(split.join("images/car").join(name)).unwrap().to_kind(Kind::Float) / 255.0)
        .collect();
    Tensor::stack(&crops, 0)
}

/// On the quick model and real crops: a trained model's margins are positive, it passes against
/// itself, and a collapsed candidate (every vertex feature the same) is rejected by its margin.
#[test]
fn measure_on_the_quick_model() {
    let need = |var: &str| env_path(var).unwrap_or_else(|| panic!("{var} is not set: run the tests with `make test`"));
    let (model_dir, data) = (need("UDAPOSE_QUICK_MODEL"), need("UDAPOSE_QUICK_DATA"));
    let model = checkpoint::load(&model_dir, Device::Cpu).unwrap();
    let images = quick_images(&data, 12);
    let config = GateConfig { margin_gain: 0.0, ..fast_config() };
    let go = &mut |_: usize, _: usize| ControlFlow::Continue(());
    let active = measure(&model, &images, &config, go).unwrap();
    eprintln!(
        "quick model: flip rate {:.3}, median margin {:.4}, entropy {:.3}",
        active.flip_rate(),
        active.median_margin(),
        active.azimuth_entropy()
    );
    assert!(active.images.iter().all(|c| c.margin >= 0.0));
    assert!(active.median_margin() > 0.0);
    assert!(decide(&active, &active, &config).unwrap().passed);

    // A collapsed candidate: every vertex feature the same vector (the mean of the mesh's), so
    // every pose scores alike up to its silhouette.
    let mut collapsed = checkpoint::load(&model_dir, Device::Cpu).unwrap();
    let c = &collapsed.neural_mesh.vertex_features;
    let mean = c.mean_dim([0i64].as_slice(), true, Kind::Float);
    collapsed.neural_mesh.vertex_features = (&mean / mean.norm()).expand_as(c).contiguous();
    let candidate = measure(&collapsed, &images, &config, go).unwrap();
    let d = decide(&active, &candidate, &config).unwrap();
    eprintln!(
        "collapsed: flip {:.3}, margin {:.5}, entropy {:.3}: {}",
        candidate.flip_rate(),
        candidate.median_margin(),
        candidate.azimuth_entropy(),
        d.reason()
    );
    assert!(!d.passed && !d.criteria[1].passed);
}
