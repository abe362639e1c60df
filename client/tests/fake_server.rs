//! The adaptation client against an in-process fake `AdaptationService` on loopback (no model,
//! no libtorch): resending after a broken stream and a full buffer, resuming a job's events,
//! which calls are retried, and the `udapose adapt` / `jobs` output lines and exit status.

use std::{
    collections::HashSet,
    path::PathBuf,
    pin::Pin,
    process::{Command, Output},
    sync::{Arc, Mutex},
    time::Duration,
};

use sha2::{Digest, Sha256};
use tokio::sync::mpsc;
use tokio_stream::{Stream, wrappers::ReceiverStream};
use tonic::{
    Code, Request, Response, Status, Streaming,
    transport::{Server, server::TcpIncoming},
};
use udapose_client::{
    AdaptOverrides, Client, ClientOptions, GateCriterion, Job, JobEvent, JobState, TargetAck, Upload,
    target_ack::{self, Rejection},
};
use udapose_proto::v1::{
    CancelJobRequest, GetJobRequest, ListJobsRequest, ListJobsResponse, ListRegressionSetsRequest,
    ListRegressionSetsResponse, StartJobRequest, TargetImage, WatchJobRequest,
    adaptation_service_server::{AdaptationService, AdaptationServiceServer},
};

#[derive(Default)]
struct State {
    stored: HashSet<String>,
    capacity: usize,
    streams: usize,
    /// On the first stream: the n-th image (1-based) is stored, then the stream fails before
    /// its ack.
    break_at: Option<usize>,
    /// The buffer grows (a job used images) after this many BUFFER_FULL rejections.
    grow_after_full: Option<usize>,
    full_rejections: usize,
    start_calls: usize,
    /// The first StartJob calls answered UNAVAILABLE.
    start_unavailable: usize,
    /// The job's history.
    events: Vec<JobEvent>,
    reason: String,
    /// The after_seq of each WatchJob call.
    watch_calls: Vec<u64>,
    /// The first WatchJob stream fails after this many events.
    watch_break_after: Option<usize>,
}

#[derive(Default)]
struct Fake(Mutex<State>);

/// The service (a local type, to implement the generated trait on).
struct Svc(Arc<Fake>);

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

fn sha(bytes: &[u8]) -> String {
    format!("{:x}", Sha256::digest(bytes))
}

impl Fake {
    fn job(&self) -> Job {
        let s = self.0.lock().unwrap();
        let last = s.events.last().cloned();
        Job {
            job_id: "j1".into(),
            category: "car".into(),
            state: last.as_ref().map_or(JobState::Queued as i32, |e| e.state),
            source_version: "seed-1".into(),
            version: last.as_ref().map_or(String::new(), |e| e.version.clone()),
            reason: s.reason.clone(),
            last_event: last,
            ..Default::default()
        }
    }
}

#[tonic::async_trait]
impl AdaptationService for Svc {
    type StreamTargetsStream = BoxStream<TargetAck>;
    type WatchJobStream = BoxStream<JobEvent>;

