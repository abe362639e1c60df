//! `udapose-lab train`: the source model (METHOD.md §5) from a SynCar-OOD dataset, resumable
//! from its last checkpoint (each epoch's end, and every `--checkpoint-minutes` within one), with
//! a validation curve on `source/val`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::json;
use tch::nn::OptimizerConfig;
use tch::{Device, Tensor, nn};
use udapose_engine::backbone::{Arch, Backbone};
use udapose_engine::checkpoint::{self, Manifest};
use udapose_engine::estimator::{self, PoseSolver, clutter_mean};
use udapose_engine::mesh::TARGET_VERTICES;
use udapose_engine::runtime::RuntimeInfo;
use udapose_engine::solver::SolverConfig;
use udapose_engine::train::{self, LearningRates, Progress, Schedule, SourceTraining, TrainConfig, VertexStatistics};
use udapose_engine::{Camera, Cuboid, PoseMetrics, pose_error_up_to};
use udapose_lab::augment::Photometric;
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::{Batch, Loader};

#[derive(clap::Args)]
pub struct Args {
    /// SynCar-OOD root (trains on source/train, validates on source/val).
    #[arg(long)]
    data: PathBuf,
    /// The model's category (default: the dataset's, `car` for datasets that name none).
    #[arg(long)]
    category: Option<String>,
    /// The new model directory (must not exist).
    #[arg(long)]
    out: PathBuf,
    /// Backbone trunk: resnet18, resnet34, resnet50, efficientnet-lite0, -lite1 or -lite2.
    #[arg(long, default_value = "resnet18")]
    arch: Arch,
    #[arg(long, default_value_t = 30)]
    epochs: usize,
    #[arg(long, default_value_t = 16)]
    batch: usize,
    /// Adam learning rate of the decoder (weight decay 1e-4), the peak of the schedule.
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    /// Peak learning rate of the trunk (default: lr / 10 with --init-backbone, else lr): a
    /// pretrained trunk moves slower than the decoder trained from scratch on top of it.
    #[arg(long)]
    trunk_lr: Option<f64>,
    /// Learning-rate schedule: `cosine` (linear warm-up, then cosine decay to 1% of the peak
    /// at the last step) or `constant` (the recipe of the first shipped model).
    #[arg(long, default_value = "cosine")]
    schedule: Schedule,
    /// Warm-up steps of the cosine schedule.
    #[arg(long, default_value_t = 200)]
    warmup_steps: usize,
    /// Run the stem and the first N stages of an EfficientNet-Lite trunk as fixed functions
    /// (default: 2 with --init-backbone, else 0): ImageNet's low-level filters are kept and their
    /// backward pass, a third of a CPU step, is skipped.
    #[arg(long)]
    freeze_stages: Option<usize>,
    /// No photometric augmentation (colour jitter, grayscale, mild blur; see lab/src/augment.rs).
    #[arg(long)]
    no_augment: bool,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Pretrained trunk weights: a torchvision ResNet exported by lab/scripts/export_torchvision.py
    /// or EfficientNet-Lite converted by lab/scripts/efficientnet_lite.py (`make lite-weights`).
    #[arg(long)]
    init_backbone: Option<PathBuf>,
    /// Where checkpoints go (default: `<out>.work`); a run resumes from the latest.
    #[arg(long)]
    work: Option<PathBuf>,
    /// Within an epoch, a checkpoint after the first batch that ends this many minutes after the
    /// last one (every epoch's end has one too); 0: at epochs' ends only.
    #[arg(long, default_value_t = 10.0)]
    checkpoint_minutes: f64,
    /// Storage of the saved model's tensors: f16 (half the size) or f32.
    #[arg(long, default_value = "f16")]
    dtype: String,
    /// Validation images per epoch (0: the whole val split).
    #[arg(long, default_value_t = 0)]
    val_images: usize,
}

