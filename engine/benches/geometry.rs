//! `cargo bench -p udapose-engine`: projection, rasterisation and visibility of the car cuboid.
//! Prints a table and writes `reports/geometry.md` and `reports/geometry.json` with the machine
//! and commit. Times are medians over repeated batches (machines are noisy: compare ratios).

mod common;

use std::hint::black_box;

use common::time;

use rayon::prelude::*;
use udapose_engine::mesh::TARGET_VERTICES;
use udapose_engine::{Camera, Cuboid, Mesh, Pose, Rasterizer, View};

/// Poses spread over the view sphere, at distances where the car fills a detection crop.
fn poses(n: usize) -> Vec<Pose> {
    (0..n)
        .map(|i| {
            let t = i as f64;
            Pose::new(
                t * 0.7 % std::f64::consts::TAU,
                (t * 0.37 % 1.4) - 0.4,
                (t * 0.23 % 0.8) - 0.4,
                4.5 + t * 0.31 % 3.0,
            )
        })
        .collect()
}

struct Row {
    name: String,
    median_us: f64,
    min_us: f64,
    max_us: f64,
}

fn main() {
    let cuboid = Cuboid::from_dimensions([0.433, 0.992, 0.270]).unwrap();
    let mesh = cuboid.mesh(TARGET_VERTICES);
    let poses = poses(64);
    let mut rows = Vec::new();
    let mut bench = |name: String, f: &mut dyn FnMut(usize)| {
        let (median_us, min_us, max_us) = time(f);
        println!("{name:<58} {median_us:>10.2} µs  (min {min_us:.2}, max {max_us:.2})");
        rows.push(Row { name, median_us, min_us, max_us });
    };

    let grids = [("16×40 (128×320 crop, stride 8)", 128, 320), ("32×84 (256×672 crop, stride 8)", 256, 672)];
    for (label, h, w) in grids {
        let cam = Camera::for_crop(h, w).unwrap().at_stride(8).unwrap();
        let mut out = [0.0f64; 3];
        bench(format!("project {} vertices, {label}", mesh.vertices().len()), &mut |i| {
            let view = View::new(&cam, &poses[i % poses.len()]).unwrap();
            for &v in mesh.vertices() {
                out = view.project(black_box(v));
            }
            black_box(out);
        });
        let mut r = Rasterizer::new();
        bench(format!("render_faces (project + raster), {label}"), &mut |i| {
            black_box(r.render_faces(&mesh, &cam, &poses[i % poses.len()]).unwrap().face.len());
        });
        bench(format!("render (project + raster + visibility), {label}"), &mut |i| {
            black_box(r.render(&mesh, &cam, &poses[i % poses.len()]).unwrap().visible.len());
        });
        bench(format!("144 poses, rayon over poses, {label}"), &mut |i| {
            let n: usize = (0..144)
                .into_par_iter()
                .map_init(Rasterizer::new, |r, k| {
                    r.render(&mesh, &cam, &poses[(i + k) % poses.len()]).unwrap().visible.iter().filter(|&&v| v).count()
                })
                .sum();
            black_box(n);
        });
    }
    for (label, h, w) in [("128×320", 128, 320), ("256×672", 256, 672)] {
        let cam = Camera::for_crop(h, w).unwrap();
        for (mode, threshold) in [("serial", usize::MAX), ("row bands", 0)] {
            let mut r = Rasterizer::with_parallel_threshold(threshold);
            bench(format!("render full-resolution {label}, {mode}"), &mut |i| {
                black_box(r.render(&mesh, &cam, &poses[i % poses.len()]).unwrap().visible.len());
            });
        }
    }
    write_report(&mesh, &rows, &grids.map(|g| g.0));
}

fn write_report(mesh: &Mesh, rows: &[Row], grids: &[&str]) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let commit = std::process::Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .current_dir(&root)
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map_or_else(|| "uncommitted".into(), |o| String::from_utf8_lossy(&o.stdout).trim().to_string());
    let dirty = std::process::Command::new("git")
        .args(["status", "--porcelain", "--untracked-files=no"])
        .current_dir(&root)
        .output()
        .is_ok_and(|o| !o.stdout.is_empty());
    let commit = if dirty { format!("{commit}+dirty") } else { commit };
    let cpu = udapose_engine::runtime::cpu_model();
    let threads = rayon::current_num_threads();
    let mut md = format!(
        "# Geometry benchmark\n\nProduced by `cargo bench -p udapose-engine` (release, {threads} rayon threads) on {cpu}, commit `{commit}`.\n\
         Car cuboid 0.433 × 0.992 × 0.270: {} vertices, {} triangles. Median of 15 batches; min and max show the noise.\n\n\
         | case | median µs | min µs | max µs |\n|---|---:|---:|---:|\n",
        mesh.vertices().len(),
        mesh.faces().len()
    );
    for r in rows {
        md.push_str(&format!("| {} | {:.2} | {:.2} | {:.2} |\n", r.name, r.median_us, r.min_us, r.max_us));
    }
    let median = |name: &str| rows.iter().find(|r| r.name == name).map(|r| r.median_us);
    let mut ratios = String::new();
    for label in ["128×320", "256×672"] {
        if let (Some(s), Some(p)) = (
            median(&format!("render full-resolution {label}, serial")),
            median(&format!("render full-resolution {label}, row bands")),
        ) {
            ratios.push_str(&format!("- full-resolution {label}: row bands are {:.2}× the speed of serial\n", s / p));
        }
    }
    for label in grids {
        if let (Some(one), Some(batch)) = (
            median(&format!("render (project + raster + visibility), {label}")),
            median(&format!("144 poses, rayon over poses, {label}")),
        ) {
            ratios.push_str(&format!(
                "- {label}: 144 poses over rayon take {:.1} µs per pose, {:.2}× the throughput of one at a time\n",
                batch / 144.0,
                one * 144.0 / batch
            ));
        }
    }
    md.push_str(&format!("\nSame-run ratios:\n\n{ratios}"));
    let json = serde_json::json!({
        "command": "cargo bench -p udapose-engine",
        "commit": commit,
        "cpu": cpu,
        "rayon_threads": threads,
        "vertices": mesh.vertices().len(),
        "triangles": mesh.faces().len(),
        "cases": rows.iter().map(|r| serde_json::json!({"name": r.name, "median_us": r.median_us, "min_us": r.min_us, "max_us": r.max_us})).collect::<Vec<_>>(),
    });
    let dir = root.join("reports");
    std::fs::create_dir_all(&dir).expect("create reports/");
    std::fs::write(dir.join("geometry.md"), md).expect("write reports/geometry.md");
    std::fs::write(dir.join("geometry.json"), serde_json::to_string_pretty(&json).unwrap() + "\n")
        .expect("write reports/geometry.json");
    println!("wrote reports/geometry.md and reports/geometry.json");
}
