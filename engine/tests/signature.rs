//! Domain signatures: statistics that move the right way, and routing that tells domains of
//! different image statistics apart.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use udapose_engine::signature::{Domain, STATS, Signature, image_stats, pick, route};

const H: usize = 32;
const W: usize = 80;

/// A "clear" image: smooth colour gradients with sharp-edged blocks and a little noise.
fn clear(rng: &mut ChaCha8Rng) -> Vec<f32> {
    let mut px = vec![0f32; 3 * H * W];
    let base: [f32; 3] = [rng.random_range(0.2..0.8), rng.random_range(0.2..0.8), rng.random_range(0.2..0.8)];
    let blocks: Vec<(usize, usize, f32)> =
        (0..6).map(|_| (rng.random_range(0..H - 8), rng.random_range(0..W - 8), rng.random_range(-0.4..0.4))).collect();
    for c in 0..3 {
        for y in 0..H {
            for x in 0..W {
                let mut v = base[c] + 0.2 * (x as f32 / W as f32 - 0.5) + rng.random_range(-0.02..0.02);
                for &(by, bx, d) in &blocks {
                    if (by..by + 8).contains(&y) && (bx..bx + 8).contains(&x) {
                        v += d;
                    }
                }
                px[(c * H + y) * W + x] = v.clamp(0.0, 1.0);
            }
        }
    }
    px
}

/// A 5×5 box blur of each plane (edges clamped).
fn blurred(px: &[f32]) -> Vec<f32> {
    let mut out = vec![0f32; px.len()];
    for c in 0..3 {
        for y in 0..H {
            for x in 0..W {
                let mut sum = 0.0;
                for dy in -2i64..=2 {
                    for dx in -2i64..=2 {
                        let yy = (y as i64 + dy).clamp(0, H as i64 - 1) as usize;
                        let xx = (x as i64 + dx).clamp(0, W as i64 - 1) as usize;
                        sum += px[(c * H + yy) * W + xx];
                    }
                }
                out[(c * H + y) * W + x] = sum / 25.0;
            }
        }
    }
    out
}

/// Haze: the image pulled toward a bright grey.
fn hazy(px: &[f32]) -> Vec<f32> {
    px.iter().map(|v| 0.45 * v + 0.5).collect()
}

fn stats(px: &[f32]) -> [f64; STATS] {
    image_stats(px, [H, W]).unwrap()
}

#[test]
fn statistics_move_with_blur_and_haze() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let image = clear(&mut rng);
    let [c, b, f] = [stats(&image), stats(&blurred(&image)), stats(&hazy(&image))];
    // Blur keeps the colour means, and removes gradient, Laplacian and high-frequency energy.
    for i in 0..3 {
        assert!((c[i] - b[i]).abs() < 0.05, "mean {i}: {} vs {}", c[i], b[i]);
    }
    for i in 6..10 {
        assert!(b[i] < c[i] - 0.3, "statistic {i}: clear {} blurred {}", c[i], b[i]);
    }
    // Haze raises the dark channel and lowers the spread and the saturation.
    assert!(f[11] > c[11] + 0.2 && f[12] < c[12] - 0.3, "{c:?} {f:?}");
    for i in 3..6 {
        assert!(f[i] < c[i] - 0.3);
    }
}

/// `n` images' statistics of domain `k`: 0 clear, 1 blurred, 2 hazy.
fn domain(rng: &mut ChaCha8Rng, k: usize, n: usize) -> Vec<[f64; STATS]> {
    (0..n)
        .map(|_| {
            let image = clear(rng);
            stats(&match k {
                0 => image,
                1 => blurred(&image),
                _ => hazy(&image),
            })
        })
        .collect()
}

#[test]
fn images_are_routed_to_the_domain_they_come_from() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let fitted: Vec<Signature> = (0..3).map(|k| Signature::fit(&domain(&mut rng, k, 40)).unwrap()).collect();
    let signatures: Vec<&Signature> = fitted.iter().collect();
    for k in 0..3 {
        let fresh = domain(&mut rng, k, 40);
        let share = fresh.iter().filter(|s| route(&signatures, s) == Some(k)).count() as f64 / fresh.len() as f64;
        assert!(share >= 0.95, "domain {k}: {share} routed to its own signature");
    }
    // Each image goes where its likelihood is highest.
    let image = domain(&mut rng, 1, 1)[0];
    let best = (0..3).max_by(|&a, &b| fitted[a].log_likelihood(&image).total_cmp(&fitted[b].log_likelihood(&image)));
    assert_eq!(route(&signatures, &image), best);
    assert_eq!(route(&[], &image), None);
}