    async fn stream_targets(
        &self,
        request: Request<Streaming<TargetImage>>,
    ) -> Result<Response<Self::StreamTargetsStream>, Status> {
        let mut images = request.into_inner();
        let (tx, rx) = mpsc::channel(16);
        let fake = self.0.clone();
        let first = {
            let mut s = fake.0.lock().unwrap();
            s.streams += 1;
            s.streams == 1
        };
        tokio::spawn(async move {
            let mut n = 0;
            while let Ok(Some(image)) = images.message().await {
                n += 1;
                let id = sha(&image.image);
                let ack = {
                    let mut s = fake.0.lock().unwrap();
                    if first && s.break_at == Some(n) {
                        s.stored.insert(id);
                        Err(Status::unavailable("going away"))
                    } else {
                        let (status, rejection, reason) = if s.stored.contains(&id) {
                            (target_ack::Status::Duplicate, Rejection::Unspecified, String::new())
                        } else if s.stored.len() >= s.capacity {
                            s.full_rejections += 1;
                            if s.grow_after_full == Some(s.full_rejections) {
                                s.capacity += 100;
                            }
                            (target_ack::Status::Rejected, Rejection::BufferFull, "BUFFER_FULL: no room".to_owned())
                        } else if image.image.starts_with(b"bad") {
                            (
                                target_ack::Status::Rejected,
                                Rejection::InvalidImage,
                                "INVALID_IMAGE: cannot decode".to_owned(),
                            )
                        } else {
                            s.stored.insert(id.clone());
                            (target_ack::Status::Accepted, Rejection::Unspecified, String::new())
                        };
                        Ok(TargetAck {
                            sha256: id,
                            status: status as i32,
                            rejection: rejection as i32,
                            reason,
                            buffered: s.stored.len() as u32,
                            capacity: s.capacity as u32,
                            job_id: String::new(),
                        })
                    }
                };
                let last = ack.is_err();
                if tx.send(ack).await.is_err() || last {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn start_job(&self, request: Request<StartJobRequest>) -> Result<Response<Job>, Status> {
        {
            let mut s = self.0.0.lock().unwrap();
            s.start_calls += 1;
            if s.start_calls <= s.start_unavailable {
                return Err(Status::unavailable("busy"));
            }
        }
        let mut job = self.0.job();
        job.state = JobState::Queued as i32;
        job.client_job_id = request.into_inner().client_job_id;
        Ok(Response::new(job))
    }

    async fn watch_job(&self, request: Request<WatchJobRequest>) -> Result<Response<Self::WatchJobStream>, Status> {
        let request = request.into_inner();
        if request.job_id != "j1" {
            return Err(Status::not_found(format!("no job {}", request.job_id)));
        }
        let mut s = self.0.0.lock().unwrap();
        s.watch_calls.push(request.after_seq);
        let mut items: Vec<Result<JobEvent, Status>> =
            s.events.iter().filter(|e| e.seq > request.after_seq).cloned().map(Ok).collect();
        if s.watch_calls.len() == 1
            && let Some(n) = s.watch_break_after
        {
            items.truncate(n);
            items.push(Err(Status::unavailable("restarting")));
        }
        Ok(Response::new(Box::pin(tokio_stream::iter(items))))
    }

    async fn get_job(&self, request: Request<GetJobRequest>) -> Result<Response<Job>, Status> {
        match request.into_inner().job_id.as_str() {
            "j1" => Ok(Response::new(self.0.job())),
            other => Err(Status::not_found(format!("no job {other}"))),
        }
    }

    async fn list_jobs(&self, _: Request<ListJobsRequest>) -> Result<Response<ListJobsResponse>, Status> {
        Ok(Response::new(ListJobsResponse { jobs: vec![self.0.job()] }))
    }

    async fn cancel_job(&self, _: Request<CancelJobRequest>) -> Result<Response<Job>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }

    async fn list_regression_sets(
        &self,
        _: Request<ListRegressionSetsRequest>,
    ) -> Result<Response<ListRegressionSetsResponse>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }
}

async fn serve(fake: &Arc<Fake>) -> String {
    let incoming = TcpIncoming::bind("127.0.0.1:0".parse().unwrap()).unwrap();
    let addr = incoming.local_addr().unwrap();
    let service = AdaptationServiceServer::new(Svc(fake.clone()));
    tokio::spawn(Server::builder().add_service(service).serve_with_incoming(incoming));
    addr.to_string()
}

async fn client(addr: &str, buffer_full_retries: u32) -> Client {
    let options = ClientOptions {
        buffer_full_retries,
        buffer_full_backoff: Duration::from_millis(10),
        ..ClientOptions::new(addr)
    };
    Client::connect_with(options).await.unwrap()
}

fn images(n: usize) -> Vec<(String, Vec<u8>)> {
    (0..n).map(|i| (format!("{i}.png"), format!("image {i}").into_bytes())).collect()
}

async fn upload_all(client: &Client, images: Vec<(String, Vec<u8>)>) -> Vec<Upload> {
    let mut uploads = client.stream_targets("car", tokio_stream::iter(images));
    let mut out = Vec::new();
    while let Some(u) = uploads.message().await.unwrap() {
        out.push(u);
    }
    out
}

fn statuses(uploads: &[Upload]) -> Vec<(String, target_ack::Status, u32)> {
    uploads.iter().map(|u| (u.name.clone(), u.ack.status(), u.sends)).collect()
}

fn event(seq: u64, state: JobState, round: u32) -> JobEvent {
    JobEvent {
        job_id: "j1".into(),
        seq,
        state: state as i32,
        round,
        max_rounds: 2,
        fired_ratio: 0.5,
        images_used: 3,
        images_held_out: 1,
        ..Default::default()
    }
}

fn history(end: JobState) -> Vec<JobEvent> {
    let gate = vec![GateCriterion {
        name: "score_margin".into(),
        active: 0.02,
        candidate: 0.03,
        threshold: 0.025,
        passed: end == JobState::Activated,
        detail: String::new(),
    }];
    vec![
        JobEvent { message: "queued".into(), ..event(1, JobState::Queued, 0) },
        JobEvent { eta_seconds: 65.0, ..event(2, JobState::Running, 1) },
        JobEvent { pose_change_median_deg: Some(2.5), ..event(3, JobState::Running, 2) },
        JobEvent { gate: gate.clone(), version: "j1".into(), ..event(4, JobState::Validating, 2) },
        JobEvent { gate, version: "j1".into(), message: "done".into(), ..event(5, end, 2) },
    ]
}

#[tokio::test]
async fn uploads_resume_after_a_broken_stream() {
    let fake = Arc::new(Fake::default());
    fake.0.lock().unwrap().capacity = 100;
    fake.0.lock().unwrap().break_at = Some(3);
    let addr = serve(&fake).await;
    let client = client(&addr, 2).await;
    let mut input = images(6);
    input[4].1 = b"bad bytes".to_vec();
    let got = statuses(&upload_all(&client, input).await);
    use target_ack::Status::*;
    let expected = [(Accepted, 1), (Accepted, 1), (Duplicate, 2), (Accepted, 2), (Rejected, 2), (Accepted, 2)];
    for (i, (status, sends)) in expected.into_iter().enumerate() {
        assert_eq!(got[i], (format!("{i}.png"), status, sends), "{got:?}");
    }
    assert_eq!(got.len(), 6);
    assert_eq!(fake.0.lock().unwrap().streams, 2);
}

#[tokio::test]
async fn buffer_full_images_are_resent_once_there_is_room_and_not_forever() {
    let fake = Arc::new(Fake::default());
    fake.0.lock().unwrap().capacity = 2;
    fake.0.lock().unwrap().grow_after_full = Some(3);
    let addr = serve(&fake).await;
    let got = statuses(&upload_all(&client(&addr, 2).await, images(5)).await);
    let sends: Vec<u32> = got.iter().map(|g| g.2).collect();
    assert!(got.iter().all(|g| g.1 == target_ack::Status::Accepted), "{got:?}");
    assert_eq!(sends, [1, 1, 2, 2, 2]);

    // A buffer that stays full: the rejection is final after the resends allowed.
    let fake = Arc::new(Fake::default());
    let addr = serve(&fake).await;
    let got = upload_all(&client(&addr, 2).await, images(2)).await;
    assert_eq!(got.len(), 2);
    assert!(got.iter().all(|u| udapose_client::buffer_full(&u.ack) && u.sends == 3), "{got:?}");
}

#[tokio::test]
async fn watching_resumes_after_the_last_event_seen() {
    let fake = Arc::new(Fake::default());
    fake.0.lock().unwrap().events = history(JobState::Activated);
    fake.0.lock().unwrap().watch_break_after = Some(2);
    let addr = serve(&fake).await;
    let client = client(&addr, 2).await;
    let mut events = client.watch_job("j1", 0).await.unwrap();
    let mut seqs = Vec::new();
    while let Some(e) = events.message().await.unwrap() {
        seqs.push(e.seq);
    }
    assert_eq!(seqs, [1, 2, 3, 4, 5]);
    assert_eq!(fake.0.lock().unwrap().watch_calls, [0, 2]);
    let err = client.watch_job("nope", 0).await.err().unwrap();
    assert_eq!(err.code(), Some(Code::NotFound));
}

#[tokio::test]
async fn start_job_is_retried_only_with_a_client_job_id() {
    let fake = Arc::new(Fake::default());
    fake.0.lock().unwrap().start_unavailable = 1;
    let addr = serve(&fake).await;
    let client = client(&addr, 2).await;
    let job = client.start_job("car", AdaptOverrides::default(), Some("cli-1")).await.unwrap();
    assert_eq!((job.client_job_id.as_str(), fake.0.lock().unwrap().start_calls), ("cli-1", 2));

    fake.0.lock().unwrap().start_calls = 0;
    let err = client.start_job("car", AdaptOverrides::default(), None).await.unwrap_err();
    assert_eq!((err.code(), fake.0.lock().unwrap().start_calls), (Some(Code::Unavailable), 1));
}

fn udapose(addr: &str, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_udapose"))
        .args(["--endpoint", addr])
        .args(args)
        .env_remove("UDAPOSE_TOKEN")
        .output()
        .unwrap()
}

fn folder(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for (name, bytes) in images(3) {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
    std::fs::write(dir.join("notes.txt"), b"not an image").unwrap();
    dir
}

#[tokio::test(flavor = "multi_thread")]
async fn the_cli_prints_the_documented_lines_and_exit_status() {
    let fake = Arc::new(Fake::default());
    fake.0.lock().unwrap().capacity = 100;
    fake.0.lock().unwrap().events = history(JobState::Activated);
    let addr = serve(&fake).await;
    let dir = folder("adapt");
    let images = dir.display().to_string();

    let run = |args: Vec<String>| {
        let addr = addr.clone();
        tokio::task::spawn_blocking(move || udapose(&addr, &args.iter().map(String::as_str).collect::<Vec<_>>()))
    };
    let args = |extra: &[&str]| {
        let mut a = vec!["adapt", "--category", "car", "--images", &images, "--seed", "3"];
        a.extend_from_slice(extra);
        a.into_iter().map(String::from).collect::<Vec<_>>()
    };

    let out = run(args(&[])).await.unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines[0], "uploaded 3 images to car: 3 accepted, 0 duplicate, 0 rejected (buffer 3/100)");
    assert_eq!(lines[1], "job j1 QUEUED category car from seed-1 (generation 0)");
    assert_eq!(lines[2], "#1 QUEUED round 0/2 fired 0.500 change - used 3 held-out 1 eta -: queued");
    assert_eq!(lines[3], "#2 RUNNING round 1/2 fired 0.500 change - used 3 held-out 1 eta 1m05s");
    assert_eq!(lines[4], "#3 RUNNING round 2/2 fired 0.500 change 2.50° used 3 held-out 1 eta -");
    assert_eq!(lines[5], "#4 VALIDATING round 2/2 fired 0.500 change - used 3 held-out 1 eta - version j1");
    assert_eq!(lines[6], "  gate score_margin active 0.0200 candidate 0.0300 threshold 0.0250 passed");
    assert_eq!(lines[7], "#5 ACTIVATED round 2/2 fired 0.500 change - used 3 held-out 1 eta - version j1: done");
    assert_eq!(lines[8], "job j1 ACTIVATED version j1", "the gate is not repeated when unchanged: {stdout}");
    assert_eq!(lines.len(), 9);

    // A rejected job: its reason, exit status 3; the images are now duplicates.
    {
        let mut s = fake.0.lock().unwrap();
        s.events = history(JobState::Rejected);
        s.reason = "score_margin: 0.030 < 0.035".into();
    }
    let out = run(args(&[])).await.unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(3), "{stdout}");
    assert!(stdout.starts_with("uploaded 3 images to car: 0 accepted, 3 duplicate, 0 rejected"), "{stdout}");
    assert_eq!(stdout.lines().last(), Some("job j1 REJECTED: score_margin: 0.030 < 0.035"));

    let out = run(args(&["--no-follow"])).await.unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    assert_eq!(stdout.lines().last(), Some("job j1 QUEUED category car from seed-1 (generation 0)"));

    let out = run(args(&["--json"])).await.unwrap();
    let lines: Vec<serde_json::Value> =
        String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(out.status.code(), Some(3));
    assert_eq!(lines[0]["uploads"]["duplicate"], 3);
    assert_eq!(lines[1]["job"]["job_id"], "j1");
    assert_eq!(lines[2]["event"]["seq"], 1);
    let result = &lines.last().unwrap()["result"];
    assert_eq!(
        (result["state"].as_str(), result["reason"].as_str()),
        (Some("REJECTED"), Some("score_margin: 0.030 < 0.035"))
    );

    // jobs: watch ends as adapt does; errors are one line with the gRPC code.
    let out = run(vec!["jobs".into(), "watch".into(), "j1".into(), "--after-seq".into(), "4".into()]).await.unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(3));
    assert!(stdout.starts_with("#5 REJECTED") && stdout.ends_with("job j1 REJECTED: score_margin: 0.030 < 0.035\n"));
    let out = run(vec!["jobs".into(), "list".into()]).await.unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.starts_with("JOB  CATEGORY  STATE     ROUND  IMAGES  VERSION  UPDATED  REASON\n"), "{stdout}");
    assert!(stdout.contains("j1   car       REJECTED  2/2    0+0     j1       -        score_margin"), "{stdout}");
    let out = run(vec!["jobs".into(), "get".into(), "nope".into()]).await.unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(String::from_utf8_lossy(&out.stderr), "udapose: error: getting job nope: NotFound: no job nope\n");
    std::fs::remove_dir_all(&dir).unwrap();
}
