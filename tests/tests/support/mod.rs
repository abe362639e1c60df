//! Starts the real `udapose-server` binary for a test and stops it on drop; a minimal HTTP/1.1
//! client; the quick SynCar-OOD images with their ground truth; pose error.
#![allow(dead_code)] // each test binary uses a different part

pub mod jobs;

use std::{
    fs::{self, File},
    io::Read,
    net::SocketAddr,
    path::{Path, PathBuf},
    process::{Child, Command, ExitStatus, Stdio},
    thread,
    time::{Duration, Instant},
};

/// How long a server may take to answer `/healthz` (or `/readyz`) after spawning.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(60);

/// A running `udapose-server` with its own models directory, store and log file.
pub struct Server {
    child: Child,
    /// How to spawn it again (a restart after a crash keeps the same ports, models and store).
    command: Vec<String>,
    dir: PathBuf,
    pub http_addr: SocketAddr,
    pub grpc_addr: SocketAddr,
    tls: bool,
    /// Environment of every start (e.g. store credentials).
    env: Vec<(String, String)>,
}

/// How to start a server.
pub struct ServerConfig {
    name: String,
    /// The model served as category `car`, if any.
    model: Option<PathBuf>,
    /// More categories served with a copy of that model.
    also_as: Vec<String>,
    args: Vec<String>,
    tls: bool,
    store: Option<String>,
    env: Vec<(String, String)>,
    wait_ready: bool,
}

impl ServerConfig {
    /// Uses this `--store` instead of the server's own directory.
    pub fn store(mut self, url: &str) -> Self {
        self.store = Some(url.into());
        self
    }

    pub fn env(mut self, key: &str, value: &str) -> Self {
        self.env.push((key.into(), value.into()));
        self
    }

    /// Returns once `/healthz` answers, without waiting for `/readyz`.
    pub fn no_wait_ready(mut self) -> Self {
        self.wait_ready = false;
        self
    }

    /// Serves the quick model (`UDAPOSE_QUICK_MODEL`) as category `car`.
    pub fn quick_model(mut self) -> Self {
        self.model = Some(env_path("UDAPOSE_QUICK_MODEL"));
        self
    }

    /// Serves the shipped car model (`models/car` of the repository) as category `car`: fixed
    /// weights, where a check's margin measured on it holds on every machine.
    pub fn shipped_model(mut self) -> Self {
        self.model = Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/car"));
        self
    }

    /// Also serves a copy of the model as `category` (its manifest says so), beside car.
    pub fn also_as(mut self, category: &str) -> Self {
        self.also_as.push(category.into());
        self
    }

    /// Serves TLS with these PEM files (readiness is then polled with `curl -k`).
    pub fn tls(mut self, cert: &Path, key: &Path) -> Self {
        self.tls = true;
        self.arg("--tls-cert").arg(cert.display().to_string()).arg("--tls-key").arg(key.display().to_string())
    }

    pub fn args<const N: usize>(mut self, args: [&str; N]) -> Self {
        self.args.extend(args.map(String::from));
        self
    }

    pub fn arg(mut self, arg: impl Into<String>) -> Self {
        self.args.push(arg.into());
        self
    }

