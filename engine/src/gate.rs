//! The label-free validation gate (ARCHITECTURE.md "Validation gate"): an adapted model replaces
//! the active one only if it does at least as well on three criteria computed without labels on
//! held-out images.
//!
//! - **flip consistency**: the estimate of the horizontally mirrored crop should be the mirrored
//!   pose `(−a, e, −θ)` (cars are left-right symmetric; `tests/gate.rs` checks the convention
//!   against [`crate::camera`] to 1e-12 px). The fraction within [`FLIP_TOLERANCE`] may fall by
//!   at most `flip_se` standard errors of the paired per-image difference.
//! - **score margin**: the estimate's score minus the best score among the grid poses more than
//!   [`MARGIN_SEPARATION`] from it; the median over images must rise by `margin_gain`. A
//!   collapsed feature space scores every pose alike, so its margins go to 0.
//! - **pose diversity**: the entropy (nats) of the estimated azimuths' histogram (12 bins
//!   centred on the grid azimuths) must be at least `min(H_active − entropy_drop, entropy_floor)`.
//!
//! [`measure`] computes each model's per-image checks on the same images; [`decide`] compares
//! the two. [`held_out`] is the rule that sets the held-out images apart.

use std::f64::consts::{FRAC_PI_4, FRAC_PI_6, TAU};
use std::ops::ControlFlow;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::adapt::Event;
use crate::camera::{Pose, rotation};
use crate::checkpoint::{Manifest, Model};
use crate::error::{EngineError, Result};
use crate::estimator::{self, Features, PoseSolver};
use crate::metrics::rotation_error;
use crate::solver::{Estimate, ScoredPose, SolverConfig};

/// An image is flip-consistent when its mirrored crop's estimate is within this geodesic angle
/// of the mirrored pose: π/6, the benchmark's accuracy threshold.
pub const FLIP_TOLERANCE: f64 = FRAC_PI_6;
/// The score margin compares the estimate with the best grid pose farther than this (π/4, the
/// solver's separation of hypotheses).
pub const MARGIN_SEPARATION: f64 = FRAC_PI_4;
/// Bins of the azimuth histogram, centred on the grid azimuths 0°, 30°, …, 330°.
pub const AZIMUTH_BINS: usize = 12;
/// Images per backbone forward pass in [`measure`] (each with its mirror: 32 crops a pass).
pub const MEASURE_BATCH: usize = 16;

/// The gate's settings.
///
/// # How `margin_gain` was chosen: 0.001
///
/// Measured with `udapose-bench gate` (reports/gate.md) on SynCar-OOD `standard`: per
/// domain (15), the source model against its 3DUDA adaptation, both measured on the held-out
/// bucket of the domain's *adapt* split (48–76 images). The labels serve only to score the
/// choice: for each value of the grid 0, 0.001, 0.0025, 0.005, …, 0.05, how many domains'
/// decisions agree with the sign of the true Acc@π/6 change on the whole adapt split. 0 to
/// 0.015 all agree in 13 of 15 domains, larger values in fewer. Of that plateau the default is
/// the smallest *positive* value: the margin must actually rise, since with 0 a no-op
/// adaptation passes (on images where no vertex fires, e.g. images of no car, 3DUDA selects
/// nothing and returns the source's weights bit for bit, and the gate would "approve" them).
/// (The rule first declared was "ties to the smallest", which gives 0; it was changed for that
/// reason, not for any accuracy figure.) Why no larger value: 3DUDA raises the median margin in
/// every standard domain, the failed adaptations (fog, contrast) most of all (0.05 → 0.29 and
/// 0.05 → 0.45: confident and collapsed onto a few azimuths, which pose diversity rejects), so a
/// larger gain buys nothing there; and margins scale with the model (0.05–0.3 for the shipped
/// model, about 0.01 for the 2-epoch quick model, whose adaptations raise it by about 0.003),
/// so a larger absolute gain tuned on one model would reject every candidate of the other.
/// The test split was never used to choose; reports/gate.md shows how the choice fares on it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GateConfig {
    /// The candidate's median score margin must be at least the active model's plus this.
    pub margin_gain: f64,
    /// The candidate's flip-consistency rate may fall below the active model's by at most this
    /// many standard errors of the paired per-image difference: 2.
    pub flip_se: f64,
    /// Nats the azimuth entropy may drop: 0.25.
    pub entropy_drop: f64,
    /// An entropy at or above this (nats) always passes: 1.0 (a domain seen only from a few
    /// directions is allowed).
    pub entropy_floor: f64,
    /// Fewest held-out images to decide on: 4.
    pub min_images: usize,
    /// Before any of the above, the target images must look like the category to the active
    /// model: before 3DUDA's first round, at least this share of visible vertices must fire on
    /// average to the unchanged model ([`target_fired`]; a job that fails it stops there).
    /// Judged after the BatchNorm step, a job on colour fields fired at 0.12 after 5 rounds and
    /// passed the gate. Unset (the default): the model's own threshold
    /// (`Manifest::min_target_fired`, measured by `udapose-lab target-check`), else
    /// [`DEFAULT_MIN_TARGET_FIRED`]; set, it holds for every model.
    /// What images of no object and each benchmark domain read, per shipped model, is in
    /// reports/target-check.md: the car model reads 0.000 on colour fields and 0.043
    /// (extreme-l2) to 0.72 on its domains, the aeroplane model already 0.126 on colour fields,
    /// so no one threshold serves every model. Quick models (2 epochs) read 0.003–0.022 on
    /// colour fields and real fog alike: for them the check separates nothing, so the service
    /// test runs the shipped model.
    pub min_target_fired: Option<f64>,
    /// On each regression set (held-out images of earlier jobs, anchor images), a criterion of
    /// [`guard`] may fall below the active model's by at most this many standard errors of its
    /// paired per-image difference: 2, the flip-consistency rule's.
    pub regression_se: f64,
    /// The solver both models are measured with.
    pub solver: SolverConfig,
}

