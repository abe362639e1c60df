//! Client for a udapose server's gRPC API: models, estimates (unary, with retries on
//! UNAVAILABLE), and a bidirectional stream for video frames.
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

use std::time::Duration;

use tokio_stream::Stream;
use tonic::{
    Code, Request, Status, Streaming,
    metadata::MetadataValue,
    transport::{Certificate, Channel, ClientTlsConfig, Endpoint},
};
use tonic_types::StatusExt;
use udapose_proto::v1::{
    DescribeModelRequest, EstimateRequest, EstimateResponse, ListModelsRequest, estimate_request::Input,
    model_service_client::ModelServiceClient, pose_service_client::PoseServiceClient,
};

pub use udapose_proto::v1::{BoundingBox, ModelDescription, ModelInfo, PoseEstimate, RawImage};

/// How long to wait for a TCP connection before giving up on an endpoint.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(1);
/// The first retry's delay; doubled per attempt.
const BACKOFF: Duration = Duration::from_millis(100);
/// The longest a server's retry hint may make us wait.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// What can go wrong talking to a server.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("invalid endpoint {endpoint:?}")]
    InvalidEndpoint {
        endpoint: String,
        #[source]
        source: tonic::transport::Error,
    },
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
}

impl From<tonic::Status> for Error {
    fn from(status: tonic::Status) -> Self {
        Error::Rpc(status)
    }
}

impl Error {
    /// The gRPC code, when the server answered.
    pub fn code(&self) -> Option<Code> {
        match self {
            Error::Rpc(s) => Some(s.code()),
            _ => None,
        }
    }
}

/// How to reach the server(s).
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// One or more `host:port` or URIs; calls are spread over the reachable ones.
    pub endpoints: Vec<String>,
    /// Bearer token sent with every call.
    pub token: Option<String>,
    /// PEM CA certificate to trust (implies TLS); otherwise `https://` endpoints use the
    /// system's roots.
    pub ca_cert: Option<Vec<u8>>,
    /// The name to verify the server's certificate against (default: the endpoint's host).
    pub tls_domain: Option<String>,
    /// Retries of an idempotent call that met UNAVAILABLE (or a transport error).
    pub retries: u32,
    /// Connect eagerly (fail fast) rather than on the first call.
    pub eager: bool,
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
        }
    }
}

/// A connection to one udapose server, or a balanced set of replicas.
#[derive(Debug, Clone)]
pub struct Client {
    models: ModelServiceClient<Channel>,
    poses: PoseServiceClient<Channel>,
    token: Option<MetadataValue<tonic::metadata::Ascii>>,
    retries: u32,
}

impl Client {
    /// Connects to `endpoint`: a URI (`http://host:port`) or a bare `host:port`.
    pub async fn connect(endpoint: &str) -> Result<Self, Error> {
        Self::connect_with(ClientOptions::new(endpoint)).await
    }

