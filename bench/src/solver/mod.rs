//! `udapose-bench solver`: times udapose's render and compare (the fast form of METHOD.md §6)
//! against the straightforward reference (`udapose_testkit::reference`: autograd rendering and
//! libtorch's Adam for METHOD's 300 steps) on the same images, the same backbone features and the
//! same initial grid poses, measures both against the ground truth, and times the backbone to
//! give the end-to-end latency of one estimate. Writes `reports/solver.json` and its Markdown
//! twin.

mod report;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use tch::{Device, Tensor};
use udapose_engine::camera::Camera;
use udapose_engine::checkpoint::{self, Model};
use udapose_engine::estimator::{self, Features, PoseSolver};
use udapose_engine::metrics::paired_bootstrap;
use udapose_engine::solver::{AdamConfig, Estimate, NeuralMeshView, Optimizer, Prune, SolverConfig, solve_from_grid};
use udapose_engine::{Pose, pose_error};
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::{Sample, load_sample};
use udapose_testkit::reference::{self, ReferenceConfig};

use crate::harness::{self, load_average};

#[derive(clap::Args)]
pub struct SolverArgs {
    /// Model directory (manifest.json + weights).
    #[arg(long)]
    model: PathBuf,
    /// SynCar-OOD root.
    #[arg(long)]
    data: PathBuf,
    /// The first this many images of each split.
    #[arg(long, default_value_t = 50)]
    images: usize,
    #[arg(long, default_value = "source")]
    domain: String,
    /// One split, or several (comma-separated, e.g. test,val,adapt) pooled into one comparison.
    #[arg(long, default_value = "test", value_delimiter = ',')]
    split: Vec<String>,
    /// Report (JSON; a Markdown twin is written next to it).
    #[arg(long, default_value = "reports/solver.json")]
    out: PathBuf,
    /// libtorch intra-op threads while the reference runs (restored afterwards). 1 is the
    /// reference's fastest setting on the 2-core machine: its per-step ops are too small to split.
    #[arg(long, default_value_t = 1)]
    reference_torch_threads: i32,
    /// libtorch intra-op threads for the backbone (0: libtorch's default, one per core).
    #[arg(long, default_value_t = 0)]
    backbone_torch_threads: i32,
    /// Refine the reference's k hypotheses concurrently (as udapose does) instead of in turn.
    #[arg(long)]
    reference_parallel: bool,
    /// A remark on the conditions of the run (e.g. other load), copied into both reports.
    #[arg(long)]
    note: Option<String>,
}

/// One image's measurements.
struct Row {
    name: String,
    truth: Pose,
    /// Decoding the PNG and making the input tensor (the crop is the image itself).
    load_ms: f64,
    backbone_ms: f64,
    /// udapose's default solver, its time split by stage.
    fast: Solved,
    stages: Stages,
    /// The fixed 150-step schedule without pruning (the default before plateau stopping).
    fixed: Solved,
    method: Solved,
    /// The default with every pose rasterised: the solver before the ray caster.
    rasterised: Solved,
    reference: Solved,
    same_inits: bool,
}

/// The default solver's time on one image by stage (ms).
#[derive(Clone, Copy, Default)]
struct Stages {
    /// `S = C·F` and the clutter map ([`PoseSolver::problem`]).
    similarity: f64,
    /// The 144 grid losses from the cached renders.
    grid: f64,
    /// Selecting and refining the k hypotheses.
    refine: f64,
}

/// One solver's answer on one image.
struct Solved {
    ms: f64,
    pose: Option<Pose>,
    loss: f64,
    error: f64,
    /// Loss evaluations over all hypotheses.
    evaluations: usize,
}

impl Solved {
    fn new(ms: f64, estimate: udapose_engine::Result<Estimate>, truth: &Pose) -> Self {
        let (pose, loss, evaluations) = match estimate {
            Ok(e) => (Some(e.pose), e.hypotheses[0].loss, e.hypotheses.iter().map(|h| h.evaluations).sum()),
            Err(_) => (None, f64::NAN, 0),
        };
        let error = pose_error(pose.map(angles), angles(*truth));
        Solved { ms, pose, loss, error, evaluations }
    }
}

