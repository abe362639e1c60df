//! When jobs start and in what order: the start policy, the claim on buffered images, the
//! queue and the one runner thread.

use std::sync::atomic::Ordering;

use super::{
    Inner, JobSpec, JobState, JobView, Jobs, Memo, Overrides, first_event, held_out, log::job_key, now,
    run::is_cancelled, view,
};
use crate::{
    error::ApiError,
    store::{StoreError, nanos},
};

impl Jobs {
    pub(super) fn start_by_policy(&self) {
        let categories: Vec<String> = self.registry.categories().map(|c| c.name.clone()).collect();
        for category in categories {
            self.maybe_start(&category);
        }
    }

    /// Buffered images no queued or running job holds. The buffer is listed (store I/O)
    /// before the state lock is taken, so readers never wait on the store.
    pub(super) fn unclaimed(&self, category: &str) -> Result<Vec<String>, StoreError> {
        let mut free = self.buffer.list(category)?;
        let inner = self.lock();
        for m in inner.jobs.values().filter(|m| m.spec.category == category && !m.last.state.terminal()) {
            for sha in m.spec.train.iter().chain(&m.spec.held_out) {
                free.remove(sha);
            }
        }
        Ok(free.into_iter().collect())
    }

    pub(super) fn busy(inner: &Inner, category: &str) -> Option<String> {
        inner
            .jobs
            .values()
            .find(|m| m.spec.category == category && !m.last.state.terminal())
            .map(|m| m.spec.job_id.clone())
    }

    /// Starts a job when the policy says so; returns its id.
    pub(super) fn maybe_start(&self, category: &str) -> Option<String> {
        if Self::busy(&self.lock(), category).is_some() {
            return None;
        }
        let free = self.unclaimed(category).ok()?;
        if free.len() < self.config.min_images {
            return None;
        }
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

    /// Creates a job on the unclaimed images. Creations take turns (`creating`), so two never
    /// claim the same images; the state lock is held only between store calls, never across one.
    pub(super) fn create(
        &self,
        category: &str,
        overrides: Overrides,
        client_job_id: Option<String>,
    ) -> Result<JobView, ApiError> {
        let _turn = self.creating.lock().unwrap_or_else(|p| p.into_inner());
        let busy = Self::busy(&self.lock(), category);
        if let Some(id) = busy {
            return Ok(view(&self.lock().jobs[&id]));
        }
        let free = self.unclaimed(category).map_err(|e| ApiError::Internal(format!("reading the buffer: {e}")))?;
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
        let first = first_event(&spec, self.adapt_config(&spec).max_rounds as u32);
        let owned = self.config.runs_jobs;
        let memo = Memo { spec, last: first, owned, cancel: Default::default(), cancel_reason: String::new() };
        self.lock().jobs.insert(id.clone(), memo);
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

    /// The job's images leave the buffer; the category may start its next job.
    pub(super) fn release(&self, spec: &JobSpec) {
        let all: Vec<String> = spec.train.iter().chain(&spec.held_out).cloned().collect();
        self.buffer.remove(&spec.category, &all);
    }

    pub(super) fn next(&self) -> Option<String> {
        let mut inner = self.lock();
        loop {
            if let Some(id) = inner.queue.pop_front() {
                return Some(id);
            }
            inner = self.wake.wait(inner).unwrap_or_else(|p| p.into_inner());
        }
    }

    pub(super) fn run_one(&self, id: &str) {
        let Some((spec, cancel, state)) =
            self.lock().jobs.get(id).map(|m| (m.spec.clone(), m.cancel.clone(), m.last.state))
        else {
            return;
        };
        if cancel.load(Ordering::Acquire) || state.terminal() {
            return; // cancelled while queued (already recorded), or ended elsewhere
        }
        let ended = match self.pool.install(|| self.execute(&spec, &cancel)) {
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

    pub(super) fn finish(&self, spec: &JobSpec) {
        self.release(spec);
        self.maybe_start(&spec.category);
    }
}

pub(super) fn run(jobs: &std::sync::Weak<Jobs>) {
    loop {
        let Some(j) = jobs.upgrade() else { return };
        if let Some(id) = j.next() {
            j.run_one(&id);
        }
    }
}