    pub async fn connect_with(options: ClientOptions) -> Result<Self, Error> {
        let tls = options.ca_cert.is_some() || options.endpoints.iter().any(|e| e.starts_with("https://"));
        let mut endpoints = Vec::new();
        for e in &options.endpoints {
            let uri = with_scheme(e, tls);
            let invalid = |source| Error::InvalidEndpoint { endpoint: e.clone(), source };
            let mut endpoint = Endpoint::from_shared(uri).map_err(invalid)?.connect_timeout(CONNECT_TIMEOUT);
            if tls {
                let mut config = ClientTlsConfig::new();
                config = match &options.ca_cert {
                    Some(pem) => config.ca_certificate(Certificate::from_pem(pem)),
                    None => config.with_native_roots(),
                };
                if let Some(domain) = &options.tls_domain {
                    config = config.domain_name(domain.clone());
                }
                endpoint = endpoint.tls_config(config).map_err(invalid)?;
            }
            endpoints.push((e.clone(), endpoint));
        }
        let channel = match endpoints.as_slice() {
            [] => return Err(Error::InvalidToken("no endpoint given".into())),
            [(name, one)] if options.eager => {
                one.connect().await.map_err(|source| Error::Connect { endpoint: name.clone(), source })?
            }
            [(_, one)] => one.connect_lazy(),
            many => Channel::balance_list(many.iter().map(|(_, e)| e.clone())),
        };
        let token = match options.token.filter(|t| !t.is_empty()) {
            Some(t) => {
                Some(format!("Bearer {t}").parse().map_err(|_| Error::InvalidToken("not printable ASCII".into()))?)
            }
            None => None,
        };
        Ok(Client {
            models: ModelServiceClient::new(channel.clone()),
            poses: PoseServiceClient::new(channel),
            token,
            retries: options.retries,
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
            .retrying(|| async { self.models.clone().list_models(self.request(ListModelsRequest {})).await })
            .await?;
        Ok(response.into_inner().models)
    }

    /// One category's model in detail.
    pub async fn describe_model(&self, category: &str) -> Result<ModelDescription, Error> {
        let message = DescribeModelRequest { category: category.into() };
        let response =
            self.retrying(|| async { self.models.clone().describe_model(self.request(message.clone())).await }).await?;
        Ok(response.into_inner())
    }

    /// Estimates the pose(s) in one image, retrying (estimates are idempotent) while the server
    /// is overloaded or unreachable.
    pub async fn estimate(&self, message: EstimateRequest) -> Result<EstimateResponse, Error> {
        let response =
            self.retrying(|| async { self.poses.clone().estimate(self.request(message.clone())).await }).await?;
        Ok(response.into_inner())
    }

    /// Streams frames; one response per frame, in order. Failed frames carry `error`.
    pub async fn estimate_stream(
        &self,
        frames: impl Stream<Item = EstimateRequest> + Send + 'static,
    ) -> Result<Streaming<EstimateResponse>, Error> {
        Ok(self.poses.clone().estimate_stream(self.request(frames)).await?.into_inner())
    }

    async fn retrying<T, F, Fut>(&self, call: F) -> Result<T, Status>
    where
        F: Fn() -> Fut,
        Fut: Future<Output = Result<T, Status>>,
    {
        let mut attempt = 0;
        loop {
            match call().await {
                Err(status) if retryable(&status) && attempt < self.retries => {
                    tokio::time::sleep(delay(&status, attempt)).await;
                    attempt += 1;
                }
                other => return other,
            }
        }
    }
}

/// An estimate request for an encoded image (PNG, JPEG, WebP) with no boxes.
pub fn request(category: &str, image: Vec<u8>) -> EstimateRequest {
    EstimateRequest { category: category.into(), input: Some(Input::Image(image)), ..Default::default() }
}

/// UNAVAILABLE is overload or a replica going away; both are worth another try.
fn retryable(status: &Status) -> bool {
    status.code() == Code::Unavailable
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
mod tests {
    use super::*;

    #[test]
    fn bare_host_port_gets_a_scheme() {
        assert_eq!(with_scheme("127.0.0.1:50051", false), "http://127.0.0.1:50051");
        assert_eq!(with_scheme("127.0.0.1:50051", true), "https://127.0.0.1:50051");
        assert_eq!(with_scheme("https://pose.example:443", false), "https://pose.example:443");
    }

    #[test]
    fn retries_follow_the_hint_or_back_off() {
        let plain = Status::unavailable("busy");
        assert!(delay(&plain, 0) >= BACKOFF && delay(&plain, 0) < BACKOFF * 2);
        assert!(delay(&plain, 3) >= BACKOFF * 8);
        assert!(delay(&plain, 30) <= MAX_BACKOFF * 2);
        let mut details = tonic_types::ErrorDetails::new();
        details.set_retry_info(Some(Duration::from_millis(700)));
        let hinted = Status::with_error_details(Code::Unavailable, "busy", details);
        assert!(delay(&hinted, 0) >= Duration::from_millis(700));
        assert!(retryable(&plain) && !retryable(&Status::invalid_argument("bad")));
    }

    #[tokio::test]
    async fn unreachable_server_is_a_connect_error() {
        // Port 1 on loopback is essentially never listening.
        let err = Client::connect("127.0.0.1:1").await.unwrap_err();
        assert!(matches!(err, Error::Connect { .. }), "{err:?}");
    }
}
