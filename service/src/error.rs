//! The service's errors and how each maps to gRPC and HTTP (ARCHITECTURE.md "Service contract").

use std::time::Duration;

/// Why a request was not answered. The message is shown to the caller as is.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ApiError {
    /// Undecodable or too small image, bad box, bad category name: INVALID_ARGUMENT / 400.
    #[error("{0}")]
    InvalidArgument(String),
    /// Unknown category: NOT_FOUND / 404.
    #[error("{0}")]
    NotFound(String),
    /// Request over the size limit: RESOURCE_EXHAUSTED / 413.
    #[error("{0}")]
    TooLarge(String),
    /// Queue full or model not loaded: UNAVAILABLE / 503, retry after the hint.
    #[error("{message}")]
    Unavailable { message: String, retry_after: Duration },
    /// Missing or wrong token: UNAUTHENTICATED / 401.
    #[error("{0}")]
    Unauthenticated(String),
    /// A token without the role: PERMISSION_DENIED / 403.
    #[error("{0}")]
    PermissionDenied(String),
    /// A stale `expected_generation` or a lost activation race: ABORTED / 409.
    #[error("{0}")]
    Aborted(String),
    /// The request cannot be served in the current state (nothing to roll back to, too few
    /// buffered images): FAILED_PRECONDITION / 400.
    #[error("{0}")]
    FailedPrecondition(String),
    /// The deadline passed before the estimate started: DEADLINE_EXCEEDED / 504.
    #[error("{0}")]
    DeadlineExceeded(String),
    /// An HTTP method the route does not take: UNIMPLEMENTED / 405.
    #[error("{0}")]
    MethodNotAllowed(String),
    /// A bug or a broken model: INTERNAL / 500.
    #[error("{0}")]
    Internal(String),
}

impl ApiError {
    /// The gRPC code's canonical name, used in JSON bodies and metrics labels.
    pub fn code_name(&self) -> &'static str {
        match self {
            ApiError::InvalidArgument(_) => "INVALID_ARGUMENT",
            ApiError::NotFound(_) => "NOT_FOUND",
            ApiError::TooLarge(_) => "RESOURCE_EXHAUSTED",
            ApiError::Unavailable { .. } => "UNAVAILABLE",
            ApiError::Unauthenticated(_) => "UNAUTHENTICATED",
            ApiError::PermissionDenied(_) => "PERMISSION_DENIED",
            ApiError::Aborted(_) => "ABORTED",
            ApiError::FailedPrecondition(_) => "FAILED_PRECONDITION",
            ApiError::DeadlineExceeded(_) => "DEADLINE_EXCEEDED",
            ApiError::MethodNotAllowed(_) => "UNIMPLEMENTED",
            ApiError::Internal(_) => "INTERNAL",
        }
    }

    pub fn http_status(&self) -> u16 {
        match self {
            ApiError::InvalidArgument(_) => 400,
            ApiError::NotFound(_) => 404,
            ApiError::TooLarge(_) => 413,
            ApiError::Unavailable { .. } => 503,
            ApiError::Unauthenticated(_) => 401,
            ApiError::PermissionDenied(_) => 403,
            ApiError::Aborted(_) => 409,
            ApiError::FailedPrecondition(_) => 400,
            ApiError::DeadlineExceeded(_) => 504,
            ApiError::MethodNotAllowed(_) => 405,
            ApiError::Internal(_) => 500,
        }
    }

    pub fn retry_after(&self) -> Option<Duration> {
        match self {
            ApiError::Unavailable { retry_after, .. } => Some(*retry_after),
            _ => None,
        }
    }

    pub fn unavailable(message: impl Into<String>) -> Self {
        ApiError::Unavailable { message: message.into(), retry_after: Duration::from_secs(1) }
    }
}

impl From<udapose_engine::EngineError> for ApiError {
    /// The engine reports bad inputs (image too small, bad box) as typed errors.
    fn from(e: udapose_engine::EngineError) -> Self {
        use udapose_engine::EngineError as E;
        match e {
            E::EmptyImage { .. } | E::InvalidInput(_) => ApiError::InvalidArgument(e.to_string()),
            other => ApiError::Internal(other.to_string()),
        }
    }
}

impl From<crate::store::StoreError> for ApiError {
    fn from(e: crate::store::StoreError) -> Self {
        use crate::store::StoreError as S;
        match e {
            S::UnknownVersion { .. } => ApiError::NotFound(e.to_string()),
            S::Conflict { .. } => ApiError::Aborted(e.to_string()),
            S::NoPrevious(_) => ApiError::FailedPrecondition(e.to_string()),
            // The store (S3 on the network) may come back: a retry is worth it.
            S::Object { .. } => ApiError::unavailable(e.to_string()),
            S::Io { .. } | S::Corrupt { .. } | S::Url { .. } | S::NotCreateOnly(_) => ApiError::Internal(e.to_string()),
        }
    }
}
