//! `udapose-lab bench service`: the inference service under load. Starts the real
//! `udapose-server` on loopback (batching on, then off), sends PNG crops over HTTP from 1, 4
//! and 16 concurrent clients, and measures throughput and p50/p99 latency; then, with the server
//! stopped, the backbone alone on the same crops (batch 1 and batch `--max-batch`) as the
//! ceiling, and the engine's own sequential image-to-pose rate. Writes `reports/service.json`
//! and its Markdown twin.

use std::{
    fs,
    io::{Read, Write},
    net::{SocketAddr, TcpListener, TcpStream},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail, ensure};
use serde_json::{Value, json};
use tch::Tensor;
use udapose_engine::{
    Camera, checkpoint,
    estimator::{self, SolverMesh},
    input::{self, Rgb8Image},
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
}

/// One concurrency level's measurements.
struct Level {
    concurrency: usize,
    requests: usize,
    errors: usize,
    seconds: f64,
    latencies_ms: Vec<f64>,
}

impl Level {
    fn throughput(&self) -> f64 {
        (self.requests - self.errors) as f64 / self.seconds
    }

    fn percentile(&self, p: f64) -> f64 {
        let mut v = self.latencies_ms.clone();
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            return f64::NAN;
        }
        v[((p * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)]
    }

