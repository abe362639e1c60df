//! The faults of the scale benchmark, in order under a steady load over every replica: an
//! adaptation job and the swap to its version, the `kill -9` of a serve replica (and its
//! restart), a rollback on one replica, and the `kill -9` of the worker in the middle of a job.

use std::{
    collections::{BTreeMap, BTreeSet},
    net::SocketAddr,
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow, ensure};
use serde_json::{Value, json};
use tokio::runtime::Runtime;

use super::ScaleArgs;
use super::cpu::{Snapshot, served, snapshot};
use super::fleet::{Fleet, Node};
use super::jobs::{
    Swap, activated_swap, job_history, job_on, job_state, now_epoch, swap_steps, terminal, upload, wait_job,
    wait_serving,
};
use super::load::{Load, connect};
use super::report::ms_list;
use crate::harness::{Record, estimate, percentile, server_log_json, window};

/// What every fault needs: the settings, the runtime of the client, the fleet, the images.
pub(super) struct Ctx<'a> {
    pub(super) args: &'a ScaleArgs,
    pub(super) rt: &'a Runtime,
    pub(super) fleet: &'a Fleet,
    pub(super) store_pid: u32,
    pub(super) images: &'a Arc<Vec<Vec<u8>>>,
    pub(super) timeout: Duration,
}

impl Ctx<'_> {
    fn snapshot(&self, replicas: &[Node], worker: &Node) -> Snapshot {
        snapshot(replicas, worker, self.store_pid)
    }

    fn image(&self) -> &[u8] {
        &self.images[0]
    }

    /// The fleet's CPU snapshot, then the targets uploaded to every replica and a job asked on
    /// serve-0: the snapshot, the uploads and the job's id.
    fn start_job(
        &self,
        replicas: &[Node],
        worker: &Node,
        job_body: &Value,
        targets: &[Vec<u8>],
    ) -> Result<(Snapshot, BTreeMap<String, usize>, String)> {
        let from = self.snapshot(replicas, worker);
        let all: Vec<&Node> = replicas.iter().collect();
        let uploaded = upload(&all, targets)?;
        let job = replicas[0].server.post_json("/v1/adapt/car/jobs", job_body)?;
        let id = job["job_id"].as_str().context("no job_id")?.to_owned();
        eprintln!("  uploaded {uploaded:?}; job {id} asked on serve-0");
        Ok((from, uploaded, id))
    }
}

/// A fault's window: snapshots of every process at its start and end.
struct Span {
    from: Snapshot,
    to: Snapshot,
}

impl Span {
    /// The load's requests in flight during the span.
    fn window(&self, records: &[Record], clients: usize) -> Value {
        fault_window(records, self.from.at, self.to.at, clients, self.to.others_cores_since(&self.from))
    }
}

/// The faults in order, under `--fault-clients` requests in flight through one client over
/// every replica (the worker and serve-2 are replaced by new processes on the way). Returns the
/// report's `faults`, every request of the load, and every swap propagation time (ms).
pub(super) fn run(
    ctx: &Ctx,
    replicas: &mut [Node],
    worker: &mut Node,
    worker_addrs: [SocketAddr; 2],
    targets: &[Vec<u8>],
    seed: &str,
) -> Result<(Value, Vec<Record>, Vec<f64>)> {
    let args = ctx.args;
    let endpoints: Vec<SocketAddr> = replicas.iter().map(|r| r.grpc).collect();
    let client = connect(ctx.rt, &endpoints)?;
    let load = Load::start(ctx.rt, &client, ctx.images, args.fault_clients);
    std::thread::sleep(Duration::from_secs(1));
    let mut overrides = json!({});
    if let Some(r) = args.max_rounds {
        overrides["max_rounds"] = json!(r);
    }
    let job_body = json!({ "overrides": overrides });
    let a = JobSwap::activation(ctx, &load, replicas, worker, &job_body, &targets[..args.targets])?;
    let b = ReplicaKill::run(ctx, &load, replicas, worker, &a.swap.version)?;
    let c = Rollback::run(ctx, &load, replicas, worker, seed)?;
    let d = WorkerKill::run(ctx, &load, replicas, worker, worker_addrs, &job_body, &targets[args.targets..])?;
    let records = load.stop(ctx.rt);
    let history_d = job_history(worker, &d.id);
    let n = args.fault_clients;
    let faults = json!({
        "swap_after_activation": a.json(&records, n),
        "serve_replica_kill9": b.json(args, &records, n),
        "rollback_on_one_replica": c.json(&records, n, seed),
        "worker_kill9_mid_job": d.json(args, &records, n, history_d),
    });
    let all_prop: Vec<f64> =
        a.swap.propagation_ms.iter().chain(&c.propagation_ms).chain(&d.job.swap.propagation_ms).copied().collect();
    Ok((faults, records, all_prop))
}

