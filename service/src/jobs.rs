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

use std::{
    collections::{BTreeMap, VecDeque},
    ops::ControlFlow,
    sync::{
        Arc, Condvar, Mutex,
        atomic::{AtomicBool, Ordering},
    },
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow, bail};
use serde::{Deserialize, Serialize};
use serde_json::json;
use tch::{Device, Tensor};
use udapose_engine::{
    EngineError,
    adapt::{self, AdaptConfig, Event},
    checkpoint::{self, Manifest},
    gate::{self, Criterion, GateConfig},
    input::{self, Rgb8Image},
};

use crate::{
    buffer::{AckStatus, Buffer},
    decode::{self, DecodeLimits},
    error::ApiError,
    registry::Registry,
    store::{Store, StoreError, failpoint, nanos},
};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum JobState {
    Queued,
    Running,
    Validating,
    Activated,
    Rejected,
    Superseded,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn terminal(self) -> bool {
        !matches!(self, JobState::Queued | JobState::Running | JobState::Validating)
    }
}

/// Settings a job may override; unset: the server's defaults.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Overrides {
    pub max_rounds: Option<u32>,
    pub learning_rate: Option<f64>,
    pub seed: Option<u64>,
}

/// What a job runs on, written once when it is created.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobSpec {
    pub job_id: String,
    pub category: String,
    pub client_job_id: Option<String>,
    pub overrides: Overrides,
    pub source_version: String,
    pub source_generation: u64,
    /// The id the candidate version gets.
    pub version: String,
    pub train: Vec<String>,
    pub held_out: Vec<String>,
    pub created: f64,
}

/// One step of a job's history.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobEvent {
    pub job_id: String,
    pub seq: u64,
    pub state: JobState,
    pub time: f64,
    pub message: String,
    pub round: u32,
    pub max_rounds: u32,
    pub fired_ratio: f64,
    pub pose_change_median_deg: Option<f64>,
    pub images_used: u32,
    pub images_held_out: u32,
    pub eta_seconds: f64,
    pub gate: Vec<Criterion>,
    /// The candidate version, once saved.
    pub version: String,
}

/// A job as the API shows it.
#[derive(Clone, Debug, Serialize)]
pub struct JobView {
    pub job_id: String,
    pub category: String,
    pub state: JobState,
    pub source_version: String,
    pub source_generation: u64,
    pub version: String,
    pub created: f64,
    pub updated: f64,
    pub images_used: u32,
    pub images_held_out: u32,
    pub reason: String,
    pub client_job_id: String,
    pub last_event: JobEvent,
}

/// The answer to one streamed target image.
#[derive(Clone, Debug, Serialize)]
pub struct TargetAck {
    pub sha256: String,
    pub status: AckStatus,
    pub reason: String,
    pub buffered: usize,
    pub capacity: usize,
    pub job_id: Option<String>,
}

