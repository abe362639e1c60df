//! Client for a udapose server's gRPC API: models and their versions, estimates (unary, with
//! retries on UNAVAILABLE), a bidirectional stream for video frames, and online adaptation
//! (uploading target images, adaptation jobs; see [`Client::stream_targets`]).
//!
//! Only idempotent calls are retried (ARCHITECTURE.md "Service contract"): estimates, reads,
//! uploads (an image's id is its sha256), `StartJob` with a `client_job_id`, and
//! `Activate`/`Rollback` with an `expected_generation`. Streams (`StreamTargets`, `WatchJob`,
//! `EstimateStream`) reconnect and resume where they broke off.
//!
//! # Several endpoints
//!
//! [`ClientOptions::endpoints`] may name several replicas (`Client::connect("a:50051,b:50051")`
//! too). The client keeps one connection per endpoint and sends each call to the next endpoint in
//! turn that is up. An endpoint that fails a call (refused or broken connection, or UNAVAILABLE:
//! overloaded, not ready) is passed over for 1 s, doubled per failure in a row up to 10 s; after
//! that it is tried again, and it is back with its first answer. An idempotent call that failed
//! so is sent again at once to another endpoint that is up (each endpoint once); when every
//! endpoint has failed it, it waits (the server's RetryInfo hint, else backoff from 100 ms) and
//! tries again, at most [`ClientOptions::retries`] times, then fails with [`Error::GaveUp`].
//! Other calls are sent once, to an endpoint that is up. A broken stream is reopened on the next
//! endpoint up, with the same budget counted from its last progress.
//!
//! ```no_run
//! # async fn run() -> Result<(), udapose_client::Error> {
//! let client = udapose_client::Client::connect("127.0.0.1:50051").await?;
//! let image = std::fs::read("car.png").unwrap();
//! let response = client.estimate(udapose_client::request("car", image)).await?;
//! let pose = &response.estimates[0];
//! println!("azimuth {:.1}°, elevation {:.1}°, theta {:.1}°", pose.azimuth_deg, pose.elevation_deg, pose.theta_deg);
//! # Ok(())
//! # }
//! ```

mod adapt;
mod pool;
mod video;

use std::{sync::Arc, time::Duration};

use pool::Pool;
use tonic::{
    Code, Request, Status,
    metadata::MetadataValue,
    transport::{Certificate, Channel, ClientTlsConfig, Endpoint},
};
use tonic_types::StatusExt;
use udapose_proto::v1::{
    ActivateRequest, DescribeModelRequest, EstimateRequest, EstimateResponse, ListModelsRequest, ListVersionsRequest,
    RollbackRequest, estimate_request::Input, model_service_client::ModelServiceClient,
    pose_service_client::PoseServiceClient,
};

pub use adapt::{JobEvents, Upload, Uploads, buffer_full, is_terminal, new_client_job_id, state_name};
pub use udapose_proto::v1::{
    ActivationEntry, AdaptOverrides, BoundingBox, GateCriterion, Job, JobEvent, JobState, ListVersionsResponse,
    ModelDescription, ModelInfo, PoseEstimate, RawImage, TargetAck, VersionInfo, target_ack,
};
pub use video::Estimates;

/// A call's replies, in order, as a stream ([`Uploads`], [`JobEvents`], [`Estimates`]): fed by
/// the task that keeps the call going across reconnections. Ends after the last reply, or
/// after an `Err`.
pub struct Replies<T>(tokio_stream::wrappers::ReceiverStream<Result<T, Error>>);

impl<T> Replies<T> {
    fn new(rx: tokio::sync::mpsc::Receiver<Result<T, Error>>) -> Self {
        Replies(tokio_stream::wrappers::ReceiverStream::new(rx))
    }

    /// The next reply; `None` after the last one.
    pub async fn message(&mut self) -> Result<Option<T>, Error> {
        tokio_stream::StreamExt::next(&mut self.0).await.transpose()
    }
}

impl<T> tokio_stream::Stream for Replies<T> {
    type Item = Result<T, Error>;