fn angles(p: Pose) -> [f64; 3] {
    [p.azimuth, p.elevation, p.theta]
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

fn median(v: impl Iterator<Item = f64>) -> f64 {
    harness::median(&v.collect::<Vec<_>>())
}

/// Acc@π/6 of udapose (its default, and METHOD's steps) against the reference, and of the
/// default against the fixed schedule, on the same images: how many only one of each pair gets
/// right, and the difference with a 95% paired bootstrap interval (1000 resamples, seed 0).
fn paired_accuracy(rows: &[Row]) -> serde_json::Value {
    let hit = |s: &Solved| f64::from(u8::from(s.error < std::f64::consts::FRAC_PI_6));
    let compare = |pick: fn(&Row) -> &Solved, baseline: fn(&Row) -> &Solved| {
        let diff: Vec<f64> = rows.iter().map(|r| hit(pick(r)) - hit(baseline(r))).collect();
        let ci = paired_bootstrap(diff.len(), 1000, 0, |idx| Some(mean(idx.iter().map(|&i| diff[i]))));
        json!({
            "only_udapose_right": diff.iter().filter(|&&d| d > 0.0).count(),
            "only_reference_right": diff.iter().filter(|&&d| d < 0.0).count(),
            "acc_pi_6_difference": mean(diff.iter().copied()),
            "ci95": ci,
        })
    };
    json!({
        "udapose": compare(|r| &r.fast, |r| &r.reference),
        "udapose_method": compare(|r| &r.method, |r| &r.reference),
        "udapose_vs_fixed": compare(|r| &r.fast, |r| &r.fixed),
        "udapose_vs_rasterised": compare(|r| &r.fast, |r| &r.rasterised),
    })
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The initial grid poses of every hypothesis, as a sorted list (the order follows the losses).
fn inits(e: &udapose_engine::Result<Estimate>) -> Inits {
    let mut v: Vec<[u64; 4]> = e
        .as_ref()
        .map(|e| {
            e.hypotheses
                .iter()
                .map(|h| [h.init.azimuth, h.init.elevation, h.init.theta, h.init.distance].map(f64::to_bits))
                .collect()
        })
        .unwrap_or_default();
    v.sort_unstable();
    v
}

/// `arg` as a POSIX shell word: as is when it is plain, else single-quoted.
fn shell_quote(arg: &str) -> String {
    let plain = !arg.is_empty() && arg.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_./=:,+@%".contains(&b));
    if plain { arg.to_string() } else { format!("'{}'", arg.replace('\'', "'\\''")) }
}

/// What the report says about the run besides its measurements.
struct Run<'a> {
    args: &'a SolverArgs,
    command: String,
    load_before: String,
    model: &'a Model,
    solver: &'a PoseSolver,
    reference_config: ReferenceConfig,
    grid: Camera,
    torch_threads: i32,
}

/// Images per turn of udapose and the reference (about 45 s of the reference on one core).
const TURN: usize = 30;

pub fn run(args: &SolverArgs) -> Result<()> {
    if args.images == 0 {
        bail!("--images must be at least 1");
    }
    if args.reference_torch_threads < 1 {
        bail!("--reference-torch-threads must be at least 1");
    }
    let command = std::env::args().map(|a| shell_quote(&a)).collect::<Vec<_>>().join(" ");
    let load_before = load_average();
    let model =
        checkpoint::load(&args.model, Device::Cpu).with_context(|| format!("loading {}", args.model.display()))?;
    let [h, w] = model.manifest.crop;
    let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, [h, w], SolverConfig::default())?;
    let fixed_config = SolverConfig {
        optimizer: Optimizer::Adam(AdamConfig::fixed()),
        prune: Prune::default(),
        ..solver.config.clone()
    };
    let fixed_solver = PoseSolver::for_neural_mesh(&model.neural_mesh, [h, w], fixed_config)?;
    let method_config =
        SolverConfig { optimizer: Optimizer::Adam(AdamConfig::method()), ..fixed_solver.config.clone() };
    let method_solver = PoseSolver::for_neural_mesh(&model.neural_mesh, [h, w], method_config)?;
    let raster_config = SolverConfig { ray_cast: false, ..solver.config.clone() };
    let raster_solver = PoseSolver::for_neural_mesh(&model.neural_mesh, [h, w], raster_config)?;
    let mesh_model = solver.mesh_model()?;
    let reference_config = ReferenceConfig { parallel_hypotheses: args.reference_parallel, ..Default::default() };
    if args.backbone_torch_threads < 0 {
        bail!("--backbone-torch-threads must be at least 0");
    }
    if args.backbone_torch_threads > 0 {
        tch::set_num_threads(args.backbone_torch_threads);
    }
    let torch_threads = tch::get_num_threads();
    let samples = open_splits(args)?;
    let total = args.images * samples.len();
    let grid = solver.camera().at_stride(solver.config.stride)?;

    let images = backbone_phase(&model, &samples, args.images, &grid, total)?;
    // udapose and the reference take turns, a chunk of images each: the reference's 15 minutes
    // would otherwise run after udapose's 30 seconds, and a shared host whose speed drifts
    // (one run measured every phase 20-60% slower than the run before) would skew the ratio.
    let (mut fast, mut reference_run) = (Vec::new(), Vec::new());
    for chunk in images.chunks(TURN) {
        fast.extend(udapose_phase(&solver, [&fixed_solver, &method_solver, &raster_solver], chunk)?);
        // The reference under its own torch thread count (switched per turn, not per call:
        // switching per call stalls libtorch's thread pool).
        tch::set_num_threads(args.reference_torch_threads);
        let turn = reference_phase(&solver, &mesh_model, &reference_config, chunk);
        tch::set_num_threads(torch_threads);
        reference_run.extend(turn?);
    }

    let rows: Vec<Row> = images
        .into_iter()
        .zip(fast)
        .zip(reference_run)
        .map(|((image, udapose), (reference, reference_inits))| Row {
            name: image.name,
            truth: image.truth,
            load_ms: image.load_ms,
            backbone_ms: image.backbone_ms,
            same_inits: !udapose.inits.is_empty() && udapose.inits == reference_inits,
            fast: udapose.fast,
            stages: udapose.stages,
            fixed: udapose.fixed,
            method: udapose.method,
            rasterised: udapose.rasterised,
            reference,
        })
        .collect();
    let run = Run { args, command, load_before, model: &model, solver: &solver, reference_config, grid, torch_threads };
    report::write(&run, &rows)
}

