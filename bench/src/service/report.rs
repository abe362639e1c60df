//! The service benchmark's Markdown: the batching levels and the ceiling, the latency during
//! adaptation, and the model swap.

use serde_json::Value;

use super::ServiceArgs;
use super::adapt::WARM_UP;
use super::ceiling::Ceiling;
use crate::harness::{Level, fmt_ms};

pub(super) fn markdown(
    args: &ServiceArgs,
    report: &Value,
    modes: &[(&str, usize, Vec<Level>)],
    crop: [usize; 2],
    ceiling: Option<&Ceiling>,
    best: f64,
) -> String {
    let m = &report["machine"];
    let mut md = format!(
        "# Service benchmark\n\n`{}`\n\nModel `{}` ({}×{} crops), {} distinct PNG crops from `{}`, {} requests per level \
         after 4 warm-up requests; HTTP/1.1 POST `/v1/pose/car`, one connection per request, on loopback. Machine: {}, \
         {} threads (torch {}), device {}; load average {} before, {} after. Commit `{}`.{}\n\n",
        report["command"].as_str().unwrap_or(""),
        args.model.display(),
        crop[0],
        crop[1],
        report["images"]["distinct"],
        args.images.display(),
        args.requests,
        m["cpu"].as_str().unwrap_or(""),
        m["threads"],
        m["torch_threads"],
        m["device"].as_str().unwrap_or(""),
        m["load_average_before"].as_str().unwrap_or(""),
        m["load_average_after"].as_str().unwrap_or(""),
        report["commit"].as_str().unwrap_or(""),
        args.note.as_ref().map(|n| format!(" Note: {n}.")).unwrap_or_default(),
    );
    if modes.is_empty() {
        md.push_str("The batching levels were skipped (`--skip-batching-levels`).\n");
    } else {
        md.push_str("| batching | clients | req/s | p50 (ms) | p99 (ms) | errors |\n|---|---:|---:|---:|---:|---:|\n");
    }
    for (name, max_batch, levels) in modes {
        for l in levels {
            md.push_str(&format!(
                "| {name} (max {max_batch}, {} ms) | {} | {:.2} | {:.0} | {:.0} | {} |\n",
                if *max_batch > 1 { args.max_delay_ms } else { 0 },
                l.concurrency,
                l.throughput(),
                l.percentile(0.5),
                l.percentile(0.99),
                l.errors
            ));
        }
    }
    let Some(c) = ceiling else {
        md.push_str("\nThe ceiling was skipped (`--skip-ceiling`).\n");
        return md;
    };
    let (backbone_ms, engine_ms) = (1e3 / c.batch1, 1e3 / c.engine);
    md.push_str(&format!(
        "\n**Ceiling**, measured in the same run with the server stopped: the backbone alone runs {:.2} crops/s at \
         batch 1 and {:.2} crops/s in passes of {}; the engine alone (backbone + solver, one image after the other, \
         no I/O) {:.2} images/s, i.e. {engine_ms:.1} ms per image of which the backbone is {backbone_ms:.1} ms and the \
         render-and-compare solver the other {:.1} ms. The best service throughput, {best:.2} req/s, is {:.0}% of \
         the engine's sequential rate. **Throughput ratio** (the most clients with batching on, over the backbone \
         alone in passes of {}): **{:.2}** (the solver runs on the same cores, so it is the gap to 1).\n",
        c.batch1,
        c.batched,
        args.max_batch,
        c.engine,
        engine_ms - backbone_ms,
        100.0 * best / c.engine,
        args.max_batch,
        report["throughput_ratio"].as_f64().unwrap_or(f64::NAN),
    ));
    md
}

/// The Markdown section of the report's `adaptation` (empty when skipped).
pub(super) fn adaptation_markdown(report: &Value) -> String {
    let a = &report["adaptation"];
    if a.is_null() {
        return String::new();
    }
    adaptation_setup_markdown(report) + &adaptation_results_markdown(a)
}

