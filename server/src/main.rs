//! `udapose-server`: serves pose estimates over gRPC and HTTP from a per-category model
//! registry, with inference workers that batch requests (ARCHITECTURE.md).

// serde_json's `json!` recurses once per token tree; the OpenAPI document needs more than 128.
#![recursion_limit = "256"]

mod grpc;
mod http;
mod openapi;
mod tls;

use std::{net::SocketAddr, path::PathBuf, sync::Arc, time::Duration};

use anyhow::{Context, Result, bail};
use clap::Parser;
use tokio::{net::TcpListener, sync::watch};
use tracing_subscriber::EnvFilter;

use udapose_engine::{adapt::AdaptConfig, gate::GateConfig};

use udapose_service::{
    auth::Tokens,
    buffer::Buffer,
    decode::DecodeLimits,
    jobs::{ExpertConfig, Jobs, JobsConfig},
    metrics::Metrics,
    registry::Registry,
    regression::RegressionConfig,
    service::{Limits, Service},
    store::{S3Options, Store},
    worker::WorkerConfig,
};

use crate::tls::{Listener, TlsFiles, TlsListener};

/// udapose pose-estimation service: gRPC and HTTP on separate addresses.
#[derive(Debug, Parser)]
#[command(version)]
struct Args {
    /// Address of the HTTP API.
    #[arg(long, default_value = "127.0.0.1:8080")]
    http_addr: SocketAddr,
    /// Address of the gRPC API (udapose.v1, grpc.health.v1, reflection).
    #[arg(long, default_value = "127.0.0.1:50051")]
    grpc_addr: SocketAddr,
    /// Seed models: one `<category>/manifest.json` per model, imported read-only into the store.
    #[arg(long, value_name = "DIR", default_value = "models")]
    models: PathBuf,
    /// The service's state (model versions, activation log, target buffer, jobs): a directory
    /// (`file:///path` or a path; created if missing) or `s3://bucket/prefix`.
    #[arg(long, value_name = "URL", default_value = "state")]
    store: String,
    /// S3-compatible endpoint (MinIO, Ceph, ...); credentials come from AWS_ACCESS_KEY_ID and
    /// AWS_SECRET_ACCESS_KEY.
    #[arg(long, env = "UDAPOSE_S3_ENDPOINT", value_name = "URL")]
    s3_endpoint: Option<String>,
    /// S3 region (default: AWS_REGION, else us-east-1).
    #[arg(long, env = "AWS_REGION")]
    s3_region: Option<String>,
    /// Allow a plain-HTTP S3 endpoint (a store on loopback or inside a cluster).
    #[arg(long)]
    s3_allow_http: bool,
    /// Where versions from a remote store are downloaded to be loaded (default: the system's
    /// temporary directory). The 3 last used per category are kept, older ones deleted.
    #[arg(long, value_name = "DIR")]
    cache_dir: Option<PathBuf>,
    /// `all`: one process does everything; `serve`: answers estimates and accepts target
    /// images, never runs adaptation jobs; `adapt`: runs the job queue (one per store).
    #[arg(long, value_enum, default_value = "all")]
    role: Role,
    /// `enforce`: a job that fails the validation gate stays inactive; `advisory`: it is
    /// activated anyway, with the gate's verdict in the activation log (for operators who
    /// validate elsewhere).
    #[arg(long, value_enum, default_value = "enforce")]
    gate: GatePolicy,
    /// Neither keep regression sets nor guard them: each job is judged on its own held-out
    /// images alone, so a job may give back what earlier ones won (for comparisons:
    /// `udapose-bench continual`'s "independent" row).
    #[arg(long)]
    no_regression_sets: bool,
    /// Per-domain experts a category's version may hold: a job that wins its own images but
    /// would regress an earlier domain is kept as an expert for images like its own (each one
    /// more model in every worker's memory; 0: rejected instead).
    #[arg(long, default_value_t = ExpertConfig::default().max)]
    max_experts: usize,
    /// The target check: the share of visible vertices that must fire to the active model on a
    /// job's images at its first round, else the job is REJECTED as "not this category" before
    /// any training (0 turns it off). Default: each model's own, measured for it (its
    /// manifest's min_target_fired), else 0.02; set, it holds for every category. Lower it for
    /// a domain far from the source (measured shares: reports/target-check.md).
    #[arg(long, value_name = "SHARE")]
    min_target_fired: Option<f64>,
    /// How much the median score margin on a job's held-out images must rise for the gate to
    /// pass it (negative: how much it may fall; see GateConfig::margin_gain for the default).
    #[arg(long, default_value_t = GateConfig::default().margin_gain, allow_negative_numbers = true)]
    margin_gain: f64,
    /// How many paired standard errors flip consistency and the mean score margin may fall on
    /// an earlier job's regression set before the gate refuses a candidate (0: any fall).
    #[arg(long, value_name = "SE", default_value_t = GateConfig::default().regression_se)]
    regression_se: f64,
    /// Largest accepted request body (HTTP) or message (gRPC), in bytes.
    #[arg(long, value_name = "BYTES", default_value_t = 16 * 1024 * 1024,
          value_parser = clap::value_parser!(u64).range(1..=u32::MAX as u64))]
    max_request_bytes: u64,
    /// Largest decoded image width or height, in pixels.
    #[arg(long, value_name = "PX", default_value_t = 8192)]
    max_image_side: u32,
    /// Most memory the estimates' images may hold at once, decoding or waiting for a worker
    /// (MiB); more wait for room until their deadline. An 8192×8192 RGBA PNG needs 448 MiB.
    #[arg(long, value_name = "MIB", default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..=1 << 22))]
    max_decoded_mib: u64,
    /// Inference worker threads per category, each with its own model copy (0: one per core, at
    /// most 4). Workers of one libtorch thread each beat one worker of every core under load
    /// (2-core Xeon, 16 clients: 54.8 against 40.5 req/s) and lose on a lone stream (p50 38
    /// against 32 ms); and a server whose workers keep every core busy leaves an adaptation job,
    /// at its lower priority, almost nothing (one round in 480 s under 4 clients, against five in
    /// 80 s with one worker): reports/service.md, reports/service-workers.md.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(0..=64))]
    workers: u32,
    /// Most crops per backbone pass: the crops of concurrent requests (and a request's boxes)
    /// share passes. An image's answer does not depend on it nor on the load (CPU passes hold
    /// at most 15 crops, the range where libtorch gives every crop the same features).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=256))]
    max_batch: u32,
    /// How long the first request of a batch waits for others, in milliseconds, when others are
    /// already queued behind it (a lone request goes at once).
    #[arg(long, default_value_t = 5)]
    max_delay_ms: u64,
    /// Requests that may wait per category; beyond it: UNAVAILABLE / 503 at once.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    queue_depth: u32,
    /// How often to re-read the store for versions activated, jobs run and images buffered by
    /// other processes, in seconds (0: never; one process alone needs none).
    #[arg(long, alias = "poll-store-secs", value_name = "SECS", default_value_t = 5)]
    poll: u64,
    /// Deadline of a request that brings none, in milliseconds.
    #[arg(long, default_value_t = 30_000)]
    timeout_ms: u64,
    /// libtorch intra-op threads of each inference worker (0: the cores divided among a
    /// category's workers, at least 1). On a shared or loaded host spinning threads fight the
    /// other work (measured: 560 ms a backbone pass with one per core on a loaded host, 170 ms
    /// with 1), so give the server fewer there.
    #[arg(long, default_value_t = 0)]
    torch_threads: i32,
    /// Bearer token with the admin role (required on everything but /, /openapi.json, health,
    /// readiness and /metrics).
    #[arg(long, env = "UDAPOSE_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// File of `<role> <token>` lines (roles: read, write, admin).
    #[arg(long, value_name = "FILE")]
    token_file: Option<PathBuf>,
    /// Serve TLS on both listeners with this PEM certificate chain (needs --tls-key).
    #[arg(long, value_name = "PEM", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert.
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Target images each category's adaptation buffer holds; beyond it an image is refused
    /// (REJECTED with BUFFER_FULL) until a job has used some.
    #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u32).range(1..))]
    buffer_capacity: u32,
    /// Unclaimed buffered images of a category that start an adaptation job on their own
    /// (`StartJob` starts one sooner).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..))]
    adapt_min_images: u32,
    /// Threads of the adaptation job's own solver pool (0: half the cores, at least 1). Serving
    /// solves keep the global pool, so they never queue behind a job's batch of solves.
    #[arg(long, default_value_t = 0)]
    job_threads: usize,
    /// How much lower the adaptation job's threads' OS priority is than serving's (a nice
    /// increment; 0: the same). Requests get the cores first while a job runs; an idle server
    /// still adapts at full speed.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(i32).range(0..=19))]
    job_nice: i32,
    /// Listen on non-loopback addresses without a token (otherwise refused).
    #[arg(long)]
    allow_unauthenticated: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum Role {
    All,
    Serve,
    Adapt,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum GatePolicy {
    Enforce,
    Advisory,
}

#[tokio::main]
async fn main() -> Result<()> {
    init_tracing();
    let args = Args::parse();
    let tokens = tokens(&args)?;
    let cores = udapose_engine::runtime::cores();
    let workers = if args.workers > 0 { args.workers as usize } else { cores.min(4) };
    let torch_threads = if args.torch_threads > 0 { args.torch_threads as usize } else { (cores / workers).max(1) };
    tch::set_num_threads(torch_threads as i32);
    let runtime = udapose_engine::runtime::RuntimeInfo::detect();
    tracing::info!(device = ?runtime.device(), workers, torch_threads, rayon_threads = runtime.rayon_threads, "runtime");
    let metrics = Arc::new(Metrics::new());
    let config = WorkerConfig {
        workers,
        max_batch: args.max_batch as usize,
        max_delay: Duration::from_millis(args.max_delay_ms),
        queue_depth: args.queue_depth as usize,
        device: runtime.device(),
        torch_threads,
    };
    let store = open_store(&args)?;
    let registry = Arc::new(Registry::start(store.clone(), &args.models, &config, metrics.clone())?);
    let poll = Duration::from_secs(args.poll);
    if args.poll > 0 {
        registry.poll(poll);
    }
    let limits = limits(&args)?;
    let buffer = Buffer::new(store.clone(), args.buffer_capacity as usize);
    let jobs = Jobs::start(store.clone(), registry.clone(), buffer, jobs_config(&args, &runtime, &limits, poll))
        .context("starting the adaptation jobs")?;
    let service = Arc::new(Service::new(registry, limits, metrics, tokens, jobs));

    // Bind both before serving either, so a bad address fails fast and both listen once the
    // process reports healthy.
    let tls = args.tls_cert.clone().zip(args.tls_key.clone()).map(|(cert, key)| TlsFiles { cert, key });
    let http_tcp = bind(args.http_addr, "HTTP").await?;
    let http_listener = match &tls {
        Some(files) => Listener::Tls(TlsListener::new(http_tcp, files)?),
        None => Listener::Plain(http_tcp),
    };
    let grpc_tls = match &tls {
        Some(files) => {
            let (cert, key) = files.read()?;
            Some(tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(cert, key)))
        }
        None => None,
    };
    let grpc_listener = bind(args.grpc_addr, "gRPC").await?;
    let (stop_tx, stop_rx) = watch::channel(false);
    tokio::spawn(async move {
        shutdown_signal().await;
        tracing::info!("shutdown requested; finishing in-flight requests");
        let _ = stop_tx.send(true);
    });

    tokio::try_join!(
        http::serve(http_listener, service.clone(), stopped(stop_rx.clone())),
        grpc::serve(grpc_listener, service, grpc_tls, stopped(stop_rx)),
    )?;
    tracing::info!("stopped");
    Ok(())
}

