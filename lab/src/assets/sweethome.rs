//! Sweet Home 3D furniture libraries (`.sh3f`, Debian package `sweethome3d-furniture`): zip
//! archives of OBJ models with a catalogue (`PluginFurnitureCatalog.properties`) that names,
//! sizes and orients each piece. Chairs, sofas and dining tables come from here.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use anyhow::{Context, Result, bail};

use super::mesh::TexturedMesh;
use super::mtl::{mtllib, read_textured_obj};

pub const DEFAULT_DIR: &str = "/usr/share/sweethome3d/furniture";
const CATALOGUE: &str = "PluginFurnitureCatalog.properties";

/// One piece of a library's catalogue.
#[derive(Clone, Debug, Default)]
pub struct Piece {
    /// `<library>/<id after '#'>`, e.g. `BlendSwap-CC-0/oakTable`: the model's name in datasets.
    pub name: String,
    /// The catalogue's display name (`Oak table`).
    pub title: String,
    pub creator: String,
    /// Path of the OBJ inside the archive, without the leading `/`.
    pub model: String,
    /// Height in centimetres, as catalogued.
    pub height_cm: f64,
    /// Row-major 3×3 rotation from the file's frame to Sweet Home 3D's (y up, front towards +z).
    pub rotation: Option<[f64; 9]>,
}

/// The pieces of one `.sh3f` archive, in catalogue order.
pub fn catalogue(archive: &Path) -> Result<Vec<Piece>> {
    let library = archive.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let mut zip = open(archive)?;
    let mut bytes = Vec::new();
    zip.by_name(CATALOGUE)
        .with_context(|| format!("{} has no {CATALOGUE}", archive.display()))?
        .read_to_end(&mut bytes)?;
    // Java properties files are ISO-8859-1: each byte is its code point.
    let text: String = bytes.iter().map(|&b| b as char).collect();
    let mut pieces: BTreeMap<u32, Piece> = BTreeMap::new();
    for (key, value) in properties(&text) {
        let Some((field, n)) = key.split_once('#') else { continue };
        let Ok(n) = n.parse::<u32>() else { continue };
        let piece = pieces.entry(n).or_default();
        match field {
            "id" => piece.name = format!("{library}/{}", value.rsplit('#').next().unwrap_or(&value)),
            "name" => piece.title = value,
            "creator" => piece.creator = value,
            "height" => piece.height_cm = value.parse().unwrap_or(0.0),
            "model" => piece.model = value.trim_start_matches('/').to_string(),
            "modelRotation" => {
                let m: Vec<f64> = value.split_whitespace().filter_map(|v| v.parse().ok()).collect();
                piece.rotation = <[f64; 9]>::try_from(m).ok();
            }
            _ => {}
        }
    }
    Ok(pieces.into_values().filter(|p| !p.name.is_empty() && p.model.ends_with(".obj")).collect())
}

/// Extracts the piece's folder into `cache` once and loads it in Sweet Home 3D's frame (y up,
/// front towards +z, the catalogue's rotation applied).
pub fn load(archive: &Path, piece: &Piece, cache: &Path) -> Result<TexturedMesh> {
    let library = archive.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let folder = Path::new(&piece.model).parent().unwrap_or(Path::new(""));
    let dir = cache.join("sweethome3d").join(&library).join(folder);
    if !dir.join(".complete").is_file() {
        extract(archive, folder, &dir)?;
    }
    let obj = cache.join("sweethome3d").join(&library).join(&piece.model);
    let mtl = mtllib(&obj)?.filter(|m| m.is_file());
    let mut mesh = read_textured_obj(&obj, mtl.as_deref(), obj.parent().unwrap_or(&dir))
        .with_context(|| format!("furniture {}", piece.name))?;
    if let Some(r) = piece.rotation {
        mesh.map_positions(|p| std::array::from_fn(|i| r[3 * i] * p[0] + r[3 * i + 1] * p[1] + r[3 * i + 2] * p[2]));
    }
    Ok(mesh)
}

fn open(archive: &Path) -> Result<zip::ZipArchive<std::fs::File>> {
    let file = std::fs::File::open(archive).with_context(|| {
        format!("opening {}: run `make assets-all` (installs sweethome3d-furniture)", archive.display())
    })?;
    zip::ZipArchive::new(file).with_context(|| format!("reading {}", archive.display()))
}

