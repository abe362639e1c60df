//! NeMo-preprocessed PASCAL3D+, Occluded PASCAL3D+ and OOD-CV exports (BENCHMARK.md §4).
//!
//! Layout, as NeMo's preparation scripts write it (`<root>` is the split folder, e.g.
//! `PASCAL3D_NeMo/` or `OOD_CV_NeMo/val/`):
//!
//! ```text
//! <root>/images/<cat>/<name>.JPEG
//! <root>/annotations/<cat>/<name>.npz
//! <root>/lists/<cat>/*.txt        # one list per subtype and/or one `meshNN.txt` per CAD model
//! ```
//!
//! `<cat>` is the category (`car`), or `carFGL<n>_BGL<n>` for occlusion level n of Occluded
//! PASCAL3D+ ([`occluded_category`]); the `annotations3D_<mesh>` / `lists3D_<mesh>` variants are
//! opened with [`NemoDirs::three_d`]. The split is the union of all list files, deduplicated and
//! sorted (a sample appears in its subtype list and in its mesh list). List lines are image names
//! with `.JPEG` (Angtian/NeMo) or without (OOD-CV-Pose and neural-mesh-model, which name samples
//! `<image>_<object>`). OOD-CV's nuisance is not a folder: it is the per-sample `nuisance` key
//! (`context`, `pose`, `shape`, `texture`, `weather` or `iid`).
//!
//! The npz holds the *original* image's PASCAL3D+ annotation; [`NemoSample::pose`] converts it to
//! the crop's frame (see [`CropFrame::NemoNormalised`] and [`NemoFlavor`]).

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

use super::{CropFrame, CropPose, DatasetError, Mask, Result, mask_from, pair, read_list, size};
use crate::npz::{NpyData, NpyError, Npz};

/// NeMo's image extension.
pub const IMAGE_EXTENSION: &str = "JPEG";
/// The distance NeMo normalises its crops to (`resize rate = distance / 5`).
pub const NEMO_DISTANCE: f64 = 5.0;

/// `car` → `carFGL2_BGL2`: the category folder of Occluded PASCAL3D+ level `level`.
pub fn occluded_category(category: &str, level: u8) -> String {
    format!("{category}FGL{level}_BGL{level}")
}

/// Folder names of one export (the category folder goes below each).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NemoDirs {
    pub images: String,
    pub annotations: String,
    pub lists: String,
}

impl Default for NemoDirs {
    fn default() -> Self {
        NemoDirs { images: "images".into(), annotations: "annotations".into(), lists: "lists".into() }
    }
}

impl NemoDirs {
    /// NeMo's 3-D annotation variant (`annotations3D_single`, `lists3D_single` for `mesh = "single"`).
    pub fn three_d(mesh: &str) -> Self {
        NemoDirs {
            images: "images".into(),
            annotations: format!("annotations3D_{mesh}"),
            lists: format!("lists3D_{mesh}"),
        }
    }
}

/// Which of NeMo's exporters wrote a file; decides how `distance` and the principal point map to
/// the crop. Detected from the keys present.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NemoFlavor {
    /// Angtian/NeMo `CreatePascal3DNeMo.py`: original distance, no `resize_rate`; the resize rate
    /// was `distance / 5`, so the crop distance is 5.
    Original,
    /// OOD-CV-Pose `prepare_ood_cv.py`: original distance plus `resize_rate`; crop distance =
    /// `distance / resize_rate`.
    OodCvPose,
    /// neural-mesh-model (wufeim/NeMo): `distance` is already the crop's and `px, py` its
    /// principal point; the original distance is `distance · resize_rate`.
    NeuralMeshModel,
}

/// A BboxTools box as NeMo stores it: `[y0, y1, x0, x1]` plus, when known, the `[height, width]`
/// of the image it lives in. Empty boxes are stored as -1s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BboxToolsBox {
    pub y0: f64,
    pub y1: f64,
    pub x0: f64,
    pub x1: f64,
    pub boundary: Option<[f64; 2]>,
}

