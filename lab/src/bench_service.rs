//! `udapose-lab bench service`: the inference service under load. Starts the real
//! `udapose-server` on loopback (batching on, then off), sends PNG crops over HTTP from 1, 4
//! and 16 concurrent clients, and measures throughput and p50/p99 latency; then, with the server
//! stopped, the backbone alone on the same crops (batch 1 and batch `--max-batch`) as the
//! ceiling, and the engine's own sequential image-to-pose rate. With a third server (batching
//! on, adaptation started only by the benchmark) it measures the estimate latency while idle and
//! while an online-adaptation job runs, then the hot-swap latency between the seed and the
//! job's version (rollback / activate round trips, with clients running and with none). Writes
//! `reports/service.json` and its Markdown twin.

use std::{
    fs,
    io::{Read, Write},
    net::{SocketAddr, TcpListener, TcpStream},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, Ordering},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow, bail, ensure};
use serde_json::{Value, json};
use tch::Tensor;
use udapose_engine::{
    checkpoint,
    estimator::Estimator,
    input::{self, Crop, Rgb8Image},
    solver::SolverConfig,
};
use udapose_lab::atomic::write_atomic;

#[derive(clap::Args)]
pub struct ServiceArgs {
    /// Model directory (served as category `car`).
    #[arg(long, default_value = "models/car")]
    model: PathBuf,
    /// Folder of PNG crops to send (the first `--images`, in name order).
    #[arg(long, default_value = "data/syncar-ood-standard/source/test/images/car")]
    images: PathBuf,
    #[arg(long, default_value_t = 16)]
    distinct: usize,
    /// Client concurrency levels.
    #[arg(long, value_delimiter = ',', default_value = "1,4,16")]
    concurrency: Vec<usize>,
    /// Requests per concurrency level (after 4 untimed warm-up requests).
    #[arg(long, default_value_t = 64)]
    requests: usize,
    /// The server's batch limit with batching on (off is `--max-batch 1`).
    #[arg(long, default_value_t = 8)]
    max_batch: usize,
    #[arg(long, default_value_t = 5)]
    max_delay_ms: u64,
    /// The server binary (default: next to this one).
    #[arg(long)]
    server: Option<PathBuf>,
    /// Report (JSON; a Markdown twin is written next to it).
    #[arg(long, default_value = "reports/service.json")]
    out: PathBuf,
    /// A remark on the conditions of the run (e.g. other load), copied into both reports.
    #[arg(long)]
    note: Option<String>,
    /// Skip the batching on/off concurrency levels.
    #[arg(long)]
    skip_batching_levels: bool,
    /// Skip the backbone-only and engine-only ceiling.
    #[arg(long)]
    skip_ceiling: bool,
    /// Skip the idle vs during-adaptation latency (the job still runs when the swap is measured).
    #[arg(long)]
    skip_adaptation: bool,
    /// Skip the swap latency.
    #[arg(long)]
    skip_swap: bool,
    /// Target images to adapt on (default: the `combined` domain's adapt split next to
    /// `--images`, i.e. `<data>/combined/adapt/images/<category>`).
    #[arg(long)]
    adapt_images: Option<PathBuf>,
    /// Most target images uploaded (the first, in name order).
    #[arg(long, default_value_t = 100)]
    adapt_count: usize,
    /// Clients sending estimates back to back while idle, during the job and during swaps.
    #[arg(long, default_value_t = 4)]
    adapt_clients: usize,
    /// Seconds of idle load measured before the job, and again after it.
    #[arg(long, default_value_t = 20.0)]
    adapt_idle_seconds: f64,
    /// The job's `max_rounds` override (default: the server's).
    #[arg(long)]
    adapt_max_rounds: Option<u32>,
    /// The job's `learning_rate` override (default: the server's).
    #[arg(long)]
    adapt_learning_rate: Option<f64>,
    /// Longest wait for the job to end, in seconds.
    #[arg(long, default_value_t = 480)]
    adapt_timeout_s: u64,
    /// Rollback/activate round trips measured with clients, and again with none.
    #[arg(long, default_value_t = 3)]
    swap_rounds: usize,
}

/// One concurrency level's measurements.
pub(crate) struct Level {
    pub(crate) concurrency: usize,
    pub(crate) requests: usize,
    pub(crate) errors: usize,
    pub(crate) seconds: f64,
    pub(crate) latencies_ms: Vec<f64>,
}

impl Level {
    pub(crate) fn throughput(&self) -> f64 {
        (self.requests - self.errors) as f64 / self.seconds
    }

    pub(crate) fn percentile(&self, p: f64) -> f64 {
        percentile(&self.latencies_ms, p)
    }

    pub(crate) fn json(&self) -> Value {
        json!({
            "concurrency": self.concurrency,
            "requests": self.requests,
            "errors": self.errors,
            "seconds": self.seconds,
            "throughput_per_s": self.throughput(),
            "p50_ms": self.percentile(0.5),
            "p99_ms": self.percentile(0.99),
        })
    }
}

/// The nearest-rank `p` quantile (0 to 1); NaN when empty.
pub(crate) fn percentile(v: &[f64], p: f64) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    v[((p * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)]
}

