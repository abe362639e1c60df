//! `udapose-lab adapt` (3DUDA from an image folder, no labels) and `udapose-lab finetune` (the
//! supervised oracle on a labelled split, with the adaptation's budget or until its loss stops
//! falling).

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail, ensure};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use tch::Tensor;
use udapose_engine::adapt::{
    self, AdaptConfig, Adapted, Budget, Event, Label, Positives, Selection, Threshold, VertexMatches,
};
use udapose_engine::checkpoint::{self, Manifest, Model};
use udapose_engine::runtime::RuntimeInfo;
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::{load_annotated, load_image_folder, training_pose, up_symmetry};

/// Settings shared by `adapt` and `finetune` (defaults: [`AdaptConfig::default`]).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct Knobs {
    /// Backbone learning rate (Adam).
    #[arg(long)]
    lr: Option<f64>,
    /// EMA weight α of the old vertex feature.
    #[arg(long)]
    alpha: Option<f64>,
    /// ψ: minimum share of an image's visible vertices that must fire (default 0.2).
    #[arg(long)]
    min_fired_ratio: Option<f64>,
    /// One cosine threshold for every vertex (default 0.8, the paper's value).
    #[arg(long, conflicts_with = "source_threshold")]
    fixed_threshold: Option<f64>,
    /// Per-vertex thresholds τ_r from the checkpoint's source statistics instead.
    #[arg(long)]
    source_threshold: bool,
    /// The ablation: use an image only if at least this share (Ω, e.g. 0.5) of its visible
    /// vertices fire, then with all of them.
    #[arg(long)]
    global_filter: Option<f64>,
    /// At most this many EM rounds.
    #[arg(long)]
    max_rounds: Option<usize>,
    /// Images per backbone step.
    #[arg(long)]
    batch: Option<usize>,
    /// Vertex updates only (no backbone fine-tuning).
    #[arg(long)]
    no_backbone: bool,
    /// Move the clutter vector towards the target's clutter features (same α).
    #[arg(long)]
    update_clutter: bool,
    /// Images scoring below this quantile of a round are left out of the backbone step.
    #[arg(long)]
    drop_quantile: Option<f64>,
    /// Keep the source BatchNorm statistics (by default they are replaced by the target
    /// images' own first: AdaBN).
    #[arg(long)]
    no_target_bn: bool,
    /// The backbone step's positives: every visible vertex (the paper's eq. 8), only the fired
    /// ones, or the visible ones whose cell matches the object better than the clutter.
    #[arg(long, value_enum)]
    positives: Option<PositivesArg>,
    /// Whose fired matches move the vertex features: all k hypotheses' or the best one's.
    #[arg(long, value_enum)]
    vertex_matches: Option<VertexMatchesArg>,
    /// Only images whose mirrored crop's estimate mirrors their pseudo-pose (flip-consistent)
    /// move the vertex features and train the backbone.
    #[arg(long)]
    flip_check: bool,
    #[arg(long)]
    seed: Option<u64>,
}

impl Knobs {
    pub fn config(&self) -> AdaptConfig {
        let mut c = AdaptConfig::default();
        c.lr = self.lr.unwrap_or(c.lr);
        c.alpha = self.alpha.unwrap_or(c.alpha);
        c.min_fired_ratio = self.min_fired_ratio.unwrap_or(c.min_fired_ratio);
        c.max_rounds = self.max_rounds.unwrap_or(c.max_rounds);
        c.batch = self.batch.unwrap_or(c.batch);
        c.seed = self.seed.unwrap_or(c.seed);
        c.update_backbone = !self.no_backbone;
        c.update_clutter = self.update_clutter;
        c.drop_quantile = self.drop_quantile.unwrap_or(c.drop_quantile);
        c.positives = self.positives.map_or(c.positives, Positives::from);
        c.vertex_matches = self.vertex_matches.map_or(c.vertex_matches, VertexMatches::from);
        c.target_batchnorm &= !self.no_target_bn;
        c.flip_check = self.flip_check;
        if let Some(t) = self.fixed_threshold {
            c.threshold = Threshold::Fixed(t);
        }
        if self.source_threshold {
            c.threshold = Threshold::Source;
        }
        if let Some(omega) = self.global_filter {
            c.selection = Selection::Global(omega);
        }
        c
    }
}

/// [`Positives`] on the command line (the engine knows no clap).
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum PositivesArg {
    Visible,
    Fired,
    Object,
}

