//! SynCar-OOD on disk (BENCHMARK.md §4):
//!
//! ```text
//! <root>/<domain>/<split>/images/car/<name>.png
//! <root>/<domain>/<split>/annotations/car/<name>.npz
//! <root>/<domain>/<split>/lists/car/list.txt      # one image file name per line
//! ```
//!
//! `<domain>` may contain a slash (`corrupt/fog`). Annotations are in the crop's own frame and are
//! written exactly as `np.savez` would write them, so Python reads them with `np.load`.

use std::fs;
use std::path::{Path, PathBuf};

use super::{CropFrame, CropPose, DatasetError, Mask, Result, file_stem, mask_from, pair, read_list, size};
use crate::npz::{NpyArray, NpyData, NpyError, Npz};

/// The category of SynCar-OOD proper; `synth --category` renders the others in the same layout.
pub const CATEGORY: &str = "car";
/// Name of the list file in `lists/<category>/`.
pub const LIST_FILE: &str = "list.txt";
/// The annotation keys in the order they are written (BENCHMARK.md §4); `occ_fraction` and
/// `occluder` only in the occlusion domains.
pub const KEYS: [&str; 15] = [
    "azimuth",
    "elevation",
    "theta",
    "distance",
    "principal",
    "viewport",
    "focal",
    "height",
    "width",
    "fill",
    "car",
    "cad_index",
    "mask",
    "occ_fraction",
    "occluder",
];

/// The ground truth of one SynCar-OOD crop, as the `synth` command writes it and readers load it.
#[derive(Clone, Debug, PartialEq)]
pub struct Annotation {
    /// Pose and camera in the crop's frame (principal point = crop centre, `M = 3000·H/256`).
    pub pose: CropPose,
    /// Fraction of the crop the car's projection reaches in its limiting dimension.
    pub fill: f64,
    /// TORCS car model name.
    pub car: String,
    pub cad_index: i64,
    /// Object mask, `pose.height × pose.width`.
    pub mask: Mask,
    /// Measured fraction of the mask covered by occluders (occlusion domains only).
    pub occ_fraction: Option<f64>,
    /// The pixels the occluders cover, `height × width` (occlusion domains of datasets rendered
    /// since it was added): the oracle leaves the vertices under them out of its positives.
    pub occluder: Option<Mask>,
}

impl Annotation {
    /// The npz: keys in [`KEYS`] order, floats as `<f8` 0-d arrays, `principal` as `<f8 (2,)`,
    /// `height`, `width`, `cad_index` as `<i8`, `car` as `<U n`, `mask` and `occluder` as `|u1 (H, W)`.
    pub fn to_npz(&self) -> Result<Npz, NpyError> {
        let p = &self.pose;
        let mask = full_size(&self.mask, "mask", p)?;
        let mut npz = Npz::new();
        npz.insert("azimuth", p.azimuth);
        npz.insert("elevation", p.elevation);
        npz.insert("theta", p.theta);
        npz.insert("distance", p.distance);
        npz.insert("principal", p.principal);
        npz.insert("viewport", p.viewport);
        npz.insert("focal", p.focal);
        npz.insert("height", p.height as i64);
        npz.insert("width", p.width as i64);
        npz.insert("fill", self.fill);
        npz.insert("car", self.car.as_str());
        npz.insert("cad_index", self.cad_index);
        npz.insert("mask", mask);
        if let Some(fraction) = self.occ_fraction {
            npz.insert("occ_fraction", fraction);
        }
        if let Some(occluder) = &self.occluder {
            npz.insert("occluder", full_size(occluder, "occluder", p)?);
        }
        Ok(npz)
    }

    /// Reads the keys of [`KEYS`]; numeric keys accept any numeric dtype.
    pub fn from_npz(npz: &Npz) -> Result<Self, NpyError> {
        let pose = CropPose {
            azimuth: npz.f64_scalar("azimuth")?,
            elevation: npz.f64_scalar("elevation")?,
            theta: npz.f64_scalar("theta")?,
            distance: npz.f64_scalar("distance")?,
            principal: pair(npz, "principal")?,
            viewport: npz.f64_scalar("viewport")?,
            focal: npz.f64_scalar("focal")?,
            height: size(npz, "height")?,
            width: size(npz, "width")?,
        };
        let crop_mask = |key: &str| mask_from(npz, key).and_then(|m| crop_sized(m, key, &pose));
        let mask = crop_mask("mask")?;
        let occ_fraction = npz.contains("occ_fraction").then(|| npz.f64_scalar("occ_fraction")).transpose()?;
        let occluder = npz.contains("occluder").then(|| crop_mask("occluder")).transpose()?;
        Ok(Annotation {
            pose,
            fill: npz.f64_scalar("fill")?,
            car: npz.str_scalar("car")?.to_owned(),
            cad_index: npz.i64_scalar("cad_index")?,
            mask,
            occ_fraction,
            occluder,
        })
    }
}

/// A mask as the npz's `|u1 (H, W)` array, refused unless it has the crop's size.
fn full_size(mask: &Mask, key: &str, p: &CropPose) -> Result<NpyArray, NpyError> {
    let mask = crop_sized(mask.clone(), key, p)?;
    NpyArray::new(vec![p.height, p.width], NpyData::U8(mask.data))
}

