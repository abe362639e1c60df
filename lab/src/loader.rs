//! Batches of labelled SynCar-OOD crops, decoded on a background thread so that loading
//! overlaps the training step that consumes them.

use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use anyhow::{Context, Result, bail};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use udapose_engine::{Pose, UpSymmetry, canonical_azimuth};

use crate::assets::category::Category;
use crate::datasets::syncar::{Annotation, SyncarSplit};

/// One batch: images as RGB `f32` in [0, 1], N×3×H×W (channel-major, as a network takes them).
pub struct Batch {
    pub height: usize,
    pub width: usize,
    pub images: Vec<f32>,
    pub poses: Vec<Pose>,
    pub names: Vec<String>,
}

impl Batch {
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }
}

/// A decoded sample: its image as planar RGB in [0, 1] (3×H×W), its ground-truth pose, its name
/// and how its object repeats itself about the up axis (poses are scored up to that).
pub struct Sample {
    pub pixels: Vec<f32>,
    pub pose: Pose,
    pub height: usize,
    pub width: usize,
    pub name: String,
    pub symmetry: UpSymmetry,
}

pub fn load_sample(split: &SyncarSplit, index: usize) -> Result<Sample> {
    let (pixels, a, name) = load_annotated(split, index)?;
    let symmetry = up_symmetry(split, &a);
    Ok(Sample { pixels, pose: a.pose.pose(), height: a.pose.height, width: a.pose.width, name, symmetry })
}

/// How the object of an annotation of `split` repeats itself about its up axis
/// ([`Category::up_symmetry`]; none for a category this build does not know).
pub fn up_symmetry(split: &SyncarSplit, a: &Annotation) -> UpSymmetry {
    Category::from_name(split.category()).map_or(UpSymmetry::NONE, |c| c.up_symmetry(&a.car))
}

/// `pose` with the one azimuth that stands for all that look alike under `symmetry`: what
/// training fits, so that images which look the same are not given labels 180° apart.
pub fn training_pose(pose: Pose, symmetry: UpSymmetry) -> Pose {
    Pose { azimuth: canonical_azimuth(pose.azimuth, symmetry), ..pose }
}

/// Decodes one sample: its image as planar RGB in [0, 1], its whole annotation and its name.
pub fn load_annotated(split: &SyncarSplit, index: usize) -> Result<(Vec<f32>, Annotation, String)> {
    let sample = split.load(index)?;
    let path = &sample.entry.image_path;
    let img = image::open(path).with_context(|| format!("decoding {}", path.display()))?.to_rgb8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let pose = &sample.annotation.pose;
    if (pose.height, pose.width) != (h, w) {
        bail!("{}: image is {w}x{h}, annotation says {}x{}", path.display(), pose.width, pose.height);
    }
    Ok((planar(&img), sample.annotation, sample.entry.name))
}

/// RGB8 pixels as planar `f32` in [0, 1] (3×H×W, channel-major).
pub fn planar(img: &image::RgbImage) -> Vec<f32> {
    let hw = (img.width() * img.height()) as usize;
    let mut planes = vec![0.0f32; 3 * hw];
    for (i, p) in img.pixels().enumerate() {
        for c in 0..3 {
            planes[c * hw + i] = p.0[c] as f32 / 255.0;
        }
    }
    planes
}

/// Reads `batch_size` samples at a time in a seeded shuffled order, one epoch per call of
/// [`Loader::epoch`], `prefetch` batches ahead on its own thread.
pub struct Loader {
    split: SyncarSplit,
    batch_size: usize,
    prefetch: usize,
    rng: ChaCha8Rng,
}

/// The batches of one epoch, arriving from the loading thread.
pub struct Epoch {
    batches: Receiver<Result<Batch>>,
    worker: Option<JoinHandle<()>>,
}

impl Iterator for Epoch {
    type Item = Result<Batch>;

