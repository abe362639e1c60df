//! `udapose-bench gate`: does the label-free validation gate (`udapose_engine::gate`,
//! ARCHITECTURE.md "Validation gate") say yes where adaptation helped and no where it hurt?
//!
//! Per domain, the held-out images are the domain's *adapt* split images whose file bytes'
//! sha256 falls in `gate::held_out` (the service's rule). The gate measures the source model
//! (the active one) and the domain's adapted model (the candidate) on them and decides. With the
//! labels, the command then computes the true Acc@π/6 change on the same held-out images, and
//! reads the true change on the domain's test split from the report's evaluations
//! (`<eval>/{source,adapted}/<domain>.json`). A decision agrees when it passes a model whose
//! accuracy rose and rejects one whose accuracy fell.
//!
//! `margin_gain` is chosen here, on the adapt split only: the value of a grid that makes the
//! decisions (made on the held-out images) agree best with the sign of the accuracy change on
//! the whole adapt split (ties: the smallest positive value). The test split only reports how
//! that choice fares. Writes the JSON report and its Markdown twin.

mod report;

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rayon::prelude::*;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};
use tch::Tensor;
use udapose_engine::checkpoint::{self, Model};
use udapose_engine::estimator::{self, PoseSolver};
use udapose_engine::gate::{self, Decision, GateConfig, GateStats, Measured};
use udapose_engine::runtime::RuntimeInfo;
use udapose_engine::solver::SolverConfig;
use udapose_engine::{Pose, PoseMetrics, pose_error};
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::load_sample;
use udapose_lab::synth::all_domains;

use crate::paired::Paired;

#[derive(clap::Args)]
pub struct GateArgs {
    /// The active model (the shipped source model).
    #[arg(long, default_value = "models/car")]
    source: PathBuf,
    /// One adapted model directory per domain, named as the domain with '/' as '-'
    /// (`adapted/combined`, `adapted/corrupt-fog`, …).
    #[arg(long, default_value = "data/report-standard/adapted")]
    adapted: PathBuf,
    /// SynCar-OOD root (each domain's adapt split gives the held-out images).
    #[arg(long, default_value = "data/syncar-ood-standard")]
    data: PathBuf,
    /// The report's evaluations (`<eval>/{source,adapted}/<domain>.json`) for the test-split
    /// change (default: `eval` next to `--adapted`); a missing file leaves it n/a.
    #[arg(long)]
    eval: Option<PathBuf>,
    /// Only these domains (default: every adapted model whose domain has an adapt split).
    #[arg(long, value_delimiter = ',')]
    domains: Vec<String>,
    /// Measure on every adapt image, not only the held-out bucket (a larger sample; the
    /// service decides on the held-out bucket only).
    #[arg(long)]
    all_adapt: bool,
    /// The gate's `margin_gain` for the reported decisions (default: `GateConfig::default()`).
    #[arg(long)]
    margin_gain: Option<f64>,
    /// The grid of `margin_gain` values the adapt-split choice is made from.
    #[arg(long, value_delimiter = ',', default_values_t = default_gains())]
    gains: Vec<f64>,
    /// Report (JSON; a Markdown twin is written next to it).
    #[arg(long, default_value = "reports/gate.json")]
    out: PathBuf,
    /// A remark on the run copied into both reports.
    #[arg(long)]
    note: Option<String>,
    /// Instead of the benchmark: decide between `--source` and `--candidate` on the held-out
    /// bucket (or, with `--all-adapt`, all) of the images in this folder, without labels, and
    /// print the decision as JSON (what a service job would decide on these images).
    #[arg(long, requires = "candidate")]
    images: Option<PathBuf>,
    /// The candidate model for `--images`.
    #[arg(long, requires = "images")]
    candidate: Option<PathBuf>,
}

fn default_gains() -> Vec<f64> {
    [0.0, 0.001].into_iter().chain((1..=20).map(|i| f64::from(i) * 0.0025)).collect()
}

/// One domain's measurements.
struct DomainResult {
    domain: String,
    /// The gate's images (held out) and their true poses.
    images: Vec<String>,
    truth: Vec<Pose>,
    active: Vec<Measured>,
    candidate: Vec<Measured>,
    /// Acc@π/6 of the source and adapted models on the whole adapt split (the gate's images
    /// included), and its size.
    adapt_split: (f64, f64, usize),
    test: Option<TestSplit>,
    /// How many images the candidate was adapted on (its manifest's `training.run.n_images`).
    trained_on: Option<u64>,
}

impl DomainResult {
    fn stats(m: &[Measured]) -> GateStats {
        GateStats { images: m.iter().map(|m| m.check.clone()).collect() }
    }

    fn accuracy(&self, m: &[Measured]) -> Result<f64> {
        let errors: Vec<f64> =
            m.iter().zip(&self.truth).map(|(m, t)| pose_error(Some(angles(&m.pose)), angles(t))).collect();
        Ok(PoseMetrics::from_errors(&errors)?.acc_pi_6)
    }