/// Every `--split` of `--domain`, each with at least `--images` images.
fn open_splits(args: &SolverArgs) -> Result<Vec<(&str, SyncarSplit)>> {
    let mut samples = Vec::new();
    for name in &args.split {
        let split = SyncarSplit::open(&args.data, &args.domain, name)?;
        if split.len() < args.images {
            bail!("{}/{name} has {} images, fewer than --images {}", args.domain, split.len(), args.images);
        }
        samples.push((name.as_str(), split));
    }
    Ok(samples)
}

fn bar(total: usize, prefix: &str) -> ProgressBar {
    let style = ProgressStyle::with_template("{prefix:>18} [{bar:30}] {pos}/{len} {elapsed} eta {eta} {msg}")
        .expect("valid template")
        .progress_chars("=> ");
    ProgressBar::new(total as u64).with_style(style).with_prefix(prefix.to_string())
}

/// One image's name, true pose, load and backbone times (ms) and features.
struct Image {
    name: String,
    truth: Pose,
    load_ms: f64,
    backbone_ms: f64,
    features: Features,
}

/// The initial grid poses of an estimate's hypotheses (see [`inits`]).
type Inits = Vec<[u64; 4]>;

/// Phase 1: the backbone's features of every image, timed per image (decoding is not timed),
/// after one untimed warm-up call.
fn backbone_phase(
    model: &Model,
    samples: &[(&str, SyncarSplit)],
    per_split: usize,
    grid: &Camera,
    total: usize,
) -> Result<Vec<Image>> {
    let [h, w] = model.manifest.crop;
    let mut images = Vec::with_capacity(total);
    let progress = bar(total, "backbone");
    let each = samples.iter().flat_map(|(name, split)| (0..per_split).map(move |i| (*name, split, i)));
    for (k, (split_name, split, i)) in each.enumerate() {
        let t = Instant::now();
        let Sample { pixels, pose: truth, height: ih, width: iw, name, .. } = load_sample(split, i)?;
        let image = Tensor::from_slice(&pixels).reshape([1, 3, ih as i64, iw as i64]);
        let load_ms = ms_since(t);
        let name = if samples.len() > 1 { format!("{split_name}/{name}") } else { name };
        if (ih, iw) != (h, w) {
            bail!("{name}: image is {iw}x{ih}, the model's crop is {w}x{h}");
        }
        if k == 0 {
            estimator::features(&model.backbone, &image)?;
        }
        let t = Instant::now();
        let mut features = estimator::features(&model.backbone, &image)?;
        let backbone_ms = ms_since(t);
        let f = features.pop().context("the backbone returned no features")?;
        if (f.height, f.width) != (grid.height, grid.width) {
            bail!("{name}: features are {}×{}, expected the {}×{} grid", f.height, f.width, grid.height, grid.width);
        }
        images.push(Image { name, truth, load_ms, backbone_ms, features: f });
        progress.inc(1);
    }
    progress.finish();
    Ok(images)
}

