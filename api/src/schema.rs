//! The OpenAPI schemas of every type above, derived (not written) so the document the server
//! serves at `/openapi.json` cannot disagree with the JSON it sends.

use serde::{Deserialize, Serialize};
use utoipa::{OpenApi, ToSchema};

use crate::{
    ActivationEntry, BoxAnswer, EstimateAnswer, GateCriterion, HypothesisAnswer, JobEvent, JobList, JobState, JobView,
    ModelDescription, ModelList, ModelSummary, PoseAnswer, RegressionSet, RegressionSets, SetKind, Timings,
    VersionView, Versions,
};

/// Every error answer of the HTTP API.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[schema(as = Error)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ErrorDetail {
    /// The gRPC code's name, e.g. INVALID_ARGUMENT.
    pub code: String,
    pub message: String,
}

impl ErrorBody {
    pub fn new(code: impl Into<String>, message: impl Into<String>) -> Self {
        ErrorBody { error: ErrorDetail { code: code.into(), message: message.into() } }
    }
}

#[derive(OpenApi)]
#[openapi(components(schemas(
    PoseAnswer,
    HypothesisAnswer,
    BoxAnswer,
    Timings,
    EstimateAnswer,
    ErrorBody,
    ErrorDetail,
    ModelSummary,
    ModelList,
    ModelDescription,
    JobState,
    GateCriterion,
    JobEvent,
    JobView,
    JobList,
    VersionView,
    ActivationEntry,
    Versions,
    SetKind,
    RegressionSet,
    RegressionSets,
)))]
struct Contract;

/// `components.schemas` of the OpenAPI 3.1 document, by schema name.
pub fn schemas() -> serde_json::Value {
    let schemas = Contract::openapi().components.map(|c| c.schemas).unwrap_or_default();
    serde_json::to_value(schemas).unwrap_or_default()
}