/// A finished job as the report shows it.
fn job_json(done: &Value) -> Value {
    json!({
        "id": done["job_id"], "state": done["state"], "version": done["version"], "source_version": done["source_version"],
        "images_used": done["images_used"], "images_held_out": done["images_held_out"], "reason": done["reason"],
        "seconds": done["updated"].as_f64().zip(done["created"].as_f64()).map(|(u, c)| u - c),
        "last_event": done["last_event"]["message"],
    })
}

/// (a) A job asked on a replica, run by the worker, and its version's swap on every replica.
struct JobSwap {
    span: Span,
    uploaded: BTreeMap<String, usize>,
    done: Value,
    swap: Swap,
}

impl JobSwap {
    fn activation(
        ctx: &Ctx,
        load: &Load,
        replicas: &[Node],
        worker: &Node,
        job_body: &Value,
        targets: &[Vec<u8>],
    ) -> Result<JobSwap> {
        eprintln!("fault: adaptation job and the swap after its activation ({} clients)", ctx.args.fault_clients);
        let (from, uploaded, id) = ctx.start_job(replicas, worker, job_body, targets)?;
        let all: Vec<&Node> = replicas.iter().collect();
        let (done, swap) = activated_swap(worker, &id, &all, ctx.image(), ctx.timeout)?;
        let to = ctx.snapshot(replicas, worker);
        eprintln!(
            "  {} reached the replicas {} ms after its activation; {:?} (answered, failed) so far",
            swap.version,
            ms_list(&swap.propagation_ms),
            load.counts()
        );
        Ok(JobSwap { span: Span { from, to }, uploaded, done, swap })
    }

    fn json(&self, records: &[Record], n: usize) -> Value {
        json!({
            "window": self.span.window(records, n),
            "uploaded": self.uploaded,
            "job": job_json(&self.done),
            "propagation_ms": self.swap.propagation_ms,
            "propagation_steps": self.swap.steps,
            "probes": self.swap.probes,
        })
    }
}

/// (b) `kill -9` of serve-2 under load, then its restart on the same ports.
struct ReplicaKill {
    span: Span,
    killed_at: Instant,
    restarting_at: Instant,
    restart_ready_s: f64,
    restarted_version: String,
    rejoin_s: f64,
    log_killed: String,
}

impl ReplicaKill {
    fn run(ctx: &Ctx, load: &Load, replicas: &mut [Node], worker: &Node, active: &str) -> Result<ReplicaKill> {
        eprintln!("fault: kill -9 of serve-2 under load ({} s), then its restart", ctx.args.kill_window_s);
        let from = ctx.snapshot(replicas, worker);
        let addrs_2 = [replicas[2].http(), replicas[2].grpc];
        let log_killed = replicas[2].server.log();
        replicas[2].kill9()?;
        let killed_at = Instant::now();
        std::thread::sleep(Duration::from_secs_f64(ctx.args.kill_window_s));
        let restarting_at = Instant::now();
        let restarted = ctx.fleet.start("serve-2-restarted", "serve", addrs_2)?;
        let ready_at = Instant::now();
        let restarted_version =
            estimate(restarted.http(), ctx.image()).map_err(|e| anyhow!("the restarted replica: {e}"))?;
        ensure!(
            restarted_version == active,
            "the restarted replica serves {restarted_version}, not the active {active}"
        );
        let first_seen = served(restarted.http()).map_or(0.0, |s| s.grpc_ok);
        let rejoin_deadline = Instant::now() + Duration::from_secs(30);
        while served(restarted.http()).is_none_or(|s| s.grpc_ok <= first_seen) {
            ensure!(Instant::now() < rejoin_deadline, "the client sent the restarted replica nothing for 30 s");
            std::thread::sleep(Duration::from_millis(100));
        }
        let rejoin_s = ready_at.elapsed().as_secs_f64();
        let _ = std::mem::replace(&mut replicas[2], restarted);
        let to = ctx.snapshot(replicas, worker);
        eprintln!(
            "  restarted in {:.1} s serving {restarted_version}; the client sent it requests again {:.1} s after it was ready; {:?} so far",
            replicas[2].ready_s,
            rejoin_s,
            load.counts()
        );
        let restart_ready_s = replicas[2].ready_s;
        Ok(ReplicaKill {
            span: Span { from, to },
            killed_at,
            restarting_at,
            restart_ready_s,
            restarted_version,
            rejoin_s,
            log_killed,
        })
    }