    fn next(&mut self) -> Option<Self::Item> {
        let next = self.batches.recv().ok();
        if next.is_none()
            && let Some(worker) = self.worker.take()
        {
            let _ = worker.join();
        }
        next
    }
}

impl Loader {
    pub fn new(split: SyncarSplit, batch_size: usize, prefetch: usize, seed: u64) -> Result<Self> {
        if split.is_empty() {
            bail!("split {} is empty", split.paths().list.display());
        }
        if batch_size == 0 {
            bail!("batch size must be at least 1");
        }
        Ok(Loader { split, batch_size, prefetch: prefetch.max(1), rng: ChaCha8Rng::seed_from_u64(seed) })
    }

    pub fn len(&self) -> usize {
        self.split.len()
    }

    pub fn is_empty(&self) -> bool {
        self.split.is_empty()
    }

    /// Starts the next epoch: a new shuffled order; the last batch may be short.
    pub fn epoch(&mut self) -> Epoch {
        self.epoch_from(0)
    }

    /// Starts the next epoch at its batch `first` (a run resumed within an epoch): the same
    /// shuffled order as [`Loader::epoch`], the batches before `first` not read.
    pub fn epoch_from(&mut self, first: usize) -> Epoch {
        let mut order: Vec<usize> = (0..self.split.len()).collect();
        order.shuffle(&mut self.rng);
        order.drain(..(first * self.batch_size).min(order.len()));
        let (tx, rx) = sync_channel(self.prefetch);
        let (split, batch_size) = (self.split.clone(), self.batch_size);
        let worker = std::thread::spawn(move || produce(&split, &order, batch_size, &tx));
        Epoch { batches: rx, worker: Some(worker) }
    }
}

/// Decodes batches in order (samples of a batch in parallel) until done or the receiver is gone.
fn produce(split: &SyncarSplit, order: &[usize], batch_size: usize, tx: &SyncSender<Result<Batch>>) {
    for chunk in order.chunks(batch_size) {
        let batch = chunk.par_iter().map(|&i| load_sample(split, i)).collect::<Result<Vec<_>>>().and_then(assemble);
        let failed = batch.is_err();
        if tx.send(batch).is_err() || failed {
            return;
        }
    }
}

/// A training batch: the samples' images and their [`training_pose`]s.
fn assemble(samples: Vec<Sample>) -> Result<Batch> {
    let (height, width) = (samples[0].height, samples[0].width);
    if samples.iter().any(|s| (s.height, s.width) != (height, width)) {
        bail!("a batch mixes image sizes");
    }
    let mut batch = Batch { height, width, images: Vec::new(), poses: Vec::new(), names: Vec::new() };
    for s in samples {
        batch.images.extend(s.pixels);
        batch.poses.push(training_pose(s.pose, s.symmetry));
        batch.names.push(s.name);
    }
    Ok(batch)
}

/// Every image (PNG/JPEG/WebP) directly in `dir`, in name order, as planar RGB in [0, 1]
/// (N×3×H×W, flattened) with their names. All must be `height`×`width` (detection crops at
/// the model's crop size).
pub fn load_image_folder(dir: &std::path::Path, height: usize, width: usize) -> Result<(Vec<f32>, Vec<String>)> {
    let mut paths: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading the image folder {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| ["png", "jpg", "jpeg", "webp"].contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    paths.sort();
    if paths.is_empty() {
        bail!("{} holds no PNG, JPEG or WebP image", dir.display());
    }
    let planes = paths
        .par_iter()
        .map(|path| {
            let img = image::open(path).with_context(|| format!("decoding {}", path.display()))?.to_rgb8();
            let (w, h) = (img.width() as usize, img.height() as usize);
            if (h, w) != (height, width) {
                bail!("{}: image is {w}x{h}, the model's crop is {width}x{height}", path.display());
            }
            Ok(planar(&img))
        })
        .collect::<Result<Vec<_>>>()?;
    let names = paths.iter().map(|p| p.file_name().unwrap_or_default().to_string_lossy().into_owned()).collect();
    Ok((planes.concat(), names))
}
