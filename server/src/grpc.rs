//! gRPC API (tonic): udapose.v1.PoseService and ModelService, grpc.health.v1 and reflection.

use std::{collections::HashMap, future::Future, pin::Pin, sync::Arc, time::Duration};

use anyhow::{Context, Result};
use tokio::{net::TcpListener, sync::mpsc};
use tokio_stream::{Stream, StreamExt, wrappers::ReceiverStream};
use tonic::{
    Request, Response, Status, Streaming,
    codegen::http::{self, HeaderValue},
    transport::{Server, ServerTlsConfig, server::TcpIncoming},
};
use tonic_types::{ErrorDetails, StatusExt};
use udapose_proto::v1::{
    self as pb, DescribeModelRequest, EstimateRequest, EstimateResponse, ListModelsRequest, ListModelsResponse,
    ModelDescription,
    adaptation_service_server::{AdaptationService, AdaptationServiceServer},
    estimate_request::Input,
    model_service_server::{ModelService, ModelServiceServer},
    pose_service_server::{PoseService, PoseServiceServer},
};

use udapose_service::{
    api::{EstimateInput, ImageInput},
    auth::Role,
    buffer::AckStatus,
    error::ApiError,
    jobs::{Overrides, Rejection, TargetAck},
    service::Service,
    views,
};

/// Serves until `stop` resolves, then lets in-flight calls finish.
pub async fn serve(
    listener: TcpListener,
    service: Arc<Service>,
    tls: Option<ServerTlsConfig>,
    stop: impl Future<Output = ()>,
) -> Result<()> {
    // The overall ("") status reports liveness; readiness (models loaded) is HTTP /readyz.
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<ModelServiceServer<Api>>().await;
    health.set_serving::<PoseServiceServer<Api>>().await;
    health.set_serving::<AdaptationServiceServer<Api>>().await;
    // Both reflection versions: older grpcurl, Postman and Evans still speak only v1alpha.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(udapose_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_v1 = reflection().build_v1().context("building the gRPC reflection service")?;
    let reflection_v1alpha = reflection().build_v1alpha().context("building the gRPC reflection service")?;
    let max = service.limits.max_request_bytes;
    let api = Api { service };
    // tonic's default decoding limit (4 MiB) is below the documented 16 MiB.
    let models = ModelServiceServer::new(api.clone()).max_decoding_message_size(max);
    let poses = PoseServiceServer::new(api.clone()).max_decoding_message_size(max);
    let adaptation = AdaptationServiceServer::new(api).max_decoding_message_size(max);

    let mut builder = Server::builder();
    if let Some(tls) = tls {
        builder = builder.tls_config(tls).context("configuring gRPC TLS")?;
    }
    builder
        .layer(tower::util::MapResponseLayer::new(too_large_is_resource_exhausted))
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(models)
        .add_service(poses)
        .add_service(adaptation)
        // TcpIncoming::from drops tonic's TCP_NODELAY default: without it each answer waits
        // for the client's delayed ACK (~40 ms).
        .serve_with_incoming_shutdown(TcpIncoming::from(listener).with_nodelay(Some(true)), stop)
        .await
        .context("serving gRPC")
}

/// tonic refuses an oversized message with OUT_OF_RANGE; the contract says RESOURCE_EXHAUSTED.
fn too_large_is_resource_exhausted<B>(mut response: http::Response<B>) -> http::Response<B> {
    let headers = response.headers_mut();
    let out_of_range = headers.get("grpc-status").is_some_and(|s| s == "11");
    let too_large = headers
        .get("grpc-message")
        .and_then(|m| m.to_str().ok())
        .is_some_and(|m| m.contains("too%20large") || m.contains("too large"));
    if out_of_range && too_large {
        headers.insert("grpc-status", HeaderValue::from_static("8"));
    }
    response
}

#[derive(Clone)]
struct Api {
    service: Arc<Service>,
}

impl Api {
    fn authorize<T>(&self, request: &Request<T>, role: Role) -> Result<(), Status> {
        let header = request.metadata().get("authorization").and_then(|v| v.to_str().ok());
        self.service.tokens.check(header, role).map_err(|e| self.refuse(e, "grpc"))
    }

