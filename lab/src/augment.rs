//! Photometric augmentation for source training: colour jitter (brightness, contrast,
//! saturation), random grayscale and a mild Gaussian blur, drawn per image from a seeded RNG.
//! Deliberately none of SynCar-OOD's 19 corruptions nor its occluders: the model must not have
//! seen the target domains (an occluder-augmented model is a separate experiment).

use rand::Rng;
use tch::{Kind, Tensor};

/// Ranges of the augmentation; factors are drawn uniformly from `[1 − x, 1 + x]`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Photometric {
    pub brightness: f64,
    pub contrast: f64,
    pub saturation: f64,
    /// Probability of replacing the image by its luma.
    pub grayscale: f64,
    /// Probability of a Gaussian blur, and the range of its σ in pixels.
    pub blur: f64,
    pub blur_sigma: [f64; 2],
}

impl Default for Photometric {
    fn default() -> Self {
        Photometric {
            brightness: 0.3,
            contrast: 0.3,
            saturation: 0.3,
            grayscale: 0.1,
            blur: 0.2,
            blur_sigma: [0.3, 1.0],
        }
    }
}

/// ITU-R BT.601 luma of N×3×H×W RGB, N×1×H×W.
fn luma(x: &Tensor) -> Tensor {
    let w = Tensor::from_slice(&[0.299f32, 0.587, 0.114]).to_device(x.device()).view([1, 3, 1, 1]);
    (x * w).sum_dim_intlist([1i64].as_slice(), true, Kind::Float)
}

/// A normalised 1-D Gaussian of radius 2 (5 taps).
fn gaussian(sigma: f64) -> Vec<f32> {
    let k: Vec<f64> = (-2..=2).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f64 = k.iter().sum();
    k.iter().map(|v| (v / sum) as f32).collect()
}

/// Separable 5×5 blur of one 1×3×H×W image, edges replicated.
fn blur(x: &Tensor, sigma: f64) -> Tensor {
    let k = Tensor::from_slice(&gaussian(sigma)).to_device(x.device());
    let horizontal = k.view([1, 1, 1, 5]).repeat([3, 1, 1, 1]);
    let vertical = k.view([1, 1, 5, 1]).repeat([3, 1, 1, 1]);
    let y = x.replication_pad2d([2, 2, 0, 0]).conv2d(&horizontal, None::<Tensor>, [1, 1], [0, 0], [1, 1], 3);
    y.replication_pad2d([0, 0, 2, 2]).conv2d(&vertical, None::<Tensor>, [1, 1], [0, 0], [1, 1], 3)
}

impl Photometric {
    /// Augments N×3×H×W RGB in [0, 1]; the result stays in [0, 1].
    pub fn apply(&self, images: &Tensor, rng: &mut impl Rng) -> Tensor {
        let n = images.size()[0];
        let mut out = Vec::with_capacity(n as usize);
        for i in 0..n {
            let mut factor = |range: f64| 1.0 + rng.random_range(-range..=range);
            let (b, c, s) = (factor(self.brightness), factor(self.contrast), factor(self.saturation));
            // A new tensor, never `*=` on the narrowed view: that would write into `images`.
            let mut x = images.narrow(0, i, 1) * b;
            let mean = luma(&x).mean(Kind::Float);
            x = (x - &mean) * c + &mean;
            let gray = luma(&x);
            x = (x - &gray) * s + &gray;
            if rng.random_bool(self.grayscale) {
                x = luma(&x).expand([1, 3, -1, -1], false);
            }
            if rng.random_bool(self.blur) {
                x = blur(&x.clamp(0.0, 1.0), rng.random_range(self.blur_sigma[0]..=self.blur_sigma[1]));
            }
            out.push(x.clamp(0.0, 1.0));
        }
        Tensor::cat(&out, 0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn augmentation_keeps_range_and_shape_and_changes_the_image() {
        let x = Tensor::rand([4, 3, 16, 24], (Kind::Float, tch::Device::Cpu));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let y = Photometric::default().apply(&x, &mut rng);
        assert_eq!(y.size(), x.size());
        assert!(y.min().double_value(&[]) >= 0.0 && y.max().double_value(&[]) <= 1.0);
        assert!((&y - &x).abs().mean(Kind::Float).double_value(&[]) > 1e-3);
        let none = Photometric {
            brightness: 0.0,
            contrast: 0.0,
            saturation: 0.0,
            grayscale: 0.0,
            blur: 0.0,
            ..Default::default()
        };
        let same = none.apply(&x, &mut rng);
        assert!((&same - &x).abs().max().double_value(&[]) < 1e-6, "zero ranges must leave the image alone");
    }

    #[test]
    fn blur_preserves_a_constant_image_and_grayscale_has_equal_channels() {
        let x = Tensor::full([1, 3, 8, 8], 0.4, (Kind::Float, tch::Device::Cpu));
        assert!((blur(&x, 1.0) - &x).abs().max().double_value(&[]) < 1e-6);
        let all_gray = Photometric { grayscale: 1.0, blur: 0.0, ..Default::default() };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let g = all_gray.apply(&Tensor::rand([2, 3, 8, 8], (Kind::Float, tch::Device::Cpu)), &mut rng);
        assert!((g.narrow(1, 0, 1) - g.narrow(1, 2, 1)).abs().max().double_value(&[]) < 1e-6);
    }
}