impl Default for GateConfig {
    fn default() -> Self {
        GateConfig {
            margin_gain: DEFAULT_MARGIN_GAIN,
            flip_se: 2.0,
            entropy_drop: 0.25,
            entropy_floor: 1.0,
            min_images: 4,
            min_target_fired: None,
            regression_se: 2.0,
            solver: SolverConfig::default(),
        }
    }
}

/// See [`GateConfig`]'s "How `margin_gain` was chosen".
pub const DEFAULT_MARGIN_GAIN: f64 = 0.001;

/// The target check's threshold for a model that has none measured: the one first chosen for
/// the car model (its domains read 0.027 and up then; colour fields 0.000).
pub const DEFAULT_MIN_TARGET_FIRED: f64 = 0.02;

impl GateConfig {
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(EngineError::InvalidInput(m));
        for (name, v) in [
            ("margin_gain", self.margin_gain),
            ("flip_se", self.flip_se),
            ("entropy_drop", self.entropy_drop),
            ("entropy_floor", self.entropy_floor),
            ("regression_se", self.regression_se),
        ] {
            if !v.is_finite() {
                return bad(format!("gate {name} must be finite, got {v}"));
            }
        }
        if self.flip_se < 0.0 || self.entropy_drop < 0.0 || self.regression_se < 0.0 {
            return bad(format!(
                "gate flip_se {}, entropy_drop {} and regression_se {} must be >= 0",
                self.flip_se, self.entropy_drop, self.regression_se
            ));
        }
        if self.min_images == 0 {
            return bad("gate min_images must be at least 1".into());
        }
        if let Some(m) = self.min_target_fired.filter(|m| !(0.0..=1.0).contains(m)) {
            return bad(format!("gate min_target_fired must be in [0, 1], got {m}"));
        }
        self.solver.validate()
    }

    /// The target check's threshold for `model` (see [`GateConfig::min_target_fired`]).
    pub fn min_target_fired_for(&self, model: &Manifest) -> f64 {
        self.min_target_fired.or(model.min_target_fired).unwrap_or(DEFAULT_MIN_TARGET_FIRED)
    }
}

