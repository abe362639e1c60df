//! Refining one hypothesis over `x = (a, e, θ, log d)`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Problem, ScoredPose, Scratch};
use crate::camera::Pose;
use crate::error::{EngineError, Result};

/// How far (as a factor) the distance may move from its initial value: the initial distance
/// fits the crop, and a detection crop's fill varies by about ±10% around it.
const MAX_DISTANCE_FACTOR: f64 = 4.0;

/// The refinement of each hypothesis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Optimizer {
    /// Keep the grid pose (multi-pose initialisation only).
    None,
    /// Adam on the analytic gradient ([`Problem::loss_and_gradient`]).
    Adam(AdamConfig),
    /// Hooke–Jeeves pattern search on the exact loss (derivative-free).
    PatternSearch(PatternSearchConfig),
}

impl Default for Optimizer {
    /// Adam on the analytic gradient, 150 steps ([`AdamConfig::default`]). Measured by
    /// `cargo bench -p udapose-engine --bench solver` (reports/solver-synthetic.md: 100 synthetic
    /// images of known pose per set, SynCar source poses, k = 3, 2-core AMD EPYC), as rotation
    /// MedErr / share under 5° / worst / median ms per image (multi-pose init included):
    ///
    /// | set | Adam 150 (default) | Adam 300 (METHOD) | Adam 100 | pattern search |
    /// |---|---|---|---|---|
    /// | 16×40, noise 0.5 | 1.07° / 100% / 4.1° / 17.5 | 0.99° / 100% / 4.1° / 31.4 | 1.12° / 100% / 4.1° / 13.0 | 1.34° / 100% / 3.5° / 15.5 |
    /// | 16×40, noise 1.0 | 1.11° / 100% / 4.2° / 17.4 | 1.06° / 100% / 4.2° / 31.5 | 1.11° / 99% / 6.7° / 12.8 | 1.41° / 100% / 3.5° / 15.4 |
    /// | 16×40, sharp features | 0.79° / 100% / 2.1° / 17.2 | 0.86° / 100% / 2.2° / 31.0 | 0.79° / 100% / 2.2° / 12.9 | 1.18° / 100% / 3.9° / 15.7 |
    /// | 32×84, noise 0.5 (*) | 0.62° / 100% / 3.4° / 43.3 | 0.59° / 100% / 2.1° / 77.6 | 0.58° / 100% / 2.6° / 30.1 | 0.80° / 100% / 2.3° / 35.1 |
    ///
    /// (*) timed while another build shared the 2 cores: 28 / 49 / 20 / 22 ms on a quiet machine.
    /// The best grid pose alone: 12° MedErr, 3 ms at 16×40. 150 Adam steps are as accurate as
    /// METHOD's 300 (same share under 5°, MedErr within 0.08°) in 1.8× less time per image (2×
    /// less refinement time); 100 steps miss once in 400 images and 50 steps more often. The
    /// pattern search (about 165 evaluations per hypothesis) reaches the lowest losses, below the
    /// true pose's, yet 20–50% larger rotation errors: the exact loss steps whenever the
    /// silhouette crosses a pixel centre of the stride-8 grid, and the search settles on those
    /// steps, while the fixed-assignment gradient follows the smooth interior term.
    fn default() -> Self {
        Optimizer::Adam(AdamConfig::default())
    }
}

impl Optimizer {
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(EngineError::InvalidInput(m));
        match self {
            Optimizer::None => Ok(()),
            Optimizer::Adam(c) => {
                let ok = c.lr.is_finite()
                    && c.lr > 0.0
                    && (0.0..1.0).contains(&c.beta1)
                    && (0.0..1.0).contains(&c.beta2)
                    && c.eps.is_finite()
                    && c.eps > 0.0
                    && c.decay.is_finite()
                    && c.decay > 0.0
                    && c.decay_every > 0
                    && c.min_improvement.is_finite()
                    && c.min_improvement >= 0.0;
                if ok { Ok(()) } else { bad(format!("invalid Adam settings {c:?}")) }
            }
            Optimizer::PatternSearch(c) => {
                let ok = c.initial_step.iter().all(|s| s.is_finite() && *s > 0.0)
                    && c.tolerance.is_finite()
                    && c.tolerance > 0.0
                    && c.shrink > 0.0
                    && c.shrink < 1.0;
                if ok { Ok(()) } else { bad(format!("invalid pattern search settings {c:?}")) }
            }
        }
    }
}