/// udapose's three solvers on one image.
struct Udapose {
    fast: Solved,
    stages: Stages,
    fixed: Solved,
    method: Solved,
    rasterised: Solved,
    inits: Inits,
}

/// Phase 2: udapose's solvers (its default, stage by stage; then the fixed schedule, METHOD's
/// 300 steps and the default rasterised) on those features.
///
/// The solves run on rayon's pool, as the server's do (`Estimator::estimate_all_in`) and as
/// `PoseSolver::solve` moves itself: the stages timed one by one from outside the pool would
/// each hand their parallel steps to a pool thread and wait to be woken, a cost that is not
/// the solver's.
fn udapose_phase(solver: &PoseSolver, others: [&PoseSolver; 3], images: &[Image]) -> Result<Vec<Udapose>> {
    rayon::scope(|_| udapose_phase_on_pool(solver, others, images))
}

fn udapose_phase_on_pool(solver: &PoseSolver, others: [&PoseSolver; 3], images: &[Image]) -> Result<Vec<Udapose>> {
    solver.solve(&images[0].features)?; // warm-up
    let progress = bar(images.len(), "udapose");
    let mut out = Vec::with_capacity(images.len());
    for image in images {
        let (estimate, stages) = staged_solve(solver, &image.features);
        let timed = |s: &PoseSolver| {
            let t = Instant::now();
            let estimate = s.solve(&image.features);
            Solved::new(ms_since(t), estimate, &image.truth)
        };
        let [fixed, method, rasterised] = others.map(timed);
        let inits = inits(&estimate);
        let ms = stages.similarity + stages.grid + stages.refine;
        let fast = Solved::new(ms, estimate, &image.truth);
        out.push(Udapose { fast, stages, fixed, method, rasterised, inits });
        progress.inc(1);
    }
    progress.finish();
    Ok(out)
}

/// [`PoseSolver::solve`] one stage at a time, timing each (the same estimate).
fn staged_solve(solver: &PoseSolver, features: &Features) -> (udapose_engine::Result<Estimate>, Stages) {
    let mut stages = Stages::default();
    let t = Instant::now();
    let problem = solver.problem(features);
    stages.similarity = ms_since(t);
    let estimate = problem.and_then(|problem| {
        let t = Instant::now();
        let grid = solver.grid_losses(&problem)?;
        stages.grid = ms_since(t);
        let t = Instant::now();
        let estimate = solve_from_grid(&problem, &grid, &solver.config);
        stages.refine = ms_since(t);
        estimate
    });
    (estimate, stages)
}

/// Phase 3: the reference on the same features (after a 5-step warm-up).
fn reference_phase(
    solver: &PoseSolver,
    mesh_model: &NeuralMeshView,
    reference_config: &ReferenceConfig,
    images: &[Image],
) -> Result<Vec<(Solved, Inits)>> {
    let (camera, config) = (solver.camera(), &solver.config);
    let short = ReferenceConfig { adam: AdamConfig { steps: 5, ..AdamConfig::method() }, ..*reference_config };
    reference::render_and_compare(mesh_model, &images[0].features.map()?, camera, config, &short)?; // warm-up
    let progress = bar(images.len(), "reference");
    let mut out = Vec::with_capacity(images.len());
    for image in images {
        let t = Instant::now();
        let estimate = image
            .features
            .map()
            .and_then(|m| reference::render_and_compare(mesh_model, &m, camera, config, reference_config));
        let ms = ms_since(t);
        let starts = inits(&estimate);
        out.push((Solved::new(ms, estimate, &image.truth), starts));
        progress.set_message(format!("{:.0} ms per image", mean(out.iter().map(|(s, _)| s.ms))));
        progress.inc(1);
    }
    progress.finish();
    Ok(out)
}