    fn poll_next(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Self::Item>> {
        std::pin::Pin::new(&mut self.0).poll_next(cx)
    }
}

/// How long to wait for a TCP connection before giving up on an endpoint.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(1);
/// The first retry's delay; doubled per attempt.
const BACKOFF: Duration = Duration::from_millis(100);
/// The longest a server's retry hint may make us wait.
const MAX_BACKOFF: Duration = Duration::from_secs(5);
/// The longest pause before resending images the server rejected with BUFFER_FULL.
const MAX_BUFFER_FULL_BACKOFF: Duration = Duration::from_secs(30);

/// What can go wrong talking to a server.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("no endpoint given")]
    NoEndpoint,
    #[error("invalid endpoint {endpoint:?}")]
    InvalidEndpoint {
        endpoint: String,
        #[source]
        source: tonic::transport::Error,
    },
    /// None of the endpoints (listed, comma-separated) could be reached; `source` is the first's
    /// error.
    #[error("cannot connect to {endpoint}")]
    Connect {
        endpoint: String,
        #[source]
        source: tonic::transport::Error,
    },
    #[error("invalid token: {0}")]
    InvalidToken(String),
    /// The server's answer (not a `#[source]`: its message is already in this one).
    #[error("{:?}: {}", .0.code(), .0.message())]
    Rpc(tonic::Status),
    /// An idempotent call (or a stream's reconnection) failed on every try: every endpoint was
    /// unreachable or UNAVAILABLE. `status` is the last try's.
    #[error("{:?}: {}{} (gave up after {tries} tries on {endpoints})", .status.code(), .status.message(), cause(.status))]
    GaveUp { status: tonic::Status, tries: u32, endpoints: String },
    /// The server broke the protocol (e.g. an ack for an image that was not sent).
    #[error("protocol error: {0}")]
    Protocol(String),
}

impl From<tonic::Status> for Error {
    fn from(status: tonic::Status) -> Self {
        Error::Rpc(status)
    }
}

impl Error {
    /// The gRPC code, when the server answered (or the connection's failure made one).
    pub fn code(&self) -> Option<Code> {
        match self {
            Error::Rpc(s) | Error::GaveUp { status: s, .. } => Some(s.code()),
            _ => None,
        }
    }
}

/// How to reach the server(s).
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// One or more `host:port` or URIs (an entry may hold several, comma-separated); calls are
    /// spread over those that are up (see the crate's documentation).
    pub endpoints: Vec<String>,
    /// Bearer token sent with every call.
    pub token: Option<String>,
    /// PEM CA certificate to trust (implies TLS); otherwise `https://` endpoints use the
    /// system's roots.
    pub ca_cert: Option<Vec<u8>>,
    /// The name to verify the server's certificate against (default: the endpoint's host).
    pub tls_domain: Option<String>,
    /// How often an idempotent call is tried again, after a pause, once every endpoint has failed
    /// it (unreachable, or UNAVAILABLE); moving to another endpoint that is up is immediate and
    /// not counted. For a stream, such pauses in a row without progress.
    pub retries: u32,
    /// Connect to the endpoints at once and fail unless one can be reached, rather than on the
    /// first call.
    pub eager: bool,
    /// How often an image rejected with BUFFER_FULL is resent (after a pause) before its
    /// REJECTED ack is final.
    pub buffer_full_retries: u32,
    /// The first pause before resending images rejected with BUFFER_FULL; doubled per resend
    /// of the same image, at most 30 s.
    pub buffer_full_backoff: Duration,
}

impl ClientOptions {
    pub fn new(endpoint: impl Into<String>) -> Self {
        ClientOptions {
            endpoints: vec![endpoint.into()],
            token: None,
            ca_cert: None,
            tls_domain: None,
            retries: 4,
            eager: true,
            buffer_full_retries: 6,
            buffer_full_backoff: Duration::from_secs(1),
        }
    }
}

/// A connection to one udapose server, or to several replicas with failover. Cheap to clone
/// (clones share the connections and what is known of the endpoints' health).
#[derive(Debug, Clone)]
pub struct Client {
    pool: Arc<Pool>,
    token: Option<MetadataValue<tonic::metadata::Ascii>>,
    retries: u32,
    buffer_full_retries: u32,
    buffer_full_backoff: Duration,
}

/// The failed tries of one call, or of a stream since its last progress.
#[derive(Debug, Default)]
struct Tries {
    total: u32,
    /// Since the last pause: each endpoint is tried once before pausing.
    since_pause: usize,
    pauses: u32,
}

