//! Online adaptation jobs (ARCHITECTURE.md "Service contract", "State", "Validation gate").
//!
//! A job adapts a copy of the category's active version on buffered target images, on its own
//! thread, never touching the serving weights; saves the result as a new immutable version;
//! compares it with the version it started from on held-out buffered images (the engine's
//! label-free gate); and activates it with a create-only write of the generation it started
//! from + 1. Its history is persisted event by event:
//!
//! ```text
//! jobs/<job-id>/job.json               what it runs on (images, source version, settings)
//! jobs/<job-id>/events/<seq:08>.json   its history; its state is the last event's
//! jobs/<job-id>/cancel.json            a cancellation asked on a replica that does not run it
//! ```
//!
//! Roles: every process reads jobs from the store (so `WatchJob` works on any replica, polling
//! every `poll`), but only a process that runs jobs (`--role all|adapt`) executes them. A job
//! created on a serve replica is a record in the store that the worker picks up. Events are
//! create-only writes: a worker whose event already exists has lost the job to another worker
//! and stands by, so two workers never both run a job to its end.
//!
//! Policy: a job starts when a category holds at least `min_images` images no job has claimed
//! and none of its jobs is queued or running, or when a client asks. Images that arrive during
//! a job stay buffered for the next one. At a terminal state the job's images (trained on and
//! held out) leave the buffer. After a crash, queued and running jobs run again from their
//! persisted image lists (a version already saved complete is reused), and a validating job
//! first looks for itself in the activation log.

mod experts;
mod log;
mod model;
pub mod priority;
mod run;
mod scheduler;
#[cfg(test)]
mod tests;

use std::{
    collections::{BTreeMap, VecDeque},
    sync::{
        Arc, Condvar, Mutex,
        atomic::{AtomicBool, Ordering},
    },
};

use anyhow::{Context, Result};

pub use experts::ExpertConfig;
use log::{job_key, read_events};
pub use model::{JobEvent, JobSpec, JobState, JobView, JobsConfig, Overrides, Rejection, TargetAck};
use model::{first_event, held_out};

use crate::{
    buffer::{AckStatus, Buffer},
    decode,
    error::ApiError,
    registry::Registry,
    regression::{Regression, RegressionSet},
    store::{Store, nanos},
};
use udapose_engine::input;

struct Memo {
    spec: JobSpec,
    last: JobEvent,
    /// This process runs the job (its events are written here, not read from the store).
    owned: bool,
    cancel: Arc<AtomicBool>,
    cancel_reason: String,
}

#[derive(Default)]
struct Inner {
    jobs: BTreeMap<String, Memo>,
    queue: VecDeque<String>,
}

pub struct Jobs {
    store: Store,
    pub buffer: Buffer,
    /// What the gate guards besides the job's own held-out images.
    pub regression: Regression,
    registry: Arc<Registry>,
    config: JobsConfig,
    /// The jobs this process knows; never held across a store call.
    inner: Mutex<Inner>,
    /// Turns for creating a job (claiming images) and for appending an event: each spans
    /// store calls, so neither is `inner`.
    creating: Mutex<()>,
    appending: Mutex<()>,
    wake: Condvar,
    /// Where a job's parallel solves run: a job's 32-image batch on the global pool made a
    /// 27 ms serving solve wait 1.3 s at the median (issue 23's measurement).
    pool: rayon::ThreadPool,
    events: tokio::sync::broadcast::Sender<JobEvent>,
}

fn now() -> f64 {
    nanos() as f64 / 1e9
}