/// How the latency during adaptation is measured.
fn adaptation_setup_markdown(report: &Value) -> String {
    let a = &report["adaptation"];
    let t = &a["targets"];
    let statuses = t["statuses"]
        .as_object()
        .map(|m| m.iter().map(|(k, v)| format!("{v} {k}")).collect::<Vec<_>>().join(", "))
        .unwrap_or_default();
    format!(
        "\n## Latency during adaptation\n\n`{}`\n\nA third server, batching on (`--max-batch {}`, {} ms) with `{}` so \
         that no job starts by itself. {} clients send estimates back to back (the crops above, one connection per \
         request): after {} s of warm-up, for {} s with the server idle; then {} target images from `{}` are uploaded ({statuses}; \
         {:.1} s), a job is started through `POST /v1/adapt/car/jobs`, and the same clients run until it ends; then \
         again idle for as long. Only requests that start and finish while the polled job state (every 100 ms) is \
         RUNNING or VALIDATING count as during adaptation; the idle baseline pools the windows before and after the \
         job, since other load on the machine drifts. The machine has {} threads: the job's pseudo-labelling and \
         training compete with inference for the same cores, which is what this measures; *other processes* is the \
         CPU that processes other than this benchmark and its server took during each window (from `/proc`), so a \
         window with a large value was disturbed from outside (load average: {}).\n\n",
        report["command"].as_str().unwrap_or(""),
        a["server"]["max_batch"],
        a["server"]["max_delay_ms"],
        a["server"]["flags"].as_str().unwrap_or(""),
        a["clients"],
        WARM_UP.as_secs(),
        a["idle_seconds"],
        t["sent"],
        t["folder"].as_str().unwrap_or(""),
        t["upload_seconds"].as_f64().unwrap_or(f64::NAN),
        report["machine"]["threads"],
        ["idle_before_start", "idle_before_end", "job_start", "job_end", "idle_after_end"]
            .iter()
            .filter_map(|k| a["load_average"][k].as_str().map(|v| format!("{v} at {}", k.replace('_', " "))))
            .collect::<Vec<_>>()
            .join(", "),
    )
}

/// One window of the adaptation table (empty when it was not measured).
fn window_row(name: &str, l: &Value) -> String {
    if l.is_null() {
        return String::new();
    }
    format!(
        "| {name} | {:.1} | {} | {} | {:.2} | {} | {} | {} | {} |\n",
        l["seconds"].as_f64().unwrap_or(f64::NAN),
        l["requests"],
        l["errors"],
        l["throughput_per_s"].as_f64().unwrap_or(f64::NAN),
        fmt_ms(&l["p50_ms"]),
        fmt_ms(&l["p99_ms"]),
        fmt_ms(&l["max_ms"]),
        l["other_processes_cores"].as_f64().map_or_else(|| "–".into(), |c| format!("{c:.2}")),
    )
}

/// The table of the idle and adaptation windows, their ratios, and the job.
fn adaptation_results_markdown(a: &Value) -> String {
    let j = &a["job"];
    let overrides = match j["overrides"].as_object().filter(|o| !o.is_empty()) {
        Some(o) => format!(" (overrides `{}`)", Value::Object(o.clone())),
        None => String::new(),
    };
    format!(
        "| phase | seconds | requests | errors | req/s | p50 (ms) | p99 (ms) | max (ms) | other processes (cores) |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|\n{}{}{}{}{}{}\n\
         **p99 during adaptation / idle: {:.2}×** (against the idle window before the job alone {:.2}×, after it \
         {:.2}×; p50 {:.2}×, throughput {:.2}×); {} requests failed while the job ran.\n\n\
         Job `{}`: {} rounds of at most {}{overrides} on {} images, {} held out for the gate; {:.1} s from creation to \
         {} ({:.1} s seen RUNNING, {:.1} s VALIDATING); last fired ratio {:.3}. Outcome: {}.\n",
        window_row("idle (before + after the job)", &a["idle"]),
        window_row("— idle before", &a["idle_before"]),
        window_row("— idle after", &a["idle_after"]),
        window_row("**during adaptation** (RUNNING + VALIDATING)", &a["during_adaptation"]),
        window_row("— RUNNING (adapting)", &a["phases"]["running"]),
        window_row("— VALIDATING (gate)", &a["phases"]["validating"]),
        a["p99_ratio"].as_f64().unwrap_or(f64::NAN),
        a["p99_ratio_vs_idle_before"].as_f64().unwrap_or(f64::NAN),
        a["p99_ratio_vs_idle_after"].as_f64().unwrap_or(f64::NAN),
        a["p50_ratio"].as_f64().unwrap_or(f64::NAN),
        a["throughput_ratio"].as_f64().unwrap_or(f64::NAN),
        a["errors_during_job"],
        j["id"].as_str().unwrap_or(""),
        j["rounds"],
        j["max_rounds"],
        j["images_used"],
        j["images_held_out"],
        j["seconds"].as_f64().unwrap_or(f64::NAN),
        j["state"].as_str().unwrap_or(""),
        j["running_seconds"].as_f64().unwrap_or(f64::NAN),
        j["validating_seconds"].as_f64().unwrap_or(f64::NAN),
        j["fired_ratio"].as_f64().unwrap_or(f64::NAN),
        j["reason"].as_str().unwrap_or(""),
    )
}

