//! The service benchmark's model swaps: rollback / activate round trips between the seed and
//! the adaptation job's version, with clients running and with none, and their latency.

use std::{
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Result, ensure};
use serde_json::{Value, json};

use super::ServiceArgs;
use super::clients::Clients;
use crate::harness::{Record, ServerProcess, estimate, median, min_median_max, percentile, server_log_json};

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
        let reason = "udapose-bench service: swap latency";
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

/// The swaps made with clients running (first the explicit activation of a rejected candidate),
/// and those made with none: `--swap-rounds` round trips each.
fn plans(rounds: usize, explicit: bool, source: &str, candidate: &str) -> (Vec<SwapAction>, Vec<SwapAction>) {
    let round_trips = || {
        (0..rounds).flat_map(|_| {
            [
                SwapAction { rollback: true, target: source.to_owned() },
                SwapAction { rollback: false, target: candidate.to_owned() },
            ]
        })
    };
    let plan: Vec<SwapAction> = explicit
        .then(|| SwapAction { rollback: false, target: candidate.to_owned() })
        .into_iter()
        .chain(round_trips())
        .collect();
    (plan, round_trips().collect())
}

/// The swaps of `plan` with `n` clients running; each swap measured from every client's record.
fn with_clients(
    server: &ServerProcess,
    images: &Arc<Vec<Vec<u8>>>,
    n: usize,
    plan: &[SwapAction],
) -> Result<(Vec<SwapSample>, Vec<Record>)> {
    let clients = Clients::start(server.http, images, n);
    std::thread::sleep(Duration::from_secs(1));
    let times = plan.iter().map(|a| swap_with_clients(server, &clients, a)).collect::<Result<Vec<_>>>()?;
    let records = clients.stop();
    let loaded: Vec<SwapSample> = times.iter().map(|t| t.measure(&records)).collect();
    Ok((loaded, records))
}

/// After job `id` (`job`: its final state) on the adaptation server: swaps between `source`, the
/// seed, and the job's version with `--adapt-clients` clients and with none. Returns the
/// report's `swap` (with `job` as its `job`), or an error value when there is no version.
pub(super) fn measure_swaps(
    args: &ServiceArgs,
    server: &ServerProcess,
    images: &Arc<Vec<Vec<u8>>>,
    source: &str,
    id: &str,
    job: &Value,
    job_ref: Value,
) -> Result<Value> {
    let n = args.adapt_clients;
    let state = job["state"].as_str().unwrap_or("").to_owned();
    let candidate = job["version"].as_str().unwrap_or("").to_owned();
    if !matches!(state.as_str(), "ACTIVATED" | "REJECTED") || candidate.is_empty() {
        let error = format!("job {id} ended {state} without a version to swap to: {}", job["reason"]);
        eprintln!("  no swap measured: {error}");
        return Ok(json!({ "error": error, "server_log": server_log_json(&server.log()) }));
    }
    let explicit = state != "ACTIVATED";
    let active = server.get_json("/v1/models/car")?["version"].as_str().unwrap_or("").to_owned();
    let expected = if explicit { source } else { &candidate };
    ensure!(active == *expected, "after job {id} ended {state}, {active} is active (expected {expected})");
    let (plan, plan_idle) = plans(args.swap_rounds, explicit, source, &candidate);
    eprintln!("  {} swaps between {source} and {candidate} with {n} clients", plan.len());
    let (loaded, records) = with_clients(server, images, n, &plan)?;
    let loaded_errors = records.iter().filter(|r| r.answer.is_err()).count();
    let mut first_errors: Vec<&str> =
        records.iter().filter_map(|r| r.answer.as_ref().err()).map(String::as_str).collect();
    first_errors.truncate(5);
    eprintln!("  {} swaps with no clients", plan_idle.len());
    let quiet = plan_idle.iter().map(|a| swap_idle(server, &images[0], a)).collect::<Result<Vec<_>>>()?;
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
    Ok(json!({
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
        "job": job_ref,
    }))
}