/// The npz as stored: the original image's annotation plus NeMo's crop bookkeeping.
#[derive(Clone, Debug, PartialEq)]
pub struct NemoAnnotation {
    /// Source image name (without the `_<object>` suffix OOD-CV adds to the sample name).
    pub name: String,
    /// Radians.
    pub azimuth: f64,
    pub elevation: f64,
    pub theta: f64,
    /// As stored: the original distance, except in [`NemoFlavor::NeuralMeshModel`] files.
    pub distance: f64,
    pub focal: f64,
    /// Principal point in the original image.
    pub principal: [f64; 2],
    pub viewport: f64,
    /// Original image size.
    pub height: usize,
    pub width: usize,
    pub cad_index: i64,
    /// Object box in the original image, `[x0, y0, x1, y1]`.
    pub bbox: Option<[f64; 4]>,
    /// `box`: the crop box in the resized, padded image.
    pub crop_box: Option<BboxToolsBox>,
    /// `box_ori`: the object box in the original image.
    pub box_ori: Option<BboxToolsBox>,
    /// `box_obj`: the object box in the crop; its boundary is the crop size.
    pub box_obj: Option<BboxToolsBox>,
    /// Keypoints in the crop, `[row, col]`.
    pub cropped_kp_list: Option<Vec<[f64; 2]>>,
    /// `visible == 1` per keypoint.
    pub visible: Option<Vec<bool>>,
    pub kp_weights: Option<Vec<f64>>,
    /// Occluder mask. `None` where NeMo stored `None` (a pickled object). Angtian/NeMo stores the
    /// original image's mask, later exporters the crop's: see [`NemoSample::occ_mask_in_crop`].
    pub occ_mask: Option<Mask>,
    pub resize_rate: Option<f64>,
    pub padding_params: Option<Vec<i64>>,
    /// OOD-CV nuisance of this sample.
    pub nuisance: Option<String>,
    /// `[px, py]` in the crop (neural-mesh-model only).
    pub crop_principal: Option<[f64; 2]>,
    /// The CAD index before neural-mesh-model's single-mesh override.
    pub true_cad_index: Option<i64>,
}

impl NemoAnnotation {
    /// Reads the keys every NeMo exporter writes; the others are optional.
    pub fn from_npz(npz: &Npz) -> Result<Self, NpyError> {
        let px_py = match (present(npz, "px"), present(npz, "py")) {
            (true, true) => Some([npz.f64_scalar("px")?, npz.f64_scalar("py")?]),
            _ => None,
        };
        Ok(NemoAnnotation {
            name: npz.str_scalar("name")?.to_owned(),
            azimuth: npz.f64_scalar("azimuth")?,
            elevation: npz.f64_scalar("elevation")?,
            theta: npz.f64_scalar("theta")?,
            distance: npz.f64_scalar("distance")?,
            focal: npz.f64_scalar("focal")?,
            principal: pair(npz, "principal")?,
            viewport: npz.f64_scalar("viewport")?,
            height: size(npz, "height")?,
            width: size(npz, "width")?,
            cad_index: npz.i64_scalar("cad_index")?,
            bbox: optional(npz, "bbox", bbox4)?,
            crop_box: optional(npz, "box", bbox_tools)?,
            box_ori: optional(npz, "box_ori", bbox_tools)?,
            box_obj: optional(npz, "box_obj", bbox_tools)?,
            cropped_kp_list: optional(npz, "cropped_kp_list", keypoints)?,
            visible: optional(npz, "visible", |n, k| Ok(n.f64_array(k)?.1.iter().map(|&v| v == 1.0).collect()))?,
            kp_weights: optional(npz, "kp_weights", |n, k| Ok(n.f64_array(k)?.1))?,
            occ_mask: optional(npz, "occ_mask", mask_from)?,
            resize_rate: optional(npz, "resize_rate", Npz::f64_scalar)?,
            padding_params: optional(npz, "padding_params", integers)?,
            nuisance: optional(npz, "nuisance", |n, k| n.str_scalar(k).map(str::to_owned))?,
            crop_principal: px_py,
            true_cad_index: optional(npz, "true_cad_index", Npz::i64_scalar)?,
        })
    }

    pub fn flavor(&self) -> NemoFlavor {
        match (self.crop_principal, self.resize_rate) {
            (Some(_), _) => NemoFlavor::NeuralMeshModel,
            (None, Some(_)) => NemoFlavor::OodCvPose,
            (None, None) => NemoFlavor::Original,
        }
    }

    /// Crop size `(height, width)` from `box_obj`'s boundary, else from the extent of `box`.
    pub fn crop_size(&self) -> Option<(usize, usize)> {
        let from_boundary = self.box_obj.and_then(|b| b.boundary).map(|[h, w]| (h, w));
        let from_box = self.crop_box.map(|b| (b.y1 - b.y0, b.x1 - b.x0));
        let (h, w) = from_boundary.or(from_box)?;
        (h >= 1.0 && w >= 1.0 && h.fract() == 0.0 && w.fract() == 0.0).then_some((h as usize, w as usize))
    }