/// `mask`, refused unless it is `height × width` of the crop.
fn crop_sized(mask: Mask, key: &str, p: &CropPose) -> Result<Mask, NpyError> {
    if (mask.height, mask.width) != (p.height, p.width) {
        return Err(NpyError::WrongType {
            key: key.into(),
            expected: "a mask of height × width",
            found: format!("{}×{} for a {}×{} crop", mask.height, mask.width, p.height, p.width),
        });
    }
    Ok(mask)
}

/// Writes one annotation (atomically: temporary file, then rename).
pub fn write_syncar_annotation(path: &Path, annotation: &Annotation) -> Result<()> {
    let npz = annotation.to_npz().map_err(|e| DatasetError::npz(path, e))?;
    npz.write_path(path).map_err(|e| DatasetError::npz(path, e))
}

/// Reads one annotation file.
pub fn read_syncar_annotation(path: &Path) -> Result<Annotation> {
    let npz = Npz::read_path(path).map_err(|e| DatasetError::npz(path, e))?;
    Annotation::from_npz(&npz).map_err(|e| DatasetError::npz(path, e))
}

/// Writes `lists/car/list.txt`: one image file name per line, in the given order (atomically).
pub fn write_syncar_list(path: &Path, names: &[String]) -> Result<()> {
    let text: String = names.iter().map(|name| format!("{name}\n")).collect();
    crate::atomic::write_atomic(path, text.as_bytes()).map_err(|e| DatasetError::io(path, e))
}

/// The three folders and the list file of one `<domain>/<split>`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SplitPaths {
    pub images: PathBuf,
    pub annotations: PathBuf,
    pub list: PathBuf,
}

impl SplitPaths {
    /// The paths of a split on disk: of its one category (`lists/<category>/`), `car` if it has
    /// none yet.
    pub fn new(root: &Path, domain: &str, split: &str) -> Self {
        let lists = root.join(domain).join(split).join("lists");
        let mut categories = fs::read_dir(&lists)
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| e.path().is_dir())
            .map(|e| e.file_name().to_string_lossy().into_owned());
        let category = match (categories.next(), categories.next()) {
            (Some(only), None) => only,
            _ => CATEGORY.to_string(),
        };
        Self::of_category(root, domain, split, &category)
    }

    /// The paths of `category`'s samples in a split (what `synth --category` writes).
    pub fn of_category(root: &Path, domain: &str, split: &str, category: &str) -> Self {
        let base = root.join(domain).join(split);
        SplitPaths {
            images: base.join("images").join(category),
            annotations: base.join("annotations").join(category),
            list: base.join("lists").join(category).join(LIST_FILE),
        }
    }

    /// Creates the three folders.
    pub fn create(&self) -> std::io::Result<()> {
        let lists = self.list.parent().unwrap_or(&self.list);
        [&self.images, &self.annotations, lists].iter().try_for_each(fs::create_dir_all)
    }
}

/// One listed sample: where its image and annotation are.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SyncarEntry {
    /// Image file name as listed (`000042.png`).
    pub name: String,
    pub image_path: PathBuf,
    pub annotation_path: PathBuf,
}

/// A loaded sample. `frame` is always [`CropFrame::Native`]: SynCar-OOD stores crop-frame values.
#[derive(Clone, Debug, PartialEq)]
pub struct SyncarSample {
    pub entry: SyncarEntry,
    pub frame: CropFrame,
    pub annotation: Annotation,
}

/// One `<domain>/<split>`, opened from its list file; annotations are loaded on demand.
#[derive(Clone, Debug)]
pub struct SyncarSplit {
    paths: SplitPaths,
    entries: Vec<SyncarEntry>,
}

impl SyncarSplit {
    /// Reads `lists/car/list.txt`, in its order.
    pub fn open(root: &Path, domain: &str, split: &str) -> Result<Self> {
        let paths = SplitPaths::new(root, domain, split);
        let entries = read_list(&paths.list)?
            .into_iter()
            .map(|name| SyncarEntry {
                image_path: paths.images.join(&name),
                annotation_path: paths.annotations.join(format!("{}.npz", file_stem(&name))),
                name,
            })
            .collect();
        Ok(SyncarSplit { paths, entries })
    }

    pub fn paths(&self) -> &SplitPaths {
        &self.paths
    }

    /// The category whose samples these are (`lists/<category>/`).
    pub fn category(&self) -> &str {
        self.paths.list.parent().and_then(|p| p.file_name()).and_then(|n| n.to_str()).unwrap_or(CATEGORY)
    }

    pub fn entries(&self) -> &[SyncarEntry] {
        &self.entries
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Loads the annotation of entry `index` (an index past the end is an error, not a panic).
    pub fn load(&self, index: usize) -> Result<SyncarSample> {
        let entry = self.entries.get(index).ok_or_else(|| {
            DatasetError::invalid(&self.paths.list, format!("sample {index} of {}", self.entries.len()))
        })?;
        Ok(SyncarSample {
            entry: entry.clone(),
            frame: CropFrame::Native,
            annotation: read_syncar_annotation(&entry.annotation_path)?,
        })
    }

    /// Every sample in list order, loaded lazily.
    pub fn iter(&self) -> impl Iterator<Item = Result<SyncarSample>> + '_ {
        (0..self.entries.len()).map(|i| self.load(i))
    }
}
