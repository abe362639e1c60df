//! Per-domain experts (ARCHITECTURE.md "Validation gate"): one shared model cannot hold two
//! domains whose BatchNorm statistics differ (`reports/continual-variants.md`), so a candidate
//! that wins its own domain but would give back an earlier one may instead join the version it
//! started from as an *expert*: a new composite version whose own tensors are the old ones and
//! whose manifest sends the images the candidate's domain takes ([`Domain`]) to the candidate.
//!
//! An expert's domain is fitted on the job's training images, with the regression sets' images
//! as its rival ([`Domain::rival`]): it takes an image that looks like its own images, and more
//! like them than like the images of the domains seen before.
//!
//! The gate compares what answers each image. Images an existing expert takes are answered by
//! that expert before and after a job, so they are left out of the comparison (a set they make
//! up entirely is not guarded: nothing the job changes answers it). The composite's verdict
//! needs no new estimate: on each image it is the candidate's check where the new domain takes
//! the image and the active version's elsewhere.

use anyhow::{Result, anyhow};
use serde_json::json;
use tch::{Kind, Tensor};
use udapose_engine::{
    checkpoint::{self, Expert, Manifest, Model},
    gate::{self, GateStats},
    signature::{Domain, STATS, Signature, image_stats, pick},
};

use super::{JobSpec, Jobs};
use crate::store::StoreError;

/// Bounds of the experts of one category.
#[derive(Clone, Debug)]
pub struct ExpertConfig {
    /// Experts a version may hold (each is one more model in every worker's memory; 0: none,
    /// a candidate that would regress an earlier domain is rejected).
    pub max: usize,
    /// Share of unseen images of its domain an expert's bound takes ([`Domain::fit`]).
    pub coverage: f64,
}

impl Default for ExpertConfig {
    fn default() -> Self {
        ExpertConfig { max: 3, coverage: 0.95 }
    }
}

/// Each crop's statistics (rows of N×3×H×W in [0, 1]).
pub(super) fn stats(images: &Tensor) -> Result<Vec<[f64; STATS]>> {
    let size = images.size();
    let [n, _, h, w] = size[..] else { return Err(anyhow!("crops of shape {size:?}")) };
    (0..n)
        .map(|i| {
            let pixels = Vec::<f32>::try_from(images.get(i).to_kind(Kind::Float).flatten(0, -1))?;
            Ok(image_stats(&pixels, [h as usize, w as usize])?)
        })
        .collect()
}

/// The rows `member` answers: expert `i` for `Some(i)`, the version's own tensors for `None`.
pub(super) fn rows_of(stats: &[[f64; STATS]], experts: &[Expert], member: Option<usize>) -> Vec<usize> {
    let domains: Vec<&Domain> = experts.iter().map(|e| &e.domain).collect();
    (0..stats.len()).filter(|&i| pick(&domains, &stats[i]) == member).collect()
}

/// What a job adapts and the gate compares the candidate with: the source version's own
/// tensors, or, where most of the job's training images go to one of its experts, that expert
/// (the candidate then replaces it in a new composite).
pub(super) struct Start {
    /// The source version (its own tensors; its manifest lists its experts).
    pub source: Model,
    /// The expert adapted, by index among the source's experts, and its model.
    pub expert: Option<(usize, Model)>,
    /// The statistics of the job's training images (routing and an expert's domain).
    pub train: Vec<[f64; STATS]>,
}

impl Start {
    pub fn model(&self) -> &Model {
        self.expert.as_ref().map_or(&self.source, |(_, m)| m)
    }

    pub fn member(&self) -> Option<usize> {
        self.expert.as_ref().map(|(i, _)| *i)
    }

    /// What the job adapts, in words.
    pub fn name(&self, spec: &JobSpec) -> String {
        match &self.expert {
            None => format!("{}'s own model", spec.source_version),
            Some((i, _)) => format!("{}'s expert {}", spec.source_version, self.source.manifest.experts[*i].version),
        }
    }
}

/// `rows` of `images`.
pub(super) fn select(images: &Tensor, rows: &[usize]) -> Tensor {
    let index: Vec<i64> = rows.iter().map(|&r| r as i64).collect();
    images.index_select(0, &Tensor::from_slice(&index))
}

