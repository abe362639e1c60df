//! The service benchmark's servers and background clients: a `udapose-server` with a scratch
//! models dir and store, client threads sending estimates until stopped, and the CPU other
//! processes took meanwhile.

use std::{
    net::SocketAddr,
    path::Path,
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, Ordering},
    },
    thread::JoinHandle,
    time::Instant,
};

use anyhow::Result;
use serde_json::{Value, json};

use crate::harness::{Level, Record, ServerProcess, estimate, machine_busy_ticks, percentile, process_ticks};

impl ServerProcess {
    /// `extra`: more server flags; `verbose`: the server logs at `info` (its own crate) so that
    /// [`ServerProcess::log`] can report model loads and job events.
    pub(super) fn start(
        binary: &Path,
        model: &Path,
        max_batch: usize,
        max_delay_ms: u64,
        extra: &[&str],
        verbose: bool,
    ) -> Result<Self> {
        let tag = if verbose { "-adapt" } else { "" };
        let (batch, delay) = (max_batch.to_string(), max_delay_ms.to_string());
        let flags = [&["--max-batch", batch.as_str(), "--max-delay-ms", delay.as_str()], extra].concat();
        let (server, _grpc) = Self::serve_model(binary, model, &format!("service-{max_batch}{tag}"), &flags, verbose)?;
        Ok(server)
    }
}

/// CPU time in clock ticks (USER_HZ: 100 per second on Linux) of the whole machine, of this
/// process (the clients) and of the server, to tell how much of the machine other processes
/// took during a window.
#[derive(Clone, Copy)]
pub(super) struct Cpu {
    at: Instant,
    busy: u64,
    own: u64,
    server: u64,
}

impl Cpu {
    pub(super) fn now(server_pid: u32) -> Option<Cpu> {
        Some(Cpu {
            at: Instant::now(),
            busy: machine_busy_ticks()?,
            own: process_ticks("self")?,
            server: process_ticks(&server_pid.to_string())?,
        })
    }

    /// Cores that other processes used on average between `self` and `later`.
    fn others(&self, later: &Cpu) -> f64 {
        let ours = (later.own - self.own) + (later.server - self.server);
        let others = (later.busy - self.busy).saturating_sub(ours);
        others as f64 / 100.0 / (later.at - self.at).as_secs_f64()
    }
}

pub(super) fn others_cores(from: Option<Cpu>, to: Option<Cpu>) -> Option<f64> {
    Some(from?.others(&to?))
}

/// Client threads sending estimates back to back (images in rotation) until stopped; every
/// request is recorded with its start, end and answering version.
pub(crate) struct Clients {
    stop: Arc<AtomicBool>,
    records: Arc<Mutex<Vec<Record>>>,
    threads: Vec<JoinHandle<()>>,
}

impl Clients {
    pub(crate) fn start(http: SocketAddr, images: &Arc<Vec<Vec<u8>>>, n: usize) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let records = Arc::new(Mutex::new(Vec::new()));
        let threads = (0..n)
            .map(|t| {
                let (stop, records, images) = (stop.clone(), records.clone(), images.clone());
                std::thread::spawn(move || {
                    for i in (t..).step_by(n) {
                        if stop.load(Ordering::Acquire) {
                            break;
                        }
                        let start = Instant::now();
                        let answer = estimate(http, &images[i % images.len()]);
                        let record = Record { start, end: Instant::now(), answer };
                        records.lock().unwrap_or_else(|p| p.into_inner()).push(record);
                    }
                })
            })
            .collect();
        Clients { stop, records, threads }
    }

    /// The end of the first answer by `version` among the requests finished since `since`.
    pub(super) fn first_answer(&self, version: &str, since: Instant) -> Option<Instant> {
        let records = self.records.lock().unwrap_or_else(|p| p.into_inner());
        records.iter().filter(|r| r.end >= since && r.answered_by(version)).map(|r| r.end).min()
    }

    /// Stops the clients (each finishes its request in flight) and returns every record.
    pub(crate) fn stop(mut self) -> Vec<Record> {
        self.stop.store(true, Ordering::Release);
        for t in std::mem::take(&mut self.threads) {
            let _ = t.join();
        }
        std::mem::take(&mut *self.records.lock().unwrap_or_else(|p| p.into_inner()))
    }
}

impl Drop for Clients {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
    }
}

/// A level's JSON plus its largest and mean latency and the cores other processes used.
pub(super) fn window_json(l: &Level, others: Option<f64>) -> Value {
    let mut v = l.json();
    v["other_processes_cores"] = json!(others);
    v["max_ms"] = json!(percentile(&l.latencies_ms, 1.0));
    v["mean_ms"] = json!(l.latencies_ms.iter().sum::<f64>() / l.latencies_ms.len() as f64);
    v
}
