//! A job's records: what it runs on and its settings; its history and how the API shows it
//! (`JobEvent`, `JobView`) are the contract's types, persisted as they are shown.

use std::time::Duration;

use serde::{Deserialize, Serialize};
use tch::Device;
pub use udapose_api::{JobEvent, JobState, JobView};
use udapose_engine::{
    adapt::AdaptConfig,
    gate::{self, GateConfig},
};

use super::ExpertConfig;
use crate::{buffer::AckStatus, decode::DecodeLimits, regression::RegressionConfig};

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

/// Why a target image was not stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum Rejection {
    /// It does not decode, or is too small.
    InvalidImage,
    /// The category's buffer is at capacity (worth resending once a job has used images).
    BufferFull,
    /// The store could not keep it.
    Storage,
}

impl Rejection {
    /// The code word the ack's `reason` starts with.
    pub fn code(self) -> &'static str {
        match self {
            Rejection::InvalidImage => "INVALID_IMAGE",
            Rejection::BufferFull => "BUFFER_FULL",
            Rejection::Storage => "STORAGE",
        }
    }
}

/// The answer to one streamed target image.
#[derive(Clone, Debug, Serialize)]
pub struct TargetAck {
    pub sha256: String,
    pub status: AckStatus,
    /// Set exactly when `status` is REJECTED.
    pub rejection: Option<Rejection>,
    /// For a rejection: its code word, ": " and an explanation.
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
    /// The bounds of the regression sets the gate guards.
    pub regression: RegressionConfig,
    /// The bounds of per-domain experts.
    pub experts: ExpertConfig,
    pub device: Device,
    pub decode: DecodeLimits,
    /// Whether this process runs jobs (`--role all|adapt`) or only records and watches them.
    pub runs_jobs: bool,
    /// Whether a job that fails the gate stays inactive (`--gate enforce`) or is activated with
    /// the verdict in its activation's reason (`--gate advisory`).
    pub enforce_gate: bool,
    /// How often the store is read for jobs and images other processes wrote.
    pub poll: Duration,
    /// Threads of the jobs' own rayon pool (adaptation and gate solves run there, never on the
    /// global pool that serving solves use).
    pub threads: usize,
    /// How much lower than serving's the OS priority of the job's threads is (a nice
    /// increment, 0..=19; 0: the same). The job runs in its pool, so this covers its training,
    /// its solves and the gate.
    pub nice: i32,
}

/// Whether an image (by its hex sha256) is held out for the gate: the engine's bucket rule.
pub(super) fn held_out(sha_hex: &str) -> bool {
    let bytes: Vec<u8> =
        (0..2).filter_map(|i| sha_hex.get(2 * i..2 * i + 2).and_then(|h| u8::from_str_radix(h, 16).ok())).collect();
    gate::held_out(&bytes)
}

/// The job's QUEUED event; `max_rounds` is what its run will allow.
pub(super) fn first_event(spec: &JobSpec, max_rounds: u32) -> JobEvent {
    JobEvent {
        job_id: spec.job_id.clone(),
        seq: 0,
        state: JobState::Queued,
        time: spec.created,
        message: String::new(),
        round: 0,
        max_rounds,
        fired_ratio: 0.0,
        pose_change_median_deg: None,
        images_used: spec.train.len() as u32,
        images_held_out: spec.held_out.len() as u32,
        eta_seconds: 0.0,
        gate: Vec::new(),
        version: String::new(),
    }
}