impl Client {
    /// Connects to `endpoint`: a URI (`http://host:port`) or a bare `host:port`, or several,
    /// comma-separated.
    pub async fn connect(endpoint: &str) -> Result<Self, Error> {
        Self::connect_with(ClientOptions::new(endpoint)).await
    }

    pub async fn connect_with(options: ClientOptions) -> Result<Self, Error> {
        let names: Vec<&str> =
            options.endpoints.iter().flat_map(|e| e.split(',')).map(str::trim).filter(|e| !e.is_empty()).collect();
        if names.is_empty() {
            return Err(Error::NoEndpoint);
        }
        let tls = options.ca_cert.is_some() || names.iter().any(|e| e.starts_with("https://"));
        let endpoints = names
            .iter()
            .map(|name| Ok((name.to_string(), endpoint(name, tls, &options)?)))
            .collect::<Result<_, Error>>()?;
        let pool = if options.eager { Pool::connect(endpoints).await? } else { Pool::lazy(endpoints) };
        let token = match options.token.filter(|t| !t.is_empty()) {
            Some(t) => {
                Some(format!("Bearer {t}").parse().map_err(|_| Error::InvalidToken("not printable ASCII".into()))?)
            }
            None => None,
        };
        Ok(Client {
            pool: Arc::new(pool),
            token,
            retries: options.retries,
            buffer_full_retries: options.buffer_full_retries,
            buffer_full_backoff: options.buffer_full_backoff,
        })
    }

    fn request<T>(&self, message: T) -> Request<T> {
        let mut request = Request::new(message);
        if let Some(t) = &self.token {
            request.metadata_mut().insert("authorization", t.clone());
        }
        request
    }

    /// Every model the server has configured, ready or not, by category.
    pub async fn list_models(&self) -> Result<Vec<ModelInfo>, Error> {
        let response = self
            .retrying(
                |ch| async move { ModelServiceClient::new(ch).list_models(self.request(ListModelsRequest {})).await },
            )
            .await?;
        Ok(response.into_inner().models)
    }

    /// One category's model in detail.
    pub async fn describe_model(&self, category: &str) -> Result<ModelDescription, Error> {
        let message = &DescribeModelRequest { category: category.into() };
        let response = self
            .retrying(
                |ch| async move { ModelServiceClient::new(ch).describe_model(self.request(message.clone())).await },
            )
            .await?;
        Ok(response.into_inner())
    }

    /// Every complete version of `category` (by id) and its activation log (newest, i.e.
    /// active, first).
    pub async fn list_versions(&self, category: &str) -> Result<ListVersionsResponse, Error> {
        let message = &ListVersionsRequest { category: category.into() };
        let response = self
            .retrying(
                |ch| async move { ModelServiceClient::new(ch).list_versions(self.request(message.clone())).await },
            )
            .await?;
        Ok(response.into_inner())
    }

    /// Makes `version` the active one (a new generation of the activation log). Retried on
    /// UNAVAILABLE only with `expected_generation` (then a retry cannot activate twice); a
    /// retry answered ABORTED whose earlier attempt did succeed (its reply lost) returns that
    /// attempt's entry.
    pub async fn activate(
        &self,
        category: &str,
        version: &str,
        reason: &str,
        expected_generation: Option<u64>,
    ) -> Result<ActivationEntry, Error> {
        let message = &ActivateRequest {
            category: category.into(),
            version: version.into(),
            reason: reason.into(),
            expected_generation,
        };
        let call = |ch| async move { ModelServiceClient::new(ch).activate(self.request(message.clone())).await };
        let Some(expected) = expected_generation else {
            return Ok(self.once(call).await?.into_inner());
        };
        let landed = |log: &ListVersionsResponse| activation_landed(log, expected, version, reason).cloned();
        self.retrying_activation(category, call, landed).await
    }

    /// Re-activates the active entry's `previous` version (a new generation). Retried as
    /// [`Client::activate`] is: only with `expected_generation`.
    pub async fn rollback(
        &self,
        category: &str,
        reason: &str,
        expected_generation: Option<u64>,
    ) -> Result<ActivationEntry, Error> {
        let message = &RollbackRequest { category: category.into(), reason: reason.into(), expected_generation };
        let call = |ch| async move { ModelServiceClient::new(ch).rollback(self.request(message.clone())).await };
        let Some(expected) = expected_generation else {
            return Ok(self.once(call).await?.into_inner());
        };
        let landed = |log: &ListVersionsResponse| rollback_landed(log, expected, reason).cloned();
        self.retrying_activation(category, call, landed).await
    }

