//! HTTP API (axum): pose estimation, models, health, readiness, metrics, the OpenAPI document
//! and the web page. Estimates go through the same `Service` as gRPC.

use std::{future::Future, sync::Arc, time::Duration};

use anyhow::{Context, Result};
use axum::{
    Json, Router,
    body::{Body, Bytes},
    extract::{DefaultBodyLimit, FromRequest, Multipart, Path, RawQuery, Request, State},
    http::{HeaderMap, HeaderValue, StatusCode, header},
    response::{Html, IntoResponse, Response},
    routing::{get, post},
};
use serde::Deserialize;
use serde_json::{Value, json};

use udapose_api::{
    ActivationEntry, ErrorBody, EstimateAnswer, JobList, JobView, ModelDescription, ModelList, Versions,
};
use udapose_service::{
    api::{EstimateInput, ImageInput},
    auth::Role,
    error::ApiError,
    service::Service,
    views,
};

use crate::tls::Listener;

use axum::serve::ListenerExt;

const INDEX_HTML: &str = include_str!("web/index.html");

/// Serves until `stop` resolves, then lets in-flight requests finish.
pub async fn serve(
    listener: Listener,
    service: Arc<Service>,
    stop: impl Future<Output = ()> + Send + 'static,
) -> Result<()> {
    let app = router(service);
    match listener {
        // No Nagle: a small answer must not wait for the client's delayed ACK (~40 ms).
        Listener::Plain(l) => {
            let l = l.tap_io(|tcp| {
                let _ = tcp.set_nodelay(true);
            });
            axum::serve(l, app).with_graceful_shutdown(stop).await
        }
        Listener::Tls(l) => axum::serve(l, app).with_graceful_shutdown(stop).await,
    }
    .context("serving HTTP")
}

pub fn router(service: Arc<Service>) -> Router {
    let limit = service.limits.max_request_bytes;
    Router::new()
        .route("/", get(index))
        .route("/openapi.json", get(openapi))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/models", get(list_models))
        .route("/v1/models/{category}", get(describe_model))
        .route("/v1/models/{category}/versions", get(list_versions))
        .route("/v1/models/{category}/activate", post(activate))
        .route("/v1/models/{category}/rollback", post(rollback))
        .route("/v1/pose/{category}", post(estimate))
        .route("/v1/adapt/{category}/images", post(put_targets))
        .route("/v1/adapt/{category}/jobs", post(start_job))
        .route("/v1/adapt/{category}/regression-sets", get(regression_sets))
        .route("/v1/jobs", get(list_jobs))
        .route("/v1/jobs/{id}", get(get_job))
        .route("/v1/jobs/{id}/events", get(job_events))
        .route("/v1/jobs/{id}/cancel", post(cancel_job))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        // axum's own default (2 MB) is below the documented 16 MiB; multipart reads obey it.
        .layer(DefaultBodyLimit::max(limit))
        .with_state(service)
}

/// An error as JSON `{"error": {"code", "message"}}`, with `Retry-After` when overloaded.
pub struct HttpError(pub ApiError);

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let e = self.0;
        let status = StatusCode::from_u16(e.http_status()).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        let body = Json(ErrorBody::new(e.code_name(), e.to_string()));
        let mut response = (status, body).into_response();
        if let Some(after) = e.retry_after() {
            let secs = after.as_secs().max(1).to_string();
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from_str(&secs).expect("digits"));
        }
        if status == StatusCode::UNAUTHORIZED {
            response
                .headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static(udapose_service::auth::CHALLENGE));
        }
        response
    }
}

/// Counts an error that never reached the estimate path, and wraps it.
fn refuse(service: &Service, e: ApiError) -> HttpError {
    service.metrics.requests.with_label_values(&["http", e.code_name()]).inc();
    service.metrics.errors.with_label_values(&[e.code_name()]).inc();
    HttpError(e)
}