    /// The crop-frame pose and the original distance, for a crop of `height × width`.
    ///
    /// The principal point is the crop centre `(W/2, H/2)`: NeMo centres the crop box on the
    /// *integer part* of the scaled principal point, so the exact point is off by less than a
    /// pixel, which NeMo's own solver ignores too.
    pub fn crop_pose(&self, height: usize, width: usize) -> Result<(CropPose, f64), String> {
        let centre = [width as f64 / 2.0, height as f64 / 2.0];
        let rate = |r: Option<f64>| match r {
            Some(r) if r.is_finite() && r > 0.0 => Ok(r),
            other => Err(format!("resize_rate {other:?} is not a positive number")),
        };
        let (distance, principal, original) = match self.flavor() {
            NemoFlavor::Original if self.distance > 0.0 => (NEMO_DISTANCE, centre, self.distance),
            // NeMo then resized by the box size instead, so the crop distance is unknown.
            NemoFlavor::Original => return Err(format!("distance {} is not positive", self.distance)),
            NemoFlavor::OodCvPose => (self.distance / rate(self.resize_rate)?, centre, self.distance),
            NemoFlavor::NeuralMeshModel => {
                let principal = self.crop_principal.unwrap_or(centre);
                (self.distance, principal, self.distance * rate(self.resize_rate)?)
            }
        };
        let pose = CropPose {
            azimuth: self.azimuth,
            elevation: self.elevation,
            theta: self.theta,
            distance,
            principal,
            viewport: self.viewport,
            focal: self.focal,
            height,
            width,
        };
        Ok((pose, original))
    }
}

/// True when `key` holds real data (NeMo writes `None` as a pickled object array).
fn present(npz: &Npz, key: &str) -> bool {
    npz.get(key).is_some_and(|a| !matches!(a.data(), NpyData::Object(_)))
}

fn optional<T>(npz: &Npz, key: &str, read: impl Fn(&Npz, &str) -> Result<T, NpyError>) -> Result<Option<T>, NpyError> {
    present(npz, key).then(|| read(npz, key)).transpose()
}

fn shape_error(npz: &Npz, key: &str, expected: &'static str) -> NpyError {
    let found = npz.get(key).map_or_else(String::new, |a| a.describe());
    NpyError::WrongType { key: key.to_owned(), expected, found }
}

fn bbox4(npz: &Npz, key: &str) -> Result<[f64; 4], NpyError> {
    match npz.f64_array(key)?.1[..] {
        [a, b, c, d] => Ok([a, b, c, d]),
        _ => Err(shape_error(npz, key, "4 numbers")),
    }
}

fn bbox_tools(npz: &Npz, key: &str) -> Result<BboxToolsBox, NpyError> {
    let (y0, y1, x0, x1, boundary) = match npz.f64_array(key)?.1[..] {
        [y0, y1, x0, x1] => (y0, y1, x0, x1, None),
        [y0, y1, x0, x1, h, w] => (y0, y1, x0, x1, Some([h, w])),
        _ => return Err(shape_error(npz, key, "a BboxTools box of 4 or 6 numbers")),
    };
    Ok(BboxToolsBox { y0, y1, x0, x1, boundary })
}

/// `(K, 2)` keypoints; `np.array([])` (shape `(0,)`) when the category lists none.
fn keypoints(npz: &Npz, key: &str) -> Result<Vec<[f64; 2]>, NpyError> {
    let (shape, values) = npz.f64_array(key)?;
    match shape[..] {
        [_, 2] => Ok(values.chunks_exact(2).map(|p| [p[0], p[1]]).collect()),
        [0] => Ok(Vec::new()),
        _ => Err(shape_error(npz, key, "a (K, 2) keypoint array")),
    }
}

fn integers(npz: &Npz, key: &str) -> Result<Vec<i64>, NpyError> {
    let array = npz.require(key)?;
    array.to_i64_vec().ok_or_else(|| shape_error(npz, key, "integers"))
}

/// One listed sample.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NemoEntry {
    /// Sample name without extension (`n02814533_1234`, or `n02814533_1234_00` in OOD-CV).
    pub name: String,
    pub image_path: PathBuf,
    pub annotation_path: PathBuf,
}

/// A loaded sample with its ground truth in the crop's frame.
#[derive(Clone, Debug, PartialEq)]
pub struct NemoSample {
    pub entry: NemoEntry,
    /// Always [`CropFrame::NemoNormalised`]: `pose` was converted from the original image.
    pub frame: CropFrame,
    pub flavor: NemoFlavor,
    /// Pose and camera in the crop (distance 5 in NeMo's default exports, viewport as stored,
    /// principal point at the crop centre, angles unchanged).
    pub pose: CropPose,
    /// The object's distance in the original image.
    pub original_distance: f64,
    /// Everything the npz stores, unconverted.
    pub annotation: NemoAnnotation,
}