pub fn run(args: &Args) -> Result<()> {
    if args.out.exists() {
        bail!("{} already exists (model versions are immutable)", args.out.display());
    }
    let dataset = Dataset::open(&args.data)?;
    let camera = Camera::for_crop(dataset.crop[0], dataset.crop[1])?;
    let device = RuntimeInfo::detect().device();
    let mesh = dataset.cuboid.mesh(TARGET_VERTICES);

    let mut vs = nn::VarStore::new(device);
    let (backbone, freeze_stages, frozen_blocks) = build_backbone(args, &mut vs)?;
    let mut training = SourceTraining::new(TrainConfig::default(), mesh, camera, 128, device);
    let work = args.work.clone().unwrap_or_else(|| PathBuf::from(format!("{}.work", args.out.display())));
    std::fs::create_dir_all(&work)?;
    let mut progress = train::state::resume(&work, &mut vs, &mut training)?;
    if progress.epoch > 0 || progress.step > 0 {
        eprintln!("resuming from {} (epoch {}, step {})", work.display(), progress.epoch, progress.step);
    }

    let train = SyncarSplit::open(&args.data, "source", "train")?;
    let val = SyncarSplit::open(&args.data, "source", "val")?;
    let mut loader = Loader::new(train.clone(), args.batch, 2, args.seed)?;
    for _ in 0..progress.epoch {
        drop(loader.epoch()); // replay the shuffles of the epochs already done
    }
    // A run resumed within an epoch draws its augmentations afresh, like Adam's moments.
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed ^ progress.epoch as u64 ^ ((progress.step as u64) << 32));
    // tch cannot save an optimiser's state: a resumed run starts Adam afresh.
    let mut opt = nn::Adam { wd: 1e-4, ..Default::default() }.build(&vs, args.lr)?;
    let recipe = Recipe {
        trunk_lr: trunk_lr(args),
        augment: (!args.no_augment).then(Photometric::default),
        freeze_stages,
        frozen_blocks,
    };
    let steps_per_epoch = loader.len().div_ceil(args.batch);
    let lr = LearningRates {
        schedule: args.schedule,
        decoder: args.lr,
        trunk: recipe.trunk_lr,
        warmup_steps: args.warmup_steps,
        total_steps: steps_per_epoch * args.epochs,
    };
    let mut run =
        Run { backbone: &backbone, training: &mut training, vs: &vs, opt: &mut opt, rng: &mut rng, work: &work };
    while progress.epoch < args.epochs {
        let epoch = progress.epoch;
        let loss = run.epoch(args, &mut loader, &recipe, &lr, &mut progress)?;
        let started = Instant::now();
        let metrics = validate(&backbone, run.training, &val, &camera, args.val_images)?;
        progress.seconds += started.elapsed().as_secs_f64();
        let point = json!({"epoch": epoch + 1, "loss": loss, "val": metrics, "seconds": progress.seconds});
        eprintln!("epoch {}: {point}", epoch + 1);
        progress.curve.push(point);
        progress.epoch = epoch + 1;
        train::state::save(&work, &vs, run.training, &progress)?;
    }
    let (tau, r_bar) = statistics(&backbone, &training, &train, args.batch)?;
    let neural_mesh = training.neural_mesh(tau, r_bar);
    let manifest = manifest(args, dataset, neural_mesh.mesh.vertices().len(), &recipe, &progress, device);
    checkpoint::save(&args.out, &manifest, &vs, &neural_mesh)?;
    eprintln!("saved {} after {:.0} s of training", args.out.display(), progress.seconds);
    Ok(())
}

/// What one epoch's steps change: the model, its optimiser and the augmentations' draws.
struct Run<'a> {
    backbone: &'a Backbone,
    training: &'a mut SourceTraining,
    vs: &'a nn::VarStore,
    opt: &'a mut nn::Optimizer,
    rng: &'a mut ChaCha8Rng,
    work: &'a std::path::Path,
}

