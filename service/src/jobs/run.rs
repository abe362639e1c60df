//! One job's work: adapt, save, validate, activate.

use std::{
    ops::ControlFlow,
    sync::atomic::{AtomicBool, Ordering},
    time::Instant,
};

use anyhow::{Context, Result, anyhow};
use serde_json::json;
use tch::Tensor;
use udapose_engine::{
    EngineError,
    adapt::{self, AdaptConfig, Event, RoundReport},
    checkpoint::{self, Manifest, Model},
    gate,
    input::{self, Rgb8Image},
};

use super::{
    JobSpec, JobState, Jobs,
    experts::{self, Compared, Start},
};
use crate::{
    decode,
    store::{StoreError, failpoint},
};

impl Jobs {
    /// Adapt, save, validate, activate; every terminal event but CANCELLED and FAILED is
    /// written here.
    pub(super) fn execute(&self, spec: &JobSpec, cancel: &AtomicBool) -> Result<()> {
        let config = self.adapt_config(spec);
        self.append(&spec.job_id, JobState::Running, |e| {
            e.message = format!("adapting {} on {} images", spec.source_version, spec.train.len());
            e.max_rounds = config.max_rounds as u32;
        })?;
        let source = self.load(spec, &spec.source_version)?;
        let start = self.starting_point(spec, source)?;
        let saved = match self.store.manifest(&spec.category, &spec.version) {
            Ok(_) => true,
            Err(StoreError::UnknownVersion { .. }) => false,
            Err(e) => return Err(e.into()),
        };
        if saved {
            tracing::info!(job = %spec.job_id, "version {} was saved before a restart; validating it", spec.version);
        } else if !self.adapt_and_save(spec, &start, &config, cancel)? {
            return Ok(());
        }
        self.validate_and_activate(spec, &start, cancel)
    }

    /// A version of the job's category, loaded.
    pub(super) fn load(&self, spec: &JobSpec, version: &str) -> Result<Model> {
        let dir = self.store.version_dir(&spec.category, version)?;
        checkpoint::load(&dir, self.config.device).with_context(|| format!("loading {}", dir.display()))
    }

    /// The server's adaptation settings with the job's overrides.
    pub(super) fn adapt_config(&self, spec: &JobSpec) -> AdaptConfig {
        let mut config = self.config.adapt.clone();
        let o = &spec.overrides;
        config.max_rounds = o.max_rounds.map_or(config.max_rounds, |r| r as usize);
        config.lr = o.learning_rate.unwrap_or(config.lr);
        config.seed = o.seed.unwrap_or(config.seed);
        config
    }

