//! Adaptation jobs and model versions as the API shows them (`/v1/jobs…`,
//! `/v1/models/{category}/versions`, `AdaptationService`, `ModelService.ListVersions`). A job's
//! events are also what the service persists as the job's log.

use serde::{Deserialize, Serialize};
use udapose_proto::v1 as pb;
use utoipa::ToSchema;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
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

/// A gRPC job state this build does not know (a newer server), or `JOB_STATE_UNSPECIFIED`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UnknownState(pub i32);

impl std::fmt::Display for UnknownState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "job state {} is not one this client knows (is the server newer?)", self.0)
    }
}

impl std::error::Error for UnknownState {}

impl From<JobState> for pb::JobState {
    fn from(s: JobState) -> Self {
        match s {
            JobState::Queued => pb::JobState::Queued,
            JobState::Running => pb::JobState::Running,
            JobState::Validating => pb::JobState::Validating,
            JobState::Activated => pb::JobState::Activated,
            JobState::Rejected => pb::JobState::Rejected,
            JobState::Superseded => pb::JobState::Superseded,
            JobState::Failed => pb::JobState::Failed,
            JobState::Cancelled => pb::JobState::Cancelled,
        }
    }
}

impl TryFrom<i32> for JobState {
    type Error = UnknownState;

    /// From a gRPC message's `state` field.
    fn try_from(state: i32) -> Result<Self, UnknownState> {
        Ok(match pb::JobState::try_from(state).map_err(|_| UnknownState(state))? {
            pb::JobState::Queued => JobState::Queued,
            pb::JobState::Running => JobState::Running,
            pb::JobState::Validating => JobState::Validating,
            pb::JobState::Activated => JobState::Activated,
            pb::JobState::Rejected => JobState::Rejected,
            pb::JobState::Superseded => JobState::Superseded,
            pb::JobState::Failed => JobState::Failed,
            pb::JobState::Cancelled => JobState::Cancelled,
            pb::JobState::Unspecified => return Err(UnknownState(state)),
        })
    }
}

/// One criterion of the gate: both models' values and the threshold the candidate had to reach.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct GateCriterion {
    /// "flip_consistency", "score_margin" or "pose_diversity".
    pub name: String,
    pub active: f64,
    pub candidate: f64,
    pub threshold: f64,
    pub passed: bool,
    pub detail: String,
}

/// One step of a job's history (the job's state is its last event's).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct JobEvent {
    pub job_id: String,
    /// 0, 1, 2, ... in order.
    pub seq: u64,
    pub state: JobState,
    /// Seconds since the Unix epoch.
    pub time: f64,
    /// What happened, for people.
    pub message: String,
    /// EM round (1-based; 0 before the first) and the most rounds the job may take.
    pub round: u32,
    pub max_rounds: u32,
    /// Mean fired-vertex ratio at the pseudo-poses after the round.
    pub fired_ratio: f64,
    /// Median change of the pseudo-poses from the previous round, degrees (`null` in round 1).
    pub pose_change_median_deg: Option<f64>,
    pub images_used: u32,
    pub images_held_out: u32,
    /// Estimated seconds to the end of the training (0 when unknown or done).
    pub eta_seconds: f64,
    /// The gate's criteria (VALIDATING and after).
    pub gate: Vec<GateCriterion>,
    /// The candidate version, once saved (empty before).
    pub version: String,
}

/// An adaptation job.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Job)]
pub struct JobView {
    pub job_id: String,
    pub category: String,
    pub state: JobState,
    /// The version the job adapted and the activation generation it started from.
    pub source_version: String,
    pub source_generation: u64,
    /// The candidate version (empty until saved).
    pub version: String,
    pub created: f64,
    pub updated: f64,
    pub images_used: u32,
    pub images_held_out: u32,
    /// Why it ended as it did (REJECTED: the failed criteria; FAILED: the error).
    pub reason: String,
    /// The caller's idempotency key, if it gave one (empty otherwise).
    pub client_job_id: String,
    pub last_event: JobEvent,
}

/// Jobs, newest first.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Jobs)]
pub struct JobList {
    pub jobs: Vec<JobView>,
}

