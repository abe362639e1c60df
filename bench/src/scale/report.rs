//! The scale benchmark's Markdown: the setting, throughput by replica count, the failed
//! requests in each fault, the swap propagation and the start-up times.

use serde_json::Value;

use super::ScaleArgs;
use crate::harness::fmt_ms;

pub(super) fn ms_list(v: &[f64]) -> String {
    v.iter().map(|x| format!("{x:.0}")).collect::<Vec<_>>().join(" / ")
}

/// `A → B (×3) → C` for the states `A B B B C`.
fn states_in_a_row<'a>(states: impl Iterator<Item = &'a str>) -> String {
    let mut runs: Vec<(&str, usize)> = Vec::new();
    for s in states {
        match runs.last_mut() {
            Some((last, n)) if *last == s => *n += 1,
            _ => runs.push((s, 1)),
        }
    }
    runs.iter().map(|(s, n)| if *n > 1 { format!("{s} (×{n})") } else { s.to_string() }).collect::<Vec<_>>().join(" → ")
}

/// The summary table of `levels` (one row per replica count), then the per-process table.
fn levels_table(levels: &Value, rows_md: &str) -> String {
    let mut out = String::from(
        "| replicas | requests | seconds | req/s | p50 (ms) | p99 (ms) | failed | CPU of the replicas (cores) | \
         client CPU (cores) | other processes (cores) |\n|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for l in levels.as_array().into_iter().flatten() {
        let replicas_cores: f64 = l["per_process"]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|p| p["name"].as_str().is_some_and(|n| n.starts_with("serve")))
            .filter_map(|p| p["cpu_cores"].as_f64())
            .sum();
        let cores = |v: &Value| v.as_f64().map_or_else(|| "–".into(), |c| format!("{c:.2}"));
        out.push_str(&format!(
            "| {} | {} | {:.1} | {:.2} | {} | {} | {} | {replicas_cores:.2} | {} | {} |\n",
            l["replicas"],
            l["requests"],
            l["seconds"].as_f64().unwrap_or(f64::NAN),
            l["throughput_per_s"].as_f64().unwrap_or(f64::NAN),
            fmt_ms(&l["p50_ms"]),
            fmt_ms(&l["p99_ms"]),
            l["errors"],
            cores(&l["machine"]["client_cpu_cores"]),
            cores(&l["machine"]["other_processes_cores"]),
        ));
    }
    out.push_str(
        "\nPer process (CPU from `/proc/<pid>/stat`, user + system, over the row's window; requests and the \
         server-side mean latency from each process's `/metrics`):\n\n\
         | replicas | process | requests answered | req/s | server-side mean (ms) | CPU (s) | CPU (cores) |\n\
         |---:|---|---:|---:|---:|---:|---:|\n",
    );
    out.push_str(rows_md);
    out
}

pub(super) fn markdown(args: &ScaleArgs, report: &Value, levels_md: &str, oversubscribed_md: &str) -> String {
    let mut md = header_markdown(args, report);
    md.push_str(&levels_markdown(args, report, levels_md, oversubscribed_md));
    md.push_str(&faults_markdown(report));
    md.push_str(&propagation_markdown(report));
    md.push_str(&startup_markdown(report));
    md
}