/// What the target check (see [`GateConfig::min_target_fired`]) reads off an adaptation event:
/// the share of visible vertices that fire to the unchanged model. That is the
/// [`Event::TargetCheck`] before round 1 or, in a run without a BatchNorm step (which has no
/// separate check), round 1's `fired_ratio_before`; `None` for every other event, so a run is
/// judged once. Judged by the unchanged model's eyes: after AdaBN almost anything fires.
pub fn target_fired(event: &Event) -> Option<f64> {
    match event {
        Event::TargetCheck { fired } => Some(*fired),
        Event::Round(r) if r.round == 1 && r.source_fired_ratio.is_none() => Some(r.fired_ratio_before),
        _ => None,
    }
}

/// One held-out image as one model sees it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageCheck {
    /// The estimate's azimuth (radians, in `[0, 2π)`).
    pub azimuth: f64,
    /// The estimate's score `1 − L`.
    pub score: f64,
    /// The score minus the best score among grid poses more than [`MARGIN_SEPARATION`] away.
    pub margin: f64,
    /// Whether the mirrored crop's estimate is within [`FLIP_TOLERANCE`] of `(−a, e, −θ)`.
    pub flip_consistent: bool,
}

/// One model's checks of the held-out images, in image order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GateStats {
    pub images: Vec<ImageCheck>,
}

impl GateStats {
    /// Fraction of flip-consistent images (0 with no images).
    pub fn flip_rate(&self) -> f64 {
        if self.images.is_empty() {
            return 0.0;
        }
        self.images.iter().filter(|c| c.flip_consistent).count() as f64 / self.images.len() as f64
    }

    /// Median score margin (the mean of the middle two for an even count; 0 with no images).
    pub fn median_margin(&self) -> f64 {
        let mut m: Vec<f64> = self.images.iter().map(|c| c.margin).collect();
        if m.is_empty() {
            return 0.0;
        }
        m.sort_by(f64::total_cmp);
        let n = m.len();
        if n % 2 == 1 { m[n / 2] } else { (m[n / 2 - 1] + m[n / 2]) / 2.0 }
    }

    /// Entropy (nats) of the histogram of estimated azimuths over [`AZIMUTH_BINS`] bins centred
    /// on 0°, 30°, …, 330° (0 with no images; ln 12 ≈ 2.485 at most).
    pub fn azimuth_entropy(&self) -> f64 {
        let mut counts = [0usize; AZIMUTH_BINS];
        for c in &self.images {
            counts[azimuth_bin(c.azimuth)] += 1;
        }
        let n = self.images.len() as f64;
        let h = -counts.iter().filter(|&&k| k > 0).map(|&k| k as f64 / n).map(|p| p * p.ln()).sum::<f64>();
        // One bin gives −0.0; report it as 0.
        if h > 0.0 { h } else { 0.0 }
    }
}

/// The histogram bin of an azimuth (radians, any value): the nearest grid azimuth.
pub fn azimuth_bin(azimuth: f64) -> usize {
    let width = TAU / AZIMUTH_BINS as f64;
    if !azimuth.is_finite() {
        return 0;
    }
    ((azimuth.rem_euclid(TAU) / width).round() as usize) % AZIMUTH_BINS
}

/// The pose of the mirrored crop: `(−a, e, −θ)`, same distance.
pub fn mirrored(pose: &Pose) -> Pose {
    Pose::new(-pose.azimuth, pose.elevation, -pose.theta, pose.distance)
}

/// The crops mirrored left-right about their centre (N×3×H×W, along W).
pub fn mirror_crops(images: &Tensor) -> Tensor {
    images.flip([3i64].as_slice())
}

/// One image's measurement with the poses behind it (for offline benchmarks with labels).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measured {
    pub check: ImageCheck,
    /// The estimate of the crop.
    pub pose: Pose,
    /// The estimate of the mirrored crop.
    pub flipped_pose: Pose,
}

