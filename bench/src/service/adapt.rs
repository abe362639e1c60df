//! The service benchmark's latency during adaptation: a server (batching on, only the benchmark
//! starts jobs) measured idle, then during an online-adaptation job on uploaded target images,
//! then idle again; the swaps follow on the same server (`swap`).

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow, bail, ensure};
use serde_json::{Value, json};

use super::ServiceArgs;
use super::clients::{Clients, Cpu, others_cores, window_json};
use super::swap;
use crate::harness::{Level, Record, ServerProcess, estimate, load_average, post_or_get, read_images, summary, window};

/// How long the clients run before an idle window is measured: the first batched requests after
/// the server starts can be much slower than the rest.
pub(super) const WARM_UP: Duration = Duration::from_secs(3);

/// The adaptation server's flags: no job starts by itself (only the benchmark starts one),
/// `--job-nice` when the benchmark is given one, then `--server-flags`.
pub(super) fn flags(args: &ServiceArgs) -> Vec<String> {
    let mut flags = vec!["--adapt-min-images".to_owned(), "1000000".to_owned()];
    if let Some(nice) = args.job_nice {
        flags.extend(["--job-nice".to_owned(), nice.to_string()]);
    }
    flags.extend(args.server_flags().into_iter().map(str::to_owned));
    flags
}

/// The target images' folder: `--adapt-images`, or the `combined` domain's adapt split next to
/// `--images`.
pub(super) fn target_folder(args: &ServiceArgs) -> Result<PathBuf> {
    match &args.adapt_images {
        Some(f) => Ok(f.clone()),
        None => default_adapt_images(&args.images),
    }
}