/// The tokens; without any, only loopback addresses (unless `--allow-unauthenticated`).
fn tokens(args: &Args) -> Result<Tokens> {
    let tokens = Tokens::new(args.token.as_deref(), args.token_file.as_deref())?;
    if !tokens.enabled() && !args.allow_unauthenticated {
        for addr in [args.http_addr, args.grpc_addr] {
            if !addr.ip().is_loopback() {
                bail!(
                    "{addr} is not loopback and no token is configured: set --token/--token-file, or pass --allow-unauthenticated"
                );
            }
        }
    }
    Ok(tokens)
}

/// The store, probed: one that does not fence create-only writes may only serve.
fn open_store(args: &Args) -> Result<Store> {
    let s3 = S3Options {
        endpoint: args.s3_endpoint.clone(),
        region: args.s3_region.clone(),
        allow_http: args.s3_allow_http,
    };
    let cache = args.cache_dir.clone().unwrap_or_else(std::env::temp_dir);
    let store =
        Store::open_url(&args.store, &s3, &cache).with_context(|| format!("opening the store {}", args.store))?;
    match store.probe() {
        Ok(()) => {
            tracing::info!(store = %store, role = ?args.role, "store refuses a second create-only write: writers are fenced")
        }
        Err(e) if args.role == Role::Serve => {
            tracing::warn!("{e}; serving anyway (a serve replica never activates on its own)")
        }
        Err(e) => bail!(
            "{e}: refusing --role {}, whose jobs and activations rely on it",
            format!("{:?}", args.role).to_lowercase()
        ),
    }
    Ok(store)
}

