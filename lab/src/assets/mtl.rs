//! Wavefront materials (`.mtl`) and the OBJ files that use them: each material's diffuse texture
//! or colour, which is all the benchmark renderer draws (no transparency, no specular).

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, Result};

use super::mesh::{Texture, TexturedMesh};

/// The grey of faces with no material (OBJ's default diffuse colour).
const DEFAULT_GREY: [f32; 3] = [0.8, 0.8, 0.8];

/// The textures of a material library and which material uses which; texture 0 is the default
/// grey.
pub struct Materials {
    pub textures: Vec<Texture>,
    names: HashMap<String, u16>,
}

impl Materials {
    /// Parses `text`; `map_Kd` files are read from `texture_dir`. A material whose texture is
    /// missing or unreadable keeps its colour (some packaged models name textures they do not
    /// ship), and the file is reported once on stderr.
    pub fn parse(text: &str, texture_dir: &Path) -> Self {
        let mut materials = Materials { textures: vec![Texture::solid(DEFAULT_GREY)], names: HashMap::new() };
        let mut loaded: HashMap<String, Option<u16>> = HashMap::new();
        let mut current: Option<(String, [f32; 3], Option<String>)> = None;
        for line in text.lines().chain(std::iter::once("newmtl")) {
            let mut t = line.split_whitespace();
            match t.next() {
                Some("newmtl") => {
                    if let Some((name, colour, map)) = current.take() {
                        let texture = map.and_then(|file| materials.texture(&mut loaded, texture_dir, &file));
                        let index = texture.unwrap_or_else(|| materials.push(Texture::solid(colour)));
                        // Duplicate names (assimp writes some): the first definition wins.
                        materials.names.entry(name).or_insert(index);
                    }
                    current = t.next().map(|name| (name.to_string(), DEFAULT_GREY, None));
                }
                Some("Kd") => {
                    let rgb: Vec<f32> = t.filter_map(|v| v.parse().ok()).collect();
                    if let (Some(m), &[r, g, b]) = (current.as_mut(), &rgb[..]) {
                        m.1 = [r, g, b].map(|c| c.clamp(0.0, 1.0));
                    }
                }
                // Options such as `-s 1 1 1` come first: the file name is the last word.
                Some("map_Kd") => {
                    if let (Some(m), Some(file)) = (current.as_mut(), t.next_back()) {
                        m.2 = Some(file.to_string());
                    }
                }
                _ => {}
            }
        }
        materials
    }

    /// The texture index of material `name`.
    pub fn index(&self, name: &str) -> Option<u16> {
        self.names.get(name).copied()
    }

    fn push(&mut self, texture: Texture) -> u16 {
        self.textures.push(texture);
        (self.textures.len() - 1) as u16
    }

    /// The index of texture `file`, loaded once per library; `None` if it cannot be read.
    fn texture(&mut self, loaded: &mut HashMap<String, Option<u16>>, dir: &Path, file: &str) -> Option<u16> {
        if let Some(&index) = loaded.get(file) {
            return index;
        }
        let index = match Texture::load(&dir.join(file)) {
            Ok(texture) => Some(self.push(texture)),
            Err(e) => {
                eprintln!("warning: {e:#}; the material keeps its colour");
                None
            }
        };
        loaded.insert(file.to_string(), index);
        index
    }
}

/// Reads an OBJ file with the material library `mtl` (if any), textures from `texture_dir`.
pub fn read_textured_obj(obj: &Path, mtl: Option<&Path>, texture_dir: &Path) -> Result<TexturedMesh> {
    let text = std::fs::read_to_string(obj).with_context(|| format!("reading {}", obj.display()))?;
    let materials = match mtl {
        Some(mtl) => {
            let lib = std::fs::read_to_string(mtl).with_context(|| format!("reading {}", mtl.display()))?;
            Materials::parse(&lib, texture_dir)
        }
        None => Materials::parse("", texture_dir),
    };
    let Materials { textures, names } = materials;
    TexturedMesh::read_obj_with(&text, textures, |name| names.get(name).copied())
        .with_context(|| format!("reading {}", obj.display()))
}

/// The `mtllib` an OBJ file names, resolved next to it.
pub fn mtllib(obj: &Path) -> Result<Option<std::path::PathBuf>> {
    let text = std::fs::read_to_string(obj).with_context(|| format!("reading {}", obj.display()))?;
    let name = text.lines().find_map(|l| l.strip_prefix("mtllib ")).map(str::trim);
    Ok(name.map(|n| obj.parent().unwrap_or(Path::new(".")).join(n)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn materials_pick_colours_per_face() {
        let mtl = "newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\nmap_Kd -s 1 1 1 missing.png\nnewmtl red\nKd 0 1 0\n";
        let m = Materials::parse(mtl, Path::new("/nonexistent"));
        let colour = |name: &str| m.textures[m.index(name).unwrap() as usize].texels[0];
        assert_eq!(colour("red"), [1.0, 0.0, 0.0], "the first of two definitions wins");
        assert_eq!(colour("blue"), [0.0, 0.0, 1.0], "a missing texture falls back to the colour");
        assert_eq!(m.index("green"), None);

        let obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nusemtl blue\nf 1 2 3\nusemtl nope\nf 1 2 3\n";
        let mesh = TexturedMesh::read_obj_with(obj, m.textures.clone(), |n| m.index(n)).unwrap();
        assert_eq!(mesh.face_texture, vec![0, m.index("blue").unwrap(), 0]);
    }
}
