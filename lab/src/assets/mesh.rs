//! Textured triangle meshes: what the benchmark renderer draws.

use std::path::Path;

use anyhow::{Context, Result, bail};
use image::RgbImage;

/// An RGB texture in linear [0, 1] floats, sampled bilinearly with wrap-around.
#[derive(Clone, Debug)]
pub struct Texture {
    pub width: usize,
    pub height: usize,
    pub texels: Vec<[f32; 3]>,
}

impl Texture {
    pub fn from_image(img: &RgbImage) -> Self {
        let texels = img.pixels().map(|p| p.0.map(|c| c as f32 / 255.0)).collect();
        Texture { width: img.width() as usize, height: img.height() as usize, texels }
    }

    pub fn solid(rgb: [f32; 3]) -> Self {
        Texture { width: 1, height: 1, texels: vec![rgb] }
    }

    /// Loads an SGI (`.rgb`, `.rgba`, `.bw`) or PNG/JPEG texture.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading texture {}", path.display()))?;
        let img = match super::sgi::decode(&bytes) {
            Ok(img) => img,
            Err(super::sgi::SgiError::Magic(_)) => {
                image::load_from_memory(&bytes).with_context(|| format!("decoding {}", path.display()))?.to_rgb8()
            }
            Err(e) => bail!("decoding {}: {e}", path.display()),
        };
        Ok(Texture::from_image(&img))
    }

    /// Bilinear sample at texture coordinates (OBJ convention: v = 0 is the bottom row).
    pub fn sample(&self, u: f32, v: f32) -> [f32; 3] {
        let x = u.rem_euclid(1.0) * self.width as f32 - 0.5;
        let y = (1.0 - v.rem_euclid(1.0)) * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let wrap = |i: f32, n: usize| (i as i64).rem_euclid(n as i64) as usize;
        let at = |xi: f32, yi: f32| self.texels[wrap(yi, self.height) * self.width + wrap(xi, self.width)];
        let (a, b, c, d) = (at(x0, y0), at(x0 + 1.0, y0), at(x0, y0 + 1.0), at(x0 + 1.0, y0 + 1.0));
        std::array::from_fn(|k| (a[k] * (1.0 - fx) + b[k] * fx) * (1.0 - fy) + (c[k] * (1.0 - fx) + d[k] * fx) * fy)
    }
}

/// Triangles with per-corner texture coordinates and a texture per face.
#[derive(Clone, Debug, Default)]
pub struct TexturedMesh {
    pub positions: Vec<[f64; 3]>,
    pub faces: Vec<[u32; 3]>,
    pub uvs: Vec<[[f32; 2]; 3]>,
    pub face_texture: Vec<u16>,
    pub textures: Vec<Texture>,
}

impl TexturedMesh {
    /// Adds `other`'s triangles and textures.
    pub fn append(&mut self, other: TexturedMesh) {
        let (base, tex_base) = (self.positions.len() as u32, self.textures.len() as u16);
        self.positions.extend(other.positions);
        self.faces.extend(other.faces.iter().map(|f| f.map(|i| i + base)));
        self.uvs.extend(other.uvs);
        self.face_texture.extend(other.face_texture.iter().map(|t| t + tex_base));
        self.textures.extend(other.textures);
    }

    pub fn map_positions(&mut self, f: impl Fn([f64; 3]) -> [f64; 3]) {
        self.positions.iter_mut().for_each(|p| *p = f(*p));
    }