    fn json(&self, args: &ScaleArgs, records: &[Record], n: usize) -> Value {
        json!({
            "window": self.span.window(records, n),
            "killed_until_restart": fault_window(records, self.killed_at, self.restarting_at, n, None),
            "timeline": timeline(records, self.killed_at - Duration::from_secs(2), self.span.to.at, self.killed_at),
            "kill_window_s": args.kill_window_s,
            "restart_ready_s": self.restart_ready_s,
            "restart_serves": self.restarted_version,
            "client_rejoin_s_after_ready": self.rejoin_s,
            "killed_replica_log": server_log_json(&self.log_killed),
        })
    }
}

/// (c) A rollback on one replica reaching every replica.
struct Rollback {
    span: Span,
    call_ms: f64,
    propagation_ms: Vec<f64>,
    steps: Vec<Value>,
    probes: Vec<Value>,
}

impl Rollback {
    fn run(ctx: &Ctx, load: &Load, replicas: &[Node], worker: &Node, seed: &str) -> Result<Rollback> {
        eprintln!("fault: rollback on serve-1");
        let from = ctx.snapshot(replicas, worker);
        let (rolled_at, epoch_c) = (Instant::now(), now_epoch());
        let rolled = replicas[1]
            .server
            .post_json("/v1/models/car/rollback", &json!({ "reason": "udapose-bench scale: rollback propagation" }))?;
        let call_ms = rolled_at.elapsed().as_secs_f64() * 1e3;
        ensure!(
            rolled["version"].as_str() == Some(seed),
            "the rollback activated {} instead of {seed}",
            rolled["version"]
        );
        let all: Vec<&Node> = replicas.iter().collect();
        let (propagation_ms, probes) = wait_serving(&all, seed, rolled_at, ctx.image(), ctx.timeout)?;
        let steps = swap_steps(&all, seed, epoch_c);
        let to = ctx.snapshot(replicas, worker);
        eprintln!(
            "  {seed} reached the replicas {} ms after the rollback; {:?} so far",
            ms_list(&propagation_ms),
            load.counts()
        );
        Ok(Rollback { span: Span { from, to }, call_ms, propagation_ms, steps, probes })
    }

    fn json(&self, records: &[Record], n: usize, seed: &str) -> Value {
        json!({
            "window": self.span.window(records, n),
            "on": "serve-1",
            "to_version": seed,
            "call_ms": self.call_ms,
            "propagation_ms": self.propagation_ms,
            "propagation_steps": self.steps,
            "probes": self.probes,
        })
    }
}

/// (d) `kill -9` of the worker in the middle of a job; a new worker resumes it.
struct WorkerKill {
    id: String,
    job: JobSwap,
    state_at_kill: String,
    round_at_kill: Value,
    new_worker_ready_s: f64,
    activations_by_job: usize,
    incomplete: Vec<String>,
    log_worker_killed: String,
}