/// Adam on `(a, e, θ, log d)`; returns the lowest-loss point it visited. The default is
/// METHOD.md §6's schedule compressed to 150 steps (lr 0.05, betas (0.4, 0.6), lr × 0.2 every
/// 50 steps); [`AdamConfig::method`] is METHOD's 300 steps with lr × 0.2 every 100.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub steps: usize,
    pub decay_every: usize,
    pub decay: f64,
    /// Plateau stopping: a phase (the steps at one learning rate) ends early once the best loss
    /// has not fallen by more than `min_improvement` for `patience` steps, and the refinement
    /// ends with its last phase. 0 keeps the fixed schedule (and configurations written before
    /// this field existed).
    #[serde(default)]
    pub patience: usize,
    #[serde(default)]
    pub min_improvement: f64,
}

impl Default for AdamConfig {
    /// [`AdamConfig::fixed`] with plateau stopping after 8 steps without a 2e-4 gain. Chosen
    /// with [`super::Prune`]'s 6 steps and 0.02 by `bench/examples/refine_variants.rs` on
    /// adapt/val splits of `models/car` (`reports/refine-variants.md`, second round: source 600
    /// images, combined and occ-l2 300 each): the fixed 150 steps' Acc@π/6 on source (600/600
    /// verdicts alike) in 51 evaluations per image instead of 453 (128 with the earlier 20 steps
    /// and pruning after 15); −1 image on combined, +3 on occ-l2. Once an evaluation cost 20 µs
    /// instead of 68 (the ray caster), the evaluation count was most of the solver's time.
    /// Pruning after 4 steps (third round) then took source to 46 evaluations, verdicts alike.
    fn default() -> Self {
        AdamConfig { patience: 8, min_improvement: 2e-4, ..AdamConfig::fixed() }
    }
}

impl AdamConfig {
    /// METHOD.md §6 (NeMo): lr 0.05, betas (0.4, 0.6), 300 steps, lr × 0.2 every 100.
    pub fn method() -> Self {
        AdamConfig {
            lr: 0.05,
            beta1: 0.4,
            beta2: 0.6,
            eps: 1e-8,
            steps: 300,
            decay_every: 100,
            decay: 0.2,
            patience: 0,
            min_improvement: 0.0,
        }
    }

    /// METHOD's schedule compressed to 150 fixed steps, lr × 0.2 every 50: the default until
    /// plateau stopping was measured, kept for comparison.
    pub fn fixed() -> Self {
        AdamConfig { steps: 150, decay_every: 50, ..AdamConfig::method() }
    }

    /// Phases of the schedule: `steps / decay_every`, rounded up.
    fn phases(&self) -> usize {
        self.steps.div_ceil(self.decay_every)
    }
}

/// Hooke–Jeeves pattern search: probe `±step` along each of `(a, e, θ, log d)` in turn, keeping
/// any improvement; after a successful sweep, jump along the direction of progress (the pattern
/// move) and probe there; after a failed sweep, multiply every step by `shrink`. Stops when the
/// angular steps fall below `tolerance` or after `max_evaluations` loss evaluations.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatternSearchConfig {
    /// Initial steps of `(a, e, θ)` in radians and of `log d`: 6°, 6°, 6°, 0.06 (grid poses are
    /// at most 15° from the nearest grid neighbour, distances within about 10%).
    pub initial_step: [f64; 4],
    /// Final angular step (radians): 0.2°.
    pub tolerance: f64,
    /// Step factor after a failed sweep: 0.5.
    pub shrink: f64,
    /// Evaluation budget per hypothesis: 400.
    pub max_evaluations: usize,
}

impl Default for PatternSearchConfig {
    fn default() -> Self {
        let deg = 6f64.to_radians();
        PatternSearchConfig {
            initial_step: [deg, deg, deg, 0.06],
            tolerance: 0.2f64.to_radians(),
            shrink: 0.5,
            max_evaluations: 400,
        }
    }
}

/// A refined pose, its loss and the number of loss evaluations spent.
#[derive(Clone, Copy, Debug)]
pub(super) struct Refined {
    pub pose: Pose,
    pub loss: f64,
    pub evaluations: usize,
}

/// The objective over `x = (a, e, θ, log d)`, with log d kept within a factor of the start.
struct Objective<'p, 's> {
    problem: &'p Problem<'p>,
    scratch: &'s mut Scratch,
    log_d: [f64; 2],
    evaluations: usize,
}

impl Objective<'_, '_> {
    fn pose(&self, x: &[f64; 4]) -> Pose {
        Pose::new(x[0], x[1], x[2], x[3].clamp(self.log_d[0], self.log_d[1]).exp())
    }

