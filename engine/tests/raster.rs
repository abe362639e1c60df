//! The rasteriser: coverage, barycentrics, depth order and vertex visibility.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use udapose_engine::mesh::TARGET_VERTICES;
use udapose_engine::raster::NO_FACE;
use udapose_engine::{Camera, Cuboid, EngineError, Mesh, Pose, Rasterizer, View};

#[test]
fn single_triangle_exact_coverage_and_barycentrics() {
    // Vertices on integer points: no pixel centre (half-integers) lies on an edge.
    // Inside: col > 1, row > 1, 6·col + 8·row < 62  ⇔  j ≥ 1, i ≥ 1, 6j + 8i < 55.
    let p = [[1.0, 1.0, 2.0], [9.0, 1.0, 2.0], [1.0, 7.0, 2.0]];
    let mut r = Rasterizer::new();
    let out = r.render_projected(&p, &[[0, 1, 2]], 12, 10).unwrap();
    let mut covered = 0;
    for i in 0..10 {
        for j in 0..12 {
            let k = i * 12 + j;
            let want = j >= 1 && i >= 1 && 6 * j + 8 * i < 55;
            assert_eq!(out.face[k] == 0, want, "pixel ({i}, {j})");
            if want {
                covered += 1;
                let b = out.barycentric[k];
                let col: f64 = (0..3).map(|v| b[v] as f64 * p[v][0]).sum();
                let row: f64 = (0..3).map(|v| b[v] as f64 * p[v][1]).sum();
                assert!((col - (j as f64 + 0.5)).abs() < 1e-5 && (row - (i as f64 + 0.5)).abs() < 1e-5);
                assert!(((b[0] + b[1] + b[2]) - 1.0).abs() < 1e-6);
                assert_eq!(out.depth[k], 2.0);
            } else {
                assert_eq!(out.depth[k], f32::INFINITY);
            }
        }
    }
    assert_eq!(covered, out.face.iter().filter(|&&f| f != NO_FACE).count());
    assert!(covered > 15);
}

#[test]
fn barycentrics_are_perspective_correct() {
    // A triangle slanted in depth: the 3-D point Σ b_k X_k must project to the pixel centre and
    // have the pixel's depth.
    let verts = vec![[-0.4, -0.3, -0.2], [0.5, 0.4, 0.0], [-0.2, 0.3, 0.35]];
    let mesh = Mesh::new(verts.clone(), vec![[0, 1, 2]]).unwrap();
    let cam = Camera::for_crop(64, 96).unwrap();
    let pose = Pose::new(0.6, 0.4, 0.2, 3.0);
    let view = View::new(&cam, &pose).unwrap();
    let mut r = Rasterizer::new();
    let out = r.render(&mesh, &cam, &pose).unwrap();
    let mut n = 0;
    for (k, &f) in out.face.iter().enumerate() {
        if f == NO_FACE {
            continue;
        }
        let b = out.barycentric[k];
        let x: [f64; 3] = std::array::from_fn(|a| (0..3).map(|v| b[v] as f64 * verts[v][a]).sum());
        let [col, row, depth] = view.project(x);
        let (i, j) = (k / cam.width, k % cam.width);
        assert!(
            (col - (j as f64 + 0.5)).abs() < 1e-3 && (row - (i as f64 + 0.5)).abs() < 1e-3,
            "pixel ({i}, {j}): {col}, {row}"
        );
        assert!((depth - out.depth[k] as f64).abs() < 1e-5);
        n += 1;
    }
    assert!(n > 100, "covered {n}");
}

#[test]
fn nearer_triangle_wins_in_either_order() {
    let near = [[2.0, 2.0, 1.0], [14.0, 2.0, 1.0], [2.0, 14.0, 1.0]];
    let far = [[4.0, 4.0, 3.0], [16.0, 4.0, 3.0], [16.0, 16.0, 3.0]];
    for (p, near_face) in [([near, far].concat(), 0u32), ([far, near].concat(), 1u32)] {
        let mut r = Rasterizer::new();
        let out = r.render_projected(&p, &[[0, 1, 2], [3, 4, 5]], 20, 20).unwrap();
        // (6.5, 6.5) is inside both triangles; (15.5, 12.5) only in the far one.
        assert_eq!(out.face[6 * 20 + 6], near_face);
        assert_eq!(out.depth[6 * 20 + 6], 1.0);
        assert_eq!(out.face[12 * 20 + 15], 1 - near_face);
        assert_eq!(out.depth[12 * 20 + 15], 3.0);
    }
}