fn authorize(service: &Service, headers: &HeaderMap, role: Role) -> Result<(), HttpError> {
    let value = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok());
    service.tokens.check(value, role).map_err(|e| refuse(service, e))
}

async fn index() -> Html<&'static str> {
    Html(INDEX_HTML)
}

async fn openapi() -> Json<Value> {
    Json(crate::openapi::document())
}

/// Liveness: the process answers; says nothing about models.
async fn healthz() -> Json<Value> {
    Json(json!({ "status": "ok" }))
}

/// Readiness: 200 only when every configured model is loaded.
async fn readyz(State(service): State<Arc<Service>>) -> (StatusCode, Json<Value>) {
    let readiness = service.registry.readiness();
    let (code, status) =
        if readiness.ready { (StatusCode::OK, "ready") } else { (StatusCode::SERVICE_UNAVAILABLE, "not_ready") };
    (code, Json(json!({ "status": status, "reason": readiness.reason })))
}

async fn metrics(State(service): State<Arc<Service>>) -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], service.metrics.render())
}

async fn not_found(State(service): State<Arc<Service>>) -> HttpError {
    refuse(&service, ApiError::NotFound("no such route; see /openapi.json".into()))
}

async fn method_not_allowed(State(service): State<Arc<Service>>, request: Request) -> HttpError {
    let (method, path) = (request.method().clone(), request.uri().path().to_owned());
    refuse(&service, ApiError::MethodNotAllowed(format!("{method} is not allowed on {path}; see /openapi.json")))
}

async fn list_models(State(service): State<Arc<Service>>, headers: HeaderMap) -> Result<Json<ModelList>, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    Ok(Json(ModelList { models: service.registry.categories().map(|c| views::summary(c)).collect() }))
}

async fn describe_model(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(category): Path<String>,
) -> Result<Json<ModelDescription>, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    let category = service.category(&category).map_err(|e| refuse(&service, e))?;
    Ok(Json(views::describe(category)))
}

/// `POST /v1/pose/{category}`: the image as the raw body (PNG, JPEG, WebP; raw RGB8 with
/// `?width=&height=`) or as the `image` part of a multipart form. Query: `bbox=x0,y0,x1,y1`
/// (repeatable), `frame_id`, `timeout_ms`.
async fn estimate(
    State(service): State<Arc<Service>>,
    Path(category): Path<String>,
    RawQuery(query): RawQuery,
    request: Request,
) -> Result<Json<EstimateAnswer>, HttpError> {
    authorize(&service, request.headers(), Role::Read)?;
    let query = EstimateQuery::parse(query.as_deref().unwrap_or("")).map_err(|e| refuse(&service, e))?;
    let bytes = read_image(&service, request).await.map_err(|e| refuse(&service, e))?;
    let image = match (query.width, query.height) {
        (Some(width), Some(height)) => ImageInput::Raw { width, height, rgb8: bytes },
        (None, None) => ImageInput::Encoded(bytes),
        _ => return Err(refuse(&service, ApiError::InvalidArgument("raw pixels need both width and height".into()))),
    };
    let input = EstimateInput { category, image, boxes: query.boxes, frame_id: query.frame_id, timeout: query.timeout };
    service.estimate(input, "http").await.map(Json).map_err(HttpError)
}

async fn list_versions(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(category): Path<String>,
) -> Result<Json<Versions>, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    service.versions(&category).await.map(Json).map_err(|e| refuse(&service, e))
}

/// The body of `activate` and `rollback` (all optional but `version` for activate).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ActivateBody {
    version: Option<String>,
    #[serde(default)]
    reason: String,
    expected_generation: Option<u64>,
}

fn json_body<T: serde::de::DeserializeOwned + Default>(service: &Service, body: &Bytes) -> Result<T, HttpError> {
    if body.iter().all(u8::is_ascii_whitespace) {
        return Ok(T::default());
    }
    serde_json::from_slice(body).map_err(|e| refuse(service, ApiError::InvalidArgument(format!("bad JSON body: {e}"))))
}