    /// Spawns the server on free loopback ports and waits until `/healthz` answers (and, with
    /// a model, until `/readyz` does).
    pub fn start(self) -> Server {
        let binary = server_binary(); // before creating anything to clean up
        let dir = scratch_dir(&self.name);
        let models = dir.join("models");
        fs::create_dir_all(&models).expect("creating the models directory");
        if let Some(model) = &self.model {
            for category in std::iter::once("car").chain(self.also_as.iter().map(String::as_str)) {
                let dir = models.join(category);
                fs::create_dir(&dir).unwrap();
                for f in fs::read_dir(model).expect("reading the model to serve").map(|e| e.unwrap().path()) {
                    fs::copy(&f, dir.join(f.file_name().unwrap())).unwrap();
                }
                let manifest = dir.join("manifest.json");
                let mut m: serde_json::Value = serde_json::from_slice(&fs::read(&manifest).unwrap()).unwrap();
                m["category"] = category.into();
                fs::write(&manifest, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
            }
        }
        let [http_addr, grpc_addr] = free_addrs();
        let mut command: Vec<String> = vec![binary.display().to_string()];
        for (flag, value) in [
            ("--http-addr", http_addr.to_string()),
            ("--grpc-addr", grpc_addr.to_string()),
            ("--models", models.display().to_string()),
            ("--store", self.store.unwrap_or_else(|| dir.join("state").display().to_string())),
        ] {
            command.extend([flag.to_string(), value]);
        }
        command.extend(self.args);
        let env = self.env;
        let child = spawn(&command, &dir, &pairs(&env));
        let mut server = Server { child, command, dir, http_addr, grpc_addr, tls: self.tls, env };
        server.wait_for("/healthz");
        if self.model.is_some() && self.wait_ready {
            server.wait_for("/readyz");
        }
        server
    }
}

fn pairs(env: &[(String, String)]) -> Vec<(&str, &str)> {
    env.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect()
}

/// Spawns the server command, appending to `dir/server.log`.
fn spawn(command: &[String], dir: &Path, env: &[(&str, &str)]) -> Child {
    let log = fs::OpenOptions::new().create(true).append(true).open(dir.join("server.log")).expect("opening the log");
    Command::new(&command[0])
        .args(&command[1..])
        .env("RUST_LOG", "info")
        .env_remove("UDAPOSE_TOKEN")
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(log.try_clone().expect("cloning the log handle"))
        .stderr(log)
        .spawn()
        .expect("spawning udapose-server")
}

impl Server {
    pub fn config(name: &str) -> ServerConfig {
        ServerConfig {
            name: name.into(),
            model: None,
            also_as: Vec::new(),
            args: Vec::new(),
            tls: false,
            store: None,
            env: Vec::new(),
            wait_ready: true,
        }
    }

    /// A server with an empty models directory.
    pub fn start(name: &str) -> Server {
        Server::config(name).start()
    }

    /// `kill -9`, then the same command again (with `env` added) on the same store; waits for
    /// `/readyz`.
    pub fn crash_and_restart(&mut self, env: &[(&str, &str)]) {
        self.kill9();
        self.child = spawn(&self.command, &self.dir, &[pairs(&self.env), env.to_vec()].concat());
        self.wait_for("/healthz");
        self.wait_for("/readyz");
    }

    /// Like [`Server::crash_and_restart`], but only starts the new process (for failpoints).
    pub fn crash_and_spawn(&mut self, env: &[(&str, &str)]) {
        self.crash_and_spawn_after(Duration::ZERO, env);
    }

    /// [`Server::crash_and_spawn`] with `pause` between the two, no server listening.
    pub fn crash_and_spawn_after(&mut self, pause: Duration, env: &[(&str, &str)]) {
        self.kill9();
        std::thread::sleep(pause);
        self.child = spawn(&self.command, &self.dir, &[pairs(&self.env), env.to_vec()].concat());
        self.wait_for("/healthz");
    }

    /// `kill -9` (SIGKILL: no cleanup of any kind), and reaps the process.
    pub fn kill9(&mut self) {
        self.child.kill().expect("kill -9");
        self.child.wait().expect("reaping the killed server");
    }

    /// Sends `signal` (e.g. "CONT") to the process.
    pub fn signal(&self, signal: &str) {
        let status = Command::new("kill").arg(format!("-{signal}")).arg(self.child.id().to_string()).status();
        assert!(status.is_ok_and(|s| s.success()), "kill -{signal} failed");
    }

    /// Whether the process is stopped (SIGSTOP), from /proc.
    pub fn stopped(&self) -> bool {
        fs::read_to_string(format!("/proc/{}/stat", self.child.id()))
            .is_ok_and(|stat| stat.rsplit(')').next().is_some_and(|rest| rest.trim_start().starts_with('T')))
    }