    /// Per-axis minimum and maximum of the vertices.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        self.positions.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(lo, hi), p| {
            (std::array::from_fn(|a| lo[a].min(p[a])), std::array::from_fn(|a| hi[a].max(p[a])))
        })
    }

    /// Reads an OBJ file whose faces all use one texture, `texture` (TORCS cars and wheels have
    /// one each); polygons are split into fans.
    pub fn read_obj(obj: &str, texture: Texture) -> Result<Self> {
        Self::read_obj_with(obj, vec![texture], |_| None)
    }

    /// Reads an OBJ file whose faces pick their texture by material: `material(name)` is the
    /// index into `textures` of a `usemtl` name; faces before any `usemtl`, or under a name it
    /// does not know, use texture 0.
    pub fn read_obj_with(obj: &str, textures: Vec<Texture>, material: impl Fn(&str) -> Option<u16>) -> Result<Self> {
        let (mut positions, mut tex_coords) = (Vec::new(), Vec::new());
        let mut mesh = TexturedMesh { textures, ..Default::default() };
        let mut current = 0u16;
        for (n, line) in obj.lines().enumerate() {
            let mut t = line.split_whitespace();
            let nums = |t: std::str::SplitWhitespace, k: usize| -> Result<Vec<f64>> {
                let v: Vec<f64> = t
                    .take(k)
                    .map(str::parse)
                    .collect::<Result<_, _>>()
                    .with_context(|| format!("OBJ line {}", n + 1))?;
                if v.len() < k {
                    bail!("OBJ line {}: expected {k} numbers", n + 1)
                }
                Ok(v)
            };
            match t.next() {
                Some("v") => positions.push(<[f64; 3]>::try_from(nums(t, 3)?).expect("3 numbers")),
                Some("vt") => tex_coords.push(<[f64; 2]>::try_from(nums(t, 2)?).expect("2 numbers").map(|c| c as f32)),
                Some("f") => {
                    let corners: Vec<(u32, [f32; 2])> = t
                        .map(|c| corner(c, &positions, &tex_coords))
                        .collect::<Option<_>>()
                        .with_context(|| format!("OBJ line {}: bad face {line:?}", n + 1))?;
                    for k in 1..corners.len().saturating_sub(1) {
                        let tri = [corners[0], corners[k], corners[k + 1]];
                        mesh.faces.push(tri.map(|c| c.0));
                        mesh.uvs.push(tri.map(|c| c.1));
                        mesh.face_texture.push(current);
                    }
                }
                Some("usemtl") => current = t.next().and_then(&material).unwrap_or(0),
                _ => {}
            }
        }
        if mesh.faces.is_empty() {
            bail!("OBJ has no faces");
        }
        mesh.positions = positions;
        Ok(mesh)
    }
}

/// One `v/vt/vn` face corner (1-based indices; texture coordinates optional).
fn corner(c: &str, positions: &[[f64; 3]], tex_coords: &[[f32; 2]]) -> Option<(u32, [f32; 2])> {
    let mut parts = c.split('/');
    let v: usize = parts.next()?.parse().ok()?;
    (1..=positions.len()).contains(&v).then_some(())?;
    let uv = match parts.next().filter(|s| !s.is_empty()) {
        Some(t) => *tex_coords.get(t.parse::<usize>().ok()?.checked_sub(1)?)?,
        None => [0.0, 0.0],
    };
    Some((v as u32 - 1, uv))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_with_uvs_and_quads() {
        let obj =
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\n";
        let m = TexturedMesh::read_obj(obj, Texture::solid([1.0; 3])).unwrap();
        assert_eq!(m.faces, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(m.uvs[1], [[0.0, 0.0], [1.0, 1.0], [0.0, 1.0]]);
        assert!(TexturedMesh::read_obj("v 0 0 0\nf 1 2 3\n", Texture::solid([1.0; 3])).is_err());
    }

    #[test]
    fn bilinear_sampling_wraps() {
        let img = RgbImage::from_fn(2, 1, |x, _| image::Rgb(if x == 0 { [0, 0, 0] } else { [255, 255, 255] }));
        let t = Texture::from_image(&img);
        assert_eq!(t.sample(0.25, 0.5), [0.0; 3]); // centre of texel 0
        assert_eq!(t.sample(0.5, 0.5), [0.5; 3]); // halfway between the texels
        assert_eq!(t.sample(1.25, 0.5), t.sample(0.25, 0.5));
    }
}