/// One complete version of a category in the store.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Version)]
pub struct VersionView {
    pub version: String,
    /// The version its manifest says it was trained as.
    pub trained_as: String,
    pub active: bool,
    /// The job that made it (`null` for a seed).
    pub job_id: Option<String>,
}

/// One entry of a category's activation log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Activation)]
pub struct ActivationEntry {
    pub category: String,
    pub generation: u64,
    pub version: String,
    /// What a rollback from this entry re-activates (`null`: nothing).
    pub previous: Option<String>,
    pub actor: String,
    pub reason: String,
    /// Seconds since the Unix epoch.
    pub time: u64,
    /// The job whose version this activated, if one did (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job_id: Option<String>,
}

/// A category's versions and its activation log, newest first.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Versions {
    pub versions: Vec<VersionView>,
    pub activations: Vec<ActivationEntry>,
}

/// What a regression set holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum SetKind {
    /// The held-out images of an activated job.
    Job,
    /// Images an operator uploaded with the anchor flag.
    Anchor,
}

/// Images the gate guards: a candidate must not get worse on them beyond noise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct RegressionSet {
    /// "anchor", or the id of the job whose held-out images these are.
    pub set_id: String,
    pub kind: SetKind,
    /// The job's activated version (empty for the anchor set).
    pub version: String,
    /// Seconds since the Unix epoch.
    pub created: f64,
    pub images: u32,
}

/// A category's regression sets, oldest first.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct RegressionSets {
    pub sets: Vec<RegressionSet>,
}

impl From<RegressionSet> for pb::RegressionSet {
    fn from(s: RegressionSet) -> Self {
        let kind = match s.kind {
            SetKind::Job => "JOB",
            SetKind::Anchor => "ANCHOR",
        };
        pb::RegressionSet {
            set_id: s.set_id,
            kind: kind.into(),
            version: s.version,
            created: s.created,
            images: s.images,
        }
    }
}

impl TryFrom<pb::RegressionSet> for RegressionSet {
    type Error = String;

    fn try_from(s: pb::RegressionSet) -> Result<Self, String> {
        let kind = match s.kind.as_str() {
            "JOB" => SetKind::Job,
            "ANCHOR" => SetKind::Anchor,
            other => return Err(format!("regression set kind {other:?} is not one this client knows")),
        };
        Ok(RegressionSet { set_id: s.set_id, kind, version: s.version, created: s.created, images: s.images })
    }
}

fn some_if_set(s: String) -> Option<String> {
    (!s.is_empty()).then_some(s)
}

impl From<GateCriterion> for pb::GateCriterion {
    fn from(c: GateCriterion) -> Self {
        let GateCriterion { name, active, candidate, threshold, passed, detail } = c;
        pb::GateCriterion { name, active, candidate, threshold, passed, detail }
    }
}

impl From<pb::GateCriterion> for GateCriterion {
    fn from(c: pb::GateCriterion) -> Self {
        let pb::GateCriterion { name, active, candidate, threshold, passed, detail } = c;
        GateCriterion { name, active, candidate, threshold, passed, detail }
    }
}

impl From<JobEvent> for pb::JobEvent {
    fn from(e: JobEvent) -> Self {
        pb::JobEvent {
            job_id: e.job_id,
            seq: e.seq,
            state: pb::JobState::from(e.state) as i32,
            time: e.time,
            message: e.message,
            round: e.round,
            max_rounds: e.max_rounds,
            fired_ratio: e.fired_ratio,
            pose_change_median_deg: e.pose_change_median_deg,
            images_used: e.images_used,
            images_held_out: e.images_held_out,
            eta_seconds: e.eta_seconds,
            gate: e.gate.into_iter().map(Into::into).collect(),
            version: e.version,
        }
    }
}

impl TryFrom<pb::JobEvent> for JobEvent {
    type Error = UnknownState;

