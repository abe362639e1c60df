//! `udapose-lab bench scale`: scale-out on one machine (issue "Deploy and scale out"). Starts a
//! real S3-compatible store (s3s-fs, on loopback), one `--role adapt` worker and three
//! `--role serve` replicas as separate `udapose-server` processes on it, then measures with the
//! gRPC client library (`udapose-client`, endpoint failover):
//!
//! * throughput and p50/p99 with 1, 2 and 3 replicas (the same client concurrency), with each
//!   replica's answered requests and CPU time (from `/proc`); then the same with three other
//!   replicas at the server's default `--torch-threads 0`, which oversubscribes the shared cores;
//! * under a steady load over every replica, the failed requests in each fault: an adaptation
//!   job and the swap to its version after activation, the `kill -9` of a serve replica (and its
//!   restart), a rollback on one replica, and the `kill -9` of the worker in the middle of a job;
//! * the swap propagation time: from an activation (or rollback) to the first estimate each
//!   replica answers with the new version.
//!
//! Writes `reports/scale.json` and its Markdown twin.

use std::{
    fs,
    net::{SocketAddr, TcpListener, TcpStream},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, AtomicUsize, Ordering},
    },
    time::{Duration, Instant, SystemTime, UNIX_EPOCH},
};

use anyhow::{Context, Result, anyhow, bail, ensure};
use serde_json::{Value, json};
use tokio::runtime::Runtime;
use udapose_lab::atomic::write_atomic;

use super::bench_service::{
    Level, Record, ServerProcess, estimate, fmt_ms, load_average, machine_busy_ticks, median, min_median_max,
    percentile, post_or_get, process_ticks, read_images, server_log_json, summary, window,
};

/// The store's credentials (s3s-fs checks them) and bucket.
const KEY: &str = "udapose-bench";
const SECRET: &str = "udapose-bench-secret";
const BUCKET: &str = "bench";
/// Version of s3s-fs that `make test` installs.
const S3S_FS_VERSION: &str = "0.14.1";
/// Clock ticks per second in `/proc` (USER_HZ).
const HZ: f64 = 100.0;
/// The longest a replica count is measured (fewer requests than asked on a loaded machine).
const LEVEL_LIMIT: Duration = Duration::from_secs(40);
const OVERSUBSCRIBED_LIMIT: Duration = Duration::from_secs(20);

#[derive(clap::Args)]
pub struct ScaleArgs {
    /// Model directory, served as category `car`.
    #[arg(long, env = "UDAPOSE_QUICK_MODEL", default_value = "models/car")]
    model: PathBuf,
    /// SynCar-OOD data: estimates send `<data>/source/test/images/car`, the adaptation jobs
    /// `<data>/combined/adapt/images/car` (default: `$UDAPOSE_CACHE/run/syncar-quick`, the quick
    /// dataset `make test` renders; `$UDAPOSE_CACHE` defaults to `~/.cache/udapose`).
    #[arg(long, env = "UDAPOSE_QUICK_DATA")]
    data: Option<PathBuf>,
    /// Distinct images sent as estimates (the first, in name order).
    #[arg(long, default_value_t = 16)]
    distinct: usize,
    /// Requests in flight through the client while 1, 2 and 3 replicas are measured.
    #[arg(long, default_value_t = 4)]
    concurrency: usize,
    /// Requests per replica count (after 2 untimed ones per replica; fewer if they take over 40 s).
    #[arg(long, default_value_t = 200)]
    requests: usize,
    /// Requests in flight (back to back) through the client during the faults.
    #[arg(long, default_value_t = 2)]
    fault_clients: usize,
    /// Target images uploaded before each of the two adaptation jobs.
    #[arg(long, default_value_t = 30)]
    targets: usize,
    /// The jobs' `max_rounds` override (default: the server's).
    #[arg(long)]
    max_rounds: Option<u32>,
    /// The processes' `--poll`: seconds between their reads of the store (activation log, jobs).
    #[arg(long, default_value_t = 5)]
    poll: u64,
    /// The replicas' `--max-batch`.
    #[arg(long, default_value_t = 8)]
    max_batch: usize,
    /// Every process's `--torch-threads` (libtorch intra-op threads). 1: the replicas share the
    /// machine's cores (the manifests keep it equal to a replica's CPU limit); the server's
    /// default, 0, is one per core.
    #[arg(long, default_value_t = 1)]
    torch_threads: u32,
    /// Requests per replica count measured again with 3 other replicas at the server's default
    /// `--torch-threads 0` (one libtorch thread per core, so the replicas oversubscribe the
    /// cores; fewer if they take over 20 s); 0 skips it.
    #[arg(long, default_value_t = 100)]
    oversubscribed_requests: usize,
    /// Seconds of load between a serve replica's `kill -9` and its restart.
    #[arg(long, default_value_t = 5.0)]
    kill_window_s: f64,
    /// Seconds after the second job is seen RUNNING before its worker is killed.
    #[arg(long, default_value_t = 3.0)]
    worker_kill_after_s: f64,
    /// Longest wait for a job to end, or for a version to reach every replica, in seconds.
    #[arg(long, default_value_t = 300)]
    timeout_s: u64,
    /// The server binary (default: next to this one).
    #[arg(long)]
    server: Option<PathBuf>,
    /// The s3s-fs binary (default: `$UDAPOSE_CACHE/tools/s3s-fs-0.14.1/bin/s3s-fs`, where
    /// `make test` installs it).
    #[arg(long, env = "UDAPOSE_S3S_FS")]
    s3s_fs: Option<PathBuf>,
    /// Report (JSON; a Markdown twin is written next to it).
    #[arg(long, default_value = "reports/scale.json")]
    out: PathBuf,
    /// A remark on the conditions of the run (e.g. other load), copied into both reports.
    #[arg(long)]
    note: Option<String>,
}

fn cache_dir() -> PathBuf {
    match std::env::var_os("UDAPOSE_CACHE") {
        Some(c) => PathBuf::from(c),
        None => PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache/udapose"),
    }
}

/// `n` free loopback addresses (bound, then released).
fn free_addrs(n: usize) -> Result<Vec<SocketAddr>> {
    let listeners: Vec<TcpListener> = (0..n).map(|_| TcpListener::bind("127.0.0.1:0")).collect::<Result<_, _>>()?;
    Ok(listeners.iter().map(TcpListener::local_addr).collect::<Result<_, _>>()?)
}

/// An s3s-fs server on loopback with bucket [`BUCKET`]; killed (and its files removed) on drop.
struct S3 {
    child: Child,
    root: PathBuf,
    endpoint: String,
}

impl S3 {
    fn start(binary: &Path, root: PathBuf, log: &Path) -> Result<S3> {
        fs::create_dir_all(root.join(BUCKET))?; // a bucket is a directory
        let [addr] = free_addrs(1)?[..] else { unreachable!() };
        let log = fs::File::create(log)?;
        let child = Command::new(binary)
            .args(["--host", "127.0.0.1", "--port", &addr.port().to_string()])
            .args(["--access-key", KEY, "--secret-key", SECRET])
            .arg(&root)
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("starting {}", binary.display()))?;
        let s3 = S3 { child, root, endpoint: format!("http://{addr}") };
        let deadline = Instant::now() + Duration::from_secs(10);
        while TcpStream::connect(addr).is_err() {
            ensure!(Instant::now() < deadline, "s3s-fs did not listen on {addr}");
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(s3)
    }
}

impl Drop for S3 {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = fs::remove_dir_all(&self.root);
    }
}

/// One `udapose-server` process of the fleet.
struct Node {
    name: String,
    grpc: SocketAddr,
    server: ServerProcess,
    /// Seconds from its start to `/readyz` answering 200.
    ready_s: f64,
}

impl Node {
    fn pid(&self) -> String {
        self.server.child.id().to_string()
    }

    fn http(&self) -> SocketAddr {
        self.server.http
    }

    /// `kill -9`, and the process reaped.
    fn kill9(&mut self) -> Result<()> {
        self.server.child.kill().with_context(|| format!("killing {}", self.name))?;
        self.server.child.wait()?;
        Ok(())
    }
}

