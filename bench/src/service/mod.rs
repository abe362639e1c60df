//! `udapose-bench service`: the inference service under load. Starts the real
//! `udapose-server` on loopback (batching on, then off), sends PNG crops over HTTP from 1, 4
//! and 16 concurrent clients, and measures throughput and p50/p99 latency; then, with the server
//! stopped, the backbone alone on the same crops (batch 1 and batch `--max-batch`) as the
//! ceiling, and the engine's own sequential image-to-pose rate. With a third server (batching
//! on, adaptation started only by the benchmark) it measures the estimate latency while idle and
//! while an online-adaptation job runs, then the hot-swap latency between the seed and the
//! job's version (rollback / activate round trips, with clients running and with none). With
//! `--models`, every category side by side (`categories`). Writes `reports/service.json` and
//! its Markdown twin.

mod adapt;
mod categories;
mod ceiling;
pub(crate) mod clients;
mod job_sizes;
mod report;
mod swap;

use std::{
    fs,
    net::SocketAddr,
    path::{Path, PathBuf},
    sync::Arc,
    time::Instant,
};

use anyhow::{Context, Result, ensure};
use serde_json::{Value, json};
use udapose_engine::checkpoint;
use udapose_lab::atomic::write_atomic;

use crate::harness::{
    Level, ServerProcess, command_line, git_commit, load_average, post_or_get, read_images, server_binary,
};

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
    /// More flags for every server this benchmark starts, e.g. `--server-flags='--workers 2
    /// --torch-threads 1'` (split at whitespace), to compare thread layouts.
    #[arg(long, allow_hyphen_values = true)]
    server_flags: Option<String>,
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
    /// The adaptation server's `--job-nice` (default: the server's own default).
    #[arg(long)]
    job_nice: Option<i32>,
    /// Target images of the jobs timed on an idle server, one job each.
    #[arg(long, value_delimiter = ',', default_value = "50,100,200")]
    job_sizes: Vec<usize>,
    /// Skip the jobs timed against their number of target images.
    #[arg(long)]
    skip_job_sizes: bool,
    /// Rollback/activate round trips measured with clients, and again with none.
    #[arg(long, default_value_t = 3)]
    swap_rounds: usize,
    /// Also serve every category under this folder side by side (e.g. `models`): memory and
    /// per-category latency under mixed load.
    #[arg(long)]
    models: Option<PathBuf>,
    /// Where the other categories' datasets are (`<this>/syncar-ood-standard-<category>`).
    #[arg(long, default_value = "data")]
    category_data: PathBuf,
    /// Clients of the side-by-side load.
    #[arg(long, default_value_t = 6)]
    categories_clients: usize,
}

impl ServiceArgs {
    /// `--server-flags`, split at whitespace.
    pub(super) fn server_flags(&self) -> Vec<&str> {
        self.server_flags.as_deref().map_or_else(Vec::new, |f| f.split_whitespace().collect())
    }
}

