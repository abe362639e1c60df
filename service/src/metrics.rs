//! Prometheus metrics: latency by category and model version, queue depth, batch sizes, and
//! errors by code. Exposed as text at `/metrics`.

use prometheus::{
    Encoder, HistogramOpts, HistogramVec, IntCounterVec, IntGauge, IntGaugeVec, Opts, Registry, TextEncoder,
};

pub struct Metrics {
    registry: Registry,
    /// Seconds from arrival to answer of successful estimates.
    pub latency: HistogramVec,
    /// Requests answered, by transport and outcome code ("OK" or a gRPC code name).
    pub requests: IntCounterVec,
    /// Failed requests by code.
    pub errors: IntCounterVec,
    /// Jobs waiting for a worker, per category.
    pub queue_depth: IntGaugeVec,
    /// Crops per backbone batch, per category.
    pub batch_size: HistogramVec,
    /// Seconds per stage (decode, queue, crop, backbone, solver) of successful estimates.
    pub stage: HistogramVec,
    /// Bytes of the models a category's workers hold (each worker has its own copy).
    pub model_bytes: IntGaugeVec,
    /// The server's resident set size, read from /proc when the metrics are rendered.
    resident_bytes: IntGauge,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let registry = Registry::new_custom(Some("udapose".into()), None).expect("a valid prefix");
        let latency_buckets = vec![0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0];
        let latency = HistogramVec::new(
            HistogramOpts::new("estimate_duration_seconds", "Estimate latency from arrival to answer")
                .buckets(latency_buckets.clone()),
            &["category", "version"],
        )
        .expect("valid metric");
        let requests = IntCounterVec::new(
            Opts::new("requests_total", "Estimate requests by transport and code"),
            &["transport", "code"],
        )
        .expect("valid metric");
        let errors =
            IntCounterVec::new(Opts::new("errors_total", "Failed requests by code"), &["code"]).expect("valid metric");
        let queue_depth =
            IntGaugeVec::new(Opts::new("queue_depth", "Jobs waiting for an inference worker"), &["category"])
                .expect("valid metric");
        let batch_size = HistogramVec::new(
            HistogramOpts::new(
                "batch_size",
                "Crops per worker batch (its backbone passes take at most --max-batch each)",
            )
            .buckets(vec![1.0, 2.0, 4.0, 8.0, 16.0, 32.0]),
            &["category"],
        )
        .expect("valid metric");
        let stage = HistogramVec::new(
            HistogramOpts::new("stage_duration_seconds", "Time per stage of successful estimates")
                .buckets(latency_buckets),
            &["stage"],
        )
        .expect("valid metric");
        let model_bytes = IntGaugeVec::new(
            Opts::new(
                "model_bytes",
                "Bytes of the models a category's workers hold: tensors and solver data, a copy per worker",
            ),
            &["category"],
        )
        .expect("valid metric");
        let resident_bytes =
            IntGauge::new("resident_bytes", "Resident set size of the server process (all categories)")
                .expect("valid metric");
        for m in [
            Box::new(latency.clone()) as Box<dyn prometheus::core::Collector>,
            Box::new(model_bytes.clone()),
            Box::new(resident_bytes.clone()),
            Box::new(requests.clone()),
            Box::new(errors.clone()),
            Box::new(queue_depth.clone()),
            Box::new(batch_size.clone()),
            Box::new(stage.clone()),
        ] {
            registry.register(m).expect("metric names are unique");
        }
        Metrics { registry, latency, requests, errors, queue_depth, batch_size, stage, model_bytes, resident_bytes }
    }

    /// The text exposition format.
    pub fn render(&self) -> String {
        if let Some(rss) = resident_set_bytes() {
            self.resident_bytes.set(rss as i64);
        }
        let mut out = Vec::new();
        TextEncoder::new().encode(&self.registry.gather(), &mut out).expect("encoding metrics into memory");
        String::from_utf8(out).unwrap_or_default()
    }
}

/// The process's resident set size (Linux: /proc/self/statm's second field, in pages).
fn resident_set_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    // SAFETY: sysconf reads a constant of the system; no memory is passed.
    let page = u64::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).ok()?;
    Some(pages * page)
}
