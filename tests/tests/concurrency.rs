//! 16 clients × 50 requests: no errors, and every answer bit-identical to the sequential one
//! (`--max-batch 1`); with dynamic batching, batches share backbone passes and answers are
//! bit-identical to each image's answer alone too, and to `--max-batch 1`'s, and with two
//! workers of one libtorch thread each;
//! a saturated queue refuses at once with UNAVAILABLE / 503 and Retry-After, never queueing
//! without bound. Needs `make test`'s quick model and data.

mod support;

use std::{collections::BTreeMap, sync::Arc};

use support::{Server, quick_images};
use udapose_client::{Client, ClientOptions, PoseEstimate};

const CLIENTS: usize = 16;
const REQUESTS: usize = 50;
const DISTINCT: usize = 8;

fn bits(p: &PoseEstimate) -> [u64; 5] {
    [p.azimuth, p.elevation, p.theta, p.distance, p.score].map(f64::to_bits)
}

#[test]
fn concurrent_answers_equal_sequential_ones_and_overload_is_refused_fast() {
    let images: Arc<Vec<Vec<u8>>> = Arc::new(quick_images("source", DISTINCT).into_iter().map(|i| i.bytes).collect());
    let runtime = tokio::runtime::Runtime::new().unwrap();

    // 1. No batching: bit-identical under concurrency.
    let server = Server::config("concurrency").quick_model().arg("--max-batch").arg("1").start();
    let unbatched = runtime.block_on(sequential(&server, &images));
    let answers = runtime.block_on(hammer(&server, &images, CLIENTS, REQUESTS, 0));
    assert_eq!(answers.len(), CLIENTS * REQUESTS);
    for (i, p) in answers {
        assert_eq!(bits(&p), bits(&unbatched[i]), "image {i}: concurrent answer differs from the sequential one");
    }
    drop(server);

    // 2. Dynamic batching: batches of more than one crop form and share backbone passes, and
    // answers are still bit-identical to the ones each image gets alone (engine::backbone::invariant,
    // engine::estimator::Estimator::features).
    let server =
        Server::config("batching").quick_model().arg("--max-batch").arg("8").arg("--max-delay-ms").arg("20").start();
    let alone = runtime.block_on(sequential(&server, &images));
    let answers = runtime.block_on(hammer(&server, &images, CLIENTS, 3, 0));
    for (i, p) in &answers {
        assert_eq!(bits(p), bits(&alone[*i]), "image {i}: a batched answer differs from the answer alone");
    }
    for (i, (a, u)) in alone.iter().zip(&unbatched).enumerate() {
        assert_eq!(bits(a), bits(u), "image {i}: --max-batch 8 answers differently from --max-batch 1");
    }
    assert!(batched_passes(&server) > 0.0, "no pass held more than one crop\n{}", server.get("/metrics").1);
    drop(server);

    // Two workers (each its own model copy, libtorch threads and solver pool, each taking its
    // share of the queue), batching on: the answers of one worker over every core.
    let server = Server::config("workers")
        .quick_model()
        .args(["--workers", "2", "--max-batch", "8", "--max-delay-ms", "20"])
        .start();
    let answers = runtime.block_on(hammer(&server, &images, CLIENTS, 3, 0));
    for (i, p) in &answers {
        assert_eq!(bits(p), bits(&unbatched[*i]), "image {i}: two workers answer differently from one");
    }
    drop(server);

    // 3. Saturation: a queue of 1 and no batching; 16 simultaneous requests over HTTP.
    let server = Server::config("saturation").quick_model().args(["--max-batch", "1", "--queue-depth", "1"]).start();
    let server = Arc::new(server);
    let threads: Vec<_> = (0..CLIENTS)
        .map(|i| {
            let (server, images) = (server.clone(), images.clone());
            std::thread::spawn(move || server.request("POST", "/v1/pose/car", &[], &images[i % DISTINCT]))
        })
        .collect();
    let responses: Vec<_> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    let refused: Vec<_> = responses.iter().filter(|r| r.status == 503).collect();
    assert!(responses.iter().all(|r| r.status == 200 || r.status == 503), "{responses:?}");
    assert!(!refused.is_empty(), "16 requests against a queue of 1 were all admitted");
    for r in &refused {
        assert_eq!(r.header("retry-after"), Some("1"), "{r:?}");
        assert_eq!(r.json()["error"]["code"], "UNAVAILABLE");
    }
    // Over gRPC (a raw stub, no retries): UNAVAILABLE with ErrorInfo and a RetryInfo hint.
    let statuses = runtime.block_on(raw_grpc_burst(&server, &images, CLIENTS));
    let unavailable: Vec<_> = statuses.iter().filter(|s| s.code() == tonic::Code::Unavailable).collect();
    assert!(!unavailable.is_empty(), "16 gRPC calls against a queue of 1 were all admitted");
    for status in unavailable {
        use tonic_types::StatusExt;
        let details = status.get_error_details();
        assert_eq!(details.retry_info().and_then(|r| r.retry_delay), Some(std::time::Duration::from_secs(1)));
        assert_eq!(details.error_info().map(|e| e.reason.as_str()), Some("UNAVAILABLE"));
    }
    // The gRPC client retries UNAVAILABLE with backoff (1 s hints), so callers that meet a
    // full queue still succeed.
    let answers = runtime.block_on(hammer(&server, &images, 4, 2, 8));
    assert_eq!(answers.len(), 8);
    assert_eq!(server.get("/readyz").0, 200);
}

