//! Foundation-stage end-to-end check: the real server starts with no models,
//! is alive but not ready, and answers over HTTP and gRPC.
//!
//! Needs `udapose-server` built in the same target dir and profile first
//! (`cargo build --release --workspace`); see support::server_binary.

mod support;

use support::Server;
use tonic::transport::{Channel, Endpoint};
use tonic_health::pb::{HealthCheckRequest, health_check_response::ServingStatus, health_client::HealthClient};

#[test]
fn server_without_models_is_live_but_not_ready() {
    let mut server = Server::start("health");

    let (code, body) = server.get("/healthz");
    assert_eq!((code, body.as_str()), (200, r#"{"status":"ok"}"#));

    let (code, body) = server.get("/readyz");
    assert_eq!(code, 503, "{body}");
    assert!(body.contains("no models"), "{body}");

    let (code, body) = server.get("/v1/models");
    assert_eq!((code, body.as_str()), (200, r#"{"models":[]}"#));

    let runtime = tokio::runtime::Runtime::new().expect("starting tokio");
    runtime.block_on(check_grpc(&server.grpc_endpoint()));

    #[cfg(unix)]
    {
        let status = server.terminate();
        assert!(status.success(), "unclean exit on SIGTERM: {status}\n{}", server.log());
    }
    // The log goes to a file here: plain text, no terminal colour codes.
    let log = server.log();
    assert!(log.contains("INFO") && !log.contains('\u{1b}'), "colour codes in a log file:\n{log}");
}

async fn check_grpc(endpoint: &str) {
    let client = udapose_client::Client::connect(endpoint).await.expect("connecting the client");
    let models = client.list_models().await.expect("ListModels");
    assert!(models.is_empty(), "{models:?}");

    let channel = Endpoint::from_shared(endpoint.to_owned())
        .expect("endpoint URI")
        .connect()
        .await
        .expect("connecting for health");
    let request = HealthCheckRequest { service: String::new() };
    let response = HealthClient::new(channel.clone()).check(request).await.expect("Health/Check");
    assert_eq!(response.into_inner().status, ServingStatus::Serving as i32);

    let services = reflected_services(channel.clone()).await;
    for expected in ["udapose.v1.ModelService", "grpc.health.v1.Health"] {
        assert!(services.iter().any(|s| s == expected), "{expected} not in {services:?}");
    }
    // Older tools (grpcurl before 1.8, Postman, Evans) speak only v1alpha.
    let services = reflected_services_v1alpha(channel).await;
    for expected in ["udapose.v1.PoseService", "udapose.v1.ModelService", "grpc.health.v1.Health"] {
        assert!(services.iter().any(|s| s == expected), "v1alpha: {expected} not in {services:?}");
    }
}

/// `async fn $name(channel) -> Vec<String>`: the service names the server lists over one
/// version of gRPC reflection (v1 and v1alpha have the same messages in different packages).
macro_rules! reflected_services {
    ($name:ident, $pb:path) => {
        async fn $name(channel: Channel) -> Vec<String> {
            use $pb::{
                ServerReflectionRequest, server_reflection_client::ServerReflectionClient,
                server_reflection_request::MessageRequest, server_reflection_response::MessageResponse,
            };
            let request = ServerReflectionRequest {
                host: String::new(),
                message_request: Some(MessageRequest::ListServices(String::new())),
            };
            let mut responses = ServerReflectionClient::new(channel)
                .server_reflection_info(tokio_stream::once(request))
                .await
                .expect("ServerReflectionInfo")
                .into_inner();
            let response = responses.message().await.expect("reflection reply").expect("one reply");
            match response.message_response {
                Some(MessageResponse::ListServicesResponse(list)) => list.service.into_iter().map(|s| s.name).collect(),
                other => panic!("unexpected reflection reply: {other:?}"),
            }
        }
    };
}
reflected_services!(reflected_services, tonic_reflection::pb::v1);
reflected_services!(reflected_services_v1alpha, tonic_reflection::pb::v1alpha);
