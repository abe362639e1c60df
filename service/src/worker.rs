//! Inference workers: threads that own their tch model copies, take requests from their category's
//! bounded queue, batch them (up to `max_batch` crops, waiting at most `max_delay` after the
//! first), then run the backbone over them in shared passes and the solver per crop
//! ([`Estimator`]). A crop's answer never depends on what it was batched with
//! ([`Estimator::features`]).

use std::{
    panic::AssertUnwindSafe,
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result};
use crossbeam_channel::{Receiver, RecvTimeoutError};
use tch::Device;
use tokio::sync::oneshot;
use udapose_engine::{
    checkpoint,
    estimator::{Estimator, PoseEstimate},
    input::{self, Crop, CropBox, Rgb8Image},
    signature::{Domain, image_stats, pick},
    solver::SolverConfig,
};

use crate::{
    api::{BoxAnswer, HypothesisAnswer, Pixels, PoseAnswer},
    error::ApiError,
    metrics::Metrics,
    registry::{ActiveVersion, Category},
};

#[derive(Debug, Clone)]
pub struct WorkerConfig {
    /// Worker threads per category, each with its own model copy.
    pub workers: usize,
    /// Most crops in one backbone pass (1: every crop alone).
    pub max_batch: usize,
    /// How long the first request of a batch waits for company.
    pub max_delay: Duration,
    /// Requests that may wait per category before more are refused.
    pub queue_depth: usize,
    pub device: Device,
    /// libtorch intra-op threads of each worker (0: libtorch's own count, one per core).
    pub torch_threads: usize,
}

#[cfg(test)]
impl WorkerConfig {
    /// One worker on the CPU, no batching, a small queue: what the unit tests serve with.
    pub(crate) fn for_tests() -> Self {
        WorkerConfig {
            workers: 1,
            max_batch: 1,
            max_delay: Duration::ZERO,
            queue_depth: 4,
            device: Device::Cpu,
            torch_threads: 0,
        }
    }
}

/// One request's work: a decoded image and its boxes.
pub struct Request {
    pub pixels: Pixels,
    pub boxes: Vec<[f64; 4]>,
    pub enqueued: Instant,
    pub deadline: Instant,
    pub reply: oneshot::Sender<Result<WorkerAnswer, ApiError>>,
    /// The image's share of the in-flight budget, given back when the request is dropped.
    pub in_flight: tokio::sync::OwnedSemaphorePermit,
}

impl Request {
    fn crops(&self) -> usize {
        self.boxes.len().max(1)
    }
}

/// What a worker computed for one request.
#[derive(Debug)]
pub struct WorkerAnswer {
    pub estimates: Vec<PoseAnswer>,
    pub version: String,
    pub queue_ms: f64,
    pub crop_ms: f64,
    pub backbone_ms: f64,
    pub solver_ms: f64,
    pub batch_size: usize,
}

/// A model as one worker holds it: the active version's own, and one per expert.
struct Loaded {
    active: Arc<ActiveVersion>,
    estimator: Estimator,
    experts: Vec<(Domain, Estimator)>,
}

impl Loaded {
    fn load(active: Arc<ActiveVersion>, device: Device) -> Result<Self> {
        let estimator = |dir: &std::path::Path| -> Result<Estimator> {
            let model = checkpoint::load(dir, device).with_context(|| format!("loading {}", dir.display()))?;
            Ok(Estimator::new(model, SolverConfig::default())?)
        };
        let experts =
            active.experts.iter().map(|e| Ok((e.domain.clone(), estimator(&e.dir)?))).collect::<Result<_>>()?;
        Ok(Loaded { estimator: estimator(&active.dir)?, experts, active })
    }

    fn resident_bytes(&self) -> usize {
        self.estimator.resident_bytes() + self.experts.iter().map(|(_, e)| e.resident_bytes()).sum::<usize>()
    }

