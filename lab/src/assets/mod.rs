//! The benchmark's raw material: TORCS cars and track photographs (Debian packages
//! `torcs-data` and `assimp-utils`, installed by `make assets`), and the other categories'
//! models: FlightGear aircraft and buses, Sweet Home 3D furniture (`make assets-all`).

pub mod backgrounds;
pub mod car;
pub mod category;
pub mod flightgear;
pub mod mesh;
pub mod mtl;
pub mod params;
pub mod sgi;
pub mod sweethome;

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

/// Cars of the source domain (BENCHMARK.md §3).
pub const SOURCE_CARS: [&str; 11] = [
    "155-DTM",
    "car1-stock1",
    "car1-trb1",
    "car1-trb3",
    "car2-trb1",
    "car3-trb1",
    "car4-trb1",
    "car5-trb1",
    "car6-trb1",
    "car8-trb1",
    "p406",
];
/// Cars of the `shape` domain, never seen in training.
pub const SHAPE_CARS: [&str; 6] = ["acura-nsx-sz", "baja-bug", "buggy", "car1-ow1", "car1-stock2", "car7-trb1"];

pub const DEFAULT_TORCS_DIR: &str = "/usr/share/games/torcs";
const INSTALL_HINT: &str = "run `make assets` (installs the Debian packages torcs-data and assimp-utils)";

/// Where the assets are, and where converted meshes are cached.
#[derive(Clone, Debug)]
pub struct Assets {
    pub torcs: PathBuf,
    /// FlightGear's data (aeroplanes, buses); checked when a model is loaded.
    pub flightgear: PathBuf,
    /// The Sweet Home 3D furniture libraries (chairs, sofas, dining tables); checked likewise.
    pub sweethome: PathBuf,
    pub cache: PathBuf,
}

impl Assets {
    /// Checks that the TORCS data and the converter are there, with a clear error if not.
    pub fn open(torcs: &Path, cache: &Path) -> Result<Self> {
        if !torcs.join("cars").is_dir() || !torcs.join("tracks").is_dir() {
            bail!("TORCS data not found under {}: {INSTALL_HINT}", torcs.display());
        }
        std::fs::create_dir_all(cache).with_context(|| format!("creating {}", cache.display()))?;
        Ok(Assets {
            torcs: torcs.to_path_buf(),
            flightgear: flightgear::DEFAULT_DIR.into(),
            sweethome: sweethome::DEFAULT_DIR.into(),
            cache: cache.to_path_buf(),
        })
    }

    pub fn car_dir(&self, name: &str) -> PathBuf {
        self.torcs.join("cars").join(name)
    }

    pub fn wheel_dir(&self, name: &str) -> PathBuf {
        self.torcs.join("wheels").join(name)
    }

    /// The OBJ conversion of an AC3D file, made once with `assimp export` and cached, with its
    /// material library beside it (`<same name>.mtl`; its `mtllib` line names a temporary file).
    pub fn obj(&self, acc: &Path) -> Result<PathBuf> {
        let parent =
            acc.parent().and_then(Path::file_name).map(|p| p.to_string_lossy().into_owned()).unwrap_or_default();
        let stem = acc.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let out = self.cache.join(format!("{parent}--{stem}.obj"));
        if out.is_file() {
            return Ok(out);
        }
        // Convert into a private name, then rename: a crash never leaves half a file cached.
        let tmp = self.cache.join(format!("{parent}--{stem}.{}.tmp.obj", std::process::id()));
        let status = Command::new("assimp")
            .arg("export")
            .arg(acc)
            .arg(&tmp)
            .stdout(std::process::Stdio::null())
            .status()
            .with_context(|| format!("running assimp: {INSTALL_HINT}"))?;
        if !status.success() {
            bail!("assimp export {} failed ({status})", acc.display());
        }
        // The material library first: the OBJ is the mark of a finished conversion.
        if tmp.with_extension("mtl").is_file() {
            std::fs::rename(tmp.with_extension("mtl"), out.with_extension("mtl"))?;
        }
        std::fs::rename(&tmp, &out)?;
        Ok(out)
    }
}
