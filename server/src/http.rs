//! HTTP API (axum): health, readiness and the model list.

use std::{future::Future, sync::Arc};

use anyhow::{Context, Result};
use axum::{
    Json, Router,
    extract::{DefaultBodyLimit, State},
    http::StatusCode,
    routing::get,
};
use serde_json::{Value, json};
use tokio::net::TcpListener;

use crate::catalog::Catalog;

/// Serves until `stop` resolves, then lets in-flight requests finish.
pub async fn serve(
    listener: TcpListener,
    catalog: Arc<Catalog>,
    max_request_bytes: usize,
    stop: impl Future<Output = ()> + Send + 'static,
) -> Result<()> {
    axum::serve(listener, router(catalog, max_request_bytes)).with_graceful_shutdown(stop).await.context("serving HTTP")
}

fn router(catalog: Arc<Catalog>, max_request_bytes: usize) -> Router {
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/v1/models", get(list_models))
        // axum's own default (2 MB) is below the documented 16 MiB.
        .layer(DefaultBodyLimit::max(max_request_bytes))
        .with_state(catalog)
}

/// Liveness: the process answers; says nothing about models.
async fn healthz() -> Json<Value> {
    Json(json!({ "status": "ok" }))
}

/// Readiness: 200 only when every configured model is loaded.
async fn readyz(State(catalog): State<Arc<Catalog>>) -> (StatusCode, Json<Value>) {
    let readiness = catalog.readiness();
    let (code, status) =
        if readiness.ready { (StatusCode::OK, "ready") } else { (StatusCode::SERVICE_UNAVAILABLE, "not_ready") };
    (code, Json(json!({ "status": status, "reason": readiness.reason })))
}

async fn list_models(State(catalog): State<Arc<Catalog>>) -> Json<Value> {
    Json(json!({ "models": catalog.models() }))
}
