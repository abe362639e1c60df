//! Images of no object at all: smooth random colour fields with stripes. The target check's
//! negatives (`udapose-lab target-check`, reports/target-check.md) and the service test's job
//! on images that are not cars (tests/tests/adapt.rs) draw the same fields.

/// Field `index` of the sequence, `width`×`height`. The fields are defined on a 160×64 canvas
/// (where the test draws them) and sampled at the canvas position of each pixel, so a larger
/// crop shows the same field at a finer resolution.
pub fn colour_field(index: usize, width: u32, height: u32) -> image::RgbImage {
    let mut draws = Xorshift(0x9e37_79b9_7f4a_7c15);
    // Six draws per field, so field `index` starts after 6·index of them.
    for _ in 0..6 * index {
        draws.next();
    }
    let (fx, fy, phase) = (draws.next() * 0.3, draws.next() * 0.3, draws.next() * 6.0);
    let base = [draws.next(), draws.next(), draws.next()];
    let (sx, sy) = (160.0 / f64::from(width), 64.0 / f64::from(height));
    image::RgbImage::from_fn(width, height, |x, y| {
        let wave = ((f64::from(x) * sx * fx + f64::from(y) * sy * fy + phase).sin() + 1.0) / 2.0;
        image::Rgb(base.map(|b| ((b * 0.6 + wave * 0.4) * 255.0) as u8))
    })
}

/// xorshift64: tiny, seeded, the same sequence everywhere.
struct Xorshift(u64);

impl Xorshift {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_differ_and_a_larger_crop_draws_the_same_field() {
        let (a, b) = (colour_field(0, 160, 64), colour_field(1, 160, 64));
        assert_ne!(a, b);
        assert_eq!(a, colour_field(0, 160, 64), "seeded: the same field each time");
        // At twice the size, every other pixel is the small field's pixel.
        let big = colour_field(0, 320, 128);
        assert!((0..64).all(|y| (0..160).all(|x| big.get_pixel(2 * x, 2 * y) == a.get_pixel(x, y))));
    }
}