#[derive(Clone, Debug)]
pub struct JobsConfig {
    /// Unclaimed images that start a job by policy.
    pub min_images: usize,
    pub adapt: AdaptConfig,
    pub gate: GateConfig,
    pub device: Device,
    pub decode: DecodeLimits,
    /// Whether this process runs jobs (`--role all|adapt`) or only records and watches them.
    pub runs_jobs: bool,
    /// Whether a job that fails the gate stays inactive (`--gate enforce`) or is activated with
    /// the verdict in its activation's reason (`--gate advisory`).
    pub enforce_gate: bool,
    /// How often the store is read for jobs and images other processes wrote.
    pub poll: Duration,
}

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
    registry: Arc<Registry>,
    config: JobsConfig,
    inner: Mutex<Inner>,
    wake: Condvar,
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
        let (events, _) = tokio::sync::broadcast::channel(1024);
        let jobs = Arc::new(Jobs {
            store,
            buffer,
            registry,
            config,
            inner: Mutex::new(Inner::default()),
            wake: Condvar::new(),
            events,
        });
        jobs.sync(true)?;
        if jobs.config.runs_jobs {
            let runner = Arc::downgrade(&jobs);
            std::thread::Builder::new()
                .name("adapt".into())
                .spawn(move || run(&runner))
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

    fn start_by_policy(&self) {
        let categories: Vec<String> = self.registry.categories().map(|c| c.name.clone()).collect();
        for category in categories {
            self.maybe_start(&category);
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Reads the jobs in the store this process does not run: new ones, and new events of
    /// those still going (published to watchers). A process that runs jobs also takes the
    /// queued ones, the interrupted ones at `restart`, and cancellations asked elsewhere, and
    /// finishes the cleanup of ended ones.
    fn sync(&self, restart: bool) -> Result<()> {
        let mut found = Vec::new();
        for id in self.store.list("jobs")?.dirs {
            let known = self.lock().jobs.get(&id).map(|m| (m.owned, m.last.state.terminal(), m.last.seq));
            match known {
                None => match read_job(&self.store, &id) {
                    Ok(Some(job)) => found.push(job),
                    Ok(None) => {} // created but never written: debris of a crash, nothing claimed
                    Err(e) => tracing::warn!("skipping job {id}: {e:#}"),
                },
                Some((false, false, seq)) => self.follow(&id, seq)?,
                Some((true, false, _)) if self.config.runs_jobs => {
                    if let Some(reason) = self.store.read(&job_key(&id, "cancel.json"))? {
                        let reason = String::from_utf8_lossy(&reason).into_owned();
                        let _ = self.cancel(&id, &reason);
                    }
                }
                Some(_) => {}
            }
        }
        found.sort_by(|a, b| a.0.created.total_cmp(&b.0.created));
        for (spec, events) in found {
            if events.is_empty() && !restart {
                continue; // being created: its first event follows
            }
            let id = spec.job_id.clone();
            let last = events.last().cloned().unwrap_or_else(|| first_event(&spec));
            let state = if events.is_empty() { None } else { Some(last.state) };
            self.lock().jobs.insert(
                id.clone(),
                Memo {
                    spec: spec.clone(),
                    last,
                    owned: false,
                    cancel: Default::default(),
                    cancel_reason: String::new(),
                },
            );
            if !self.config.runs_jobs {
                continue;
            }
            let take = |jobs: &Self| {
                let mut inner = jobs.lock();
                inner.jobs.get_mut(&spec.job_id).expect("inserted above").owned = true;
                inner.queue.push_back(spec.job_id.clone());
                jobs.wake.notify_all();
            };
            match state {
                Some(s) if s.terminal() => self.release(&spec),
                Some(JobState::Queued) if !restart => {
                    tracing::info!(job = %id, "took a job queued on another replica");
                    take(self);
                }
                // Running on another worker that is alive: followed, not taken (at a restart,
                // below, what was running was this process's and is run again).
                _ if !restart => {}
                Some(JobState::Validating) if self.activated_by(&spec)? => {
                    self.append(&id, JobState::Activated, |e| {
                        e.message = "found in the activation log after a restart".into();
                    })?;
                    self.release(&spec);
                }
                _ => {
                    self.append(&id, JobState::Queued, |e| {
                        e.message = "interrupted by a restart; runs again from its buffered images".into();
                    })?;
                    take(self);
                }
            }
        }
        Ok(())
    }

    /// Publishes the events another process wrote for job `id` after `seq`.
    fn follow(&self, id: &str, seq: u64) -> Result<()> {
        for event in read_events(&self.store, id, seq)? {
            let mut inner = self.lock();
            let Some(memo) = inner.jobs.get_mut(id) else { return Ok(()) };
            if event.seq <= memo.last.seq {
                continue;
            }
            memo.last = event.clone();
            drop(inner);
            let _ = self.events.send(event);
        }
        Ok(())
    }

    fn activated_by(&self, spec: &JobSpec) -> Result<bool> {
        let log = self.store.activations(&spec.category)?;
        Ok(log.iter().any(|(_, a)| a.job_id.as_deref() == Some(&spec.job_id)))
    }

    /// Validates and buffers one target image; may start a job by policy.
    pub fn put_target(&self, category: &str, bytes: &[u8]) -> TargetAck {
        let sha256 = crate::buffer::sha256_hex(bytes);
        let capacity = self.buffer.capacity;
        let rejected = |reason: String| TargetAck {
            sha256: sha256.clone(),
            status: AckStatus::Rejected,
            reason,
            buffered: self.buffer.count(category).unwrap_or(0),
            capacity,
            job_id: None,
        };
        let pixels = match decode::decode(bytes, self.config.decode) {
            Ok(p) => p,
            Err(e) => return rejected(format!("INVALID_IMAGE: {e}")),
        };
        if pixels.width < input::MIN_IMAGE_SIDE || pixels.height < input::MIN_IMAGE_SIDE {
            let min = input::MIN_IMAGE_SIDE;
            return rejected(format!("INVALID_IMAGE: {}x{} px; at least {min}x{min}", pixels.width, pixels.height));
        }
        match self.buffer.put(category, bytes, pixels.width as u32, pixels.height as u32) {
            Ok((AckStatus::Rejected, buffered)) => TargetAck {
                reason: format!(
                    "BUFFER_FULL: the {category} buffer holds {buffered} of {capacity} images; retry once a job has used them"
                ),
                ..rejected(String::new())
            },
            Ok((status, buffered)) => {
                let job_id = (status == AckStatus::Accepted && self.config.runs_jobs)
                    .then(|| self.maybe_start(category))
                    .flatten();
                TargetAck { sha256, status, reason: String::new(), buffered, capacity, job_id }
            }
            Err(e) => rejected(format!("STORAGE: {e}")),
        }
    }

    /// Buffered images no queued or running job holds.
    fn unclaimed(&self, inner: &Inner, category: &str) -> Result<Vec<String>, StoreError> {
        let mut free = self.buffer.list(category)?;
        for m in inner.jobs.values().filter(|m| m.spec.category == category && !m.last.state.terminal()) {
            for sha in m.spec.train.iter().chain(&m.spec.held_out) {
                free.remove(sha);
            }
        }
        Ok(free.into_iter().collect())
    }

    fn busy(inner: &Inner, category: &str) -> Option<String> {
        inner
            .jobs
            .values()
            .find(|m| m.spec.category == category && !m.last.state.terminal())
            .map(|m| m.spec.job_id.clone())
    }

    /// Starts a job when the policy says so; returns its id.
    fn maybe_start(&self, category: &str) -> Option<String> {
        let inner = self.lock();
        if Self::busy(&inner, category).is_some() {
            return None;
        }
        let free = self.unclaimed(&inner, category).ok()?;
        if free.len() < self.config.min_images {
            return None;
        }
        drop(inner);
        match self.create(category, Overrides::default(), None) {
            Ok(view) => Some(view.job_id),
            Err(e) => {
                tracing::warn!(%category, "cannot start an adaptation job: {e}");
                None
            }
        }
    }

    /// `StartJob`: a new job on the unclaimed images, or the category's running one.
    pub fn start_job(
        &self,
        category: &str,
        overrides: Overrides,
        client_job_id: Option<String>,
    ) -> Result<JobView, ApiError> {
        if !self.config.runs_jobs {
            // Jobs created on other replicas claim images too.
            self.sync(false).map_err(|e| ApiError::Internal(format!("reading jobs: {e:#}")))?;
        }
        {
            let inner = self.lock();
            if let Some(id) = &client_job_id
                && let Some(m) = inner.jobs.values().find(|m| m.spec.client_job_id.as_ref() == Some(id))
            {
                return Ok(view(m));
            }
            if let Some(id) = Self::busy(&inner, category) {
                return Ok(view(&inner.jobs[&id]));
            }
        }
        self.create(category, overrides, client_job_id)
    }

    fn create(&self, category: &str, overrides: Overrides, client_job_id: Option<String>) -> Result<JobView, ApiError> {
        let mut inner = self.lock();
        if let Some(id) = Self::busy(&inner, category) {
            return Ok(view(&inner.jobs[&id]));
        }
        let free =
            self.unclaimed(&inner, category).map_err(|e| ApiError::Internal(format!("reading the buffer: {e}")))?;
        let (held_out, train): (Vec<String>, Vec<String>) = free.into_iter().partition(|sha| held_out(sha));
        let needed = self.config.gate.min_images;
        if held_out.len() < needed || train.len() < needed {
            return Err(ApiError::FailedPrecondition(format!(
                "too few buffered {category} images: {} to train on and {} held out for validation; \
                 at least {needed} of each are needed (about 20% of images are held out)",
                train.len(),
                held_out.len()
            )));
        }
        let (source_generation, head) = self
            .store
            .head(category)
            .map_err(ApiError::from)?
            .ok_or_else(|| ApiError::FailedPrecondition(format!("{category} has no active version to adapt")))?;
        let created = now();
        let suffix = &crate::buffer::sha256_hex(format!("{}{}", nanos(), std::process::id()).as_bytes())[..6];
        let stamp = created as u64;
        let spec = JobSpec {
            job_id: format!("job-{stamp}-{suffix}"),
            category: category.into(),
            client_job_id,
            overrides,
            source_version: head.version,
            source_generation,
            version: format!("adapt-{stamp}-{suffix}"),
            train,
            held_out,
            created,
        };
        let bytes = serde_json::to_vec_pretty(&spec).expect("a job spec serialises");
        match self.store.create(&job_key(&spec.job_id, "job.json"), bytes) {
            Ok(true) => {}
            Ok(false) => return Err(ApiError::Internal(format!("job id collision: {}", spec.job_id))),
            Err(e) => return Err(ApiError::Internal(format!("writing job {}: {e}", spec.job_id))),
        }
        let id = spec.job_id.clone();
        let first = first_event(&spec);
        let owned = self.config.runs_jobs;
        let memo = Memo { spec, last: first, owned, cancel: Default::default(), cancel_reason: String::new() };
        inner.jobs.insert(id.clone(), memo);
        drop(inner);
        let message = if owned { "queued" } else { "queued; the adaptation worker runs it" };
        self.append(&id, JobState::Queued, |e| e.message = message.into())
            .map_err(|e| ApiError::Internal(format!("{e:#}")))?;
        let mut inner = self.lock();
        if owned {
            inner.queue.push_back(id.clone());
            self.wake.notify_all();
        }
        tracing::info!(job = %id, %category, "adaptation job queued");
        Ok(view(&inner.jobs[&id]))
    }

    /// Persists the next event (create-only: losing the race means another worker owns the
    /// job) and publishes it.
    fn append(&self, id: &str, state: JobState, edit: impl FnOnce(&mut JobEvent)) -> Result<JobEvent> {
        let mut inner = self.lock();
        let memo = inner.jobs.get_mut(id).ok_or_else(|| anyhow!("no job {id}"))?;
        if memo.last.state.terminal() {
            bail!("job {id} already ended {:?}", memo.last.state);
        }
        let mut event = memo.last.clone();
        event.seq += 1;
        event.state = state;
        event.time = now();
        event.message.clear();
        if state.terminal() {
            event.eta_seconds = 0.0;
        }
        edit(&mut event);
        let key = job_key(id, &format!("events/{:08}.json", event.seq));
        let bytes = serde_json::to_vec_pretty(&event)?;
        if !self.store.create(&key, bytes)? {
            memo.owned = false;
            bail!("job {id}: event {} exists: another worker owns this job; standing by", event.seq);
        }
        memo.last = event.clone();
        drop(inner);
        tracing::info!(job = %id, state = ?event.state, round = event.round, "{}", event.message);
        let _ = self.events.send(event.clone());
        Ok(event)
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

    /// Reads the store once when `id` is not known yet (created on another replica since the
    /// last poll).
    fn discover(&self, id: &str) {
        if !self.lock().jobs.contains_key(id)
            && let Err(e) = self.sync(false)
        {
            tracing::warn!("reading jobs from the store: {e:#}");
        }
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

    /// New events of every job.
    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<JobEvent> {
        self.events.subscribe()
    }

    /// The job's persisted events after `after_seq`.
    pub fn events(&self, id: &str, after_seq: u64) -> Result<Vec<JobEvent>, ApiError> {
        self.get(id)?;
        read_events(&self.store, id, after_seq).map_err(|e| ApiError::Internal(format!("{e:#}")))
    }

    /// The job's images leave the buffer; the category may start its next job.
    fn release(&self, spec: &JobSpec) {
        let all: Vec<String> = spec.train.iter().chain(&spec.held_out).cloned().collect();
        self.buffer.remove(&spec.category, &all);
    }

    fn next(&self) -> Option<String> {
        let mut inner = self.lock();
        loop {
            if let Some(id) = inner.queue.pop_front() {
                return Some(id);
            }
            inner = self.wake.wait(inner).unwrap_or_else(|p| p.into_inner());
        }
    }

    fn run_one(&self, id: &str) {
        let Some((spec, cancel, state)) =
            self.lock().jobs.get(id).map(|m| (m.spec.clone(), m.cancel.clone(), m.last.state))
        else {
            return;
        };
        if cancel.load(Ordering::Acquire) || state.terminal() {
            return; // cancelled while queued (already recorded), or ended elsewhere
        }
        let ended = match self.execute(&spec, &cancel) {
            Ok(()) => return self.finish(&spec),
            Err(e) if is_cancelled(&e) => {
                let why = self.lock().jobs.get(id).map(|m| m.cancel_reason.clone()).unwrap_or_default();
                self.append(id, JobState::Cancelled, |ev| ev.message = why)
            }
            Err(e) => {
                tracing::error!(job = %id, "adaptation job failed: {e:#}");
                self.append(id, JobState::Failed, |ev| ev.message = format!("{e:#}"))
            }
        };
        match ended {
            Ok(_) => self.finish(&spec),
            Err(e) => tracing::error!(job = %id, "cannot record the job's end: {e:#}"),
        }
    }

    fn finish(&self, spec: &JobSpec) {
        self.release(spec);
        self.maybe_start(&spec.category);
    }

    /// Adapt, save, validate, activate; every terminal event but CANCELLED and FAILED is
    /// written here.
    fn execute(&self, spec: &JobSpec, cancel: &AtomicBool) -> Result<()> {
        let id = spec.job_id.as_str();
        let mut config = self.config.adapt.clone();
        let o = &spec.overrides;
        config.max_rounds = o.max_rounds.map_or(config.max_rounds, |r| r as usize);
        config.lr = o.learning_rate.unwrap_or(config.lr);
        config.seed = o.seed.unwrap_or(config.seed);
        let max_rounds = config.max_rounds as u32;
        self.append(id, JobState::Running, |e| {
            e.message = format!("adapting {} on {} images", spec.source_version, spec.train.len());
            e.max_rounds = max_rounds;
        })?;
        let source_dir = self.store.version_dir(&spec.category, &spec.source_version)?;
        let source = checkpoint::load(&source_dir, self.config.device)
            .with_context(|| format!("loading {}", source_dir.display()))?;
        let crop = source.manifest.crop;
        let saved = match self.store.manifest(&spec.category, &spec.version) {
            Ok(_) => true,
            Err(StoreError::UnknownVersion { .. }) => false,
            Err(e) => return Err(e.into()),
        };
        if saved {
            tracing::info!(job = %id, "version {} was saved before a restart; validating it", spec.version);
        } else {
            let train = self.images(&spec.category, &spec.train, crop)?;
            let started = Instant::now();
            // Set when the images do not look like the category (see GateConfig::min_target_fired).
            let mut mismatch = None;
            let min_fired = self.config.gate.min_target_fired;
            let mut on_event = |event: Event| {
                if cancel.load(Ordering::Acquire) {
                    return ControlFlow::Break(());
                }
                if let Event::Round(r) = event
                    && let Some(seen) = self.config.gate.target_mismatch(r)
                {
                    mismatch = Some(seen);
                    return ControlFlow::Break(());
                }
                if let Event::Round(r) = event {
                    let per_round = started.elapsed().as_secs_f64() / r.round as f64;
                    let result = self.append(id, JobState::Running, |e| {
                        e.message = format!("round {} of at most {max_rounds}", r.round);
                        e.round = r.round as u32;
                        e.fired_ratio = r.fired_ratio;
                        e.pose_change_median_deg = r.pose_change_median_deg;
                        e.eta_seconds = per_round * (max_rounds as f64 - r.round as f64).max(0.0);
                    });
                    if let Err(e) = result {
                        tracing::error!(job = %id, "{e:#}");
                        return ControlFlow::Break(());
                    }
                }
                ControlFlow::Continue(())
            };
            let adapted = adapt::adapt(&source, &train, &config, &mut on_event);
            drop(train);
            if let Some(fired) = mismatch {
                self.append(id, JobState::Rejected, |e| {
                    e.message = format!(
                        "the target images do not look like {} to {}: {:.1}% of visible vertices fire \
                         (at least {:.1}% needed); nothing was saved",
                        spec.category,
                        spec.source_version,
                        100.0 * fired,
                        100.0 * min_fired
                    );
                    e.fired_ratio = fired;
                })?;
                return Ok(());
            }
            let adapted = adapted?;
            let manifest = Manifest {
                version: spec.version.clone(),
                training: json!({
                    "kind": "3duda-online",
                    "job_id": id,
                    "source_version": spec.source_version,
                    "source_training": source.manifest.training,
                    "config": config,
                    "images": spec.train.len(),
                    "rounds": adapted.rounds,
                    "converged": adapted.converged,
                    "backbone_steps": adapted.backbone_steps,
                }),
                // f32: f16 would round the small updates of adaptation away (METHOD.md §7.6).
                dtype: "f32".into(),
                metrics: serde_json::Value::Null,
                files: Default::default(),
                ..source.manifest.clone()
            };
            self.store.put_version(&spec.category, &spec.version, |dir| {
                checkpoint::save(dir, &manifest, &adapted.vs, &adapted.neural_mesh).map_err(|e| e.to_string())
            })?;
        }
        self.append(id, JobState::Validating, |e| {
            e.message = format!("saved {}; validating on {} held-out images", spec.version, spec.held_out.len());
            e.version = spec.version.clone();
        })?;

        let candidate_dir = self.store.version_dir(&spec.category, &spec.version)?;
        let candidate = checkpoint::load(&candidate_dir, self.config.device)
            .with_context(|| format!("loading {}", candidate_dir.display()))?;
        let held_out = self.images(&spec.category, &spec.held_out, crop)?;
        let mut check = |_: usize, _: usize| {
            if cancel.load(Ordering::Acquire) { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        };
        let before = gate::measure(&source, &held_out, &self.config.gate, &mut check)?;
        let after = gate::measure(&candidate, &held_out, &self.config.gate, &mut check)?;
        let decision = gate::decide(&before, &after, &self.config.gate)?;
        if !decision.passed && self.config.enforce_gate {
            self.append(id, JobState::Rejected, |e| {
                e.message = format!("the gate kept {} inactive: {}", spec.version, decision.reason());
                e.gate = decision.criteria.clone();
            })?;
            return Ok(());
        }
        let reason = if decision.passed {
            format!("job {id}: passed the validation gate")
        } else {
            format!("job {id}: activated by --gate advisory although the gate failed: {}", decision.reason())
        };
        let actor = format!("job:{id}");
        failpoint("before-activate");
        let activated =
            self.store.activate(&spec.category, &spec.version, &actor, &reason, Some(spec.source_generation), Some(id));
        match activated {
            Ok(generation) => {
                self.registry.refresh();
                self.append(id, JobState::Activated, |e| {
                    e.message = format!("activated {} as generation {generation}", spec.version);
                    e.gate = decision.criteria.clone();
                })?;
            }
            Err(StoreError::Conflict { found, .. }) => {
                tracing::warn!(job = %id, "activation conflict: generation {found} is active, the job started from {}", spec.source_generation);
                self.append(id, JobState::Superseded, |e| {
                    e.message = format!(
                        "passed the gate, but generation {found} was activated since the job started from {}",
                        spec.source_generation
                    );
                    e.gate = decision.criteria.clone();
                })?;
            }
            Err(e) => return Err(e.into()),
        }
        Ok(())
    }

    /// Buffered images as the model's crops (N×3×H×W in [0, 1]).
    fn images(&self, category: &str, shas: &[String], crop: [usize; 2]) -> Result<Tensor> {
        let [h, w] = crop;
        let mut pixels = Vec::with_capacity(shas.len() * 3 * h * w);
        for sha in shas {
            let bytes = self.buffer.read(category, sha).with_context(|| format!("reading buffered image {sha}"))?;
            let decoded = decode::decode(&bytes, self.config.decode).map_err(|e| anyhow!("image {sha}: {e}"))?;
            let image = Rgb8Image::new(&decoded.rgb8, decoded.width, decoded.height)?;
            pixels.extend(input::crop(&image, None, crop)?.pixels);
        }
        Ok(Tensor::from_slice(&pixels).view([shas.len() as i64, 3, h as i64, w as i64]))
    }
}

fn run(jobs: &std::sync::Weak<Jobs>) {
    loop {
        let Some(j) = jobs.upgrade() else { return };
        if let Some(id) = j.next() {
            j.run_one(&id);
        }
    }
}

fn is_cancelled(e: &anyhow::Error) -> bool {
    matches!(e.downcast_ref::<EngineError>(), Some(EngineError::Cancelled))
}

/// Whether an image (by its hex sha256) is held out for the gate: the engine's bucket rule.
fn held_out(sha_hex: &str) -> bool {
    let bytes: Vec<u8> =
        (0..2).filter_map(|i| sha_hex.get(2 * i..2 * i + 2).and_then(|h| u8::from_str_radix(h, 16).ok())).collect();
    gate::held_out(&bytes)
}

fn first_event(spec: &JobSpec) -> JobEvent {
    JobEvent {
        job_id: spec.job_id.clone(),
        seq: 0,
        state: JobState::Queued,
        time: spec.created,
        message: String::new(),
        round: 0,
        max_rounds: 0,
        fired_ratio: 0.0,
        pose_change_median_deg: None,
        images_used: spec.train.len() as u32,
        images_held_out: spec.held_out.len() as u32,
        eta_seconds: 0.0,
        gate: Vec::new(),
        version: String::new(),
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

fn job_key(id: &str, rest: &str) -> String {
    format!("jobs/{id}/{rest}")
}

/// A job's spec and events; `None` when it has no spec (a crash before it was written).
fn read_job(store: &Store, id: &str) -> Result<Option<(JobSpec, Vec<JobEvent>)>> {
    let Some(spec) = store.read_json::<JobSpec>(&job_key(id, "job.json"))? else { return Ok(None) };
    Ok(Some((spec, read_events(store, id, 0)?)))
}

/// The job's events after `after_seq`, in order.
fn read_events(store: &Store, id: &str, after_seq: u64) -> Result<Vec<JobEvent>> {
    let mut out = Vec::new();
    for name in store.list(&job_key(id, "events"))?.files {
        let Some(seq) = name.strip_suffix(".json").and_then(|n| n.parse::<u64>().ok()) else { continue };
        if seq > after_seq {
            let key = job_key(id, &format!("events/{name}"));
            out.push(store.read_json::<JobEvent>(&key)?.with_context(|| format!("{key} vanished"))?);
        }
    }
    Ok(out)
}