impl NemoSample {
    /// The occluder mask when it is in the crop's frame (same size as the crop); Angtian/NeMo
    /// stores the original image's mask instead, which this returns as `None`.
    pub fn occ_mask_in_crop(&self) -> Option<&Mask> {
        let mask = self.annotation.occ_mask.as_ref()?;
        ((mask.height, mask.width) == (self.pose.height, self.pose.width)).then_some(mask)
    }
}

/// One category folder of a NeMo export, opened from its list files.
#[derive(Clone, Debug)]
pub struct NemoDataset {
    list_dir: PathBuf,
    entries: Vec<NemoEntry>,
}

impl NemoDataset {
    /// `<root>/{images,annotations,lists}/<category_dir>/`.
    pub fn open(root: &Path, category_dir: &str) -> Result<Self> {
        Self::open_with(root, category_dir, &NemoDirs::default())
    }

    pub fn open_with(root: &Path, category_dir: &str, dirs: &NemoDirs) -> Result<Self> {
        let list_dir = root.join(&dirs.lists).join(category_dir);
        let images = root.join(&dirs.images).join(category_dir);
        let annotations = root.join(&dirs.annotations).join(category_dir);
        let entries = sample_names(&list_dir)?
            .into_iter()
            .map(|name| NemoEntry {
                image_path: images.join(format!("{name}.{IMAGE_EXTENSION}")),
                annotation_path: annotations.join(format!("{name}.npz")),
                name,
            })
            .collect();
        Ok(NemoDataset { list_dir, entries })
    }

    pub fn entries(&self) -> &[NemoEntry] {
        &self.entries
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Loads entry `index` and converts it to the crop's frame.
    pub fn load(&self, index: usize) -> Result<NemoSample> {
        let entry = self.entries.get(index).ok_or_else(|| {
            DatasetError::invalid(&self.list_dir, format!("sample {index} of {}", self.entries.len()))
        })?;
        load_sample(entry.clone())
    }

    /// Every sample in name order, loaded lazily.
    pub fn iter(&self) -> impl Iterator<Item = Result<NemoSample>> + '_ {
        (0..self.entries.len()).map(|i| self.load(i))
    }
}

fn load_sample(entry: NemoEntry) -> Result<NemoSample> {
    let path = &entry.annotation_path;
    let npz = Npz::read_path(path).map_err(|e| DatasetError::npz(path, e))?;
    let annotation = NemoAnnotation::from_npz(&npz).map_err(|e| DatasetError::npz(path, e))?;
    let (height, width) = match annotation.crop_size() {
        Some(size) => size,
        // Files without box bookkeeping: the crop is the image itself (reads only its header).
        None => image::image_dimensions(&entry.image_path)
            .map(|(w, h)| (h as usize, w as usize))
            .map_err(|e| DatasetError::invalid(&entry.image_path, e.to_string()))?,
    };
    let (pose, original_distance) =
        annotation.crop_pose(height, width).map_err(|message| DatasetError::invalid(path, message))?;
    Ok(NemoSample {
        entry,
        frame: CropFrame::NemoNormalised,
        flavor: annotation.flavor(),
        pose,
        original_distance,
        annotation,
    })
}

/// Union of every `*.txt` list in `list_dir`: names without `.JPEG`, deduplicated, sorted.
fn sample_names(list_dir: &Path) -> Result<Vec<String>> {
    let mut lists = Vec::new();
    for item in fs::read_dir(list_dir).map_err(|e| DatasetError::io(list_dir, e))? {
        let path = item.map_err(|e| DatasetError::io(list_dir, e))?.path();
        if path.extension().is_some_and(|e| e == "txt") && path.is_file() {
            lists.push(path);
        }
    }
    // An empty folder is almost certainly a wrong category name, not an empty split.
    if lists.is_empty() {
        return Err(DatasetError::invalid(list_dir, "no *.txt list files"));
    }
    let mut names = BTreeSet::new();
    for list in &lists {
        names.extend(read_list(list)?.into_iter().map(|line| strip_image_extension(&line).to_owned()));
    }
    Ok(names.into_iter().collect())
}

fn strip_image_extension(name: &str) -> &str {
    [".JPEG", ".jpeg", ".jpg", ".JPG"].iter().find_map(|ext| name.strip_suffix(ext)).unwrap_or(name)
}
