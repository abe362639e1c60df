//! Failover over several endpoints, against in-process fake replicas on loopback (no model, no
//! libtorch): each answers with its own name, can be made to answer UNAVAILABLE, and can be
//! killed (its runtime dropped, so its port refuses and its open connections break) and
//! restarted on the same port.

use std::{
    net::SocketAddr,
    pin::Pin,
    process::{Command, Output},
    sync::{
        Arc,
        atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use tokio::sync::{mpsc, oneshot};
use tokio_stream::{Stream, StreamExt, wrappers::ReceiverStream};
use tonic::{
    Code, Request, Response, Status, Streaming,
    transport::{Server, server::TcpIncoming},
};
use udapose_client::{ActivationEntry, Client, ClientOptions};
use udapose_proto::v1::{
    ActivateRequest, DescribeModelRequest, EstimateRequest, EstimateResponse, ListModelsRequest, ListModelsResponse,
    ListVersionsRequest, ListVersionsResponse, ModelDescription, RollbackRequest,
    model_service_server::{ModelService, ModelServiceServer},
    pose_service_server::{PoseService, PoseServiceServer},
};

/// What a replica saw, and how it behaves; survives its restarts.
#[derive(Default)]
struct Counters {
    /// Estimates (unary calls and stream frames) and activations received.
    hits: AtomicUsize,
    activations: AtomicUsize,
    /// Answer UNAVAILABLE with this RetryInfo hint (ms), as an overloaded server does.
    busy: AtomicBool,
    hint_ms: AtomicU64,
}

impl Counters {
    fn refuse(&self) -> Result<(), Status> {
        if !self.busy.load(Ordering::SeqCst) {
            return Ok(());
        }
        let mut details = tonic_types::ErrorDetails::new();
        details.set_retry_info(Some(Duration::from_millis(self.hint_ms.load(Ordering::SeqCst))));
        Err(<Status as tonic_types::StatusExt>::with_error_details(Code::Unavailable, "queue full", details))
    }
}

#[derive(Clone)]
struct Fake {
    name: &'static str,
    counters: Arc<Counters>,
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

#[tonic::async_trait]
impl PoseService for Fake {
    async fn estimate(&self, request: Request<EstimateRequest>) -> Result<Response<EstimateResponse>, Status> {
        self.counters.hits.fetch_add(1, Ordering::SeqCst);
        self.counters.refuse()?;
        let frame_id = request.into_inner().frame_id;
        Ok(Response::new(EstimateResponse { model_version: self.name.into(), frame_id, ..Default::default() }))
    }

    type EstimateStreamStream = BoxStream<EstimateResponse>;

    async fn estimate_stream(
        &self,
        request: Request<Streaming<EstimateRequest>>,
    ) -> Result<Response<Self::EstimateStreamStream>, Status> {
        self.counters.refuse()?;
        let fake = self.clone();
        let answers = request.into_inner().map(move |frame| {
            fake.counters.hits.fetch_add(1, Ordering::SeqCst);
            let frame_id = frame?.frame_id;
            Ok(EstimateResponse { model_version: fake.name.into(), frame_id, ..Default::default() })
        });
        Ok(Response::new(Box::pin(answers)))
    }
}

#[tonic::async_trait]
impl ModelService for Fake {
    async fn list_models(&self, _: Request<ListModelsRequest>) -> Result<Response<ListModelsResponse>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }

    async fn describe_model(&self, _: Request<DescribeModelRequest>) -> Result<Response<ModelDescription>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }

    async fn list_versions(&self, _: Request<ListVersionsRequest>) -> Result<Response<ListVersionsResponse>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }

    async fn activate(&self, request: Request<ActivateRequest>) -> Result<Response<ActivationEntry>, Status> {
        self.counters.activations.fetch_add(1, Ordering::SeqCst);
        self.counters.refuse()?;
        let version = request.into_inner().version;
        Ok(Response::new(ActivationEntry { version, actor: self.name.into(), ..Default::default() }))
    }

    async fn rollback(&self, _: Request<RollbackRequest>) -> Result<Response<ActivationEntry>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }
}

/// One fake server on its own thread and runtime: stopping it drops the runtime, which closes
/// the listener and every connection at once, as a crash does.
struct Replica {
    fake: Fake,
    addr: SocketAddr,
    running: Option<(oneshot::Sender<()>, JoinHandle<()>)>,
    /// While stopped, the port held bound (not listening) so that a replica another test starts
    /// is not handed it; best effort, as a port in TIME_WAIT cannot be bound this way.
    held: Option<tokio::net::TcpSocket>,
}