    fn decide(&self, config: &GateConfig) -> Result<Decision> {
        Ok(gate::decide(&Self::stats(&self.active), &Self::stats(&self.candidate), config)?)
    }

    /// Held-out (adapt split) Acc@π/6 of the source and adapted models.
    fn adapt_accuracy(&self) -> Result<(f64, f64)> {
        Ok((self.accuracy(&self.active)?, self.accuracy(&self.candidate)?))
    }
}

fn angles(p: &Pose) -> [f64; 3] {
    [p.azimuth, p.elevation, p.theta]
}

fn slug(domain: &str) -> String {
    domain.replace('/', "-")
}

/// Whether a decision agrees with the sign of an accuracy change: pass when it rose, reject
/// when it fell; `None` when it did not change.
fn agrees(passed: bool, change: f64) -> Option<bool> {
    (change != 0.0).then_some(passed == (change > 0.0))
}

pub fn run(args: &GateArgs) -> Result<()> {
    let started = Instant::now();
    let device = RuntimeInfo::detect().device();
    let source =
        checkpoint::load(&args.source, device).with_context(|| format!("loading {}", args.source.display()))?;
    let mut config = GateConfig::default();
    if let Some(g) = args.margin_gain {
        config.margin_gain = g;
    }
    config.validate()?;
    if args.gains.is_empty() || args.gains.iter().any(|g| !g.is_finite()) {
        bail!("--gains must be finite values");
    }
    if let (Some(images), Some(candidate)) = (&args.images, &args.candidate) {
        return decide_folder(args, &source, candidate, images, &config);
    }
    let eval = args.eval.clone().unwrap_or_else(|| args.adapted.parent().unwrap_or(Path::new(".")).join("eval"));
    let domains: Vec<String> = if args.domains.is_empty() {
        all_domains()
            .into_iter()
            .map(|d| d.name)
            .filter(|d| args.adapted.join(slug(d)).join(checkpoint::MANIFEST).is_file())
            .filter(|d| args.data.join(d).join("adapt").is_dir())
            .collect()
    } else {
        args.domains.clone()
    };
    if domains.is_empty() {
        bail!("no adapted model under {} has an adapt split under {}", args.adapted.display(), args.data.display());
    }
    let mut results = Vec::with_capacity(domains.len());
    for domain in &domains {
        let t = Instant::now();
        let r = measure_domain(args, &source, domain, &eval, &config)?;
        let d = r.decide(&config)?;
        eprintln!("{domain}: {} images, {} ({:.0} s)", r.images.len(), d.reason(), t.elapsed().as_secs_f64());
        results.push(r);
    }
    report::write_report(args, &config, &results, started.elapsed().as_secs_f64())
}

