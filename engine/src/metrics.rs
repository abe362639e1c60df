//! Pose error and the benchmark metrics (METHOD.md §2).

use std::f64::consts::PI;

use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

use crate::camera::{rot_z, rotation};
use crate::error::{EngineError, Result};

/// Geodesic angle between two rotations, `‖logm(R_predᵀ R_gt)‖_F / √2`, in radians.
///
/// Computed as `atan2(‖w‖, (tr Q − 1)/2)` with `w` the axial vector of `Q = R_predᵀ R_gt`: unlike
/// `acos` of the trace, this keeps full precision near 0 and near π. Non-finite input gives π.
pub fn rotation_error(pred: &Matrix3<f64>, gt: &Matrix3<f64>) -> f64 {
    let q = pred.transpose() * gt;
    let w = [(q[(2, 1)] - q[(1, 2)]) / 2.0, (q[(0, 2)] - q[(2, 0)]) / 2.0, (q[(1, 0)] - q[(0, 1)]) / 2.0];
    let sin = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    let cos = (q.trace() - 1.0) / 2.0;
    let angle = sin.atan2(cos);
    if angle.is_finite() { angle } else { PI }
}

/// Error between poses given as `[azimuth, elevation, theta]`; a failed estimate (`None` or
/// any NaN) counts as π.
pub fn pose_error(pred: Option<[f64; 3]>, gt: [f64; 3]) -> f64 {
    match pred {
        Some([a, e, t]) if a.is_finite() && e.is_finite() && t.is_finite() => {
            rotation_error(&rotation(a, e, t), &rotation(gt[0], gt[1], gt[2]))
        }
        _ => PI,
    }
}

/// How an object repeats itself about its up axis (the mesh's z): rotations about it that leave
/// it looking the same, so that a pose is only defined up to them. A rectangular table is
/// `Order(2)` (front and back alike), a square one `Order(4)`, a round one `Continuous`; a car
/// is `Order(1)`, no symmetry. Poses are scored up to it ([`pose_error_up_to`]) and labels are
/// put into one representative for training ([`canonical_azimuth`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UpSymmetry {
    Order(u32),
    Continuous,
}

impl UpSymmetry {
    pub const NONE: UpSymmetry = UpSymmetry::Order(1);
}

/// [`rotation_error`] up to `symmetry`: the smallest error over the rotations `R_gt·Rz(δ)` that
/// look like `R_gt`.
pub fn rotation_error_up_to(pred: &Matrix3<f64>, gt: &Matrix3<f64>, symmetry: UpSymmetry) -> f64 {
    rotation_error(pred, &(gt * rot_z(look_alike_turn(pred, gt, symmetry))))
}

/// The turn δ about the up axis that brings `R_gt·Rz(δ)`, a rotation that looks like `R_gt`,
/// closest to `R_pred`. For the continuous case it is closed-form: with `Q = R_predᵀ R_gt`,
/// `tr(Q·Rz(δ)) = (q00 + q11) cos δ + (q01 − q10) sin δ + q22`, largest at `atan2` of the two.
fn look_alike_turn(pred: &Matrix3<f64>, gt: &Matrix3<f64>, symmetry: UpSymmetry) -> f64 {
    match symmetry {
        UpSymmetry::Order(n) if n > 1 => {
            (0..n)
                .map(|k| 2.0 * PI * f64::from(k) / f64::from(n))
                .map(|delta| (rotation_error(pred, &(gt * rot_z(delta))), delta))
                .fold((f64::INFINITY, 0.0), |best, e| if e.0 < best.0 { e } else { best })
                .1
        }
        UpSymmetry::Order(_) => 0.0,
        UpSymmetry::Continuous => {
            let q = pred.transpose() * gt;
            let delta = (q[(0, 1)] - q[(1, 0)]).atan2(q[(0, 0)] + q[(1, 1)]);
            if delta.is_finite() { delta } else { 0.0 }
        }
    }
}

/// The pose that looks like `gt` under `symmetry` and lies closest to `pred` (all
/// `[azimuth, elevation, theta]`): where a label-based check of an estimate must put the
/// object, as the estimate cannot tell `gt` from its look-alikes. (`R(a, e, θ)·Rz(δ) =
/// R(a − δ, e, θ)`.)
pub fn nearest_look_alike(pred: [f64; 3], gt: [f64; 3], symmetry: UpSymmetry) -> [f64; 3] {
    let delta = look_alike_turn(&rotation(pred[0], pred[1], pred[2]), &rotation(gt[0], gt[1], gt[2]), symmetry);
    [gt[0] - delta, gt[1], gt[2]]
}

