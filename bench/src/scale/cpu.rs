//! CPU time and answered requests of every process of the scale benchmark, from `/proc` and
//! each server's `/metrics`.

use std::{fs, net::SocketAddr, time::Instant};

use serde_json::{Value, json};

use super::HZ;
use super::fleet::Node;
use crate::harness::{machine_busy_ticks, post_or_get, process_ticks};

/// Successful gRPC estimates a server answered and the server-side latency sum, from `/metrics`.
#[derive(Clone, Copy, Default)]
pub(super) struct Served {
    pub(super) grpc_ok: f64,
    latency_sum_s: f64,
    latency_count: f64,
}

pub(super) fn served(http: SocketAddr) -> Option<Served> {
    let (status, text) = post_or_get(http, "GET", "/metrics", b"").ok()?;
    if status != 200 {
        return None;
    }
    let mut s = Served::default();
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let Some((name, value)) = line.rsplit_once(' ') else { continue };
        let Ok(value) = value.parse::<f64>() else { continue };
        if name.starts_with("udapose_requests_total{")
            && name.contains("code=\"OK\"")
            && name.contains("transport=\"grpc\"")
        {
            s.grpc_ok += value;
        } else if name.starts_with("udapose_estimate_duration_seconds_sum{") {
            s.latency_sum_s += value;
        } else if name.starts_with("udapose_estimate_duration_seconds_count{") {
            s.latency_count += value;
        }
    }
    Some(s)
}

/// The CPU ticks of this process's children that have ended and been waited for (cutime +
/// cstime): the servers killed so far.
pub(super) fn reaped_children_ticks() -> Option<u64> {
    let stat = fs::read_to_string("/proc/self/stat").ok()?;
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    Some(fields.get(13)?.parse::<u64>().ok()? + fields.get(14)?.parse::<u64>().ok()?)
}

/// CPU ticks and answered requests of every process at one moment.
pub(super) struct Snapshot {
    pub(super) at: Instant,
    busy: Option<u64>,
    /// This process (the client).
    own: Option<u64>,
    /// The servers killed so far, and the store.
    reaped: Option<u64>,
    store: Option<u64>,
    /// Per node: CPU ticks and `/metrics` counters.
    nodes: Vec<(Option<u64>, Option<Served>)>,
}

impl Snapshot {
    pub(super) fn take(nodes: &[&Node], store_pid: u32) -> Snapshot {
        Snapshot {
            at: Instant::now(),
            busy: machine_busy_ticks(),
            own: process_ticks("self"),
            reaped: reaped_children_ticks(),
            store: process_ticks(&store_pid.to_string()),
            nodes: nodes.iter().map(|n| (process_ticks(&n.pid()), served(n.http()))).collect(),
        }
    }

    /// Everything this benchmark runs: itself, its servers (alive or killed) and the store.
    pub(super) fn ours(&self) -> u64 {
        self.own.unwrap_or(0)
            + self.reaped.unwrap_or(0)
            + self.store.unwrap_or(0)
            + self.nodes.iter().filter_map(|(t, _)| *t).sum::<u64>()
    }

    /// Cores that other processes used on average since `from`.
    pub(super) fn others_cores_since(&self, from: &Snapshot) -> Option<f64> {
        let busy = self.busy?.saturating_sub(from.busy?);
        Some(
            busy.saturating_sub(self.ours().saturating_sub(from.ours())) as f64
                / HZ
                / (self.at - from.at).as_secs_f64(),
        )
    }
}

/// Per node between two snapshots: requests answered, req/s, server-side mean latency, CPU.
pub(super) fn per_node(nodes: &[&Node], from: &Snapshot, to: &Snapshot) -> (Vec<Value>, Value) {
    let seconds = (to.at - from.at).as_secs_f64();
    let rows = nodes
        .iter()
        .zip(from.nodes.iter().zip(&to.nodes))
        .map(|(n, ((t0, s0), (t1, s1)))| {
            let ticks = t0.zip(*t1).map(|(a, b)| b.saturating_sub(a));
            let (answered, mean_ms) = match (s0, s1) {
                (Some(a), Some(b)) => {
                    let count = b.latency_count - a.latency_count;
                    (
                        Some(b.grpc_ok - a.grpc_ok),
                        (count > 0.0).then(|| (b.latency_sum_s - a.latency_sum_s) / count * 1e3),
                    )
                }
                _ => (None, None),
            };
            json!({
                "name": n.name,
                "grpc_answered": answered,
                "throughput_per_s": answered.map(|a| a / seconds),
                "server_mean_ms": mean_ms,
                "cpu_s": ticks.map(|t| t as f64 / HZ),
                "cpu_cores": ticks.map(|t| t as f64 / HZ / seconds),
            })
        })
        .collect();
    let own = from.own.zip(to.own).map(|(a, b)| b.saturating_sub(a));
    let store = from.store.zip(to.store).map(|(a, b)| b.saturating_sub(a));
    let busy = from.busy.zip(to.busy).map(|(a, b)| b.saturating_sub(a));
    let machine = json!({
        "seconds": seconds,
        "client_cpu_s": own.map(|o| o as f64 / HZ),
        "client_cpu_cores": own.map(|o| o as f64 / HZ / seconds),
        "store_cpu_cores": store.map(|o| o as f64 / HZ / seconds),
        "machine_busy_cores": busy.map(|b| b as f64 / HZ / seconds),
        "other_processes_cores": to.others_cores_since(from),
    });
    (rows, machine)
}

/// A snapshot of the replicas, the worker and the store.
pub(super) fn snapshot(replicas: &[Node], worker: &Node, store_pid: u32) -> Snapshot {
    Snapshot::take(&replicas.iter().chain([worker]).collect::<Vec<_>>(), store_pid)
}