impl WorkerKill {
    fn run(
        ctx: &Ctx,
        load: &Load,
        replicas: &[Node],
        worker: &mut Node,
        worker_addrs: [SocketAddr; 2],
        job_body: &Value,
        targets: &[Vec<u8>],
    ) -> Result<WorkerKill> {
        eprintln!("fault: kill -9 of the worker mid-job, then a new worker");
        let (from, uploaded, id) = ctx.start_job(replicas, worker, job_body, targets)?;
        let all: Vec<&Node> = replicas.iter().collect();
        let (before_kill, log_worker_killed) = kill_mid_job(ctx, worker, &id)?;
        let state_at_kill = job_state(&before_kill).to_owned();
        let new_worker = ctx.fleet.start("worker-restarted", "adapt", worker_addrs)?;
        let old_worker = std::mem::replace(worker, new_worker);
        drop(old_worker);
        let (done, swap) = activated_swap(worker, &id, &all, ctx.image(), ctx.timeout)?;
        let to = ctx.snapshot(replicas, worker);
        let log = replicas[0].server.get_json("/v1/models/car/versions")?;
        let activations_by_job =
            log["activations"].as_array().map_or(0, |a| a.iter().filter(|a| a["job_id"] == id.as_str()).count());
        let complete: BTreeSet<&str> =
            log["versions"].as_array().into_iter().flatten().filter_map(|v| v["version"].as_str()).collect();
        let incomplete: Vec<String> = log["activations"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|a| a["version"].as_str())
            .filter(|v| !complete.contains(v))
            .map(str::to_owned)
            .collect();
        eprintln!(
            "  {} activated ({activations_by_job} activation(s) by the job, {} incomplete version(s) activated), reached the replicas {} ms after; {:?} so far",
            swap.version,
            incomplete.len(),
            ms_list(&swap.propagation_ms),
            load.counts()
        );
        Ok(WorkerKill {
            id,
            job: JobSwap { span: Span { from, to }, uploaded, done, swap },
            state_at_kill,
            round_at_kill: before_kill["last_event"]["round"].clone(),
            new_worker_ready_s: worker.ready_s,
            activations_by_job,
            incomplete,
            log_worker_killed,
        })
    }

    fn json(&self, args: &ScaleArgs, records: &[Record], n: usize, history: Vec<String>) -> Value {
        let j = &self.job;
        json!({
            "window": j.span.window(records, n),
            "uploaded": j.uploaded,
            "state_at_kill": self.state_at_kill,
            "round_at_kill": self.round_at_kill,
            "killed_after_running_s": args.worker_kill_after_s,
            "new_worker_ready_s": self.new_worker_ready_s,
            "job": job_json(&j.done),
            "history": history,
            "activations_by_job": self.activations_by_job,
            "incomplete_versions_activated": self.incomplete,
            "propagation_ms": j.swap.propagation_ms,
            "propagation_steps": j.swap.steps,
            "probes": j.swap.probes,
            "killed_worker_log": server_log_json(&self.log_worker_killed),
        })
    }
}

/// Waits for job `id` to run on `worker`, then `--worker-kill-after-s` later kills the worker;
/// returns the job as the worker last showed it, and the worker's log.
fn kill_mid_job(ctx: &Ctx, worker: &mut Node, id: &str) -> Result<(Value, String)> {
    let (_, running_at) = wait_job(worker, id, ctx.timeout, |s| s == "RUNNING" || terminal(s))?;
    std::thread::sleep(Duration::from_secs_f64(ctx.args.worker_kill_after_s));
    let before_kill = job_on(worker, id)?.context("the worker forgot the job")?;
    let state_at_kill = job_state(&before_kill).to_owned();
    ensure!(
        !terminal(&state_at_kill),
        "job {id} ended {state_at_kill} before the worker was killed: lower --worker-kill-after-s"
    );
    let log_worker_killed = worker.server.log();
    worker.kill9()?;
    eprintln!(
        "  killed the worker {:.1} s after the job was seen RUNNING (state {state_at_kill}, round {})",
        running_at.elapsed().as_secs_f64(),
        before_kill["last_event"]["round"]
    );
    Ok((before_kill, log_worker_killed))
}

/// The requests of the load in flight during `[from, to]`: counts, latency, first errors.
fn fault_window(records: &[Record], from: Instant, to: Instant, clients: usize, others: Option<f64>) -> Value {
    let inside: Vec<&Record> = records.iter().filter(|r| r.overlaps(from, to)).collect();
    let failed: Vec<&str> = inside.iter().filter_map(|r| r.answer.as_ref().err()).map(String::as_str).collect();
    let ok_ms: Vec<f64> = inside.iter().filter(|r| r.answer.is_ok()).map(|r| r.ms()).collect();
    let mut versions = BTreeMap::<&str, usize>::new();
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