impl Replica {
    fn start(name: &'static str) -> Replica {
        let fake = Fake { name, counters: Arc::default() };
        let mut replica = Replica { fake, addr: "127.0.0.1:0".parse().unwrap(), running: None, held: None };
        replica.restart();
        replica
    }

    /// Starts (again) on the same port (std sets SO_REUSEADDR, so the port is free at once).
    fn restart(&mut self) {
        self.held = None;
        let listener = std::net::TcpListener::bind(self.addr).unwrap();
        listener.set_nonblocking(true).unwrap();
        self.addr = listener.local_addr().unwrap();
        let (kill, killed) = oneshot::channel::<()>();
        let fake = self.fake.clone();
        let thread = std::thread::spawn(move || {
            let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
            runtime.block_on(async move {
                let incoming = TcpIncoming::from(tokio::net::TcpListener::from_std(listener).unwrap());
                let server = Server::builder()
                    .add_service(PoseServiceServer::new(fake.clone()))
                    .add_service(ModelServiceServer::new(fake))
                    .serve_with_incoming(incoming);
                tokio::select! {
                    _ = server => {}
                    _ = killed => {}
                }
            });
            runtime.shutdown_background();
        });
        self.running = Some((kill, thread));
    }

    fn stop(&mut self) {
        if let Some((kill, thread)) = self.running.take() {
            let _ = kill.send(());
            thread.join().unwrap();
            self.held = refusing_port(self.addr).ok();
        }
    }

    fn endpoint(&self) -> String {
        self.addr.to_string()
    }

    fn hits(&self) -> usize {
        self.fake.counters.hits.load(Ordering::SeqCst)
    }