/// `--images`: the gate's decision on a folder of unlabelled images, printed as JSON.
fn decide_folder(args: &GateArgs, source: &Model, candidate: &Path, dir: &Path, config: &GateConfig) -> Result<()> {
    let adapted =
        checkpoint::load(candidate, source.vs.device()).with_context(|| format!("loading {}", candidate.display()))?;
    let [h, w] = source.manifest.crop;
    let (pixels, names) = udapose_lab::loader::load_image_folder(dir, h, w)?;
    let mut keep = Vec::new();
    for (i, name) in names.iter().enumerate() {
        let bytes = std::fs::read(dir.join(name)).with_context(|| format!("reading {name}"))?;
        if args.all_adapt || gate::held_out(&Sha256::digest(&bytes)) {
            keep.push(i as i64);
        }
    }
    let all = Tensor::from_slice(&pixels).reshape([names.len() as i64, 3, h as i64, w as i64]);
    let images = all.index_select(0, &Tensor::from_slice(&keep));
    let go = &mut |_: usize, _: usize| ControlFlow::Continue(());
    let active = gate::measure(source, &images, config, go)?;
    let cand = gate::measure(&adapted, &images, config, go)?;
    let decision = gate::decide(&active, &cand, config)?;
    let kept: Vec<&String> = keep.iter().map(|&i| &names[i as usize]).collect();
    let out = json!({
        "images": kept, "config": config, "decision": decision, "reason": decision.reason(),
        "active": active, "candidate": cand,
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}

fn measure_domain(
    args: &GateArgs,
    source: &Model,
    domain: &str,
    eval: &Path,
    config: &GateConfig,
) -> Result<DomainResult> {
    let dir = args.adapted.join(slug(domain));
    let adapted = checkpoint::load(&dir, source.vs.device()).with_context(|| format!("loading {}", dir.display()))?;
    if adapted.manifest.crop != source.manifest.crop {
        bail!(
            "{}: crop {:?} differs from the source's {:?}",
            dir.display(),
            adapted.manifest.crop,
            source.manifest.crop
        );
    }
    let split = SyncarSplit::open(&args.data, domain, "adapt")?;
    let mut indices = Vec::new();
    for (i, entry) in split.entries().iter().enumerate() {
        let bytes =
            std::fs::read(&entry.image_path).with_context(|| format!("reading {}", entry.image_path.display()))?;
        if args.all_adapt || gate::held_out(&Sha256::digest(&bytes)) {
            indices.push(i);
        }
    }
    let [h, w] = source.manifest.crop;
    let load = |indices: &[usize]| -> Result<(Tensor, Vec<Pose>, Vec<String>)> {
        let (mut pixels, mut truth, mut names) = (Vec::new(), Vec::new(), Vec::new());
        for &i in indices {
            let s = load_sample(&split, i)?;
            if (s.height, s.width) != (h, w) {
                bail!("{domain}: images are {}x{}, the model's crop is {w}x{h}", s.width, s.height);
            }
            pixels.extend(s.pixels);
            truth.push(s.pose);
            names.push(s.name);
        }
        Ok((Tensor::from_slice(&pixels).reshape([names.len() as i64, 3, h as i64, w as i64]), truth, names))
    };
    let (tensor, truth, images) = load(&indices)?;
    let go = &mut |_: usize, _: usize| ControlFlow::Continue(());
    let active = gate::measure_poses(source, &tensor, config, go)?;
    let candidate = gate::measure_poses(&adapted, &tensor, config, go)?;
    // The rest of the adapt split, for its accuracy change (labels only; the gate never sees it).
    let rest: Vec<usize> = (0..split.len()).filter(|i| !indices.contains(i)).collect();
    let (rest_tensor, rest_truth, _) = load(&rest)?;
    let errors = |model: &Model, measured: &[Measured]| -> Result<Vec<f64>> {
        let mut poses: Vec<Pose> = measured.iter().map(|m| m.pose).collect();
        poses.extend(estimate_all(model, &rest_tensor, &config.solver)?);
        Ok(poses
            .iter()
            .zip(truth.iter().chain(&rest_truth))
            .map(|(p, t)| pose_error(Some(angles(p)), angles(t)))
            .collect())
    };
    let acc = |e: Vec<f64>| -> Result<f64> { Ok(PoseMetrics::from_errors(&e)?.acc_pi_6) };
    let adapt_split = (acc(errors(source, &active)?)?, acc(errors(&adapted, &candidate)?)?, split.len());
    let test = test_accuracy(eval, domain);
    let trained_on = adapted.manifest.training["run"]["n_images"].as_u64();
    Ok(DomainResult { domain: domain.to_string(), images, truth, active, candidate, adapt_split, test, trained_on })
}

/// The estimate of every image (N×3×H×W in [0, 1]): the backbone 16 images a pass, the
/// solver in parallel over them.
fn estimate_all(model: &Model, images: &Tensor, config: &SolverConfig) -> Result<Vec<Pose>> {
    let n = images.size()[0];
    let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, model.manifest.crop, config.clone())?;
    let mut out = Vec::with_capacity(n as usize);
    for start in (0..n).step_by(gate::MEASURE_BATCH) {
        let len = (gate::MEASURE_BATCH as i64).min(n - start);
        let batch = images.narrow(0, start, len).to_device(model.vs.device());
        let features = estimator::features(&model.backbone, &batch)?;
        // Host data only crosses into the worker threads (tch tensors are not Sync).
        let poses: Vec<Pose> =
            features.par_iter().map(|f| Ok(solver.solve(f)?.pose)).collect::<udapose_engine::Result<_>>()?;
        out.extend(poses);
    }
    Ok(out)
}

/// The test split's Acc@π/6 for both models, from the report's evaluations.
#[derive(Clone, Copy, Debug)]
struct TestSplit {
    source: f64,
    adapted: f64,
    /// Source → adapted, image by image.
    paired: Paired,
}

impl TestSplit {
    fn change(&self) -> f64 {
        self.adapted - self.source
    }
}

/// Test-split Acc@π/6 of the source and adapted models from the report's evaluations, paired
/// by their per-image errors (the same list order).
fn test_accuracy(eval: &Path, domain: &str) -> Option<TestSplit> {
    let read = |variant: &str| -> Option<(f64, Vec<f64>)> {
        let path = eval.join(variant).join(format!("{}.json", slug(domain)));
        let v: Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
        let d = &v["domains"][domain];
        let errors = d["errors_deg"].as_array()?.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>()?;
        Some((d["acc_pi_6"].as_f64()?, errors))
    };
    let ((source, s), (adapted, a)) = (read("source")?, read("adapted")?);
    if s.len() != a.len() {
        return None;
    }
    let right = |e: f64| e < 30.0;
    let paired =
        Paired::new(&s.iter().map(|&e| right(e)).collect::<Vec<_>>(), &a.iter().map(|&e| right(e)).collect::<Vec<_>>());
    Some(TestSplit { source, adapted, paired })
}