async fn activate(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(category): Path<String>,
    body: Bytes,
) -> Result<Json<ActivationEntry>, HttpError> {
    switch_version(&service, &headers, &category, &body, false).await
}

async fn rollback(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(category): Path<String>,
    body: Bytes,
) -> Result<Json<ActivationEntry>, HttpError> {
    switch_version(&service, &headers, &category, &body, true).await
}

/// Activate (the body names a version) or roll back (it must not).
async fn switch_version(
    service: &Service,
    headers: &HeaderMap,
    category: &str,
    body: &Bytes,
    rollback: bool,
) -> Result<Json<ActivationEntry>, HttpError> {
    authorize(service, headers, Role::Admin)?;
    let b: ActivateBody = json_body(service, body)?;
    let bad = |why: &str| refuse(service, ApiError::InvalidArgument(why.into()));
    let entry = match (rollback, b.version) {
        (false, None) => return Err(bad("the body needs a \"version\"")),
        (true, Some(_)) => return Err(bad("rollback takes no version")),
        (false, Some(version)) => service.activate(category, version, b.reason, b.expected_generation, "api").await,
        (true, None) => service.rollback(category, b.reason, b.expected_generation, "api").await,
    };
    entry.map(Json).map_err(|e| refuse(service, e))
}

/// `POST /v1/adapt/{category}/images[?anchor=true]`: one image as the raw body, or many as the
/// parts of a multipart form, for the buffer (or the anchor set). 200 with one result per image;
/// `Retry-After` when any met a full buffer.
async fn put_targets(
    State(service): State<Arc<Service>>,
    Path(category): Path<String>,
    request: Request,
) -> Result<Response, HttpError> {
    authorize(&service, request.headers(), Role::Write)?;
    service.category(&category).map_err(|e| refuse(&service, e))?;
    let anchor = match query_value(request.uri().query(), "anchor").as_deref() {
        None | Some("false") => false,
        Some("true") => true,
        Some(other) => {
            let why = format!("anchor must be true or false, got {other:?}");
            return Err(refuse(&service, ApiError::InvalidArgument(why)));
        }
    };
    let images = read_images(&service, request).await.map_err(|e| refuse(&service, e))?;
    let mut results = Vec::with_capacity(images.len());
    for image in images {
        results.push(service.put_target(&category, image, anchor).await.map_err(|e| refuse(&service, e))?);
    }
    let full = results.iter().any(|a| a.rejection == Some(udapose_service::jobs::Rejection::BufferFull));
    let mut response = Json(json!({ "results": results })).into_response();
    if full {
        response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from_static("10"));
    }
    Ok(response)
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct StartJobBody {
    #[serde(default)]
    overrides: udapose_service::jobs::Overrides,
    client_job_id: Option<String>,
}

async fn start_job(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(category): Path<String>,
    body: Bytes,
) -> Result<Json<JobView>, HttpError> {
    authorize(&service, &headers, Role::Write)?;
    let b: StartJobBody = json_body(&service, &body)?;
    let job = service.start_job(&category, b.overrides, b.client_job_id).await;
    job.map(Json).map_err(|e| refuse(&service, e))
}

async fn regression_sets(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(category): Path<String>,
) -> Result<Json<udapose_api::RegressionSets>, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    let sets = service.regression_sets(&category).await.map_err(|e| refuse(&service, e))?;
    Ok(Json(udapose_api::RegressionSets { sets }))
}

async fn list_jobs(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    RawQuery(query): RawQuery,
) -> Result<Json<JobList>, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    let category = query_value(query.as_deref(), "category");
    Ok(Json(JobList { jobs: service.jobs.list(category.as_deref()) }))
}

async fn get_job(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(id): Path<String>,
) -> Result<Json<JobView>, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    service.job(id).await.map(Json).map_err(|e| refuse(&service, e))
}

