//! `udapose-lab eval`: Acc@π/6, Acc@π/18 and MedErr of a model on every domain of a dataset.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde_json::json;
use tch::Tensor;
use udapose_engine::adapt::{AdaptConfig, FiringTest, Threshold};
use udapose_engine::camera::Pose;
use udapose_engine::checkpoint;
use udapose_engine::estimator::Estimator;
use udapose_engine::metrics::MetricIntervals;
use udapose_engine::runtime::RuntimeInfo;
use udapose_engine::solver::SolverConfig;
use udapose_engine::{PoseMetrics, nearest_look_alike, pose_error_up_to};
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::{Sample, load_sample, training_pose};
use udapose_lab::synth::all_domains;

#[derive(clap::Args)]
pub struct Args {
    /// Model directory (manifest.json + weights).
    #[arg(long)]
    model: PathBuf,
    /// SynCar-OOD root.
    #[arg(long)]
    data: PathBuf,
    /// Report (JSON; a Markdown twin is written next to it).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value = "test")]
    split: String,
    /// Only these domains (default: every domain present).
    #[arg(long, value_delimiter = ',')]
    domains: Vec<String>,
    /// At most this many images per domain (0: all).
    #[arg(long, default_value_t = 0)]
    limit: usize,
}

pub fn run(args: &Args) -> Result<()> {
    let device = RuntimeInfo::detect().device();
    let model = checkpoint::load(&args.model, device).with_context(|| format!("loading {}", args.model.display()))?;
    let estimator = Estimator::new(model, SolverConfig::default())?;
    let (model, config) = (&estimator.model, &estimator.solver().config);
    // The fired-vertex diagnostic uses the adaptation's firing test.
    let threshold = AdaptConfig::default().threshold;
    let names: Vec<String> =
        if args.domains.is_empty() { domains_present(&args.data, &args.split) } else { args.domains.clone() };
    if names.is_empty() {
        bail!("no domain with a {} split under {}", args.split, args.data.display());
    }
    let mut domains = serde_json::Map::new();
    let mut md = format!(
        "# Evaluation of `{}`\n\n`udapose-lab eval --model {} --data {} --split {}` (k = {}), commit `{}`.\n\nIn brackets: 95% bootstrap intervals (1000 resamples of the test images, seed 0).\n\n\
         | domain | Acc@π/6 | Acc@π/18 | MedErr (°) | n |\n|---|---:|---:|---:|---:|\n",
        model.manifest.version,
        args.model.display(),
        args.data.display(),
        args.split,
        config.hypotheses,
        crate::synth_cmd::git_commit()
    );
    for name in &names {
        let errors = domain_errors(&estimator, args, name, threshold)?;
        let (entry, row) = domain_entry(name, errors)?;
        md.push_str(&row);
        domains.insert(name.clone(), entry);
    }
    let profile = std::fs::read_to_string(args.data.join("manifest.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .map_or(serde_json::Value::Null, |m| m["profile"].clone());
    let report = json!({
        "profile": profile,
        "train_seconds": model.manifest.training["train_seconds"],
        "machine": machine(),
        "model": model.manifest.version,
        "model_dir": args.model.display().to_string(),
        "data": args.data.display().to_string(),
        "split": args.split,
        "commit": crate::synth_cmd::git_commit(),
        "domains": domains,
    });
    udapose_lab::atomic::write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    udapose_lab::atomic::write_atomic(&args.out.with_extension("md"), md.as_bytes())?;
    Ok(())
}

/// One domain's per-image results, in list order.
struct DomainErrors {
    errors: Vec<f64>,
    azimuths_deg: Vec<f64>,
    fired: Vec<f64>,
    /// Matches that fire at the estimated poses, and those the labels call false.
    fired_matches: usize,
    false_matches: usize,
}

/// Estimates every image of `name`'s split (at most `--limit`).
fn domain_errors(estimator: &Estimator, args: &Args, name: &str, threshold: Threshold) -> Result<DomainErrors> {
    let [h, w] = estimator.model.manifest.crop;
    let solver = estimator.solver();
    let split = SyncarSplit::open(&args.data, name, &args.split)?;
    let n = if args.limit == 0 { split.len() } else { args.limit.min(split.len()) };
    let mut out = DomainErrors {
        errors: Vec::with_capacity(n),
        azimuths_deg: Vec::with_capacity(n),
        fired: Vec::with_capacity(n),
        fired_matches: 0,
        false_matches: 0,
    };
    let firing = FiringTest::new(&estimator.model.neural_mesh, solver.camera(), solver.config.stride, threshold)?;
    for i in 0..n {
        let Sample { pixels, pose, height: ih, width: iw, symmetry, .. } = load_sample(&split, i)?;
        if (ih, iw) != (h, w) {
            bail!("{name}: images are {iw}x{ih}, the model's crop is {w}x{h}");
        }
        let image = Tensor::from_slice(&pixels).reshape([1, 3, h as i64, w as i64]);
        let features = estimator.batch_features(&image)?;
        let estimate = solver.solve(&features[0]).ok();
        let angles = estimate.as_ref().map(|e| [e.pose.azimuth, e.pose.elevation, e.pose.theta]);
        out.errors.push(pose_error_up_to(angles, [pose.azimuth, pose.elevation, pose.theta], symmetry));
        out.azimuths_deg.push(pose.azimuth.to_degrees());
        // Fired at the pose the mesh was trained on; false matches against the look-alike of the
        // truth nearest the estimate (for a symmetric object, the labels cannot tell them apart).
        out.fired.push(firing.fired_ratio(&features[0], &training_pose(pose, symmetry))?);
        if let (Some(e), Some(estimated)) = (estimate, angles) {
            let [azimuth, ..] = nearest_look_alike(estimated, [pose.azimuth, pose.elevation, pose.theta], symmetry);
            let truth = Pose { azimuth, ..pose };
            let (fired, wrong) = firing.false_matches(&features[0], &e.pose, &truth)?;
            out.fired_matches += fired;
            out.false_matches += wrong;
        }
    }
    Ok(out)
}

/// A domain's report entry (metrics, intervals, per-image arrays) and its Markdown row.
fn domain_entry(name: &str, d: DomainErrors) -> Result<(serde_json::Value, String)> {
    let m = PoseMetrics::from_errors(&d.errors)?;
    let ci = MetricIntervals::bootstrap(&d.errors, 1000, 0)?;
    eprintln!(
        "{name}: Acc@π/6 {:.3}, Acc@π/18 {:.3}, MedErr {:.1}° (n = {})",
        m.acc_pi_6, m.acc_pi_18, m.med_err_deg, m.n
    );
    let row = format!(
        "| {name} | {:.3} [{:.3}, {:.3}] | {:.3} [{:.3}, {:.3}] | {:.1} [{:.1}, {:.1}] | {} |\n",
        m.acc_pi_6,
        ci.acc_pi_6_ci[0],
        ci.acc_pi_6_ci[1],
        m.acc_pi_18,
        ci.acc_pi_18_ci[0],
        ci.acc_pi_18_ci[1],
        m.med_err_deg,
        ci.med_err_deg_ci[0],
        ci.med_err_deg_ci[1],
        m.n
    );
    let mut entry = serde_json::to_value(m)?;
    if let (Some(entry), serde_json::Value::Object(ci)) = (entry.as_object_mut(), serde_json::to_value(ci)?) {
        entry.extend(ci);
        // Per image, in list order: for paired comparisons and the report's histograms.
        let degrees: Vec<f64> = d.errors.iter().map(|e| e.to_degrees()).collect();
        entry.insert("errors_deg".into(), json!(degrees));
        entry.insert("azimuths_deg".into(), json!(d.azimuths_deg));
        entry.insert("fired_ratios".into(), json!(d.fired));
        // At the estimated pose (the first round's pseudo-pose): the share of fired matches
        // that the labels call false (hidden, or over a cell away from the vertex's true cell).
        let share = d.false_matches as f64 / d.fired_matches.max(1) as f64;
        entry.insert("fired_matches".into(), json!(d.fired_matches));
        entry.insert("false_fired_share".into(), json!(share));
    }
    Ok((entry, row))
}

/// Every domain under `root` with a `split` directory, one or two levels deep (`fog`,
/// `corrupt/fog`; BENCHMARK.md §4's layout): SynCar-OOD's own in their usual order, then any
/// others by name.
pub(crate) fn domains_present(root: &Path, split: &str) -> Vec<String> {
    let mut found = Vec::new();
    let mut visit = |rel: String| {
        if root.join(&rel).join(split).is_dir() {
            found.push(rel);
        }
    };
    for top in subdirs(root) {
        visit(top.clone());
        for sub in subdirs(&root.join(&top)) {
            if sub != split {
                visit(format!("{top}/{sub}"));
            }
        }
    }
    let known: Vec<String> = all_domains().into_iter().map(|d| d.name).collect();
    found.sort_by_key(|d| (known.iter().position(|k| k == d).unwrap_or(usize::MAX), d.clone()));
    found
}

fn subdirs(dir: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    entries
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir()) // follows symlinks: a domain may be a link to another disk
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .collect()
}

/// CPU model and thread count, for reports.
pub use udapose_lab::machine;