/// The title, the setting and the caveat of one shared machine.
fn header_markdown(args: &ScaleArgs, report: &Value) -> String {
    let m = &report["machine"];
    let s = &report["setup"];
    format!(
        "# Scale-out benchmark\n\n`{}`\n\n\
         One `--role adapt` worker and three `--role serve` replicas of `udapose-server`, separate processes on one \
         store: {} (`{}`). Model `{}`; estimates send {} distinct PNG crops from `{}`; the jobs adapt on `{}`. \
         Load through the gRPC client library: {}. Machine: {}, **{} threads**; load average {} before, {} after; \
         {:.0} s in all. Commit `{}`.{}\n\n\
         **The replicas, the worker and the client share the machine's {} cores**, so this is not a measurement of \
         scaling: no number of replicas computes more than these cores do, and the figures below show the overhead \
         of spreading calls over replicas and that failover and swaps are correct. Scaling out needs a core budget \
         per replica (a machine or a pod each).\n\n",
        report["command"].as_str().unwrap_or(""),
        s["store"].as_str().unwrap_or(""),
        s["flags"].as_str().unwrap_or(""),
        args.model.display(),
        report["images"]["distinct"],
        report["images"]["folder"].as_str().unwrap_or(""),
        report["targets"]["folder"].as_str().unwrap_or(""),
        s["client"].as_str().unwrap_or(""),
        m["cpu"].as_str().unwrap_or(""),
        m["threads"],
        m["load_average_before"].as_str().unwrap_or(""),
        m["load_average_after"].as_str().unwrap_or(""),
        report["seconds"].as_f64().unwrap_or(f64::NAN),
        report["commit"].as_str().unwrap_or(""),
        args.note.as_ref().map(|n| format!(" Note: {n}.")).unwrap_or_default(),
        m["threads"],
    )
}

/// Throughput and latency by replica count, and with one libtorch thread per core.
fn levels_markdown(args: &ScaleArgs, report: &Value, levels_md: &str, oversubscribed_md: &str) -> String {
    let mut md = String::new();
    md.push_str(&format!(
        "## Throughput and latency by replica count\n\n{} requests per row (fewer if they take over 40 s), {} in \
         flight through one client over the first 1, 2 or 3 replicas (after 2 untimed requests per replica); latency \
         as the client sees it; *other processes*: the CPU that processes other than this benchmark, its servers and \
         its store took meanwhile (the machine is shared). Every process runs `--torch-threads {}`: a replica's \
         backbone then runs on one core, so one replica alone leaves part of the second core idle and a second \
         replica can take it (see *CPU of the replicas*); that is the only gain more replicas can bring here, and \
         beyond it only the overhead of spreading the calls remains.\n\n",
        args.requests, args.concurrency, args.torch_threads
    ));
    md.push_str(&levels_table(&report["levels"], levels_md));
    if !oversubscribed_md.is_empty() {
        md.push_str(&format!(
            "\n### With one libtorch thread per core in every replica (the server's default)\n\n\
             The same, {} requests per row (fewer if they take over 20 s), on 3 other replicas started with `--torch-threads 0` (the others idle): \
             each replica runs as many intra-op threads as the machine has cores, so 2 or 3 busy replicas \
             oversubscribe the cores. This is why a replica's `--torch-threads` should match its CPU share (the \
             manifests keep it equal to the CPU limit).\n\n",
            args.oversubscribed_requests
        ));
        md.push_str(&levels_table(&report["levels_torch_threads_0"], oversubscribed_md));
    }
    md
}

/// One row of the faults table: the window of fault `k` and what happened.
fn fault_row(f: &Value, name: &str, k: &str, detail: String) -> String {
    let v = &f[k]["window"];
    format!(
        "| {name} | {:.1} | {} | **{}** | {} | {} | {} | {} | {detail} |\n",
        v["seconds"].as_f64().unwrap_or(f64::NAN),
        v["requests"],
        v["failed"],
        fmt_ms(&v["p50_ms"]),
        fmt_ms(&v["p99_ms"]),
        fmt_ms(&v["max_ms"]),
        v["other_processes_cores"].as_f64().map_or_else(|| "–".into(), |c| format!("{c:.2}")),
    )
}

/// A fault's propagation times to serve-0 / 1 / 2.
fn prop(v: &Value) -> String {
    v.as_array().map(|a| a.iter().map(fmt_ms).collect::<Vec<_>>().join(" / ")).unwrap_or_default()
}