fn limits(args: &Args) -> Result<Limits> {
    Ok(Limits {
        max_request_bytes: usize::try_from(args.max_request_bytes).context("--max-request-bytes")?,
        decode: DecodeLimits {
            max_side: args.max_image_side,
            in_flight: args.max_decoded_mib << 20,
            ..DecodeLimits::default()
        },
        default_timeout: Duration::from_millis(args.timeout_ms),
    })
}

fn jobs_config(
    args: &Args,
    runtime: &udapose_engine::runtime::RuntimeInfo,
    limits: &Limits,
    poll: Duration,
) -> JobsConfig {
    JobsConfig {
        min_images: args.adapt_min_images as usize,
        adapt: AdaptConfig::default(),
        gate: GateConfig {
            min_target_fired: args.min_target_fired,
            margin_gain: args.margin_gain,
            regression_se: args.regression_se,
            ..Default::default()
        },
        regression: RegressionConfig { enabled: !args.no_regression_sets, ..Default::default() },
        experts: ExpertConfig { max: args.max_experts, ..Default::default() },
        device: runtime.device(),
        decode: limits.decode,
        runs_jobs: args.role != Role::Serve,
        enforce_gate: args.gate == GatePolicy::Enforce,
        poll,
        threads: if args.job_threads == 0 { (runtime.cpus / 2).max(1) } else { args.job_threads },
        nice: args.job_nice,
    }
}

/// Logs to stdout; `RUST_LOG` overrides the default `info` level. Colours only on a terminal, so
/// files and log collectors get plain text.
fn init_tracing() {
    use std::io::IsTerminal;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    tracing_subscriber::fmt().with_env_filter(filter).with_ansi(std::io::stdout().is_terminal()).init();
    udapose_service::store::check_failpoints();
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
