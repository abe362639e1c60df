//! The udapose JSON contract, written once: the HTTP API serialises these types, the OpenAPI
//! document's schemas are derived from them (utoipa reads the same serde attributes), and the
//! `udapose` CLI converts the gRPC messages it receives into them before printing `--json`.
//! So the three cannot drift apart; the gRPC messages (proto/udapose/v1) carry the same fields.

pub mod estimate;
pub mod jobs;
pub mod models;
mod schema;
#[cfg(test)]
mod tests;

pub use estimate::{BoxAnswer, EstimateAnswer, HypothesisAnswer, PoseAnswer, Timings};
pub use jobs::{
    ActivationEntry, GateCriterion, JobEvent, JobList, JobState, JobView, RegressionSet, RegressionSets, SetKind,
    UnknownState, VersionView, Versions,
};
pub use models::{ModelDescription, ModelList, ModelSummary};
pub use schema::{ErrorBody, ErrorDetail, schemas};