/// Server-Sent Events: one `data:` JSON event per job event (`id:` its seq), from `after_seq`
/// (query) or `Last-Event-ID`, ending after the terminal one.
async fn job_events(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
) -> Result<Response, HttpError> {
    authorize(&service, &headers, Role::Read)?;
    let after = query_value(query.as_deref(), "after_seq")
        .or_else(|| headers.get("last-event-id").and_then(|v| v.to_str().ok()).map(str::to_owned))
        .map(|v| v.parse::<u64>())
        .transpose()
        .map_err(|_| refuse(&service, ApiError::InvalidArgument("bad after_seq".into())))?
        .unwrap_or(0);
    let events = udapose_service::service::watch(&service.jobs, id, after).map_err(|e| refuse(&service, e))?;
    let stream = tokio_stream::StreamExt::map(events, |e| {
        let event = match e {
            Ok(ev) => axum::response::sse::Event::default()
                .id(ev.seq.to_string())
                .event("job")
                .json_data(&ev)
                .unwrap_or_else(|_| axum::response::sse::Event::default().comment("unserialisable event")),
            Err(err) => axum::response::sse::Event::default().event("error").data(err.to_string()),
        };
        Ok::<_, std::convert::Infallible>(event)
    });
    Ok(axum::response::sse::Sse::new(stream).keep_alive(axum::response::sse::KeepAlive::default()).into_response())
}

async fn cancel_job(
    State(service): State<Arc<Service>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
) -> Result<Json<JobView>, HttpError> {
    authorize(&service, &headers, Role::Admin)?;
    let reason = query_value(query.as_deref(), "reason").unwrap_or_default();
    service.cancel_job(id, reason).await.map(Json).map_err(|e| refuse(&service, e))
}

fn query_value(query: Option<&str>, key: &str) -> Option<String> {
    query?.split('&').filter_map(|p| p.split_once('=')).find(|(k, _)| *k == key).map(|(_, v)| percent_decode(v))
}

/// One part of a request: the raw body, or a part of a multipart form.
struct Part {
    name: Option<String>,
    /// Sent as a file (a form part with a file name; the raw body).
    file: bool,
    data: Bytes,
}

/// The raw body as one part, or every part of a multipart form, within the size limit.
async fn read_parts(service: &Service, request: Request) -> Result<Vec<Part>, ApiError> {
    let limit = service.limits.max_request_bytes;
    let too_large = || ApiError::TooLarge(format!("request body over the limit of {limit} bytes"));
    let declared = request.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit as u64) {
        return Err(too_large());
    }
    let multipart = request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("multipart/form-data"));
    if !multipart {
        let body: Body = request.into_body();
        let data = axum::body::to_bytes(body, limit).await.map_err(|_| too_large())?;
        return Ok(vec![Part { name: None, file: true, data }]);
    }
    let bad = |e: &dyn std::fmt::Display| ApiError::InvalidArgument(format!("bad multipart form: {e}"));
    let mut form = Multipart::from_request(request, &()).await.map_err(|e| bad(&e.body_text()))?;
    let mut parts = Vec::new();
    loop {
        let field = match form.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => return Ok(parts),
            Err(e) if e.status() == StatusCode::PAYLOAD_TOO_LARGE => return Err(too_large()),
            Err(e) => return Err(bad(&e.body_text())),
        };
        let (name, file) = (field.name().map(str::to_owned), field.file_name().is_some());
        let data = field
            .bytes()
            .await
            .map_err(|e| if e.status() == StatusCode::PAYLOAD_TOO_LARGE { too_large() } else { bad(&e.body_text()) })?;
        parts.push(Part { name, file, data });
    }
}

/// Every image of the request: the body, or each part of a multipart form.
async fn read_images(service: &Service, request: Request) -> Result<Vec<Bytes>, ApiError> {
    let parts = read_parts(service, request).await?;
    if parts.is_empty() {
        return Err(ApiError::InvalidArgument("the multipart form has no image part".into()));
    }
    Ok(parts.into_iter().map(|p| p.data).collect())
}

