//! Model directories: `manifest.json` (written last, with the sha256 of every file) next to
//! `backbone.safetensors` (torchvision names) and `mesh.safetensors` (the neural mesh: vertex
//! features, clutter, per-vertex κ and the source similarity statistics of METHOD.md §7).
//!
//! Saving builds the directory under a temporary name and renames it into place, so a model
//! directory either is complete or does not exist; loading validates every field and file.

use std::collections::BTreeMap;
use std::fs::{self, File};
use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tch::{Device, Kind, Tensor, nn};

use crate::backbone::{Arch, Backbone};
use crate::error::{CheckpointError, EngineError, Result};
use crate::mesh::{Cuboid, Mesh, TARGET_VERTICES};
use crate::signature::Domain;

pub const FORMAT_VERSION: u32 = 1;
pub const MANIFEST: &str = "manifest.json";
pub const BACKBONE_FILE: &str = "backbone.safetensors";
pub const MESH_FILE: &str = "mesh.safetensors";

/// Everything about a model except its tensors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    pub category: String,
    /// Identifier of this version (unique per category).
    pub version: String,
    pub cuboid: Cuboid,
    /// Vertex count R of the cuboid mesh (checked against the cuboid).
    pub vertices: usize,
    pub backbone: Arch,
    /// What the trunk's weights expect of their input ([`Arch::input_normalization`]); the
    /// backbone itself always takes ImageNet-normalised input. Absent in older manifests.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_normalization: Option<String>,
    pub feature_dim: usize,
    /// Crop `[height, width]` the model was trained on.
    pub crop: [usize; 2],
    /// Clutter vectors N in `mesh.safetensors`.
    pub clutter: usize,
    /// How the tensors are stored: "f32" or "f16" (always loaded as f32).
    pub dtype: String,
    /// How the model was made: command, data, seed, commit, durations, settings.
    pub training: serde_json::Value,
    /// Evaluation results, if any.
    #[serde(default)]
    pub metrics: serde_json::Value,
    /// sha256 of every other file in the directory.
    #[serde(default)]
    pub files: BTreeMap<String, String>,
    /// Versions of the category that answer the images of their own domain; this version's
    /// tensors answer every other image (a *composite* version, ARCHITECTURE.md "Validation
    /// gate"). Empty for a plain model.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub experts: Vec<Expert>,
    /// The target check's threshold measured for this model (`udapose-lab target-check --set`,
    /// reports/target-check.md): halfway between what images of no object read and what the
    /// lowest of its benchmark's domains reads. Adapted versions inherit it. Absent: the gate's
    /// default ([`crate::gate::GateConfig::min_target_fired`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_target_fired: Option<f64>,
}

/// A version that answers the images its domain takes ([`Domain::accepts`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Expert {
    pub version: String,
    pub domain: Domain,
}

/// The per-category neural mesh (METHOD.md §3): geometry plus features, all `f32`.
#[derive(Debug)]
pub struct NeuralMesh {
    pub mesh: Mesh,
    /// `C`, R×D, unit rows.
    pub vertex_features: Tensor,
    /// Clutter vectors, N×D, unit rows.
    pub clutter: Tensor,
    /// Per-vertex concentration κ_r, R.
    pub kappa: Tensor,
    /// Per-vertex cosine threshold τ_r (10% quantile at ground-truth poses), R.
    pub tau: Tensor,
    /// Per-vertex mean resultant length R̄_r, R.
    pub r_bar: Tensor,
}

/// A loaded model: manifest, backbone (with its variables) and neural mesh.
pub struct Model {
    pub manifest: Manifest,
    pub vs: nn::VarStore,
    pub backbone: Backbone,
    pub neural_mesh: NeuralMesh,
}

impl Model {
    /// Bytes of its tensors (backbone variables and buffers, neural mesh), on its device.
    pub fn tensor_bytes(&self) -> usize {
        let bytes = |t: &Tensor| t.numel() * t.kind().elt_size_in_bytes();
        let nm = &self.neural_mesh;
        self.vs.variables().values().map(bytes).sum::<usize>()
            + [&nm.vertex_features, &nm.clutter, &nm.kappa, &nm.tau, &nm.r_bar].into_iter().map(bytes).sum::<usize>()
    }
}

fn invalid(dir: &Path, what: impl std::fmt::Display) -> EngineError {
    EngineError::InvalidInput(format!("model {}: {what}", dir.display()))
}

