//! The one internal API both transports call: validate, decode off the runtime, admit to the
//! category's queue, await the worker, assemble the answer, record metrics.

use std::{
    sync::Arc,
    time::{Duration, Instant},
};

use tokio::sync::{OwnedSemaphorePermit, Semaphore, oneshot};
use tracing::Instrument;
use udapose_api::{ActivationEntry, VersionView, Versions};
use udapose_engine::input::{self, CropBox};

use crate::{
    api::{EstimateAnswer, EstimateInput, ImageInput, Timings},
    auth::Tokens,
    decode::{self, DecodeLimits},
    error::ApiError,
    jobs::{JobEvent, JobView, Jobs, Overrides, TargetAck},
    metrics::Metrics,
    registry::{Category, Registry},
    store::{Activation, valid_category},
    worker::Request,
};

/// Most boxes in one request.
pub const MAX_BOXES: usize = 16;

/// How long `CancelJob` waits for a running job to stop before it answers.
pub const CANCEL_WAIT: std::time::Duration = std::time::Duration::from_secs(30);

#[derive(Debug, Clone)]
pub struct Limits {
    pub max_request_bytes: usize,
    pub decode: DecodeLimits,
    /// Deadline of a request that brings none.
    pub default_timeout: Duration,
}

pub struct Service {
    pub registry: Arc<Registry>,
    pub limits: Limits,
    pub metrics: Arc<Metrics>,
    pub tokens: Tokens,
    /// Target buffers and adaptation jobs.
    pub jobs: Arc<Jobs>,
    /// Decodes running at once (each may hold a large image in memory).
    decode_slots: Semaphore,
    /// The estimates' image bytes in flight, in KiB permits (`DecodeLimits::in_flight`): taken
    /// before an image decodes, given back when its job is dropped.
    in_flight: Arc<Semaphore>,
}

impl Service {
    pub fn new(
        registry: Arc<Registry>,
        limits: Limits,
        metrics: Arc<Metrics>,
        tokens: Tokens,
        jobs: Arc<Jobs>,
    ) -> Self {
        let slots = std::thread::available_parallelism().map_or(2, |n| n.get()) * 2;
        let in_flight = Arc::new(Semaphore::new(kib(limits.decode.in_flight) as usize));
        Service { registry, limits, metrics, tokens, jobs, decode_slots: Semaphore::new(slots), in_flight }
    }

    /// The category, if the name is valid and configured.
    pub fn category(&self, name: &str) -> Result<&Arc<Category>, ApiError> {
        if !valid_category(name) {
            return Err(ApiError::InvalidArgument(format!(
                "invalid category name {:?}: 1-64 characters of a-z, 0-9, '_' and '-'",
                truncate(name, 80)
            )));
        }
        self.registry.get(name).ok_or_else(|| {
            let known: Vec<&str> = self.registry.categories().map(|c| c.name.as_str()).collect();
            ApiError::NotFound(format!("unknown category {name:?}; this server has: {}", known.join(", ")))
        })
    }

    /// Estimates, recording metrics by `transport` ("http", "grpc").
    pub async fn estimate(&self, input: EstimateInput, transport: &str) -> Result<EstimateAnswer, ApiError> {
        let arrived = Instant::now();
        let category = input.category.clone();
        // One span per request; the worker's timings and the serving version are recorded on it.
        let span = tracing::info_span!("estimate", transport, category = %category, frame_id = %input.frame_id,
            version = tracing::field::Empty, total_ms = tracing::field::Empty);
        let result = self.estimate_inner(input, arrived).instrument(span.clone()).await;
        let _entered = span.enter(); // no await below: the events that follow belong to the span
        let code = result.as_ref().map_or_else(ApiError::code_name, |_| "OK");
        self.metrics.requests.with_label_values(&[transport, code]).inc();
        match &result {
            Ok(a) => {
                span.record("version", a.model_version.as_str());
                span.record("total_ms", a.timings.total_ms);
                self.metrics
                    .latency
                    .with_label_values(&[category.as_str(), a.model_version.as_str()])
                    .observe(a.timings.total_ms / 1e3);
                let t = &a.timings;
                for (stage, v) in [
                    ("decode", t.decode_ms),
                    ("queue", t.queue_ms),
                    ("crop", t.crop_ms),
                    ("backbone", t.backbone_ms),
                    ("solver", t.solver_ms),
                ] {
                    self.metrics.stage.with_label_values(&[stage]).observe(v / 1e3);
                }
                tracing::info!(
                    decode_ms = t.decode_ms,
                    queue_ms = t.queue_ms,
                    crop_ms = t.crop_ms,
                    backbone_ms = t.backbone_ms,
                    solver_ms = t.solver_ms,
                    batch = t.batch_size,
                    "answered"
                );
            }
            Err(e) => {
                self.metrics.errors.with_label_values(&[e.code_name()]).inc();
                tracing::info!(code = e.code_name(), "refused: {e}");
            }
        }
        result
    }