impl From<PositivesArg> for Positives {
    fn from(p: PositivesArg) -> Self {
        match p {
            PositivesArg::Visible => Positives::Visible,
            PositivesArg::Fired => Positives::Fired,
            PositivesArg::Object => Positives::Object,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
enum VertexMatchesArg {
    All,
    Best,
}

impl From<VertexMatchesArg> for VertexMatches {
    fn from(m: VertexMatchesArg) -> Self {
        match m {
            VertexMatchesArg::All => VertexMatches::All,
            VertexMatchesArg::Best => VertexMatches::Best,
        }
    }
}

#[derive(clap::Args)]
pub struct AdaptArgs {
    /// The source model directory (never modified).
    #[arg(long)]
    model: PathBuf,
    /// A folder of target-domain images (detection crops at the model's crop size); nothing
    /// else is read, so no annotation can leak in.
    #[arg(long)]
    images: PathBuf,
    /// The new model directory (must not exist). Each round is snapshotted beside it, in
    /// `.<name>.rounds/`: the same command rerun after an interruption resumes there.
    #[arg(long)]
    out: PathBuf,
    /// Version name of the new model (default: the name of `--out`).
    #[arg(long)]
    version: Option<String>,
    #[command(flatten)]
    knobs: Knobs,
}

#[derive(clap::Args)]
pub struct FinetuneArgs {
    /// The source model directory (never modified).
    #[arg(long)]
    model: PathBuf,
    /// A labelled split directory, e.g. data/syncar-ood-standard/combined/adapt.
    #[arg(long)]
    data: PathBuf,
    /// The new model directory (must not exist). Each round is snapshotted beside it, in
    /// `.<name>.rounds/`: the same command rerun after an interruption resumes there.
    #[arg(long)]
    out: PathBuf,
    /// Backbone optimiser steps (the budget).
    #[arg(long, conflicts_with_all = ["budget_of", "until_plateau"])]
    steps: Option<usize>,
    /// Take the budget from an adapted model's manifest (its backbone steps).
    #[arg(long, conflicts_with = "until_plateau")]
    budget_of: Option<PathBuf>,
    /// The strong oracle: passes over the split until a pass's mean loss is no longer 1% below
    /// the best earlier pass's (at least --min-passes, at most --max-passes).
    #[arg(long)]
    until_plateau: bool,
    #[arg(long, default_value_t = 10, requires = "until_plateau")]
    min_passes: usize,
    #[arg(long, default_value_t = 40, requires = "until_plateau")]
    max_passes: usize,
    #[arg(long)]
    version: Option<String>,
    #[command(flatten)]
    knobs: Knobs,
}

pub fn run_adapt(args: &AdaptArgs) -> Result<()> {
    adapt_folder(&args.model, &args.images, &args.out, args.version.as_deref(), &args.knobs.config())?;
    Ok(())
}

pub fn run_finetune(args: &FinetuneArgs) -> Result<()> {
    let budget = match (args.steps, &args.budget_of) {
        _ if args.until_plateau => {
            ensure!(args.min_passes <= args.max_passes, "--min-passes is above --max-passes");
            Budget::Plateau { min_passes: args.min_passes, max_passes: args.max_passes, tolerance: 0.01 }
        }
        (Some(s), _) => Budget::Steps(s),
        (None, Some(dir)) => Budget::Steps(backbone_steps(dir)?),
        (None, None) => bail!("give the budget: --steps N, --budget-of ADAPTED_MODEL or --until-plateau"),
    };
    finetune_split(&args.model, &args.data, &args.out, budget, args.version.as_deref(), &args.knobs.config())?;
    Ok(())
}

/// The backbone steps an adapted model's run took (its manifest's `training.backbone_steps`).
pub fn backbone_steps(model: &Path) -> Result<usize> {
    let text = std::fs::read_to_string(model.join(checkpoint::MANIFEST))
        .with_context(|| format!("reading {}", model.join(checkpoint::MANIFEST).display()))?;
    let m: serde_json::Value = serde_json::from_str(&text)?;
    m["training"]["backbone_steps"]
        .as_u64()
        .map(|s| s as usize)
        .with_context(|| format!("{}: no training.backbone_steps (not an adapted model?)", model.display()))
}

/// Adapts `model` on the images of `dir`; writes `out`. Returns the run's summary (JSON).
pub fn adapt_folder(
    model: &Path,
    dir: &Path,
    out: &Path,
    version: Option<&str>,
    config: &AdaptConfig,
) -> Result<serde_json::Value> {
    refuse_existing(out)?;
    let source = load(model)?;
    let [h, w] = source.manifest.crop;
    let (pixels, names) = load_image_folder(dir, h, w)?;
    let images = Tensor::from_slice(&pixels).reshape([names.len() as i64, 3, h as i64, w as i64]);
    eprintln!("adapting {} on {} images of {}", source.manifest.version, names.len(), dir.display());
    if config.batchnorm_only() {
        eprintln!("α = 1 and no backbone step: the target's BatchNorm statistics alone (AdaBN), no EM round");
    }
    let started = Instant::now();
    let work = rounds_dir(out)?;
    let adapted = adapt::adapt_resumable(&source, &images, config, &work, &mut reporter(config.max_rounds, &work))?;
    let seconds = started.elapsed().as_secs_f64() + restored_seconds(&adapted);
    let summary = json!({
        "kind": "3duda",
        "images": dir.display().to_string(),
        "n_images": names.len(),
        "seconds": seconds,
        "rounds": adapted.rounds,
        "converged": adapted.converged,
        "backbone_steps": adapted.backbone_steps,
        "resumed_after": adapted.resumed_after,
        "fired_ratio_before": adapted.rounds.first().map(|r| r.fired_ratio_before),
        "fired_ratio_after": adapted.rounds.last().map(|r| r.fired_ratio),
    });
    save(&source, adapted, out, version, config, summary.clone())?;
    remove_rounds(&work)?;
    eprintln!("saved {} after {seconds:.0} s", out.display());
    Ok(summary)
}

/// Fine-tunes `model` with the labels of the split directory `split_dir`
/// (`<root>/<domain>/<split>`) for `budget`, leaving out the vertices its occluder masks cover
/// (where it has them); writes `out`.
pub fn finetune_split(
    model: &Path,
    split_dir: &Path,
    out: &Path,
    budget: Budget,
    version: Option<&str>,
    config: &AdaptConfig,
) -> Result<serde_json::Value> {
    refuse_existing(out)?;
    let split = open_split_dir(split_dir)?;
    let source = load(model)?;
    let [h, w] = source.manifest.crop;
    let mut pixels = Vec::new();
    let mut labels = Vec::new();
    for i in 0..split.len() {
        let (p, a, name) = load_annotated(&split, i)?;
        let (ih, iw) = (a.pose.height, a.pose.width);
        if (ih, iw) != (h, w) {
            bail!("{name}: image is {iw}x{ih}, the model's crop is {w}x{h}");
        }
        pixels.extend(p);
        let pose = training_pose(a.pose.pose(), up_symmetry(&split, &a));
        let occluded = a.occluder.map(|m| m.data.iter().map(|&v| v != 0).collect());
        labels.push(Label { pose, occluded });
    }
    let images = Tensor::from_slice(&pixels).reshape([labels.len() as i64, 3, h as i64, w as i64]);
    let masked = labels.iter().filter(|l| l.occluded.is_some()).count();
    eprintln!(
        "oracle: fine-tuning {} with labels on {} images ({masked} with occluder masks), {budget:?}",
        source.manifest.version,
        labels.len()
    );
    let started = Instant::now();
    let work = rounds_dir(out)?;
    let tuned = adapt::finetune_resumable(&source, &images, &labels, budget, config, &work, &mut reporter(0, &work))?;
    let seconds = started.elapsed().as_secs_f64() + restored_seconds(&tuned);
    let summary = json!({
        "kind": "oracle",
        "data": split_dir.display().to_string(),
        "n_images": labels.len(),
        "occluder_masks": masked,
        "budget": match budget {
            Budget::Steps(n) => json!({ "steps": n }),
            Budget::Plateau { min_passes, max_passes, tolerance } =>
                json!({ "plateau": { "min_passes": min_passes, "max_passes": max_passes, "tolerance": tolerance } }),
        },
        "seconds": seconds,
        "backbone_steps": tuned.backbone_steps,
        "resumed_after": tuned.resumed_after,
        "rounds": tuned.rounds,
    });
    save(&source, tuned, out, version, config, summary.clone())?;
    remove_rounds(&work)?;
    eprintln!("saved {} after {seconds:.0} s", out.display());
    Ok(summary)
}

/// `<root>/<domain...>/<split>` → the split (domains may be nested: `corrupt/fog`).
fn open_split_dir(dir: &Path) -> Result<SyncarSplit> {
    let mut root = dir.to_path_buf();
    let mut parts = Vec::new();
    while let Some(parent) = root.parent().map(Path::to_path_buf) {
        parts.push(root.file_name().unwrap_or_default().to_string_lossy().into_owned());
        root = parent;
        if root.join("manifest.json").is_file() {
            break;
        }
    }
    if parts.len() < 2 || !root.join("manifest.json").is_file() {
        bail!("{} is not a split directory of a SynCar-OOD dataset (<root>/<domain>/<split>)", dir.display());
    }
    parts.reverse();
    let split = parts.pop().unwrap_or_default();
    SyncarSplit::open(&root, &parts.join("/"), &split).with_context(|| format!("opening {}", dir.display()))
}

/// The seconds of the rounds a resumed run restored, so that a run's `seconds` counts all its
/// sessions (the report's stage times read them).
fn restored_seconds(run: &Adapted) -> f64 {
    run.rounds.iter().take(run.resumed_after.unwrap_or(0)).map(|r| r.seconds).sum()
}

/// Where a run writes `out` keeps its snapshot after each round: `<out's folder>/.<name>.rounds`,
/// beside the model and hidden, so that the same command rerun after an interruption resumes
/// there (a round can take ten minutes on a CPU) and a listing of models does not see it.
fn rounds_dir(out: &Path) -> Result<PathBuf> {
    let name = out.file_name().and_then(|n| n.to_str()).context("--out has no file name")?;
    Ok(out.with_file_name(format!(".{name}.rounds")))
}

/// Removes a finished run's round snapshots (a BN-only run, which has no round, leaves none).
fn remove_rounds(work: &Path) -> Result<()> {
    match std::fs::remove_dir_all(work) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(e).with_context(|| format!("removing {}", work.display()))
        }
        _ => Ok(()),
    }
}

fn refuse_existing(out: &Path) -> Result<()> {
    if out.exists() {
        bail!("{} already exists (model versions are immutable)", out.display());
    }
    Ok(())
}

fn load(model: &Path) -> Result<Model> {
    let device = RuntimeInfo::detect().device();
    checkpoint::load(model, device).with_context(|| format!("loading {}", model.display()))
}

fn save(
    source: &Model,
    adapted: Adapted,
    out: &Path,
    version: Option<&str>,
    config: &AdaptConfig,
    summary: serde_json::Value,
) -> Result<()> {
    let version = match version {
        Some(v) => v.to_string(),
        None => out.file_name().and_then(|n| n.to_str()).context("--out has no file name")?.to_string(),
    };
    let manifest = Manifest {
        version,
        training: json!({
            "command": std::env::args().collect::<Vec<_>>().join(" "),
            "commit": crate::synth_cmd::git_commit(),
            "source_version": source.manifest.version,
            "source_training": source.manifest.training,
            "config": config,
            "backbone_steps": adapted.backbone_steps,
            "run": summary,
        }),
        // f32: f16 would round the small updates of adaptation away (METHOD.md §7.6).
        dtype: "f32".into(),
        metrics: serde_json::Value::Null,
        files: Default::default(),
        ..source.manifest.clone()
    };
    checkpoint::save(out, &manifest, &adapted.vs, &adapted.neural_mesh)?;
    Ok(())
}

/// A progress bar per phase and one log line per round.
fn reporter(max_rounds: usize, work: &Path) -> impl FnMut(Event) -> ControlFlow<()> {
    let work = work.display().to_string();
    let style = ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {elapsed} eta {eta}")
        .expect("valid template")
        .progress_chars("=> ");
    let mut bar: Option<(ProgressBar, String)> = None;
    move |event| {
        match event {
            Event::Step { round, phase, done, total } => {
                let prefix = if max_rounds > 0 {
                    format!("round {round}/{max_rounds} {phase:?}")
                } else {
                    format!("pass {round} {phase:?}")
                };
                if bar.as_ref().is_none_or(|(_, p)| *p != prefix) {
                    if let Some((b, _)) = bar.take() {
                        b.finish_and_clear();
                    }
                    let b = ProgressBar::new(total as u64).with_style(style.clone()).with_prefix(prefix.clone());
                    bar = Some((b, prefix));
                }
                if let Some((b, _)) = &bar {
                    b.set_position(done as u64);
                }
            }
            Event::Round(r) => {
                if let Some((b, _)) = bar.take() {
                    b.finish_and_clear();
                }
                eprintln!("round {}: {}", r.round, serde_json::to_string(r).unwrap_or_default());
            }
            Event::TargetCheck { fired } => {
                eprintln!("target check: {:.2}% of visible vertices fire to the unchanged model", 100.0 * fired)
            }
            Event::Resumed { rounds } => {
                eprintln!("resuming after round {rounds} from {work} (Adam's moments restart: tch cannot save them)")
            }
        }
        ControlFlow::Continue(())
    }
}