    fn busy(&self, busy: bool, hint: Duration) {
        self.fake.counters.hint_ms.store(hint.as_millis() as u64, Ordering::SeqCst);
        self.fake.counters.busy.store(busy, Ordering::SeqCst);
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A bound port nothing listens on: connections to it are refused, and without SO_REUSEADDR no
/// other socket can bind it while it is held.
fn refusing_port(addr: SocketAddr) -> std::io::Result<tokio::net::TcpSocket> {
    let socket = tokio::net::TcpSocket::new_v4()?;
    socket.bind(addr)?;
    Ok(socket)
}

async fn client(replicas: &[&Replica], retries: u32) -> Client {
    let endpoints = replicas.iter().map(|r| r.endpoint()).collect();
    Client::connect_with(ClientOptions { endpoints, retries, ..ClientOptions::new("") }).await.unwrap()
}

/// Which replica answered an estimate.
async fn estimate(client: &Client) -> Result<String, udapose_client::Error> {
    Ok(client.estimate(udapose_client::request("car", b"image".to_vec())).await?.model_version)
}

/// `n` estimates at once; the names of the replicas that answered, or the errors.
async fn concurrent(client: &Client, n: usize) -> Vec<Result<String, String>> {
    let tasks: Vec<_> = (0..n)
        .map(|_| {
            let client = client.clone();
            tokio::spawn(async move { estimate(&client).await.map_err(|e| e.to_string()) })
        })
        .collect();
    let mut out = Vec::new();
    for task in tasks {
        out.push(task.await.unwrap());
    }
    out
}

fn count(answers: &[String], name: &str) -> usize {
    answers.iter().filter(|a| *a == name).count()
}

#[tokio::test(flavor = "multi_thread")]
async fn calls_are_spread_over_every_endpoint() {
    let replicas = [Replica::start("a"), Replica::start("b"), Replica::start("c")];
    let client = client(&replicas.iter().collect::<Vec<_>>(), 1).await;
    let mut answers = Vec::new();
    for _ in 0..60 {
        answers.push(estimate(&client).await.unwrap());
    }
    for name in ["a", "b", "c"] {
        assert!(count(&answers, name) >= 10, "{name} answered {} of 60", count(&answers, name));
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_dead_endpoint_is_skipped_and_comes_back_once_restarted() {
    let [a, mut b, c] = [Replica::start("a"), Replica::start("b"), Replica::start("c")];
    let client = client(&[&a, &b, &c], 1).await;
    for _ in 0..6 {
        estimate(&client).await.unwrap();
    }
    b.stop();

    let mut answers = Vec::new();
    for i in 0..30 {
        answers.push(estimate(&client).await.unwrap_or_else(|e| panic!("sequential call {i} with b down: {e}")));
    }
    for result in concurrent(&client, 40).await {
        answers.push(result.unwrap_or_else(|e| panic!("concurrent call with b down: {e}")));
    }
    assert_eq!(count(&answers, "b"), 0);
    assert!(count(&answers, "a") >= 20 && count(&answers, "c") >= 20, "{answers:?}");

    // Back on the same port: it gets calls again once its cool-down is over.
    b.restart();
    let started = Instant::now();
    while estimate(&client).await.unwrap() != "b" {
        assert!(started.elapsed() < Duration::from_secs(12), "b got no call after its restart");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let back = started.elapsed();
    let mut answers = Vec::new();
    for _ in 0..30 {
        answers.push(estimate(&client).await.unwrap());
    }
    assert!(count(&answers, "b") >= 5, "b back after {back:?}, then {answers:?}");
    eprintln!("b answered again {back:?} after its restart");
}

#[tokio::test(flavor = "multi_thread")]
async fn an_overloaded_endpoint_sends_the_call_to_another_at_once() {
    let [a, b] = [Replica::start("a"), Replica::start("b")];
    // A hint long enough that sleeping on it would show.
    a.busy(true, Duration::from_secs(3));
    let client = client(&[&a, &b], 2).await;
    let started = Instant::now();
    let mut answers = Vec::new();
    for _ in 0..10 {
        answers.push(estimate(&client).await.unwrap());
    }
    answers.extend(concurrent(&client, 10).await.into_iter().map(Result::unwrap));
    assert_eq!(count(&answers, "b"), 20);
    assert!(a.hits() >= 1, "a was never tried");
    assert!(started.elapsed() < Duration::from_secs(2), "waited for the hint: {:?}", started.elapsed());

    // Not overloaded any more: a gets calls again.
    a.busy(false, Duration::ZERO);
    let started = Instant::now();
    while estimate(&client).await.unwrap() != "a" {
        assert!(started.elapsed() < Duration::from_secs(12), "a got no call once it was no longer busy");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn with_every_endpoint_down_a_call_fails_after_bounded_retries() {
    // Refused connections: a clear error, soon. The ports are held bound but not listening, so
    // a replica that another test starts meanwhile cannot be handed one of them (a stopped
    // replica's freed port was, once, and this test connected to it).
    let any = "127.0.0.1:0".parse().unwrap();
    let held = [refusing_port(any).unwrap(), refusing_port(any).unwrap()];
    let [a, b] = held.each_ref().map(|socket| socket.local_addr().unwrap().to_string());
    let options = ClientOptions { endpoints: vec![a.clone(), b.clone()], ..ClientOptions::new("") };
    let err = Client::connect_with(options.clone()).await.expect_err("connected to nothing");
    assert!(matches!(err, udapose_client::Error::Connect { .. }), "{err:?}");
    let lazy = Client::connect_with(ClientOptions { eager: false, retries: 2, ..options }).await.unwrap();
    let started = Instant::now();
    let err = estimate(&lazy).await.unwrap_err();
    let elapsed = started.elapsed();
    assert_eq!(err.code(), Some(Code::Unavailable), "{err}");
    assert!(elapsed < Duration::from_secs(5), "{elapsed:?}");
    let message = err.to_string();
    assert!(message.contains(&a) && message.contains(&b), "{message}");
    eprintln!("all endpoints down: {message} ({elapsed:?})");

    // Overloaded everywhere: each endpoint tried, then `retries` more tries after a pause.
    let [a, b] = [Replica::start("a"), Replica::start("b")];
    a.busy(true, Duration::from_millis(50));
    b.busy(true, Duration::from_millis(50));
    let client = client(&[&a, &b], 2).await;
    let err = estimate(&client).await.unwrap_err();
    assert_eq!(err.code(), Some(Code::Unavailable), "{err}");
    let tries = a.hits() + b.hits();
    assert!((3..=6).contains(&tries) && a.hits() >= 1 && b.hits() >= 1, "a {} b {}", a.hits(), b.hits());
}

#[tokio::test(flavor = "multi_thread")]
async fn a_call_that_is_not_idempotent_goes_to_a_healthy_endpoint_once() {
    let [mut a, b] = [Replica::start("a"), Replica::start("b")];
    let client = client(&[&a, &b], 3).await;
    a.stop();
    // An idempotent call finds a down (and is answered by b).
    for _ in 0..2 {
        assert_eq!(estimate(&client).await.unwrap(), "b");
    }
    for _ in 0..4 {
        let entry = client.activate("car", "v2", "", None).await.unwrap();
        assert_eq!(entry.actor, "b");
    }
    // Overloaded: the answer is the caller's (no resend without expected_generation).
    b.busy(true, Duration::from_millis(10));
    let before = b.fake.counters.activations.load(Ordering::SeqCst);
    let err = client.activate("car", "v2", "", None).await.unwrap_err();
    assert_eq!(err.code(), Some(Code::Unavailable), "{err}");
    assert_eq!(b.fake.counters.activations.load(Ordering::SeqCst), before + 1);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_video_stream_moves_to_another_endpoint_when_its_server_dies() {
    let mut replicas = [Replica::start("a"), Replica::start("b")];
    let client = client(&replicas.iter().collect::<Vec<_>>(), 2).await;
    let (frames, rx) = mpsc::channel(4);
    let mut answers = client.estimate_stream(ReceiverStream::new(rx)).await.unwrap();
    let frame = |i: usize| EstimateRequest { frame_id: format!("frame-{i}"), ..udapose_client::request("car", vec![]) };
    let mut got = Vec::new();
    for i in 0..10 {
        if i == 4 {
            // The replica serving the stream dies between two frames.
            let serving = if got[0] == ("frame-0".to_owned(), "a".to_owned()) { 0 } else { 1 };
            replicas[serving].stop();
        }
        frames.send(frame(i)).await.unwrap();
        let answer = tokio::time::timeout(Duration::from_secs(10), answers.message())
            .await
            .expect("an answer")
            .unwrap_or_else(|e| panic!("frame {i}: {e}"))
            .expect("not the end");
        got.push((answer.frame_id, answer.model_version));
    }
    drop(frames);
    assert!(answers.message().await.unwrap().is_none());
    let ids: Vec<String> = got.iter().map(|g| g.0.clone()).collect();
    assert_eq!(ids, (0..10).map(|i| format!("frame-{i}")).collect::<Vec<_>>(), "in order, none lost or repeated");
    let first = &got[0].1;
    assert!(got[..4].iter().all(|g| &g.1 == first) && got[4..].iter().all(|g| &g.1 != first), "{got:?}");
}

fn udapose(args: &[&str], env_endpoint: Option<&str>) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_udapose"));
    command.args(args).env_remove("UDAPOSE_TOKEN").env_remove("UDAPOSE_ENDPOINT");
    if let Some(e) = env_endpoint {
        command.env("UDAPOSE_ENDPOINT", e);
    }
    command.output().unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn the_cli_takes_several_endpoints() {
    let [mut dead, live] = [Replica::start("dead"), Replica::start("live")];
    dead.stop();
    let image = std::env::temp_dir().join(format!("udapose-failover-{}.png", std::process::id()));
    std::fs::write(&image, b"not decoded by the fake").unwrap();
    let (dead, live) = (dead.endpoint(), live.endpoint());
    let both = format!("{dead},{live}");
    let runs = [
        (vec!["--endpoints", &both], None),
        (vec!["--endpoint", &both], None),
        (vec!["--endpoint", &dead, "--endpoint", &live], None),
        (vec![], Some(both.clone())),
    ];
    for (flags, env) in runs {
        let mut args: Vec<String> = flags.iter().map(|f| f.to_string()).collect();
        args.extend(["estimate", "--category", "car", "--json"].map(String::from));
        args.extend([image.display().to_string(), image.display().to_string()]);
        let out = tokio::task::spawn_blocking(move || {
            udapose(&args.iter().map(String::as_str).collect::<Vec<_>>(), env.as_deref())
        })
        .await
        .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{flags:?}: {stdout}{}", String::from_utf8_lossy(&out.stderr));
        let versions: Vec<String> = stdout
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["model_version"].as_str().unwrap().into())
            .collect();
        assert_eq!(versions, ["live", "live"], "{flags:?}");
    }
    let help = udapose(&["--help"], None);
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(help.contains("--endpoints") && help.contains("fail"), "{help}");
    std::fs::remove_file(&image).unwrap();
}
