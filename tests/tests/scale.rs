//! Scale-out on one machine (issue "Deploy and scale out"): 3 `serve` replicas and `adapt`
//! workers as separate processes on a real S3-compatible server (s3s-fs, on loopback), with
//! estimates through the client's failover on every replica throughout. Targets streamed to
//! any replica reach the worker, the job's version reaches every replica, a replica's
//! `kill -9` fails no request, a worker's `kill -9` loses no job and activates nothing partial,
//! a second worker loses cleanly, and a rollback on one replica reaches all.
//!
//! Needs `make test`'s quick model and data, and `UDAPOSE_S3S_FS` (the s3s-fs binary that
//! `make test` installs).

mod support;

use std::{
    collections::BTreeSet,
    fs,
    net::TcpStream,
    process::{Child, Command, Stdio},
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, Ordering},
    },
    thread,
    time::{Duration, Instant},
};

use serde_json::Value;
use support::{Server, beside_tests, env_path, free_addrs, quick_images, scratch_dir};

/// Replicas re-read the store this often (`--poll`).
const POLL: Duration = Duration::from_secs(2);
/// How long a new version may take to reach every replica: a poll, the download, the batch in
/// progress and the load. Not a speed claim (`udapose-bench scale` measures propagation:
/// reports/scale.md); only a bound that a replica that never swaps exceeds. It was 4 polls, and
/// on a loaded 2-core machine one replica took 9.5 s, twice.
const PROPAGATION: Duration = Duration::from_secs(30);
const JOB_TIMEOUT: Duration = Duration::from_secs(300);
const KEY: &str = "udapose-test";
const SECRET: &str = "udapose-test-secret";

/// An s3s-fs server on a free loopback port, with bucket `fleet`; killed on drop.
struct S3 {
    child: Child,
    url: String,
    endpoint: String,
    root: std::path::PathBuf,
    /// The servers' `--cache-dir`s, removed with the store.
    caches: std::path::PathBuf,
}

impl S3 {
    fn start() -> S3 {
        let binary = env_path("UDAPOSE_S3S_FS");
        let root = scratch_dir("s3");
        fs::create_dir_all(root.join("fleet")).unwrap(); // a bucket is a directory
        let [addr] = free_addrs();
        let child = Command::new(&binary)
            .args(["--host", "127.0.0.1", "--port", &addr.port().to_string()])
            .args(["--access-key", KEY, "--secret-key", SECRET])
            .arg(&root)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", binary.display()));
        let deadline = Instant::now() + Duration::from_secs(10);
        while TcpStream::connect(addr).is_err() {
            assert!(Instant::now() < deadline, "s3s-fs did not listen on {addr}");
            thread::sleep(Duration::from_millis(50));
        }
        let caches = scratch_dir("s3-caches");
        S3 { child, url: "s3://fleet/udapose".into(), endpoint: format!("http://{addr}"), root, caches }
    }

    /// A server process of `role` on this store.
    fn server(&self, name: &str, role: &str, extra: &[&str]) -> Server {
        let mut config = Server::config(name)
            .quick_model()
            .store(&self.url)
            .env("AWS_ACCESS_KEY_ID", KEY)
            .env("AWS_SECRET_ACCESS_KEY", SECRET)
            .env("AWS_REGION", "us-east-1");
        let cache = self.caches.join(name).display().to_string();
        let poll = POLL.as_secs().to_string();
        for arg in ["--s3-endpoint", &self.endpoint, "--s3-allow-http", "--role", role, "--poll", &poll]
            .into_iter()
            .chain(["--cache-dir", &cache, "--gate", "advisory", "--adapt-min-images", "100000"])
            .chain(extra.iter().copied())
        {
            config = config.arg(arg);
        }
        config.start()
    }

    /// The objects under `prefix` in the store (s3s-fs keeps them as plain files).
    fn files(&self, prefix: &str) -> BTreeSet<String> {
        let dir = self.root.join("fleet/udapose").join(prefix);
        fs::read_dir(dir).map_or_else(
            |_| BTreeSet::new(),
            |d| d.map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect(),
        )
    }
}

impl Drop for S3 {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = fs::remove_dir_all(&self.root);
        let _ = fs::remove_dir_all(&self.caches);
    }
}

/// What the load saw since it was last asked.
#[derive(Default)]
struct Stats {
    ok: usize,
    failed: usize,
    first_failure: Option<String>,
}

/// Estimates through the client library over every replica until stopped.
struct Load {
    stop: Arc<AtomicBool>,
    stats: Arc<Mutex<Stats>>,
    thread: Option<thread::JoinHandle<()>>,
}