/// One set of images as the gate compares them: the active version's and the candidate's checks
/// of the images the version's own tensors answer, with those images' statistics.
pub(super) struct Compared {
    pub before: GateStats,
    pub after: GateStats,
    pub stats: Vec<[f64; STATS]>,
}

impl Compared {
    /// The composite's checks with `domain` as a new expert, and how many images it takes.
    pub fn with_expert(&self, domain: &Domain) -> (GateStats, usize) {
        let mut taken = 0;
        let images = (self.before.images.iter().zip(&self.after.images).zip(&self.stats))
            .map(|((before, after), stats)| match domain.accepts(stats) {
                Some(_) => {
                    taken += 1;
                    after.clone()
                }
                None => before.clone(),
            })
            .collect();
        (GateStats { images }, taken)
    }
}

impl Jobs {
    /// Where the job starts: the expert that more than half of its training images go to, if
    /// any, else the source's own tensors.
    pub(super) fn starting_point(&self, spec: &JobSpec, source: Model) -> Result<Start> {
        let train = stats(&self.images(&spec.category, &spec.train, source.manifest.crop)?)?;
        let experts = &source.manifest.experts;
        let majority = (0..experts.len()).find(|&i| 2 * rows_of(&train, experts, Some(i)).len() > train.len());
        let expert = match majority {
            Some(i) => {
                tracing::info!(job = %spec.job_id, "most of its images look like expert {}'s: adapting it", experts[i].version);
                Some((i, self.load(spec, &experts[i].version)?))
            }
            None => None,
        };
        Ok(Start { source, expert, train })
    }

    /// Whether the candidate may join the source as an expert: its domain fitted on the job's
    /// training images, the composite's verdicts on the held-out images ([`gate::decide`]) and
    /// on every regression set ([`gate::guard`]). The expert and what it takes, or why not.
    pub(super) fn expert(
        &self,
        spec: &JobSpec,
        start: &Start,
        held: &Compared,
        sets: &[(String, Compared)],
    ) -> Result<std::result::Result<(Expert, String), String>> {
        let source = &start.source;
        let bounds = &self.config.experts;
        let held_by = source.manifest.experts.len();
        if held_by >= bounds.max {
            return Ok(Err(format!(
                "{} holds {held_by} experts, the most allowed (--max-experts {})",
                spec.source_version, bounds.max
            )));
        }
        let own: Vec<[f64; STATS]> =
            rows_of(&start.train, &source.manifest.experts, None).into_iter().map(|r| start.train[r]).collect();
        let mut domain = match Domain::fit(&own, bounds.coverage) {
            Ok(domain) => domain,
            Err(e) => return Ok(Err(format!("no domain signature: {e}"))),
        };
        // The images of the earlier domains are what the expert must leave to the version's own
        // tensors: their signature is its rival (too few of them for one: the bound alone).
        let earlier: Vec<[f64; STATS]> = sets.iter().flat_map(|(_, c)| c.stats.iter().copied()).collect();
        domain.rival = Signature::fit(&earlier).ok();
        let (mixed, taken) = held.with_expert(&domain);
        let decision = gate::decide(&held.before, &mixed, &self.config.gate)?;
        if !decision.passed {
            return Ok(Err(format!(
                "it would take {taken} of {} held-out images, too few to pass: {}",
                mixed.images.len(),
                decision.reason()
            )));
        }
        let mut shares = Vec::new();
        let mut regressed = Vec::new();
        for (set_id, c) in sets {
            let (mixed, set_taken) = c.with_expert(&domain);
            let d = gate::guard(&c.before, &mixed, &self.config.gate)?;
            shares.push(format!("{set_taken}/{} of {set_id}", mixed.images.len()));
            if !d.passed {
                regressed.push((set_id.as_str(), d));
            }
        }
        if !regressed.is_empty() {
            return Ok(Err(format!(
                "it would take {} and so still regress: {}",
                shares.join(", "),
                super::run::regressions(&regressed).join("; ")
            )));
        }
        let summary = format!(
            ", {} answering the images like its own: {taken} of {} held-out images; {}",
            spec.version,
            mixed.images.len(),
            if shares.is_empty() { "no regression set".into() } else { shares.join(", ") }
        );
        Ok(Ok((Expert { version: spec.version.clone(), domain }, summary)))
    }