impl Jobs {
    /// Loads every job from the store, recovers the interrupted ones (when it runs jobs), and
    /// starts the runner thread (one job at a time: a job uses every core it gets) and the
    /// store poller.
    pub fn start(store: Store, registry: Arc<Registry>, buffer: Buffer, config: JobsConfig) -> Result<Arc<Self>> {
        config.gate.validate().context("the validation gate's settings")?;
        config.adapt.validate().context("the adaptation's settings")?;
        let (events, _) = tokio::sync::broadcast::channel(1024);
        let nice = config.nice;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads.max(1))
            .thread_name(|i| format!("adapt-solve-{i}"))
            .start_handler(move |_| {
                priority::lower_this_thread(nice);
                // Every core for the job's own libtorch work, at its lower priority, whatever
                // count the inference workers were given.
                crate::threads::pin_torch_threads(udapose_engine::runtime::cores());
            })
            .build()
            .context("building the adaptation jobs' thread pool")?;
        let regression = Regression::new(store.clone(), config.regression.clone());
        let jobs = Arc::new(Jobs {
            store,
            buffer,
            regression,
            registry,
            config,
            inner: Mutex::new(Inner::default()),
            creating: Mutex::new(()),
            appending: Mutex::new(()),
            wake: Condvar::new(),
            pool,
            events,
        });
        jobs.sync(true)?;
        if jobs.config.runs_jobs {
            let runner = Arc::downgrade(&jobs);
            std::thread::Builder::new()
                .name("adapt".into())
                .spawn(move || scheduler::run(&runner))
                .context("spawning the adaptation thread")?;
            jobs.start_by_policy();
        }
        let poller = Arc::downgrade(&jobs);
        let period = jobs.config.poll;
        if period.is_zero() {
            return Ok(jobs);
        }
        std::thread::Builder::new()
            .name("jobs-poll".into())
            .spawn(move || {
                while let Some(j) = poller.upgrade() {
                    if let Err(e) = j.sync(false) {
                        tracing::warn!("reading jobs from the store: {e:#}");
                    }
                    if j.config.runs_jobs {
                        j.start_by_policy();
                    }
                    drop(j);
                    std::thread::sleep(period);
                }
            })
            .context("spawning the jobs poller")?;
        Ok(jobs)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Validates and buffers one target image (or, `anchor`, keeps it in the category's anchor
    /// set); may start a job by policy.
    pub fn put_target(&self, category: &str, bytes: &[u8], anchor: bool) -> TargetAck {
        let sha256 = crate::buffer::sha256_hex(bytes);
        let capacity = self.buffer.capacity;
        let rejected = |why: Rejection, detail: String| TargetAck {
            sha256: sha256.clone(),
            status: AckStatus::Rejected,
            rejection: Some(why),
            reason: format!("{}: {detail}", why.code()),
            buffered: self.buffer.count(category).unwrap_or(0),
            capacity,
            job_id: None,
        };
        let pixels = match decode::decode(bytes, self.config.decode) {
            Ok(p) => p,
            Err(e) => return rejected(Rejection::InvalidImage, e.to_string()),
        };
        if pixels.width < input::MIN_IMAGE_SIDE || pixels.height < input::MIN_IMAGE_SIDE {
            let min = input::MIN_IMAGE_SIDE;
            return rejected(
                Rejection::InvalidImage,
                format!("{}x{} px; at least {min}x{min}", pixels.width, pixels.height),
            );
        }
        if anchor {
            let max = self.regression.config.max_anchor;
            return match self.regression.put_anchor(category, bytes) {
                Ok((AckStatus::Rejected, held)) => TargetAck {
                    buffered: held,
                    capacity: max,
                    ..rejected(
                        Rejection::BufferFull,
                        format!("the {category} anchor set holds {held} of {max} images, its most"),
                    )
                },
                Ok((status, held)) => TargetAck {
                    sha256,
                    status,
                    rejection: None,
                    reason: String::new(),
                    buffered: held,
                    capacity: max,
                    job_id: None,
                },
                Err(e) => rejected(Rejection::Storage, e.to_string()),
            };
        }
        match self.buffer.put(category, bytes, pixels.width as u32, pixels.height as u32) {
            Ok((AckStatus::Rejected, buffered)) => TargetAck {
                buffered,
                ..rejected(
                    Rejection::BufferFull,
                    format!(
                        "the {category} buffer holds {buffered} of {capacity} images; retry once a job has used them"
                    ),
                )
            },
            Ok((status, buffered)) => {
                let job_id = (status == AckStatus::Accepted && self.config.runs_jobs)
                    .then(|| self.maybe_start(category))
                    .flatten();
                TargetAck { sha256, status, rejection: None, reason: String::new(), buffered, capacity, job_id }
            }
            Err(e) => rejected(Rejection::Storage, e.to_string()),
        }
    }

    pub fn get(&self, id: &str) -> Result<JobView, ApiError> {
        self.discover(id);
        let inner = self.lock();
        inner.jobs.get(id).map(view).ok_or_else(|| ApiError::NotFound(format!("no job {id:?}")))
    }

    /// Jobs, newest first, optionally of one category.
    pub fn list(&self, category: Option<&str>) -> Vec<JobView> {
        let inner = self.lock();
        let mut out: Vec<JobView> =
            inner.jobs.values().filter(|m| category.is_none_or(|c| m.spec.category == c)).map(view).collect();
        out.sort_by(|a, b| b.created.total_cmp(&a.created));
        out
    }

    pub fn cancel(&self, id: &str, reason: &str) -> Result<JobView, ApiError> {
        self.discover(id);
        let mut inner = self.lock();
        let memo = inner.jobs.get(id).ok_or_else(|| ApiError::NotFound(format!("no job {id:?}")))?;
        if memo.last.state.terminal() {
            return Ok(view(memo));
        }
        if !memo.owned {
            // Another process runs it: ask through the store (its poller acts on it).
            drop(inner);
            self.store
                .create(&job_key(id, "cancel.json"), reason.as_bytes().to_vec())
                .map_err(|e| ApiError::Internal(format!("asking job {id} to cancel: {e}")))?;
            return self.get(id);
        }
        let why = if reason.is_empty() { "cancelled".to_string() } else { format!("cancelled: {reason}") };
        let memo = inner.jobs.get_mut(id).expect("present above");
        memo.cancel_reason = why.clone();
        memo.cancel.store(true, Ordering::Release);
        let queued = memo.last.state == JobState::Queued;
        let spec = memo.spec.clone();
        if queued {
            inner.queue.retain(|q| q != id);
        }
        drop(inner);
        if queued {
            self.append(id, JobState::Cancelled, |e| e.message = why)
                .map_err(|e| ApiError::Internal(format!("{e:#}")))?;
            self.release(&spec);
        }
        // A running job stops at its next progress report and records CANCELLED itself.
        self.get(id)
    }

    /// The category's regression sets, oldest first (see `regression.rs`).
    pub fn regression_sets(&self, category: &str) -> Result<Vec<RegressionSet>, ApiError> {
        let sets =
            self.regression.sets(category).map_err(|e| ApiError::Internal(format!("reading regression sets: {e}")))?;
        Ok(sets.into_iter().map(|s| s.set).collect())
    }

    /// New events of every job.
    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<JobEvent> {
        self.events.subscribe()
    }

    /// The job's persisted events after `after_seq`.
    pub fn events(&self, id: &str, after_seq: u64) -> Result<Vec<JobEvent>, ApiError> {
        self.get(id)?;
        read_events(&self.store, id, after_seq).map_err(|e| ApiError::Internal(format!("{e:#}")))
    }
}

fn view(m: &Memo) -> JobView {
    let s = &m.spec;
    let reason = if m.last.state.terminal() { m.last.message.clone() } else { String::new() };
    JobView {
        job_id: s.job_id.clone(),
        category: s.category.clone(),
        state: m.last.state,
        source_version: s.source_version.clone(),
        source_generation: s.source_generation,
        version: m.last.version.clone(),
        created: s.created,
        updated: m.last.time,
        images_used: s.train.len() as u32,
        images_held_out: s.held_out.len() as u32,
        reason,
        client_job_id: s.client_job_id.clone().unwrap_or_default(),
        last_event: m.last.clone(),
    }
}
