//! Job time against the work: a job on each of `--job-sizes` target images (50, 100, 200 by
//! default), each on a fresh idle server from the seed, with no clients: what adapting costs
//! as the buffer grows, beside the job measured under load.

use std::{path::Path, time::Instant};

use anyhow::{Result, bail};
use serde_json::{Value, json};

use super::{
    ServiceArgs,
    adapt::{self, Upload},
};
use crate::harness::{ServerProcess, read_images};

pub(super) fn job_sizes(args: &ServiceArgs, server_bin: &Path, model: &Path) -> Result<Value> {
    let folder = adapt::target_folder(args)?;
    let flags = adapt::flags(args);
    let flag_refs: Vec<&str> = flags.iter().map(String::as_str).collect();
    let mut jobs = Vec::new();
    for &n in &args.job_sizes {
        let targets = read_images(&folder, n)?;
        if targets.len() < n {
            bail!("{} holds {} images, fewer than --job-sizes' {n}", folder.display(), targets.len());
        }
        eprintln!("job on {n} target images, idle server");
        let server = ServerProcess::start(server_bin, model, args.max_batch, args.max_delay_ms, &flag_refs, true)?;
        Upload::send(&server, folder.clone(), &targets)?;
        let started = Instant::now();
        let mut loads = Vec::new();
        let (id, overrides, job, seen) = adapt::run_job(args, &server, &mut loads)?;
        let total = started.elapsed().as_secs_f64();
        let (Some(from), Some(to)) = (seen.running, seen.active_until) else {
            bail!("job {id} was never seen RUNNING; it ended {}: {}", job["state"], job["reason"]);
        };
        let split = seen.validating.unwrap_or(to);
        let mut report = adapt::job_json(&job, &overrides, (split - from).as_secs_f64(), (to - split).as_secs_f64());
        report["target_images"] = json!(n);
        report["wall_seconds"] = json!(total);
        report["load_average"] = loads.iter().map(|(k, v)| ((*k).to_owned(), json!(v))).collect();
        eprintln!("  {n} images: {} after {total:.1} s ({} rounds)", job["state"], report["rounds"]);
        jobs.push(report);
    }
    Ok(json!({ "folder": folder.display().to_string(), "jobs": jobs }))
}

pub(super) fn markdown(report: &Value) -> String {
    let Some(jobs) = report["job_sizes"]["jobs"].as_array() else { return String::new() };
    let mut md = format!(
        "\n## Job time against target images\n\nA job on the first *n* images of `{}`, each on a fresh server \
         from the seed with no clients (`--job-sizes`): from the job's creation to its end, and the share of \
         it spent adapting (RUNNING) and in the gate (VALIDATING).\n\n\
         | target images | trained on | held out | rounds | RUNNING (s) | VALIDATING (s) | total (s) | s per image | outcome |\n\
         |---:|---:|---:|---:|---:|---:|---:|---:|---|\n",
        report["job_sizes"]["folder"].as_str().unwrap_or("")
    );
    for j in jobs {
        let n = j["target_images"].as_f64().unwrap_or(f64::NAN);
        let total = j["seconds"].as_f64().unwrap_or(f64::NAN);
        md.push_str(&format!(
            "| {n} | {} | {} | {} | {:.1} | {:.1} | {total:.1} | {:.2} | {} |\n",
            j["images_used"],
            j["images_held_out"],
            j["rounds"],
            j["running_seconds"].as_f64().unwrap_or(f64::NAN),
            j["validating_seconds"].as_f64().unwrap_or(f64::NAN),
            total / n,
            j["state"].as_str().unwrap_or("?"),
        ));
    }
    md
}