    fn try_from(e: pb::JobEvent) -> Result<Self, UnknownState> {
        Ok(JobEvent {
            job_id: e.job_id,
            seq: e.seq,
            state: JobState::try_from(e.state)?,
            time: e.time,
            message: e.message,
            round: e.round,
            max_rounds: e.max_rounds,
            fired_ratio: e.fired_ratio,
            pose_change_median_deg: e.pose_change_median_deg,
            images_used: e.images_used,
            images_held_out: e.images_held_out,
            eta_seconds: e.eta_seconds,
            gate: e.gate.into_iter().map(Into::into).collect(),
            version: e.version,
        })
    }
}

impl From<JobView> for pb::Job {
    fn from(j: JobView) -> Self {
        pb::Job {
            job_id: j.job_id,
            category: j.category,
            state: pb::JobState::from(j.state) as i32,
            source_version: j.source_version,
            source_generation: j.source_generation,
            version: j.version,
            created: j.created,
            updated: j.updated,
            images_used: j.images_used,
            images_held_out: j.images_held_out,
            reason: j.reason,
            client_job_id: j.client_job_id,
            last_event: Some(j.last_event.into()),
        }
    }
}

impl TryFrom<pb::Job> for JobView {
    type Error = UnknownState;

    fn try_from(j: pb::Job) -> Result<Self, UnknownState> {
        let state = JobState::try_from(j.state)?;
        let last_event = match j.last_event {
            Some(e) => JobEvent::try_from(e)?,
            // Every server sends one; an empty event of the job's state keeps the shape.
            None => JobEvent {
                job_id: j.job_id.clone(),
                seq: 0,
                state,
                time: j.updated,
                message: String::new(),
                round: 0,
                max_rounds: 0,
                fired_ratio: 0.0,
                pose_change_median_deg: None,
                images_used: j.images_used,
                images_held_out: j.images_held_out,
                eta_seconds: 0.0,
                gate: Vec::new(),
                version: j.version.clone(),
            },
        };
        Ok(JobView {
            job_id: j.job_id,
            category: j.category,
            state,
            source_version: j.source_version,
            source_generation: j.source_generation,
            version: j.version,
            created: j.created,
            updated: j.updated,
            images_used: j.images_used,
            images_held_out: j.images_held_out,
            reason: j.reason,
            client_job_id: j.client_job_id,
            last_event,
        })
    }
}

impl From<VersionView> for pb::VersionInfo {
    fn from(v: VersionView) -> Self {
        pb::VersionInfo {
            version: v.version,
            trained_as: v.trained_as,
            active: v.active,
            job_id: v.job_id.unwrap_or_default(),
        }
    }
}

impl From<pb::VersionInfo> for VersionView {
    fn from(v: pb::VersionInfo) -> Self {
        VersionView { version: v.version, trained_as: v.trained_as, active: v.active, job_id: some_if_set(v.job_id) }
    }
}

impl From<ActivationEntry> for pb::ActivationEntry {
    fn from(a: ActivationEntry) -> Self {
        pb::ActivationEntry {
            category: a.category,
            generation: a.generation,
            version: a.version,
            previous: a.previous.unwrap_or_default(),
            actor: a.actor,
            reason: a.reason,
            time: a.time,
            job_id: a.job_id.unwrap_or_default(),
        }
    }
}

impl From<pb::ActivationEntry> for ActivationEntry {
    fn from(a: pb::ActivationEntry) -> Self {
        ActivationEntry {
            category: a.category,
            generation: a.generation,
            version: a.version,
            previous: some_if_set(a.previous),
            actor: a.actor,
            reason: a.reason,
            time: a.time,
            job_id: some_if_set(a.job_id),
        }
    }
}

impl From<Versions> for pb::ListVersionsResponse {
    fn from(v: Versions) -> Self {
        pb::ListVersionsResponse {
            versions: v.versions.into_iter().map(Into::into).collect(),
            activations: v.activations.into_iter().map(Into::into).collect(),
        }
    }
}

impl From<pb::ListVersionsResponse> for Versions {
    fn from(v: pb::ListVersionsResponse) -> Self {
        Versions {
            versions: v.versions.into_iter().map(Into::into).collect(),
            activations: v.activations.into_iter().map(Into::into).collect(),
        }
    }
}