    /// A memory figure of the process from /proc (`VmRSS`, `VmHWM`: its peak), in KiB.
    pub fn memory_kib(&self, field: &str) -> u64 {
        let status = fs::read_to_string(format!("/proc/{}/status", self.child.id())).expect("reading /proc");
        let line = status.lines().find(|l| l.starts_with(&format!("{field}:"))).expect("no such field");
        line.split_whitespace().nth(1).and_then(|v| v.parse().ok()).expect("a number of kB")
    }

    /// The server's `--store` directory.
    pub fn store_dir(&self) -> PathBuf {
        self.dir.join("state")
    }

    /// `http://host:port` of the gRPC listener.
    pub fn grpc_endpoint(&self) -> String {
        format!("http://{}", self.grpc_addr)
    }

    /// GETs `path` from the HTTP listener; returns (status code, body).
    pub fn get(&self, path: &str) -> (u16, String) {
        let r = self.request("GET", path, &[], b"");
        (r.status, r.body)
    }

    /// Any request to the HTTP listener.
    pub fn request(&self, method: &str, path: &str, headers: &[(&str, &str)], body: &[u8]) -> HttpResponse {
        http_request(self.http_addr, method, path, headers, body)
            .unwrap_or_else(|e| panic!("{method} {path}: {e}\n{}", self.log()))
    }

    /// Sends SIGTERM and waits (bounded) for the process to exit.
    #[cfg(unix)]
    pub fn terminate(&mut self) -> ExitStatus {
        let pid = self.child.id().to_string();
        let sent = Command::new("kill").args(["-TERM", &pid]).status().expect("running kill");
        assert!(sent.success(), "kill -TERM {pid} failed");
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(status) = self.child.try_wait().expect("waiting for the server") {
                return status;
            }
            assert!(Instant::now() < deadline, "server ignored SIGTERM\n{}", self.log());
            thread::sleep(Duration::from_millis(50));
        }
    }

    /// Everything the server has logged so far (for failure messages).
    pub fn log(&self) -> String {
        let log = fs::read_to_string(self.dir.join("server.log")).unwrap_or_default();
        format!("--- udapose-server log ---\n{log}")
    }

