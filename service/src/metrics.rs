//! Prometheus metrics: latency by category and model version, queue depth, batch sizes, and
//! errors by code. Exposed as text at `/metrics`.

use prometheus::{Encoder, HistogramOpts, HistogramVec, IntCounterVec, IntGaugeVec, Opts, Registry, TextEncoder};

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
        for m in [
            Box::new(latency.clone()) as Box<dyn prometheus::core::Collector>,
            Box::new(requests.clone()),
            Box::new(errors.clone()),
            Box::new(queue_depth.clone()),
            Box::new(batch_size.clone()),
            Box::new(stage.clone()),
        ] {
            registry.register(m).expect("metric names are unique");
        }
        Metrics { registry, latency, requests, errors, queue_depth, batch_size, stage }
    }

    /// The text exposition format.
    pub fn render(&self) -> String {
        let mut out = Vec::new();
        TextEncoder::new().encode(&self.registry.gather(), &mut out).expect("encoding metrics into memory");
        String::from_utf8(out).unwrap_or_default()
    }
}