    async fn estimate_inner(&self, input: EstimateInput, arrived: Instant) -> Result<EstimateAnswer, ApiError> {
        let category = self.category(&input.category)?.clone();
        if input.boxes.len() > MAX_BOXES {
            return Err(ApiError::InvalidArgument(format!(
                "{} boxes; at most {MAX_BOXES} per request",
                input.boxes.len()
            )));
        }
        // Refuse before decoding when the queue is already full: overload costs no CPU.
        if category.saturated() {
            return Err(ApiError::unavailable(format!("overloaded: the {} queue is full; retry later", category.name)));
        }
        let timeout = input.timeout.filter(|t| !t.is_zero()).unwrap_or(self.limits.default_timeout);
        let decode_started = Instant::now();
        let deadline = arrived + timeout;
        // How much smaller the image may be kept for the crops this model will cut from it.
        let crop = category.active().map(|a| a.manifest.crop);
        let boxes: Vec<CropBox> = input.boxes.iter().map(|&[x0, y0, x1, y1]| CropBox { x0, y0, x1, y1 }).collect();
        let reduction =
            move |w: u32, h: u32| crop.map_or(1, |crop| input::max_reduction(w as usize, h as usize, &boxes, crop));
        let (pixels, in_flight) = self.decode(input.image, deadline, reduction).await?;
        let decode_ms = decode_started.elapsed().as_secs_f64() * 1e3;
        let (reply, answer) = oneshot::channel();
        let request = Request { pixels, boxes: input.boxes, enqueued: Instant::now(), deadline, reply, in_flight };
        category.submit(request)?;
        let queued = category.queued() as i64;
        self.metrics.queue_depth.with_label_values(&[category.name.as_str()]).set(queued);
        let answer =
            answer.await.map_err(|_| ApiError::Internal("the inference worker dropped the request".into()))??;
        let timings = Timings {
            decode_ms,
            queue_ms: answer.queue_ms,
            crop_ms: answer.crop_ms,
            backbone_ms: answer.backbone_ms,
            solver_ms: answer.solver_ms,
            total_ms: arrived.elapsed().as_secs_f64() * 1e3,
            batch_size: answer.batch_size as u32,
        };
        Ok(EstimateAnswer {
            estimates: answer.estimates,
            model_version: answer.version,
            frame_id: input.frame_id,
            timings,
        })
    }

    /// Decodes on a blocking thread, never on the async runtime, once the image's bytes fit in
    /// the in-flight budget (waiting for it until `deadline`); `reduction(width, height)` says
    /// how much smaller an image of that size may be kept ([`decode::Header::decode_for`]).
    async fn decode(
        &self,
        image: ImageInput,
        deadline: Instant,
        reduction: impl FnOnce(u32, u32) -> u32 + Send + 'static,
    ) -> Result<(crate::api::Pixels, OwnedSemaphorePermit), ApiError> {
        let limits = self.limits.decode;
        // A decode slot only once the budget is had: an image waiting for room holds none.
        Ok(match image {
            ImageInput::Encoded(bytes) => {
                let head = bytes.clone();
                let header = blocking(move || decode::Header::read(&head, limits)).await?;
                let permit = self.reserve(header.cost(), deadline).await?;
                let _slot = self.decode_slot().await?;
                let r = reduction(header.width, header.height);
                (blocking(move || header.decode_for(&bytes, limits, r)).await?, permit)
            }
            ImageInput::Raw { width, height, rgb8 } => {
                let permit = self.reserve(decode::raw_cost(width, height), deadline).await?;
                let _slot = self.decode_slot().await?;
                let r = reduction(width, height);
                (blocking(move || decode::reduced(decode::raw(width, height, &rgb8, limits)?, r)).await?, permit)
            }
        })
    }