#[test]
fn signatures_survive_json_and_refuse_bad_input() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let sample: Vec<[f64; STATS]> = (0..30).map(|_| stats(&clear(&mut rng))).collect();
    let signature = Signature::fit(&sample).unwrap();
    assert_eq!(signature.images, 30);
    let back: Signature = serde_json::from_str(&serde_json::to_string(&signature).unwrap()).unwrap();
    // serde_json's default float parsing may move the last bit.
    let (a, b) = (back.log_likelihood(&sample[0]), signature.log_likelihood(&sample[0]));
    assert!((a - b).abs() < 1e-9 * b.abs(), "{a} vs {b}");
    assert!(Signature::fit(&sample[..STATS + 1]).is_err(), "too few images");
    assert!(Signature::fit(&vec![sample[0]; 30]).is_err(), "identical images");
    assert!(image_stats(&[0.5; 3 * 3 * 3], [3, 3]).is_err(), "too small");
    assert!(image_stats(&[0.5; 10], [H, W]).is_err(), "wrong length");
}

#[test]
fn a_domain_takes_its_own_images_and_refuses_others() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let blur = Domain::fit(&domain(&mut rng, 1, 60), 0.95).unwrap();
    let haze = Domain::fit(&domain(&mut rng, 2, 60), 0.95).unwrap();
    let share = |k: usize, d: &Domain, rng: &mut ChaCha8Rng| {
        domain(rng, k, 60).iter().filter(|s| d.accepts(s).is_some()).count() as f64 / 60.0
    };
    // Fresh images of its own domain pass the bound about as often as it was set for;
    // clear images, whose statistics no domain was fitted on, are refused by both.
    assert!(share(1, &blur, &mut rng) >= 0.8, "blur takes {}", share(1, &blur, &mut rng));
    assert!(share(2, &haze, &mut rng) >= 0.8, "haze takes {}", share(2, &haze, &mut rng));
    assert!(share(0, &blur, &mut rng) <= 0.05 && share(0, &haze, &mut rng) <= 0.05);
    assert!(share(2, &blur, &mut rng) <= 0.05 && share(1, &haze, &mut rng) <= 0.05);
    // `pick` sends a blurred image to blur, a clear one to none.
    let (b, c) = (domain(&mut rng, 1, 20), domain(&mut rng, 0, 1)[0]);
    let picked = b.iter().filter(|s| pick(&[&haze, &blur], s) == Some(1)).count();
    assert!(picked >= 16, "{picked} of 20 blurred images picked blur");
    assert_eq!(pick(&[&haze, &blur], &c), None);
    assert_eq!(pick(&[], &c), None);
    // A domain fitted on clear and blurred images alike takes some blurred ones; a rival
    // fitted on blurred images keeps those, and leaves the clear ones to the domain.
    let mut broad = domain(&mut rng, 0, 40);
    broad.extend(domain(&mut rng, 1, 20));
    let mut broad = Domain::fit(&broad, 0.95).unwrap();
    let blurred_taken =
        |d: &Domain, rng: &mut ChaCha8Rng| domain(rng, 1, 40).iter().filter(|s| d.accepts(s).is_some()).count();
    assert!(blurred_taken(&broad, &mut rng) >= 20, "{}", blurred_taken(&broad, &mut rng));
    broad.rival = Some(blur.signature.clone());
    assert!(blurred_taken(&broad, &mut rng) <= 2, "{}", blurred_taken(&broad, &mut rng));
    assert!(share(0, &broad, &mut rng) >= 0.8, "{}", share(0, &broad, &mut rng));
    // Coverage 1 keeps every fitted image; a coverage outside (0, 1] is refused.
    let fitted = domain(&mut rng, 2, 30);
    let all = Domain::fit(&fitted, 1.0).unwrap();
    assert!(fitted.iter().all(|s| all.accepts(s).is_some()));
    assert!(Domain::fit(&fitted[..16], 0.9).is_err(), "a fold's rest is too small to fit");
    assert!(Domain::fit(&fitted, 0.0).is_err() && Domain::fit(&fitted, 1.5).is_err());
}