/// Per image, the estimate, its score margin and flip consistency (see [`measure_poses`]).
pub fn measure(
    model: &Model,
    images: &Tensor,
    config: &GateConfig,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<GateStats> {
    let measured = measure_poses(model, images, config, progress)?;
    Ok(GateStats { images: measured.into_iter().map(|m| m.check).collect() })
}

/// [`measure`], keeping each image's estimated and mirrored poses. `images`: N×3×H×W float in
/// [0, 1] at the model's crop size. The backbone sees [`MEASURE_BATCH`] images and their mirrors
/// per pass; the solver runs over a batch's crops in parallel. `progress(done, total)` is
/// called before the first batch and after each; `Break` stops with [`EngineError::Cancelled`].
pub fn measure_poses(
    model: &Model,
    images: &Tensor,
    config: &GateConfig,
    progress: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
) -> Result<Vec<Measured>> {
    config.validate()?;
    let [h, w] = model.manifest.crop;
    let size = images.size();
    if size.len() != 4 || size[1] != 3 || size[2] != h as i64 || size[3] != w as i64 {
        return Err(EngineError::InvalidInput(format!("gate images are {size:?}; the model takes N×3×{h}×{w} crops")));
    }
    if !images.is_floating_point() {
        return Err(EngineError::InvalidInput(format!("gate images are {:?}, not floats in [0, 1]", images.kind())));
    }
    let n = size[0] as usize;
    let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, [h, w], config.solver.clone())?;
    let device = model.vs.device();
    let mut out = Vec::with_capacity(n);
    if progress(0, n).is_break() {
        return Err(EngineError::Cancelled);
    }
    for start in (0..n).step_by(MEASURE_BATCH) {
        let len = MEASURE_BATCH.min(n - start);
        let batch = images.narrow(0, start as i64, len as i64).to_kind(Kind::Float).to_device(device);
        let both = Tensor::cat(&[&batch, &mirror_crops(&batch)], 0);
        let features = estimator::features(&model.backbone, &both)?;
        let (plain, flipped) = features.split_at(len);
        // Host data only crosses into the worker threads (tch tensors are not Sync).
        let measured: Vec<Measured> =
            plain.par_iter().zip(flipped).map(|(f, g)| measure_one(&solver, f, g)).collect::<Result<_>>()?;
        out.extend(measured);
        if progress(out.len(), n).is_break() {
            return Err(EngineError::Cancelled);
        }
    }
    Ok(out)
}

fn measure_one(solver: &PoseSolver, plain: &Features, flipped: &Features) -> Result<Measured> {
    let (estimate, grid) = solver.solve_with_grid(plain)?;
    let margin = score_margin(&estimate, &grid)?;
    let mirror = solver.solve(flipped)?;
    let flip_consistent = flip_consistent(&estimate.pose, &mirror.pose);
    let check = ImageCheck { azimuth: estimate.pose.azimuth, score: estimate.score, margin, flip_consistent };
    Ok(Measured { check, pose: estimate.pose, flipped_pose: mirror.pose })
}

/// The estimate's score minus the best score (`1 − L`) among the grid poses farther than
/// [`MARGIN_SEPARATION`] (geodesic) from the estimate.
pub fn score_margin(estimate: &Estimate, grid: &[ScoredPose]) -> Result<f64> {
    let r = estimate.pose.rotation();
    let far = grid
        .iter()
        .filter(|g| rotation_error(&r, &g.pose.rotation()) > MARGIN_SEPARATION)
        .map(|g| 1.0 - g.loss)
        .fold(f64::NEG_INFINITY, f64::max);
    if far == f64::NEG_INFINITY {
        return Err(EngineError::InvalidInput(format!(
            "the pose grid has no pose more than {:.0}° from the estimate",
            MARGIN_SEPARATION.to_degrees()
        )));
    }
    Ok(estimate.score - far)
}

/// Whether the mirrored crop's pose is within [`FLIP_TOLERANCE`] of the mirror of the crop's.
pub fn flip_consistent(pose: &Pose, mirror_pose: &Pose) -> bool {
    let m = mirrored(pose);
    let error = rotation_error(
        &rotation(mirror_pose.azimuth, mirror_pose.elevation, mirror_pose.theta),
        &rotation(m.azimuth, m.elevation, m.theta),
    );
    error < FLIP_TOLERANCE
}

/// One criterion of a decision: both models' values, the threshold the candidate's value had to
/// reach (`candidate >= threshold` passes), and a sentence for the job's events.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Criterion {
    /// "flip_consistency", "score_margin" or "pose_diversity".
    pub name: String,
    pub active: f64,
    pub candidate: f64,
    pub threshold: f64,
    pub passed: bool,
    pub detail: String,
}