impl Run<'_> {
    /// The batches of epoch `progress.epoch` from `progress.step` on, checkpointed every
    /// `--checkpoint-minutes`; the epoch's mean loss. `progress` ends at the epoch's last batch
    /// (step 0 again, the time spent added), ready for the caller's epoch-end checkpoint.
    fn epoch(
        &mut self,
        args: &Args,
        loader: &mut Loader,
        recipe: &Recipe,
        lr: &LearningRates,
        progress: &mut Progress,
    ) -> Result<f64> {
        let (epoch, first) = (progress.epoch, progress.step);
        let steps_per_epoch = loader.len().div_ceil(args.batch);
        let bar = bar(loader.len() as u64, &format!("epoch {}/{}", epoch + 1, args.epochs));
        bar.set_position((first * args.batch).min(loader.len()) as u64);
        let mut since = Instant::now();
        for (step, batch) in (first..).zip(loader.epoch_from(first)) {
            let batch = batch?;
            lr.apply(self.opt, epoch * steps_per_epoch + step);
            let mut images = images_tensor(&batch, self.training.vertex_features.device());
            if let Some(augment) = &recipe.augment {
                images = augment.apply(&images, self.rng);
            }
            let stats = self.training.backward_step(self.backbone, self.opt, &images, &batch.poses, self.rng)?;
            progress.loss_sum += stats.loss;
            progress.step = step + 1;
            bar.set_message(format!("loss {:.3}", progress.loss_sum / progress.step as f64));
            bar.inc(batch.len() as u64);
            let due = args.checkpoint_minutes > 0.0 && since.elapsed().as_secs_f64() >= args.checkpoint_minutes * 60.0;
            if due && progress.step < steps_per_epoch {
                progress.seconds += std::mem::replace(&mut since, Instant::now()).elapsed().as_secs_f64();
                train::state::save(self.work, self.vs, self.training, progress)?;
            }
        }
        bar.finish_and_clear();
        progress.seconds += since.elapsed().as_secs_f64();
        let loss = progress.loss_sum / progress.step.max(1) as f64;
        (progress.step, progress.loss_sum) = (0, 0.0);
        Ok(loss)
    }
}

/// The dataset's manifest and what training takes from it.
struct Dataset {
    manifest: serde_json::Value,
    cuboid: Cuboid,
    /// `[height, width]`.
    crop: [usize; 2],
}

impl Dataset {
    fn open(root: &std::path::Path) -> Result<Dataset> {
        let text =
            std::fs::read_to_string(root.join("manifest.json")).context("reading the dataset's manifest.json")?;
        let manifest: serde_json::Value = serde_json::from_str(&text)?;
        let cuboid: Cuboid = serde_json::from_value(manifest["cuboid"].clone()).context("dataset manifest: cuboid")?;
        let side = |k: &str| manifest["crop"][k].as_u64().unwrap_or(0) as usize;
        let crop = [side("height"), side("width")];
        Ok(Dataset { manifest, cuboid, crop })
    }
}

/// The recipe's derived settings, recorded in the model's manifest.
struct Recipe {
    trunk_lr: f64,
    augment: Option<Photometric>,
    freeze_stages: usize,
    frozen_blocks: usize,
}

/// The trained model's manifest: what it is, and how it was trained (reproducibly).
fn manifest(
    args: &Args,
    dataset: Dataset,
    vertices: usize,
    recipe: &Recipe,
    progress: &Progress,
    device: tch::Device,
) -> Manifest {
    let data = &dataset.manifest;
    Manifest {
        format_version: checkpoint::FORMAT_VERSION,
        category: args.category.clone().unwrap_or_else(|| data["category"].as_str().unwrap_or("car").to_string()),
        version: format!("source-{}", crate::synth_cmd::git_commit()),
        vertices,
        cuboid: dataset.cuboid,
        backbone: args.arch,
        input_normalization: Some(args.arch.input_normalization().into()),
        feature_dim: 128,
        crop: dataset.crop,
        clutter: 1,
        dtype: args.dtype.clone(),
        training: json!({
            "command": std::env::args().collect::<Vec<_>>().join(" "),
            "data": {"profile": data["profile"], "seed": data["seed"], "commit": data["commit"]},
            "commit": crate::synth_cmd::git_commit(),
            "epochs": args.epochs, "batch": args.batch, "lr": args.lr, "seed": args.seed,
            "trunk_lr": recipe.trunk_lr, "schedule": args.schedule, "warmup_steps": args.warmup_steps,
            "augment": recipe.augment, "freeze_stages": recipe.freeze_stages, "frozen_blocks": recipe.frozen_blocks,
            "init_backbone": args.init_backbone.as_ref().map(|p| p.display().to_string()),
            "train_seconds": progress.seconds,
            "validation_curve": progress.curve,
            "device": format!("{device:?}"),
        }),
        metrics: serde_json::Value::Null,
        files: Default::default(),
        experts: Vec::new(),
        // Measured on the trained model: `udapose-lab target-check --set`.
        min_target_fired: None,
    }
}