    /// Which estimator answers each crop: 0 the version's own, `i + 1` its expert `i`
    /// (the one whose domain takes the crop with the highest likelihood).
    fn route(&self, crops: &[&Crop]) -> Vec<usize> {
        let domains: Vec<&Domain> = self.experts.iter().map(|(d, _)| d).collect();
        crops
            .iter()
            .map(|c| match image_stats(&c.pixels, c.size) {
                Ok(stats) => pick(&domains, &stats).map_or(0, |i| i + 1),
                Err(_) => 0,
            })
            .collect()
    }

    fn member(&self, index: usize) -> &Estimator {
        if index == 0 { &self.estimator } else { &self.experts[index - 1].1 }
    }
}

pub fn spawn(
    category: Arc<Category>,
    rx: Receiver<Request>,
    config: WorkerConfig,
    metrics: Arc<Metrics>,
    index: usize,
) -> Result<()> {
    std::thread::Builder::new()
        .name(format!("infer-{}-{index}", category.name))
        .spawn(move || run(&category, &rx, &config, &metrics))
        .context("spawning an inference worker")?;
    Ok(())
}

/// How often an idle worker looks for a new active version, so that a swap is loaded before
/// the next request rather than by it.
const IDLE_CHECK: Duration = Duration::from_millis(200);

fn run(category: &Category, rx: &Receiver<Request>, config: &WorkerConfig, metrics: &Metrics) {
    // 16 clients on two workers of one thread each, batching on: 39 req/s with the count set
    // in `main` only, 67 with `OMP_NUM_THREADS=1`, which pinning gives each worker without the
    // environment (`udapose-bench service --server-flags='--workers 2 --torch-threads 1'`,
    // 2-core Xeon; `crate::threads`).
    if config.torch_threads > 0 {
        crate::threads::pin_torch_threads(config.torch_threads);
    }
    let pool = crate::threads::solver_pool(config.workers, &format!("infer-{}", category.name));
    let Some(mut loaded) = load_active(category, config.device, None) else { return };
    category.worker_loaded();
    // This worker's share of the category's memory: its own copy of the model.
    let memory = metrics.model_bytes.with_label_values(&[category.name.as_str()]);
    memory.add(loaded.resident_bytes() as i64);
    let depth = metrics.queue_depth.with_label_values(&[category.name.as_str()]);
    let batch_sizes = metrics.batch_size.with_label_values(&[category.name.as_str()]);
    // A generation that failed to load is not retried until another one is activated.
    let mut failed = None;
    loop {
        let first = match rx.recv_timeout(IDLE_CHECK) {
            Ok(request) => Some(request),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => {
                memory.sub(loaded.resident_bytes() as i64);
                return;
            }
        };
        // Swap between batches: a new generation is loaded here, on this thread, while the
        // previous copy keeps serving until it is ready.
        if let Some(active) = category.active()
            && active.generation != loaded.active.generation
            && failed != Some(active.generation)
        {
            match load_active(category, config.device, Some(&loaded)) {
                Some(next) => {
                    memory.add(next.resident_bytes() as i64 - loaded.resident_bytes() as i64);
                    loaded = next;
                }
                None => failed = Some(active.generation),
            }
        }
        let Some(first) = first else { continue };
        let batch = collect(rx, first, config);
        depth.set(rx.len() as i64);
        let crops: usize = batch.iter().map(Request::crops).sum();
        batch_sizes.observe(crops as f64);
        process(&loaded, batch, config, pool.as_ref());
    }
}

/// Loads the category's active version; on failure keeps `current` serving (or marks the
/// category failed when there is none).
fn load_active(category: &Category, device: Device, current: Option<&Loaded>) -> Option<Loaded> {
    let active = category.active()?;
    let started = Instant::now();
    match Loaded::load(active.clone(), device) {
        Ok(loaded) => {
            tracing::info!(category = %category.name, version = %active.version, generation = active.generation,
                experts = active.experts.len(), ms = started.elapsed().as_millis() as u64, "model loaded");
            category.set_error(None);
            Some(loaded)
        }
        Err(e) => {
            tracing::error!(category = %category.name, version = %active.version, "cannot load the model: {e:#}");
            if current.is_none() {
                category.set_error(Some(format!("{e:#}")));
            }
            None
        }
    }
}