    /// [`Client::retrying`] for a generation-guarded activation: when a retry is answered
    /// ABORTED, an earlier attempt may have been applied with its reply lost; `landed` finds
    /// that attempt's entry in the log.
    async fn retrying_activation<F, Fut>(
        &self,
        category: &str,
        call: F,
        landed: impl Fn(&ListVersionsResponse) -> Option<ActivationEntry>,
    ) -> Result<ActivationEntry, Error>
    where
        F: Fn(Channel) -> Fut,
        Fut: Future<Output = Result<tonic::Response<ActivationEntry>, Status>>,
    {
        let mut tries = Tries::default();
        loop {
            let (endpoint, channel) = self.pool.pick();
            let status = match call(channel).await {
                Err(status) if retryable(&status) => status,
                Err(status) if status.code() == Code::Aborted && tries.total > 0 => {
                    self.pool.answered(endpoint);
                    let log = self.list_versions(category).await;
                    return log.ok().as_ref().and_then(&landed).ok_or(Error::Rpc(status));
                }
                answer => {
                    self.pool.answered(endpoint);
                    return Ok(answer?.into_inner());
                }
            };
            self.again(&mut tries, endpoint, status).await?;
        }
    }

    /// Estimates the pose(s) in one image, retrying (estimates are idempotent) while the server
    /// is overloaded or unreachable.
    pub async fn estimate(&self, message: EstimateRequest) -> Result<EstimateResponse, Error> {
        let message = &message;
        let response = self
            .retrying(|ch| async move { PoseServiceClient::new(ch).estimate(self.request(message.clone())).await })
            .await?;
        Ok(response.into_inner())
    }

    /// An idempotent call: on the next endpoint up, tried again (see the crate's documentation)
    /// while the endpoints are unreachable or UNAVAILABLE.
    async fn retrying<T, F, Fut>(&self, call: F) -> Result<T, Error>
    where
        F: Fn(Channel) -> Fut,
        Fut: Future<Output = Result<T, Status>>,
    {
        Ok(self.retrying_on(call).await?.1)
    }

    /// [`Client::retrying`], also saying which endpoint answered (a stream's, to mark it down if
    /// the stream breaks).
    async fn retrying_on<T, F, Fut>(&self, call: F) -> Result<(usize, T), Error>
    where
        F: Fn(Channel) -> Fut,
        Fut: Future<Output = Result<T, Status>>,
    {
        let mut tries = Tries::default();
        loop {
            let (endpoint, channel) = self.pool.pick();
            let status = match call(channel).await {
                Err(status) if retryable(&status) => status,
                answer => {
                    self.pool.answered(endpoint);
                    return Ok((endpoint, answer?));
                }
            };
            self.again(&mut tries, endpoint, status).await?;
        }
    }

    /// A call that is not safe to repeat: sent once, to the next endpoint up.
    async fn once<T, F, Fut>(&self, call: F) -> Result<T, Error>
    where
        F: FnOnce(Channel) -> Fut,
        Fut: Future<Output = Result<T, Status>>,
    {
        let (endpoint, channel) = self.pool.pick();
        match call(channel).await {
            Err(status) if retryable(&status) => {
                self.pool.failed(endpoint);
                Err(status.into())
            }
            answer => {
                self.pool.answered(endpoint);
                Ok(answer?)
            }
        }
    }

    /// After a try on `endpoint` failed with `status`: `Ok` to try again, at once while an
    /// endpoint not yet tried since the last pause is up, else after a pause (the server's hint
    /// or backoff), at most `retries` pauses; `Err` to give up. Marks the endpoint down when the
    /// failure is its (unreachable, UNAVAILABLE).
    async fn again(&self, tries: &mut Tries, endpoint: usize, status: Status) -> Result<(), Error> {
        if !retryable(&status) {
            return Err(status.into());
        }
        self.pool.failed(endpoint);
        tries.total += 1;
        tries.since_pause += 1;
        if tries.since_pause < self.pool.len() && self.pool.any_up() {
            return Ok(());
        }
        if tries.pauses >= self.retries {
            return Err(Error::GaveUp { status, tries: tries.total, endpoints: self.pool.names() });
        }
        tokio::time::sleep(delay(&status, tries.pauses)).await;
        tries.pauses += 1;
        tries.since_pause = 0;
        Ok(())
    }
}