impl Load {
    fn start(replicas: &[&Server]) -> Load {
        let endpoints: Vec<String> = replicas.iter().map(|s| s.grpc_addr.to_string()).collect();
        let image = quick_images("source", 1).remove(0).bytes;
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(Mutex::new(Stats::default()));
        let (stop2, stats2) = (stop.clone(), stats.clone());
        let thread = thread::spawn(move || {
            let rt = tokio::runtime::Runtime::new().unwrap();
            rt.block_on(async move {
                let mut options = udapose_client::ClientOptions::new(endpoints[0].clone());
                options.endpoints = endpoints;
                let client = udapose_client::Client::connect_with(options).await.unwrap();
                // Two requests in flight: every replica gets some, and the machine keeps
                // cores for the job.
                let one = |client: udapose_client::Client| {
                    let (stop, stats, image) = (stop2.clone(), stats2.clone(), image.clone());
                    async move {
                        while !stop.load(Ordering::Relaxed) {
                            let r = client.estimate(udapose_client::request("car", image.clone())).await;
                            {
                                let mut s = stats.lock().unwrap();
                                match r {
                                    Ok(_) => s.ok += 1,
                                    Err(e) => {
                                        s.failed += 1;
                                        s.first_failure.get_or_insert(e.to_string());
                                    }
                                }
                            }
                            tokio::time::sleep(Duration::from_millis(50)).await;
                        }
                    }
                };
                tokio::join!(one(client.clone()), one(client));
            });
        });
        Load { stop, stats, thread: Some(thread) }
    }

    /// (ok, failed, first failure) so far, and the counters reset.
    fn take(&self) -> (usize, usize, Option<String>) {
        let s = std::mem::take(&mut *self.stats.lock().unwrap());
        (s.ok, s.failed, s.first_failure)
    }
}