/// The first request plus whatever else arrives within `max_delay`, up to `max_batch` crops.
/// The wait is only for a request that found others queued behind it (concurrent clients): a
/// lone request goes at once. Measured with one client (`udapose-bench service --concurrency
/// 1`): waiting 5 ms for nobody cost 17 ms per request (28.6 vs 44.6 req/s, p50 38 vs 21 ms),
/// while under load the batch's companions are already queued when the worker picks it up.
///
/// A worker takes at most its share of what is queued (`queued / workers`, rounded up) so that
/// the category's other workers are not left idle while one works through everything: with two
/// workers and 4 clients, one worker took all four requests in one pass (53 req/s against 70
/// with `--max-batch 1`).
fn collect(rx: &Receiver<Request>, first: Request, config: &WorkerConfig) -> Vec<Request> {
    let mut crops = first.crops();
    let mut batch = vec![first];
    let queued = rx.len();
    let wait = if queued == 0 { Duration::ZERO } else { config.max_delay };
    let limit = match config.workers {
        0 | 1 => config.max_batch,
        n => config.max_batch.min((queued + 1).div_ceil(n)),
    };
    let until = Instant::now() + wait;
    while crops < limit {
        match rx.recv_deadline(until) {
            Ok(request) => {
                crops += request.crops();
                batch.push(request);
            }
            Err(_) => break,
        }
    }
    batch
}

/// A request whose crops are cut, waiting for the backbone.
struct Pending {
    request: Request,
    crops: Vec<Crop>,
    queue_ms: f64,
    crop_ms: f64,
}

fn process(loaded: &Loaded, batch: Vec<Request>, config: &WorkerConfig, pool: Option<&rayon::ThreadPool>) {
    let mut pending = Vec::with_capacity(batch.len());
    for request in batch {
        let started = Instant::now();
        let queue_ms = ms(started - request.enqueued);
        if request.reply.is_closed() {
            continue; // the caller gave up (cancelled, timed out): nothing to compute
        }
        if started > request.deadline {
            let _ = request.reply.send(Err(ApiError::DeadlineExceeded(format!(
                "the deadline passed after {queue_ms:.0} ms in the queue; not computed"
            ))));
            continue;
        }
        match cut(loaded, &request) {
            Ok(crops) => pending.push(Pending { request, crops, queue_ms, crop_ms: ms(started.elapsed()) }),
            Err(e) => {
                let _ = request.reply.send(Err(e));
            }
        }
    }
    if pending.is_empty() {
        return;
    }
    let crops: Vec<&Crop> = pending.iter().flat_map(|p| &p.crops).collect();
    let outcome = std::panic::catch_unwind(AssertUnwindSafe(|| infer(loaded, &crops, config, pool)));
    let (mut results, backbone_ms) = match outcome {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => (crops.iter().map(|_| Err(e.clone())).collect(), 0.0),
        Err(_) => (crops.iter().map(|_| Err(ApiError::Internal("inference panicked".into()))).collect(), 0.0),
    };
    let batch_size = crops.len();
    let mut results = results.drain(..);
    for p in pending {
        let answers: Vec<_> = results.by_ref().take(p.crops.len()).collect();
        let solver_ms = answers.iter().map(|a| a.as_ref().map_or(0.0, |(_, t)| *t)).sum();
        let estimates: Result<Vec<PoseAnswer>, ApiError> = answers.into_iter().map(|a| a.map(|(e, _)| e)).collect();
        let reply = estimates.map(|estimates| WorkerAnswer {
            estimates,
            version: loaded.active.version.clone(),
            queue_ms: p.queue_ms,
            crop_ms: p.crop_ms,
            backbone_ms,
            solver_ms,
            batch_size,
        });
        let _ = p.request.reply.send(reply);
    }
}