    async fn decode_slot(&self) -> Result<tokio::sync::SemaphorePermit<'_>, ApiError> {
        self.decode_slots.acquire().await.map_err(|_| ApiError::Internal("shutting down".into()))
    }

    /// `bytes` of the in-flight budget, waited for until `deadline`.
    async fn reserve(&self, bytes: u64, deadline: Instant) -> Result<OwnedSemaphorePermit, ApiError> {
        let budget = self.limits.decode.in_flight;
        if bytes > budget {
            return Err(ApiError::TooLarge(format!(
                "the image decodes to {} MiB, over the server's in-flight budget of {} MiB",
                bytes >> 20,
                budget >> 20
            )));
        }
        let wait = self.in_flight.clone().acquire_many_owned(kib(bytes));
        match tokio::time::timeout_at(deadline.into(), wait).await {
            Ok(Ok(permit)) => Ok(permit),
            Ok(Err(_)) => Err(ApiError::Internal("shutting down".into())),
            Err(_) => Err(ApiError::unavailable(format!(
                "overloaded: other images hold the in-flight budget of {} MiB past the deadline; retry later",
                budget >> 20
            ))),
        }
    }
}

/// Whole KiB, rounded up (the budget's permits; u32 holds 4 TiB).
fn kib(bytes: u64) -> u32 {
    u32::try_from(bytes.div_ceil(1024)).unwrap_or(u32::MAX)
}

impl Service {
    /// The category's versions and activation log (newest first).
    pub async fn versions(&self, category: &str) -> Result<Versions, ApiError> {
        let name = self.category(category)?.name.clone();
        let store = self.registry.store().clone();
        blocking(move || {
            let log = store.activations(&name)?;
            let active = log.first().map(|(_, a)| a.version.clone());
            let versions = store
                .versions(&name)?
                .into_iter()
                .map(|version| {
                    let manifest = store.manifest(&name, &version)?;
                    let job_id = manifest.training.get("job_id").and_then(|j| j.as_str()).map(str::to_owned);
                    Ok(VersionView {
                        active: active.as_deref() == Some(version.as_str()),
                        trained_as: manifest.version,
                        version,
                        job_id,
                    })
                })
                .collect::<Result<_, ApiError>>()?;
            let log = log.into_iter().map(|(generation, activation)| entry(&name, generation, activation)).collect();
            Ok(Versions { versions, activations: log })
        })
        .await
    }

    /// `StartJob`: a new job on the category's unclaimed images, or its running one.
    pub async fn start_job(
        &self,
        category: &str,
        overrides: Overrides,
        client_job_id: Option<String>,
    ) -> Result<JobView, ApiError> {
        let name = self.category(category)?.name.clone();
        let jobs = self.jobs.clone();
        blocking(move || jobs.start_job(&name, overrides, client_job_id)).await
    }

    /// A job (read from the store when it was created on another replica).
    pub async fn job(&self, id: String) -> Result<JobView, ApiError> {
        let jobs = self.jobs.clone();
        blocking(move || jobs.get(&id)).await
    }

    /// `CancelJob`: asks the job to stop and answers once it has (a running job stops at its
    /// next progress report, within seconds), or after [`CANCEL_WAIT`] with its state then.
    pub async fn cancel_job(&self, id: String, reason: String) -> Result<JobView, ApiError> {
        // Subscribed first, so that the terminal event cannot slip in between.
        let mut events = self.jobs.subscribe();
        let (jobs, job) = (self.jobs.clone(), id.clone());
        let view = blocking(move || jobs.cancel(&job, &reason)).await?;
        if view.state.terminal() {
            return Ok(view);
        }
        let deadline = tokio::time::Instant::now() + CANCEL_WAIT;
        loop {
            use tokio::sync::broadcast::error::RecvError;
            match tokio::time::timeout_at(deadline, events.recv()).await {
                Ok(Ok(e)) if e.job_id == id && e.state.terminal() => break,
                Ok(Ok(_)) => {}
                // Events were dropped: the state itself says whether ours was among them.
                Ok(Err(RecvError::Lagged(_))) if self.jobs.get(&id)?.state.terminal() => break,
                Ok(Err(RecvError::Lagged(_))) => {}
                Ok(Err(RecvError::Closed)) | Err(_) => break,
            }
        }
        let jobs = self.jobs.clone();
        blocking(move || jobs.get(&id)).await
    }

    /// Activates `version` and swaps the serving workers to it.
    pub async fn activate(
        &self,
        category: &str,
        version: String,
        reason: String,
        expected_generation: Option<u64>,
        actor: &str,
    ) -> Result<ActivationEntry, ApiError> {
        self.switch(category, Switch::To(version), reason, expected_generation, actor).await
    }

    /// Re-activates what the head entry of the log says precedes it (rollbacks walk back).
    pub async fn rollback(
        &self,
        category: &str,
        reason: String,
        expected_generation: Option<u64>,
        actor: &str,
    ) -> Result<ActivationEntry, ApiError> {
        self.switch(category, Switch::Back, reason, expected_generation, actor).await
    }