/// The table of the failed requests in each fault.
fn faults_markdown(report: &Value) -> String {
    let s = &report["setup"];
    let f = &report["faults"];
    let mut md = String::new();
    md.push_str(&format!(
        "\n## Failed requests in each fault\n\n{} requests in flight back to back through one client over every \
         replica, for the whole sequence below, in this order; each row counts the requests in flight during its \
         window (latency of the answered ones; *other processes*: the CPU that processes other than this benchmark, \
         its servers and its store took during the window, from `/proc`).\n\n\
         | fault | window (s) | requests | failed | p50 (ms) | p99 (ms) | max (ms) | other processes (cores) | what happened |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---|\n",
        s["fault_clients"]
    ));
    md.push_str(&fault_row(
        f,
        "adaptation job, then the swap after its activation",
        "swap_after_activation",
        activation_detail(&f["swap_after_activation"]),
    ));
    md.push_str(&fault_row(
        f,
        "`kill -9` of serve-2 under load",
        "serve_replica_kill9",
        replica_kill_detail(&f["serve_replica_kill9"]),
    ));
    md.push_str(&fault_row(
        f,
        "rollback on one replica",
        "rollback_on_one_replica",
        rollback_detail(&f["rollback_on_one_replica"]),
    ));
    md.push_str(&fault_row(
        f,
        "`kill -9` of the worker mid-job",
        "worker_kill9_mid_job",
        worker_kill_detail(&f["worker_kill9_mid_job"]),
    ));
    md
}

fn activation_detail(a: &Value) -> String {
    format!(
        "{} targets uploaded round-robin to the replicas; the job asked on serve-0 ran on the worker and ended {} \
         in {:.1} s ({} images trained on, {} held out); its version reached serve-0 / 1 / 2 {} ms after its activation",
        a["uploaded"]["ACCEPTED"],
        a["job"]["state"].as_str().unwrap_or(""),
        a["job"]["seconds"].as_f64().unwrap_or(f64::NAN),
        a["job"]["images_used"],
        a["job"]["images_held_out"],
        prop(&a["propagation_ms"]),
    )
}

fn replica_kill_detail(b: &Value) -> String {
    format!(
        "{} s with serve-2 dead ({} requests, {} failed, p50 {} ms, max {} ms), then restarted on the same ports: \
         ready in {:.1} s, serving the active `{}`; the client sent it requests again {:.1} s after that (it retries \
         an endpoint that failed after a cool-down of 1 s, doubled per failure in a row, at most 10 s)",
        b["kill_window_s"],
        b["killed_until_restart"]["requests"],
        b["killed_until_restart"]["failed"],
        fmt_ms(&b["killed_until_restart"]["p50_ms"]),
        fmt_ms(&b["killed_until_restart"]["max_ms"]),
        b["restart_ready_s"].as_f64().unwrap_or(f64::NAN),
        b["restart_serves"].as_str().unwrap_or(""),
        b["client_rejoin_s_after_ready"].as_f64().unwrap_or(f64::NAN),
    )
}

fn rollback_detail(c: &Value) -> String {
    format!(
        "`POST /v1/models/car/rollback` on serve-1 (answered in {} ms); `{}` reached serve-0 / 1 / 2 {} ms after \
         the call",
        fmt_ms(&c["call_ms"]),
        c["to_version"].as_str().unwrap_or(""),
        prop(&c["propagation_ms"]),
    )
}

fn worker_kill_detail(d: &Value) -> String {
    let history = d["history"].as_array().cloned().unwrap_or_default();
    format!(
        "killed {} s after the job was seen RUNNING (state {}, round {}); a new worker (ready in {:.1} s) took it \
         over{}: its states {}; {} ({}), {} activation(s) by the job, {} incomplete version(s) activated; its \
         version reached serve-0 / 1 / 2 {} ms after its activation",
        d["killed_after_running_s"],
        d["state_at_kill"].as_str().unwrap_or(""),
        d["round_at_kill"],
        d["new_worker_ready_s"].as_f64().unwrap_or(f64::NAN),
        history
            .iter()
            .find_map(|h| h.as_str().filter(|h| h.contains("restart")))
            .map(|h| format!(" (\"{}\")", h.split_once(": ").map_or(h, |(_, m)| m)))
            .unwrap_or_default(),
        states_in_a_row(history.iter().filter_map(|h| h.as_str()?.split(':').next())),
        d["job"]["state"].as_str().unwrap_or(""),
        d["job"]["last_event"].as_str().unwrap_or(""),
        d["activations_by_job"],
        d["incomplete_versions_activated"].as_array().map_or(0, Vec::len),
        prop(&d["propagation_ms"]),
    )
}

