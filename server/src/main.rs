//! `udapose-server`: serves the udapose API over gRPC and HTTP.
//!
//! Foundation stage: no model loader exists yet, so the server only discovers
//! model directories, reports them as not loadable, and is never ready.

mod catalog;
mod grpc;
mod http;

use std::{net::SocketAddr, path::PathBuf, sync::Arc};

use anyhow::{Context, Result};
use clap::Parser;
use tokio::{net::TcpListener, sync::watch};
use tracing_subscriber::EnvFilter;

use crate::catalog::Catalog;

/// udapose pose-estimation service: gRPC and HTTP on separate addresses.
///
/// This build cannot load models yet: it lists the model directories under
/// --models, reports them as not loaded, and /readyz answers 503.
#[derive(Debug, Parser)]
#[command(version)]
struct Args {
    /// Address of the HTTP API (health, readiness, /v1/models).
    #[arg(long, default_value = "127.0.0.1:8080")]
    http_addr: SocketAddr,
    /// Address of the gRPC API (udapose.v1, grpc.health.v1, reflection).
    #[arg(long, default_value = "127.0.0.1:50051")]
    grpc_addr: SocketAddr,
    /// Directory holding one `<category>/manifest.json` per model.
    #[arg(long, value_name = "DIR", default_value = "models")]
    models: PathBuf,
    /// Largest accepted request body (HTTP) or message (gRPC), in bytes.
    #[arg(long, value_name = "BYTES", default_value_t = 16 * 1024 * 1024,
          value_parser = clap::value_parser!(u64).range(1..=u32::MAX as u64))]
    max_request_bytes: u64,
}

#[tokio::main]
async fn main() -> Result<()> {
    init_tracing();
    let args = Args::parse();
    let catalog = Arc::new(Catalog::scan(&args.models)?);
    catalog.log_summary();
    let max_bytes = usize::try_from(args.max_request_bytes).context("--max-request-bytes")?;

    // Bind both before serving either, so a bad address fails fast and both
    // listen once the process reports healthy.
    let http_listener = bind(args.http_addr, "HTTP").await?;
    let grpc_listener = bind(args.grpc_addr, "gRPC").await?;
    let (stop_tx, stop_rx) = watch::channel(false);
    tokio::spawn(async move {
        shutdown_signal().await;
        tracing::info!("shutdown requested; finishing in-flight requests");
        let _ = stop_tx.send(true);
    });

    tokio::try_join!(
        http::serve(http_listener, catalog.clone(), max_bytes, stopped(stop_rx.clone())),
        grpc::serve(grpc_listener, catalog, max_bytes, stopped(stop_rx)),
    )?;
    tracing::info!("stopped");
    Ok(())
}

/// Logs to stdout; `RUST_LOG` overrides the default `info` level.
fn init_tracing() {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    tracing_subscriber::fmt().with_env_filter(filter).init();
}

async fn bind(addr: SocketAddr, what: &str) -> Result<TcpListener> {
    let listener = TcpListener::bind(addr).await.with_context(|| format!("binding the {what} listener on {addr}"))?;
    let local = listener.local_addr().context("reading the bound address")?;
    tracing::info!("{what} listening on {local}");
    Ok(listener)
}

/// Resolves once shutdown has been requested.
async fn stopped(mut rx: watch::Receiver<bool>) {
    // An error means the sender is gone, which also means stop.
    let _ = rx.wait_for(|stop| *stop).await;
}

/// Resolves on SIGINT (Ctrl-C) or, on Unix, SIGTERM (what Kubernetes sends).
async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!("cannot listen for SIGINT: {e}");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!("cannot listen for SIGTERM: {e}");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {}
        () = term => {}
    }
}