/// [`pose_error`] up to `symmetry`.
pub fn pose_error_up_to(pred: Option<[f64; 3]>, gt: [f64; 3], symmetry: UpSymmetry) -> f64 {
    match pred {
        Some([a, e, t]) if a.is_finite() && e.is_finite() && t.is_finite() => {
            rotation_error_up_to(&rotation(a, e, t), &rotation(gt[0], gt[1], gt[2]), symmetry)
        }
        _ => PI,
    }
}

/// The one azimuth that stands for all that look alike under `symmetry`, so that images which
/// look the same are trained with the same label: the azimuth moved into `[−π/n, π/n)` for
/// `Order(n)`, 0 for `Continuous`. (Turning the object by δ about its up axis is the azimuth
/// moved by δ: `R(a, e, θ)·Rz(−δ) = R(a + δ, e, θ)`.)
pub fn canonical_azimuth(azimuth: f64, symmetry: UpSymmetry) -> f64 {
    match symmetry {
        UpSymmetry::Order(n) if n > 1 => {
            let period = 2.0 * PI / f64::from(n);
            azimuth - period * ((azimuth + period / 2.0) / period).floor()
        }
        UpSymmetry::Order(_) => azimuth,
        UpSymmetry::Continuous => 0.0,
    }
}

/// Acc@π/6, Acc@π/18 and MedErr (degrees), pooled over the images of a split.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseMetrics {
    pub acc_pi_6: f64,
    pub acc_pi_18: f64,
    pub med_err_deg: f64,
    pub n: usize,
}

impl PoseMetrics {
    /// Metrics from per-image errors in radians; a NaN error counts as π.
    pub fn from_errors(errors: &[f64]) -> Result<Self> {
        if errors.is_empty() {
            return Err(EngineError::InvalidInput("metrics of an empty split".into()));
        }
        let mut e: Vec<f64> = errors.iter().map(|&x| if x.is_nan() { PI } else { x }).collect();
        e.sort_by(f64::total_cmp);
        let n = e.len();
        let frac = |t: f64| e.iter().filter(|&&x| x < t).count() as f64 / n as f64;
        let median = if n % 2 == 1 { e[n / 2] } else { (e[n / 2 - 1] + e[n / 2]) / 2.0 };
        Ok(PoseMetrics { acc_pi_6: frac(PI / 6.0), acc_pi_18: frac(PI / 18.0), med_err_deg: median.to_degrees(), n })
    }
}

/// 95% percentile-bootstrap intervals of the metrics (BENCHMARK.md §6): `[low, high]` each.
/// A 95% percentile-bootstrap interval of `stat` over `n` paired observations (images scored
/// by several models): `resamples` draws of `n` indices with replacement (ChaCha8 from `seed`),
/// the same indices for every quantity `stat` compares. Draws where `stat` is undefined (None)
/// are skipped; None when fewer than a tenth of the draws are left.
pub fn paired_bootstrap(
    n: usize,
    resamples: usize,
    seed: u64,
    mut stat: impl FnMut(&[usize]) -> Option<f64>,
) -> Option<[f64; 2]> {
    use rand::{Rng, SeedableRng};
    if n == 0 {
        return None;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut idx = vec![0; n];
    let mut draws = Vec::with_capacity(resamples);
    for _ in 0..resamples {
        idx.iter_mut().for_each(|i| *i = rng.random_range(0..n));
        draws.extend(stat(&idx));
    }
    if draws.is_empty() || draws.len() * 10 < resamples {
        return None;
    }
    draws.sort_by(f64::total_cmp);
    let at = |q: f64| draws[((draws.len() - 1) as f64 * q).round() as usize];
    Some([at(0.025), at(0.975)])
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MetricIntervals {
    pub acc_pi_6_ci: [f64; 2],
    pub acc_pi_18_ci: [f64; 2],
    pub med_err_deg_ci: [f64; 2],
}

impl MetricIntervals {
    /// Resamples the images `resamples` times (with replacement) with a fixed seed.
    pub fn bootstrap(errors: &[f64], resamples: usize, seed: u64) -> Result<Self> {
        use rand::{Rng, SeedableRng};
        PoseMetrics::from_errors(errors)?;
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut draws: Vec<PoseMetrics> = Vec::with_capacity(resamples);
        let mut sample = vec![0.0; errors.len()];
        for _ in 0..resamples.max(1) {
            sample.iter_mut().for_each(|s| *s = errors[rng.random_range(0..errors.len())]);
            draws.push(PoseMetrics::from_errors(&sample)?);
        }
        let interval = |f: fn(&PoseMetrics) -> f64| {
            let mut v: Vec<f64> = draws.iter().map(f).collect();
            v.sort_by(f64::total_cmp);
            let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
            [at(0.025), at(0.975)]
        };
        Ok(MetricIntervals {
            acc_pi_6_ci: interval(|m| m.acc_pi_6),
            acc_pi_18_ci: interval(|m| m.acc_pi_18),
            med_err_deg_ci: interval(|m| m.med_err_deg),
        })
    }
}