    /// 3DUDA on the job's images, then the candidate saved as its version. `false` when the
    /// target check rejected the images (recorded; nothing saved).
    fn adapt_and_save(&self, spec: &JobSpec, start: &Start, config: &AdaptConfig, cancel: &AtomicBool) -> Result<bool> {
        let (id, source) = (spec.job_id.as_str(), start.model());
        let train = self.images(&spec.category, &spec.train, source.manifest.crop)?;
        let started = Instant::now();
        // Set when the images do not look like the category (see GateConfig::min_target_fired).
        let mut mismatch = None;
        let min_fired = self.config.gate.min_target_fired_for(&source.manifest);
        let mut on_event = |event: Event| {
            if cancel.load(Ordering::Acquire) {
                return ControlFlow::Break(());
            }
            if let Some(seen) = gate::target_fired(&event) {
                tracing::info!(job = %id, "target check: {:.2}% of visible vertices fire to {} (at least {:.2}% needed)", 100.0 * seen, spec.source_version, 100.0 * min_fired);
                if seen < min_fired {
                    mismatch = Some(seen);
                    return ControlFlow::Break(());
                }
            }
            let Event::Round(r) = event else { return ControlFlow::Continue(()) };
            self.report_round(id, r, started, config.max_rounds)
        };
        let adapted = adapt::adapt(source, &train, config, &mut on_event);
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
            return Ok(false);
        }
        let adapted = adapted?;
        let manifest = Manifest {
            version: spec.version.clone(),
            training: json!({
                "kind": "3duda-online",
                "job_id": id,
                "source_version": spec.source_version,
                "expert_of_source": start.expert.as_ref().map(|(i, _)| &start.source.manifest.experts[*i].version),
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
            // A new version's own tensors answer what the source's did; an adapted expert is
            // a plain model, answering what the composite routes to it.
            experts: if start.expert.is_some() { Vec::new() } else { start.source.manifest.experts.clone() },
            ..source.manifest.clone()
        };
        self.store.put_version(&spec.category, &spec.version, |dir| {
            checkpoint::save(dir, &manifest, &adapted.vs, &adapted.neural_mesh).map_err(|e| e.to_string())
        })?;
        Ok(true)
    }

    /// A round's progress as a RUNNING event (a failed write stops the job).
    fn report_round(&self, id: &str, r: &RoundReport, started: Instant, max_rounds: usize) -> ControlFlow<()> {
        let per_round = started.elapsed().as_secs_f64() / r.round as f64;
        let result = self.append(id, JobState::Running, |e| {
            e.message = format!("round {} of at most {max_rounds}", r.round);
            e.round = r.round as u32;
            e.fired_ratio = r.fired_ratio;
            e.pose_change_median_deg = r.pose_change_median_deg;
            e.eta_seconds = per_round * (max_rounds as f64 - r.round as f64).max(0.0);
        });
        match result {
            Ok(_) => ControlFlow::Continue(()),
            Err(e) => {
                tracing::error!(job = %id, "{e:#}");
                ControlFlow::Break(())
            }
        }
    }

    /// The gate on the held-out images and the regression sets, candidate against source; then
    /// the create-only activation of the generation the job started from + 1: of the candidate,
    /// or, where it would regress an earlier domain, of the source with the candidate as an
    /// expert (`experts.rs`).
    fn validate_and_activate(&self, spec: &JobSpec, start: &Start, cancel: &AtomicBool) -> Result<()> {
        let id = spec.job_id.as_str();
        self.append(id, JobState::Validating, |e| {
            e.message = format!("saved {}; validating on {} held-out images", spec.version, spec.held_out.len());
            e.version = spec.version.clone();
        })?;

        let candidate = self.load(spec, &spec.version)?;
        let mut check = |_: usize, _: usize| {
            if cancel.load(Ordering::Acquire) { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
        };
        let held_out = self.images(&spec.category, &spec.held_out, start.source.manifest.crop)?;
        let Some(held) = self.compare(held_out, start, &candidate, &mut check)? else {
            self.append(id, JobState::Rejected, |e| {
                e.message = format!(
                    "the gate kept {} inactive: fewer than {} of its held-out images are answered by {}, \
                     which it adapted; the version's other members answer the rest",
                    spec.version,
                    self.config.gate.min_images,
                    start.name(spec)
                );
            })?;
            return Ok(());
        };
        let mut decision = gate::decide(&held.before, &held.after, &self.config.gate)?;
        let mut criteria: Vec<_> = decision.criteria.iter().map(criterion).collect();
        // Every set is measured even when the new domain already failed, so the events always
        // show what the candidate would do to the domains seen before (bounded: see
        // RegressionConfig).
        let sets = self.guard(spec, start, &candidate, &mut check)?;
        let guarded: Vec<(&str, gate::Decision)> = sets
            .iter()
            .map(|(set_id, c)| Ok((set_id.as_str(), gate::guard(&c.before, &c.after, &self.config.gate)?)))
            .collect::<Result<_>>()?;
        for (set_id, d) in &guarded {
            tracing::info!(job = %id, "regression set {set_id}: {}", d.reason());
            criteria.extend(set_criteria(set_id, d));
        }
        let regressed = regressions(&guarded);
        let passed_alone = decision.passed;
        decision.passed &= regressed.is_empty();
        let why = || {
            let own = (!passed_alone).then(|| decision.reason());
            own.into_iter().chain(regressed.iter().cloned()).collect::<Vec<_>>().join("; ")
        };
        if !decision.passed && self.config.enforce_gate {
            let as_expert = match start.expert {
                None if passed_alone => self.expert(spec, start, &held, &sets)?,
                _ => Err(String::new()),
            };
            return match as_expert {
                Ok((expert, summary)) => {
                    let mut experts = start.source.manifest.experts.clone();
                    experts.push(expert);
                    let reason = format!(
                        "job {id}: {} wins its own images but would regress an earlier domain; kept as an expert of {}",
                        spec.version, spec.source_version
                    );
                    self.activate_composite(spec, &start.source, experts, &reason, &summary, criteria)
                }
                Err(no) => {
                    let no = if no.is_empty() { no } else { format!("; not kept as an expert: {no}") };
                    self.append(id, JobState::Rejected, |e| {
                        e.message = format!("the gate kept {} inactive: {}{no}", spec.version, why());
                        e.gate = criteria.clone();
                    })?;
                    Ok(())
                }
            };
        }
        let reason = if decision.passed {
            format!("job {id}: passed the validation gate")
        } else {
            format!("job {id}: activated by --gate advisory although the gate failed: {}", why())
        };
        match &start.expert {
            None => self.activate(spec, &spec.version, &reason, criteria, String::new()),
            Some((i, _)) => {
                let mut experts = start.source.manifest.experts.clone();
                let replaced = std::mem::replace(&mut experts[*i].version, spec.version.clone());
                let summary = format!(", {} replacing its expert {replaced}", spec.version);
                self.activate_composite(spec, &start.source, experts, &reason, &summary, criteria)
            }
        }
    }

    /// Records the job's regression set, then activates `version` as the generation the job
    /// started from + 1 (SUPERSEDED where another was activated since).
    pub(super) fn activate(
        &self,
        spec: &JobSpec,
        version: &str,
        reason: &str,
        criteria: Vec<udapose_api::GateCriterion>,
        detail: String,
    ) -> Result<()> {
        let id = spec.job_id.as_str();
        // Whatever is activated, its domain is now one the service has seen.
        self.record_set(spec)?;
        let actor = format!("job:{id}");
        failpoint("before-activate");
        let activated =
            self.store.activate(&spec.category, version, &actor, reason, Some(spec.source_generation), Some(id));
        match activated {
            Ok(generation) => {
                self.registry.refresh();
                self.append(id, JobState::Activated, |e| {
                    e.message = format!("activated {version} as generation {generation}{detail}");
                    e.gate = criteria.clone();
                })?;
            }
            Err(StoreError::Conflict { found, .. }) => {
                tracing::warn!(job = %id, "activation conflict: generation {found} is active, the job started from {}", spec.source_generation);
                self.append(id, JobState::Superseded, |e| {
                    e.message = format!(
                        "passed the gate, but generation {found} was activated since the job started from {}",
                        spec.source_generation
                    );
                    e.gate = criteria.clone();
                })?;
            }
            Err(e) => return Err(e.into()),
        }
        Ok(())
    }

    /// The images of `images` that what the job adapted answers, as it and the candidate see
    /// them; `None` when fewer than the gate's minimum are left.
    fn compare(
        &self,
        images: Tensor,
        start: &Start,
        candidate: &Model,
        check: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    ) -> Result<Option<Compared>> {
        let (all, source) = (experts::stats(&images)?, start.model());
        let rows = experts::rows_of(&all, &start.source.manifest.experts, start.member());
        if rows.len() < self.config.gate.min_images {
            return Ok(None);
        }
        let images = if rows.len() == all.len() { images } else { experts::select(&images, &rows) };
        let before = gate::measure(source, &images, &self.config.gate, check)?;
        let after = gate::measure(candidate, &images, &self.config.gate, check)?;
        Ok(Some(Compared { before, after, stats: rows.iter().map(|&r| all[r]).collect() }))
    }

    /// Each of the category's regression sets compared (ARCHITECTURE.md "Validation gate"),
    /// candidate against the version the job started from, by id. A set too small to decide on,
    /// or answered by the experts, is skipped (logged).
    fn guard(
        &self,
        spec: &JobSpec,
        start: &Start,
        candidate: &Model,
        check: &mut dyn FnMut(usize, usize) -> ControlFlow<()>,
    ) -> Result<Vec<(String, Compared)>> {
        if !self.regression.config.enabled {
            return Ok(Vec::new());
        }
        let sets = self.regression.sets(&spec.category)?;
        let mut out = Vec::with_capacity(sets.len());
        for s in sets {
            let id = &s.set.set_id;
            let bytes = s.shas.iter().map(|sha| self.regression.read(&spec.category, id, sha).map_err(Into::into));
            let images = crops(bytes, &s.shas, start.source.manifest.crop, self.config.decode)?;
            match self.compare(images, start, candidate, check)? {
                Some(compared) => out.push((id.clone(), compared)),
                None => tracing::info!(job = %spec.job_id,
                    "regression set {id}: {} images, too few answered by {} to guard", s.shas.len(), start.name(spec)),
            }
        }
        Ok(out)
    }

    /// The job's held-out images become a regression set (before activation: see
    /// `regression.rs`), and the category's sets are thinned to their bound.
    pub(super) fn record_set(&self, spec: &JobSpec) -> Result<()> {
        if !self.regression.config.enabled {
            return Ok(());
        }
        let shas = self.regression.sample(&spec.held_out);
        let read = |sha: &str| self.buffer.read(&spec.category, sha);
        self.regression.record(&spec.category, &spec.job_id, &spec.version, &shas, read)?;
        self.regression.thin(&spec.category, &spec.job_id)?;
        Ok(())
    }

    /// Buffered images as the model's crops (N×3×H×W in [0, 1]).
    pub(super) fn images(&self, category: &str, shas: &[String], crop: [usize; 2]) -> Result<Tensor> {
        let bytes = shas
            .iter()
            .map(|sha| self.buffer.read(category, sha).with_context(|| format!("reading buffered image {sha}")));
        crops(bytes, shas, crop, self.config.decode)
    }
}

/// Encoded images as crops at the model's size (N×3×H×W in [0, 1]); `shas` name them in errors.
fn crops(
    bytes: impl Iterator<Item = Result<Vec<u8>>>,
    shas: &[String],
    crop: [usize; 2],
    limits: decode::DecodeLimits,
) -> Result<Tensor> {
    let [h, w] = crop;
    let mut pixels = Vec::with_capacity(shas.len() * 3 * h * w);
    for (bytes, sha) in bytes.zip(shas) {
        let decoded = decode::decode(&bytes?, limits).map_err(|e| anyhow!("image {sha}: {e}"))?;
        let image = Rgb8Image::new(&decoded.rgb8, decoded.width, decoded.height)?;
        pixels.extend(input::crop(&image, None, crop)?.pixels);
    }
    Ok(Tensor::from_slice(&pixels).view([shas.len() as i64, 3, h as i64, w as i64]))
}

pub(super) fn is_cancelled(e: &anyhow::Error) -> bool {
    matches!(e.downcast_ref::<EngineError>(), Some(EngineError::Cancelled))
}

/// A regression set's criteria as the job's events show them, named `<set>/<criterion>`.
pub(super) fn set_criteria<'a>(
    set_id: &'a str,
    d: &'a gate::Decision,
) -> impl Iterator<Item = udapose_api::GateCriterion> + 'a {
    d.criteria.iter().map(move |c| udapose_api::GateCriterion { name: format!("{set_id}/{}", c.name), ..criterion(c) })
}

/// Why each failing set failed.
pub(super) fn regressions(guarded: &[(&str, gate::Decision)]) -> Vec<String> {
    guarded
        .iter()
        .filter(|(_, d)| !d.passed)
        .map(|(set_id, d)| format!("it would regress on regression set {set_id}: {}", d.reason()))
        .collect()
}

/// A gate criterion as the job's events show it.
pub(super) fn criterion(c: &gate::Criterion) -> udapose_api::GateCriterion {
    let gate::Criterion { name, active, candidate, threshold, passed, detail } = c.clone();
    udapose_api::GateCriterion { name, active, candidate, threshold, passed, detail }
}