/// The gate's verdict: passed when every criterion passed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Decision {
    pub passed: bool,
    pub criteria: Vec<Criterion>,
}

impl Decision {
    /// "passed", or each failed criterion as `name: candidate < threshold needed`, joined by "; ".
    pub fn reason(&self) -> String {
        if self.passed {
            return "passed".into();
        }
        self.criteria
            .iter()
            .filter(|c| !c.passed)
            .map(|c| format!("{}: {:.3} < {:.3} needed", c.name, c.candidate, c.threshold))
            .collect::<Vec<_>>()
            .join("; ")
    }
}

/// Compares the candidate's checks with the active model's on the same images (same order).
/// Errors when the lengths differ or there are fewer than `config.min_images` images.
pub fn decide(active: &GateStats, candidate: &GateStats, config: &GateConfig) -> Result<Decision> {
    comparable(active, candidate, config)?;
    let criteria = vec![
        flip_criterion(active, candidate, config.flip_se),
        margin_criterion(active, candidate, config),
        diversity_criterion(active, candidate, config),
    ];
    Ok(Decision { passed: criteria.iter().all(|c| c.passed), criteria })
}

/// The regression rule, for a set of images of a domain an earlier job adapted to (or an
/// operator's anchor images): the candidate need not improve there, only not get worse beyond
/// noise. Flip consistency and the mean score margin may each fall by at most `regression_se`
/// standard errors of their paired per-image difference; pose diversity has [`decide`]'s rule.
/// The same checks on the new domain demand a rising margin; here a falling one is what
/// forgetting looks like (the features stop matching the mesh on that domain).
pub fn guard(active: &GateStats, candidate: &GateStats, config: &GateConfig) -> Result<Decision> {
    comparable(active, candidate, config)?;
    let criteria = vec![
        flip_criterion(active, candidate, config.regression_se),
        mean_margin_criterion(active, candidate, config.regression_se),
        diversity_criterion(active, candidate, config),
    ];
    Ok(Decision { passed: criteria.iter().all(|c| c.passed), criteria })
}

/// Both models measured on the same (enough) images, with finite values.
fn comparable(active: &GateStats, candidate: &GateStats, config: &GateConfig) -> Result<()> {
    config.validate()?;
    let n = active.images.len();
    if candidate.images.len() != n {
        return Err(EngineError::InvalidInput(format!(
            "the gate compares the same images: active has {n}, candidate {}",
            candidate.images.len()
        )));
    }
    if n < config.min_images {
        return Err(EngineError::InvalidInput(format!(
            "the gate needs at least {} held-out images, got {n}",
            config.min_images
        )));
    }
    let finite = |s: &GateStats| s.images.iter().all(|c| [c.azimuth, c.score, c.margin].iter().all(|v| v.is_finite()));
    if !finite(active) || !finite(candidate) {
        return Err(EngineError::InvalidInput("non-finite azimuth, score or margin in the gate's checks".into()));
    }
    Ok(())
}

