//! FlightGear scenery models (Debian package `flightgear-data-base`): AC3D aircraft and buses,
//! converted to OBJ by `assimp` as the TORCS cars are. Aeroplanes and buses come from here.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

use super::Assets;
use super::mesh::TexturedMesh;
use super::mtl::read_textured_obj;

pub const DEFAULT_DIR: &str = "/usr/share/games/flightgear";

/// Where a model's front points in its AC3D file (y is up in all of them). Read off the
/// orientation sheets (`udapose-lab synth --category … --preview --orientation`), one model at a
/// time: the files follow no single convention (aircraft noses point along −x, −z or +x).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Front {
    NegX,
    PosX,
    NegZ,
    PosZ,
}

impl Front {
    /// The unit vector of the front in the file's frame.
    pub fn vector(self) -> [f64; 3] {
        match self {
            Front::NegX => [-1.0, 0.0, 0.0],
            Front::PosX => [1.0, 0.0, 0.0],
            Front::NegZ => [0.0, 0.0, -1.0],
            Front::PosZ => [0.0, 0.0, 1.0],
        }
    }
}

/// A model file under `Scenery/Models/` (without `.ac`) and its front.
#[derive(Clone, Copy, Debug)]
pub struct Model {
    pub file: &'static str,
    pub front: Front,
}

impl Model {
    /// The name a dataset records: the file's stem.
    pub fn name(&self) -> &'static str {
        self.file.rsplit('/').next().unwrap_or(self.file)
    }
}

/// The model's AC3D file, with a clear error when the package is missing.
pub fn ac_path(root: &Path, model: &Model) -> Result<PathBuf> {
    let path = root.join("Scenery/Models").join(format!("{}.ac", model.file));
    if !path.is_file() {
        bail!("{} not found: run `make assets-all` (installs flightgear-data-base)", path.display());
    }
    Ok(path)
}

/// Loads a model in its file's frame, textures from the file's folder.
pub fn load(assets: &Assets, root: &Path, model: &Model) -> Result<TexturedMesh> {
    let ac = ac_path(root, model)?;
    let obj = assets.obj(&ac)?;
    let mtl = obj.with_extension("mtl");
    read_textured_obj(&obj, mtl.is_file().then_some(mtl.as_path()), ac.parent().unwrap_or(root))
}