/// The swap propagation: overall, then each replica's steps from its log.
fn propagation_markdown(report: &Value) -> String {
    let s = &report["setup"];
    let f = &report["faults"];
    let (a, c, d) = (&f["swap_after_activation"], &f["rollback_on_one_replica"], &f["worker_kill9_mid_job"]);
    let mut md = String::new();
    let p = &report["propagation_ms"];
    md.push_str(&format!(
        "\n**Failed requests: {} in all** ({} requests during the faults).\n\n\
         ## Swap propagation\n\n\
         From an activation (the job's ACTIVATED event, as the worker timestamps it) or a rollback (its HTTP call) \
         to the first estimate each replica answers with the new version (each replica's active version polled every \
         50 ms, then confirmed by an estimate): **{} / {} / {} ms** (min / median / max over {} replica swaps). A \
         replica learns of a new activation when it next re-reads the store (`--poll {}`: every {} s), downloads the \
         version if it has not yet (`--cache-dir`), and its inference worker loads it before its next batch; so the \
         propagation is up to one poll period plus the download, the batch in progress and the load (each slower on \
         a busy machine). The replica that took the rollback re-reads the log at once: no poll in its figure.\n",
        report["failed_requests_in_faults"],
        report["fault_load"]["requests"],
        fmt_ms(&p["min"]),
        fmt_ms(&p["median"]),
        fmt_ms(&p["max"]),
        [a, c, d].iter().filter_map(|x| x["propagation_ms"].as_array()).map(Vec::len).sum::<usize>(),
        s["poll_s"],
        s["poll_s"],
    ));
    md.push_str(
        "\nEach replica's steps, from its log (ms after the activation): when its registry saw the new version active, \
         when its inference worker had loaded it (and how long that load took); the first answer then waits for the \
         batches queued meanwhile.\n\n\
         | swap | replica | new version seen active (ms) | loaded (ms) | load took (ms) | first answer by it (ms) |\n\
         |---|---|---:|---:|---:|---:|\n",
    );
    for (name, x) in [
        ("the first job's version", a),
        ("rollback on serve-1", c),
        ("the second job's version (after the worker's kill)", d),
    ] {
        let steps = x["propagation_steps"].as_array().cloned().unwrap_or_default();
        for (i, ms) in x["propagation_ms"].as_array().into_iter().flatten().enumerate() {
            let step = steps.get(i).cloned().unwrap_or(Value::Null);
            md.push_str(&format!(
                "| {name} | {} | {} | {} | {} | {} |\n",
                step["name"].as_str().unwrap_or("?"),
                fmt_ms(&step["seen_ms"]),
                fmt_ms(&step["loaded_ms"]),
                fmt_ms(&step["load_ms"]),
                fmt_ms(ms),
            ));
        }
    }
    md
}

/// The start-up times, and how to reproduce the report.
fn startup_markdown(report: &Value) -> String {
    let st = &report["startup"];
    format!(
        "\nStart-up (process start to `/readyz`, seed import and model download from the store included): worker {:.1} s, \
         replicas {} s.\n\nTo reproduce: `udapose-bench scale` (after `make test` has rendered the quick data and \
         installed s3s-fs; `--help` lists the settings).\n",
        st["worker_ready_s"].as_f64().unwrap_or(f64::NAN),
        st["replicas_ready_s"]
            .as_array()
            .map(|a| a
                .iter()
                .map(|x| x.as_f64().map_or("–".into(), |v| format!("{v:.1}")))
                .collect::<Vec<_>>()
                .join(" / "))
            .unwrap_or_default(),
    )
}