/// The builder of one endpoint's connections.
fn endpoint(name: &str, tls: bool, options: &ClientOptions) -> Result<Endpoint, Error> {
    let invalid = |source| Error::InvalidEndpoint { endpoint: name.to_owned(), source };
    let endpoint = Endpoint::from_shared(with_scheme(name, tls)).map_err(invalid)?.connect_timeout(CONNECT_TIMEOUT);
    if !tls {
        return Ok(endpoint);
    }
    let mut config = ClientTlsConfig::new();
    config = match &options.ca_cert {
        Some(pem) => config.ca_certificate(Certificate::from_pem(pem)),
        None => config.with_native_roots(),
    };
    if let Some(domain) = &options.tls_domain {
        config = config.domain_name(domain.clone());
    }
    endpoint.tls_config(config).map_err(invalid)
}

/// The innermost cause of a status made from a connection's failure (`: Connection refused (os
/// error 111)`), which its message (`tcp connect error`) leaves out; empty for the server's.
fn cause(status: &Status) -> String {
    let mut source = std::error::Error::source(status);
    let mut last = None;
    while let Some(s) = source {
        last = Some(s);
        source = s.source();
    }
    last.map(|s| s.to_string()).filter(|s| *s != status.message()).map_or_else(String::new, |s| format!(": {s}"))
}

/// An estimate request for an encoded image (PNG, JPEG, WebP) with no boxes.
pub fn request(category: &str, image: Vec<u8>) -> EstimateRequest {
    EstimateRequest { category: category.into(), input: Some(Input::Image(image)), ..Default::default() }
}

/// UNAVAILABLE is overload or a replica going away, a transport error a connection that broke;
/// all are worth another try (of an idempotent call).
fn retryable(status: &Status) -> bool {
    status.code() == Code::Unavailable || transport_error(status)
}

/// A status made on this side from a connection's failure (h2, hyper or I/O error: it has a
/// source), not one the server sent (those are parsed from trailers and have none).
fn transport_error(status: &Status) -> bool {
    std::error::Error::source(status).is_some()
        && matches!(status.code(), Code::Unknown | Code::Internal | Code::Cancelled | Code::Unavailable)
}

/// The head of the log is the activation of `version` at `expected + 1` with our reason.
fn activation_landed<'a>(
    log: &'a ListVersionsResponse,
    expected: u64,
    version: &str,
    reason: &str,
) -> Option<&'a ActivationEntry> {
    let head = log.activations.first()?;
    (head.generation == expected + 1 && head.version == version && head.reason == reason).then_some(head)
}

/// The head of the log is, at `expected + 1` with our reason, the `previous` of the entry at
/// `expected`: what a rollback from `expected` writes.
fn rollback_landed<'a>(log: &'a ListVersionsResponse, expected: u64, reason: &str) -> Option<&'a ActivationEntry> {
    let head = log.activations.first()?;
    let from = log.activations.iter().find(|e| e.generation == expected)?;
    let landed = head.generation == expected + 1 && !from.previous.is_empty() && head.version == from.previous;
    (landed && head.reason == reason).then_some(head)
}

/// The server's RetryInfo hint if it gave one, else exponential backoff; a little jitter so
/// that many clients do not retry in step.
fn delay(status: &Status, attempt: u32) -> Duration {
    let backoff = BACKOFF * 2u32.saturating_pow(attempt);
    let hint = status.get_details_retry_info().and_then(|r| r.retry_delay);
    let base = hint.unwrap_or(backoff).min(MAX_BACKOFF);
    let jitter =
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos()) % 100;
    base + base * jitter / 400
}

/// tonic needs a scheme; plain `host:port` means cleartext HTTP/2 (or TLS when asked for).
fn with_scheme(endpoint: &str, tls: bool) -> String {
    match (endpoint.contains("://"), tls) {
        (true, _) => endpoint.to_owned(),
        (false, false) => format!("http://{endpoint}"),
        (false, true) => format!("https://{endpoint}"),
    }
}

#[cfg(test)]
mod tests;