    fn json(&self) -> Value {
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

pub fn run(args: &ServiceArgs) -> Result<()> {
    ensure!(args.requests >= 1 && args.distinct >= 1, "--requests and --distinct must be at least 1");
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let load_before = load_average();
    let images = read_images(&args.images, args.distinct)?;
    let server_bin = match &args.server {
        Some(p) => p.clone(),
        None => std::env::current_exe()?.with_file_name("udapose-server"),
    };
    ensure!(server_bin.is_file(), "{} not found: build the workspace first", server_bin.display());
    let model = fs::canonicalize(&args.model).with_context(|| format!("model {}", args.model.display()))?;

    let mut modes = Vec::new();
    for (name, max_batch) in [("on", args.max_batch), ("off", 1)] {
        eprintln!("batching {name} (--max-batch {max_batch})");
        let server = ServerProcess::start(&server_bin, &model, max_batch, args.max_delay_ms)?;
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

    eprintln!("backbone alone and engine alone (server stopped)");
    let ceiling = backbone_ceiling(&model, &images, args.max_batch)?;
    let best = modes.iter().flat_map(|(_, _, l)| l).map(Level::throughput).fold(0.0, f64::max);
    let backbone_best = ceiling.batch1.max(ceiling.batched);
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
        "crop": ceiling.crop,
        "images": { "folder": args.images.display().to_string(), "distinct": images.len() },
        "transport": "HTTP/1.1 POST /v1/pose/car with a PNG body, one connection per request, loopback",
        "max_delay_ms": args.max_delay_ms,
        "modes": modes.iter().map(|(name, max_batch, levels)| json!({
            "batching": name, "max_batch": max_batch, "levels": levels.iter().map(Level::json).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
        "backbone_only_per_s": { "batch_1": ceiling.batch1, "batched": ceiling.batched, "batch": args.max_batch },
        "engine_sequential_per_s": ceiling.engine,
        "best_service_per_s": best,
        "ratio_to_backbone_ceiling": best / backbone_best,
        "ratio_to_engine_sequential": best / ceiling.engine,
    });
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), markdown(args, &report, &modes, &ceiling, best).as_bytes())?;
    eprintln!("wrote {} and its .md", args.out.display());
    Ok(())
}

fn markdown(args: &ServiceArgs, report: &Value, modes: &[(&str, usize, Vec<Level>)], c: &Ceiling, best: f64) -> String {
    let m = &report["machine"];
    let mut md = format!(
        "# Service benchmark\n\n`{}`\n\nModel `{}` ({}×{} crops), {} distinct PNG crops from `{}`, {} requests per level \
         after 4 warm-up requests; HTTP/1.1 POST `/v1/pose/car`, one connection per request, on loopback. Machine: {}, \
         {} threads (torch {}), device {}; load average {} before, {} after. Commit `{}`.{}\n\n\
         | batching | clients | req/s | p50 (ms) | p99 (ms) | errors |\n|---|---:|---:|---:|---:|---:|\n",
        report["command"].as_str().unwrap_or(""),
        args.model.display(),
        c.crop[0],
        c.crop[1],
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
fn read_images(dir: &Path, n: usize) -> Result<Vec<Vec<u8>>> {
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
struct ServerProcess {
    child: Child,
    dir: PathBuf,
    http: SocketAddr,
}

impl ServerProcess {
    fn start(binary: &Path, model: &Path, max_batch: usize, max_delay_ms: u64) -> Result<Self> {
        let dir = std::env::temp_dir().join(format!("udapose-bench-service-{}-{max_batch}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(dir.join("models"))?;
        std::os::unix::fs::symlink(model, dir.join("models/car"))?;
        let ports: Vec<TcpListener> = (0..2).map(|_| TcpListener::bind("127.0.0.1:0")).collect::<Result<_, _>>()?;
        let (http, grpc) = (ports[0].local_addr()?, ports[1].local_addr()?);
        drop(ports);
        let log = fs::File::create(dir.join("server.log"))?;
        let child = Command::new(binary)
            .args(["--http-addr", &http.to_string(), "--grpc-addr", &grpc.to_string()])
            .arg("--models")
            .arg(dir.join("models"))
            .arg("--store")
            .arg(dir.join("state"))
            .args(["--max-batch", &max_batch.to_string(), "--max-delay-ms", &max_delay_ms.to_string()])
            .env("RUST_LOG", "warn")
            .env_remove("UDAPOSE_TOKEN")
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("starting {}", binary.display()))?;
        let server = ServerProcess { child, dir, http };
        let deadline = Instant::now() + Duration::from_secs(120);
        while post_or_get(http, "GET", "/readyz", b"").map(|(s, _)| s).unwrap_or(0) != 200 {
            if Instant::now() > deadline {
                bail!("the server did not become ready: {}", fs::read_to_string(server.dir.join("server.log"))?);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(server)
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
fn post_or_get(addr: SocketAddr, method: &str, path: &str, body: &[u8]) -> std::io::Result<(u16, String)> {
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

struct Ceiling {
    crop: [usize; 2],
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
    let model = checkpoint::load(model_dir, device)?;
    let crop = model.manifest.crop;
    let crops: Vec<Tensor> = images
        .iter()
        .map(|bytes| -> Result<Tensor> {
            let img = image::load_from_memory(bytes)?.into_rgb8();
            let (w, h) = (img.width() as usize, img.height() as usize);
            Ok(input::crop(&Rgb8Image::new(img.as_raw(), w, h)?, None, crop)?.tensor())
        })
        .collect::<Result<_>>()?;
    let backbone = &model.backbone;
    let run = |batch: &[Tensor]| estimator::features(backbone, &Tensor::cat(batch, 0).to_device(device));
    run(&crops[..1])?; // warm-up
    let rounds = 3;
    let t = Instant::now();
    for _ in 0..rounds {
        for c in crops.chunks(1) {
            run(c)?;
        }
    }
    let batch1 = (rounds * crops.len()) as f64 / t.elapsed().as_secs_f64();
    let batch: Vec<Tensor> = crops.iter().cycle().take(max_batch).map(Tensor::shallow_clone).collect();
    run(&batch)?;
    let t = Instant::now();
    let batches = (rounds * crops.len()).div_ceil(max_batch);
    for _ in 0..batches {
        run(&batch)?;
    }
    let batched = (batches * max_batch) as f64 / t.elapsed().as_secs_f64();
    let solver_mesh = SolverMesh::from_neural_mesh(&model.neural_mesh)?;
    let camera = Camera::for_crop(crop[0], crop[1])?;
    let config = SolverConfig::default();
    let solve = |c: &Tensor| -> Result<()> {
        let f = run(std::slice::from_ref(c))?;
        estimator::estimate(&model.neural_mesh.mesh, &solver_mesh, &f[0], &camera, &config)?;
        Ok(())
    };
    solve(&crops[0])?; // warm-up (the solver's thread pool and buffers)
    let t = Instant::now();
    for _ in 0..rounds {
        crops.iter().try_for_each(solve)?;
    }
    let engine = (rounds * crops.len()) as f64 / t.elapsed().as_secs_f64();
    Ok(Ceiling { crop, batch1, batched, engine })
}

fn load_average() -> String {
    fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}