/// The body, or the `image` part of a multipart form, else its first file part: a text field
/// (`-F foo=bar`) is not an image.
async fn read_image(service: &Service, request: Request) -> Result<Bytes, ApiError> {
    let mut parts = read_parts(service, request).await?;
    let image = parts.iter().position(|p| p.name.as_deref() == Some("image"));
    match image.or_else(|| parts.iter().position(|p| p.file)) {
        Some(i) => Ok(parts.swap_remove(i).data),
        None => Err(ApiError::InvalidArgument(
            "the multipart form has no image part (send the file as `-F image=@photo.jpg`)".into(),
        )),
    }
}

#[derive(Debug, Default, PartialEq)]
struct EstimateQuery {
    boxes: Vec<[f64; 4]>,
    width: Option<u32>,
    height: Option<u32>,
    frame_id: String,
    timeout: Option<Duration>,
}

impl EstimateQuery {
    fn parse(query: &str) -> Result<Self, ApiError> {
        let bad = |what: &str, v: &str| ApiError::InvalidArgument(format!("bad {what} {v:?}"));
        let mut q = EstimateQuery::default();
        for pair in query.split('&').filter(|p| !p.is_empty()) {
            let (key, value) = pair.split_once('=').unwrap_or((pair, ""));
            let value = percent_decode(value);
            match key {
                "bbox" => {
                    let v: Vec<f64> = value
                        .split(',')
                        .map(|x| x.trim().parse::<f64>())
                        .collect::<Result<_, _>>()
                        .map_err(|_| bad("bbox", &value))?;
                    let b: [f64; 4] = v.try_into().map_err(|_| bad("bbox (want x0,y0,x1,y1)", &value))?;
                    q.boxes.push(b);
                }
                "width" => q.width = Some(value.parse().map_err(|_| bad("width", &value))?),
                "height" => q.height = Some(value.parse().map_err(|_| bad("height", &value))?),
                "frame_id" => q.frame_id = value,
                "timeout_ms" => {
                    let ms: u64 = value.parse().map_err(|_| bad("timeout_ms", &value))?;
                    q.timeout = Some(Duration::from_millis(ms));
                }
                _ => return Err(ApiError::InvalidArgument(format!("unknown query parameter {key:?}"))),
            }
        }
        Ok(q)
    }
}

/// `%XX` escapes and `+` as space; invalid escapes are kept as they are.
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let hex = |c: u8| (c as char).to_digit(16).map(|d| d as u8);
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let (Some(hi), Some(lo)) = (hex(b[i + 1]), hex(b[i + 2]))
        {
            out.push(hi * 16 + lo);
            i += 3;
            continue;
        }
        out.push(if b[i] == b'+' { b' ' } else { b[i] });
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queries_parse_boxes_and_raw_sizes() {
        let q = EstimateQuery::parse("bbox=1,2,30,40&bbox=5%2C6%2C70%2C80&width=4&height=3&frame_id=f+1&timeout_ms=50")
            .unwrap();
        assert_eq!(q.boxes, [[1.0, 2.0, 30.0, 40.0], [5.0, 6.0, 70.0, 80.0]]);
        assert_eq!((q.width, q.height, q.frame_id.as_str()), (Some(4), Some(3), "f 1"));
        assert_eq!(q.timeout, Some(Duration::from_millis(50)));
        for bad in ["bbox=1,2,3", "bbox=a,b,c,d", "width=-1", "nope=1"] {
            assert!(matches!(EstimateQuery::parse(bad), Err(ApiError::InvalidArgument(_))), "{bad}");
        }
        assert_eq!(percent_decode("a%2"), "a%2");
        assert_eq!(percent_decode("%zz%41"), "%zzA");
    }
}
