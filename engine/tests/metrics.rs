//! Geodesic pose error and the benchmark metrics.

use std::f64::consts::PI;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use udapose_engine::camera::rotation;
use udapose_engine::{PoseMetrics, pose_error, rotation_error};

fn angles(v: &Value) -> Option<[f64; 3]> {
    let a = v.as_array()?;
    Some([a[0].as_f64()?, a[1].as_f64()?, a[2].as_f64()?])
}

#[test]
fn geodesic_matches_reference_vectors_including_edges() {
    let v: Value = serde_json::from_str(include_str!("data/camera-vectors.json")).unwrap();
    for key in ["geodesic", "geodesic_edge"] {
        for c in v[key].as_array().unwrap() {
            let gt = angles(&c["gt"]).unwrap();
            let got = pose_error(angles(&c["pred"]), gt);
            let want = c["error_rad"].as_f64().unwrap();
            assert!((got - want).abs() < 1e-9, "{key}: got {got}, want {want} ({c})");
        }
    }
}

/// Rodrigues' rotation about a unit axis.
fn axis_angle(axis: [f64; 3], angle: f64) -> nalgebra::Matrix3<f64> {
    let k = nalgebra::Vector3::from(axis).normalize();
    nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(k), angle).into_inner()
}

#[test]
fn identical_poses_have_zero_error_and_known_rotations_their_angle() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..500 {
        let [a, e, t] = [rng.random_range(-PI..PI), rng.random_range(-1.5..1.5), rng.random_range(-PI..PI)];
        let r = rotation(a, e, t);
        assert_eq!(pose_error(Some([a, e, t]), [a, e, t]), 0.0);
        let angle = rng.random_range(0.0..PI);
        let axis = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        let other = axis_angle(axis, angle) * r;
        let d = rotation_error(&other, &r);
        assert!((d - angle).abs() < 1e-9, "got {d}, want {angle}");
        assert_eq!(d, rotation_error(&r, &other), "symmetric");
    }
}

#[test]
fn no_nan_at_zero_and_pi() {
    let r = rotation(0.3, 0.2, 0.1);
    for angle in [0.0, 1e-12, PI - 1e-12, PI] {
        let d = rotation_error(&(axis_angle([0.3, -0.5, 0.8], angle) * r), &r);
        assert!(d.is_finite() && (d - angle).abs() < 1e-9, "angle {angle}: {d}");
    }
    // Azimuth moved by π about the vertical axis: exactly π.
    let d = pose_error(Some([0.4 + PI, 0.0, 0.0]), [0.4, 0.0, 0.0]);
    assert!((d - PI).abs() < 1e-12);
    assert_eq!(pose_error(None, [0.0; 3]), PI);
    assert_eq!(pose_error(Some([f64::NAN, 0.0, 0.0]), [0.0; 3]), PI);
}

#[test]
fn metrics_on_hand_computed_cases() {
    let deg = |d: f64| d.to_radians();
    // 5°, 15°, 25°, 40°, NaN (counts as 180°): Acc@π/18 = 1/5, Acc@π/6 = 3/5, median 25°.
    let m = PoseMetrics::from_errors(&[deg(25.0), deg(5.0), f64::NAN, deg(40.0), deg(15.0)]).unwrap();
    assert_eq!(m.n, 5);
    assert!((m.acc_pi_18 - 0.2).abs() < 1e-15);
    assert!((m.acc_pi_6 - 0.6).abs() < 1e-15);
    assert!((m.med_err_deg - 25.0).abs() < 1e-12);
    // Even count: median is the mean of the middle two; thresholds are strict.
    let m = PoseMetrics::from_errors(&[deg(10.0), deg(29.0), PI / 6.0, deg(1.0)]).unwrap();
    assert!((m.med_err_deg - 19.5).abs() < 1e-12);
    assert!((m.acc_pi_6 - 0.75).abs() < 1e-15, "π/6 itself is not below π/6");
    assert!(PoseMetrics::from_errors(&[]).is_err());
}

#[test]
fn bootstrap_intervals_bracket_the_estimate_and_shrink_with_n() {
    use udapose_engine::metrics::MetricIntervals;
    let errors: Vec<f64> = (0..300).map(|i| ((i * 37) % 100) as f64 / 100.0 * 1.2).collect();
    let m = PoseMetrics::from_errors(&errors).unwrap();
    let ci = MetricIntervals::bootstrap(&errors, 1000, 0).unwrap();
    assert!(ci.acc_pi_6_ci[0] <= m.acc_pi_6 && m.acc_pi_6 <= ci.acc_pi_6_ci[1]);
    assert!(ci.med_err_deg_ci[0] <= m.med_err_deg && m.med_err_deg <= ci.med_err_deg_ci[1]);
    // p ≈ 0.44 with n = 300: the 95% interval is about ±0.056.
    let width = ci.acc_pi_6_ci[1] - ci.acc_pi_6_ci[0];
    assert!((0.08..0.15).contains(&width), "width {width}");
    let small = MetricIntervals::bootstrap(&errors[..30], 1000, 0).unwrap();
    assert!(small.acc_pi_6_ci[1] - small.acc_pi_6_ci[0] > 2.0 * width);
    assert_eq!(ci, MetricIntervals::bootstrap(&errors, 1000, 0).unwrap(), "fixed seed");
}

