//! The benchmark renderer: a textured car, Lambertian + ambient light, supersampled, composited
//! over a background; the engine's rasteriser does the visibility.

use anyhow::{Context, Result};
use image::RgbImage;
use udapose_engine::{Camera, Mesh, Pose, Rasterizer, raster::NO_FACE};

use crate::assets::mesh::{Texture, TexturedMesh};

/// A textured mesh ready for the rasteriser, with its face normals.
pub struct Model {
    pub textured: TexturedMesh,
    pub mesh: Mesh,
    normals: Vec<[f64; 3]>,
}

impl Model {
    pub fn new(textured: TexturedMesh) -> Result<Self> {
        let mesh = Mesh::new(textured.positions.clone(), textured.faces.clone()).context("car mesh")?;
        let normals = textured.faces.iter().map(|f| face_normal(f.map(|i| textured.positions[i as usize]))).collect();
        Ok(Model { textured, mesh, normals })
    }
}

fn face_normal([a, b, c]: [[f64; 3]; 3]) -> [f64; 3] {
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-300);
    n.map(|x| x / len)
}

/// Directional light in the object frame (unit vector towards the light) plus ambient.
#[derive(Clone, Copy, Debug)]
pub struct Light {
    pub direction: [f64; 3],
    pub ambient: f32,
    pub diffuse: f32,
}

/// A rendered object: premultiplied colour and coverage per pixel, both in [0, 1].
pub struct Layer {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<[f32; 3]>,
    pub coverage: Vec<f32>,
}

impl Layer {
    /// The object over `background` (same size), and its mask: 1 where it covers at least half
    /// of the pixel.
    pub fn composite(&self, background: &RgbImage) -> (RgbImage, Vec<u8>) {
        let out = RgbImage::from_fn(self.width as u32, self.height as u32, |x, y| {
            let i = y as usize * self.width + x as usize;
            let bg = background.get_pixel(x, y).0;
            let a = self.coverage[i];
            image::Rgb(std::array::from_fn(|k| to_u8(self.rgb[i][k] + (1.0 - a) * bg[k] as f32 / 255.0)))
        });
        (out, self.coverage.iter().map(|&a| u8::from(a >= 0.5)).collect())
    }
}

fn to_u8(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}

/// Renders with `supersample`² samples per pixel; reuses its buffers across calls.
pub struct Renderer {
    supersample: usize,
    raster: Rasterizer,
}

impl Renderer {
    pub fn new(supersample: usize) -> Self {
        Renderer { supersample: supersample.max(1), raster: Rasterizer::new() }
    }

    /// Renders `model` at `height × width`; `textures` replaces the model's own when given.
    pub fn render(
        &mut self,
        model: &Model,
        textures: Option<&[Texture]>,
        pose: &Pose,
        height: usize,
        width: usize,
        light: &Light,
    ) -> Result<Layer> {
        let textures = textures.unwrap_or(&model.textured.textures);
        let s = self.supersample;
        let camera = Camera::for_crop(height * s, width * s)?;
        let eye = pose.camera_centre();
        let frags = self.raster.render_faces(&model.mesh, &camera, pose)?;
        let mut layer =
            Layer { width, height, rgb: vec![[0.0; 3]; width * height], coverage: vec![0.0; width * height] };
        let weight = 1.0 / (s * s) as f32;
        for (p, &f) in frags.face.iter().enumerate() {
            if f == NO_FACE {
                continue;
            }
            let (row, col) = (p / camera.width, p % camera.width);
            let out = (row / s) * width + col / s;
            let colour = shade(model, textures, f as usize, frags.barycentric[p], [eye.x, eye.y, eye.z], light);
            layer.coverage[out] += weight;
            (0..3).for_each(|k| layer.rgb[out][k] += weight * colour[k]);
        }
        Ok(layer)
    }
}

/// Texture colour times Lambertian + ambient light; normals are turned towards the camera since
/// CAD meshes are not consistently wound.
fn shade(model: &Model, textures: &[Texture], f: usize, bary: [f32; 3], eye: [f64; 3], light: &Light) -> [f32; 3] {
    let t = &model.textured;
    let uv = t.uvs[f];
    let u = bary[0] * uv[0][0] + bary[1] * uv[1][0] + bary[2] * uv[2][0];
    let v = bary[0] * uv[0][1] + bary[1] * uv[1][1] + bary[2] * uv[2][1];
    let texel = textures[t.face_texture[f] as usize].sample(u, v);
    let n = model.normals[f];
    let a = t.positions[t.faces[f][0] as usize];
    let towards_eye = (0..3).map(|k| n[k] * (eye[k] - a[k])).sum::<f64>();
    let sign = if towards_eye < 0.0 { -1.0 } else { 1.0 };
    let lambert = (0..3).map(|k| sign * n[k] * light.direction[k]).sum::<f64>().max(0.0) as f32;
    let intensity = light.ambient + light.diffuse * lambert;
    texel.map(|c| (c * intensity).min(1.0))
}
