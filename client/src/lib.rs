//! Client for a udapose server's gRPC API.
//!
//! ```no_run
//! # async fn run() -> Result<(), udapose_client::Error> {
//! let client = udapose_client::Client::connect("127.0.0.1:50051").await?;
//! for model in client.list_models().await? {
//!     println!("{} ready={}", model.category, model.ready);
//! }
//! # Ok(())
//! # }
//! ```

use std::time::Duration;

use tonic::transport::{Channel, Endpoint};
use udapose_proto::v1::{ListModelsRequest, model_service_client::ModelServiceClient};

pub use udapose_proto::v1::ModelInfo;

/// How long to wait for a TCP connection before giving up on an endpoint.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(1);

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
    #[error("gRPC call failed: {}: {}", .0.code(), .0.message())]
    Rpc(#[from] tonic::Status),
}

/// A connection to one udapose server.
#[derive(Debug, Clone)]
pub struct Client {
    models: ModelServiceClient<Channel>,
}

impl Client {
    /// Connects to `endpoint`: a URI (`http://host:port`) or a bare `host:port`.
    pub async fn connect(endpoint: &str) -> Result<Self, Error> {
        let uri = with_scheme(endpoint);
        let channel = Endpoint::from_shared(uri)
            .map_err(|source| Error::InvalidEndpoint { endpoint: endpoint.to_owned(), source })?
            .connect_timeout(CONNECT_TIMEOUT)
            .connect()
            .await
            .map_err(|source| Error::Connect { endpoint: endpoint.to_owned(), source })?;
        Ok(Self { models: ModelServiceClient::new(channel) })
    }

    /// Every model the server has configured, ready or not, by category.
    pub async fn list_models(&self) -> Result<Vec<ModelInfo>, Error> {
        // tonic clients are cheap clones over one channel; cloning keeps `&self`.
        let response = self.models.clone().list_models(ListModelsRequest {}).await?;
        Ok(response.into_inner().models)
    }
}

/// tonic needs a scheme; plain `host:port` means cleartext HTTP/2.
fn with_scheme(endpoint: &str) -> String {
    if endpoint.contains("://") { endpoint.to_owned() } else { format!("http://{endpoint}") }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bare_host_port_gets_http() {
        assert_eq!(with_scheme("127.0.0.1:50051"), "http://127.0.0.1:50051");
        assert_eq!(with_scheme("https://pose.example:443"), "https://pose.example:443");
    }

    #[tokio::test]
    async fn unreachable_server_is_a_connect_error() {
        // Port 1 on loopback is essentially never listening.
        let err = Client::connect("127.0.0.1:1").await.unwrap_err();
        assert!(matches!(err, Error::Connect { .. }), "{err:?}");
    }
}