#[test]
fn paired_bootstrap_resamples_the_same_images_for_every_model() {
    use udapose_engine::metrics::paired_bootstrap;
    // Model b is right wherever a is, plus on 30 more of 100 images: every draw favours b.
    let a: Vec<bool> = (0..100).map(|i| i < 50).collect();
    let b: Vec<bool> = (0..100).map(|i| i < 80).collect();
    let acc = |h: &[bool], idx: &[usize]| idx.iter().filter(|&&i| h[i]).count() as f64 / idx.len() as f64;
    let [lo, hi] = paired_bootstrap(100, 1000, 0, |idx| Some(acc(&b, idx) - acc(&a, idx))).unwrap();
    assert!(0.0 < lo && lo < 0.3 && 0.3 < hi && hi < 0.45, "[{lo}, {hi}]");
    // Fixed seed: the same interval again.
    assert_eq!(paired_bootstrap(100, 1000, 0, |idx| Some(acc(&b, idx) - acc(&a, idx))).unwrap(), [lo, hi]);
    // Undefined in most draws, or nothing to resample: no interval.
    assert!(paired_bootstrap(100, 1000, 0, |idx| (idx[0] < 5).then_some(1.0)).is_none());
    assert!(paired_bootstrap(0, 1000, 0, |_| Some(1.0)).is_none());
}

#[test]
fn errors_up_to_a_symmetry_about_the_up_axis() {
    use udapose_engine::{UpSymmetry, canonical_azimuth, nearest_look_alike, pose_error_up_to};
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for _ in 0..500 {
        let gt = [rng.random_range(-PI..PI), rng.random_range(-1.5..1.5), rng.random_range(-PI..PI)];
        let pred = [rng.random_range(-PI..PI), rng.random_range(-1.5..1.5), rng.random_range(-PI..PI)];
        let plain = pose_error(Some(pred), gt);
        assert_eq!(pose_error_up_to(Some(pred), gt, UpSymmetry::NONE), plain);
        // More symmetry never scores worse, and each score is the smallest over its turns.
        let [half, quarter, round] = [UpSymmetry::Order(2), UpSymmetry::Order(4), UpSymmetry::Continuous]
            .map(|s| pose_error_up_to(Some(pred), gt, s));
        assert!(half <= plain && quarter <= half && round <= quarter + 1e-9, "{plain} {half} {quarter} {round}");
        let turned = |d: f64| pose_error(Some([pred[0] + d, pred[1], pred[2]]), gt);
        assert!((half - turned(0.0).min(turned(PI))).abs() < 1e-12);
        let scan = (0..3600).map(|i| turned(2.0 * PI * f64::from(i) / 3600.0)).fold(PI, f64::min);
        assert!(round <= scan + 1e-9 && scan - round < 2e-3, "closed form {round}, scan {scan}");
        // The nearest look-alike is one (it scores as gt) and the estimate's error to it is the
        // error up to the symmetry.
        for s in [UpSymmetry::NONE, UpSymmetry::Order(2), UpSymmetry::Order(4), UpSymmetry::Continuous] {
            let twin = nearest_look_alike(pred, gt, s);
            assert!(pose_error_up_to(Some(twin), gt, s) < 1e-7, "{s:?}: {twin:?} does not look like {gt:?}");
            let up_to = pose_error_up_to(Some(pred), gt, s);
            assert!((pose_error(Some(pred), twin) - up_to).abs() < 1e-9, "{s:?}");
        }
        // An estimate turned by a symmetry about the up axis is right; any other error stays.
        let [a, e, t] = gt;
        assert!(pose_error_up_to(Some([a + PI, e, t]), gt, UpSymmetry::Order(2)) < 1e-7);
        assert!(pose_error_up_to(Some([a + PI / 2.0, e, t]), gt, UpSymmetry::Order(4)) < 1e-7);
        assert!((pose_error_up_to(Some([a + PI / 2.0, e, t]), gt, UpSymmetry::Order(2)) - PI / 2.0).abs() < 1e-7);
        let de = rng.random_range(-0.5..0.5);
        let r = pose_error_up_to(Some([a + rng.random_range(-PI..PI), e + de, t]), gt, UpSymmetry::Continuous);
        assert!((r - de.abs()).abs() < 1e-6, "round, elevation off by {de}: {r}");
        // The canonical azimuth is in its window and looks the same as the original.
        for (s, half_window) in [(UpSymmetry::Order(2), PI / 2.0), (UpSymmetry::Order(4), PI / 4.0)] {
            let c = canonical_azimuth(a, s);
            assert!((-half_window..half_window).contains(&c), "{a} -> {c}");
            assert!(pose_error_up_to(Some([c, e, t]), gt, s) < 1e-7);
        }
        assert_eq!(canonical_azimuth(a, UpSymmetry::NONE), a);
        assert_eq!(canonical_azimuth(a, UpSymmetry::Continuous), 0.0);
    }
}
