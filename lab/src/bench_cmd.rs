//! `udapose-lab bench`: benchmarks on real data.
//!
//! `bench solver` times udapose's render and compare (the fast form of METHOD.md §6) against the
//! straightforward reference (`udapose_engine::solver::reference`: autograd rendering and
//! libtorch's Adam for METHOD's 300 steps) on the same images, the same backbone features and the
//! same initial grid poses, measures both against the ground truth, and times the backbone to
//! give the end-to-end latency of one estimate. Writes `reports/solver.json` and its Markdown
//! twin.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use tch::{Device, Tensor};
use udapose_engine::checkpoint;
use udapose_engine::estimator::{self, PoseSolver};
use udapose_engine::solver::reference::{self, ReferenceConfig};
use udapose_engine::solver::{AdamConfig, Estimate, Optimizer, SolverConfig};

use udapose_engine::metrics::paired_bootstrap;
use udapose_engine::{Pose, PoseMetrics, pose_error, rotation_error};
use udapose_lab::atomic::write_atomic;
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::load_sample;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: Bench,
}

#[derive(clap::Subcommand)]
enum Bench {
    /// udapose's solver vs the autograd reference (NeMo's way) on the same images and features:
    /// time per image, Acc@π/6, and end-to-end latency with the backbone's share.
    Solver(SolverArgs),
    /// The inference service under load: throughput and p50/p99 latency at several client
    /// concurrencies, batching on and off, against the backbone-only ceiling.
    Service(bench_service::ServiceArgs),
    /// The label-free validation gate on SynCar-OOD: source vs. adapted model per domain on the
    /// held-out adapt images, and whether each decision agrees with the true accuracy change.
    Gate(gate_cmd::GateArgs),
    /// Scale-out on one machine: serve replicas and an adapt worker on an S3-compatible store;
    /// throughput with 1, 2 and 3 replicas, failed requests under faults (kill -9 of a replica
    /// or of the worker mid-job, swaps, a rollback), and the swap propagation time.
    Scale(bench_scale::ScaleArgs),
}

#[path = "bench_service.rs"]
mod bench_service;

#[path = "bench_scale.rs"]
mod bench_scale;

#[path = "gate_cmd.rs"]
mod gate_cmd;

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

pub fn run(args: &Args) -> Result<()> {
    match &args.command {
        Bench::Solver(a) => solver(a),
        Bench::Service(a) => bench_service::run(a),
        Bench::Gate(a) => gate_cmd::run(a),
        Bench::Scale(a) => bench_scale::run(a),
    }
}

/// One image's measurements.
struct Row {
    name: String,
    truth: Pose,
    backbone_ms: f64,
    fast: Solved,
    method: Solved,
    reference: Solved,
    same_inits: bool,
}

/// One solver's answer on one image.
struct Solved {
    ms: f64,
    pose: Option<Pose>,
    loss: f64,
    error: f64,
}

