//! SynCar-OOD (BENCHMARK.md): every domain and split, rendered deterministically from a seed.
//!
//! Each sample draws from its own generator, seeded by `(seed, domain, split, index)`, so samples
//! can be rendered in any order, in parallel, and a run that stopped resumes where it was: a
//! sample is done when its annotation (written last) exists.

mod domains;
mod nuisance;
mod occlusion;

use anyhow::Result;
use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;
use sha2::{Digest, Sha256};
use udapose_engine::camera::fit_distance;
use udapose_engine::{Camera, Cuboid, Pose};

pub use domains::{Domain, Nuisance, all_domains};

use crate::assets::Assets;
use crate::assets::backgrounds::{Backgrounds, Group, random_crop};
use crate::assets::category::{Catalogue, Category};
use crate::datasets::syncar::Annotation;
use crate::datasets::{CropPose, Mask};
use crate::render::{Layer, Light, Model, Renderer};

/// Supersampling factor per axis: 9 samples per pixel.
pub const SUPERSAMPLE: usize = 3;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    Quick,
    Standard,
    Full,
}

impl Profile {
    pub fn name(self) -> &'static str {
        match self {
            Profile::Quick => "quick",
            Profile::Standard => "standard",
            Profile::Full => "full",
        }
    }

    /// Crop `(height, width)`.
    pub fn crop(self) -> (usize, usize) {
        match self {
            Profile::Quick => (64, 160),
            Profile::Standard => (128, 320),
            Profile::Full => (256, 672),
        }
    }

    /// Images in a split.
    pub fn count(self, split: &str) -> usize {
        let [train, val, other] = match self {
            Profile::Quick => [300, 60, 60],
            Profile::Standard => [3000, 300, 300],
            Profile::Full => [10000, 1000, 1000],
        };
        match split {
            "train" => train,
            "val" => val,
            _ => other,
        }
    }
}

/// Everything a sample is drawn from, loaded once per run.
pub struct World {
    pub catalogue: Catalogue,
    /// The source models, then the `shape` domain's; a model's index here is its `cad_index`.
    pub models: Vec<(String, Model)>,
    pub backgrounds: Backgrounds,
    /// The category cuboid: 99% extent of the pooled source-model vertices (METHOD.md §3).
    pub cuboid: Cuboid,
}

impl World {
    pub fn load(assets: &Assets, category: Category, crop_height: usize) -> Result<Self> {
        let catalogue = Catalogue::of(assets, category)?;
        let models: Vec<(String, Model)> = catalogue
            .source
            .iter()
            .chain(&catalogue.shape)
            .map(|n| Ok((n.clone(), Model::new(catalogue.load(assets, n)?)?)))
            .collect::<Result<_>>()?;
        let pooled: Vec<[f64; 3]> =
            models[..catalogue.source.len()].iter().flat_map(|(_, m)| m.mesh.vertices().iter().copied()).collect();
        let cuboid = Cuboid::from_cad_vertices(&pooled, udapose_engine::mesh::CAD_COVERAGE)?;
        let backgrounds = Backgrounds::load(&assets.torcs, (2 * crop_height).max(256) as u32)?;
        Ok(World { catalogue, models, backgrounds, cuboid })
    }

    /// Index of a model in `models` (= its `cad_index`).
    fn model_index(&self, name: &str) -> usize {
        self.models.iter().position(|(n, _)| n == name).expect("known model")
    }
}

/// A rendered sample and its ground truth.
pub struct Sample {
    pub image: RgbImage,
    pub annotation: Annotation,
}

/// The generator of one sample.
pub fn sample_rng(seed: u64, domain: &str, split: &str, index: usize) -> ChaCha8Rng {
    let digest = Sha256::digest(format!("syncar-ood/{seed}/{domain}/{split}/{index}"));
    ChaCha8Rng::from_seed(digest.into())
}