#[test]
fn shared_edges_cover_each_pixel_once_without_cracks() {
    // A square whose edges and diagonal run through pixel centres: the top-left rule must give
    // exactly the 8 × 6 pixels whose centres are in [2.5, 10.5) × [1.5, 7.5).
    let p = [[2.5, 1.5, 1.0], [10.5, 1.5, 1.0], [10.5, 7.5, 1.0], [2.5, 7.5, 1.0]];
    let faces = [[0, 1, 2], [0, 2, 3]];
    let mut r = Rasterizer::new();
    let out = r.render_projected(&p, &faces, 14, 10).unwrap();
    for i in 0..10 {
        for j in 0..14 {
            let want = (2..10).contains(&j) && (1..7).contains(&i);
            assert_eq!(out.face[i * 14 + j] != NO_FACE, want, "pixel ({i}, {j})");
        }
    }
}

/// The side (±x, ±y, ±z) of a cuboid face, from its normal.
fn side(mesh: &Mesh, f: u32) -> usize {
    let [a, b, c] = mesh.faces()[f as usize].map(|i| mesh.vertices()[i as usize]);
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
    let axis = (0..3).max_by(|&p, &q| n[p].abs().total_cmp(&n[q].abs())).unwrap();
    2 * axis + usize::from(n[axis] > 0.0)
}

#[test]
fn cuboid_head_on_shows_only_the_front_face() {
    let cuboid = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap();
    let mesh = cuboid.mesh(TARGET_VERTICES);
    // Azimuth 0, elevation 0: the camera is on −y looking along +y at the y = min face.
    let pose = Pose::new(0.0, 0.0, 0.0, 4.0);
    for cam in [Camera::for_crop(256, 672).unwrap(), Camera::for_crop(256, 672).unwrap().at_stride(8).unwrap()] {
        let mut r = Rasterizer::new();
        let out = r.render(&mesh, &cam, &pose).unwrap();
        for (k, v) in mesh.vertices().iter().enumerate() {
            assert_eq!(out.visible[k], v[1] == cuboid.min[1], "vertex {k} at {v:?}, grid {}x{}", cam.width, cam.height);
        }
        // 11 × 7 front-face vertices, plus the border copies from 4 adjacent faces.
        assert_eq!(out.visible.iter().filter(|&&v| v).count(), 11 * 7 + 2 * 11 + 2 * 7);
    }
}

#[test]
fn visibility_is_stable_under_subpixel_pose_changes_away_from_edges() {
    let mesh = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap().mesh(TARGET_VERTICES);
    let cam = Camera::for_crop(256, 672).unwrap().at_stride(8).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (mut a, mut b) = (Rasterizer::new(), Rasterizer::new());
    let mut checked = 0;
    for _ in 0..200 {
        let pose = Pose::new(
            rng.random_range(0.0..std::f64::consts::TAU),
            rng.random_range(-0.5..1.2),
            rng.random_range(-0.5..0.5),
            rng.random_range(3.0..8.0),
        );
        // 1e-4 rad moves a vertex by well under 0.05 feature pixels.
        let moved = Pose { azimuth: pose.azimuth + 1e-4, elevation: pose.elevation - 1e-4, ..pose };
        let fa = a.render(&mesh, &cam, &pose).unwrap();
        let fb = b.render(&mesh, &cam, &moved).unwrap();
        for k in 0..mesh.vertices().len() {
            let [col, row, _] = fa.projected[k];
            let (i, j) = (row.floor() as i64, col.floor() as i64);
            // Away from edges: the 3 × 3 pixels around the vertex all show one cuboid side.
            let mut sides = (-1..=1).flat_map(|di| (-1..=1).map(move |dj| (i + di, j + dj))).map(|(y, x)| {
                let inside = (0..cam.height as i64).contains(&y) && (0..cam.width as i64).contains(&x);
                let p = (y * cam.width as i64 + x) as usize;
                if !inside || fa.face[p] == NO_FACE || fb.face[p] == NO_FACE {
                    usize::MAX
                } else if side(&mesh, fa.face[p]) == side(&mesh, fb.face[p]) {
                    side(&mesh, fa.face[p])
                } else {
                    usize::MAX - 1
                }
            });
            let first = sides.next().unwrap();
            if first < 6 && sides.all(|s| s == first) {
                assert_eq!(fa.visible[k], fb.visible[k], "vertex {k}, pose {pose:?}");
                checked += 1;
            }
        }
    }
    assert!(checked > 20_000, "checked {checked}");
}

