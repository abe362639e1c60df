//! Adaptation jobs and versions across the fleet: a job's state on a node, waiting for it, and
//! how a new version reaches every replica (probes, and each replica's log).

use std::{
    collections::BTreeMap,
    time::{Duration, Instant, SystemTime, UNIX_EPOCH},
};

use anyhow::{Context, Result, anyhow, bail, ensure};
use serde_json::{Value, json};

use super::fleet::Node;
use crate::harness::{estimate, post_or_get};

pub(super) fn now_epoch() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// The instant of an epoch time in seconds (the server's timestamps), at most `now`.
pub(super) fn instant_of(epoch_s: f64) -> Instant {
    let age = (now_epoch() - epoch_s).max(0.0);
    Instant::now().checked_sub(Duration::from_secs_f64(age)).unwrap_or_else(Instant::now)
}

/// A job as a node sees it (`None` while it does not know it yet).
pub(super) fn job_on(node: &Node, id: &str) -> Result<Option<Value>> {
    let (status, body) = post_or_get(node.http(), "GET", &format!("/v1/jobs/{id}"), b"")?;
    match status {
        200 => Ok(Some(serde_json::from_str(&body).with_context(|| format!("job {id}: {body}"))?)),
        404 => Ok(None),
        _ => bail!("GET /v1/jobs/{id} on {}: {status} {body}", node.name),
    }
}

pub(super) fn job_state(job: &Value) -> &str {
    job["state"].as_str().unwrap_or("")
}

pub(super) fn terminal(state: &str) -> bool {
    !matches!(state, "" | "QUEUED" | "RUNNING" | "VALIDATING")
}

