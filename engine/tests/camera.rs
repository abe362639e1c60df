//! The camera of METHOD.md §2 against the shared reference values and an independent
//! formulation (a look-at camera on a y-up mesh).

use std::f64::consts::PI;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use udapose_engine::{Camera, Pose, View};

fn vectors() -> Value {
    let text = include_str!("data/camera-vectors.json");
    serde_json::from_str(text).expect("camera-vectors.json parses")
}

fn f(v: &Value) -> f64 {
    v.as_f64().expect("number")
}

fn vec3(v: &Value) -> [f64; 3] {
    [f(&v[0]), f(&v[1]), f(&v[2])]
}

fn pose_of(c: &Value, distance: f64) -> Pose {
    Pose::new(f(&c["azimuth"]), f(&c["elevation"]), f(&c["theta"]), distance)
}

#[test]
fn projection_matches_reference_vectors() {
    let v = vectors();
    let cases = v["projection"].as_array().unwrap();
    assert!(cases.len() >= 100);
    let mut worst = 0.0f64;
    for c in cases {
        let principal = [f(&c["principal"][0]), f(&c["principal"][1])];
        let cam = Camera::new(f(&c["viewport"]), principal, 1, 1).unwrap();
        let view = View::new(&cam, &pose_of(c, f(&c["distance"]))).unwrap();
        for (p, px) in c["points"].as_array().unwrap().iter().zip(c["pixels_col_row"].as_array().unwrap()) {
            let [col, row, _] = view.project(vec3(p));
            worst = worst.max((col - f(&px[0])).abs()).max((row - f(&px[1])).abs());
        }
    }
    assert!(worst < 1e-6, "worst pixel difference {worst}");
}

#[test]
fn rotation_matches_reference_vectors() {
    let v = vectors();
    for c in v["rotation"].as_array().unwrap() {
        let r = pose_of(c, 1.0).rotation();
        for i in 0..3 {
            for j in 0..3 {
                let want = f(&c["matrix"][i][j]);
                assert!((r[(i, j)] - want).abs() < 1e-12, "R[{i}][{j}] = {} want {want}", r[(i, j)]);
            }
        }
    }
}

/// Independent formulation: convert the z-up mesh to y-up, place the eye on a sphere around
/// the origin (azimuth from +z towards +x, elevation up from the xz-plane), build a look-at
/// basis with world-up +y, roll the image by θ and apply a pinhole with focal M.
fn look_at_project(pose: &Pose, m: f64, principal: [f64; 2], x_zup: [f64; 3]) -> [f64; 2] {
    let p = [x_zup[0], x_zup[2], -x_zup[1]];
    let (a, e, d) = (pose.azimuth, pose.elevation, pose.distance);
    let eye = [d * e.cos() * a.sin(), d * e.sin(), d * e.cos() * a.cos()];
    let forward = normalise(scale(eye, -1.0));
    let right = normalise(cross(forward, [0.0, 1.0, 0.0]));
    let up = cross(right, forward);
    let rel = sub(p, eye);
    let depth = dot(rel, forward);
    let (x, y) = (m * dot(rel, right) / depth, m * dot(rel, up) / depth);
    // In-plane roll: the image turns counter-clockwise by θ (image y up).
    let (s, c) = pose.theta.sin_cos();
    let (u, v) = (c * x - s * y, s * x + c * y);
    [principal[0] + u, principal[1] - v]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    a.map(|x| x * s)
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn normalise(a: [f64; 3]) -> [f64; 3] {
    scale(a, 1.0 / dot(a, a).sqrt())
}

#[test]
fn projection_agrees_with_independent_look_at_camera() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut worst = 0.0f64;
    let mut count = 0;
    for _ in 0..1000 {
        // Elevation stays off the poles, where a look-at basis with world-up is undefined.
        let pose = Pose::new(
            rng.random_range(-PI..PI),
            rng.random_range(-1.4..1.4),
            rng.random_range(-PI..PI),
            rng.random_range(2.0..20.0),
        );
        let (h, w) = ([64usize, 128, 256][rng.random_range(0..3)], [160usize, 320, 672][rng.random_range(0..3)]);
        let cam = Camera::for_crop(h, w).unwrap();
        let cam = if rng.random_bool(0.5) { cam.at_stride(8).unwrap() } else { cam };
        let view = View::new(&cam, &pose).unwrap();
        for _ in 0..4 {
            let x = [rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5)];
            let [col, row, depth] = view.project(x);
            assert!(depth > 0.0);
            let [c2, r2] = look_at_project(&pose, cam.viewport, cam.principal, x);
            worst = worst.max((col - c2).abs()).max((row - r2).abs());
            count += 1;
        }
    }
    assert!(count >= 1000);
    assert!(worst < 1e-6, "worst pixel difference {worst}");
}

#[test]
fn origin_projects_to_principal_point_and_stride_scales_pixels() {
    let full = Camera::for_crop(256, 672).unwrap();
    assert_eq!(full.viewport, 3000.0);
    assert_eq!(full.principal, [336.0, 128.0]);
    let feat = full.at_stride(8).unwrap();
    assert_eq!((feat.width, feat.height, feat.viewport, feat.principal), (84, 32, 375.0, [42.0, 16.0]));
    let small = Camera::for_crop(128, 320).unwrap();
    assert_eq!((small.viewport, small.at_stride(8).unwrap().width), (1500.0, 40));

    let pose = Pose::new(0.7, 0.3, -0.4, 6.0);
    let [col, row, depth] = View::new(&full, &pose).unwrap().project([0.0; 3]);
    assert!((col - 336.0).abs() < 1e-9 && (row - 128.0).abs() < 1e-9 && (depth - 6.0).abs() < 1e-12);
    // A point's feature-grid position is its image position divided by the stride.
    let x = [0.2, -0.3, 0.1];
    let a = View::new(&full, &pose).unwrap().project(x);
    let b = View::new(&feat, &pose).unwrap().project(x);
    assert!((a[0] / 8.0 - b[0]).abs() < 1e-9 && (a[1] / 8.0 - b[1]).abs() < 1e-9);
}

#[test]
fn bad_poses_and_cameras_are_typed_errors() {
    let cam = Camera::for_crop(128, 320).unwrap();
    for pose in [
        Pose::new(f64::NAN, 0.0, 0.0, 5.0),
        Pose::new(0.0, f64::INFINITY, 0.0, 5.0),
        Pose::new(0.0, 0.0, f64::NAN, 5.0),
        Pose::new(0.0, 0.0, 0.0, 0.0),
        Pose::new(0.0, 0.0, 0.0, -1.0),
        Pose::new(0.0, 0.0, 0.0, f64::NAN),
    ] {
        assert!(matches!(View::new(&cam, &pose), Err(udapose_engine::EngineError::InvalidPose(_))), "{pose:?}");
    }
    assert!(matches!(Camera::for_crop(0, 320), Err(udapose_engine::EngineError::EmptyImage { .. })));
    assert!(Camera::new(f64::NAN, [0.0, 0.0], 4, 4).is_err());
    assert!(Camera::new(100.0, [0.0, 0.0], 4, 4).unwrap().at_stride(0).is_err());
}