    fn wait_for(&mut self, path: &str) {
        let deadline = Instant::now() + STARTUP_TIMEOUT;
        loop {
            if self.answers_200(path) {
                return;
            }
            if let Some(status) = self.child.try_wait().expect("polling the server") {
                panic!("udapose-server exited during startup ({status})\n{}", self.log());
            }
            if Instant::now() >= deadline {
                panic!("udapose-server: {path} not 200 after {STARTUP_TIMEOUT:?}\n{}", self.log());
            }
            thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Server {
    fn answers_200(&self, path: &str) -> bool {
        if !self.tls {
            return matches!(http_request(self.http_addr, "GET", path, &[], b""), Ok(HttpResponse { status: 200, .. }));
        }
        let url = format!("https://{}{path}", self.http_addr);
        let out = Command::new("curl").args(["-sk", "-o", "/dev/null", "-w", "%{http_code}", &url]).output();
        out.is_ok_and(|o| o.stdout == b"200")
    }
}

impl Drop for Server {
    /// Runs on test failure too, so no server outlives its test.
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = fs::remove_dir_all(&self.dir);
    }
}

pub fn env_path(var: &str) -> PathBuf {
    PathBuf::from(std::env::var_os(var).unwrap_or_else(|| panic!("{var} is set by `make test`")))
}

/// The `udapose-server` next to this test executable (`target/<profile>/`),
/// or `$UDAPOSE_SERVER_BIN`.
fn server_binary() -> PathBuf {
    let server =
        std::env::var_os("UDAPOSE_SERVER_BIN").map(PathBuf::from).unwrap_or_else(|| beside_tests("udapose-server"));
    assert!(
        server.is_file(),
        "{} not found: build it first with `cargo build --release --workspace` \
         (same profile and target dir as the tests), or set UDAPOSE_SERVER_BIN",
        server.display()
    );
    server
}

/// A workspace binary of this build (test executables live in target/<profile>/deps/).
pub fn beside_tests(name: &str) -> PathBuf {
    udapose_harness::workspace_binary(name).expect("locating the workspace's binaries")
}

/// Distinct loopback addresses whose ports were free a moment ago.
pub fn free_addrs<const N: usize>() -> [SocketAddr; N] {
    let addrs = udapose_harness::free_addrs(N).expect("binding free ports");
    std::array::from_fn(|i| addrs[i])
}

pub fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-e2e-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    dir
}

pub use udapose_harness::{HttpResponse, http_request};

/// One quick SynCar-OOD test image with its ground-truth angles.
pub struct QuickImage {
    pub path: PathBuf,
    pub bytes: Vec<u8>,
    /// `[azimuth, elevation, theta]`, radians.
    pub truth: [f64; 3],
}

/// The first `n` images of the quick dataset's `domain/test` split.
pub fn quick_images(domain: &str, n: usize) -> Vec<QuickImage> {
    let root = env_path("UDAPOSE_QUICK_DATA").join(domain).join("test");
    // The split's list order, which `udapose-lab eval --limit` follows too.
    let list = fs::read_to_string(root.join("lists/car/list.txt")).expect("the quick split's list");
    list.lines()
        .map(str::trim)
        .filter(|n| !n.is_empty())
        .map(str::to_owned)
        .take(n)
        .map(|name| {
            let path = root.join("images/car").join(&name);
            let npz = root.join("annotations/car").join(name.replace(".png", ".npz"));
            let truth = ["azimuth", "elevation", "theta"].map(|k| npz_scalar(&npz, k));
            QuickImage { bytes: fs::read(&path).unwrap(), path, truth }
        })
        .collect()
}

/// A scalar `f8` member of an `.npz`: the last 8 bytes of `<key>.npy`.
fn npz_scalar(path: &Path, key: &str) -> f64 {
    let mut zip = zip::ZipArchive::new(File::open(path).unwrap()).unwrap();
    let mut member = zip.by_name(&format!("{key}.npy")).unwrap();
    let mut bytes = Vec::new();
    member.read_to_end(&mut bytes).unwrap();
    f64::from_le_bytes(bytes[bytes.len() - 8..].try_into().unwrap())
}

/// `R(a, e, θ) = Rz(θ)·Rx(−(π/2 − e))·Rz(−a)` (METHOD.md §2), row-major.
pub fn rotation([a, e, t]: [f64; 3]) -> [[f64; 3]; 3] {
    let rz = |x: f64| [[x.cos(), -x.sin(), 0.0], [x.sin(), x.cos(), 0.0], [0.0, 0.0, 1.0]];
    let rx = |x: f64| [[1.0, 0.0, 0.0], [0.0, x.cos(), -x.sin()], [0.0, x.sin(), x.cos()]];
    mul(mul(rz(t), rx(-(std::f64::consts::FRAC_PI_2 - e))), rz(-a))
}

fn mul(a: [[f64; 3]; 3], b: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// Geodesic angle between two rotations, radians.
pub fn geodesic(a: [[f64; 3]; 3], b: [[f64; 3]; 3]) -> f64 {
    let at: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| a[j][i]));
    let q = mul(at, b);
    let w = [(q[2][1] - q[1][2]) / 2.0, (q[0][2] - q[2][0]) / 2.0, (q[1][0] - q[0][1]) / 2.0];
    let norm = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    norm.atan2((q[0][0] + q[1][1] + q[2][2] - 1.0) / 2.0)
}

/// The value of the Prometheus line `name` (labels included) in a `/metrics` text.
pub fn metric(metrics: &str, name: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("{name} missing:\n{metrics}"))
        .trim()
        .parse()
        .unwrap()
}
