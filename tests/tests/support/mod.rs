//! Starts the real `udapose-server` binary for a test and stops it on drop.

use std::{
    fs::{self, File},
    io::{Read, Write},
    net::{SocketAddr, TcpListener, TcpStream},
    path::{Path, PathBuf},
    process::{Child, Command, ExitStatus, Stdio},
    thread,
    time::{Duration, Instant},
};

/// How long a server may take to answer `/healthz` after spawning.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(20);

/// A running `udapose-server` with its own models directory and log file.
pub struct Server {
    child: Child,
    dir: PathBuf,
    pub http_addr: SocketAddr,
    pub grpc_addr: SocketAddr,
}

impl Server {
    /// Spawns the server on free loopback ports with an empty models
    /// directory and waits until `/healthz` answers.
    pub fn start(name: &str) -> Server {
        let binary = server_binary(); // before creating anything to clean up
        let dir = scratch_dir(name);
        let models = dir.join("models");
        fs::create_dir_all(&models).expect("creating the models directory");
        let [http_addr, grpc_addr] = free_addrs();
        let log = File::create(dir.join("server.log")).expect("creating the server log");
        let child = Command::new(binary)
            .arg("--http-addr")
            .arg(http_addr.to_string())
            .arg("--grpc-addr")
            .arg(grpc_addr.to_string())
            .arg("--models")
            .arg(&models)
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("cloning the log handle"))
            .stderr(log)
            .spawn()
            .expect("spawning udapose-server");
        let mut server = Server { child, dir, http_addr, grpc_addr };
        server.wait_healthy();
        server
    }

    /// `http://host:port` of the gRPC listener.
    pub fn grpc_endpoint(&self) -> String {
        format!("http://{}", self.grpc_addr)
    }

    /// GETs `path` from the HTTP listener; returns (status code, body).
    pub fn get(&self, path: &str) -> (u16, String) {
        http_get(self.http_addr, path).unwrap_or_else(|e| panic!("GET {path}: {e}\n{}", self.log()))
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

    fn wait_healthy(&mut self) {
        let deadline = Instant::now() + STARTUP_TIMEOUT;
        loop {
            if let Ok((200, _)) = http_get(self.http_addr, "/healthz") {
                return;
            }
            if let Some(status) = self.child.try_wait().expect("polling the server") {
                panic!("udapose-server exited during startup ({status})\n{}", self.log());
            }
            if Instant::now() >= deadline {
                panic!("udapose-server not healthy after {STARTUP_TIMEOUT:?}\n{}", self.log());
            }
            thread::sleep(Duration::from_millis(100));
        }
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

/// The `udapose-server` next to this test executable (`target/<profile>/`),
/// or `$UDAPOSE_SERVER_BIN`.
fn server_binary() -> PathBuf {
    let server = std::env::var_os("UDAPOSE_SERVER_BIN").map(PathBuf::from).unwrap_or_else(beside_tests);
    assert!(
        server.is_file(),
        "{} not found: build it first with `cargo build --release --workspace` \
         (same profile and target dir as the tests), or set UDAPOSE_SERVER_BIN",
        server.display()
    );
    server
}

/// Test executables live in target/<profile>/deps/; binaries in target/<profile>/.
fn beside_tests() -> PathBuf {
    let exe = std::env::current_exe().expect("locating the test executable");
    let profile_dir = exe.parent().and_then(Path::parent).expect("test executable has no target dir");
    profile_dir.join(format!("udapose-server{}", std::env::consts::EXE_SUFFIX))
}

/// Distinct loopback addresses whose ports were free a moment ago: bind
/// port 0 for each (all held at once, so they differ), then release them.
fn free_addrs<const N: usize>() -> [SocketAddr; N] {
    let listeners: Vec<_> = (0..N).map(|_| TcpListener::bind("127.0.0.1:0").expect("binding a free port")).collect();
    std::array::from_fn(|i| listeners[i].local_addr().expect("reading the free port"))
}

fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-e2e-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    dir
}

/// Minimal HTTP/1.1 GET with `Connection: close`, enough for JSON endpoints
/// that send a Content-Length (no chunked decoding).
fn http_get(addr: SocketAddr, path: &str) -> std::io::Result<(u16, String)> {
    let timeout = Duration::from_secs(5);
    let mut stream = TcpStream::connect_timeout(&addr, timeout)?;
    stream.set_read_timeout(Some(timeout))?;
    write!(stream, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    let invalid = || std::io::Error::new(std::io::ErrorKind::InvalidData, response.clone());
    let (head, body) = response.split_once("\r\n\r\n").ok_or_else(invalid)?;
    let code = head.split_whitespace().nth(1).and_then(|c| c.parse().ok()).ok_or_else(invalid)?;
    Ok((code, body.to_owned()))
}
