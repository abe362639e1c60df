//! Weather corruptions (IN PROGRESS).

use image::RgbImage;
use rand_chacha::ChaCha8Rng;

pub fn snow(_image: &RgbImage, _severity: u8, _rng: &mut ChaCha8Rng) -> RgbImage {
    unimplemented!("snow")
}
pub fn frost(_image: &RgbImage, _severity: u8, _rng: &mut ChaCha8Rng) -> RgbImage {
    unimplemented!("frost")
}
pub fn fog(_image: &RgbImage, _severity: u8, _rng: &mut ChaCha8Rng) -> RgbImage {
    unimplemented!("fog")
}
pub fn spatter(_image: &RgbImage, _severity: u8, _rng: &mut ChaCha8Rng) -> RgbImage {
    unimplemented!("spatter")
}
