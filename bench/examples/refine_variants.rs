//! How the refinement's stopping rules trade evaluations for accuracy on real images: the
//! default solver's plateau stopping and pruning against the fixed 150-step schedule, on one
//! domain's splits, each variant on the same backbone features. What chose the defaults of
//! `AdamConfig` and `Prune` (on adapt/val splits; never tune on test):
//!
//! ```text
//! cargo run --release -p udapose-bench --example refine_variants -- \
//!     models/car data/syncar-ood-standard source val,adapt 150 20:1e-4:15:0.02 20:1e-4:0:0
//! ```
//!
//! Each variant is `patience:min_improvement:prune_after:prune_margin`; the fixed schedule is
//! always the first row. Prints Acc@π/6, Acc@π/18, median and 90th-percentile error, mean
//! evaluations and ms per image, and on how many images Acc@π/6 agrees with the fixed schedule.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use tch::{Device, Tensor};
use udapose_engine::estimator::{self, Features, PoseSolver};
use udapose_engine::solver::{AdamConfig, Optimizer, Prune, SolverConfig};
use udapose_engine::{Pose, checkpoint, pose_error};
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::{Sample, load_sample};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [model, data, domain, splits, per_split, specs @ ..] = args.as_slice() else {
        bail!("usage: refine_variants MODEL DATA DOMAIN SPLITS PER_SPLIT [PATIENCE:MIN_IMPROVEMENT:AFTER:MARGIN ...]");
    };
    let per_split: usize = per_split.parse().context("PER_SPLIT")?;
    tch::set_num_threads(1);
    let model = checkpoint::load(Path::new(model), Device::Cpu)?;
    let images = features(&model, Path::new(data), domain, splits, per_split)?;
    let fixed = SolverConfig {
        optimizer: Optimizer::Adam(AdamConfig::fixed()),
        prune: Prune::default(),
        ..SolverConfig::default()
    };
    let mut variants = vec![("fixed 150".to_string(), fixed)];
    for spec in specs {
        variants.push((spec.clone(), variant(spec)?));
    }
    let mut baseline: Option<Vec<bool>> = None;
    for (name, config) in variants {
        let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, model.manifest.crop, config)?;
        let (mut errors, mut evaluations, mut ms) = (Vec::new(), 0usize, 0.0);
        for (f, truth) in &images {
            let t = Instant::now();
            let e = solver.solve(f)?;
            ms += t.elapsed().as_secs_f64() * 1e3;
            evaluations += e.hypotheses.iter().map(|h| h.evaluations).sum::<usize>();
            let angles = |p: &Pose| [p.azimuth, p.elevation, p.theta];
            errors.push(pose_error(Some(angles(&e.pose)), angles(truth)).to_degrees());
        }
        let hits: Vec<bool> = errors.iter().map(|e| *e < 30.0).collect();
        let agree = baseline.as_ref().map_or(hits.len(), |b| b.iter().zip(&hits).filter(|(a, b)| a == b).count());
        let n = errors.len() as f64;
        errors.sort_by(f64::total_cmp);
        let share = |deg: f64| errors.iter().filter(|e| **e < deg).count() as f64 / n;
        println!(
            "{name:>20}: Acc@π/6 {:.4}  Acc@π/18 {:.4}  median {:.2}°  p90 {:.2}°  evaluations {:.1}  {:.2} ms  agree {agree}/{}",
            share(30.0),
            share(10.0),
            errors[errors.len() / 2],
            errors[errors.len() * 9 / 10],
            evaluations as f64 / n,
            ms / n,
            hits.len()
        );
        baseline.get_or_insert(hits);
    }
    Ok(())
}

/// `patience:min_improvement:prune_after:prune_margin` on the fixed schedule.
fn variant(spec: &str) -> Result<SolverConfig> {
    let v: Vec<f64> = spec.split(':').map(str::parse).collect::<Result<_, _>>().with_context(|| spec.to_string())?;
    let &[patience, min_improvement, after, margin] = v.as_slice() else { bail!("{spec}: four fields") };
    let adam = AdamConfig { patience: patience as usize, min_improvement, ..AdamConfig::fixed() };
    Ok(SolverConfig {
        optimizer: Optimizer::Adam(adam),
        prune: Prune { after: after as usize, margin },
        ..SolverConfig::default()
    })
}

/// The backbone's features and the true pose of the first `per_split` images of each split.
fn features(
    model: &checkpoint::Model,
    data: &Path,
    domain: &str,
    splits: &str,
    per_split: usize,
) -> Result<Vec<(Features, Pose)>> {
    let mut out = Vec::new();
    for name in splits.split(',') {
        let split = SyncarSplit::open(data, domain, name)?;
        for i in 0..per_split.min(split.len()) {
            let Sample { pixels, pose: truth, height: h, width: w, .. } = load_sample(&split, i)?;
            let image = Tensor::from_slice(&pixels).reshape([1, 3, h as i64, w as i64]);
            let f = estimator::features(&model.backbone, &image)?.pop().context("no features")?;
            out.push((f, truth));
        }
    }
    eprintln!("{} images of {domain}/{splits}", out.len());
    Ok(out)
}
