//! TORCS cars as benchmark objects: body + four wheels, in the canonical frame of BENCHMARK.md
//! §2 (z up, front facing −y, centred on the bounding box, length 1).

use std::f64::consts::TAU;

use anyhow::{Context, Result};

use super::Assets;
use super::mesh::{Texture, TexturedMesh};
use super::params::Params;

/// A car ready to render, and its size before normalisation.
pub struct Car {
    pub name: String,
    pub mesh: TexturedMesh,
    /// Length in metres of the body with wheels (the unit of the canonical frame).
    pub length_m: f64,
}

/// The four wheels: (params section, axle section, on the car's left).
const WHEELS: [(&str, &str, bool); 4] = [
    ("Front Right Wheel", "Front Axle", false),
    ("Front Left Wheel", "Front Axle", true),
    ("Rear Right Wheel", "Rear Axle", false),
    ("Rear Left Wheel", "Rear Axle", true),
];

/// A wheel's placement in the exported OBJ frame (x forward, y up, z to the car's right).
struct Wheel {
    centre: [f64; 3],
    radius: f64,
    width: f64,
    left: bool,
}

impl Car {
    pub fn load(assets: &Assets, name: &str) -> Result<Car> {
        let dir = assets.car_dir(name);
        let obj = std::fs::read_to_string(assets.obj(&dir.join(format!("{name}.acc")))?)?;
        let params = Params::parse(&std::fs::read_to_string(dir.join(format!("{name}.xml")))?)
            .with_context(|| format!("reading {name}.xml"))?;
        let texture = Texture::load(&dir.join(format!("{name}.rgb")))?;
        let mut mesh = TexturedMesh::read_obj(&obj, texture).with_context(|| format!("car {name}"))?;
        let (lo, _) = mesh.bounds();
        for wheel in wheels(&params, lo[1])? {
            mesh.append(wheel_mesh(assets, &params, &dir, &wheel)?);
        }
        // OBJ (x forward, y up, z right) → canonical (x left, y backward, z up).
        mesh.map_positions(|[x, y, z]| [-z, -x, y]);
        let length_m = normalise(&mut mesh);
        Ok(Car { name: name.into(), mesh, length_m })
    }
}

/// Centres the mesh on its bounding box and scales its length (y extent) to 1.
fn normalise(mesh: &mut TexturedMesh) -> f64 {
    let (lo, hi) = mesh.bounds();
    let centre: [f64; 3] = std::array::from_fn(|a| (lo[a] + hi[a]) / 2.0);
    let length = hi[1] - lo[1];
    mesh.map_positions(|p| std::array::from_fn(|a| (p[a] - centre[a]) / length));
    length
}

/// Wheel placement from the car's parameters; the ground is the body's lowest point minus the
/// ride height.
fn wheels(params: &Params, body_bottom: f64) -> Result<Vec<Wheel>> {
    WHEELS
        .iter()
        .map(|&(section, axle, left)| {
            let n = |key: &str| params.length(&format!("{section}/{key}"));
            let ratio = params.ratio(&format!("{section}/tire height-width ratio"))?;
            let radius = n("rim diameter")? / 2.0 + n("tire width")? * ratio;
            let ground = body_bottom - n("ride height")?;
            let x = params.length(&format!("{axle}/xpos"))?;
            Ok(Wheel { centre: [x, ground + radius, -n("ypos")?], radius, width: n("tire width")?, left })
        })
        .collect()
}

/// The car's 3-D wheel model where its parameters name one, else a procedural one; either way
/// its axle along z with the rim facing outwards.
fn wheel_mesh(assets: &Assets, params: &Params, car_dir: &std::path::Path, wheel: &Wheel) -> Result<TexturedMesh> {
    let mut mesh = match params.string("Graphic Objects/3d wheel directory") {
        Some(dir) => {
            let dir = assets.wheel_dir(dir);
            let obj = std::fs::read_to_string(assets.obj(&dir.join("wheel0.acc"))?)?;
            // The model is a unit-diameter, unit-width wheel whose rim faces −z.
            TexturedMesh::read_obj(&obj, Texture::load(&dir.join("wheel3d.png"))?)?
        }
        None => {
            let texture = params.string("Graphic Objects/wheel texture").unwrap_or("tex-wheel.rgb");
            procedural_wheel(Texture::load(&car_dir.join(texture))?)
        }
    };
    // Left wheels face −z (outwards); right ones are mirrored to face +z.
    let side = if wheel.left { 1.0 } else { -1.0 };
    let (d, w, c) = (2.0 * wheel.radius, wheel.width, wheel.centre);
    mesh.map_positions(|[x, y, z]| [c[0] + x * d, c[1] + y * d, c[2] + side * z * w]);
    Ok(mesh)
}

/// A tyre (dark cylinder) with the wheel texture on the outer (−z) disc, unit diameter and width.
/// TORCS wheel textures hold four wheel images (speed variants): the disc shows the top-left one.
fn procedural_wheel(rim: Texture) -> TexturedMesh {
    const N: usize = 24;
    let ring = |z: f64| {
        (0..N).map(move |i| {
            let a = TAU * i as f64 / N as f64;
            [0.5 * a.cos(), 0.5 * a.sin(), z]
        })
    };
    let mut m = TexturedMesh { textures: vec![Texture::solid([0.05, 0.05, 0.05]), rim], ..Default::default() };
    m.positions.extend(ring(-0.5).chain(ring(0.5)));
    m.positions.push([0.0, 0.0, -0.5]);
    let hub = (2 * N) as u32;
    for i in 0..N as u32 {
        let j = (i + 1) % N as u32;
        let n = N as u32;
        m.faces.extend([[i, j, j + n], [i, j + n, i + n]]);
        m.uvs.extend([[[0.0; 2]; 3]; 2]);
        m.face_texture.extend([0, 0]);
        m.faces.push([hub, j, i]);
        let uv = |k: u32| {
            let a = TAU * k as f64 / N as f64;
            [(0.25 + 0.25 * a.cos()) as f32, (0.75 + 0.25 * a.sin()) as f32]
        };
        m.uvs.push([[0.25, 0.75], uv(j), uv(i)]);
        m.face_texture.push(1);
    }
    m
}