/// What every process of the fleet shares: the binary, the seed models, the store.
struct Fleet {
    binary: PathBuf,
    scratch: PathBuf,
    s3: S3,
    poll: u64,
    max_batch: usize,
    torch_threads: u32,
}

impl Fleet {
    fn store_url() -> String {
        format!("s3://{BUCKET}/udapose")
    }

    /// Starts a server of `role` (`serve` or `adapt`) listening on `addrs` (HTTP, gRPC).
    fn start(&self, name: &str, role: &str, addrs: [SocketAddr; 2]) -> Result<Node> {
        self.start_with(name, role, addrs, self.torch_threads)
    }

    /// [`Fleet::start`] with another `--torch-threads`.
    fn start_with(&self, name: &str, role: &str, addrs: [SocketAddr; 2], torch_threads: u32) -> Result<Node> {
        let dir = self.scratch.join(name);
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(dir.join("cache"))?;
        let mut command = Command::new(&self.binary);
        command
            .args(["--http-addr", &addrs[0].to_string(), "--grpc-addr", &addrs[1].to_string()])
            .arg("--models")
            .arg(self.scratch.join("models"))
            .args(["--store", &Self::store_url(), "--s3-endpoint", &self.s3.endpoint, "--s3-allow-http"])
            .args(["--role", role, "--poll", &self.poll.to_string()])
            .arg("--cache-dir")
            .arg(dir.join("cache"))
            .args(["--gate", "advisory", "--adapt-min-images", "100000"])
            .args(["--max-batch", &self.max_batch.to_string(), "--torch-threads", &torch_threads.to_string()])
            .env("AWS_ACCESS_KEY_ID", KEY)
            .env("AWS_SECRET_ACCESS_KEY", SECRET)
            .env("AWS_REGION", "us-east-1")
            .env_remove("UDAPOSE_S3_ENDPOINT")
            .env("RUST_LOG", "warn,udapose_server=info");
        let started = Instant::now();
        let server = ServerProcess::spawn(command, dir, addrs[0]).with_context(|| format!("starting {name}"))?;
        Ok(Node { name: name.into(), grpc: addrs[1], server, ready_s: started.elapsed().as_secs_f64() })
    }

    /// The flags every process gets (for the report).
    fn flags(&self) -> String {
        format!(
            "--store {} --s3-endpoint {} --s3-allow-http --poll {} --gate advisory --adapt-min-images 100000 --max-batch {} \
             --torch-threads {} --cache-dir <its own>",
            Self::store_url(),
            self.s3.endpoint,
            self.poll,
            self.max_batch,
            self.torch_threads
        )
    }
}

/// A client over `endpoints` (gRPC), with the library's failover.
fn connect(rt: &Runtime, endpoints: &[SocketAddr]) -> Result<udapose_client::Client> {
    let names: Vec<String> = endpoints.iter().map(ToString::to_string).collect();
    let mut options = udapose_client::ClientOptions::new(names[0].clone());
    options.endpoints = names;
    rt.block_on(udapose_client::Client::connect_with(options)).context("connecting the client")
}

/// One estimate through `client`: the answering version, or the error.
async fn grpc_estimate(client: &udapose_client::Client, image: &[u8]) -> Result<String, String> {
    match client.estimate(udapose_client::request("car", image.to_vec())).await {
        Ok(r) => Ok(r.model_version),
        Err(e) => Err(e.to_string()),
    }
}

/// `requests` estimates through `client`, `concurrency` in flight (images in rotation); none
/// sent after `limit` (the level then holds fewer).
fn level(
    rt: &Runtime,
    client: &udapose_client::Client,
    images: &Arc<Vec<Vec<u8>>>,
    concurrency: usize,
    requests: usize,
    limit: Duration,
) -> Level {
    let next = Arc::new(AtomicUsize::new(0));
    let started = Instant::now();
    let deadline = started + limit;
    let results: Vec<(bool, f64)> = rt.block_on(async {
        let tasks: Vec<_> = (0..concurrency)
            .map(|_| {
                let (client, images, next) = (client.clone(), images.clone(), next.clone());
                tokio::spawn(async move {
                    let mut out = Vec::new();
                    loop {
                        let r = next.fetch_add(1, Ordering::Relaxed);
                        if r >= requests || Instant::now() > deadline {
                            break out;
                        }
                        let sent = Instant::now();
                        let ok = grpc_estimate(&client, &images[r % images.len()]).await.is_ok();
                        out.push((ok, sent.elapsed().as_secs_f64() * 1e3));
                    }
                })
            })
            .collect();
        let mut all = Vec::new();
        for t in tasks {
            all.extend(t.await.unwrap_or_default());
        }
        all
    });
    Level {
        concurrency,
        requests: results.len(),
        errors: results.iter().filter(|(ok, _)| !ok).count(),
        seconds: started.elapsed().as_secs_f64(),
        latencies_ms: results.iter().filter(|(ok, _)| *ok).map(|(_, ms)| *ms).collect(),
    }
}

/// Estimates through the client, back to back from `n` tasks, until stopped; every request
/// recorded with its start, end and answering version.
struct Load {
    stop: Arc<AtomicBool>,
    records: Arc<Mutex<Vec<Record>>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Load {
    fn start(rt: &Runtime, client: &udapose_client::Client, images: &Arc<Vec<Vec<u8>>>, n: usize) -> Load {
        let stop = Arc::new(AtomicBool::new(false));
        let records = Arc::new(Mutex::new(Vec::new()));
        let tasks = (0..n)
            .map(|t| {
                let (client, images, stop, records) = (client.clone(), images.clone(), stop.clone(), records.clone());
                rt.spawn(async move {
                    for i in (t..).step_by(n) {
                        if stop.load(Ordering::Acquire) {
                            break;
                        }
                        let start = Instant::now();
                        let answer = grpc_estimate(&client, &images[i % images.len()]).await;
                        let record = Record { start, end: Instant::now(), answer };
                        records.lock().unwrap_or_else(|p| p.into_inner()).push(record);
                    }
                })
            })
            .collect();
        Load { stop, records, tasks }
    }

    /// (answered, failed) so far.
    fn counts(&self) -> (usize, usize) {
        let records = self.records.lock().unwrap_or_else(|p| p.into_inner());
        let failed = records.iter().filter(|r| r.answer.is_err()).count();
        (records.len() - failed, failed)
    }

    fn stop(self, rt: &Runtime) -> Vec<Record> {
        self.stop.store(true, Ordering::Release);
        rt.block_on(async {
            for t in self.tasks {
                let _ = t.await;
            }
        });
        std::mem::take(&mut *self.records.lock().unwrap_or_else(|p| p.into_inner()))
    }
}

/// Successful gRPC estimates a server answered and the server-side latency sum, from `/metrics`.
#[derive(Clone, Copy, Default)]
struct Served {
    grpc_ok: f64,
    latency_sum_s: f64,
    latency_count: f64,
}

fn served(http: SocketAddr) -> Option<Served> {
    let (status, text) = post_or_get(http, "GET", "/metrics", b"").ok()?;
    if status != 200 {
        return None;
    }
    let mut s = Served::default();
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let Some((name, value)) = line.rsplit_once(' ') else { continue };
        let Ok(value) = value.parse::<f64>() else { continue };
        if name.starts_with("udapose_requests_total{")
            && name.contains("code=\"OK\"")
            && name.contains("transport=\"grpc\"")
        {
            s.grpc_ok += value;
        } else if name.starts_with("udapose_estimate_duration_seconds_sum{") {
            s.latency_sum_s += value;
        } else if name.starts_with("udapose_estimate_duration_seconds_count{") {
            s.latency_count += value;
        }
    }
    Some(s)
}

/// The CPU ticks of this process's children that have ended and been waited for (cutime +
/// cstime): the servers killed so far.
fn reaped_children_ticks() -> Option<u64> {
    let stat = fs::read_to_string("/proc/self/stat").ok()?;
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    Some(fields.get(13)?.parse::<u64>().ok()? + fields.get(14)?.parse::<u64>().ok()?)
}