impl Solved {
    fn new(ms: f64, estimate: udapose_engine::Result<Estimate>, truth: &Pose) -> Self {
        let (pose, loss) = match estimate {
            Ok(e) => (Some(e.pose), e.hypotheses[0].loss),
            Err(_) => (None, f64::NAN),
        };
        let error = pose_error(pose.map(angles), angles(*truth));
        Solved { ms, pose, loss, error }
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
    let mut v: Vec<f64> = v.collect();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// Acc@π/6 of udapose (its default, and METHOD's steps) against the reference on the same
/// images: how many only one of them gets right, and the difference with a 95% paired
/// bootstrap interval (1000 resamples, seed 0).
fn paired_accuracy(rows: &[Row]) -> serde_json::Value {
    let hit = |s: &Solved| f64::from(u8::from(s.error < std::f64::consts::FRAC_PI_6));
    let compare = |pick: fn(&Row) -> &Solved| {
        let diff: Vec<f64> = rows.iter().map(|r| hit(pick(r)) - hit(&r.reference)).collect();
        let ci = paired_bootstrap(diff.len(), 1000, 0, |idx| Some(mean(idx.iter().map(|&i| diff[i]))));
        json!({
            "only_udapose_right": diff.iter().filter(|&&d| d > 0.0).count(),
            "only_reference_right": diff.iter().filter(|&&d| d < 0.0).count(),
            "acc_pi_6_difference": mean(diff.iter().copied()),
            "ci95": ci,
        })
    };
    json!({"udapose": compare(|r| &r.fast), "udapose_method": compare(|r| &r.method)})
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The initial grid poses of every hypothesis, as a sorted list (the order follows the losses).
fn inits(e: &udapose_engine::Result<Estimate>) -> Vec<[u64; 4]> {
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

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

fn solver(args: &SolverArgs) -> Result<()> {
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
    let mut method_solver = solver.clone();
    method_solver.config.optimizer = Optimizer::Adam(AdamConfig::method());
    let (camera, config, mesh_model) = (*solver.camera(), &solver.config, solver.mesh_model()?);
    let reference_config = ReferenceConfig { parallel_hypotheses: args.reference_parallel, ..Default::default() };
    if args.backbone_torch_threads < 0 {
        bail!("--backbone-torch-threads must be at least 0");
    }
    if args.backbone_torch_threads > 0 {
        tch::set_num_threads(args.backbone_torch_threads);
    }
    let torch_threads = tch::get_num_threads();
    let mut samples = Vec::new();
    for name in &args.split {
        let split = SyncarSplit::open(&args.data, &args.domain, name)?;
        if split.len() < args.images {
            bail!("{}/{name} has {} images, fewer than --images {}", args.domain, split.len(), args.images);
        }
        samples.push((name.as_str(), split));
    }
    let total = args.images * samples.len();
    let grid = camera.at_stride(config.stride)?;
    let style = ProgressStyle::with_template("{prefix:>18} [{bar:30}] {pos}/{len} {elapsed} eta {eta} {msg}")
        .expect("valid template")
        .progress_chars("=> ");
    let bar = |prefix: &str| ProgressBar::new(total as u64).with_style(style.clone()).with_prefix(prefix.to_string());

    // Phase 1: the backbone's features of every image, timed per image (decoding is not timed),
    // after one untimed warm-up call.
    let mut images = Vec::with_capacity(total);
    let progress = bar("backbone");
    let each = samples.iter().flat_map(|(name, split)| (0..args.images).map(move |i| (*name, split, i)));
    for (k, (split_name, split, i)) in each.enumerate() {
        let (pixels, truth, ih, iw, name) = load_sample(split, i)?;
        let name = if samples.len() > 1 { format!("{split_name}/{name}") } else { name };
        if (ih, iw) != (h, w) {
            bail!("{name}: image is {iw}x{ih}, the model's crop is {w}x{h}");
        }
        let image = Tensor::from_slice(&pixels).reshape([1, 3, h as i64, w as i64]);
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
        images.push((name, truth, backbone_ms, f));
        progress.inc(1);
    }
    progress.finish();

    // Phase 2: udapose's solver (its default, and METHOD's 300 steps) on those features.
    solver.solve(&images[0].3)?; // warm-up
    let progress = bar("udapose");
    let mut fast = Vec::with_capacity(total);
    for (_, truth, _, f) in &images {
        let t = Instant::now();
        let estimate = solver.solve(f);
        let fast_ms = ms_since(t);
        let t = Instant::now();
        let estimate_method = method_solver.solve(f);
        let method_ms = ms_since(t);
        let starts = inits(&estimate);
        fast.push((Solved::new(fast_ms, estimate, truth), Solved::new(method_ms, estimate_method, truth), starts));
        progress.inc(1);
    }
    progress.finish();

    // Phase 3: the reference on the same features, under its own torch thread count (switched
    // once: switching per call stalls libtorch's thread pool).
    tch::set_num_threads(args.reference_torch_threads);
    let reference_run = (|| -> Result<Vec<(Solved, Vec<[u64; 4]>)>> {
        let short = ReferenceConfig { adam: AdamConfig { steps: 5, ..AdamConfig::method() }, ..reference_config };
        reference::render_and_compare(&mesh_model, &images[0].3.map()?, &camera, config, &short)?; // warm-up
        let progress = bar("reference");
        let mut out = Vec::with_capacity(total);
        for (_, truth, _, f) in &images {
            let t = Instant::now();
            let estimate = f
                .map()
                .and_then(|m| reference::render_and_compare(&mesh_model, &m, &camera, config, &reference_config));
            let ms = ms_since(t);
            let starts = inits(&estimate);
            out.push((Solved::new(ms, estimate, truth), starts));
            progress.set_message(format!("{:.0} ms per image", mean(out.iter().map(|(s, _)| s.ms))));
            progress.inc(1);
        }
        progress.finish();
        Ok(out)
    })();
    tch::set_num_threads(torch_threads);

    let rows: Vec<Row> = images
        .into_iter()
        .zip(fast)
        .zip(reference_run?)
        .map(|(((name, truth, backbone_ms, _), (fast, method, fast_inits)), (reference, reference_inits))| Row {
            name,
            truth,
            backbone_ms,
            fast,
            method,
            reference,
            same_inits: !fast_inits.is_empty() && fast_inits == reference_inits,
        })
        .collect();

    let metrics = |pick: fn(&Row) -> &Solved| -> Result<PoseMetrics> {
        Ok(PoseMetrics::from_errors(&rows.iter().map(|r| pick(r).error).collect::<Vec<_>>())?)
    };
    let (m_fast, m_method, m_ref) = (metrics(|r| &r.fast)?, metrics(|r| &r.method)?, metrics(|r| &r.reference)?);
    let backbone_ms = mean(rows.iter().map(|r| r.backbone_ms));
    let fast_ms = mean(rows.iter().map(|r| r.fast.ms));
    let method_ms = mean(rows.iter().map(|r| r.method.ms));
    let reference_ms = mean(rows.iter().map(|r| r.reference.ms));
    let end_to_end = backbone_ms + fast_ms;
    let backbone_median = median(rows.iter().map(|r| r.backbone_ms));
    let fast_median = median(rows.iter().map(|r| r.fast.ms));
    let n = rows.len();
    let same_inits = rows.iter().filter(|r| r.same_inits).count();
    let both = |r: &Row| r.fast.pose.zip(r.reference.pose);
    let disagreement =
        median(rows.iter().filter_map(both).map(|(a, b)| rotation_error(&a.rotation(), &b.rotation()).to_degrees()));
    let reference_lower = rows.iter().filter(|r| r.reference.loss < r.fast.loss).count();
    let paired = paired_accuracy(&rows);
    let failures = |pick: fn(&Row) -> &Solved| rows.iter().filter(|r| pick(r).pose.is_none()).count();
    let commit = crate::synth_cmd::git_commit();
    let cpu = udapose_engine::runtime::cpu_model();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let load_after = load_average();
    let solved = |s: &Solved| {
        json!({
            "ms": s.ms,
            "pose": s.pose.map(|p| [p.azimuth, p.elevation, p.theta, p.distance]),
            "loss": s.loss,
            "error_deg": s.error.to_degrees(),
        })
    };
    let per_image: Vec<serde_json::Value> = rows
        .iter()
        .map(|r| {
            json!({
                "name": r.name,
                "truth": [r.truth.azimuth, r.truth.elevation, r.truth.theta, r.truth.distance],
                "backbone_ms": r.backbone_ms,
                "udapose": solved(&r.fast),
                "udapose_method": solved(&r.method),
                "reference": solved(&r.reference),
                "same_inits": r.same_inits,
            })
        })
        .collect();
    let Optimizer::Adam(fast_adam) = &config.optimizer else { bail!("the default optimiser is Adam") };
    let report = json!({
        "grid": [grid.height, grid.width],
        "crop": [h, w],
        "udapose_ms_per_image": fast_ms,
        "reference_ms_per_image": reference_ms,
        "speedup": reference_ms / fast_ms,
        "udapose_acc_pi_6": m_fast.acc_pi_6,
        "reference_acc_pi_6": m_ref.acc_pi_6,
        "end_to_end_ms": end_to_end,
        "backbone_share": backbone_ms / end_to_end,
        "backbone_ms_per_image": backbone_ms,
        "backbone_median_ms": backbone_median,
        "end_to_end_median_ms": backbone_median + fast_median,
        "backbone_share_median": backbone_median / (backbone_median + fast_median),
        "udapose_median_ms": fast_median,
        "reference_median_ms": median(rows.iter().map(|r| r.reference.ms)),
        "udapose_metrics": m_fast,
        "reference_metrics": m_ref,
        "udapose_method_steps": {
            "note": "udapose's solver with METHOD's 300-step schedule (the reference's), for a same-steps comparison",
            "ms_per_image": method_ms,
            "speedup": reference_ms / method_ms,
            "metrics": m_method,
        },
        "same_inits": same_inits,
        "reference_lower_loss": reference_lower,
        "median_disagreement_deg": disagreement,
        "failures": {"udapose": failures(|r| &r.fast), "reference": failures(|r| &r.reference)},
        "hypotheses": config.hypotheses,
        "udapose_optimizer": config.optimizer,
        "reference_optimizer": {
            "adam": reference_config.adam,
            "parallel_hypotheses": reference_config.parallel_hypotheses,
            "torch_threads": args.reference_torch_threads,
            "rendering": "tch autograd ops per step (projection, perspective-correct barycentrics, feature render, per-pixel dot product); face assignment from udapose's rasteriser",
        },
        "n": n,
        "model": model.manifest.version,
        "model_dir": args.model.display().to_string(),
        "data": args.data.display().to_string(),
        "domain": args.domain,
        "split": args.split.join(","),
        "paired": paired,
        "machine": {
            "cpu": cpu,
            "threads": threads,
            "torch_threads": torch_threads,
            "rayon_threads": rayon::current_num_threads(),
            "load_average_before": load_before,
            "load_average_after": load_after,
        },
        "commit": commit,
        "command": command,
        "note": args.note,
        "timing": "mean wall-clock ms per image after one untimed warm-up image; image decoding untimed; backbone: one image per batch on the CPU; udapose: render_and_compare (similarity GEMM, multi-pose init, k refinements); reference: udapose's multi-pose init then k autograd refinements",
        "images": per_image,
    });

    let pct = |x: f64| 100.0 * x;
    let md = format!(
        "# Solver benchmark: udapose vs the autograd reference\n\n\
         `{command}`\n\n\
         Model `{version}` ({backbone:?}, D = {dim}), {n} images of `{domain}/{split}` ({h}×{w} crops, \
         {gh}×{gw} feature grid), k = {k} hypotheses from the same grid poses ({same_inits}/{n} images checked \
         identical). Machine: {cpu}, {threads} threads (torch {tt}, rayon {rt}; the reference runs with torch \
         {rtt}); load average {load_before} before, {load_after} after. Commit `{commit}`.\n\n\
         | solver | ms per image (mean) | median | Acc@π/6 | Acc@π/18 | MedErr (°) |\n\
         |---|---:|---:|---:|---:|---:|\n\
         | udapose (Adam {fs} steps, analytic gradient over S = C·F) | {fast_ms:.1} | {fast_med:.1} | {fa:.3} | {fb:.3} | {fc:.1} |\n\
         | udapose, METHOD's 300 steps | {method_ms:.1} | {method_med:.1} | {ma:.3} | {mb:.3} | {mc:.1} |\n\
         | reference (tch autograd render, Adam 300 steps) | {reference_ms:.1} | {ref_med:.1} | {ra:.3} | {rb:.3} | {rc:.1} |\n\n\
         **Speedup** (reference / udapose, mean ms per image): **{speedup:.0}×** ({speedup300:.0}× against udapose \
         at the reference's 300 steps).\n\n\
         **Paired** (Acc@π/6 on the same images): udapose alone right on {only_u}, the reference alone on \
         {only_r}; difference {pd:+.3} [{plo:+.3}, {phi:+.3}] (95% paired bootstrap).\n\n\
         **End to end** (backbone + udapose solver): {end_to_end:.1} ms per image, of which the backbone is \
         {backbone_ms:.1} ms (**{share:.0}%**); by medians, {e2e_median:.1} ms of which the backbone is \
         {backbone_median:.1} ms ({share_median:.0}%).\n\n\
         The two solvers' estimates differ by {disagreement:.1}° (median); the reference reached a lower loss on \
         {reference_lower}/{n} images. Times are wall-clock means after one untimed warm-up image; decoding is \
         not timed. The reference renders with autograd ops at every step (projection, perspective-correct \
         barycentrics, feature render, per-pixel dot product with F); its face assignment comes from \
         udapose's rasteriser, so it is a lower bound on a PyTorch3D renderer's cost. It refines the k \
         hypotheses {order}.\n{note}",
        version = model.manifest.version,
        backbone = model.manifest.backbone,
        dim = solver.dim(),
        domain = args.domain,
        split = args.split.join(","),
        only_u = paired["udapose"]["only_udapose_right"],
        only_r = paired["udapose"]["only_reference_right"],
        pd = paired["udapose"]["acc_pi_6_difference"].as_f64().unwrap_or(f64::NAN),
        plo = paired["udapose"]["ci95"][0].as_f64().unwrap_or(f64::NAN),
        phi = paired["udapose"]["ci95"][1].as_f64().unwrap_or(f64::NAN),
        gh = grid.height,
        gw = grid.width,
        k = config.hypotheses,
        tt = torch_threads,
        rtt = args.reference_torch_threads,
        rt = rayon::current_num_threads(),
        fs = fast_adam.steps,
        fast_med = fast_median,
        e2e_median = backbone_median + fast_median,
        share_median = pct(backbone_median / (backbone_median + fast_median)),
        method_med = median(rows.iter().map(|r| r.method.ms)),
        ref_med = median(rows.iter().map(|r| r.reference.ms)),
        fa = m_fast.acc_pi_6,
        fb = m_fast.acc_pi_18,
        fc = m_fast.med_err_deg,
        ma = m_method.acc_pi_6,
        mb = m_method.acc_pi_18,
        mc = m_method.med_err_deg,
        ra = m_ref.acc_pi_6,
        rb = m_ref.acc_pi_18,
        rc = m_ref.med_err_deg,
        speedup = reference_ms / fast_ms,
        speedup300 = reference_ms / method_ms,
        share = pct(backbone_ms / end_to_end),
        note = args.note.as_ref().map(|n| format!("\nNote: {n}\n")).unwrap_or_default(),
        order =
            if reference_config.parallel_hypotheses { "concurrently, as udapose does" } else { "one after the other" },
    );
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), md.as_bytes())?;
    eprintln!(
        "udapose {fast_ms:.1} ms/image (Acc@π/6 {:.3}), reference {reference_ms:.1} ms/image (Acc@π/6 {:.3}): \
         {:.0}× faster; end to end {end_to_end:.1} ms, backbone {:.0}%. Wrote {} and .md",
        m_fast.acc_pi_6,
        m_ref.acc_pi_6,
        reference_ms / fast_ms,
        pct(backbone_ms / end_to_end),
        args.out.display()
    );
    Ok(())
}