    /// Saves the source's own tensors with `experts` as a new composite version (named after
    /// the candidate) and activates it.
    pub(super) fn activate_composite(
        &self,
        spec: &JobSpec,
        source: &Model,
        experts: Vec<Expert>,
        reason: &str,
        summary: &str,
        criteria: Vec<udapose_api::GateCriterion>,
    ) -> Result<()> {
        let composite = format!("{}-experts", spec.version);
        let manifest = Manifest {
            version: composite.clone(),
            training: json!({
                "kind": "experts",
                "job_id": spec.job_id,
                "base": spec.source_version,
                "candidate": spec.version,
                "base_training": source.manifest.training,
            }),
            metrics: serde_json::Value::Null,
            files: Default::default(),
            experts,
            ..source.manifest.clone()
        };
        // Saved before a restart: validation is deterministic, so the same composite.
        match self.store.manifest(&spec.category, &composite) {
            Ok(_) => {}
            Err(StoreError::UnknownVersion { .. }) => self.store.put_version(&spec.category, &composite, |dir| {
                checkpoint::save(dir, &manifest, &source.vs, &source.neural_mesh).map_err(|e| e.to_string())
            })?,
            Err(e) => return Err(e.into()),
        }
        self.activate(spec, &composite, reason, criteria, summary.to_owned())
    }
}

#[cfg(test)]
mod tests {
    use udapose_engine::gate::ImageCheck;

    use super::*;

    /// Statistics around `centre` on every axis, spread by a fixed pseudo-random pattern.
    fn cloud(centre: f64, n: usize) -> Vec<[f64; STATS]> {
        (0..n).map(|i| std::array::from_fn(|k| centre + (((i * 7 + k * 13) % 17) as f64 - 8.0) / 20.0)).collect()
    }

    fn checks(margin: f64, n: usize) -> GateStats {
        GateStats {
            images: (0..n).map(|_| ImageCheck { azimuth: 0.0, score: 0.5, margin, flip_consistent: true }).collect(),
        }
    }

    #[test]
    fn the_composite_takes_the_candidates_checks_where_its_domain_takes_the_image() {
        let near = cloud(0.0, 40);
        let domain = Domain::fit(&near, 0.95).unwrap();
        // Ten images like the domain's, ten far from it.
        let mut stats = cloud(0.0, 10);
        stats.extend(cloud(5.0, 10));
        let compared = Compared { before: checks(0.1, 20), after: checks(0.3, 20), stats };
        let (mixed, taken) = compared.with_expert(&domain);
        assert!((8..=10).contains(&taken), "{taken}");
        assert!(mixed.images[10..].iter().all(|c| c.margin == 0.1), "far images keep the source's checks");
        assert_eq!(mixed.images[..10].iter().filter(|c| c.margin == 0.3).count(), taken);
        // An existing expert with that domain answers the near images: only the far ones are
        // the version's own.
        let expert = Expert { version: "v".into(), domain };
        let own = |experts: &[Expert]| rows_of(&compared.stats, experts, None);
        assert_eq!(own(std::slice::from_ref(&expert)), (10..20).collect::<Vec<_>>());
        assert_eq!(rows_of(&compared.stats, std::slice::from_ref(&expert), Some(0)).len(), taken);
        assert_eq!(own(&[]).len(), 20);
    }

    #[test]
    fn rows_are_selected_from_the_crops() {
        let images = Tensor::arange(4 * 3 * 8 * 8, (Kind::Float, tch::Device::Cpu)).view([4, 3, 8, 8]) / 768.0;
        let picked = select(&images, &[1, 3]);
        assert_eq!(picked.size(), [2, 3, 8, 8]);
        assert!(picked.get(1).equal(&images.get(3)));
        assert_eq!(stats(&images).unwrap().len(), 4);
        assert!(stats(&images.view([4, 192])).is_err(), "not N×3×H×W");
    }
}
