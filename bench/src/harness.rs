//! What the benchmarks share: a `udapose-server` process on loopback and plain HTTP requests to
//! it (the end-to-end tests' client, from `udapose-harness`), the records of background
//! clients' estimates and their statistics, CPU time from `/proc`, and the run's provenance
//! (commit, machine, load average).

use std::{
    fs,
    net::SocketAddr,
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail, ensure};
use serde_json::{Value, json};

pub(crate) use udapose_lab::machine;

/// The commit the benches are built from (lab's build script records it), for reports.
pub(crate) fn git_commit() -> String {
    udapose_lab::BUILD_COMMIT.to_string()
}

/// This process's command line as a shell takes it back (an argument with spaces or quotes in
/// single quotes), for reports: a `--note` is one argument again when the line is pasted.
pub(crate) fn command_line() -> String {
    std::env::args().map(|a| shell_quoted(&a)).collect::<Vec<_>>().join(" ")
}

pub(crate) fn shell_quoted(arg: &str) -> String {
    let plain = |c: char| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c);
    if !arg.is_empty() && arg.chars().all(plain) { arg.to_owned() } else { format!("'{}'", arg.replace('\'', "'\\''")) }
}

/// The 1, 5 and 15 minute load averages (`/proc/loadavg`), for reports.
pub(crate) fn load_average() -> String {
    fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

/// The server binary: `server` (`--server`), else `udapose-server` next to this one.
pub(crate) fn server_binary(server: Option<&Path>) -> Result<PathBuf> {
    let binary = match server {
        Some(p) => p.to_path_buf(),
        None => udapose_harness::workspace_binary("udapose-server")?,
    };
    ensure!(binary.is_file(), "{} not found: build the workspace first", binary.display());
    Ok(binary)
}

/// `n` free loopback addresses (bound, then released).
pub(crate) fn free_addrs(n: usize) -> Result<Vec<SocketAddr>> {
    Ok(udapose_harness::free_addrs(n)?)
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

/// The log filter of a server whose log a bench reads: its model loads and swaps are logged by
/// the service library (`udapose_service`), its start by the binary. (With the binary's alone,
/// as before the library split, the swap and load lines were filtered out and the reports said
/// "0 model loads".)
pub(crate) const SERVER_LOG: &str = "warn,udapose_server=info,udapose_service=info";

/// A `udapose-server` on free loopback ports with a scratch models dir and store.
pub(crate) struct ServerProcess {
    pub(crate) child: Child,
    dir: PathBuf,
    pub(crate) http: SocketAddr,
}

impl ServerProcess {
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

    /// A server on `model` (served as `car`) on free loopback ports, in a scratch directory
    /// `udapose-bench-<name>-<pid>`, with `flags`; with `verbose`, its own crate logs at `info`
    /// so that [`ServerProcess::log`] shows model loads and job events. Returns it and its gRPC
    /// address.
    pub(crate) fn serve_model(
        binary: &Path,
        model: &Path,
        name: &str,
        flags: &[&str],
        verbose: bool,
    ) -> Result<(Self, SocketAddr)> {
        Self::serve_models(binary, &[("car", model)], name, flags, verbose)
    }

    /// As [`ServerProcess::serve_model`], with each `(category, model)` served side by side.
    pub(crate) fn serve_models(
        binary: &Path,
        models: &[(&str, &Path)],
        name: &str,
        flags: &[&str],
        verbose: bool,
    ) -> Result<(Self, SocketAddr)> {
        let dir = std::env::temp_dir().join(format!("udapose-bench-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(dir.join("models"))?;
        for (category, model) in models {
            // A relative target would resolve inside `dir/models`, not where the caller meant.
            let model = fs::canonicalize(model).with_context(|| format!("model {}", model.display()))?;
            std::os::unix::fs::symlink(&model, dir.join("models").join(category))?;
        }
        let [http, grpc] = free_addrs(2)?[..] else { unreachable!("two addresses") };
        let mut command = Command::new(binary);
        command
            .args(["--http-addr", &http.to_string(), "--grpc-addr", &grpc.to_string()])
            .arg("--models")
            .arg(dir.join("models"))
            .arg("--store")
            .arg(dir.join("state"))
            .args(flags)
            .env("RUST_LOG", if verbose { SERVER_LOG } else { "warn" });
        Ok((Self::spawn(command, dir, http)?, grpc))
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

/// HTTP/1.1 with `Connection: close`; returns (status, body).
pub(crate) fn post_or_get(addr: SocketAddr, method: &str, path: &str, body: &[u8]) -> std::io::Result<(u16, String)> {
    request(addr, method, path, &[], body)
}

/// [`post_or_get`] with extra headers (the tests' HTTP client, `udapose-harness`).
pub(crate) fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> std::io::Result<(u16, String)> {
    udapose_harness::http_request(addr, method, path, headers, body).map(|r| (r.status, r.body))
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

    pub(crate) fn answered_by(&self, version: &str) -> bool {
        matches!(&self.answer, Ok(v) if v == version)
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

pub(crate) fn fmt_ms(v: &Value) -> String {
    v.as_f64().map_or_else(|| "–".into(), |x| format!("{x:.0}"))
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