    /// A status for `e`, counted in the metrics (estimates count their own).
    fn refuse(&self, e: ApiError, transport: &str) -> Status {
        self.service.metrics.requests.with_label_values(&[transport, e.code_name()]).inc();
        self.service.metrics.errors.with_label_values(&[e.code_name()]).inc();
        to_status(&e)
    }
}

/// The status with ErrorInfo (reason = the code name) and, when overloaded, RetryInfo.
pub fn to_status(e: &ApiError) -> Status {
    let mut details = ErrorDetails::new();
    details.set_error_info(e.code_name(), "udapose", HashMap::<String, String>::new());
    if let Some(after) = e.retry_after() {
        details.set_retry_info(Some(after));
    }
    Status::with_error_details(grpc_code(e), e.to_string(), details)
}

type EstimateStream = Pin<Box<dyn Stream<Item = Result<EstimateResponse, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl PoseService for Api {
    async fn estimate(&self, request: Request<EstimateRequest>) -> Result<Response<EstimateResponse>, Status> {
        self.authorize(&request, Role::Read)?;
        let deadline = grpc_timeout(request.metadata());
        let input = to_input(request.into_inner(), deadline).map_err(|e| self.refuse(e, "grpc"))?;
        let answer = self.service.estimate(input, "grpc").await.map_err(|e| to_status(&e))?;
        Ok(Response::new(answer.into()))
    }

    type EstimateStreamStream = EstimateStream;

    async fn estimate_stream(
        &self,
        request: Request<Streaming<EstimateRequest>>,
    ) -> Result<Response<Self::EstimateStreamStream>, Status> {
        self.authorize(&request, Role::Read)?;
        let mut frames = request.into_inner();
        let (tx, rx) = mpsc::channel(4);
        let service = self.service.clone();
        tokio::spawn(async move {
            // Frames are answered in order, one at a time: a stream is one camera.
            while let Some(frame) = frames.next().await {
                let frame = match frame {
                    Ok(f) => f,
                    Err(status) => {
                        let _ = tx.send(Err(status)).await;
                        break;
                    }
                };
                let frame_id = frame.frame_id.clone();
                let result = match to_input(frame, None) {
                    Ok(input) => service.estimate(input, "grpc-stream").await,
                    Err(e) => Err(e),
                };
                let response = match result {
                    Ok(answer) => answer.into(),
                    Err(e) => EstimateResponse {
                        frame_id,
                        error: Some(pb::ErrorStatus { code: grpc_code(&e) as i32, message: e.to_string() }),
                        ..Default::default()
                    },
                };
                if tx.send(Ok(response)).await.is_err() {
                    break; // the client went away
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

#[tonic::async_trait]
impl ModelService for Api {
    async fn list_models(&self, request: Request<ListModelsRequest>) -> Result<Response<ListModelsResponse>, Status> {
        self.authorize(&request, Role::Read)?;
        let models = self.service.registry.categories().map(|c| views::summary(c).into()).collect();
        Ok(Response::new(ListModelsResponse { models }))
    }

    async fn describe_model(
        &self,
        request: Request<DescribeModelRequest>,
    ) -> Result<Response<ModelDescription>, Status> {
        self.authorize(&request, Role::Read)?;
        let category = self.service.category(&request.get_ref().category).map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(views::describe(category).into()))
    }

    async fn list_versions(
        &self,
        request: Request<pb::ListVersionsRequest>,
    ) -> Result<Response<pb::ListVersionsResponse>, Status> {
        self.authorize(&request, Role::Read)?;
        let versions = self.service.versions(&request.get_ref().category).await.map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(versions.into()))
    }

    async fn activate(&self, request: Request<pb::ActivateRequest>) -> Result<Response<pb::ActivationEntry>, Status> {
        self.authorize(&request, Role::Admin)?;
        let r = request.into_inner();
        let entry = self
            .service
            .activate(&r.category, r.version, r.reason, r.expected_generation, "api")
            .await
            .map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(entry.into()))
    }

    async fn rollback(&self, request: Request<pb::RollbackRequest>) -> Result<Response<pb::ActivationEntry>, Status> {
        self.authorize(&request, Role::Admin)?;
        let r = request.into_inner();
        let entry = self
            .service
            .rollback(&r.category, r.reason, r.expected_generation, "api")
            .await
            .map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(entry.into()))
    }
}

type AckStream = Pin<Box<dyn Stream<Item = Result<pb::TargetAck, Status>> + Send + 'static>>;
type EventStream = Pin<Box<dyn Stream<Item = Result<pb::JobEvent, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl AdaptationService for Api {
    type StreamTargetsStream = AckStream;

    async fn stream_targets(
        &self,
        request: Request<Streaming<pb::TargetImage>>,
    ) -> Result<Response<Self::StreamTargetsStream>, Status> {
        self.authorize(&request, Role::Write)?;
        let mut images = request.into_inner();
        let (tx, rx) = mpsc::channel(16);
        let service = self.service.clone();
        tokio::spawn(async move {
            // In order, one ack per image, each sent once its image is durable.
            while let Some(image) = images.next().await {
                let ack = match image {
                    Ok(t) => match service.put_target(&t.category, t.image.into(), t.anchor).await {
                        Ok(ack) => to_ack(ack),
                        Err(e) => pb::TargetAck {
                            status: pb::target_ack::Status::Rejected as i32,
                            rejection: pb::target_ack::Rejection::Refused as i32,
                            reason: format!("{}: {e}", e.code_name()),
                            ..Default::default()
                        },
                    },
                    Err(status) => {
                        let _ = tx.send(Err(status)).await;
                        break;
                    }
                };
                if tx.send(Ok(ack)).await.is_err() {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn start_job(&self, request: Request<pb::StartJobRequest>) -> Result<Response<pb::Job>, Status> {
        self.authorize(&request, Role::Write)?;
        let r = request.into_inner();
        let o = r.overrides.unwrap_or_default();
        let overrides = Overrides { max_rounds: o.max_rounds, learning_rate: o.learning_rate, seed: o.seed };
        let client_job_id = Some(r.client_job_id).filter(|c| !c.is_empty());
        let job = self.service.start_job(&r.category, overrides, client_job_id).await;
        Ok(Response::new(job.map_err(|e| self.refuse(e, "grpc"))?.into()))
    }

    type WatchJobStream = EventStream;

    async fn watch_job(&self, request: Request<pb::WatchJobRequest>) -> Result<Response<Self::WatchJobStream>, Status> {
        self.authorize(&request, Role::Read)?;
        let r = request.into_inner();
        let events = udapose_service::service::watch(&self.service.jobs, r.job_id, r.after_seq)
            .map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(Box::pin(events.map(|e| e.map(Into::into).map_err(|e| to_status(&e))))))
    }

    async fn get_job(&self, request: Request<pb::GetJobRequest>) -> Result<Response<pb::Job>, Status> {
        self.authorize(&request, Role::Read)?;
        let job = self.service.job(request.into_inner().job_id).await.map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(job.into()))
    }

    async fn list_jobs(&self, request: Request<pb::ListJobsRequest>) -> Result<Response<pb::ListJobsResponse>, Status> {
        self.authorize(&request, Role::Read)?;
        let category = Some(request.get_ref().category.as_str()).filter(|c| !c.is_empty());
        let jobs = self.service.jobs.list(category).into_iter().map(Into::into).collect();
        Ok(Response::new(pb::ListJobsResponse { jobs }))
    }

    async fn cancel_job(&self, request: Request<pb::CancelJobRequest>) -> Result<Response<pb::Job>, Status> {
        self.authorize(&request, Role::Admin)?;
        let r = request.into_inner();
        let job = self.service.cancel_job(r.job_id, r.reason).await.map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(job.into()))
    }

    async fn list_regression_sets(
        &self,
        request: Request<pb::ListRegressionSetsRequest>,
    ) -> Result<Response<pb::ListRegressionSetsResponse>, Status> {
        self.authorize(&request, Role::Read)?;
        let sets =
            self.service.regression_sets(&request.get_ref().category).await.map_err(|e| self.refuse(e, "grpc"))?;
        Ok(Response::new(pb::ListRegressionSetsResponse { sets: sets.into_iter().map(Into::into).collect() }))
    }
}

fn to_ack(a: TargetAck) -> pb::TargetAck {
    use pb::target_ack::Status as S;
    let status = match a.status {
        AckStatus::Accepted => S::Accepted,
        AckStatus::Duplicate => S::Duplicate,
        AckStatus::Rejected => S::Rejected,
    };
    let rejection = match a.rejection {
        None => pb::target_ack::Rejection::Unspecified,
        Some(Rejection::InvalidImage) => pb::target_ack::Rejection::InvalidImage,
        Some(Rejection::BufferFull) => pb::target_ack::Rejection::BufferFull,
        Some(Rejection::Storage) => pb::target_ack::Rejection::Storage,
    };
    pb::TargetAck {
        sha256: a.sha256,
        status: status as i32,
        rejection: rejection as i32,
        reason: a.reason,
        buffered: a.buffered as u32,
        capacity: a.capacity as u32,
        job_id: a.job_id.unwrap_or_default(),
    }
}

/// The gRPC status code of a service error.
fn grpc_code(e: &ApiError) -> tonic::Code {
    match e {
        ApiError::InvalidArgument(_) => tonic::Code::InvalidArgument,
        ApiError::NotFound(_) => tonic::Code::NotFound,
        ApiError::TooLarge(_) => tonic::Code::ResourceExhausted,
        ApiError::Unavailable { .. } => tonic::Code::Unavailable,
        ApiError::Unauthenticated(_) => tonic::Code::Unauthenticated,
        ApiError::PermissionDenied(_) => tonic::Code::PermissionDenied,
        ApiError::Aborted(_) => tonic::Code::Aborted,
        ApiError::FailedPrecondition(_) => tonic::Code::FailedPrecondition,
        ApiError::DeadlineExceeded(_) => tonic::Code::DeadlineExceeded,
        ApiError::MethodNotAllowed(_) => tonic::Code::Unimplemented,
        ApiError::Internal(_) => tonic::Code::Internal,
    }
}

fn to_input(r: EstimateRequest, timeout: Option<Duration>) -> Result<EstimateInput, ApiError> {
    let image = match r.input {
        Some(Input::Image(bytes)) => ImageInput::Encoded(bytes.into()),
        Some(Input::Raw(raw)) => ImageInput::Raw { width: raw.width, height: raw.height, rgb8: raw.rgb8.into() },
        None => return Err(ApiError::InvalidArgument("the request has no image (set image or raw)".into())),
    };
    let from_options = r.options.map(|o| o.timeout_ms).filter(|&t| t > 0).map(|t| Duration::from_millis(t.into()));
    let timeout = match (timeout, from_options) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    };
    Ok(EstimateInput {
        category: r.category,
        image,
        boxes: r.boxes.iter().map(|b| [b.x0, b.y0, b.x1, b.y1]).collect(),
        frame_id: r.frame_id,
        timeout,
    })
}

/// The `grpc-timeout` header (`<digits><unit>`, unit one of H M S m u n).
fn grpc_timeout(metadata: &tonic::metadata::MetadataMap) -> Option<Duration> {
    let value = metadata.get("grpc-timeout")?.to_str().ok()?;
    let (digits, unit) = value.split_at(value.len().checked_sub(1)?);
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grpc_timeouts_parse() {
        let mut m = tonic::metadata::MetadataMap::new();
        assert_eq!(grpc_timeout(&m), None);
        for (v, d) in
            [("250m", Duration::from_millis(250)), ("3S", Duration::from_secs(3)), ("2M", Duration::from_secs(120))]
        {
            m.insert("grpc-timeout", v.parse().unwrap());
            assert_eq!(grpc_timeout(&m), Some(d));
        }
        m.insert("grpc-timeout", "x".parse().unwrap());
        assert_eq!(grpc_timeout(&m), None);
    }
}
