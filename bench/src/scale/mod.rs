//! `udapose-bench scale`: scale-out on one machine (issue "Deploy and scale out"). Starts a
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

mod cpu;
mod faults;
mod fleet;
mod jobs;
mod load;
mod report;

use std::{
    fs,
    net::SocketAddr,
    path::{Path, PathBuf},
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow, ensure};
use serde_json::{Value, json};
use tokio::runtime::Runtime;
use udapose_lab::atomic::write_atomic;

use crate::harness::{
    command_line, estimate, free_addrs, git_commit, load_average, median, min_median_max, percentile, read_images,
    server_binary, server_log_json,
};
use fleet::{Fleet, Node, S3};
use load::replica_levels;
use report::ms_list;

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

pub fn run(args: &ScaleArgs) -> Result<()> {
    ensure!(
        args.requests >= 1 && args.distinct >= 1 && args.concurrency >= 1,
        "--requests, --distinct, --concurrency must be at least 1"
    );
    ensure!(args.fault_clients >= 1 && args.targets >= 1, "--fault-clients and --targets must be at least 1");
    let began = Instant::now();
    let command = command_line();
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
    let binary = server_binary(args.server.as_deref())?;
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
    report["commit"] = json!(git_commit());
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
    write_atomic(
        &args.out.with_extension("md"),
        report::markdown(args, &report, &levels_md, &oversubscribed_md).as_bytes(),
    )?;
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
    let fleet = start_store(args, binary, s3s_fs, scratch)?;
    let store_pid = fleet.s3.child.id();
    let worker_addrs = free_addrs(2)?;
    let (mut worker, mut replicas) = start_nodes(&fleet, [worker_addrs[0], worker_addrs[1]])?;
    let startup = json!({
        "worker_ready_s": worker.ready_s,
        "replicas_ready_s": replicas.iter().map(|r| r.ready_s).collect::<Vec<_>>(),
    });
    let seed =
        replicas[0].server.get_json("/v1/models/car")?["version"].as_str().context("no active car version")?.to_owned();
    warm_up(&replicas, images)?;

    // 1, 2 and 3 replicas under the same client concurrency.
    let (levels, levels_md) =
        replica_levels(&rt, &replicas, &[&worker], images, args.concurrency, (args.requests, LEVEL_LIMIT), store_pid)?;
    let (oversubscribed, oversubscribed_md) = if args.oversubscribed_requests > 0 && args.torch_threads != 0 {
        oversubscribed_levels(&rt, args, &fleet, &replicas, &worker, images)?
    } else {
        (Vec::new(), String::new())
    };

    // The faults, under a steady load over every replica.
    let ctx = faults::Ctx { args, rt: &rt, fleet: &fleet, store_pid, images, timeout };
    let (faults, records, all_prop) =
        faults::run(&ctx, &mut replicas, &mut worker, [worker_addrs[0], worker_addrs[1]], targets, &seed)?;
    let failed_total: u64 =
        ["swap_after_activation", "serve_replica_kill9", "rollback_on_one_replica", "worker_kill9_mid_job"]
            .iter()
            .filter_map(|k| faults[k]["window"]["failed"].as_u64())
            .sum();
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
            "fault_clients": args.fault_clients,
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
        "server_logs": server_logs(&replicas, &worker),
    });
    Ok((report, levels_md, oversubscribed_md))
}

/// The store, and what the fleet's processes share.
fn start_store(args: &ScaleArgs, binary: &Path, s3s_fs: &Path, scratch: &Path) -> Result<Fleet> {
    eprintln!("store: s3s-fs on loopback; starting 1 adapt worker and 3 serve replicas (--poll {})", args.poll);
    let s3 = S3::start(s3s_fs, scratch.join("s3"), &scratch.join("s3s-fs.log"))?;
    Ok(Fleet {
        torch_threads: args.torch_threads,
        binary: binary.to_owned(),
        scratch: scratch.to_owned(),
        s3,
        poll: args.poll,
        max_batch: args.max_batch,
    })
}

/// The worker (on `worker_addrs`), then the 3 serve replicas.
fn start_nodes(fleet: &Fleet, worker_addrs: [SocketAddr; 2]) -> Result<(Node, Vec<Node>)> {
    let worker = fleet.start("worker", "adapt", worker_addrs)?;
    eprintln!("  worker ready in {:.1} s", worker.ready_s);
    let mut replicas = Vec::new();
    for i in 0..3 {
        let a = free_addrs(2)?;
        let node = fleet.start(&format!("serve-{i}"), "serve", [a[0], a[1]])?;
        eprintln!("  {} ready in {:.1} s", node.name, node.ready_s);
        replicas.push(node);
    }
    Ok((worker, replicas))
}

/// What each process of the fleet logged (see [`server_log_json`]).
fn server_logs(replicas: &[Node], worker: &Node) -> Vec<Value> {
    replicas
        .iter()
        .chain([worker])
        .map(|n| json!({ "name": n.name, "log": server_log_json(&n.server.log()) }))
        .collect()
}

/// 4 untimed estimates on each of `nodes`.
fn warm_up(nodes: &[Node], images: &[Vec<u8>]) -> Result<()> {
    for r in nodes {
        for image in images.iter().take(4) {
            estimate(r.http(), image).map_err(|e| anyhow!("warm-up request to {} failed: {e}", r.name))?;
        }
    }
    Ok(())
}

/// The replica levels again on 3 other replicas at `--torch-threads 0` (the fleet's others idle);
/// they are stopped after.
fn oversubscribed_levels(
    rt: &Runtime,
    args: &ScaleArgs,
    fleet: &Fleet,
    replicas: &[Node],
    worker: &Node,
    images: &Arc<Vec<Vec<u8>>>,
) -> Result<(Vec<Value>, String)> {
    eprintln!("the same with 3 other replicas at --torch-threads 0 (one libtorch thread per core)");
    let mut extra = Vec::new();
    for i in 0..3 {
        let a = free_addrs(2)?;
        extra.push(fleet.start_with(&format!("serve-t0-{i}"), "serve", [a[0], a[1]], 0)?);
    }
    warm_up(&extra, images)?;
    let idle: Vec<&Node> = replicas.iter().chain([worker]).collect();
    let budget = (args.oversubscribed_requests, OVERSUBSCRIBED_LIMIT);
    replica_levels(rt, &extra, &idle, images, args.concurrency, budget, fleet.s3.child.id())
}