    fn loss(&mut self, x: &[f64; 4]) -> Result<f64> {
        self.evaluations += 1;
        let pose = self.pose(x);
        self.problem.loss(self.scratch, &pose)
    }

    fn loss_and_gradient(&mut self, x: &[f64; 4]) -> Result<(f64, [f64; 4])> {
        self.evaluations += 1;
        let pose = self.pose(x);
        self.problem.loss_and_gradient(self.scratch, &pose)
    }
}

pub(super) fn refine(
    problem: &Problem,
    scratch: &mut Scratch,
    init: &ScoredPose,
    optimizer: &Optimizer,
) -> Result<Refined> {
    let (x0, log_d) = start(init);
    let mut f = Objective { problem, scratch, log_d, evaluations: 0 };
    let (x, loss) = match optimizer {
        Optimizer::None => (x0, init.loss),
        Optimizer::Adam(c) => adam(&mut f, x0, c)?,
        Optimizer::PatternSearch(c) => pattern_search(&mut f, x0, init.loss, c)?,
    };
    Ok(settle(&f, init, x, loss))
}

/// The refined pose, or the initial one where refinement ended worse.
fn settle(f: &Objective, init: &ScoredPose, x: [f64; 4], loss: f64) -> Refined {
    let (x, loss) = if loss <= init.loss { (x, loss) } else { (start(init).0, init.loss) };
    Refined { pose: f.pose(&x), loss, evaluations: f.evaluations }
}

/// Stopping hypotheses that trail: after `after` Adam steps of every hypothesis, those whose
/// best loss exceeds the leader's by more than `margin` stop where they are (they stay in the
/// answer, refined that far). `after` 0 never prunes; other optimisers ignore it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Prune {
    pub after: usize,
    pub margin: f64,
}

impl Prune {
    pub fn validate(&self) -> Result<()> {
        if self.margin.is_finite() && self.margin >= 0.0 {
            Ok(())
        } else {
            Err(EngineError::InvalidInput(format!("prune margin must be finite and >= 0, got {}", self.margin)))
        }
    }
}

/// Refines every initial pose (in parallel, one scratch per thread), pruning per `prune`.
pub(super) fn refine_all(
    problem: &Problem,
    inits: &[ScoredPose],
    optimizer: &Optimizer,
    prune: &Prune,
) -> Result<Vec<Refined>> {
    let c = match optimizer {
        Optimizer::Adam(c) if prune.after > 0 && inits.len() > 1 => c,
        _ => {
            return inits
                .par_iter()
                .map_init(Scratch::default, |s, init| refine(problem, s, init, optimizer))
                .collect();
        }
    };
    let mut runs: Vec<Pruned> = inits.iter().map(Pruned::new).collect();
    let advance = |runs: &mut [Pruned], limit: usize| {
        runs.par_iter_mut().try_for_each_init(Scratch::default, |scratch, r| {
            let mut f = Objective { problem, scratch, log_d: start(&r.init).1, evaluations: 0 };
            r.adam.advance(&mut f, c, limit)?;
            r.evaluations += f.evaluations;
            Ok::<_, EngineError>(())
        })
    };
    advance(&mut runs, prune.after)?;
    let leader = runs.iter().map(|r| r.adam.best.1).fold(f64::INFINITY, f64::min);
    for r in runs.iter_mut().filter(|r| r.adam.best.1 > leader + prune.margin) {
        r.adam.done = true;
    }
    advance(&mut runs, c.steps)?;
    runs.par_iter_mut()
        .map_init(Scratch::default, |scratch, r| {
            let mut f = Objective { problem, scratch, log_d: start(&r.init).1, evaluations: r.evaluations };
            let (x, loss) = r.adam.finish(&mut f)?;
            Ok(settle(&f, &r.init, x, loss))
        })
        .collect()
}

/// One hypothesis of [`refine_all`] between its rounds.
struct Pruned {
    init: ScoredPose,
    adam: AdamRun,
    evaluations: usize,
}

impl Pruned {
    fn new(init: &ScoredPose) -> Self {
        Pruned { init: *init, adam: AdamRun::new(start(init).0), evaluations: 0 }
    }
}

/// The search's start `(a, e, θ, log d)` and the bounds of `log d`.
fn start(init: &ScoredPose) -> ([f64; 4], [f64; 2]) {
    let p = init.pose;
    let x0 = [p.azimuth, p.elevation, p.theta, p.distance.ln()];
    let spread = MAX_DISTANCE_FACTOR.ln();
    (x0, [x0[3] - spread, x0[3] + spread])
}