#[test]
fn parallel_bands_match_serial_and_buffers_are_reused() {
    let mesh = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap().mesh(TARGET_VERTICES);
    let cam = Camera::for_crop(256, 672).unwrap();
    let pose = Pose::new(2.1, 0.4, 0.1, 3.0);
    let mut serial = Rasterizer::with_parallel_threshold(usize::MAX);
    let mut parallel = Rasterizer::with_parallel_threshold(0);
    let s = serial.render(&mesh, &cam, &pose).unwrap();
    let ptrs = (s.face.as_ptr(), s.barycentric.as_ptr(), s.depth.as_ptr(), s.visible.as_ptr());
    let (face, bary, depth, vis) = (s.face.to_vec(), s.barycentric.to_vec(), s.depth.to_vec(), s.visible.to_vec());
    let p = parallel.render(&mesh, &cam, &pose).unwrap();
    assert!(face.iter().filter(|&&f| f != NO_FACE).count() > 10_000);
    assert_eq!(
        (face.as_slice(), bary.as_slice(), depth.as_slice(), vis.as_slice()),
        (p.face, p.barycentric, p.depth, p.visible)
    );
    // A second call at the same size writes into the same buffers.
    let s = serial.render(&mesh, &cam, &Pose { azimuth: 0.3, ..pose }).unwrap();
    assert_eq!(ptrs, (s.face.as_ptr(), s.barycentric.as_ptr(), s.depth.as_ptr(), s.visible.as_ptr()));
}

#[test]
fn bad_input_is_a_typed_error_not_a_panic() {
    let mesh = Cuboid::from_dimensions([0.4, 1.0, 0.3]).unwrap().mesh(TARGET_VERTICES);
    let cam = Camera::for_crop(64, 160).unwrap();
    let mut r = Rasterizer::new();
    let nan = Pose::new(f64::NAN, 0.0, 0.0, 5.0);
    assert!(matches!(r.render(&mesh, &cam, &nan), Err(EngineError::InvalidPose(_))));
    let empty = Camera { width: 0, ..cam };
    assert!(matches!(r.render(&mesh, &empty, &Pose::new(0.0, 0.0, 0.0, 5.0)), Err(EngineError::EmptyImage { .. })));
    assert!(matches!(r.render_projected(&[[0.0; 3]; 3], &[[0, 1, 2]], 0, 5), Err(EngineError::EmptyImage { .. })));
    assert!(matches!(r.render_projected(&[[0.0; 3]; 3], &[[0, 1, 3]], 4, 4), Err(EngineError::InvalidMesh(_))));
    // Non-finite or behind-the-camera vertices are dropped, not drawn and not visible.
    let p = [[1.0, 1.0, 1.0], [f64::NAN, 1.0, 1.0], [1.0, 3.0, 1.0], [3.0, 3.0, -1.0]];
    let out = r.render_projected(&p, &[[0, 1, 2], [0, 2, 3]], 4, 4).unwrap();
    assert!(out.face.iter().all(|&f| f == NO_FACE));
    assert_eq!(out.visible, &[true, false, true, false]);
    // Camera inside the object: no panic.
    assert!(r.render(&mesh, &cam, &Pose::new(0.0, 0.0, 0.0, 0.1)).is_ok());
}

#[test]
fn back_face_culling_changes_nothing_but_time() {
    let culled = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap().mesh(TARGET_VERTICES);
    assert!(culled.is_closed_outward());
    let plain = Mesh::new(culled.vertices().to_vec(), culled.faces().to_vec()).unwrap();
    assert!(!plain.is_closed_outward());
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let (mut a, mut b) = (Rasterizer::new(), Rasterizer::new());
    for _ in 0..100 {
        let pose = Pose::new(
            rng.random_range(-3.2..3.2),
            rng.random_range(-1.5..1.5),
            rng.random_range(-1.0..1.0),
            rng.random_range(2.5..10.0),
        );
        let cam = Camera::for_crop(128, 320).unwrap().at_stride([1, 8][rng.random_range(0..2)]).unwrap();
        let x = a.render(&culled, &cam, &pose).unwrap();
        let y = b.render(&plain, &cam, &pose).unwrap();
        assert_eq!((x.face, x.depth, x.visible), (y.face, y.depth, y.visible), "{pose:?}");
    }
}
