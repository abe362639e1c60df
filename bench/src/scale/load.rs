//! The scale benchmark's load: estimates through the gRPC client library over the replicas, as
//! levels of a fixed number of requests or back to back until stopped.

use std::{
    net::SocketAddr,
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, AtomicUsize, Ordering},
    },
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow};
use serde_json::{Value, json};
use tokio::runtime::Runtime;

use super::cpu::{Snapshot, per_node};
use super::fleet::Node;
use crate::harness::{Level, Record, fmt_ms, summary};

/// A client over `endpoints` (gRPC), with the library's failover.
pub(super) fn connect(rt: &Runtime, endpoints: &[SocketAddr]) -> Result<udapose_client::Client> {
    let names: Vec<String> = endpoints.iter().map(ToString::to_string).collect();
    let mut options = udapose_client::ClientOptions::new(names[0].clone());
    options.endpoints = names;
    rt.block_on(udapose_client::Client::connect_with(options)).context("connecting the client")
}

/// One estimate through `client`: the answering version, or the error.
pub(super) async fn grpc_estimate(client: &udapose_client::Client, image: &[u8]) -> Result<String, String> {
    match client.estimate(udapose_client::request("car", image.to_vec())).await {
        Ok(r) => Ok(r.model_version),
        Err(e) => Err(e.to_string()),
    }
}

/// `requests` estimates through `client`, `concurrency` in flight (images in rotation); none
/// sent after `limit` (the level then holds fewer).
pub(super) fn level(
    rt: &Runtime,
    client: &udapose_client::Client,
    images: &Arc<Vec<Vec<u8>>>,
    concurrency: usize,
    requests: usize,
    limit: Duration,
) -> Level {
    let next = Arc::new(AtomicUsize::new(0));
    let started = Instant::now();
    let deadline = started + limit;
    let results: Vec<(bool, f64)> = rt.block_on(async {
        let tasks: Vec<_> = (0..concurrency)
            .map(|_| {
                let (client, images, next) = (client.clone(), images.clone(), next.clone());
                tokio::spawn(async move {
                    let mut out = Vec::new();
                    loop {
                        let r = next.fetch_add(1, Ordering::Relaxed);
                        if r >= requests || Instant::now() > deadline {
                            break out;
                        }
                        let sent = Instant::now();
                        let ok = grpc_estimate(&client, &images[r % images.len()]).await.is_ok();
                        out.push((ok, sent.elapsed().as_secs_f64() * 1e3));
                    }
                })
            })
            .collect();
        let mut all = Vec::new();
        for t in tasks {
            all.extend(t.await.unwrap_or_default());
        }
        all
    });
    Level {
        concurrency,
        requests: results.len(),
        errors: results.iter().filter(|(ok, _)| !ok).count(),
        seconds: started.elapsed().as_secs_f64(),
        latencies_ms: results.iter().filter(|(ok, _)| *ok).map(|(_, ms)| *ms).collect(),
    }
}

/// Estimates through the client, back to back from `n` tasks, until stopped; every request
/// recorded with its start, end and answering version.
pub(super) struct Load {
    stop: Arc<AtomicBool>,
    records: Arc<Mutex<Vec<Record>>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Load {
    pub(super) fn start(rt: &Runtime, client: &udapose_client::Client, images: &Arc<Vec<Vec<u8>>>, n: usize) -> Load {
        let stop = Arc::new(AtomicBool::new(false));
        let records = Arc::new(Mutex::new(Vec::new()));
        let tasks = (0..n)
            .map(|t| {
                let (client, images, stop, records) = (client.clone(), images.clone(), stop.clone(), records.clone());
                rt.spawn(async move {
                    for i in (t..).step_by(n) {
                        if stop.load(Ordering::Acquire) {
                            break;
                        }
                        let start = Instant::now();
                        let answer = grpc_estimate(&client, &images[i % images.len()]).await;
                        let record = Record { start, end: Instant::now(), answer };
                        records.lock().unwrap_or_else(|p| p.into_inner()).push(record);
                    }
                })
            })
            .collect();
        Load { stop, records, tasks }
    }

    /// (answered, failed) so far.
    pub(super) fn counts(&self) -> (usize, usize) {
        let records = self.records.lock().unwrap_or_else(|p| p.into_inner());
        let failed = records.iter().filter(|r| r.answer.is_err()).count();
        (records.len() - failed, failed)
    }

    pub(super) fn stop(self, rt: &Runtime) -> Vec<Record> {
        self.stop.store(true, Ordering::Release);
        rt.block_on(async {
            for t in self.tasks {
                let _ = t.await;
            }
        });
        std::mem::take(&mut *self.records.lock().unwrap_or_else(|p| p.into_inner()))
    }
}

/// Throughput and latency through one client over the first 1, 2 and 3 of `replicas`, with
/// every process's requests and CPU (`idle`: other processes of the fleet, shown too); the
/// report's values and the Markdown rows of the per-process table.
pub(super) fn replica_levels(
    rt: &Runtime,
    replicas: &[Node],
    idle: &[&Node],
    images: &Arc<Vec<Vec<u8>>>,
    concurrency: usize,
    (requests, limit): (usize, Duration),
    store_pid: u32,
) -> Result<(Vec<Value>, String)> {
    let mut levels = Vec::new();
    let mut md = String::new();
    for k in 1..=replicas.len() {
        let endpoints: Vec<SocketAddr> = replicas[..k].iter().map(|r| r.grpc).collect();
        let client = connect(rt, &endpoints)?;
        rt.block_on(async {
            for i in 0..2 * k {
                grpc_estimate(&client, &images[i % images.len()]).await.map_err(|e| anyhow!("warm-up: {e}"))?;
            }
            Ok::<_, anyhow::Error>(())
        })?;
        let all: Vec<&Node> = replicas.iter().chain(idle.iter().copied()).collect();
        let before = Snapshot::take(&all, store_pid);
        let l = level(rt, &client, images, concurrency, requests, limit);
        let after = Snapshot::take(&all, store_pid);
        let (rows, machine) = per_node(&all, &before, &after);
        eprintln!("{k} replica(s), {concurrency} in flight: {}", summary(&l));
        for row in &rows {
            let s = format!(
                "| {k} | {} | {} | {} | {} | {} | {} |\n",
                row["name"].as_str().unwrap_or(""),
                row["grpc_answered"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.0}")),
                row["throughput_per_s"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.2}")),
                fmt_ms(&row["server_mean_ms"]),
                row["cpu_s"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.1}")),
                row["cpu_cores"].as_f64().map_or_else(|| "–".into(), |v| format!("{v:.2}")),
            );
            eprint!("  {}", s.trim_start_matches("| "));
            md.push_str(&s);
        }
        let mut v = l.json();
        v["replicas"] = json!(k);
        v["per_process"] = json!(rows);
        v["machine"] = machine;
        levels.push(v);
    }
    Ok((levels, md))
}
