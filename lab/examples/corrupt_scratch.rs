// TEMPORARY scratch tool (weather/digital helper): corrupt_scratch IN OUT_PREFIX NAME SEVERITY SEEDS
use rand::SeedableRng;
use udapose_lab::corruptions::Corruption;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let img = image::open(&a[1]).unwrap().to_rgb8();
    let c: Corruption = a[3].parse().unwrap();
    let s: u8 = a[4].parse().unwrap();
    let n: u64 = a[5].parse().unwrap();
    for seed in 0..n {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let out = c.apply(&img, s, &mut rng).unwrap();
        out.save(format!("{}_{seed}.png", a[2])).unwrap();
    }
}
