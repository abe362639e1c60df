//! gRPC API (tonic): udapose.v1.ModelService, grpc.health.v1 and reflection.

use std::{future::Future, sync::Arc};

use anyhow::{Context, Result};
use tokio::net::TcpListener;
use tonic::{
    Request, Response, Status,
    transport::{Server, server::TcpIncoming},
};
use udapose_proto::v1::{
    ListModelsRequest, ListModelsResponse, ModelInfo,
    model_service_server::{ModelService, ModelServiceServer},
};

use crate::catalog::{Catalog, ModelEntry};

/// Serves until `stop` resolves, then lets in-flight calls finish.
pub async fn serve(
    listener: TcpListener,
    catalog: Arc<Catalog>,
    max_request_bytes: usize,
    stop: impl Future<Output = ()>,
) -> Result<()> {
    // The overall ("") status starts SERVING: it reports liveness, while
    // readiness (models loaded) is HTTP /readyz.
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<ModelServiceServer<Models>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(udapose_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .context("building the gRPC reflection service")?;
    // tonic's default decoding limit (4 MiB) is below the documented 16 MiB.
    let models = ModelServiceServer::new(Models { catalog }).max_decoding_message_size(max_request_bytes);

    Server::builder()
        .add_service(health_service)
        .add_service(reflection)
        .add_service(models)
        .serve_with_incoming_shutdown(TcpIncoming::from(listener), stop)
        .await
        .context("serving gRPC")
}

struct Models {
    catalog: Arc<Catalog>,
}

#[tonic::async_trait]
impl ModelService for Models {
    async fn list_models(&self, _request: Request<ListModelsRequest>) -> Result<Response<ListModelsResponse>, Status> {
        let models = self.catalog.models().iter().map(to_proto).collect();
        Ok(Response::new(ListModelsResponse { models }))
    }
}

fn to_proto(entry: &ModelEntry) -> ModelInfo {
    ModelInfo {
        category: entry.category.clone(),
        version: entry.version.clone().unwrap_or_default(),
        ready: entry.ready,
    }
}