    async fn switch(
        &self,
        category: &str,
        to: Switch,
        reason: String,
        expected_generation: Option<u64>,
        actor: &str,
    ) -> Result<ActivationEntry, ApiError> {
        let name = self.category(category)?.name.clone();
        let store = self.registry.store().clone();
        let actor = actor.to_owned();
        let entry = blocking(move || {
            let generation = match to {
                Switch::To(v) => store.activate(&name, &v, &actor, &reason, expected_generation, None)?,
                Switch::Back => store.rollback(&name, &actor, &reason, expected_generation)?,
            };
            let (generation, activation) = store
                .activations(&name)?
                .into_iter()
                .find(|(g, _)| *g == generation)
                .ok_or_else(|| ApiError::Internal(format!("generation {generation} vanished")))?;
            Ok(entry(&name, generation, activation))
        })
        .await?;
        tracing::info!(category = %entry.category, version = %entry.version, generation = entry.generation,
            actor = %entry.actor, "activated");
        self.registry.refresh();
        Ok(entry)
    }

    /// Buffers one target image, or keeps it in the anchor set (decoding off the runtime).
    pub async fn put_target(&self, category: &str, bytes: bytes::Bytes, anchor: bool) -> Result<TargetAck, ApiError> {
        let name = self.category(category)?.name.clone();
        if bytes.len() > self.limits.max_request_bytes {
            return Err(ApiError::TooLarge(format!("image over the limit of {} bytes", self.limits.max_request_bytes)));
        }
        // Its decode (a check) holds budget too; a bad header is the buffer's to reject.
        let (head, limits) = (bytes.clone(), self.limits.decode);
        let cost = blocking(move || Ok(decode::Header::read(&head, limits).map_or(0, |h| h.cost()))).await?;
        let _in_flight = self.reserve(cost, Instant::now() + self.limits.default_timeout).await?;
        let _slot = self.decode_slot().await?;
        let jobs = self.jobs.clone();
        blocking(move || Ok(jobs.put_target(&name, &bytes, anchor))).await
    }

    /// The regression sets the gate guards for `category`, oldest first.
    pub async fn regression_sets(&self, category: &str) -> Result<Vec<udapose_api::RegressionSet>, ApiError> {
        let name = self.category(category)?.name.clone();
        let jobs = self.jobs.clone();
        blocking(move || jobs.regression_sets(&name)).await
    }
}

/// The job's events after `after_seq`, then new ones as they happen, until the terminal one.
pub fn watch(
    jobs: &Arc<Jobs>,
    id: String,
    after_seq: u64,
) -> Result<tokio_stream::wrappers::ReceiverStream<Result<JobEvent, ApiError>>, ApiError> {
    // Subscribed before the history is read, so no event falls in between.
    let mut live = jobs.subscribe();
    let history = jobs.events(&id, after_seq)?;
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    let jobs = jobs.clone();
    tokio::spawn(async move {
        let mut last = after_seq;
        let mut pending = history;
        loop {
            for event in pending.drain(..) {
                if event.seq <= last {
                    continue;
                }
                last = event.seq;
                let done = event.state.terminal();
                if tx.send(Ok(event)).await.is_err() || done {
                    return;
                }
            }
            match live.recv().await {
                Ok(event) if event.job_id == id => pending.push(event),
                Ok(_) => {}
                // Too slow a reader: catch up from the persisted history.
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => match jobs.events(&id, last) {
                    Ok(events) => pending = events,
                    Err(e) => {
                        let _ = tx.send(Err(e)).await;
                        return;
                    }
                },
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
            }
        }
    });
    Ok(tokio_stream::wrappers::ReceiverStream::new(rx))
}

/// Runs store work (files, or S3 calls) off the async runtime.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T, ApiError> + Send + 'static) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f).await.map_err(|e| ApiError::Internal(format!("a worker task failed: {e}")))?
}

fn truncate(s: &str, n: usize) -> String {
    s.chars().take(n).collect()
}

/// Where an activation goes.
enum Switch {
    To(String),
    Back,
}

/// An activation-log entry as the API shows it.
fn entry(category: &str, generation: u64, a: Activation) -> ActivationEntry {
    ActivationEntry {
        category: category.to_owned(),
        generation,
        version: a.version,
        previous: a.previous,
        actor: a.actor,
        reason: a.reason,
        time: a.time,
        job_id: a.job_id,
    }
}
