//! A job's history in the store: `jobs/<id>/job.json` once, then create-only events; other
//! processes' jobs are followed by reading them.

use anyhow::{Context, Result, anyhow, bail};

use super::{JobEvent, JobSpec, JobState, Jobs, Memo, first_event, now};
use crate::store::Store;

impl Jobs {
    /// Reads the jobs in the store this process does not run: new ones, and new events of
    /// those still going (published to watchers). A process that runs jobs also takes the
    /// queued ones, the interrupted ones at `restart`, and cancellations asked elsewhere, and
    /// finishes the cleanup of ended ones.
    pub(super) fn sync(&self, restart: bool) -> Result<()> {
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
            let last = events
                .last()
                .cloned()
                .unwrap_or_else(|| first_event(&spec, self.adapt_config(&spec).max_rounds as u32));
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
                    // Its regression set was written before the activation; complete it if the
                    // crash tore it (its images are still buffered).
                    if let Err(e) = self.record_set(&spec) {
                        tracing::warn!(job = %id, "completing the job's regression set: {e:#}");
                    }
                    self.append(&id, JobState::Activated, |e| {
                        e.message = "found in the activation log after a restart".into();
                    })?;
                    self.release(&spec);
                }
                _ => {
                    self.append(&id, JobState::Queued, |e| {
                        e.message = "interrupted by a restart; runs again from its buffered images".into();
                        // It starts over: the interrupted run's progress no longer applies.
                        (e.round, e.eta_seconds, e.fired_ratio, e.pose_change_median_deg) = (0, 0.0, 0.0, None);
                    })?;
                    take(self);
                }
            }
        }
        Ok(())
    }

    /// Publishes the events another process wrote for job `id` after `seq`.
    pub(super) fn follow(&self, id: &str, seq: u64) -> Result<()> {
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

    pub(super) fn activated_by(&self, spec: &JobSpec) -> Result<bool> {
        let log = self.store.activations(&spec.category)?;
        Ok(log.iter().any(|(_, a)| a.job_id.as_deref() == Some(&spec.job_id)))
    }

    /// Persists the next event (create-only: losing the race means another worker owns the
    /// job) and publishes it.
    pub(super) fn append(&self, id: &str, state: JobState, edit: impl FnOnce(&mut JobEvent)) -> Result<JobEvent> {
        // Appends take turns, so the next sequence number is this one's until it is written;
        // the state lock is released while the store writes.
        let _turn = self.appending.lock().unwrap_or_else(|p| p.into_inner());
        let mut event = {
            let inner = self.lock();
            let memo = inner.jobs.get(id).ok_or_else(|| anyhow!("no job {id}"))?;
            if memo.last.state.terminal() {
                bail!("job {id} already ended {:?}", memo.last.state);
            }
            memo.last.clone()
        };
        event.seq += 1;
        event.state = state;
        event.time = now();
        event.message.clear();
        if state.terminal() {
            event.eta_seconds = 0.0;
        }
        edit(&mut event);
        let key = job_key(id, &format!("events/{:08}.json", event.seq));
        let created = self.store.create(&key, serde_json::to_vec_pretty(&event)?)?;
        let mut inner = self.lock();
        let memo = inner.jobs.get_mut(id).ok_or_else(|| anyhow!("no job {id}"))?;
        if !created {
            memo.owned = false;
            bail!("job {id}: event {} exists: another worker owns this job; standing by", event.seq);
        }
        memo.last = event.clone();
        drop(inner);
        tracing::info!(job = %id, state = ?event.state, round = event.round, "{}", event.message);
        let _ = self.events.send(event.clone());
        Ok(event)
    }

    /// Reads the store once when `id` is not known yet (created on another replica since the
    /// last poll).
    pub(super) fn discover(&self, id: &str) {
        if !self.lock().jobs.contains_key(id)
            && let Err(e) = self.sync(false)
        {
            tracing::warn!("reading jobs from the store: {e:#}");
        }
    }
}

pub(super) fn job_key(id: &str, rest: &str) -> String {
    format!("jobs/{id}/{rest}")
}

/// A job's spec and events; `None` when it has no spec (a crash before it was written).
fn read_job(store: &Store, id: &str) -> Result<Option<(JobSpec, Vec<JobEvent>)>> {
    let Some(spec) = store.read_json::<JobSpec>(&job_key(id, "job.json"))? else { return Ok(None) };
    Ok(Some((spec, read_events(store, id, 0)?)))
}

/// The job's events after `after_seq`, in order.
pub(super) fn read_events(store: &Store, id: &str, after_seq: u64) -> Result<Vec<JobEvent>> {
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