/// Renders sample `index` of `split` in `domain`.
pub fn render_sample(
    world: &World,
    renderer: &mut Renderer,
    profile: Profile,
    domain: &Domain,
    rng: &mut ChaCha8Rng,
) -> Result<Sample> {
    let (height, width) = profile.crop();
    let nuisances = domain.nuisances(rng);
    let has = |n: Nuisance| nuisances.contains(&n);

    let names = if has(Nuisance::Shape) { &world.catalogue.shape } else { &world.catalogue.source };
    let name = &names[rng.random_range(0..names.len())];
    let cad_index = world.model_index(name);
    let model = &world.models[cad_index].1;
    let angles = sample_angles(rng, has(Nuisance::Pose));
    let fill = rng.random_range(0.80..0.95);
    let distance = fit_distance(model.mesh.vertices(), angles, &Camera::for_crop(height, width)?, fill)?;
    let pose = Pose::new(angles[0], angles[1], angles[2], distance);
    let light = random_light(rng);

    let textures = if has(Nuisance::Texture) {
        Some(nuisance::retexture(&model.textured.textures, &world.backgrounds.source, rng))
    } else {
        None
    };
    let layer: Layer = renderer.render(model, textures.as_deref(), &pose, height, width, &light)?;
    let group = if has(Nuisance::Context) { Group::Context } else { Group::Source };
    let pool = world.backgrounds.group(group);
    let background = random_crop(&pool[rng.random_range(0..pool.len())], width as u32, height as u32, rng);
    let (mut image, mask) = layer.composite(&background);

    let occlusion = match domain.occlusion {
        Some(band) => Some(occlusion::occlude(&mut image, &mask, band, &world.backgrounds.source, rng)?),
        None => None,
    };
    if has(Nuisance::Weather) {
        image = nuisance::weather(&image, rng)?;
    }
    if let Some((corruption, severity)) = domain.corruption {
        image = corruption.apply(&image, severity, rng)?;
    }
    let pose = CropPose {
        azimuth: pose.azimuth,
        elevation: pose.elevation,
        theta: pose.theta,
        distance: pose.distance,
        principal: [width as f64 / 2.0, height as f64 / 2.0],
        viewport: udapose_engine::camera::VIEWPORT_AT_256 * height as f64 / 256.0,
        focal: 1.0,
        height,
        width,
    };
    let mask = Mask::new(height, width, mask).expect("the renderer makes a full-size mask");
    let (occ_fraction, occluder) = match occlusion {
        Some(o) => (Some(o.fraction), Mask::new(height, width, o.covered)),
        None => (None, None),
    };
    let annotation =
        Annotation { pose, fill, car: name.clone(), cad_index: cad_index as i64, mask, occ_fraction, occluder };
    Ok(Sample { image, annotation })
}

/// Source poses: azimuth uniform, elevation −10°…40°, θ ~ N(0, 5°) clipped to ±15°; the `pose`
/// domain: elevation 30°…70°, θ ~ N(0, 15°) clipped to ±40°.
fn sample_angles(rng: &mut ChaCha8Rng, pose_shift: bool) -> [f64; 3] {
    let (elevation, sigma, clip): ((f64, f64), f64, f64) =
        if pose_shift { ((30.0, 70.0), 15.0, 40.0) } else { ((-10.0, 40.0), 5.0, 15.0) };
    let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
    let elevation = rng.random_range(elevation.0..elevation.1).to_radians();
    let theta: f64 = Normal::new(0.0, sigma).expect("valid sigma").sample(rng);
    [azimuth, elevation, theta.clamp(-clip, clip).to_radians()]
}

/// A light from a random direction above the horizon, with random strength.
fn random_light(rng: &mut ChaCha8Rng) -> Light {
    let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
    let elevation = rng.random_range(0.15..1.45f64);
    let direction = [elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin()];
    Light { direction, ambient: rng.random_range(0.35..0.55), diffuse: rng.random_range(0.45..0.75) }
}