/// One batching mode's name, `--max-batch` and levels.
type Mode = (&'static str, usize, Vec<Level>);

pub fn run(args: &ServiceArgs) -> Result<()> {
    ensure!(args.requests >= 1 && args.distinct >= 1, "--requests and --distinct must be at least 1");
    ensure!(args.adapt_clients >= 1, "--adapt-clients must be at least 1");
    let command = command_line();
    let load_before = load_average();
    let images = read_images(&args.images, args.distinct)?;
    let server_bin = server_binary(args.server.as_deref())?;
    let model = fs::canonicalize(&args.model).with_context(|| format!("model {}", args.model.display()))?;
    let manifest_path = model.join(checkpoint::MANIFEST);
    let manifest: checkpoint::Manifest = serde_json::from_str(&fs::read_to_string(&manifest_path)?)
        .with_context(|| format!("parsing {}", manifest_path.display()))?;

    let modes =
        if args.skip_batching_levels { Vec::new() } else { batching_levels(args, &server_bin, &model, &images)? };

    let (adaptation, swap) = if args.skip_adaptation && args.skip_swap {
        (Value::Null, Value::Null)
    } else {
        adapt::adapt_and_swap(args, &server_bin, &model, &images)?
    };

    let job_sizes = if args.skip_job_sizes || args.job_sizes.is_empty() {
        Value::Null
    } else {
        job_sizes::job_sizes(args, &server_bin, &model)?
    };

    let side_by_side = match &args.models {
        Some(models) => categories::side_by_side(args, &server_bin, models)?,
        None => Value::Null,
    };

    let ceiling = if args.skip_ceiling {
        None
    } else {
        eprintln!("backbone alone and engine alone (server stopped)");
        Some(ceiling::backbone_ceiling(&model, &images, args.max_batch)?)
    };
    let best = modes.iter().flat_map(|(_, _, l)| l).map(Level::throughput).fold(f64::NAN, f64::max);
    let report = json!({
        "command": command,
        "commit": git_commit(),
        "machine": {
            "cpu": udapose_engine::runtime::cpu_model(),
            "threads": std::thread::available_parallelism().map_or(1, |n| n.get()),
            "torch_threads": tch::get_num_threads(),
            "device": format!("{:?}", udapose_engine::runtime::RuntimeInfo::detect().device()),
            "load_average_before": load_before,
            "load_average_after": load_average(),
        },
        "note": args.note,
        "server_flags": args.server_flags,
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
        "throughput_ratio": throughput_ratio(&modes, args.max_batch, ceiling.as_ref()),
        "p99_job_over_idle": adaptation["p99_ratio"],
        "job_seconds": adaptation["job"]["seconds"],
        "failed_requests": failed_requests(&modes, &adaptation) + side_by_side["failed_requests"].as_u64().unwrap_or(0),
        "adaptation": adaptation,
        "swap": swap,
        "job_sizes": job_sizes,
        "side_by_side": side_by_side,
    });
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    let mut md = report::markdown(args, &report, &modes, manifest.crop, ceiling.as_ref(), best);
    md.push_str(&report::adaptation_markdown(&report));
    md.push_str(&report::swap_markdown(&report));
    md.push_str(&job_sizes::markdown(&report));
    md.push_str(&categories::markdown(&report));
    write_atomic(&args.out.with_extension("md"), md.as_bytes())?;
    eprintln!("wrote {} and its .md", args.out.display());
    Ok(())
}

/// The yardstick: the most clients' throughput with batching on, over the backbone alone
/// in passes of `max_batch` (the most any serving could do without a solver).
fn throughput_ratio(modes: &[Mode], max_batch: usize, ceiling: Option<&ceiling::Ceiling>) -> Option<f64> {
    let (_, _, levels) = modes.iter().find(|(_, b, _)| *b == max_batch && max_batch > 1)?;
    let busiest = levels.iter().max_by_key(|l| l.concurrency)?;
    Some(busiest.throughput() / ceiling?.batched)
}

/// Requests that failed at any concurrency level and while the job ran.
fn failed_requests(modes: &[Mode], adaptation: &Value) -> u64 {
    let levels: usize = modes.iter().flat_map(|(_, _, l)| l).map(|l| l.errors).sum();
    levels as u64 + adaptation["errors_during_job"].as_u64().unwrap_or(0)
}

/// The concurrency levels with batching on (`--max-batch`), then off (1), a server each.
fn batching_levels(args: &ServiceArgs, server_bin: &Path, model: &Path, images: &[Vec<u8>]) -> Result<Vec<Mode>> {
    let mut modes = Vec::new();
    for (name, max_batch) in [("on", args.max_batch), ("off", 1)] {
        eprintln!("batching {name} (--max-batch {max_batch})");
        let server =
            ServerProcess::start(server_bin, model, max_batch, args.max_delay_ms, &args.server_flags(), false)?;
        let levels = args
            .concurrency
            .iter()
            .map(|&c| load(server.http, images, c, args.requests))
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
    Ok(modes)
}

/// `requests` estimates from `concurrency` threads (images in rotation), after a warm-up.
fn load(http: SocketAddr, images: &[Vec<u8>], concurrency: usize, requests: usize) -> Result<Level> {
    let mut levels = load_categories(http, &[("car", images)], concurrency, requests)?;
    Ok(levels.remove(0))
}

/// `requests` estimates from `concurrency` threads, request `r` to category `r mod n` (its
/// images in rotation), after a warm-up of each; a level per category, all over the same time.
fn load_categories(
    http: SocketAddr,
    targets: &[(&str, &[Vec<u8>])],
    concurrency: usize,
    requests: usize,
) -> Result<Vec<Level>> {
    ensure!(concurrency >= 1, "concurrency must be at least 1");
    ensure!(!targets.is_empty() && targets.iter().all(|(_, i)| !i.is_empty()), "no images to send");
    for (category, images) in targets {
        for image in images.iter().cycle().take(4) {
            let (status, body) = post_or_get(http, "POST", &format!("/v1/pose/{category}"), image)?;
            ensure!(status == 200, "warm-up request to {category} failed: {status} {body}");
        }
    }
    let targets: Arc<Vec<(String, Vec<Vec<u8>>)>> =
        Arc::new(targets.iter().map(|(c, i)| (c.to_string(), i.to_vec())).collect());
    let started = Instant::now();
    let threads: Vec<_> = (0..concurrency)
        .map(|t| {
            let targets = targets.clone();
            std::thread::spawn(move || {
                let mut out = Vec::new();
                for r in (t..requests).step_by(concurrency) {
                    let (category, images) = &targets[r % targets.len()];
                    let image = &images[(r / targets.len()) % images.len()];
                    let sent = Instant::now();
                    let ok = matches!(post_or_get(http, "POST", &format!("/v1/pose/{category}"), image), Ok((200, _)));
                    out.push((r % targets.len(), ok, sent.elapsed().as_secs_f64() * 1e3));
                }
                out
            })
        })
        .collect();
    let mut per: Vec<(usize, usize, Vec<f64>)> = vec![(0, 0, Vec::new()); targets.len()];
    for t in threads {
        for (k, ok, ms) in t.join().map_err(|_| anyhow::anyhow!("a client thread panicked"))? {
            per[k].0 += 1;
            if ok {
                per[k].2.push(ms);
            } else {
                per[k].1 += 1;
            }
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    Ok(per
        .into_iter()
        .map(|(requests, errors, latencies_ms)| Level { concurrency, requests, errors, seconds, latencies_ms })
        .collect())
}