impl Drop for Load {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn post(server: &Server, path: &str, body: &[u8]) -> Value {
    let r = server.request("POST", path, &[], body);
    assert_eq!(r.status, 200, "POST {path}: {}", r.body);
    r.json()
}

fn job(server: &Server, id: &str) -> Value {
    let (status, body) = server.get(&format!("/v1/jobs/{id}"));
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Polls job `id` on `server` until `done`; fails after JOB_TIMEOUT with every log.
fn wait_job(server: &Server, id: &str, logs: &[&Server], done: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + JOB_TIMEOUT;
    loop {
        let j = job(server, id);
        if done(&j) {
            return j;
        }
        assert!(Instant::now() < deadline, "job {id}: {j}\n{}", logs.iter().map(|s| s.log()).collect::<String>());
        thread::sleep(Duration::from_millis(200));
    }
}

fn terminal(j: &Value) -> bool {
    !["QUEUED", "RUNNING", "VALIDATING"].contains(&j["state"].as_str().unwrap())
}

/// The version `server` answers estimates with.
fn serving(server: &Server, image: &[u8]) -> String {
    post(server, "/v1/pose/car", image)["model_version"].as_str().unwrap().to_owned()
}

/// Waits until every replica answers with `version`; returns the slowest replica's delay.
fn wait_serving(replicas: &[&Server], version: &str, image: &[u8]) -> Duration {
    let start = Instant::now();
    let mut pending: Vec<&&Server> = replicas.iter().collect();
    while !pending.is_empty() {
        pending.retain(|s| serving(s, image) != version);
        assert!(
            start.elapsed() < PROPAGATION,
            "{} replica(s) still not serving {version} after {:?}",
            pending.len(),
            start.elapsed()
        );
        thread::sleep(Duration::from_millis(50));
    }
    start.elapsed()
}

/// Streams `n` unseen adapt images of `domain` (from `skip` on) round-robin to `replicas`;
/// returns how many were accepted.
fn stream(replicas: &[&Server], domain: &str, skip: usize, n: usize) -> usize {
    let dir = env_path("UDAPOSE_QUICK_DATA").join(domain).join("adapt/images/car");
    let mut files: Vec<_> = fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    assert!(files.len() >= skip + n, "{} has {} images", dir.display(), files.len());
    files[skip..skip + n]
        .iter()
        .enumerate()
        .filter(|(i, f)| {
            let ack = post(replicas[i % replicas.len()], "/v1/adapt/car/images", &fs::read(f).unwrap());
            ack["results"][0]["status"] == "ACCEPTED"
        })
        .count()
}

#[test]
fn three_replicas_and_a_worker_on_s3_adapt_swap_fail_over_and_roll_back() {
    let s3 = S3::start();
    let mut worker = s3.server("scale-worker", "adapt", &[]);
    let r: Vec<Server> = (0..3).map(|i| s3.server(&format!("scale-serve-{i}"), "serve", &[])).collect();
    let image = quick_images("source", 1).remove(0).bytes;
    let seed = serving(&r[0], &image);
    let load = Load::start(&[&r[0], &r[1], &r[2]]);

    // 1. Targets streamed round-robin to the serve replicas all reach the worker's buffer.
    let sent = 30;
    assert_eq!(stream(&[&r[0], &r[1], &r[2]], "combined", 0, sent), sent);
    assert_eq!(s3.files("buffers/car").iter().filter(|f| f.ends_with(".json")).count(), sent);
    // 2. A job asked on one replica runs on the worker and is watched on another.
    let id = post(&r[0], "/v1/adapt/car/jobs", b"{}")["job_id"].as_str().unwrap().to_owned();
    let watch = Command::new(beside_tests("udapose"))
        .args(["--endpoints", &r[2].grpc_addr.to_string(), "jobs", "watch", &id])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the udapose binary (build the workspace first)");
    let done = wait_job(&r[1], &id, &[&worker], terminal);
    assert_eq!(done["state"], "ACTIVATED", "{done}\n{}", worker.log());
    let used = done["images_used"].as_u64().unwrap() + done["images_held_out"].as_u64().unwrap();
    assert_eq!(used, sent as u64, "every streamed image reached the worker: {done}");
    assert!(worker.log().contains("took a job queued on another replica"), "{}", worker.log());
    let watched = watch.wait_with_output().unwrap();
    let watched = String::from_utf8_lossy(&watched.stdout).into_owned() + &String::from_utf8_lossy(&watched.stderr);
    assert!(watched.contains("RUNNING") && watched.contains("ACTIVATED"), "WatchJob on a serve replica:\n{watched}");
    let v1 = done["version"].as_str().unwrap().to_owned();
    let took = wait_serving(&[&r[0], &r[1], &r[2]], &v1, &image);
    let (ok, failed, why) = load.take();
    assert_eq!(failed, 0, "{failed} failed requests during the job and its swap ({ok} ok): {why:?}");
    eprintln!("swap propagation {took:?}; {ok} requests ok during the job");

    // 3. kill -9 of one replica under load: the client fails over, nothing fails.
    let mut r = r;
    let mut gone = r.pop().unwrap();
    gone.kill9();
    thread::sleep(Duration::from_secs(3));
    let (ok, failed, why) = load.take();
    assert!(ok > 0);
    assert_eq!(failed, 0, "{failed} failed requests after a replica's kill -9 ({ok} ok): {why:?}");

    // 4. A rollback on one replica reaches the others.
    let rolled = post(&r[1], "/v1/models/car/rollback", b"{\"reason\":\"test\"}");
    assert_eq!(rolled["version"], seed.as_str(), "{rolled}");
    wait_serving(&[&r[0], &r[1]], &seed, &image);

    // 5. kill -9 of the worker mid-job; its restart resumes the job, which activates only a
    //    complete version. The restarted worker stops itself just before activating...
    assert_eq!(stream(&[&r[0], &r[1]], "combined", sent, sent), sent);
    let id = post(&r[0], "/v1/adapt/car/jobs", b"{}")["job_id"].as_str().unwrap().to_owned();
    wait_job(&r[0], &id, &[&worker], |j| j["state"] == "RUNNING");
    worker.crash_and_spawn(&[("UDAPOSE_FAILPOINT", "stop:before-activate")]);
    let deadline = Instant::now() + JOB_TIMEOUT;
    while !worker.stopped() {
        assert!(Instant::now() < deadline, "the worker never reached activation\n{}", worker.log());
        thread::sleep(Duration::from_millis(200));
    }
    // 6. ...where a second worker, started by mistake, takes the job over and activates it;
    //    the first, resumed with its stale generation, loses the activation and stands by.
    let second = s3.server("scale-worker-2", "adapt", &[]);
    let done = wait_job(&r[1], &id, &[&worker, &second], terminal);
    assert_eq!(done["state"], "ACTIVATED", "{done}\n{}", second.log());
    worker.signal("CONT");
    let deadline = Instant::now() + Duration::from_secs(30);
    while !worker.log().contains("standing by") {
        assert!(Instant::now() < deadline, "the first worker did not stand by\n{}", worker.log());
        thread::sleep(Duration::from_millis(200));
    }
    assert!(worker.log().contains("activation conflict"), "{}", worker.log());
    let (_, log) = r[0].get("/v1/models/car/versions");
    let log: Value = serde_json::from_str(&log).unwrap();
    let by_job = log["activations"].as_array().unwrap().iter().filter(|a| a["job_id"] == id.as_str()).count();
    assert_eq!(by_job, 1, "exactly one activation for job {id}: {log}");
    // Every activated version is complete (listed with its manifest).
    let versions: BTreeSet<&str> =
        log["versions"].as_array().unwrap().iter().map(|v| v["version"].as_str().unwrap()).collect();
    for a in log["activations"].as_array().unwrap() {
        assert!(versions.contains(a["version"].as_str().unwrap()), "{a} is not a complete version: {log}");
    }
    wait_serving(&[&r[0], &r[1]], done["version"].as_str().unwrap(), &image);
    let (ok, failed, why) = load.take();
    assert_eq!(failed, 0, "{failed} failed requests during the worker crashes ({ok} ok): {why:?}");
    drop(load);
}