/// The load average at each step of the measurement.
pub(super) type Loads = Vec<(&'static str, String)>;

/// The adaptation server (batching on; only the benchmark starts jobs): `--adapt-clients`
/// clients idle, then during a job on the uploaded target images; then swaps between the seed
/// and the job's version with the clients running and with none. Returns the report's
/// `adaptation` and `swap` values (null when skipped).
pub(super) fn adapt_and_swap(
    args: &ServiceArgs,
    server_bin: &Path,
    model: &Path,
    images: &[Vec<u8>],
) -> Result<(Value, Value)> {
    let folder = target_folder(args)?;
    let targets = read_images(&folder, args.adapt_count)?;
    let n = args.adapt_clients;
    let flags = flags(args);
    eprintln!("adaptation (--max-batch {} {}), {n} clients", args.max_batch, flags.join(" "));
    let flag_refs: Vec<&str> = flags.iter().map(String::as_str).collect();
    let server = ServerProcess::start(server_bin, model, args.max_batch, args.max_delay_ms, &flag_refs, true)?;
    let images = Arc::new(images.to_vec());
    for image in images.iter().cycle().take(4) {
        estimate(server.http, image).map_err(|e| anyhow!("warm-up request failed: {e}"))?;
    }
    let source = server.get_json("/v1/models/car")?["version"].as_str().context("no active car version")?.to_owned();

    let measure_idle = |when: &str| measure_idle(&server, &images, n, args.adapt_idle_seconds, when);
    let mut loads = vec![("idle_before_start", load_average())];
    let idle_before = (!args.skip_adaptation).then(|| measure_idle("before"));
    loads.push(("idle_before_end", load_average()));
    let upload = Upload::send(&server, folder, &targets)?;

    let clients = (!args.skip_adaptation).then(|| Clients::start(server.http, &images, n));
    if clients.is_some() {
        std::thread::sleep(Duration::from_secs(1));
    }
    let (id, overrides, job, seen) = run_job(args, &server, &mut loads)?;
    let records = clients.map(Clients::stop);
    loads.push(("job_end", load_average()));
    let state = job["state"].as_str().unwrap_or("").to_owned();
    eprintln!("  job {id} ended {state}: {}", job["reason"].as_str().unwrap_or(""));
    let idle_after = (!args.skip_adaptation).then(|| measure_idle("after"));
    loads.push(("idle_after_end", load_average()));
    let (Some(from), Some(to)) = (seen.running, seen.active_until) else {
        bail!("job {id} was never seen RUNNING; it ended {state}: {}", job["reason"]);
    };
    let split = seen.validating.unwrap_or(to);
    let job_report = job_json(&job, &overrides, (split - from).as_secs_f64(), (to - split).as_secs_f64());

    let adaptation = match (&idle_before, &idle_after, &records) {
        (Some(before), Some(after), Some(records)) => {
            let mut a = adaptation_json(args, &upload, [before, after], records, &seen, (from, to), &loads);
            a["job"] = job_report.clone();
            a
        }
        _ => Value::Null,
    };

    if args.skip_swap {
        return Ok((adaptation, Value::Null));
    }
    let job_ref = if adaptation.is_null() { job_report } else { json!(id) };
    let swap = swap::measure_swaps(args, &server, &images, &source, &id, &job, job_ref)?;
    Ok((adaptation, swap))
}

/// The clients for `--adapt-idle-seconds` after a warm-up, with no job: their window and the
/// cores other processes used meanwhile.
fn measure_idle(
    server: &ServerProcess,
    images: &Arc<Vec<Vec<u8>>>,
    n: usize,
    seconds: f64,
    when: &str,
) -> (Level, Option<f64>) {
    let pid = server.child.id();
    let clients = Clients::start(server.http, images, n);
    std::thread::sleep(WARM_UP);
    let (from, cpu_from) = (Instant::now(), Cpu::now(pid));
    std::thread::sleep(Duration::from_secs_f64(seconds));
    let (to, cpu_to) = (Instant::now(), Cpu::now(pid));
    let idle = window(&clients.stop(), from, to, n);
    let others = others_cores(cpu_from, cpu_to);
    eprintln!("  idle {when} the job: {}; other processes {:.2} cores", summary(&idle), others.unwrap_or(f64::NAN));
    (idle, others)
}

/// The target images uploaded before the job, and the answers.
pub(super) struct Upload {
    folder: PathBuf,
    sent: usize,
    statuses: BTreeMap<String, usize>,
    /// The first 5 images not accepted, with why.
    rejections: Vec<String>,
    seconds: f64,
}

impl Upload {
    pub(super) fn send(server: &ServerProcess, folder: PathBuf, targets: &[Vec<u8>]) -> Result<Upload> {
        eprintln!("  uploading {} target images from {}", targets.len(), folder.display());
        let upload_started = Instant::now();
        let mut statuses = BTreeMap::<String, usize>::new();
        let mut rejections = Vec::new();
        for target in targets {
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
        let seconds = upload_started.elapsed().as_secs_f64();
        Ok(Upload { folder, sent: targets.len(), statuses, rejections, seconds })
    }
}

/// What the polls of the job saw: when it was first RUNNING, first VALIDATING and last in
/// either state, with the CPU counters at those polls.
#[derive(Default)]
pub(super) struct Seen {
    pub(super) running: Option<Instant>,
    pub(super) validating: Option<Instant>,
    pub(super) active_until: Option<Instant>,
    cpu_running: Option<Cpu>,
    cpu_validating: Option<Cpu>,
    cpu_until: Option<Cpu>,
}

/// Starts a job (with the `--adapt-*` overrides) and polls it until it ends; returns its id,
/// the overrides, its final state and what the polls saw.
pub(super) fn run_job(
    args: &ServiceArgs,
    server: &ServerProcess,
    loads: &mut Loads,
) -> Result<(String, Value, Value, Seen)> {
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
    let (job, seen) = poll_job(args, server, &id)?;
    Ok((id, overrides, job, seen))
}

/// Polls job `id` every 100 ms until it leaves QUEUED, RUNNING and VALIDATING (cancelled after
/// `--adapt-timeout-s`).
fn poll_job(args: &ServiceArgs, server: &ServerProcess, id: &str) -> Result<(Value, Seen)> {
    let pid = server.child.id();
    let deadline = Instant::now() + Duration::from_secs(args.adapt_timeout_s);
    let mut seen = Seen::default();
    let mut round = 0;
    let job = loop {
        let job = server.get_json(&format!("/v1/jobs/{id}"))?;
        let now = Instant::now();
        let cpu = Cpu::now(pid);
        let state = job["state"].as_str().unwrap_or("").to_owned();
        match state.as_str() {
            "QUEUED" => {}
            "RUNNING" | "VALIDATING" => {
                if seen.running.is_none() {
                    (seen.running, seen.cpu_running) = (Some(now), cpu);
                }
                (seen.active_until, seen.cpu_until) = (Some(now), cpu);
                let e = &job["last_event"];
                if e["round"].as_u64().is_some_and(|r| r != round) {
                    round = e["round"].as_u64().unwrap_or(0);
                    eprintln!("  round {round}: fired ratio {:.3}", e["fired_ratio"].as_f64().unwrap_or(f64::NAN));
                }
                if state == "VALIDATING" && seen.validating.is_none() {
                    (seen.validating, seen.cpu_validating) = (Some(now), cpu);
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
    Ok((job, seen))
}

/// The report's `adaptation` (but its `job`): the idle windows before and after the job, pooled,
/// against the requests while it was RUNNING or VALIDATING (`[from, to]`).
fn adaptation_json(
    args: &ServiceArgs,
    upload: &Upload,
    [(before, before_cpu), (after, after_cpu)]: [&(Level, Option<f64>); 2],
    records: &[Record],
    seen: &Seen,
    (from, to): (Instant, Instant),
    loads: &Loads,
) -> Value {
    let n = args.adapt_clients;
    let split = seen.validating.unwrap_or(to);
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
    let phase_validating = seen.validating.map(|v| window(records, v, to, n));
    let during_cpu = others_cores(seen.cpu_running, seen.cpu_until);
    let running_cpu = others_cores(seen.cpu_running, seen.cpu_validating.or(seen.cpu_until));
    let validating_cpu = others_cores(seen.cpu_validating, seen.cpu_until);
    let idle_cpu = before_cpu
        .zip(*after_cpu)
        .map(|(b, a)| (b * before.seconds + a * after.seconds) / (before.seconds + after.seconds));
    eprintln!("  during adaptation: {}; other processes {:.2} cores", summary(&during), during_cpu.unwrap_or(f64::NAN));
    eprintln!("  idle, before and after: {}", summary(&idle));
    json!({
        "server": { "max_batch": args.max_batch, "max_delay_ms": args.max_delay_ms, "flags": flags(args).join(" ") },
        "clients": n,
        "idle_seconds": args.adapt_idle_seconds,
        "targets": {
            "folder": upload.folder.display().to_string(),
            "sent": upload.sent,
            "statuses": upload.statuses,
            "not_accepted": upload.rejections,
            "upload_seconds": upload.seconds,
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
    })
}

/// `<data>/combined/adapt/images/<category>` for `--images` `<data>/<domain>/<split>/images/<category>`.
fn default_adapt_images(images: &Path) -> Result<PathBuf> {
    let underivable = || format!("cannot derive --adapt-images from --images {}: pass it", images.display());
    let category = images.file_name().with_context(underivable)?;
    let data = images.ancestors().nth(4).filter(|p| !p.as_os_str().is_empty()).with_context(underivable)?;
    Ok(data.join("combined/adapt/images").join(category))
}

/// The adaptation job as the report shows it.
pub(super) fn job_json(job: &Value, overrides: &Value, running_s: f64, validating_s: f64) -> Value {
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