/// The request's crops at the model's size; boxes and crop boxes in the encoded image's pixels
/// (the decode may be smaller, [`Pixels::encoded`]).
fn cut(loaded: &Loaded, request: &Request) -> Result<Vec<Crop>, ApiError> {
    let Pixels { rgb8, width, height, encoded: [ew, eh] } = &request.pixels;
    let image = Rgb8Image::new(rgb8, *width, *height)?.decoded_from(*ew, *eh)?;
    let size = loaded.active.manifest.crop;
    if request.boxes.is_empty() {
        return Ok(vec![input::crop(&image, None, size)?]);
    }
    request
        .boxes
        .iter()
        .map(|&[x0, y0, x1, y1]| Ok(input::crop(&image, Some(CropBox { x0, y0, x1, y1 }), size)?))
        .collect()
}

type CropResult = Result<(PoseAnswer, f64), ApiError>;

/// Each crop on the estimator it is routed to ([`Loaded::route`]); answers in the crops' order,
/// and the backbone's time over all members.
fn infer(
    loaded: &Loaded,
    crops: &[&Crop],
    config: &WorkerConfig,
    pool: Option<&rayon::ThreadPool>,
) -> Result<(Vec<CropResult>, f64), ApiError> {
    if loaded.experts.is_empty() {
        return infer_on(loaded, &loaded.estimator, crops, config, pool);
    }
    let routes = loaded.route(crops);
    let mut results: Vec<Option<CropResult>> = crops.iter().map(|_| None).collect();
    let mut backbone_ms = 0.0;
    for member in 0..=loaded.experts.len() {
        let picked: Vec<usize> = (0..crops.len()).filter(|&i| routes[i] == member).collect();
        if picked.is_empty() {
            continue;
        }
        let group: Vec<&Crop> = picked.iter().map(|&i| crops[i]).collect();
        let (answers, ms) = infer_on(loaded, loaded.member(member), &group, config, pool)?;
        backbone_ms += ms;
        for (i, a) in picked.into_iter().zip(answers) {
            results[i] = Some(a);
        }
    }
    Ok((results.into_iter().map(|r| r.expect("every crop is routed once")).collect(), backbone_ms))
}

/// The backbone over the crops on this thread, in passes of at most `max_batch`, then the crops'
/// solves in parallel on `pool` (the global pool where `None`). Returns each crop's answer and
/// solver time, and the backbone's time.
fn infer_on(
    loaded: &Loaded,
    estimator: &Estimator,
    crops: &[&Crop],
    config: &WorkerConfig,
    pool: Option<&rayon::ThreadPool>,
) -> Result<(Vec<CropResult>, f64), ApiError> {
    let started = Instant::now();
    let features = estimator.features(crops, config.max_batch)?;
    let backbone_ms = ms(started.elapsed());
    let results = estimator
        .estimate_all_in(pool, crops, &features)
        .into_iter()
        .map(|r| Ok(r.map(|(estimate, ms)| (answer(loaded, estimate), ms))?))
        .collect();
    Ok((results, backbone_ms))
}

fn answer(loaded: &Loaded, e: PoseEstimate) -> PoseAnswer {
    let p = e.estimate.pose;
    let [azimuth_deg, elevation_deg, theta_deg] = e.degrees;
    let b = e.crop_box;
    PoseAnswer {
        azimuth: p.azimuth,
        elevation: p.elevation,
        theta: p.theta,
        azimuth_deg,
        elevation_deg,
        theta_deg,
        distance: p.distance,
        rotation: e.rotation.to_vec(),
        score: e.estimate.score,
        hypotheses: e
            .estimate
            .hypotheses
            .iter()
            .map(|h| HypothesisAnswer {
                azimuth: h.pose.azimuth,
                elevation: h.pose.elevation,
                theta: h.pose.theta,
                distance: h.pose.distance,
                score: 1.0 - h.loss,
            })
            .collect(),
        runner_up_gap: e.estimate.runner_up_gap(std::f64::consts::FRAC_PI_6),
        crop_box: BoxAnswer { x0: b.x0, y0: b.y0, x1: b.x1, y1: b.y1 },
        cuboid: e.cuboid.iter().flatten().copied().collect(),
        model_version: loaded.active.version.clone(),
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}