impl Manifest {
    /// Field checks that need no files.
    pub fn validate(&self, dir: &Path) -> Result<Mesh> {
        if self.format_version != FORMAT_VERSION {
            return Err(invalid(
                dir,
                format!("format version {} (this build reads {FORMAT_VERSION})", self.format_version),
            ));
        }
        let name_ok = |s: &str| {
            !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
        };
        if !name_ok(&self.category) || !name_ok(&self.version) || !self.experts.iter().all(|e| name_ok(&e.version)) {
            return Err(invalid(dir, format!("bad category {:?} or version {:?}", self.category, self.version)));
        }
        if self.crop.iter().any(|&c| c == 0 || c % 8 != 0) {
            return Err(invalid(dir, format!("crop {:?} must be positive multiples of 8", self.crop)));
        }
        if let Some(norm) = &self.input_normalization
            && norm != self.backbone.input_normalization()
        {
            return Err(invalid(
                dir,
                format!(
                    "input normalisation {norm:?} is not {}'s {:?}",
                    self.backbone,
                    self.backbone.input_normalization()
                ),
            ));
        }
        if self.feature_dim == 0 || self.clutter == 0 {
            return Err(invalid(dir, "feature_dim and clutter must be at least 1"));
        }
        if !["f32", "f16"].contains(&self.dtype.as_str()) {
            return Err(invalid(dir, format!("dtype {:?} is neither f32 nor f16", self.dtype)));
        }
        Cuboid::from_dimensions(self.cuboid.dimensions()).map_err(|e| invalid(dir, e))?;
        let mesh = self.cuboid.mesh(TARGET_VERTICES);
        if mesh.vertices().len() != self.vertices {
            return Err(invalid(
                dir,
                format!("cuboid gives {} vertices, manifest says {}", mesh.vertices().len(), self.vertices),
            ));
        }
        Ok(mesh)
    }
}

/// Saves a model as the new directory `dir` (which must not exist), tensors stored as the
/// manifest's `dtype`.
pub fn save(dir: &Path, manifest: &Manifest, vs: &nn::VarStore, neural_mesh: &NeuralMesh) -> Result<()> {
    manifest.validate(dir)?;
    if dir.exists() {
        return Err(invalid(dir, "already exists (model versions are immutable)"));
    }
    let parent = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    fs::create_dir_all(parent)?;
    let tmp = parent.join(format!(
        ".{}.tmp{}",
        dir.file_name().and_then(|n| n.to_str()).unwrap_or("model"),
        std::process::id()
    ));
    if tmp.exists() {
        fs::remove_dir_all(&tmp)?;
    }
    fs::create_dir(&tmp)?;
    let kind = if manifest.dtype == "f16" { Kind::Half } else { Kind::Float };
    let backbone: Vec<(String, Tensor)> = vs.variables().into_iter().map(|(n, t)| (n, t.to_kind(kind))).collect();
    let n = neural_mesh;
    let mesh_tensors: Vec<(String, Tensor)> = [
        ("vertex_features", &n.vertex_features),
        ("clutter", &n.clutter),
        ("kappa", &n.kappa),
        ("tau", &n.tau),
        ("r_bar", &n.r_bar),
    ]
    .into_iter()
    .map(|(k, t)| (k.to_string(), t.to_kind(kind)))
    .collect();
    let mut manifest = manifest.clone();
    manifest.files.clear();
    for (file, tensors) in [(BACKBONE_FILE, backbone), (MESH_FILE, mesh_tensors)] {
        let path = tmp.join(file);
        Tensor::write_safetensors(&tensors, &path).map_err(|e| invalid(dir, format!("writing {file}: {e}")))?;
        File::open(&path)?.sync_all()?;
        manifest.files.insert(file.to_string(), sha256_file(&path)?);
    }
    let json = serde_json::to_string_pretty(&manifest).map_err(|e| invalid(dir, e))? + "\n";
    let mut f = File::create(tmp.join(MANIFEST))?;
    f.write_all(json.as_bytes())?;
    f.sync_all()?;
    File::open(&tmp)?.sync_all()?;
    fs::rename(&tmp, dir)?;
    File::open(parent)?.sync_all()?;
    Ok(())
}

/// Loads and validates a model directory; tensors go to `device` as `f32`.
pub fn load(dir: &Path, device: Device) -> Result<Model> {
    let manifest_path = dir.join(MANIFEST);
    let text = fs::read_to_string(&manifest_path)
        .map_err(|_| CheckpointError::NotFound { path: manifest_path.display().to_string() })?;
    let manifest: Manifest = serde_json::from_str(&text).map_err(|e| invalid(dir, format!("{MANIFEST}: {e}")))?;
    let mesh = manifest.validate(dir)?;
    for file in [BACKBONE_FILE, MESH_FILE] {
        let path = dir.join(file);
        if !path.is_file() {
            return Err(CheckpointError::NotFound { path: path.display().to_string() }.into());
        }
        let want =
            manifest.files.get(file).ok_or_else(|| invalid(dir, format!("{MANIFEST} lists no sha256 for {file}")))?;
        if &sha256_file(&path)? != want {
            return Err(invalid(dir, format!("{file} does not match its sha256 in {MANIFEST} (corrupt or truncated)")));
        }
    }
    let vs = nn::VarStore::new(device);
    let backbone = Backbone::new(vs.root(), manifest.backbone, manifest.feature_dim as i64);
    let file = dir.join(BACKBONE_FILE);
    let variables: BTreeMap<String, Tensor> = vs.variables().into_iter().collect();
    copy_checked(&file, &variables, read_tensors(&file)?)?;
    let neural_mesh = read_neural_mesh(dir, &manifest, mesh, device)?;
    Ok(Model { manifest, vs, backbone, neural_mesh })
}

