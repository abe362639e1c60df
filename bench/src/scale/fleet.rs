//! The fleet of the scale benchmark: an s3s-fs store on loopback, and `udapose-server`
//! processes of either role on it.

use std::{
    fs,
    net::{SocketAddr, TcpStream},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    time::{Duration, Instant},
};

use anyhow::{Context, Result, ensure};

use super::{BUCKET, KEY, SECRET};
use crate::harness::{ServerProcess, free_addrs};

/// An s3s-fs server on loopback with bucket [`BUCKET`]; killed (and its files removed) on drop.
pub(super) struct S3 {
    pub(super) child: Child,
    root: PathBuf,
    endpoint: String,
}

impl S3 {
    pub(super) fn start(binary: &Path, root: PathBuf, log: &Path) -> Result<S3> {
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
pub(super) struct Node {
    pub(super) name: String,
    pub(super) grpc: SocketAddr,
    pub(super) server: ServerProcess,
    /// Seconds from its start to `/readyz` answering 200.
    pub(super) ready_s: f64,
}

impl Node {
    pub(super) fn pid(&self) -> String {
        self.server.child.id().to_string()
    }

    pub(super) fn http(&self) -> SocketAddr {
        self.server.http
    }

    /// `kill -9`, and the process reaped.
    pub(super) fn kill9(&mut self) -> Result<()> {
        self.server.child.kill().with_context(|| format!("killing {}", self.name))?;
        self.server.child.wait()?;
        Ok(())
    }
}

/// What every process of the fleet shares: the binary, the seed models, the store.
pub(super) struct Fleet {
    pub(super) binary: PathBuf,
    pub(super) scratch: PathBuf,
    pub(super) s3: S3,
    pub(super) poll: u64,
    pub(super) max_batch: usize,
    pub(super) torch_threads: u32,
}

impl Fleet {
    pub(super) fn store_url() -> String {
        format!("s3://{BUCKET}/udapose")
    }

    /// Starts a server of `role` (`serve` or `adapt`) listening on `addrs` (HTTP, gRPC).
    pub(super) fn start(&self, name: &str, role: &str, addrs: [SocketAddr; 2]) -> Result<Node> {
        self.start_with(name, role, addrs, self.torch_threads)
    }

    /// [`Fleet::start`] with another `--torch-threads`.
    pub(super) fn start_with(
        &self,
        name: &str,
        role: &str,
        addrs: [SocketAddr; 2],
        torch_threads: u32,
    ) -> Result<Node> {
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
            .env("RUST_LOG", crate::harness::SERVER_LOG);
        let started = Instant::now();
        let server = ServerProcess::spawn(command, dir, addrs[0]).with_context(|| format!("starting {name}"))?;
        Ok(Node { name: name.into(), grpc: addrs[1], server, ready_s: started.elapsed().as_secs_f64() })
    }

    /// The flags every process gets (for the report).
    pub(super) fn flags(&self) -> String {
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