pub fn run(args: &ServiceArgs) -> Result<()> {
    ensure!(args.requests >= 1 && args.distinct >= 1, "--requests and --distinct must be at least 1");
    ensure!(args.adapt_clients >= 1, "--adapt-clients must be at least 1");
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let load_before = load_average();
    let images = read_images(&args.images, args.distinct)?;
    let server_bin = match &args.server {
        Some(p) => p.clone(),
        None => std::env::current_exe()?.with_file_name("udapose-server"),
    };
    ensure!(server_bin.is_file(), "{} not found: build the workspace first", server_bin.display());
    let model = fs::canonicalize(&args.model).with_context(|| format!("model {}", args.model.display()))?;
    let manifest_path = model.join(checkpoint::MANIFEST);
    let manifest: checkpoint::Manifest = serde_json::from_str(&fs::read_to_string(&manifest_path)?)
        .with_context(|| format!("parsing {}", manifest_path.display()))?;

    let mut modes = Vec::new();
    if !args.skip_batching_levels {
        for (name, max_batch) in [("on", args.max_batch), ("off", 1)] {
            eprintln!("batching {name} (--max-batch {max_batch})");
            let server = ServerProcess::start(&server_bin, &model, max_batch, args.max_delay_ms, &[])?;
            let levels = args
                .concurrency
                .iter()
                .map(|&c| load(server.http, &images, c, args.requests))
                .collect::<Result<Vec<_>>>()?;
            for l in &levels {
                eprintln!(
                    "  c={:>2}: {:.2} req/s, p50 {:.0} ms, p99 {:.0} ms, {} errors",
                    l.concurrency,
                    l.throughput(),
                    l.percentile(0.5),
                    l.percentile(0.99),
                    l.errors
                );
            }
            modes.push((name, max_batch, levels));
        }
    }

    let (adaptation, swap) = if args.skip_adaptation && args.skip_swap {
        (Value::Null, Value::Null)
    } else {
        adapt_and_swap(args, &server_bin, &model, &images)?
    };

    let ceiling = if args.skip_ceiling {
        None
    } else {
        eprintln!("backbone alone and engine alone (server stopped)");
        Some(backbone_ceiling(&model, &images, args.max_batch)?)
    };
    let best = modes.iter().flat_map(|(_, _, l)| l).map(Level::throughput).fold(f64::NAN, f64::max);
    let report = json!({
        "command": command,
        "commit": crate::synth_cmd::git_commit(),
        "machine": {
            "cpu": udapose_engine::runtime::cpu_model(),
            "threads": std::thread::available_parallelism().map_or(1, |n| n.get()),
            "torch_threads": tch::get_num_threads(),
            "device": format!("{:?}", udapose_engine::runtime::RuntimeInfo::detect().device()),
            "load_average_before": load_before,
            "load_average_after": load_average(),
        },
        "note": args.note,
        "model": args.model.display().to_string(),
        "crop": manifest.crop,
        "images": { "folder": args.images.display().to_string(), "distinct": images.len() },
        "transport": "HTTP/1.1 POST /v1/pose/car with a PNG body, one connection per request, loopback",
        "max_delay_ms": args.max_delay_ms,
        "modes": modes.iter().map(|(name, max_batch, levels)| json!({
            "batching": name, "max_batch": max_batch, "levels": levels.iter().map(Level::json).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
        "backbone_only_per_s": ceiling.as_ref().map(|c| json!({
            "batch_1": c.batch1, "batched": c.batched, "batch": args.max_batch,
        })),
        "engine_sequential_per_s": ceiling.as_ref().map(|c| c.engine),
        "best_service_per_s": best,
        "ratio_to_backbone_ceiling": ceiling.as_ref().map(|c| best / c.batch1.max(c.batched)),
        "ratio_to_engine_sequential": ceiling.as_ref().map(|c| best / c.engine),
        "adaptation": adaptation,
        "swap": swap,
    });
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    let mut md = markdown(args, &report, &modes, manifest.crop, ceiling.as_ref(), best);
    md.push_str(&adaptation_markdown(&report));
    md.push_str(&swap_markdown(&report));
    write_atomic(&args.out.with_extension("md"), md.as_bytes())?;
    eprintln!("wrote {} and its .md", args.out.display());
    Ok(())
}

fn markdown(
    args: &ServiceArgs,
    report: &Value,
    modes: &[(&str, usize, Vec<Level>)],
    crop: [usize; 2],
    ceiling: Option<&Ceiling>,
    best: f64,
) -> String {
    let m = &report["machine"];
    let mut md = format!(
        "# Service benchmark\n\n`{}`\n\nModel `{}` ({}×{} crops), {} distinct PNG crops from `{}`, {} requests per level \
         after 4 warm-up requests; HTTP/1.1 POST `/v1/pose/car`, one connection per request, on loopback. Machine: {}, \
         {} threads (torch {}), device {}; load average {} before, {} after. Commit `{}`.{}\n\n",
        report["command"].as_str().unwrap_or(""),
        args.model.display(),
        crop[0],
        crop[1],
        report["images"]["distinct"],
        args.images.display(),
        args.requests,
        m["cpu"].as_str().unwrap_or(""),
        m["threads"],
        m["torch_threads"],
        m["device"].as_str().unwrap_or(""),
        m["load_average_before"].as_str().unwrap_or(""),
        m["load_average_after"].as_str().unwrap_or(""),
        report["commit"].as_str().unwrap_or(""),
        args.note.as_ref().map(|n| format!(" Note: {n}.")).unwrap_or_default(),
    );
    if modes.is_empty() {
        md.push_str("The batching levels were skipped (`--skip-batching-levels`).\n");
    } else {
        md.push_str("| batching | clients | req/s | p50 (ms) | p99 (ms) | errors |\n|---|---:|---:|---:|---:|---:|\n");
    }
    for (name, max_batch, levels) in modes {
        for l in levels {
            md.push_str(&format!(
                "| {name} (max {max_batch}, {} ms) | {} | {:.2} | {:.0} | {:.0} | {} |\n",
                if *max_batch > 1 { args.max_delay_ms } else { 0 },
                l.concurrency,
                l.throughput(),
                l.percentile(0.5),
                l.percentile(0.99),
                l.errors
            ));
        }
    }
    let Some(c) = ceiling else {
        md.push_str("\nThe ceiling was skipped (`--skip-ceiling`).\n");
        return md;
    };
    let ceiling = c.batch1.max(c.batched);
    let (backbone_ms, engine_ms) = (1e3 / c.batch1, 1e3 / c.engine);
    md.push_str(&format!(
        "\n**Ceiling**, measured in the same run with the server stopped: the backbone alone runs {:.2} crops/s at \
         batch 1 and {:.2} crops/s at batch {}; the engine alone (backbone + solver, one image after the other, no \
         I/O) {:.2} images/s, i.e. {engine_ms:.1} ms per image of which the backbone is {backbone_ms:.1} ms and the \
         render-and-compare solver the other {:.1} ms. The best service throughput, {best:.2} req/s, is **{:.0}%** \
         of the backbone-only ceiling (the solver runs after the backbone on the worker thread, so the backbone \
         alone is out of reach) and {:.0}% of the engine's sequential rate. Batched, the backbone saves {:.1} ms per crop, which explains only part of \
         that gain; the rest is not established (a likely cause: libtorch's OpenMP threads spin after each forward \
         pass and slow the solver's threads that follow, once per batch in the worker but once per image in the \
         sequential loop).\n",
        c.batch1,
        c.batched,
        args.max_batch,
        c.engine,
        engine_ms - backbone_ms,
        100.0 * best / ceiling,
        100.0 * best / c.engine,
        backbone_ms - 1e3 / c.batched,
    ));
    md
}

/// The PNG bytes of the first `n` images of a folder.
pub(crate) fn read_images(dir: &Path, n: usize) -> Result<Vec<Vec<u8>>> {
    let mut paths: Vec<PathBuf> = fs::read_dir(dir)
        .with_context(|| format!("listing {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    paths.sort();
    paths.truncate(n);
    ensure!(!paths.is_empty(), "no PNG images in {}", dir.display());
    paths.iter().map(|p| fs::read(p).with_context(|| format!("reading {}", p.display()))).collect()
}

/// A `udapose-server` on free loopback ports with a scratch models dir and store.
pub(crate) struct ServerProcess {
    pub(crate) child: Child,
    dir: PathBuf,
    pub(crate) http: SocketAddr,
}

impl ServerProcess {
    /// `extra`: more server flags; with any, the server logs at `info` (its own crate) so that
    /// [`ServerProcess::log`] can report model loads and job events.
    fn start(binary: &Path, model: &Path, max_batch: usize, max_delay_ms: u64, extra: &[&str]) -> Result<Self> {
        let tag = if extra.is_empty() { "" } else { "-adapt" };
        let dir = std::env::temp_dir().join(format!("udapose-bench-service-{}-{max_batch}{tag}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(dir.join("models"))?;
        std::os::unix::fs::symlink(model, dir.join("models/car"))?;
        let ports: Vec<TcpListener> = (0..2).map(|_| TcpListener::bind("127.0.0.1:0")).collect::<Result<_, _>>()?;
        let (http, grpc) = (ports[0].local_addr()?, ports[1].local_addr()?);
        drop(ports);
        let mut command = Command::new(binary);
        command
            .args(["--http-addr", &http.to_string(), "--grpc-addr", &grpc.to_string()])
            .arg("--models")
            .arg(dir.join("models"))
            .arg("--store")
            .arg(dir.join("state"))
            .args(["--max-batch", &max_batch.to_string(), "--max-delay-ms", &max_delay_ms.to_string()])
            .args(extra)
            .env("RUST_LOG", if extra.is_empty() { "warn" } else { "warn,udapose_server=info" });
        Self::spawn(command, dir, http)
    }

    /// Runs `command` (a server listening for HTTP on `http`) with its output to
    /// `<dir>/server.log`, and waits until it is ready. `dir` is removed when it is dropped.
    pub(crate) fn spawn(mut command: Command, dir: PathBuf, http: SocketAddr) -> Result<Self> {
        fs::create_dir_all(&dir)?;
        let log = fs::File::create(dir.join("server.log"))?;
        let child = command
            .env("NO_COLOR", "1")
            .env_remove("UDAPOSE_TOKEN")
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("starting {}", command.get_program().display()))?;
        let mut server = ServerProcess { child, dir, http };
        let deadline = Instant::now() + Duration::from_secs(120);
        while post_or_get(http, "GET", "/readyz", b"").map(|(s, _)| s).unwrap_or(0) != 200 {
            if Instant::now() > deadline {
                bail!("the server did not become ready: {}", server.log());
            }
            if let Ok(Some(status)) = server.child.try_wait() {
                bail!("the server exited ({status}) before it was ready: {}", server.log());
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(server)
    }

    /// The server's log so far, without terminal colour codes.
    pub(crate) fn log(&self) -> String {
        let text = fs::read_to_string(self.dir.join("server.log")).unwrap_or_default();
        let mut out = String::with_capacity(text.len());
        let mut chars = text.chars();
        while let Some(c) = chars.next() {
            if c == '\u{1b}' {
                // CSI: ESC [ parameters final-byte
                for d in chars.by_ref() {
                    if d.is_ascii_alphabetic() {
                        break;
                    }
                }
            } else {
                out.push(c);
            }
        }
        out
    }

    pub(crate) fn get_json(&self, path: &str) -> Result<Value> {
        let (status, body) = post_or_get(self.http, "GET", path, b"").with_context(|| format!("GET {path}"))?;
        ensure!(status == 200, "GET {path}: {status} {body}");
        serde_json::from_str(&body).with_context(|| format!("GET {path}: {body}"))
    }

    pub(crate) fn post_json(&self, path: &str, body: &Value) -> Result<Value> {
        let (status, answer) = post_or_get(self.http, "POST", path, body.to_string().as_bytes())
            .with_context(|| format!("POST {path}"))?;
        ensure!(status == 200, "POST {path}: {status} {answer}");
        serde_json::from_str(&answer).with_context(|| format!("POST {path}: {answer}"))
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = fs::remove_dir_all(&self.dir);
    }
}

/// `requests` estimates from `concurrency` threads (images in rotation), after a warm-up.
fn load(http: SocketAddr, images: &[Vec<u8>], concurrency: usize, requests: usize) -> Result<Level> {
    ensure!(concurrency >= 1, "concurrency must be at least 1");
    for image in images.iter().cycle().take(4) {
        let (status, body) = post_or_get(http, "POST", "/v1/pose/car", image)?;
        ensure!(status == 200, "warm-up request failed: {status} {body}");
    }
    let images = Arc::new(images.to_vec());
    let started = Instant::now();
    let threads: Vec<_> = (0..concurrency)
        .map(|t| {
            let images = images.clone();
            std::thread::spawn(move || {
                let mut out = Vec::new();
                for r in (t..requests).step_by(concurrency) {
                    let sent = Instant::now();
                    let ok =
                        matches!(post_or_get(http, "POST", "/v1/pose/car", &images[r % images.len()]), Ok((200, _)));
                    out.push((ok, sent.elapsed().as_secs_f64() * 1e3));
                }
                out
            })
        })
        .collect();
    let mut latencies = Vec::new();
    let mut errors = 0;
    for t in threads {
        for (ok, ms) in t.join().map_err(|_| anyhow::anyhow!("a client thread panicked"))? {
            if ok {
                latencies.push(ms);
            } else {
                errors += 1;
            }
        }
    }
    Ok(Level { concurrency, requests, errors, seconds: started.elapsed().as_secs_f64(), latencies_ms: latencies })
}

/// HTTP/1.1 with `Connection: close`; returns (status, body).
pub(crate) fn post_or_get(addr: SocketAddr, method: &str, path: &str, body: &[u8]) -> std::io::Result<(u16, String)> {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    stream.set_read_timeout(Some(Duration::from_secs(120)))?;
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n\r\n",
        body.len()
    )?;
    stream.write_all(body)?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    let status = response.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let body = response.split_once("\r\n\r\n").map(|(_, b)| b.to_owned()).unwrap_or_default();
    Ok((status, body))
}

/// CPU time in clock ticks (USER_HZ: 100 per second on Linux) of the whole machine, of this
/// process (the clients) and of the server, to tell how much of the machine other processes
/// took during a window.
#[derive(Clone, Copy)]
struct Cpu {
    at: Instant,
    busy: u64,
    own: u64,
    server: u64,
}

impl Cpu {
    fn now(server_pid: u32) -> Option<Cpu> {
        Some(Cpu {
            at: Instant::now(),
            busy: machine_busy_ticks()?,
            own: process_ticks("self")?,
            server: process_ticks(&server_pid.to_string())?,
        })
    }

    /// Cores that other processes used on average between `self` and `later`.
    fn others(&self, later: &Cpu) -> f64 {
        let ours = (later.own - self.own) + (later.server - self.server);
        let others = (later.busy - self.busy).saturating_sub(ours);
        others as f64 / 100.0 / (later.at - self.at).as_secs_f64()
    }
}

/// The CPU time (clock ticks, 100 per second) the whole machine has spent busy since boot.
pub(crate) fn machine_busy_ticks() -> Option<u64> {
    let stat = fs::read_to_string("/proc/stat").ok()?;
    let ticks: Vec<u64> = stat.lines().next()?.split_whitespace().skip(1).map(|t| t.parse().unwrap_or(0)).collect();
    // user nice system idle iowait irq softirq steal (guest time is within user)
    Some(ticks.iter().take(8).sum::<u64>() - ticks.get(3)? - ticks.get(4)?)
}

/// The CPU time (user + system, clock ticks) of process `pid` (or `self`) so far.
pub(crate) fn process_ticks(pid: &str) -> Option<u64> {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    Some(fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?)
}

fn others_cores(from: Option<Cpu>, to: Option<Cpu>) -> Option<f64> {
    Some(from?.others(&to?))
}

/// One estimate a background client sent.
pub(crate) struct Record {
    pub(crate) start: Instant,
    pub(crate) end: Instant,
    /// The model version that answered, or why the request failed.
    pub(crate) answer: Result<String, String>,
}

impl Record {
    pub(crate) fn ms(&self) -> f64 {
        (self.end - self.start).as_secs_f64() * 1e3
    }

    /// Started and finished within `[from, to]`.
    pub(crate) fn within(&self, from: Instant, to: Instant) -> bool {
        self.start >= from && self.end <= to
    }

    /// In flight at some moment of `[from, to]`.
    pub(crate) fn overlaps(&self, from: Instant, to: Instant) -> bool {
        self.start <= to && self.end >= from
    }

    fn answered_by(&self, version: &str) -> bool {
        matches!(&self.answer, Ok(v) if v == version)
    }
}

/// One estimate: the model version that answered it, or why it failed.
pub(crate) fn estimate(http: SocketAddr, image: &[u8]) -> Result<String, String> {
    let short = |s: &str| s.chars().take(200).collect::<String>();
    match post_or_get(http, "POST", "/v1/pose/car", image) {
        Ok((200, body)) => serde_json::from_str::<Value>(&body)
            .ok()
            .and_then(|v| v["model_version"].as_str().map(str::to_owned))
            .ok_or_else(|| format!("200 without a model_version: {}", short(&body))),
        Ok((status, body)) => Err(format!("{status} {}", short(&body))),
        Err(e) => Err(e.to_string()),
    }
}

/// Client threads sending estimates back to back (images in rotation) until stopped; every
/// request is recorded with its start, end and answering version.
struct Clients {
    stop: Arc<AtomicBool>,
    records: Arc<Mutex<Vec<Record>>>,
    threads: Vec<JoinHandle<()>>,
}

impl Clients {
    fn start(http: SocketAddr, images: &Arc<Vec<Vec<u8>>>, n: usize) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let records = Arc::new(Mutex::new(Vec::new()));
        let threads = (0..n)
            .map(|t| {
                let (stop, records, images) = (stop.clone(), records.clone(), images.clone());
                std::thread::spawn(move || {
                    for i in (t..).step_by(n) {
                        if stop.load(Ordering::Acquire) {
                            break;
                        }
                        let start = Instant::now();
                        let answer = estimate(http, &images[i % images.len()]);
                        let record = Record { start, end: Instant::now(), answer };
                        records.lock().unwrap_or_else(|p| p.into_inner()).push(record);
                    }
                })
            })
            .collect();
        Clients { stop, records, threads }
    }

    /// The end of the first answer by `version` among the requests finished since `since`.
    fn first_answer(&self, version: &str, since: Instant) -> Option<Instant> {
        let records = self.records.lock().unwrap_or_else(|p| p.into_inner());
        records.iter().filter(|r| r.end >= since && r.answered_by(version)).map(|r| r.end).min()
    }

    /// Stops the clients (each finishes its request in flight) and returns every record.
    fn stop(mut self) -> Vec<Record> {
        self.stop.store(true, Ordering::Release);
        for t in std::mem::take(&mut self.threads) {
            let _ = t.join();
        }
        std::mem::take(&mut *self.records.lock().unwrap_or_else(|p| p.into_inner()))
    }
}

impl Drop for Clients {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
    }
}

/// The requests that started and finished within `[from, to]`, as a level.
pub(crate) fn window(records: &[Record], from: Instant, to: Instant, concurrency: usize) -> Level {
    let inside: Vec<&Record> = records.iter().filter(|r| r.within(from, to)).collect();
    Level {
        concurrency,
        requests: inside.len(),
        errors: inside.iter().filter(|r| r.answer.is_err()).count(),
        seconds: to.saturating_duration_since(from).as_secs_f64(),
        latencies_ms: inside.iter().filter(|r| r.answer.is_ok()).map(|r| r.ms()).collect(),
    }
}

/// A level's JSON plus its largest and mean latency and the cores other processes used.
fn window_json(l: &Level, others: Option<f64>) -> Value {
    let mut v = l.json();
    v["other_processes_cores"] = json!(others);
    v["max_ms"] = json!(percentile(&l.latencies_ms, 1.0));
    v["mean_ms"] = json!(l.latencies_ms.iter().sum::<f64>() / l.latencies_ms.len() as f64);
    v
}

pub(crate) fn summary(l: &Level) -> String {
    format!(
        "{} requests in {:.1} s, {:.2} req/s, p50 {:.0} ms, p99 {:.0} ms, {} errors",
        l.requests,
        l.seconds,
        l.throughput(),
        l.percentile(0.5),
        l.percentile(0.99),
        l.errors
    )
}

pub(crate) fn min_median_max(v: &[f64]) -> Value {
    json!({ "min": percentile(v, 0.0), "median": median(v), "max": percentile(v, 1.0) })
}

pub(crate) fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

/// `<data>/combined/adapt/images/<category>` for `--images` `<data>/<domain>/<split>/images/<category>`.
fn default_adapt_images(images: &Path) -> Result<PathBuf> {
    let underivable = || format!("cannot derive --adapt-images from --images {}: pass it", images.display());
    let category = images.file_name().with_context(underivable)?;
    let data = images.ancestors().nth(4).filter(|p| !p.as_os_str().is_empty()).with_context(underivable)?;
    Ok(data.join("combined/adapt/images").join(category))
}

/// A rollback (to the active version's predecessor) or an activation of `target`.
struct SwapAction {
    rollback: bool,
    target: String,
}

impl SwapAction {
    fn name(&self) -> &'static str {
        if self.rollback { "rollback" } else { "activate" }
    }

    /// Calls the API and checks that `target` is now active.
    fn call(&self, server: &ServerProcess) -> Result<()> {
        let reason = "udapose-lab bench service: swap latency";
        let answer = if self.rollback {
            server.post_json("/v1/models/car/rollback", &json!({ "reason": reason }))?
        } else {
            server.post_json("/v1/models/car/activate", &json!({ "version": self.target, "reason": reason }))?
        };
        ensure!(
            answer["version"].as_str() == Some(self.target.as_str()),
            "{} activated {} instead of {}",
            self.name(),
            answer["version"],
            self.target
        );
        Ok(())
    }
}

/// One swap's measurements.
struct SwapSample {
    action: &'static str,
    target: String,
    /// The activation call's own duration.
    call_ms: f64,
    /// From the call's response to the first answer by `target`.
    latency_ms: f64,
    /// The largest latency of the requests in flight between the call and that first answer.
    max_request_ms: f64,
    /// Requests in flight between the call and that first answer.
    requests: usize,
    /// Failed requests between the call and the end of the settling time after the first answer.
    errors: usize,
    /// Answers by another version to requests sent after the call's response (and answered
    /// before the next swap).
    stale: usize,
    /// With no clients: the median latency of 3 requests right after the first one.
    steady_ms: Option<f64>,
}

impl SwapSample {
    fn json(&self) -> Value {
        json!({
            "action": self.action,
            "to_version": self.target,
            "call_ms": self.call_ms,
            "latency_ms": self.latency_ms,
            "max_request_ms": self.max_request_ms,
            "requests_in_flight": self.requests,
            "errors": self.errors,
            "stale_answers_after_response": self.stale,
            "steady_request_ms": self.steady_ms,
        })
    }
}

/// How long the clients run before an idle window is measured: the first batched requests after
/// the server starts can be much slower than the rest.
const WARM_UP: Duration = Duration::from_secs(3);

/// How long the clients keep running after a swap's first new answer before the next swap.
const SETTLE: Duration = Duration::from_millis(500);

/// The times of one swap made while clients run; measured once the clients have stopped.
struct SwapTimes {
    action: &'static str,
    target: String,
    sent: Instant,
    answered: Instant,
    settled: Instant,
}

impl SwapTimes {
    fn measure(&self, records: &[Record]) -> SwapSample {
        let first = records
            .iter()
            .filter(|r| r.end >= self.sent && r.answered_by(&self.target))
            .map(|r| r.end)
            .min()
            .unwrap_or(self.settled);
        let around: Vec<&Record> = records.iter().filter(|r| r.overlaps(self.sent, first)).collect();
        SwapSample {
            action: self.action,
            target: self.target.clone(),
            call_ms: (self.answered - self.sent).as_secs_f64() * 1e3,
            latency_ms: first.saturating_duration_since(self.answered).as_secs_f64() * 1e3,
            max_request_ms: around.iter().map(|r| r.ms()).fold(0.0, f64::max),
            requests: around.len(),
            errors: records.iter().filter(|r| r.overlaps(self.sent, self.settled) && r.answer.is_err()).count(),
            stale: records
                .iter()
                .filter(|r| r.start >= self.answered && r.end <= self.settled)
                .filter(|r| r.answer.as_ref().is_ok_and(|v| *v != self.target))
                .count(),
            steady_ms: None,
        }
    }
}

/// A swap while `clients` run: call, wait for the first answer by the new version, settle.
fn swap_with_clients(server: &ServerProcess, clients: &Clients, action: &SwapAction) -> Result<SwapTimes> {
    let sent = Instant::now();
    action.call(server)?;
    let answered = Instant::now();
    let deadline = answered + Duration::from_secs(120);
    while clients.first_answer(&action.target, sent).is_none() {
        ensure!(Instant::now() < deadline, "no answer by {} 120 s after its {}", action.target, action.name());
        std::thread::sleep(Duration::from_millis(5));
    }
    std::thread::sleep(SETTLE);
    Ok(SwapTimes { action: action.name(), target: action.target.clone(), sent, answered, settled: Instant::now() })
}

/// A swap with no clients: after a quiet moment, call, then one request (the worker loads the
/// new version when it arrives), then 3 more for the steady latency.
fn swap_idle(server: &ServerProcess, image: &[u8], action: &SwapAction) -> Result<SwapSample> {
    std::thread::sleep(SETTLE);
    let sent = Instant::now();
    action.call(server)?;
    let answered = Instant::now();
    let first = estimate(server.http, image);
    let end = Instant::now();
    let mut errors = usize::from(first.is_err());
    let mut steady = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        match estimate(server.http, image) {
            Ok(_) => steady.push(t.elapsed().as_secs_f64() * 1e3),
            Err(_) => errors += 1,
        }
    }
    let ms = (end - answered).as_secs_f64() * 1e3;
    Ok(SwapSample {
        action: action.name(),
        target: action.target.clone(),
        call_ms: (answered - sent).as_secs_f64() * 1e3,
        latency_ms: if first.is_ok() { ms } else { f64::NAN },
        max_request_ms: ms,
        requests: 1,
        errors,
        stale: usize::from(first.as_ref().is_ok_and(|v| *v != action.target)),
        steady_ms: Some(median(&steady)),
    })
}

/// The adaptation job as the report shows it.
fn job_json(job: &Value, overrides: &Value, running_s: f64, validating_s: f64) -> Value {
    let e = &job["last_event"];
    json!({
        "id": job["job_id"],
        "state": job["state"],
        "reason": job["reason"],
        "version": job["version"],
        "source_version": job["source_version"],
        "overrides": overrides,
        "rounds": e["round"],
        "max_rounds": e["max_rounds"],
        "fired_ratio": e["fired_ratio"],
        "pose_change_median_deg": e["pose_change_median_deg"],
        "images_used": job["images_used"],
        "images_held_out": job["images_held_out"],
        "gate": e["gate"],
        "seconds": job["updated"].as_f64().zip(job["created"].as_f64()).map(|(u, c)| u - c),
        "running_seconds": running_s,
        "validating_seconds": validating_s,
    })
}

/// What the server logged: its model loads after the first (the swaps) and its warnings.
pub(crate) fn server_log_json(log: &str) -> Value {
    let loads: Vec<f64> = log
        .lines()
        .filter(|l| l.contains("model loaded"))
        .filter_map(|l| l.split_whitespace().find_map(|w| w.strip_prefix("ms="))?.parse().ok())
        .skip(1)
        .collect();
    let problems: Vec<&str> = log.lines().filter(|l| l.contains(" WARN ") || l.contains(" ERROR ")).collect();
    json!({
        "model_loads_after_start_ms": { "samples": loads.len(), "min": percentile(&loads, 0.0), "median": median(&loads), "max": percentile(&loads, 1.0) },
        "warnings_and_errors": problems.len(),
        "first_warnings_and_errors": problems.iter().take(10).collect::<Vec<_>>(),
    })
}

/// The adaptation server (batching on; only the benchmark starts jobs): `--adapt-clients`
/// clients idle, then during a job on the uploaded target images; then swaps between the seed
/// and the job's version with the clients running and with none. Returns the report's
/// `adaptation` and `swap` values (null when skipped).
fn adapt_and_swap(args: &ServiceArgs, server_bin: &Path, model: &Path, images: &[Vec<u8>]) -> Result<(Value, Value)> {
    let folder = match &args.adapt_images {
        Some(f) => f.clone(),
        None => default_adapt_images(&args.images)?,
    };
    let targets = read_images(&folder, args.adapt_count)?;
    let n = args.adapt_clients;
    let flags = ["--adapt-min-images", "1000000"];
    eprintln!("adaptation (--max-batch {} {}), {n} clients", args.max_batch, flags.join(" "));
    let server = ServerProcess::start(server_bin, model, args.max_batch, args.max_delay_ms, &flags)?;
    let images = Arc::new(images.to_vec());
    for image in images.iter().cycle().take(4) {
        estimate(server.http, image).map_err(|e| anyhow!("warm-up request failed: {e}"))?;
    }
    let source = server.get_json("/v1/models/car")?["version"].as_str().context("no active car version")?.to_owned();

    // The clients for `--adapt-idle-seconds` after a second's warm-up, with no job.
    let pid = server.child.id();
    let measure_idle = |when: &str| {
        let clients = Clients::start(server.http, &images, n);
        std::thread::sleep(WARM_UP);
        let (from, cpu_from) = (Instant::now(), Cpu::now(pid));
        std::thread::sleep(Duration::from_secs_f64(args.adapt_idle_seconds));
        let (to, cpu_to) = (Instant::now(), Cpu::now(pid));
        let idle = window(&clients.stop(), from, to, n);
        let others = others_cores(cpu_from, cpu_to);
        eprintln!("  idle {when} the job: {}; other processes {:.2} cores", summary(&idle), others.unwrap_or(f64::NAN));
        (idle, others)
    };
    let mut loads = vec![("idle_before_start", load_average())];
    let idle_before = (!args.skip_adaptation).then(|| measure_idle("before"));
    loads.push(("idle_before_end", load_average()));

    eprintln!("  uploading {} target images from {}", targets.len(), folder.display());
    let upload_started = Instant::now();
    let mut statuses = std::collections::BTreeMap::<String, usize>::new();
    let mut rejections = Vec::new();
    for target in &targets {
        let (status, body) = post_or_get(server.http, "POST", "/v1/adapt/car/images", target)?;
        ensure!(status == 200, "uploading a target image: {status} {body}");
        let answer: Value = serde_json::from_str(&body).with_context(|| format!("upload answer {body}"))?;
        let result = &answer["results"][0];
        let s = result["status"].as_str().unwrap_or("?").to_owned();
        if s != "ACCEPTED" && rejections.len() < 5 {
            rejections.push(format!("{s}: {}", result["reason"].as_str().unwrap_or("")));
        }
        *statuses.entry(s).or_default() += 1;
    }
    let upload_seconds = upload_started.elapsed().as_secs_f64();

    let clients = (!args.skip_adaptation).then(|| Clients::start(server.http, &images, n));
    if clients.is_some() {
        std::thread::sleep(Duration::from_secs(1));
    }
    let mut overrides = json!({});
    if let Some(r) = args.adapt_max_rounds {
        overrides["max_rounds"] = json!(r);
    }
    if let Some(lr) = args.adapt_learning_rate {
        overrides["learning_rate"] = json!(lr);
    }
    let job = server.post_json("/v1/adapt/car/jobs", &json!({ "overrides": overrides }))?;
    let id = job["job_id"].as_str().context("the job has no job_id")?.to_owned();
    loads.push(("job_start", load_average()));
    eprintln!("  job {id}: {} images trained on, {} held out", job["images_used"], job["images_held_out"]);
    let deadline = Instant::now() + Duration::from_secs(args.adapt_timeout_s);
    let (mut running, mut validating, mut active_until) = (None, None, None);
    let (mut cpu_running, mut cpu_validating, mut cpu_until) = (None, None, None);
    let mut round = 0;
    let job = loop {
        let job = server.get_json(&format!("/v1/jobs/{id}"))?;
        let now = Instant::now();
        let cpu = Cpu::now(pid);
        let state = job["state"].as_str().unwrap_or("").to_owned();
        match state.as_str() {
            "QUEUED" => {}
            "RUNNING" | "VALIDATING" => {
                if running.is_none() {
                    (running, cpu_running) = (Some(now), cpu);
                }
                (active_until, cpu_until) = (Some(now), cpu);
                let e = &job["last_event"];
                if e["round"].as_u64().is_some_and(|r| r != round) {
                    round = e["round"].as_u64().unwrap_or(0);
                    eprintln!("  round {round}: fired ratio {:.3}", e["fired_ratio"].as_f64().unwrap_or(f64::NAN));
                }
                if state == "VALIDATING" && validating.is_none() {
                    (validating, cpu_validating) = (Some(now), cpu);
                    eprintln!("  validating");
                }
            }
            _ => break job,
        }
        if now > deadline {
            let _ = post_or_get(server.http, "POST", &format!("/v1/jobs/{id}/cancel"), b"");
            bail!(
                "job {id} still {state} after {} s: lower --adapt-count or --adapt-max-rounds, or raise --adapt-timeout-s",
                args.adapt_timeout_s
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let records = clients.map(Clients::stop);
    loads.push(("job_end", load_average()));
    let state = job["state"].as_str().unwrap_or("").to_owned();
    eprintln!("  job {id} ended {state}: {}", job["reason"].as_str().unwrap_or(""));
    let idle_after = (!args.skip_adaptation).then(|| measure_idle("after"));
    loads.push(("idle_after_end", load_average()));
    let (Some(from), Some(to)) = (running, active_until) else {
        bail!("job {id} was never seen RUNNING; it ended {state}: {}", job["reason"]);
    };
    let split = validating.unwrap_or(to);
    let job_report = job_json(&job, &overrides, (split - from).as_secs_f64(), (to - split).as_secs_f64());

    let adaptation = match (&idle_before, &idle_after, &records) {
        (Some((before, before_cpu)), Some((after, after_cpu)), Some(records)) => {
            // Idle before and after the job, pooled: other load on the machine drifts.
            let idle = Level {
                concurrency: n,
                requests: before.requests + after.requests,
                errors: before.errors + after.errors,
                seconds: before.seconds + after.seconds,
                latencies_ms: [before.latencies_ms.as_slice(), &after.latencies_ms].concat(),
            };
            let during = window(records, from, to, n);
            let phase_running = window(records, from, split, n);
            let phase_validating = validating.map(|v| window(records, v, to, n));
            let during_cpu = others_cores(cpu_running, cpu_until);
            let running_cpu = others_cores(cpu_running, cpu_validating.or(cpu_until));
            let validating_cpu = others_cores(cpu_validating, cpu_until);
            let idle_cpu = before_cpu
                .zip(*after_cpu)
                .map(|(b, a)| (b * before.seconds + a * after.seconds) / (before.seconds + after.seconds));
            eprintln!(
                "  during adaptation: {}; other processes {:.2} cores",
                summary(&during),
                during_cpu.unwrap_or(f64::NAN)
            );
            eprintln!("  idle, before and after: {}", summary(&idle));
            json!({
                "server": { "max_batch": args.max_batch, "max_delay_ms": args.max_delay_ms, "flags": flags.join(" ") },
                "clients": n,
                "idle_seconds": args.adapt_idle_seconds,
                "targets": {
                    "folder": folder.display().to_string(),
                    "sent": targets.len(),
                    "statuses": statuses,
                    "not_accepted": rejections,
                    "upload_seconds": upload_seconds,
                },
                "idle": window_json(&idle, idle_cpu),
                "idle_before": window_json(before, *before_cpu),
                "idle_after": window_json(after, *after_cpu),
                "during_adaptation": window_json(&during, during_cpu),
                "phases": {
                    "running": window_json(&phase_running, running_cpu),
                    "validating": phase_validating.as_ref().map(|l| window_json(l, validating_cpu)),
                },
                "p50_ratio": during.percentile(0.5) / idle.percentile(0.5),
                "p99_ratio": during.percentile(0.99) / idle.percentile(0.99),
                "p99_ratio_vs_idle_before": during.percentile(0.99) / before.percentile(0.99),
                "p99_ratio_vs_idle_after": during.percentile(0.99) / after.percentile(0.99),
                "throughput_ratio": during.throughput() / idle.throughput(),
                "load_average": loads.iter().map(|(k, v)| (k.to_string(), json!(v))).collect::<serde_json::Map<_, _>>(),
                "errors_during_job": records.iter().filter(|r| r.overlaps(from, to) && r.answer.is_err()).count(),
                "job": job_report,
            })
        }
        _ => Value::Null,
    };

    if args.skip_swap {
        return Ok((adaptation, Value::Null));
    }
    let candidate = job["version"].as_str().unwrap_or("").to_owned();
    if !matches!(state.as_str(), "ACTIVATED" | "REJECTED") || candidate.is_empty() {
        let error = format!("job {id} ended {state} without a version to swap to: {}", job["reason"]);
        eprintln!("  no swap measured: {error}");
        return Ok((adaptation, json!({ "error": error, "server_log": server_log_json(&server.log()) })));
    }
    let explicit = state != "ACTIVATED";
    let active = server.get_json("/v1/models/car")?["version"].as_str().unwrap_or("").to_owned();
    let expected = if explicit { &source } else { &candidate };
    ensure!(active == *expected, "after job {id} ended {state}, {active} is active (expected {expected})");
    let round_trips = || {
        (0..args.swap_rounds).flat_map(|_| {
            [
                SwapAction { rollback: true, target: source.clone() },
                SwapAction { rollback: false, target: candidate.clone() },
            ]
        })
    };
    let plan: Vec<SwapAction> = explicit
        .then(|| SwapAction { rollback: false, target: candidate.clone() })
        .into_iter()
        .chain(round_trips())
        .collect();
    eprintln!("  {} swaps between {source} and {candidate} with {n} clients", plan.len());
    let clients = Clients::start(server.http, &images, n);
    std::thread::sleep(Duration::from_secs(1));
    let times = plan.iter().map(|a| swap_with_clients(&server, &clients, a)).collect::<Result<Vec<_>>>()?;
    let records = clients.stop();
    let loaded: Vec<SwapSample> = times.iter().map(|t| t.measure(&records)).collect();
    let loaded_errors = records.iter().filter(|r| r.answer.is_err()).count();
    let mut first_errors: Vec<&str> =
        records.iter().filter_map(|r| r.answer.as_ref().err()).map(String::as_str).collect();
    first_errors.truncate(5);
    let plan_idle: Vec<SwapAction> = round_trips().collect();
    eprintln!("  {} swaps with no clients", plan_idle.len());
    let quiet = plan_idle.iter().map(|a| swap_idle(&server, &images[0], a)).collect::<Result<Vec<_>>>()?;
    let quiet_errors: usize = quiet.iter().map(|s| s.errors).sum();
    let latencies = |s: &[SwapSample]| s.iter().map(|s| s.latency_ms).filter(|l| l.is_finite()).collect::<Vec<_>>();
    let (loaded_ms, quiet_ms) = (latencies(&loaded), latencies(&quiet));
    let max_request = loaded.iter().map(|s| s.max_request_ms).fold(0.0, f64::max);
    eprintln!(
        "  swap latency with {n} clients: min {:.0} / median {:.0} / max {:.0} ms, largest request {max_request:.0} ms, \
         {loaded_errors} errors; with none: median {:.0} ms, {quiet_errors} errors",
        percentile(&loaded_ms, 0.0),
        median(&loaded_ms),
        percentile(&loaded_ms, 1.0),
        median(&quiet_ms)
    );
    let swap = json!({
        "from_version": source,
        "to_version": candidate,
        "explicit_activation": explicit,
        "clients": n,
        "latency_ms": min_median_max(&loaded_ms),
        "samples": loaded.len(),
        "errors": loaded_errors + quiet_errors,
        "max_request_ms_during_swap": max_request,
        "stale_answers_after_response": loaded.iter().map(|s| s.stale).sum::<usize>(),
        "first_errors": first_errors,
        "with_clients": {
            "errors": loaded_errors,
            "requests": records.len(),
            "settle_ms": SETTLE.as_secs_f64() * 1e3,
            "per_swap": loaded.iter().map(SwapSample::json).collect::<Vec<_>>(),
        },
        "no_clients": {
            "latency_ms": min_median_max(&quiet_ms),
            "samples": quiet.len(),
            "errors": quiet_errors,
            "steady_request_ms": median(&quiet.iter().filter_map(|s| s.steady_ms).collect::<Vec<_>>()),
            "per_swap": quiet.iter().map(SwapSample::json).collect::<Vec<_>>(),
        },
        "server_log": server_log_json(&server.log()),
        "job": if adaptation.is_null() { job_report } else { json!(id) },
    });
    Ok((adaptation, swap))
}

pub(crate) fn fmt_ms(v: &Value) -> String {
    v.as_f64().map_or_else(|| "–".into(), |x| format!("{x:.0}"))
}

/// The Markdown section of the report's `adaptation` (empty when skipped).
fn adaptation_markdown(report: &Value) -> String {
    let a = &report["adaptation"];
    if a.is_null() {
        return String::new();
    }
    let j = &a["job"];
    let t = &a["targets"];
    let row = |name: &str, l: &Value| {
        if l.is_null() {
            return String::new();
        }
        format!(
            "| {name} | {:.1} | {} | {} | {:.2} | {} | {} | {} | {} |\n",
            l["seconds"].as_f64().unwrap_or(f64::NAN),
            l["requests"],
            l["errors"],
            l["throughput_per_s"].as_f64().unwrap_or(f64::NAN),
            fmt_ms(&l["p50_ms"]),
            fmt_ms(&l["p99_ms"]),
            fmt_ms(&l["max_ms"]),
            l["other_processes_cores"].as_f64().map_or_else(|| "–".into(), |c| format!("{c:.2}")),
        )
    };
    let statuses = t["statuses"]
        .as_object()
        .map(|m| m.iter().map(|(k, v)| format!("{v} {k}")).collect::<Vec<_>>().join(", "))
        .unwrap_or_default();
    let overrides = match j["overrides"].as_object().filter(|o| !o.is_empty()) {
        Some(o) => format!(" (overrides `{}`)", Value::Object(o.clone())),
        None => String::new(),
    };
    format!(
        "\n## Latency during adaptation\n\n`{}`\n\nA third server, batching on (`--max-batch {}`, {} ms) with `{}` so \
         that no job starts by itself. {} clients send estimates back to back (the crops above, one connection per \
         request): after {} s of warm-up, for {} s with the server idle; then {} target images from `{}` are uploaded ({statuses}; \
         {:.1} s), a job is started through `POST /v1/adapt/car/jobs`, and the same clients run until it ends; then \
         again idle for as long. Only requests that start and finish while the polled job state (every 100 ms) is \
         RUNNING or VALIDATING count as during adaptation; the idle baseline pools the windows before and after the \
         job, since other load on the machine drifts. The machine has {} threads: the job's pseudo-labelling and \
         training compete with inference for the same cores, which is what this measures; *other processes* is the \
         CPU that processes other than this benchmark and its server took during each window (from `/proc`), so a \
         window with a large value was disturbed from outside (load average: {}).\n\n\
         | phase | seconds | requests | errors | req/s | p50 (ms) | p99 (ms) | max (ms) | other processes (cores) |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|\n{}{}{}{}{}{}\n\
         **p99 during adaptation / idle: {:.2}×** (against the idle window before the job alone {:.2}×, after it \
         {:.2}×; p50 {:.2}×, throughput {:.2}×); {} requests failed while the job ran.\n\n\
         Job `{}`: {} rounds of at most {}{overrides} on {} images, {} held out for the gate; {:.1} s from creation to \
         {} ({:.1} s seen RUNNING, {:.1} s VALIDATING); last fired ratio {:.3}. Outcome: {}.\n",
        report["command"].as_str().unwrap_or(""),
        a["server"]["max_batch"],
        a["server"]["max_delay_ms"],
        a["server"]["flags"].as_str().unwrap_or(""),
        a["clients"],
        WARM_UP.as_secs(),
        a["idle_seconds"],
        t["sent"],
        t["folder"].as_str().unwrap_or(""),
        t["upload_seconds"].as_f64().unwrap_or(f64::NAN),
        report["machine"]["threads"],
        ["idle_before_start", "idle_before_end", "job_start", "job_end", "idle_after_end"]
            .iter()
            .filter_map(|k| a["load_average"][k].as_str().map(|v| format!("{v} at {}", k.replace('_', " "))))
            .collect::<Vec<_>>()
            .join(", "),
        row("idle (before + after the job)", &a["idle"]),
        row("— idle before", &a["idle_before"]),
        row("— idle after", &a["idle_after"]),
        row("**during adaptation** (RUNNING + VALIDATING)", &a["during_adaptation"]),
        row("— RUNNING (adapting)", &a["phases"]["running"]),
        row("— VALIDATING (gate)", &a["phases"]["validating"]),
        a["p99_ratio"].as_f64().unwrap_or(f64::NAN),
        a["p99_ratio_vs_idle_before"].as_f64().unwrap_or(f64::NAN),
        a["p99_ratio_vs_idle_after"].as_f64().unwrap_or(f64::NAN),
        a["p50_ratio"].as_f64().unwrap_or(f64::NAN),
        a["throughput_ratio"].as_f64().unwrap_or(f64::NAN),
        a["errors_during_job"],
        j["id"].as_str().unwrap_or(""),
        j["rounds"],
        j["max_rounds"],
        j["images_used"],
        j["images_held_out"],
        j["seconds"].as_f64().unwrap_or(f64::NAN),
        j["state"].as_str().unwrap_or(""),
        j["running_seconds"].as_f64().unwrap_or(f64::NAN),
        j["validating_seconds"].as_f64().unwrap_or(f64::NAN),
        j["fired_ratio"].as_f64().unwrap_or(f64::NAN),
        j["reason"].as_str().unwrap_or(""),
    )
}

/// The Markdown section of the report's `swap` (empty when skipped).
fn swap_markdown(report: &Value) -> String {
    let s = &report["swap"];
    if s.is_null() {
        return String::new();
    }
    if let Some(error) = s["error"].as_str() {
        return format!("\n## Model swap\n\nNot measured: {error}.\n");
    }
    let (w, q, log) = (&s["with_clients"], &s["no_clients"], &s["server_log"]);
    let loads = &log["model_loads_after_start_ms"];
    let explicit = if s["explicit_activation"].as_bool() == Some(true) {
        "The gate rejected the job's version, so the first swap activates it explicitly \
         (`POST /v1/models/car/activate`); then "
            .to_string()
    } else {
        "The job activated its version itself; then ".to_string()
    };
    let problems = log["first_warnings_and_errors"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_str).map(|l| format!("\n    {l}")).collect::<String>())
        .unwrap_or_default();
    format!(
        "\n## Model swap\n\n`{}`\n\nOn the same server, after the job: swaps between the seed `{}` and the job's \
         version `{}`. {explicit}{} rollback (`POST /v1/models/car/rollback`) / activate round trips with {} clients \
         sending estimates back to back, {} ms apart after each swap's first new answer, and the same round trips with \
         no clients. **Swap latency**: from the activation call's HTTP response to the first estimate answered by the \
         new version (`model_version`); with no clients, the answer to the first request sent after the response \
         (the worker loads the new version on its thread when a batch arrives, so that request waits for the load).\n\n\
         | clients | swaps | min (ms) | median (ms) | max (ms) | failed requests | largest request latency around a swap (ms) |\n\
         |---|---:|---:|---:|---:|---:|---:|\n\
         | {} | {} | {} | {} | {} | {} | {} |\n\
         | none | {} | {} | {} | {} | {} | {} |\n\n\
         With no clients, the requests right after the first one take {} ms (median), so the load adds about \
         {:.0} ms. Around a swap with clients: the largest latency of a request in flight between the call and the \
         first new answer; {} answers came from the old version to requests sent after the call's response. The \
         server logged {} model loads after its start (the job's activation and the swaps): {} / {} / {} ms \
         (min / median / max), and {} warnings or errors.{}\n",
        report["command"].as_str().unwrap_or(""),
        s["from_version"].as_str().unwrap_or(""),
        s["to_version"].as_str().unwrap_or(""),
        report["swap"]["no_clients"]["samples"].as_u64().unwrap_or(0) / 2,
        s["clients"],
        fmt_ms(&w["settle_ms"]),
        s["clients"],
        s["samples"],
        fmt_ms(&s["latency_ms"]["min"]),
        fmt_ms(&s["latency_ms"]["median"]),
        fmt_ms(&s["latency_ms"]["max"]),
        w["errors"],
        fmt_ms(&s["max_request_ms_during_swap"]),
        q["samples"],
        fmt_ms(&q["latency_ms"]["min"]),
        fmt_ms(&q["latency_ms"]["median"]),
        fmt_ms(&q["latency_ms"]["max"]),
        q["errors"],
        fmt_ms(&q["latency_ms"]["max"]),
        fmt_ms(&q["steady_request_ms"]),
        q["latency_ms"]["median"].as_f64().unwrap_or(f64::NAN) - q["steady_request_ms"].as_f64().unwrap_or(f64::NAN),
        s["stale_answers_after_response"],
        loads["samples"],
        fmt_ms(&loads["min"]),
        fmt_ms(&loads["median"]),
        fmt_ms(&loads["max"]),
        log["warnings_and_errors"],
        if problems.is_empty() { String::new() } else { format!(" The first:\n{problems}") },
    )
}

struct Ceiling {
    /// Backbone crops per second, one at a time.
    batch1: f64,
    /// Backbone crops per second in batches of `max_batch`.
    batched: f64,
    /// Backbone + solver images per second, one after the other.
    engine: f64,
}

/// The backbone (and the engine) alone on the same crops, on this process's CPU or GPU.
fn backbone_ceiling(model_dir: &Path, images: &[Vec<u8>], max_batch: usize) -> Result<Ceiling> {
    let device = udapose_engine::runtime::RuntimeInfo::detect().device();
    let estimator = Estimator::new(checkpoint::load(model_dir, device)?, SolverConfig::default())?;
    let size = estimator.model.manifest.crop;
    let crops: Vec<Crop> = images
        .iter()
        .map(|bytes| -> Result<Crop> {
            let img = image::load_from_memory(bytes)?.into_rgb8();
            let (w, h) = (img.width() as usize, img.height() as usize);
            Ok(input::crop(&Rgb8Image::new(img.as_raw(), w, h)?, None, size)?)
        })
        .collect::<Result<_>>()?;
    let run = |batch: &[&Crop]| {
        let tensors: Vec<Tensor> = batch.iter().map(|c| c.tensor()).collect();
        estimator.batch_features(&Tensor::cat(&tensors, 0))
    };
    run(&[&crops[0]])?; // warm-up
    let rounds = 3;
    let t = Instant::now();
    for _ in 0..rounds {
        for c in &crops {
            run(&[c])?;
        }
    }
    let batch1 = (rounds * crops.len()) as f64 / t.elapsed().as_secs_f64();
    let batch: Vec<&Crop> = crops.iter().cycle().take(max_batch).collect();
    run(&batch)?;
    let t = Instant::now();
    let batches = (rounds * crops.len()).div_ceil(max_batch);
    for _ in 0..batches {
        run(&batch)?;
    }
    let batched = (batches * max_batch) as f64 / t.elapsed().as_secs_f64();
    estimator.estimate(&crops[0])?; // warm-up (the solver's thread pool and buffers)
    let t = Instant::now();
    for _ in 0..rounds {
        crops.iter().try_for_each(|c| estimator.estimate(c).map(drop))?;
    }
    let engine = (rounds * crops.len()) as f64 / t.elapsed().as_secs_f64();
    Ok(Ceiling { batch1, batched, engine })
}

pub(crate) fn load_average() -> String {
    fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}