/// Mean and standard error of the paired differences `candidate_i − active_i` (SE 0 for one).
fn paired(active: &GateStats, candidate: &GateStats, value: impl Fn(&ImageCheck) -> f64) -> (f64, f64) {
    let d: Vec<f64> = active.images.iter().zip(&candidate.images).map(|(a, c)| value(c) - value(a)).collect();
    let n = d.len() as f64;
    let mean = d.iter().sum::<f64>() / n;
    let se = if d.len() > 1 {
        (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt() / n.sqrt()
    } else {
        0.0
    };
    (mean, se)
}

/// The mean score margin may fall by at most `se_allowed` paired standard errors.
fn mean_margin_criterion(active: &GateStats, candidate: &GateStats, se_allowed: f64) -> Criterion {
    let mean = |s: &GateStats| s.images.iter().map(|c| c.margin).sum::<f64>() / s.images.len() as f64;
    let (ma, mc) = (mean(active), mean(candidate));
    let (_, se) = paired(active, candidate, |c| c.margin);
    let threshold = ma - se_allowed * se;
    Criterion {
        name: "score_margin".into(),
        active: ma,
        candidate: mc,
        threshold,
        passed: mc >= threshold,
        detail: format!(
            "mean score margin over the best grid pose more than {:.0}° away: candidate {mc:.4}, active {ma:.4} over \
             {} images; may fall by {se_allowed} × paired SE {se:.4}, so needs >= {threshold:.4}",
            MARGIN_SEPARATION.to_degrees(),
            active.images.len()
        ),
    }
}

/// Flip consistency may fall by at most `se_allowed` paired standard errors.
fn flip_criterion(active: &GateStats, candidate: &GateStats, se_allowed: f64) -> Criterion {
    let n = active.images.len();
    let (fa, fc) = (active.flip_rate(), candidate.flip_rate());
    // Paired difference d_i = c_i − a_i of the 0/1 outcomes.
    let (_, se) = paired(active, candidate, |c| f64::from(u8::from(c.flip_consistent)));
    let flip_threshold = fa - se_allowed * se;
    Criterion {
        name: "flip_consistency".into(),
        active: fa,
        candidate: fc,
        threshold: flip_threshold,
        passed: fc >= flip_threshold,
        detail: format!(
            "flip-consistent images (mirrored estimate within {:.0}° of (−a, e, −θ)): candidate {fc:.3}, active {fa:.3} \
             over {n} images; may fall by {se_allowed} × paired SE {se:.3}, so needs >= {flip_threshold:.3}",
            FLIP_TOLERANCE.to_degrees(),
        ),
    }
}

/// The median score margin must rise by `margin_gain`.
fn margin_criterion(active: &GateStats, candidate: &GateStats, config: &GateConfig) -> Criterion {
    let (ma, mc) = (active.median_margin(), candidate.median_margin());
    let margin_threshold = ma + config.margin_gain;
    Criterion {
        name: "score_margin".into(),
        active: ma,
        candidate: mc,
        threshold: margin_threshold,
        passed: mc >= margin_threshold,
        detail: format!(
            "median score margin over the best grid pose more than {:.0}° away: candidate {mc:.4}, active {ma:.4}; \
             must rise by {}, so needs >= {margin_threshold:.4}",
            MARGIN_SEPARATION.to_degrees(),
            config.margin_gain
        ),
    }
}

/// The azimuth entropy may fall by `entropy_drop`, or to `entropy_floor`.
fn diversity_criterion(active: &GateStats, candidate: &GateStats, config: &GateConfig) -> Criterion {
    let (ha, hc) = (active.azimuth_entropy(), candidate.azimuth_entropy());
    let entropy_threshold = (ha - config.entropy_drop).min(config.entropy_floor);
    Criterion {
        name: "pose_diversity".into(),
        active: ha,
        candidate: hc,
        threshold: entropy_threshold,
        passed: hc >= entropy_threshold,
        detail: format!(
            "azimuth entropy ({AZIMUTH_BINS} bins, nats; ln {AZIMUTH_BINS} = {:.3} at most): candidate {hc:.3}, \
             active {ha:.3}; needs >= min({ha:.3} − {}, {}) = {entropy_threshold:.3}",
            (AZIMUTH_BINS as f64).ln(),
            config.entropy_drop,
            config.entropy_floor
        ),
    }
}

/// Whether an image is in the held-out bucket (about 20%), by the sha256 of its encoded bytes:
/// `u16::from_be_bytes([d[0], d[1]]) % 5 == 0`. Adaptation never trains on these images; the
/// gate decides on them. A digest shorter than 2 bytes is never held out.
pub fn held_out(sha256: &[u8]) -> bool {
    match sha256 {
        [a, b, ..] => u16::from_be_bytes([*a, *b]) % 5 == 0,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::*;

    #[test]
    fn azimuth_bins_are_centred_on_the_grid() {
        assert_eq!(azimuth_bin(0.0), 0);
        assert_eq!(azimuth_bin(14.9f64.to_radians()), 0);
        assert_eq!(azimuth_bin(15.1f64.to_radians()), 1);
        assert_eq!(azimuth_bin(345.1f64.to_radians()), 0);
        assert_eq!(azimuth_bin(-10f64.to_radians()), 0);
        assert_eq!(azimuth_bin(-20f64.to_radians()), 11);
        assert_eq!(azimuth_bin(PI), 6);
        assert_eq!(azimuth_bin(TAU), 0);
    }
}