/// CPU ticks and answered requests of every process at one moment.
struct Snapshot {
    at: Instant,
    busy: Option<u64>,
    /// This process (the client).
    own: Option<u64>,
    /// The servers killed so far, and the store.
    reaped: Option<u64>,
    store: Option<u64>,
    /// Per node: CPU ticks and `/metrics` counters.
    nodes: Vec<(Option<u64>, Option<Served>)>,
}

impl Snapshot {
    fn take(nodes: &[&Node], store_pid: u32) -> Snapshot {
        Snapshot {
            at: Instant::now(),
            busy: machine_busy_ticks(),
            own: process_ticks("self"),
            reaped: reaped_children_ticks(),
            store: process_ticks(&store_pid.to_string()),
            nodes: nodes.iter().map(|n| (process_ticks(&n.pid()), served(n.http()))).collect(),
        }
    }

    /// Everything this benchmark runs: itself, its servers (alive or killed) and the store.
    fn ours(&self) -> u64 {
        self.own.unwrap_or(0)
            + self.reaped.unwrap_or(0)
            + self.store.unwrap_or(0)
            + self.nodes.iter().filter_map(|(t, _)| *t).sum::<u64>()
    }

    /// Cores that other processes used on average since `from`.
    fn others_cores_since(&self, from: &Snapshot) -> Option<f64> {
        let busy = self.busy?.saturating_sub(from.busy?);
        Some(
            busy.saturating_sub(self.ours().saturating_sub(from.ours())) as f64
                / HZ
                / (self.at - from.at).as_secs_f64(),
        )
    }
}

/// Per node between two snapshots: requests answered, req/s, server-side mean latency, CPU.
fn per_node(nodes: &[&Node], from: &Snapshot, to: &Snapshot) -> (Vec<Value>, Value) {
    let seconds = (to.at - from.at).as_secs_f64();
    let rows = nodes
        .iter()
        .zip(from.nodes.iter().zip(&to.nodes))
        .map(|(n, ((t0, s0), (t1, s1)))| {
            let ticks = t0.zip(*t1).map(|(a, b)| b.saturating_sub(a));
            let (answered, mean_ms) = match (s0, s1) {
                (Some(a), Some(b)) => {
                    let count = b.latency_count - a.latency_count;
                    (
                        Some(b.grpc_ok - a.grpc_ok),
                        (count > 0.0).then(|| (b.latency_sum_s - a.latency_sum_s) / count * 1e3),
                    )
                }
                _ => (None, None),
            };
            json!({
                "name": n.name,
                "grpc_answered": answered,
                "throughput_per_s": answered.map(|a| a / seconds),
                "server_mean_ms": mean_ms,
                "cpu_s": ticks.map(|t| t as f64 / HZ),
                "cpu_cores": ticks.map(|t| t as f64 / HZ / seconds),
            })
        })
        .collect();
    let own = from.own.zip(to.own).map(|(a, b)| b.saturating_sub(a));
    let store = from.store.zip(to.store).map(|(a, b)| b.saturating_sub(a));
    let busy = from.busy.zip(to.busy).map(|(a, b)| b.saturating_sub(a));
    let machine = json!({
        "seconds": seconds,
        "client_cpu_s": own.map(|o| o as f64 / HZ),
        "client_cpu_cores": own.map(|o| o as f64 / HZ / seconds),
        "store_cpu_cores": store.map(|o| o as f64 / HZ / seconds),
        "machine_busy_cores": busy.map(|b| b as f64 / HZ / seconds),
        "other_processes_cores": to.others_cores_since(from),
    });
    (rows, machine)
}

fn now_epoch() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// The instant of an epoch time in seconds (the server's timestamps), at most `now`.
fn instant_of(epoch_s: f64) -> Instant {
    let age = (now_epoch() - epoch_s).max(0.0);
    Instant::now().checked_sub(Duration::from_secs_f64(age)).unwrap_or_else(Instant::now)
}

/// A job as a node sees it (`None` while it does not know it yet).
fn job_on(node: &Node, id: &str) -> Result<Option<Value>> {
    let (status, body) = post_or_get(node.http(), "GET", &format!("/v1/jobs/{id}"), b"")?;
    match status {
        200 => Ok(Some(serde_json::from_str(&body).with_context(|| format!("job {id}: {body}"))?)),
        404 => Ok(None),
        _ => bail!("GET /v1/jobs/{id} on {}: {status} {body}", node.name),
    }
}

fn job_state(job: &Value) -> &str {
    job["state"].as_str().unwrap_or("")
}

fn terminal(state: &str) -> bool {
    !matches!(state, "" | "QUEUED" | "RUNNING" | "VALIDATING")
}

