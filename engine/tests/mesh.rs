//! Cuboid neural-mesh geometry and mesh files.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use udapose_engine::mesh::{self, CAD_COVERAGE, TARGET_VERTICES};
use udapose_engine::{Cuboid, EngineError, Mesh};

#[test]
fn syncar_body_cuboid_has_1054_vertices() {
    // METHOD.md §3: 0.433 × 0.992 × 0.270 gives 11 × 25 × 7 samples and R = 1054.
    let c = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap();
    assert_eq!(c.grid_counts(TARGET_VERTICES), [11, 25, 7]);
    let m = c.mesh(TARGET_VERTICES);
    assert_eq!(m.vertices().len(), 1054);
    assert_eq!(m.faces().len(), 2 * (10 * 24 + 24 * 6 + 6 * 10) * 2);
    // Every vertex lies on the surface, and every corner is present (faces share none: 3 copies).
    for v in m.vertices() {
        let on_face = (0..3).any(|a| (v[a] - c.min[a]).abs() < 1e-12 || (v[a] - c.max[a]).abs() < 1e-12);
        assert!(on_face && (0..3).all(|a| v[a] >= c.min[a] - 1e-12 && v[a] <= c.max[a] + 1e-12));
    }
    let corner = c.max;
    assert_eq!(m.vertices().iter().filter(|v| **v == corner).count(), 3);
}

#[test]
fn triangles_face_outwards() {
    let m = Cuboid::from_dimensions([0.5, 1.0, 0.3]).unwrap().mesh(TARGET_VERTICES);
    for f in m.faces() {
        let [a, b, c] = f.map(|i| m.vertices()[i as usize]);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        let centre = [(a[0] + b[0] + c[0]) / 3.0, (a[1] + b[1] + c[1]) / 3.0, (a[2] + b[2] + c[2]) / 3.0];
        let outward = n[0] * centre[0] + n[1] * centre[1] + n[2] * centre[2];
        assert!(outward > 0.0, "face {f:?} points inwards");
    }
}

#[test]
fn cad_cuboid_is_the_narrowest_99_percent_interval_per_axis() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    // 1000 points in a box, plus 10 far outliers on one side of each axis: a 99% interval
    // must drop exactly the outliers.
    let mut pts: Vec<[f64; 3]> = (0..990)
        .map(|_| [rng.random_range(-0.2..0.2), rng.random_range(-0.5..0.5), rng.random_range(0.0..0.3)])
        .collect();
    pts.extend((0..10).map(|i| [5.0 + i as f64, -9.0 - i as f64, 7.0]));
    let c = Cuboid::from_cad_vertices(&pts, CAD_COVERAGE).unwrap();
    let lo = |a: usize| pts[..990].iter().map(|p| p[a]).fold(f64::INFINITY, f64::min);
    let hi = |a: usize| pts[..990].iter().map(|p| p[a]).fold(f64::NEG_INFINITY, f64::max);
    for a in 0..3 {
        assert_eq!((c.min[a], c.max[a]), (lo(a), hi(a)), "axis {a}");
    }
    // With all points kept the interval is the full range.
    let full = Cuboid::from_cad_vertices(&pts, 1.0).unwrap();
    assert_eq!(full.max[0], 14.0);
    assert!(Cuboid::from_cad_vertices(&[], 0.99).is_err());
    assert!(Cuboid::from_cad_vertices(&[[0.0, 0.0, f64::NAN]], 0.99).is_err());
    assert!(Cuboid::from_cad_vertices(&[[0.0, 0.0, 0.0]; 4], 0.99).is_err(), "flat box");
    assert!(Cuboid::from_dimensions([1.0, 0.0, 1.0]).is_err());
}

#[test]
fn off_and_obj_round_trip() {
    let m = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap().mesh(TARGET_VERTICES);
    let mut off = Vec::new();
    mesh::write_off(&m, &mut off).unwrap();
    let back = mesh::read_off(&off[..]).unwrap();
    assert!(back.vertices() == m.vertices() && back.faces() == m.faces());
    let mut obj = Vec::new();
    mesh::write_obj(&m, &mut obj).unwrap();
    let back = mesh::read_obj(&obj[..]).unwrap();
    assert!(back.vertices() == m.vertices() && back.faces() == m.faces());
}

#[test]
fn off_and_obj_read_polygons_comments_and_index_forms() {
    let off = "OFF # a square\n\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";
    let m = mesh::read_off(off.as_bytes()).unwrap();
    assert_eq!(m.faces(), &[[0, 1, 2], [0, 2, 3]]);
    let obj = "# square\nv 0 0 0\nv 1 0 0\nvt 0 0\nv 1 1 0\nv 0 1 0\nf 1/1/1 2/1 -2 -1\n";
    let m = mesh::read_obj(obj.as_bytes()).unwrap();
    assert_eq!(m.faces(), &[[0, 1, 2], [0, 2, 3]]);
}

#[test]
fn degenerate_meshes_and_bad_files_are_typed_errors() {
    let tri = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let invalid = |r: Result<Mesh, EngineError>| matches!(r, Err(EngineError::InvalidMesh(_)));
    assert!(invalid(Mesh::new(vec![], vec![[0, 1, 2]])));
    assert!(invalid(Mesh::new(tri.clone(), vec![])));
    assert!(invalid(Mesh::new(tri.clone(), vec![[0, 1, 3]])));
    assert!(invalid(Mesh::new(tri.clone(), vec![[0, 0, 1]])), "zero-area only");
    assert!(invalid(Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], vec![[0, 1, 2]])), "collinear");
    assert!(invalid(Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, f64::NAN, 0.0]], vec![[0, 1, 2]])));
    assert!(Mesh::new(tri, vec![[0, 1, 2], [0, 0, 1]]).is_ok(), "a zero-area face among others is kept");

    let format = |r: Result<Mesh, EngineError>| matches!(r, Err(EngineError::MeshFormat { .. }));
    assert!(format(mesh::read_off("PLY\n".as_bytes())));
    assert!(format(mesh::read_off("OFF\n3 1 0\n0 0 0\n1 0 0\n".as_bytes())), "truncated");
    assert!(format(mesh::read_off("OFF\n3 1 0\n0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n".as_bytes())));
    assert!(format(mesh::read_off("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n2 0 1\n".as_bytes())));
    assert!(format(mesh::read_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n".as_bytes())));
    assert!(format(mesh::read_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n".as_bytes())));
    assert!(matches!(mesh::read_obj("".as_bytes()), Err(EngineError::InvalidMesh(_))));
}
