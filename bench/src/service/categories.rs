//! `udapose-bench service --models DIR`: every category under `DIR` served side by side by one
//! server. Memory: the server's resident set with car alone and with every category, and what
//! each category's workers hold (`udapose_model_bytes`). Latency: clients sending to every
//! category in rotation, p50/p99 per category, beside car alone under the same clients.

use std::{
    fs,
    path::{Path, PathBuf},
    time::Duration,
};

use anyhow::{Context, Result, ensure};
use serde_json::{Value, json};
use udapose_engine::checkpoint::MANIFEST;

use super::{ServiceArgs, load_categories};
use crate::harness::{ServerProcess, post_or_get, read_images};

/// The categories under `models` (folders with a manifest), sorted, car first if present.
fn categories(models: &Path) -> Result<Vec<(String, PathBuf)>> {
    let mut found: Vec<(String, PathBuf)> = fs::read_dir(models)
        .with_context(|| format!("listing {}", models.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join(MANIFEST).is_file())
        .filter_map(|p| Some((p.file_name()?.to_string_lossy().into_owned(), p)))
        .collect();
    found.sort_by_key(|(c, _)| (c != "car", c.clone()));
    ensure!(found.first().is_some_and(|(c, _)| c == "car"), "no car model under {}", models.display());
    Ok(found)
}

/// Test crops of a category: `--images` for car, else its dataset's source/test split
/// (`<data-root>/syncar-ood-standard-<category>`, as `synth --category` names it).
fn images(args: &ServiceArgs, category: &str) -> Result<Vec<Vec<u8>>> {
    let dir = if category == "car" {
        args.images.clone()
    } else {
        args.category_data.join(format!("syncar-ood-standard-{category}")).join("source/test/images").join(category)
    };
    read_images(&dir, args.distinct).with_context(|| format!("{category}'s crops ({})", dir.display()))
}

/// A gauge from the server's `/metrics`: the value of the line `name` (labels included).
fn gauge(server: &ServerProcess, name: &str) -> Result<f64> {
    let (status, text) = post_or_get(server.http, "GET", "/metrics", b"")?;
    ensure!(status == 200, "GET /metrics: {status}");
    let line =
        text.lines().find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')).with_context(|| format!("no {name}"))?;
    Ok(line.trim().parse()?)
}

/// Resident bytes once the workers have loaded (readiness) and the allocator settled.
fn resident(server: &ServerProcess) -> Result<f64> {
    std::thread::sleep(Duration::from_secs(2));
    gauge(server, "udapose_resident_bytes")
}

pub(super) fn side_by_side(args: &ServiceArgs, server_bin: &Path, models: &Path) -> Result<Value> {
    let categories = categories(models)?;
    let crops: Vec<Vec<Vec<u8>>> = categories.iter().map(|(c, _)| images(args, c)).collect::<Result<_>>()?;
    let flags = [&["--max-batch", "1"][..], &args.server_flags()].concat();
    let clients = args.categories_clients;
    let requests = args.requests * categories.len();

    eprintln!("car alone");
    let car = [("car", categories[0].1.as_path())];
    let (server, _) = ServerProcess::serve_models(server_bin, &car, "service-car-alone", &flags, false)?;
    let car_rss = resident(&server)?;
    let alone = load_categories(server.http, &[("car", &crops[0])], clients, requests)?.remove(0);
    drop(server);

    eprintln!("{} categories side by side", categories.len());
    let all: Vec<(&str, &Path)> = categories.iter().map(|(c, p)| (c.as_str(), p.as_path())).collect();
    let (server, _) = ServerProcess::serve_models(server_bin, &all, "service-categories", &flags, false)?;
    let all_rss = resident(&server)?;
    let model_bytes: Vec<f64> = categories
        .iter()
        .map(|(c, _)| gauge(&server, &format!("udapose_model_bytes{{category=\"{c}\"}}")))
        .collect::<Result<_>>()?;
    let targets: Vec<(&str, &[Vec<u8>])> =
        categories.iter().zip(&crops).map(|((c, _), i)| (c.as_str(), i.as_slice())).collect();
    let mixed = load_categories(server.http, &targets, clients, requests)?;
    drop(server);

    let seconds = mixed.first().map_or(f64::NAN, |l| l.seconds);
    let served: usize = mixed.iter().map(|l| l.requests - l.errors).sum();
    Ok(json!({
        "clients": clients,
        "requests": requests,
        "resident_bytes": {"car_alone": car_rss, "all": all_rss},
        "car_alone": alone.json(),
        "mixed_throughput_per_s": served as f64 / seconds,
        "failed_requests": alone.errors + mixed.iter().map(|l| l.errors).sum::<usize>(),
        "categories": categories.iter().zip(&model_bytes).zip(&mixed).map(|(((c, p), bytes), level)| json!({
            "category": c, "model": p.display().to_string(), "model_bytes": bytes, "mixed": level.json(),
        })).collect::<Vec<_>>(),
    }))
}

pub(super) fn markdown(report: &Value) -> String {
    let s = &report["side_by_side"];
    if s.is_null() {
        return String::new();
    }
    let mib = |v: &Value| v.as_f64().unwrap_or(f64::NAN) / (1 << 20) as f64;
    let ms = |l: &Value, k: &str| l[k].as_f64().unwrap_or(f64::NAN);
    let mut md = format!(
        "\n## Categories side by side\n\nOne server (`--max-batch 1`) on every category of `--models`; {} clients send {} \
         estimates back to back, request r to category r mod n (each its own `source/test` crops). Resident set (`udapose_resident_bytes`, \
         after loading): **{:.0} MiB** with car alone, **{:.0} MiB** with all {} categories. The same clients on car alone: \
         {:.2} req/s, p50 {:.0} ms, p99 {:.0} ms; side by side {:.2} req/s in all, {} failed requests.\n\n\
         | category | model memory (MiB) | requests | p50 (ms) | p99 (ms) | errors |\n|---|---:|---:|---:|---:|---:|\n",
        s["clients"],
        s["requests"],
        mib(&s["resident_bytes"]["car_alone"]),
        mib(&s["resident_bytes"]["all"]),
        s["categories"].as_array().map_or(0, Vec::len),
        ms(&s["car_alone"], "throughput_per_s"),
        ms(&s["car_alone"], "p50_ms"),
        ms(&s["car_alone"], "p99_ms"),
        s["mixed_throughput_per_s"].as_f64().unwrap_or(f64::NAN),
        s["failed_requests"],
    );
    for c in s["categories"].as_array().into_iter().flatten() {
        let l = &c["mixed"];
        md.push_str(&format!(
            "| {} | {:.1} | {} | {:.0} | {:.0} | {} |\n",
            c["category"].as_str().unwrap_or(""),
            mib(&c["model_bytes"]),
            l["requests"],
            ms(l, "p50_ms"),
            ms(l, "p99_ms"),
            l["errors"]
        ));
    }
    md.push_str(
        "\nModel memory is what `/metrics` reports per category: the tensors and the solver's host data of each worker's copy.\n",
    );
    md
}
