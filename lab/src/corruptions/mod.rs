//! The 19 image corruptions of ImageNet-C as shipped by `imagecorruptions` (BENCHMARK.md §3),
//! severities 1–5, in Rust. `imagecorruptions-imaug` 1.1.5 is the reference implementation:
//! `reports/corruptions.md` measures how close each one is.

mod blur;
mod digital;
/// Filters and resampling shared by the corruptions (public so tests can check them).
pub mod kernels;
mod noise;
mod weather;

use std::fmt;
use std::str::FromStr;

use image::RgbImage;
use rand_chacha::ChaCha8Rng;

/// One corruption; `name()` is the reference package's name for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Corruption {
    GaussianNoise,
    ShotNoise,
    ImpulseNoise,
    DefocusBlur,
    GlassBlur,
    MotionBlur,
    ZoomBlur,
    Snow,
    Frost,
    Fog,
    Brightness,
    Contrast,
    ElasticTransform,
    Pixelate,
    JpegCompression,
    SpeckleNoise,
    GaussianBlur,
    Spatter,
    Saturate,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CorruptionError {
    #[error("unknown corruption {0:?}; known: {known}", known = Corruption::ALL.map(|c| c.name()).join(", "))]
    Unknown(String),
    #[error("severity must be 1 to 5, got {0}")]
    Severity(u8),
    #[error("image {0}x{1} is too small to corrupt")]
    TooSmall(u32, u32),
    /// A file the corruption needs at run time is not installed (frost's textures).
    #[error("missing asset: {0}")]
    MissingAsset(String),
}

impl Corruption {
    pub const ALL: [Corruption; 19] = [
        Corruption::GaussianNoise,
        Corruption::ShotNoise,
        Corruption::ImpulseNoise,
        Corruption::DefocusBlur,
        Corruption::GlassBlur,
        Corruption::MotionBlur,
        Corruption::ZoomBlur,
        Corruption::Snow,
        Corruption::Frost,
        Corruption::Fog,
        Corruption::Brightness,
        Corruption::Contrast,
        Corruption::ElasticTransform,
        Corruption::Pixelate,
        Corruption::JpegCompression,
        Corruption::SpeckleNoise,
        Corruption::GaussianBlur,
        Corruption::Spatter,
        Corruption::Saturate,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Corruption::GaussianNoise => "gaussian_noise",
            Corruption::ShotNoise => "shot_noise",
            Corruption::ImpulseNoise => "impulse_noise",
            Corruption::DefocusBlur => "defocus_blur",
            Corruption::GlassBlur => "glass_blur",
            Corruption::MotionBlur => "motion_blur",
            Corruption::ZoomBlur => "zoom_blur",
            Corruption::Snow => "snow",
            Corruption::Frost => "frost",
            Corruption::Fog => "fog",
            Corruption::Brightness => "brightness",
            Corruption::Contrast => "contrast",
            Corruption::ElasticTransform => "elastic_transform",
            Corruption::Pixelate => "pixelate",
            Corruption::JpegCompression => "jpeg_compression",
            Corruption::SpeckleNoise => "speckle_noise",
            Corruption::GaussianBlur => "gaussian_blur",
            Corruption::Spatter => "spatter",
            Corruption::Saturate => "saturate",
        }
    }

    /// Applies the corruption at `severity` (1–5). Random corruptions draw from `rng` only, so a
    /// seeded generator gives identical output.
    pub fn apply(self, image: &RgbImage, severity: u8, rng: &mut ChaCha8Rng) -> Result<RgbImage, CorruptionError> {
        if !(1..=5).contains(&severity) {
            return Err(CorruptionError::Severity(severity));
        }
        let (w, h) = image.dimensions();
        if w < 8 || h < 8 {
            return Err(CorruptionError::TooSmall(w, h));
        }
        let s = severity;
        Ok(match self {
            Corruption::GaussianNoise => noise::gaussian_noise(image, s, rng),
            Corruption::ShotNoise => noise::shot_noise(image, s, rng),
            Corruption::ImpulseNoise => noise::impulse_noise(image, s, rng),
            Corruption::SpeckleNoise => noise::speckle_noise(image, s, rng),
            Corruption::DefocusBlur => blur::defocus_blur(image, s),
            Corruption::GlassBlur => blur::glass_blur(image, s, rng),
            Corruption::MotionBlur => blur::motion_blur(image, s, rng),
            Corruption::ZoomBlur => blur::zoom_blur(image, s),
            Corruption::GaussianBlur => blur::gaussian_blur(image, s),
            Corruption::Snow => weather::snow(image, s, rng),
            Corruption::Frost => weather::frost(image, s, rng)?,
            Corruption::Fog => weather::fog(image, s, rng),
            Corruption::Spatter => weather::spatter(image, s, rng),
            Corruption::Brightness => digital::brightness(image, s),
            Corruption::Contrast => digital::contrast(image, s),
            Corruption::Saturate => digital::saturate(image, s),
            Corruption::ElasticTransform => digital::elastic_transform(image, s, rng),
            Corruption::Pixelate => digital::pixelate(image, s),
            Corruption::JpegCompression => digital::jpeg_compression(image, s),
        })
    }
}

impl fmt::Display for Corruption {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Corruption {
    type Err = CorruptionError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Corruption::ALL.into_iter().find(|c| c.name() == s).ok_or_else(|| CorruptionError::Unknown(s.to_string()))
    }
}