/// Writes the archive's files under `folder` into `dir`, then the `.complete` mark: a crash
/// leaves no folder that looks finished.
fn extract(archive: &Path, folder: &Path, dir: &Path) -> Result<()> {
    let mut zip = open(archive)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for i in 0..zip.len() {
        let mut entry = zip.by_index(i)?;
        // `enclosed_name` refuses absolute paths and `..`: nothing is written outside `dir`.
        let Some(path) = entry.enclosed_name() else { continue };
        let Ok(relative) = path.strip_prefix(folder) else { continue };
        if entry.is_dir() || relative.as_os_str().is_empty() {
            continue;
        }
        let out = dir.join(relative);
        if let Some(parent) = out.parent() {
            std::fs::create_dir_all(parent)?;
        }
        // The header's size is not trusted for the allocation; the read grows as needed.
        let mut bytes = Vec::with_capacity(entry.size().min(1 << 26) as usize);
        entry.read_to_end(&mut bytes)?;
        std::fs::write(&out, bytes).with_context(|| format!("writing {}", out.display()))?;
    }
    if std::fs::read_dir(dir)?.next().is_none() {
        bail!("{} has no files under {}", archive.display(), folder.display());
    }
    std::fs::write(dir.join(".complete"), b"")?;
    Ok(())
}

/// `key=value` pairs of a Java properties text (comments skipped, `\uXXXX` and `\x` unescaped;
/// the catalogues use no line continuations).
fn properties(text: &str) -> impl Iterator<Item = (String, String)> + '_ {
    text.lines().filter_map(|line| {
        let line = line.trim_start();
        if line.starts_with('#') || line.starts_with('!') {
            return None;
        }
        let (key, value) = line.split_once('=')?;
        Some((key.trim().to_string(), unescape(value.trim())))
    })
}

fn unescape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut chars = s.chars();
    while let Some(c) = chars.next() {
        if c != '\\' {
            out.push(c);
            continue;
        }
        match chars.next() {
            Some('u') => {
                let hex: String = chars.by_ref().take(4).collect();
                out.extend(u32::from_str_radix(&hex, 16).ok().and_then(char::from_u32));
            }
            Some(other) => out.push(other),
            None => {}
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;

    /// A library of two pieces, one rotated, with a texture that is missing (colour kept) and a
    /// file that tries to escape the cache.
    fn library(dir: &Path) -> std::path::PathBuf {
        let path = dir.join("Lib.sh3f");
        let mut zip = zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
        let options = zip::write::SimpleFileOptions::default();
        let catalogue = "id#1=Lib#chairA\nname#1=Chair\nmodel#1=/lib/chairA/chairA.obj\nheight#1=80\n\
                         modelRotation#1=0 0 1 0 1 0 -1 0 0\n\
                         id#2=Lib#tableB\nname#2=Table\nmodel#2=/lib/tableB/tableB.obj\nheight#2=75\n\
                         id#3=Lib#icon\nname#3=Icon\nmodel#3=/lib/icon.png\n";
        let files: [(&str, &str); 4] = [
            (CATALOGUE, catalogue),
            ("lib/chairA/chairA.obj", "mtllib chairA.mtl\nv 1 0 0\nv 0 1 0\nv 0 0 1\nusemtl red\nf 1 2 3\n"),
            ("lib/chairA/chairA.mtl", "newmtl red\nKd 1 0 0\nmap_Kd missing.png\n"),
            ("lib/tableB/tableB.obj", "v 0 0 0\nv 2 0 0\nv 0 0 2\nf 1 2 3\n"),
        ];
        for (name, text) in files {
            zip.start_file(name, options).unwrap();
            zip.write_all(text.as_bytes()).unwrap();
        }
        zip.start_file("../escape.txt", options).unwrap();
        zip.finish().unwrap();
        path
    }

    #[test]
    fn pieces_are_listed_extracted_and_rotated() {
        let dir = std::env::temp_dir().join(format!("udapose-sh3f-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let archive = library(&dir);
        let pieces = catalogue(&archive).unwrap();
        let names: Vec<&str> = pieces.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["Lib/chairA", "Lib/tableB"], "entries without an OBJ model are skipped");
        assert_eq!(pieces[0].height_cm, 80.0);

        let cache = dir.join("cache");
        let chair = load(&archive, &pieces[0], &cache).unwrap();
        // The rotation maps (x, y, z) to (z, y, −x).
        assert_eq!(chair.positions, vec![[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]);
        assert_eq!(chair.textures[chair.face_texture[0] as usize].texels, vec![[1.0, 0.0, 0.0]]);
        assert!(cache.join("sweethome3d/Lib/lib/chairA/.complete").is_file());
        assert!(!cache.join("sweethome3d/Lib/lib/tableB").exists(), "only the piece's folder is extracted");
        assert!(!dir.join("escape.txt").exists() && !cache.join("escape.txt").exists());
        let table = load(&archive, &pieces[1], &cache).unwrap();
        assert_eq!(table.positions[1], [2.0, 0.0, 0.0]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn properties_are_unescaped() {
        let text = "# comment\nname#3=Caf\\u00e9 chair\nid#3=Lib\\#cafe\nmodelRotation#3=0 0 1 0 1 0 -1 0 0\n";
        let p: Vec<_> = properties(text).collect();
        assert_eq!(p[0], ("name#3".into(), "Café chair".into()));
        assert_eq!(p[1], ("id#3".into(), "Lib#cafe".into()));
    }
}