/// Adam's state over one hypothesis, resumable so that [`refine_all`] can stop some
/// hypotheses between steps.
struct AdamRun {
    x: [f64; 4],
    m: [f64; 4],
    v: [f64; 4],
    /// Steps taken; also Adam's bias-correction time.
    t: usize,
    phase: usize,
    phase_steps: usize,
    /// Steps since the best loss last fell by more than `min_improvement`.
    stale: usize,
    best: ([f64; 4], f64),
    done: bool,
}

impl AdamRun {
    fn new(x0: [f64; 4]) -> Self {
        AdamRun {
            x: x0,
            m: [0.0; 4],
            v: [0.0; 4],
            t: 0,
            phase: 0,
            phase_steps: 0,
            stale: 0,
            best: (x0, f64::INFINITY),
            done: false,
        }
    }

    /// Steps until `limit` steps in all, or the schedule's end.
    fn advance(&mut self, f: &mut Objective, c: &AdamConfig, limit: usize) -> Result<()> {
        while !self.done && self.t < limit {
            let (loss, g) = f.loss_and_gradient(&self.x)?;
            self.stale = if loss < self.best.1 - c.min_improvement { 0 } else { self.stale + 1 };
            if loss < self.best.1 {
                self.best = (self.x, loss);
            }
            let lr = c.lr * c.decay.powi(self.phase as i32);
            let t = self.t as i32 + 1;
            let (b1t, b2t) = (1.0 - c.beta1.powi(t), 1.0 - c.beta2.powi(t));
            for (i, g) in g.into_iter().enumerate() {
                self.m[i] = c.beta1 * self.m[i] + (1.0 - c.beta1) * g;
                self.v[i] = c.beta2 * self.v[i] + (1.0 - c.beta2) * g * g;
                self.x[i] -= lr * (self.m[i] / b1t) / ((self.v[i] / b2t).sqrt() + c.eps);
            }
            self.x[3] = self.x[3].clamp(f.log_d[0], f.log_d[1]);
            self.t += 1;
            self.phase_steps += 1;
            if self.phase_steps == c.decay_every || (c.patience > 0 && self.stale >= c.patience) {
                (self.phase, self.phase_steps, self.stale) = (self.phase + 1, 0, 0);
            }
            self.done = self.t >= c.steps || self.phase >= c.phases();
        }
        Ok(())
    }

    /// The lowest-loss point visited, the last one included.
    fn finish(&self, f: &mut Objective) -> Result<([f64; 4], f64)> {
        let loss = f.loss(&self.x)?;
        Ok(if loss < self.best.1 { (self.x, loss) } else { self.best })
    }
}

fn adam(f: &mut Objective, x0: [f64; 4], c: &AdamConfig) -> Result<([f64; 4], f64)> {
    let mut run = AdamRun::new(x0);
    run.advance(f, c, c.steps)?;
    run.finish(f)
}

fn pattern_search(f: &mut Objective, x0: [f64; 4], f0: f64, c: &PatternSearchConfig) -> Result<([f64; 4], f64)> {
    let mut step = c.initial_step;
    let (mut base, mut fbase) = (x0, f0);
    let budget = |f: &Objective| f.evaluations < c.max_evaluations;
    while budget(f) && step[0].max(step[1]).max(step[2]) >= c.tolerance {
        let (mut xn, mut fnew) = explore(f, base, fbase, &step, c.max_evaluations)?;
        if fnew >= fbase {
            step = step.map(|s| s * c.shrink);
            continue;
        }
        // Pattern moves: keep jumping along the direction of progress while it pays.
        while budget(f) {
            let xp: [f64; 4] = std::array::from_fn(|i| 2.0 * xn[i] - base[i]);
            (base, fbase) = (xn, fnew);
            let fp = f.loss(&xp)?;
            let (xe, fe) = explore(f, xp, fp, &step, c.max_evaluations)?;
            if fe < fbase {
                (xn, fnew) = (xe, fe);
            } else {
                break;
            }
        }
        if fnew < fbase {
            (base, fbase) = (xn, fnew);
        }
    }
    Ok((base, fbase))
}

/// One exploratory sweep: per coordinate, `+step` then `−step`, keeping improvements.
fn explore(f: &mut Objective, mut x: [f64; 4], mut fx: f64, step: &[f64; 4], max: usize) -> Result<([f64; 4], f64)> {
    for i in 0..4 {
        for sign in [1.0, -1.0] {
            if f.evaluations >= max {
                return Ok((x, fx));
            }
            let mut y = x;
            y[i] += sign * step[i];
            let fy = f.loss(&y)?;
            if fy < fx {
                (x, fx) = (y, fy);
                break;
            }
        }
    }
    Ok((x, fx))
}