/// Polls job `id` on `node` every 100 ms until `done(state)`; returns the job and when that was
/// seen.
pub(super) fn wait_job(
    node: &Node,
    id: &str,
    timeout: Duration,
    done: impl Fn(&str) -> bool,
) -> Result<(Value, Instant)> {
    let deadline = Instant::now() + timeout;
    let mut last = String::new();
    loop {
        if let Some(job) = job_on(node, id)? {
            let state = job_state(&job).to_owned();
            if state != last {
                eprintln!("    job {id} on {}: {state}", node.name);
                last.clone_from(&state);
            }
            if done(&state) {
                return Ok((job, Instant::now()));
            }
        }
        ensure!(
            Instant::now() < deadline,
            "job {id} still {last:?} on {} after {timeout:?}: {}",
            node.name,
            node.server.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A job's version and how it reached the replicas.
pub(super) struct Swap {
    pub(super) version: String,
    /// Per replica, ms from the activation to its first answer by the version.
    pub(super) propagation_ms: Vec<f64>,
    pub(super) steps: Vec<Value>,
    pub(super) probes: Vec<Value>,
}

/// Waits for job `id` on `worker` to end ACTIVATED, then for its version to reach `nodes`.
pub(super) fn activated_swap(
    worker: &Node,
    id: &str,
    nodes: &[&Node],
    image: &[u8],
    timeout: Duration,
) -> Result<(Value, Swap)> {
    let (done, _) = wait_job(worker, id, timeout, terminal)?;
    ensure!(
        job_state(&done) == "ACTIVATED",
        "job {id} ended {}: {}\n{}",
        job_state(&done),
        done["reason"],
        worker.server.log()
    );
    let version = done["version"].as_str().context("the job has no version")?.to_owned();
    let epoch = done["updated"].as_f64().unwrap_or_else(now_epoch);
    let (propagation_ms, probes) = wait_serving(nodes, &version, instant_of(epoch), image, timeout)?;
    let steps = swap_steps(nodes, &version, epoch);
    Ok((done, Swap { version, propagation_ms, steps, probes }))
}

/// Waits until each node answers an estimate with `version` (its registry is polled every
/// 50 ms, then estimates confirm it); returns each node's delay after `since`, in ms.
/// The probes' estimates (sent and answered, ms after `since`, and the answering version) go to
/// the second value, per node.
pub(super) fn wait_serving(
    nodes: &[&Node],
    version: &str,
    since: Instant,
    image: &[u8],
    timeout: Duration,
) -> Result<(Vec<f64>, Vec<Value>)> {
    let deadline = Instant::now() + timeout;
    let ms = |t: Instant| t.saturating_duration_since(since).as_secs_f64() * 1e3;
    let results: Vec<(f64, Value)> = std::thread::scope(|s| {
        let probes: Vec<_> = nodes
            .iter()
            .map(|n| {
                s.spawn(move || -> Result<(f64, Value)> {
                    let mut tries = Vec::new();
                    loop {
                        let active = post_or_get(n.http(), "GET", "/v1/models/car", b"")
                            .ok()
                            .and_then(|(_, body)| serde_json::from_str::<Value>(&body).ok())
                            .and_then(|v| v["version"].as_str().map(str::to_owned));
                        if active.as_deref() == Some(version) {
                            let sent = Instant::now();
                            let answer = estimate(n.http(), image);
                            let end = Instant::now();
                            tries.push(json!([ms(sent), ms(end), answer.as_deref().unwrap_or("failed")]));
                            if answer.as_deref() == Ok(version) {
                                return Ok((ms(end), json!({ "name": n.name, "estimates": tries })));
                            }
                        }
                        ensure!(Instant::now() < deadline, "{} does not serve {version} after {timeout:?}", n.name);
                        std::thread::sleep(Duration::from_millis(50));
                    }
                })
            })
            .collect();
        probes.into_iter().map(|p| p.join().map_err(|_| anyhow!("a probe panicked"))?).collect::<Result<_>>()
    })?;
    Ok(results.into_iter().unzip())
}

/// Seconds since the Unix epoch of a log line's timestamp (`2026-01-02T03:04:05.678901Z ...`,
/// tracing's default format, UTC).
pub(super) fn log_epoch(line: &str) -> Option<f64> {
    let stamp = line.split_whitespace().next()?.strip_suffix('Z')?;
    let (date, time) = stamp.split_once('T')?;
    let mut d = date.split('-').map(|x| x.parse::<i64>().ok());
    let (y, m, day) = (d.next()??, d.next()??, d.next()??);
    let mut t = time.split(':');
    let (h, min, sec) =
        (t.next()?.parse::<f64>().ok()?, t.next()?.parse::<f64>().ok()?, t.next()?.parse::<f64>().ok()?);
    // Days from 1970-01-01 to the civil date (Howard Hinnant's days_from_civil).
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let doy = (153 * (m + if m > 2 { -3 } else { 9 }) + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    Some(days as f64 * 86_400.0 + h * 3600.0 + min * 60.0 + sec)
}

/// Per node, from its log, after an activation at `since` (epoch seconds): when it saw `version`
/// become active (its poll, or its own rollback) and how long its inference worker took to load it.
pub(super) fn swap_steps(nodes: &[&Node], version: &str, since: f64) -> Vec<Value> {
    nodes
        .iter()
        .map(|n| {
            let log = n.server.log();
            let lines = || log.lines().filter(|l| l.contains(version)).filter_map(|l| Some((log_epoch(l)?, l)));
            let seen = lines().find(|(t, l)| *t >= since - 0.5 && l.contains("new active version")).map(|(t, _)| t);
            let loaded = seen.and_then(|s| lines().find(|(t, l)| *t >= s && l.contains("model loaded")));
            let load_ms =
                loaded.and_then(|(_, l)| l.split_whitespace().find_map(|w| w.strip_prefix("ms="))?.parse::<f64>().ok());
            json!({
                "name": n.name,
                "seen_ms": seen.map(|s| (s - since) * 1e3),
                "loaded_ms": loaded.map(|(t, _)| (t - since) * 1e3),
                "load_ms": load_ms,
            })
        })
        .collect()
}

/// A job's history (`GET /v1/jobs/{id}/events`, Server-Sent Events that end after the terminal
/// one): each event's state and message.
pub(super) fn job_history(node: &Node, id: &str) -> Vec<String> {
    let Ok((200, body)) = post_or_get(node.http(), "GET", &format!("/v1/jobs/{id}/events"), b"") else {
        return Vec::new();
    };
    body.lines()
        .filter_map(|l| l.strip_prefix("data:"))
        .filter_map(|d| serde_json::from_str::<Value>(d.trim()).ok())
        .map(|e| format!("{}: {}", e["state"].as_str().unwrap_or("?"), e["message"].as_str().unwrap_or("")))
        .collect()
}

/// Uploads `targets` round-robin to `nodes`; returns the answers' statuses.
pub(super) fn upload(nodes: &[&Node], targets: &[Vec<u8>]) -> Result<BTreeMap<String, usize>> {
    let mut statuses = BTreeMap::new();
    for (i, t) in targets.iter().enumerate() {
        let node = nodes[i % nodes.len()];
        let (status, body) = post_or_get(node.http(), "POST", "/v1/adapt/car/images", t)?;
        ensure!(status == 200, "uploading a target image to {}: {status} {body}", node.name);
        let answer: Value = serde_json::from_str(&body).with_context(|| format!("upload answer {body}"))?;
        *statuses.entry(answer["results"][0]["status"].as_str().unwrap_or("?").to_owned()).or_default() += 1;
    }
    Ok(statuses)
}
