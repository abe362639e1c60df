//! The domains of SynCar-OOD (BENCHMARK.md §3) and what each changes.

use rand::Rng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

use crate::corruptions::Corruption;

/// A way a target image differs from the source distribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Nuisance {
    Shape,
    Texture,
    Context,
    Weather,
    Pose,
}

const ALL_NUISANCES: [Nuisance; 5] =
    [Nuisance::Shape, Nuisance::Texture, Nuisance::Context, Nuisance::Weather, Nuisance::Pose];

/// Which nuisances a domain's images get.
#[derive(Clone, Debug)]
pub enum Nuisances {
    Fixed(Vec<Nuisance>),
    /// One or two of the five, at random per image (`combined`).
    Random,
}

#[derive(Clone, Debug)]
pub struct Domain {
    pub name: String,
    pub splits: &'static [&'static str],
    pub nuisances: Nuisances,
    pub corruption: Option<(Corruption, u8)>,
    /// Band of the object mask the occluders must cover.
    pub occlusion: Option<(f64, f64)>,
}

const TARGET_SPLITS: &[&str] = &["adapt", "test"];

impl Domain {
    fn new(name: &str, nuisances: Nuisances) -> Self {
        Domain { name: name.into(), splits: TARGET_SPLITS, nuisances, corruption: None, occlusion: None }
    }

    /// The nuisances of one image (drawn for `combined`).
    pub fn nuisances(&self, rng: &mut ChaCha8Rng) -> Vec<Nuisance> {
        match &self.nuisances {
            Nuisances::Fixed(n) => n.clone(),
            Nuisances::Random => {
                let mut all = ALL_NUISANCES;
                all.shuffle(rng);
                all[..rng.random_range(1..=2)].to_vec()
            }
        }
    }
}

/// Every domain, in the order they are generated.
pub fn all_domains() -> Vec<Domain> {
    let mut source = Domain::new("source", Nuisances::Fixed(vec![]));
    source.splits = &["train", "val", "adapt", "test"];
    let mut domains = vec![source];
    for (name, n) in [
        ("shape", Nuisance::Shape),
        ("texture", Nuisance::Texture),
        ("context", Nuisance::Context),
        ("weather", Nuisance::Weather),
        ("pose", Nuisance::Pose),
    ] {
        domains.push(Domain::new(name, Nuisances::Fixed(vec![n])));
    }
    domains.push(Domain::new("combined", Nuisances::Random));
    for c in Corruption::ALL {
        let mut d = Domain::new(&format!("corrupt/{}", c.name()), Nuisances::Fixed(vec![]));
        d.corruption = Some((c, 3));
        domains.push(d);
    }
    for (level, band) in [(1, (0.2, 0.4)), (2, (0.4, 0.6)), (3, (0.6, 0.8))] {
        let mut d = Domain::new(&format!("occ-l{level}"), Nuisances::Random);
        d.occlusion = Some(band);
        domains.push(d);
    }
    let mut extreme = Domain::new("extreme-l2", Nuisances::Random);
    extreme.occlusion = Some((0.4, 0.6));
    extreme.corruption = Some((Corruption::SpeckleNoise, 3));
    domains.push(extreme);
    domains
}