/// The backbone, its trunk initialised from `--init-backbone`, its first stages frozen; with
/// the number of stages and of blocks frozen.
fn build_backbone(args: &Args, vs: &mut nn::VarStore) -> Result<(Backbone, usize, usize)> {
    let mut backbone = Backbone::new(vs.root(), args.arch, 128);
    if let Some(init) = &args.init_backbone {
        let loaded = backbone.load_trunk(vs, init)?;
        eprintln!("initialised the trunk from {} ({} tensors)", init.display(), loaded.loaded);
    }
    let stages = freeze_stages(args);
    let frozen = backbone.freeze_stages(stages)?;
    Ok((backbone, stages, frozen))
}

fn freeze_stages(args: &Args) -> usize {
    let pretrained_lite = args.init_backbone.is_some() && args.arch.lite_variant().is_some();
    args.freeze_stages.unwrap_or(if pretrained_lite { 2 } else { 0 })
}

fn trunk_lr(args: &Args) -> f64 {
    args.trunk_lr.unwrap_or(if args.init_backbone.is_some() { args.lr / 10.0 } else { args.lr })
}

fn bar(len: u64, prefix: &str) -> ProgressBar {
    let style = ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {elapsed} eta {eta} {msg}")
        .expect("valid template")
        .progress_chars("=> ");
    ProgressBar::new(len).with_style(style).with_prefix(prefix.to_string())
}

fn images_tensor(batch: &Batch, device: Device) -> Tensor {
    Tensor::from_slice(&batch.images)
        .reshape([batch.len() as i64, 3, batch.height as i64, batch.width as i64])
        .to_device(device)
}

/// Acc@π/6, Acc@π/18 and MedErr on (the first `limit` images of) the validation split.
fn validate(
    backbone: &Backbone,
    training: &SourceTraining,
    val: &SyncarSplit,
    camera: &Camera,
    limit: usize,
) -> Result<PoseMetrics> {
    let clutter = clutter_mean(&training.clutter);
    let solver =
        PoseSolver::new(&training.mesh, &training.vertex_features, &clutter, *camera, SolverConfig::default())?;
    let n = if limit == 0 { val.len() } else { limit.min(val.len()) };
    let mut errors = Vec::with_capacity(n);
    for i in 0..n {
        let s = udapose_lab::loader::load_sample(val, i)?;
        let (pose, h, w) = (s.pose, s.height, s.width);
        let image = Tensor::from_slice(&s.pixels).reshape([1, 3, h as i64, w as i64]);
        let features = estimator::features(backbone, &image)?;
        let estimate = solver.solve(&features[0]);
        let gt = [pose.azimuth, pose.elevation, pose.theta];
        let angles = estimate.ok().map(|e| [e.pose.azimuth, e.pose.elevation, e.pose.theta]);
        errors.push(pose_error_up_to(angles, gt, s.symmetry));
    }
    Ok(PoseMetrics::from_errors(&errors)?)
}

/// τ_r and R̄_r over the training set at ground-truth poses, in eval mode.
fn statistics(
    backbone: &Backbone,
    training: &SourceTraining,
    train: &SyncarSplit,
    batch: usize,
) -> Result<(Tensor, Tensor)> {
    let mut stats = VertexStatistics::new(training.mesh.vertices().len(), 128, training.vertex_features.device());
    let mut loader = Loader::new(train.clone(), batch, 2, 0)?;
    let bar = bar(loader.len() as u64, "vertex statistics");
    for b in loader.epoch() {
        let b = b?;
        let images = images_tensor(&b, training.vertex_features.device());
        stats.add_images(training, backbone, &images, &b.poses)?;
        bar.inc(b.len() as u64);
    }
    bar.finish_and_clear();
    Ok(stats.finish(0.1))
}