/// Polls job `id` on `node` every 100 ms until `done(state)`; returns the job and when that was
/// seen.
fn wait_job(node: &Node, id: &str, timeout: Duration, done: impl Fn(&str) -> bool) -> Result<(Value, Instant)> {
    let deadline = Instant::now() + timeout;
    let mut last = String::new();
    loop {
        if let Some(job) = job_on(node, id)? {
            let state = job_state(&job).to_owned();
            if state != last {
                eprintln!("    job {id} on {}: {state}", node.name);
                last.clone_from(&state);
            }
            if done(&state) {
                return Ok((job, Instant::now()));
            }
        }
        ensure!(
            Instant::now() < deadline,
            "job {id} still {last:?} on {} after {timeout:?}: {}",
            node.name,
            node.server.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A job's version and how it reached the replicas.
struct Swap {
    version: String,
    /// Per replica, ms from the activation to its first answer by the version.
    propagation_ms: Vec<f64>,
    steps: Vec<Value>,
    probes: Vec<Value>,
}

/// Waits for job `id` on `worker` to end ACTIVATED, then for its version to reach `nodes`.
fn activated_swap(worker: &Node, id: &str, nodes: &[&Node], image: &[u8], timeout: Duration) -> Result<(Value, Swap)> {
    let (done, _) = wait_job(worker, id, timeout, terminal)?;
    ensure!(
        job_state(&done) == "ACTIVATED",
        "job {id} ended {}: {}\n{}",
        job_state(&done),
        done["reason"],
        worker.server.log()
    );
    let version = done["version"].as_str().context("the job has no version")?.to_owned();
    let epoch = done["updated"].as_f64().unwrap_or_else(now_epoch);
    let (propagation_ms, probes) = wait_serving(nodes, &version, instant_of(epoch), image, timeout)?;
    let steps = swap_steps(nodes, &version, epoch);
    Ok((done, Swap { version, propagation_ms, steps, probes }))
}

/// Waits until each node answers an estimate with `version` (its registry is polled every
/// 50 ms, then estimates confirm it); returns each node's delay after `since`, in ms.
/// The probes' estimates (sent and answered, ms after `since`, and the answering version) go to
/// the second value, per node.
fn wait_serving(
    nodes: &[&Node],
    version: &str,
    since: Instant,
    image: &[u8],
    timeout: Duration,
) -> Result<(Vec<f64>, Vec<Value>)> {
    let deadline = Instant::now() + timeout;
    let ms = |t: Instant| t.saturating_duration_since(since).as_secs_f64() * 1e3;
    let results: Vec<(f64, Value)> = std::thread::scope(|s| {
        let probes: Vec<_> = nodes
            .iter()
            .map(|n| {
                s.spawn(move || -> Result<(f64, Value)> {
                    let mut tries = Vec::new();
                    loop {
                        let active = post_or_get(n.http(), "GET", "/v1/models/car", b"")
                            .ok()
                            .and_then(|(_, body)| serde_json::from_str::<Value>(&body).ok())
                            .and_then(|v| v["version"].as_str().map(str::to_owned));
                        if active.as_deref() == Some(version) {
                            let sent = Instant::now();
                            let answer = estimate(n.http(), image);
                            let end = Instant::now();
                            tries.push(json!([ms(sent), ms(end), answer.as_deref().unwrap_or("failed")]));
                            if answer.as_deref() == Ok(version) {
                                return Ok((ms(end), json!({ "name": n.name, "estimates": tries })));
                            }
                        }
                        ensure!(Instant::now() < deadline, "{} does not serve {version} after {timeout:?}", n.name);
                        std::thread::sleep(Duration::from_millis(50));
                    }
                })
            })
            .collect();
        probes.into_iter().map(|p| p.join().map_err(|_| anyhow!("a probe panicked"))?).collect::<Result<_>>()
    })?;
    Ok(results.into_iter().unzip())
}

/// Throughput and latency through one client over the first 1, 2 and 3 of `replicas`, with
/// every process's requests and CPU (`idle`: other processes of the fleet, shown too); the
/// report's values and the Markdown rows of the per-process table.
fn replica_levels(
    rt: &Runtime,
    replicas: &[Node],
    idle: &[&Node],
    images: &Arc<Vec<Vec<u8>>>,
    concurrency: usize,
    (requests, limit): (usize, Duration),
    store_pid: u32,
) -> Result<(Vec<Value>, String)> {
    let mut levels = Vec::new();
    let mut md = String::new();
    for k in 1..=replicas.len() {
        let endpoints: Vec<SocketAddr> = replicas[..k].iter().map(|r| r.grpc).collect();
        let client = connect(rt, &endpoints)?;
        rt.block_on(async {
            for i in 0..2 * k {
                grpc_estimate(&client, &images[i % images.len()]).await.map_err(|e| anyhow!("warm-up: {e}"))?;
            }
            Ok::<_, anyhow::Error>(())
        })?;
        let all: Vec<&Node> = replicas.iter().chain(idle.iter().copied()).collect();
        let before = Snapshot::take(&all, store_pid);
        let l = level(rt, &client, images, concurrency, requests, limit);
        let after = Snapshot::take(&all, store_pid);
        let (rows, machine) = per_node(&all, &before, &after);
        eprintln!("{k} replica(s), {concurrency} in flight: {}", summary(&l));
        for row in &rows {
            let s = format!(
                "| {k} | {} | {} | {} | {} | {} | {} |\n",
                row["name"].as_str().unwrap_or(""),
                row["grpc_answered"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.0}")),
                row["throughput_per_s"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.2}")),
                fmt_ms(&row["server_mean_ms"]),
                row["cpu_s"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.1}")),
                row["cpu_cores"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.2}")),
            );
            eprint!("  {}", s.trim_start_matches("| "));
            md.push_str(&s);
        }
        let mut v = l.json();
        v["replicas"] = json!(k);
        v["per_process"] = json!(rows);
        v["machine"] = machine;
        levels.push(v);
    }
    Ok((levels, md))
}

/// Seconds since the Unix epoch of a log line's timestamp (`2026-01-02T03:04:05.678901Z ...`,
/// tracing's default format, UTC).
fn log_epoch(line: &str) -> Option<f64> {
    let stamp = line.split_whitespace().next()?.strip_suffix('Z')?;
    let (date, time) = stamp.split_once('T')?;
    let mut d = date.split('-').map(|x| x.parse::<i64>().ok());
    let (y, m, day) = (d.next()??, d.next()??, d.next()??);
    let mut t = time.split(':');
    let (h, min, sec) =
        (t.next()?.parse::<f64>().ok()?, t.next()?.parse::<f64>().ok()?, t.next()?.parse::<f64>().ok()?);
    // Days from 1970-01-01 to the civil date (Howard Hinnant's days_from_civil).
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let doy = (153 * (m + if m > 2 { -3 } else { 9 }) + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    Some(days as f64 * 86_400.0 + h * 3600.0 + min * 60.0 + sec)
}

/// Per node, from its log, after an activation at `since` (epoch seconds): when it saw `version`
/// become active (its poll, or its own rollback) and how long its inference worker took to load it.
fn swap_steps(nodes: &[&Node], version: &str, since: f64) -> Vec<Value> {
    nodes
        .iter()
        .map(|n| {
            let log = n.server.log();
            let lines = || log.lines().filter(|l| l.contains(version)).filter_map(|l| Some((log_epoch(l)?, l)));
            let seen = lines().find(|(t, l)| *t >= since - 0.5 && l.contains("new active version")).map(|(t, _)| t);
            let loaded = seen.and_then(|s| lines().find(|(t, l)| *t >= s && l.contains("model loaded")));
            let load_ms =
                loaded.and_then(|(_, l)| l.split_whitespace().find_map(|w| w.strip_prefix("ms="))?.parse::<f64>().ok());
            json!({
                "name": n.name,
                "seen_ms": seen.map(|s| (s - since) * 1e3),
                "loaded_ms": loaded.map(|(t, _)| (t - since) * 1e3),
                "load_ms": load_ms,
            })
        })
        .collect()
}

/// The requests of the load in flight during `[from, to]`: counts, latency, first errors.
fn fault_window(records: &[Record], from: Instant, to: Instant, clients: usize, others: Option<f64>) -> Value {
    let inside: Vec<&Record> = records.iter().filter(|r| r.overlaps(from, to)).collect();
    let failed: Vec<&str> = inside.iter().filter_map(|r| r.answer.as_ref().err()).map(String::as_str).collect();
    let ok_ms: Vec<f64> = inside.iter().filter(|r| r.answer.is_ok()).map(|r| r.ms()).collect();
    let mut versions = std::collections::BTreeMap::<&str, usize>::new();
    for r in &inside {
        if let Ok(v) = &r.answer {
            *versions.entry(v.as_str()).or_default() += 1;
        }
    }
    let level = window(records, from, to, clients);
    json!({
        "seconds": (to - from).as_secs_f64(),
        "requests": inside.len(),
        "failed": failed.len(),
        "first_failures": failed.iter().take(5).collect::<Vec<_>>(),
        "throughput_per_s": level.throughput(),
        "p50_ms": percentile(&ok_ms, 0.5),
        "p99_ms": percentile(&ok_ms, 0.99),
        "max_ms": percentile(&ok_ms, 1.0),
        "answers_by_version": versions,
        "other_processes_cores": others,
    })
}

/// The requests that ended in each second of `[from, to]`: seconds since `zero` (bin start),
/// answered, failed, median and largest latency.
fn timeline(records: &[Record], from: Instant, to: Instant, zero: Instant) -> Vec<Value> {
    let offset =
        |t: Instant| t.saturating_duration_since(zero).as_secs_f64() - zero.saturating_duration_since(t).as_secs_f64();
    let (first, last) = (offset(from).floor() as i64, offset(to).ceil() as i64);
    (first..last)
        .map(|bin| {
            let inside: Vec<&Record> =
                records.iter().filter(|r| offset(r.end) >= bin as f64 && offset(r.end) < (bin + 1) as f64).collect();
            let ms: Vec<f64> = inside.iter().filter(|r| r.answer.is_ok()).map(|r| r.ms()).collect();
            json!({
                "from_s": bin,
                "answered": ms.len(),
                "failed": inside.len() - ms.len(),
                "p50_ms": percentile(&ms, 0.5),
                "max_ms": percentile(&ms, 1.0),
            })
        })
        .collect()
}

/// A snapshot of the replicas, the worker and the store.
fn snapshot(replicas: &[Node], worker: &Node, store_pid: u32) -> Snapshot {
    Snapshot::take(&replicas.iter().chain([worker]).collect::<Vec<_>>(), store_pid)
}

/// A job's history (`GET /v1/jobs/{id}/events`, Server-Sent Events that end after the terminal
/// one): each event's state and message.
fn job_history(node: &Node, id: &str) -> Vec<String> {
    let Ok((200, body)) = post_or_get(node.http(), "GET", &format!("/v1/jobs/{id}/events"), b"") else {
        return Vec::new();
    };
    body.lines()
        .filter_map(|l| l.strip_prefix("data:"))
        .filter_map(|d| serde_json::from_str::<Value>(d.trim()).ok())
        .map(|e| format!("{}: {}", e["state"].as_str().unwrap_or("?"), e["message"].as_str().unwrap_or("")))
        .collect()
}

/// Uploads `targets` round-robin to `nodes`; returns the answers' statuses.
fn upload(nodes: &[&Node], targets: &[Vec<u8>]) -> Result<std::collections::BTreeMap<String, usize>> {
    let mut statuses = std::collections::BTreeMap::new();
    for (i, t) in targets.iter().enumerate() {
        let node = nodes[i % nodes.len()];
        let (status, body) = post_or_get(node.http(), "POST", "/v1/adapt/car/images", t)?;
        ensure!(status == 200, "uploading a target image to {}: {status} {body}", node.name);
        let answer: Value = serde_json::from_str(&body).with_context(|| format!("upload answer {body}"))?;
        *statuses.entry(answer["results"][0]["status"].as_str().unwrap_or("?").to_owned()).or_default() += 1;
    }
    Ok(statuses)
}

fn ms_list(v: &[f64]) -> String {
    v.iter().map(|x| format!("{x:.0}")).collect::<Vec<_>>().join(" / ")
}

pub fn run(args: &ScaleArgs) -> Result<()> {
    ensure!(
        args.requests >= 1 && args.distinct >= 1 && args.concurrency >= 1,
        "--requests, --distinct, --concurrency must be at least 1"
    );
    ensure!(args.fault_clients >= 1 && args.targets >= 1, "--fault-clients and --targets must be at least 1");
    let began = Instant::now();
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let load_before = load_average();
    let data = args.data.clone().unwrap_or_else(|| cache_dir().join("run/syncar-quick"));
    let images_dir = data.join("source/test/images/car");
    let targets_dir = data.join("combined/adapt/images/car");
    let images = Arc::new(read_images(&images_dir, args.distinct)?);
    let targets = read_images(&targets_dir, 2 * args.targets)?;
    ensure!(
        targets.len() == 2 * args.targets,
        "{} has {} images; two jobs of --targets {} need {}",
        targets_dir.display(),
        targets.len(),
        args.targets,
        2 * args.targets
    );
    let binary = match &args.server {
        Some(p) => p.clone(),
        None => std::env::current_exe()?.with_file_name("udapose-server"),
    };
    ensure!(binary.is_file(), "{} not found: build the workspace first", binary.display());
    let s3s_fs =
        args.s3s_fs.clone().unwrap_or_else(|| cache_dir().join(format!("tools/s3s-fs-{S3S_FS_VERSION}/bin/s3s-fs")));
    ensure!(s3s_fs.is_file(), "{} not found: `make test` installs it (or pass --s3s-fs)", s3s_fs.display());
    let model = fs::canonicalize(&args.model).with_context(|| format!("model {}", args.model.display()))?;
    let timeout = Duration::from_secs(args.timeout_s);

    let scratch = std::env::temp_dir().join(format!("udapose-bench-scale-{}", std::process::id()));
    let _ = fs::remove_dir_all(&scratch);
    fs::create_dir_all(scratch.join("models"))?;
    std::os::unix::fs::symlink(&model, scratch.join("models/car"))?;
    let result = bench(args, &binary, &s3s_fs, &scratch, &images, &targets, timeout);
    let _ = fs::remove_dir_all(&scratch);
    let (mut report, levels_md, oversubscribed_md) = result?;
    report["command"] = json!(command);
    report["commit"] = json!(crate::synth_cmd::git_commit());
    report["machine"] = json!({
        "cpu": udapose_engine::runtime::cpu_model(),
        "threads": std::thread::available_parallelism().map_or(1, |n| n.get()),
        "load_average_before": load_before,
        "load_average_after": load_average(),
    });
    report["note"] = json!(args.note);
    report["model"] = json!(args.model.display().to_string());
    report["images"] = json!({ "folder": images_dir.display().to_string(), "distinct": images.len() });
    report["targets"] = json!({ "folder": targets_dir.display().to_string(), "per_job": args.targets });
    report["seconds"] = json!(began.elapsed().as_secs_f64());
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), markdown(args, &report, &levels_md, &oversubscribed_md).as_bytes())?;
    eprintln!("wrote {} and its .md ({:.0} s)", args.out.display(), began.elapsed().as_secs_f64());
    Ok(())
}

type Bench = (Value, String, String);

fn bench(
    args: &ScaleArgs,
    binary: &Path,
    s3s_fs: &Path,
    scratch: &Path,
    images: &Arc<Vec<Vec<u8>>>,
    targets: &[Vec<u8>],
    timeout: Duration,
) -> Result<Bench> {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    eprintln!("store: s3s-fs on loopback; starting 1 adapt worker and 3 serve replicas (--poll {})", args.poll);
    let s3 = S3::start(s3s_fs, scratch.join("s3"), &scratch.join("s3s-fs.log"))?;
    let fleet = Fleet {
        torch_threads: args.torch_threads,
        binary: binary.to_owned(),
        scratch: scratch.to_owned(),
        s3,
        poll: args.poll,
        max_batch: args.max_batch,
    };
    let store_pid = fleet.s3.child.id();
    let worker_addrs = free_addrs(2)?;
    let mut worker = fleet.start("worker", "adapt", [worker_addrs[0], worker_addrs[1]])?;
    eprintln!("  worker ready in {:.1} s", worker.ready_s);
    let mut replicas = Vec::new();
    for i in 0..3 {
        let a = free_addrs(2)?;
        let node = fleet.start(&format!("serve-{i}"), "serve", [a[0], a[1]])?;
        eprintln!("  {} ready in {:.1} s", node.name, node.ready_s);
        replicas.push(node);
    }
    let startup = json!({
        "worker_ready_s": worker.ready_s,
        "replicas_ready_s": replicas.iter().map(|r| r.ready_s).collect::<Vec<_>>(),
    });
    let seed =
        replicas[0].server.get_json("/v1/models/car")?["version"].as_str().context("no active car version")?.to_owned();
    for r in &replicas {
        for image in images.iter().take(4) {
            estimate(r.http(), image).map_err(|e| anyhow!("warm-up request to {} failed: {e}", r.name))?;
        }
    }

    // 1, 2 and 3 replicas under the same client concurrency.
    let (levels, levels_md) =
        replica_levels(&rt, &replicas, &[&worker], images, args.concurrency, (args.requests, LEVEL_LIMIT), store_pid)?;
    let (oversubscribed, oversubscribed_md) = if args.oversubscribed_requests > 0 && args.torch_threads != 0 {
        eprintln!("the same with 3 other replicas at --torch-threads 0 (one libtorch thread per core)");
        let mut extra = Vec::new();
        for i in 0..3 {
            let a = free_addrs(2)?;
            extra.push(fleet.start_with(&format!("serve-t0-{i}"), "serve", [a[0], a[1]], 0)?);
        }
        for r in &extra {
            for image in images.iter().take(4) {
                estimate(r.http(), image).map_err(|e| anyhow!("warm-up request to {} failed: {e}", r.name))?;
            }
        }
        let idle: Vec<&Node> = replicas.iter().chain([&worker]).collect();
        let budget = (args.oversubscribed_requests, OVERSUBSCRIBED_LIMIT);
        replica_levels(&rt, &extra, &idle, images, args.concurrency, budget, store_pid)?
    } else {
        (Vec::new(), String::new())
    };

    // The faults, under a steady load over every replica.
    let endpoints: Vec<SocketAddr> = replicas.iter().map(|r| r.grpc).collect();
    let client = connect(&rt, &endpoints)?;
    let load = Load::start(&rt, &client, images, args.fault_clients);
    std::thread::sleep(Duration::from_secs(1));
    let image = &images[0];
    let mut overrides = json!({});
    if let Some(r) = args.max_rounds {
        overrides["max_rounds"] = json!(r);
    }
    let job_body = json!({ "overrides": overrides });

    // (a) A job asked on a replica, run by the worker, and its version's swap on every replica.
    eprintln!("fault: adaptation job and the swap after its activation ({} clients)", args.fault_clients);
    let snap_a0 = snapshot(&replicas, &worker, store_pid);
    let a_from = snap_a0.at;
    let all: Vec<&Node> = replicas.iter().collect();
    let statuses_a = upload(&all, &targets[..args.targets])?;
    let job = replicas[0].server.post_json("/v1/adapt/car/jobs", &job_body)?;
    let id_a = job["job_id"].as_str().context("no job_id")?.to_owned();
    eprintln!("  uploaded {statuses_a:?}; job {id_a} asked on serve-0");
    let (done_a, Swap { version: version_a, propagation_ms: prop_a, steps: steps_a, probes: probes_a }) =
        activated_swap(&worker, &id_a, &all, image, timeout)?;
    let snap_a1 = snapshot(&replicas, &worker, store_pid);
    let a_to = snap_a1.at;
    eprintln!(
        "  {version_a} reached the replicas {} ms after its activation; {:?} (answered, failed) so far",
        ms_list(&prop_a),
        load.counts()
    );

    // (b) kill -9 of a serve replica under load, then its restart on the same ports.
    eprintln!("fault: kill -9 of serve-2 under load ({} s), then its restart", args.kill_window_s);
    let snap_b0 = snapshot(&replicas, &worker, store_pid);
    let b_from = snap_b0.at;
    let addrs_2 = [replicas[2].http(), replicas[2].grpc];
    let log_killed = replicas[2].server.log();
    replicas[2].kill9()?;
    let killed_at = Instant::now();
    std::thread::sleep(Duration::from_secs_f64(args.kill_window_s));
    let restarting_at = Instant::now();
    let restarted = fleet.start("serve-2-restarted", "serve", addrs_2)?;
    let ready_at = Instant::now();
    let restarted_version = estimate(restarted.http(), image).map_err(|e| anyhow!("the restarted replica: {e}"))?;
    ensure!(
        restarted_version == version_a,
        "the restarted replica serves {restarted_version}, not the active {version_a}"
    );
    let first_seen = served(restarted.http()).map_or(0.0, |s| s.grpc_ok);
    let rejoin_deadline = Instant::now() + Duration::from_secs(30);
    while served(restarted.http()).is_none_or(|s| s.grpc_ok <= first_seen) {
        ensure!(Instant::now() < rejoin_deadline, "the client sent the restarted replica nothing for 30 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    let rejoin_s = ready_at.elapsed().as_secs_f64();
    let _ = std::mem::replace(&mut replicas[2], restarted);
    let snap_b1 = snapshot(&replicas, &worker, store_pid);
    let b_to = snap_b1.at;
    eprintln!(
        "  restarted in {:.1} s serving {restarted_version}; the client sent it requests again {:.1} s after it was ready; {:?} so far",
        replicas[2].ready_s,
        rejoin_s,
        load.counts()
    );

    // (c) A rollback on one replica reaching every replica.
    eprintln!("fault: rollback on serve-1");
    let snap_c0 = snapshot(&replicas, &worker, store_pid);
    let c_from = snap_c0.at;
    let (rolled_at, epoch_c) = (Instant::now(), now_epoch());
    let rolled = replicas[1]
        .server
        .post_json("/v1/models/car/rollback", &json!({ "reason": "udapose-lab bench scale: rollback propagation" }))?;
    let rollback_call_ms = rolled_at.elapsed().as_secs_f64() * 1e3;
    ensure!(
        rolled["version"].as_str() == Some(seed.as_str()),
        "the rollback activated {} instead of {seed}",
        rolled["version"]
    );
    let all: Vec<&Node> = replicas.iter().collect();
    let (prop_c, probes_c) = wait_serving(&all, &seed, rolled_at, image, timeout)?;
    let steps_c = swap_steps(&all, &seed, epoch_c);
    let snap_c1 = snapshot(&replicas, &worker, store_pid);
    let c_to = snap_c1.at;
    eprintln!("  {seed} reached the replicas {} ms after the rollback; {:?} so far", ms_list(&prop_c), load.counts());

    // (d) kill -9 of the worker in the middle of a job; a new worker resumes it.
    eprintln!("fault: kill -9 of the worker mid-job, then a new worker");
    let snap_d0 = snapshot(&replicas, &worker, store_pid);
    let d_from = snap_d0.at;
    let statuses_d = upload(&all, &targets[args.targets..])?;
    let job = replicas[0].server.post_json("/v1/adapt/car/jobs", &job_body)?;
    let id_d = job["job_id"].as_str().context("no job_id")?.to_owned();
    eprintln!("  uploaded {statuses_d:?}; job {id_d} asked on serve-0");
    let (_, running_at) = wait_job(&worker, &id_d, timeout, |s| s == "RUNNING" || terminal(s))?;
    std::thread::sleep(Duration::from_secs_f64(args.worker_kill_after_s));
    let before_kill = job_on(&worker, &id_d)?.context("the worker forgot the job")?;
    let state_at_kill = job_state(&before_kill).to_owned();
    ensure!(
        !terminal(&state_at_kill),
        "job {id_d} ended {state_at_kill} before the worker was killed: lower --worker-kill-after-s"
    );
    let log_worker_killed = worker.server.log();
    worker.kill9()?;
    eprintln!(
        "  killed the worker {:.1} s after the job was seen RUNNING (state {state_at_kill}, round {})",
        running_at.elapsed().as_secs_f64(),
        before_kill["last_event"]["round"]
    );
    let new_worker = fleet.start("worker-restarted", "adapt", [worker_addrs[0], worker_addrs[1]])?;
    let old_worker = std::mem::replace(&mut worker, new_worker);
    drop(old_worker);
    let (done_d, Swap { version: version_d, propagation_ms: prop_d, steps: steps_d, probes: probes_d }) =
        activated_swap(&worker, &id_d, &all, image, timeout)?;
    let snap_d1 = snapshot(&replicas, &worker, store_pid);
    let d_to = snap_d1.at;
    let log = replicas[0].server.get_json("/v1/models/car/versions")?;
    let by_job = log["activations"].as_array().map_or(0, |a| a.iter().filter(|a| a["job_id"] == id_d.as_str()).count());
    let complete: std::collections::BTreeSet<&str> =
        log["versions"].as_array().into_iter().flatten().filter_map(|v| v["version"].as_str()).collect();
    let incomplete: Vec<&str> = log["activations"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|a| a["version"].as_str())
        .filter(|v| !complete.contains(v))
        .collect();
    eprintln!(
        "  {version_d} activated ({by_job} activation(s) by the job, {} incomplete version(s) activated), reached the replicas {} ms after; {:?} so far",
        incomplete.len(),
        ms_list(&prop_d),
        load.counts()
    );
    let records = load.stop(&rt);
    let history_d = job_history(&worker, &id_d);

    let n = args.fault_clients;
    let job_json = |done: &Value| {
        json!({
            "id": done["job_id"], "state": done["state"], "version": done["version"], "source_version": done["source_version"],
            "images_used": done["images_used"], "images_held_out": done["images_held_out"], "reason": done["reason"],
            "seconds": done["updated"].as_f64().zip(done["created"].as_f64()).map(|(u, c)| u - c),
            "last_event": done["last_event"]["message"],
        })
    };
    let faults = json!({
        "swap_after_activation": {
            "window": fault_window(&records, a_from, a_to, n, snap_a1.others_cores_since(&snap_a0)),
            "uploaded": statuses_a,
            "job": job_json(&done_a),
            "propagation_ms": prop_a,
            "propagation_steps": steps_a,
            "probes": probes_a,
        },
        "serve_replica_kill9": {
            "window": fault_window(&records, b_from, b_to, n, snap_b1.others_cores_since(&snap_b0)),
            "killed_until_restart": fault_window(&records, killed_at, restarting_at, n, None),
            "timeline": timeline(&records, killed_at - Duration::from_secs(2), b_to, killed_at),
            "kill_window_s": args.kill_window_s,
            "restart_ready_s": replicas[2].ready_s,
            "restart_serves": restarted_version,
            "client_rejoin_s_after_ready": rejoin_s,
            "killed_replica_log": server_log_json(&log_killed),
        },
        "rollback_on_one_replica": {
            "window": fault_window(&records, c_from, c_to, n, snap_c1.others_cores_since(&snap_c0)),
            "on": "serve-1",
            "to_version": seed,
            "call_ms": rollback_call_ms,
            "propagation_ms": prop_c,
            "propagation_steps": steps_c,
            "probes": probes_c,
        },
        "worker_kill9_mid_job": {
            "window": fault_window(&records, d_from, d_to, n, snap_d1.others_cores_since(&snap_d0)),
            "uploaded": statuses_d,
            "state_at_kill": state_at_kill,
            "round_at_kill": before_kill["last_event"]["round"],
            "killed_after_running_s": args.worker_kill_after_s,
            "new_worker_ready_s": worker.ready_s,
            "job": job_json(&done_d),
            "history": history_d,
            "activations_by_job": by_job,
            "incomplete_versions_activated": incomplete,
            "propagation_ms": prop_d,
            "propagation_steps": steps_d,
            "probes": probes_d,
            "killed_worker_log": server_log_json(&log_worker_killed),
        },
    });
    let failed_total: u64 =
        ["swap_after_activation", "serve_replica_kill9", "rollback_on_one_replica", "worker_kill9_mid_job"]
            .iter()
            .filter_map(|k| faults[k]["window"]["failed"].as_u64())
            .sum();
    let all_prop: Vec<f64> = prop_a.iter().chain(&prop_c).chain(&prop_d).copied().collect();
    let logs: Vec<Value> = replicas
        .iter()
        .chain([&worker])
        .map(|n| json!({ "name": n.name, "log": server_log_json(&n.server.log()) }))
        .collect();
    eprintln!(
        "load during the faults: {} requests, {} failed; propagation {} ms (min / median / max)",
        records.len(),
        records.iter().filter(|r| r.answer.is_err()).count(),
        ms_list(&[percentile(&all_prop, 0.0), median(&all_prop), percentile(&all_prop, 1.0)])
    );
    let report = json!({
        "setup": {
            "store": format!("s3s-fs {S3S_FS_VERSION} on loopback, {}", Fleet::store_url()),
            "flags": fleet.flags(),
            "poll_s": args.poll,
            "replicas": 3,
            "workers": 1,
            "client": "udapose-client (gRPC), one endpoint per replica, calls spread over those up, failover on transport errors and UNAVAILABLE",
            "concurrency": args.concurrency,
            "requests_per_level": args.requests,
            "fault_clients": n,
            "max_rounds": args.max_rounds,
            "torch_threads": args.torch_threads,
        },
        "startup": startup,
        "levels": levels,
        "levels_torch_threads_0": oversubscribed,
        "faults": faults,
        "failed_requests_in_faults": failed_total,
        "fault_load": {
            "requests": records.len(),
            "failed": records.iter().filter(|r| r.answer.is_err()).count(),
        },
        "propagation_ms": min_median_max(&all_prop),
        "server_logs": logs,
    });
    Ok((report, levels_md, oversubscribed_md))
}

/// `A → B (×3) → C` for the states `A B B B C`.
fn states_in_a_row<'a>(states: impl Iterator<Item = &'a str>) -> String {
    let mut runs: Vec<(&str, usize)> = Vec::new();
    for s in states {
        match runs.last_mut() {
            Some((last, n)) if *last == s => *n += 1,
            _ => runs.push((s, 1)),
        }
    }
    runs.iter().map(|(s, n)| if *n > 1 { format!("{s} (×{n})") } else { s.to_string() }).collect::<Vec<_>>().join(" → ")
}

/// The summary table of `levels` (one row per replica count), then the per-process table.
fn levels_table(levels: &Value, rows_md: &str) -> String {
    let mut out = String::from(
        "| replicas | requests | seconds | req/s | p50 (ms) | p99 (ms) | failed | CPU of the replicas (cores) | \
         client CPU (cores) | other processes (cores) |\n|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for l in levels.as_array().into_iter().flatten() {
        let replicas_cores: f64 = l["per_process"]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|p| p["name"].as_str().is_some_and(|n| n.starts_with("serve")))
            .filter_map(|p| p["cpu_cores"].as_f64())
            .sum();
        let cores = |v: &Value| v.as_f64().map_or_else(|| "–".into(), |c| format!("{c:.2}"));
        out.push_str(&format!(
            "| {} | {} | {:.1} | {:.2} | {} | {} | {} | {replicas_cores:.2} | {} | {} |\n",
            l["replicas"],
            l["requests"],
            l["seconds"].as_f64().unwrap_or(f64::NAN),
            l["throughput_per_s"].as_f64().unwrap_or(f64::NAN),
            fmt_ms(&l["p50_ms"]),
            fmt_ms(&l["p99_ms"]),
            l["errors"],
            cores(&l["machine"]["client_cpu_cores"]),
            cores(&l["machine"]["other_processes_cores"]),
        ));
    }
    out.push_str(
        "\nPer process (CPU from `/proc/<pid>/stat`, user + system, over the row's window; requests and the \
         server-side mean latency from each process's `/metrics`):\n\n\
         | replicas | process | requests answered | req/s | server-side mean (ms) | CPU (s) | CPU (cores) |\n\
         |---:|---|---:|---:|---:|---:|---:|\n",
    );
    out.push_str(rows_md);
    out
}

fn markdown(args: &ScaleArgs, report: &Value, levels_md: &str, oversubscribed_md: &str) -> String {
    let m = &report["machine"];
    let s = &report["setup"];
    let f = &report["faults"];
    let mut md = format!(
        "# Scale-out benchmark\n\n`{}`\n\n\
         One `--role adapt` worker and three `--role serve` replicas of `udapose-server`, separate processes on one \
         store: {} (`{}`). Model `{}`; estimates send {} distinct PNG crops from `{}`; the jobs adapt on `{}`. \
         Load through the gRPC client library: {}. Machine: {}, **{} threads**; load average {} before, {} after; \
         {:.0} s in all. Commit `{}`.{}\n\n\
         **The replicas, the worker and the client share the machine's {} cores**, so this is not a measurement of \
         scaling: no number of replicas computes more than these cores do, and the figures below show the overhead \
         of spreading calls over replicas and that failover and swaps are correct. Scaling out needs a core budget \
         per replica (a machine or a pod each).\n\n",
        report["command"].as_str().unwrap_or(""),
        s["store"].as_str().unwrap_or(""),
        s["flags"].as_str().unwrap_or(""),
        args.model.display(),
        report["images"]["distinct"],
        report["images"]["folder"].as_str().unwrap_or(""),
        report["targets"]["folder"].as_str().unwrap_or(""),
        s["client"].as_str().unwrap_or(""),
        m["cpu"].as_str().unwrap_or(""),
        m["threads"],
        m["load_average_before"].as_str().unwrap_or(""),
        m["load_average_after"].as_str().unwrap_or(""),
        report["seconds"].as_f64().unwrap_or(f64::NAN),
        report["commit"].as_str().unwrap_or(""),
        args.note.as_ref().map(|n| format!(" Note: {n}.")).unwrap_or_default(),
        m["threads"],
    );
    md.push_str(&format!(
        "## Throughput and latency by replica count\n\n{} requests per row (fewer if they take over 40 s), {} in \
         flight through one client over the first 1, 2 or 3 replicas (after 2 untimed requests per replica); latency \
         as the client sees it; *other processes*: the CPU that processes other than this benchmark, its servers and \
         its store took meanwhile (the machine is shared). Every process runs `--torch-threads {}`: a replica's \
         backbone then runs on one core, so one replica alone leaves part of the second core idle and a second \
         replica can take it (see *CPU of the replicas*); that is the only gain more replicas can bring here, and \
         beyond it only the overhead of spreading the calls remains.\n\n",
        args.requests, args.concurrency, args.torch_threads
    ));
    md.push_str(&levels_table(&report["levels"], levels_md));
    if !oversubscribed_md.is_empty() {
        md.push_str(&format!(
            "\n### With one libtorch thread per core in every replica (the server's default)\n\n\
             The same, {} requests per row (fewer if they take over 20 s), on 3 other replicas started with `--torch-threads 0` (the others idle): \
             each replica runs as many intra-op threads as the machine has cores, so 2 or 3 busy replicas \
             oversubscribe the cores. This is why a replica's `--torch-threads` should match its CPU share (the \
             manifests keep it equal to the CPU limit).\n\n",
            args.oversubscribed_requests
        ));
        md.push_str(&levels_table(&report["levels_torch_threads_0"], oversubscribed_md));
    }
    let w = |k: &str| &f[k]["window"];
    let row = |name: &str, k: &str, detail: String| {
        let v = w(k);
        format!(
            "| {name} | {:.1} | {} | **{}** | {} | {} | {} | {} | {detail} |\n",
            v["seconds"].as_f64().unwrap_or(f64::NAN),
            v["requests"],
            v["failed"],
            fmt_ms(&v["p50_ms"]),
            fmt_ms(&v["p99_ms"]),
            fmt_ms(&v["max_ms"]),
            v["other_processes_cores"].as_f64().map_or_else(|| "–".into(), |c| format!("{c:.2}")),
        )
    };
    let (a, b, c, d) = (
        &f["swap_after_activation"],
        &f["serve_replica_kill9"],
        &f["rollback_on_one_replica"],
        &f["worker_kill9_mid_job"],
    );
    let prop =
        |v: &Value| v.as_array().map(|a| a.iter().map(fmt_ms).collect::<Vec<_>>().join(" / ")).unwrap_or_default();
    md.push_str(&format!(
        "\n## Failed requests in each fault\n\n{} requests in flight back to back through one client over every \
         replica, for the whole sequence below, in this order; each row counts the requests in flight during its \
         window (latency of the answered ones; *other processes*: the CPU that processes other than this benchmark, \
         its servers and its store took during the window, from `/proc`).\n\n\
         | fault | window (s) | requests | failed | p50 (ms) | p99 (ms) | max (ms) | other processes (cores) | what happened |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---|\n",
        s["fault_clients"]
    ));
    md.push_str(&row(
        "adaptation job, then the swap after its activation",
        "swap_after_activation",
        format!(
            "{} targets uploaded round-robin to the replicas; the job asked on serve-0 ran on the worker and ended {} \
             in {:.1} s ({} images trained on, {} held out); its version reached serve-0 / 1 / 2 {} ms after its activation",
            a["uploaded"]["ACCEPTED"],
            a["job"]["state"].as_str().unwrap_or(""),
            a["job"]["seconds"].as_f64().unwrap_or(f64::NAN),
            a["job"]["images_used"],
            a["job"]["images_held_out"],
            prop(&a["propagation_ms"]),
        ),
    ));
    md.push_str(&row(
        "`kill -9` of serve-2 under load",
        "serve_replica_kill9",
        format!(
            "{} s with serve-2 dead ({} requests, {} failed, p50 {} ms, max {} ms), then restarted on the same ports: \
             ready in {:.1} s, serving the active `{}`; the client sent it requests again {:.1} s after that (it retries \
             an endpoint that failed after a cool-down of 1 s, doubled per failure in a row, at most 10 s)",
            b["kill_window_s"],
            b["killed_until_restart"]["requests"],
            b["killed_until_restart"]["failed"],
            fmt_ms(&b["killed_until_restart"]["p50_ms"]),
            fmt_ms(&b["killed_until_restart"]["max_ms"]),
            b["restart_ready_s"].as_f64().unwrap_or(f64::NAN),
            b["restart_serves"].as_str().unwrap_or(""),
            b["client_rejoin_s_after_ready"].as_f64().unwrap_or(f64::NAN),
        ),
    ));
    md.push_str(&row(
        "rollback on one replica",
        "rollback_on_one_replica",
        format!(
            "`POST /v1/models/car/rollback` on serve-1 (answered in {} ms); `{}` reached serve-0 / 1 / 2 {} ms after \
             the call",
            fmt_ms(&c["call_ms"]),
            c["to_version"].as_str().unwrap_or(""),
            prop(&c["propagation_ms"]),
        ),
    ));
    let history = d["history"].as_array().cloned().unwrap_or_default();
    md.push_str(&row(
        "`kill -9` of the worker mid-job",
        "worker_kill9_mid_job",
        format!(
            "killed {} s after the job was seen RUNNING (state {}, round {}); a new worker (ready in {:.1} s) took it \
             over{}: its states {}; {} ({}), {} activation(s) by the job, {} incomplete version(s) activated; its \
             version reached serve-0 / 1 / 2 {} ms after its activation",
            d["killed_after_running_s"],
            d["state_at_kill"].as_str().unwrap_or(""),
            d["round_at_kill"],
            d["new_worker_ready_s"].as_f64().unwrap_or(f64::NAN),
            history
                .iter()
                .find_map(|h| h.as_str().filter(|h| h.contains("restart")))
                .map(|h| format!(" (\"{}\")", h.split_once(": ").map_or(h, |(_, m)| m)))
                .unwrap_or_default(),
            states_in_a_row(history.iter().filter_map(|h| h.as_str()?.split(':').next())),
            d["job"]["state"].as_str().unwrap_or(""),
            d["job"]["last_event"].as_str().unwrap_or(""),
            d["activations_by_job"],
            d["incomplete_versions_activated"].as_array().map_or(0, Vec::len),
            prop(&d["propagation_ms"]),
        ),
    ));
    let p = &report["propagation_ms"];
    md.push_str(&format!(
        "\n**Failed requests: {} in all** ({} requests during the faults).\n\n\
         ## Swap propagation\n\n\
         From an activation (the job's ACTIVATED event, as the worker timestamps it) or a rollback (its HTTP call) \
         to the first estimate each replica answers with the new version (each replica's active version polled every \
         50 ms, then confirmed by an estimate): **{} / {} / {} ms** (min / median / max over {} replica swaps). A \
         replica learns of a new activation when it next re-reads the store (`--poll {}`: every {} s), downloads the \
         version if it has not yet (`--cache-dir`), and its inference worker loads it before its next batch; so the \
         propagation is up to one poll period plus the download, the batch in progress and the load (each slower on \
         a busy machine). The replica that took the rollback re-reads the log at once: no poll in its figure.\n",
        report["failed_requests_in_faults"],
        report["fault_load"]["requests"],
        fmt_ms(&p["min"]),
        fmt_ms(&p["median"]),
        fmt_ms(&p["max"]),
        [a, c, d].iter().filter_map(|x| x["propagation_ms"].as_array()).map(Vec::len).sum::<usize>(),
        s["poll_s"],
        s["poll_s"],
    ));
    md.push_str(
        "\nEach replica's steps, from its log (ms after the activation): when its registry saw the new version active, \
         when its inference worker had loaded it (and how long that load took); the first answer then waits for the \
         batches queued meanwhile.\n\n\
         | swap | replica | new version seen active (ms) | loaded (ms) | load took (ms) | first answer by it (ms) |\n\
         |---|---|---:|---:|---:|---:|\n",
    );
    for (name, x) in [
        ("the first job's version", a),
        ("rollback on serve-1", c),
        ("the second job's version (after the worker's kill)", d),
    ] {
        let steps = x["propagation_steps"].as_array().cloned().unwrap_or_default();
        for (i, ms) in x["propagation_ms"].as_array().into_iter().flatten().enumerate() {
            let step = steps.get(i).cloned().unwrap_or(Value::Null);
            md.push_str(&format!(
                "| {name} | {} | {} | {} | {} | {} |\n",
                step["name"].as_str().unwrap_or("?"),
                fmt_ms(&step["seen_ms"]),
                fmt_ms(&step["loaded_ms"]),
                fmt_ms(&step["load_ms"]),
                fmt_ms(ms),
            ));
        }
    }
    let st = &report["startup"];
    md.push_str(&format!(
        "\nStart-up (process start to `/readyz`, seed import and model download from the store included): worker {:.1} s, \
         replicas {} s.\n\nTo reproduce: `udapose-lab bench scale` (after `make test` has rendered the quick data and \
         installed s3s-fs; `--help` lists the settings).\n",
        st["worker_ready_s"].as_f64().unwrap_or(f64::NAN),
        st["replicas_ready_s"]
            .as_array()
            .map(|a| a.iter().map(|x| x.as_f64().map_or("–".into(), |v| format!("{v:.1}"))).collect::<Vec<_>>().join(" / "))
            .unwrap_or_default(),
    ));
    md
}