/// The Markdown section of the report's `swap` (empty when skipped).
pub(super) fn swap_markdown(report: &Value) -> String {
    let s = &report["swap"];
    if s.is_null() {
        return String::new();
    }
    if let Some(error) = s["error"].as_str() {
        return format!("\n## Model swap\n\nNot measured: {error}.\n");
    }
    let (w, q, log) = (&s["with_clients"], &s["no_clients"], &s["server_log"]);
    let loads = &log["model_loads_after_start_ms"];
    let explicit = if s["explicit_activation"].as_bool() == Some(true) {
        "The gate rejected the job's version, so the first swap activates it explicitly \
         (`POST /v1/models/car/activate`); then "
            .to_string()
    } else {
        "The job activated its version itself; then ".to_string()
    };
    let problems = log["first_warnings_and_errors"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_str).map(|l| format!("\n    {l}")).collect::<String>())
        .unwrap_or_default();
    format!(
        "\n## Model swap\n\n`{}`\n\nOn the same server, after the job: swaps between the seed `{}` and the job's \
         version `{}`. {explicit}{} rollback (`POST /v1/models/car/rollback`) / activate round trips with {} clients \
         sending estimates back to back, {} ms apart after each swap's first new answer, and the same round trips with \
         no clients. **Swap latency**: from the activation call's HTTP response to the first estimate answered by the \
         new version (`model_version`); with no clients, the answer to the first request sent after the response \
         (the worker loads the new version on its thread when a batch arrives, so that request waits for the load).\n\n\
         | clients | swaps | min (ms) | median (ms) | max (ms) | failed requests | largest request latency around a swap (ms) |\n\
         |---|---:|---:|---:|---:|---:|---:|\n\
         | {} | {} | {} | {} | {} | {} | {} |\n\
         | none | {} | {} | {} | {} | {} | {} |\n\n\
         With no clients, the requests right after the first one take {} ms (median), so the load adds about \
         {:.0} ms. Around a swap with clients: the largest latency of a request in flight between the call and the \
         first new answer; {} answers came from the old version to requests sent after the call's response. The \
         server logged {} model loads after its start (the job's activation and the swaps): {} / {} / {} ms \
         (min / median / max), and {} warnings or errors.{}\n",
        report["command"].as_str().unwrap_or(""),
        s["from_version"].as_str().unwrap_or(""),
        s["to_version"].as_str().unwrap_or(""),
        report["swap"]["no_clients"]["samples"].as_u64().unwrap_or(0) / 2,
        s["clients"],
        fmt_ms(&w["settle_ms"]),
        s["clients"],
        s["samples"],
        fmt_ms(&s["latency_ms"]["min"]),
        fmt_ms(&s["latency_ms"]["median"]),
        fmt_ms(&s["latency_ms"]["max"]),
        w["errors"],
        fmt_ms(&s["max_request_ms_during_swap"]),
        q["samples"],
        fmt_ms(&q["latency_ms"]["min"]),
        fmt_ms(&q["latency_ms"]["median"]),
        fmt_ms(&q["latency_ms"]["max"]),
        q["errors"],
        fmt_ms(&q["latency_ms"]["max"]),
        fmt_ms(&q["steady_request_ms"]),
        q["latency_ms"]["median"].as_f64().unwrap_or(f64::NAN) - q["steady_request_ms"].as_f64().unwrap_or(f64::NAN),
        s["stale_answers_after_response"],
        loads["samples"],
        fmt_ms(&loads["min"]),
        fmt_ms(&loads["median"]),
        fmt_ms(&loads["max"]),
        log["warnings_and_errors"],
        if problems.is_empty() { String::new() } else { format!(" The first:\n{problems}") },
    )
}