async fn sequential(server: &Server, images: &[Vec<u8>]) -> Vec<PoseEstimate> {
    let client = Client::connect(&server.grpc_endpoint()).await.unwrap();
    let mut out = Vec::new();
    for image in images {
        let r = client.estimate(udapose_client::request("car", image.clone())).await.unwrap();
        out.push(r.estimates[0].clone());
    }
    out
}

/// `clients` tasks, each with its own connection, each sending `requests` estimates (images in
/// rotation), retrying UNAVAILABLE `retries` times. Returns (image index, estimate) for every
/// request; any error fails the test. Below the queue depth (64 by default; 16 clients have at
/// most 16 requests in flight) no retry is allowed, so a single UNAVAILABLE fails the test.
async fn hammer(
    server: &Server,
    images: &Arc<Vec<Vec<u8>>>,
    clients: usize,
    requests: usize,
    retries: u32,
) -> Vec<(usize, PoseEstimate)> {
    let mut tasks = Vec::new();
    for c in 0..clients {
        let options = ClientOptions { retries, ..ClientOptions::new(server.grpc_endpoint()) };
        let images = images.clone();
        tasks.push(tokio::spawn(async move {
            let client = Client::connect_with(options).await.unwrap();
            let mut out = Vec::new();
            for r in 0..requests {
                let i = (c + r) % images.len();
                let answer = client.estimate(udapose_client::request("car", images[i].clone())).await;
                let answer = answer.unwrap_or_else(|e| panic!("client {c} request {r}: {e}"));
                assert!(e_ok(&answer.estimates), "client {c} request {r}");
                out.push((i, answer.estimates[0].clone()));
            }
            out
        }));
    }
    let mut all = Vec::new();
    let mut per_code = BTreeMap::new();
    for t in tasks {
        match t.await {
            Ok(v) => all.extend(v),
            Err(e) => *per_code.entry(format!("{e}")).or_insert(0) += 1,
        }
    }
    assert!(per_code.is_empty(), "failed clients: {per_code:?}");
    all
}

/// Backbone passes of more than one crop, from /metrics.
fn batched_passes(server: &Server) -> f64 {
    let (_, metrics) = server.get("/metrics");
    let value = |prefix: &str| -> f64 {
        metrics.lines().find_map(|l| l.strip_prefix(prefix)).and_then(|v| v.trim().parse().ok()).unwrap()
    };
    value("udapose_batch_size_count{category=\"car\"}") - value("udapose_batch_size_bucket{category=\"car\",le=\"1\"}")
}

fn e_ok(estimates: &[PoseEstimate]) -> bool {
    estimates.len() == 1 && estimates[0].model_version.starts_with("seed-")
}

/// `clients` simultaneous unary calls on a raw stub; the failures' statuses.
async fn raw_grpc_burst(server: &Server, images: &Arc<Vec<Vec<u8>>>, clients: usize) -> Vec<tonic::Status> {
    use udapose_proto::v1::{EstimateRequest, estimate_request::Input, pose_service_client::PoseServiceClient};
    let channel = tonic::transport::Endpoint::from_shared(server.grpc_endpoint()).unwrap().connect().await.unwrap();
    let calls = (0..clients).map(|i| {
        let mut stub = PoseServiceClient::new(channel.clone());
        let image = images[i % DISTINCT].clone();
        tokio::spawn(async move {
            let request =
                EstimateRequest { category: "car".into(), input: Some(Input::Image(image)), ..Default::default() };
            stub.estimate(request).await.err()
        })
    });
    let mut out = Vec::new();
    for call in calls.collect::<Vec<_>>() {
        out.extend(call.await.unwrap());
    }
    out
}