fn read_neural_mesh(dir: &Path, m: &Manifest, mesh: Mesh, device: Device) -> Result<NeuralMesh> {
    let file = dir.join(MESH_FILE);
    let mut tensors = read_tensors(&file)?;
    let (r, d, n) = (m.vertices as i64, m.feature_dim as i64, m.clutter as i64);
    let path = file.display().to_string();
    let mut take = |key: &str, shape: &[i64]| -> Result<Tensor> {
        let t = tensors
            .remove(key)
            .ok_or_else(|| CheckpointError::MissingKeys { path: path.clone(), keys: vec![key.into()] })?;
        if t.size() != shape {
            return Err(CheckpointError::Shape {
                path: path.clone(),
                key: key.into(),
                expected: shape.to_vec(),
                found: t.size(),
            }
            .into());
        }
        if !t.is_floating_point() {
            return Err(CheckpointError::Dtype {
                path: path.clone(),
                key: key.into(),
                found: format!("{:?}", t.kind()),
            }
            .into());
        }
        let t = t.to_kind(Kind::Float).to_device(device);
        if !bool::try_from(t.isfinite().all()).unwrap_or(false) {
            return Err(invalid(dir, format!("{MESH_FILE}: {key} has non-finite values")));
        }
        Ok(t)
    };
    let nm = NeuralMesh {
        mesh,
        vertex_features: take("vertex_features", &[r, d])?,
        clutter: take("clutter", &[n, d])?,
        kappa: take("kappa", &[r])?,
        tau: take("tau", &[r])?,
        r_bar: take("r_bar", &[r])?,
    };
    if !tensors.is_empty() {
        let keys = tensors.into_keys().collect();
        return Err(CheckpointError::UnexpectedKeys { path, keys }.into());
    }
    // Unit rows, to the precision of f16 storage.
    for (key, t) in [("vertex_features", &nm.vertex_features), ("clutter", &nm.clutter)] {
        let worst = f64::try_from((t.norm_scalaropt_dim(2, [1], false) - 1.0).abs().max()).unwrap_or(f64::INFINITY);
        if worst > 1e-2 {
            return Err(invalid(dir, format!("{MESH_FILE}: rows of {key} are not unit vectors (off by {worst:.3})")));
        }
    }
    Ok(nm)
}

pub(crate) fn read_tensors(file: &Path) -> Result<BTreeMap<String, Tensor>> {
    let path = file.display().to_string();
    if !file.is_file() {
        return Err(CheckpointError::NotFound { path }.into());
    }
    let tensors =
        Tensor::read_safetensors(file).map_err(|e| CheckpointError::Format { path, reason: e.to_string() })?;
    Ok(tensors.into_iter().collect())
}

/// Copies `src` into the variables `dst` after checking that the names match exactly and every
/// shape and dtype fits; on error nothing is written.
pub(crate) fn copy_checked(file: &Path, dst: &BTreeMap<String, Tensor>, src: BTreeMap<String, Tensor>) -> Result<()> {
    let path = file.display().to_string();
    let missing: Vec<String> = dst.keys().filter(|k| !src.contains_key(*k)).cloned().collect();
    if !missing.is_empty() {
        return Err(CheckpointError::MissingKeys { path, keys: missing }.into());
    }
    let unexpected: Vec<String> = src.keys().filter(|k| !dst.contains_key(*k)).cloned().collect();
    if !unexpected.is_empty() {
        return Err(CheckpointError::UnexpectedKeys { path, keys: unexpected }.into());
    }
    for (key, s) in &src {
        let d = &dst[key];
        if s.size() != d.size() {
            return Err(CheckpointError::Shape { path, key: key.clone(), expected: d.size(), found: s.size() }.into());
        }
        if !s.is_floating_point() {
            return Err(CheckpointError::Dtype { path, key: key.clone(), found: format!("{:?}", s.kind()) }.into());
        }
    }
    tch::no_grad(|| -> Result<()> {
        for (key, s) in &src {
            let mut d = dst[key].shallow_clone();
            d.f_copy_(s).map_err(|e| EngineError::InvalidInput(format!("copying {key}: {e}")))?;
        }
        Ok(())
    })
}

pub fn sha256_file(path: &Path) -> Result<String> {
    let bytes = fs::read(path)?;
    Ok(Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect())
}
