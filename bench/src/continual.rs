//! `udapose-bench continual`: online adaptation over a sequence of domains, through real
//! servers. Each step streams a domain's adapt images to the server, starts a job and waits for
//! its verdict; then Acc@π/6 is measured on the test split of *every* domain of the sequence.
//! Background clients estimate during the whole sequence; any failed request is counted.
//!
//! Rows, each on a fresh server with the same seed model:
//! - `none`: no adaptation (the seed's accuracy, measured once);
//! - `independent`: `--no-regression-sets`, each job judged on its own held-out images only
//!   (the service before regression sets);
//! - `continual`: the default service, whose gate also guards every earlier job's held-out images
//!   and keeps a job that wins its own domain but would regress an earlier one as an expert.
//!
//! Per step the report keeps what a user sees (the job's state and reason) and, when the gate
//! refused the job, what the refused candidate would have scored on the step's domain
//! (activated for the measurement, then the previous version again), so that a step's gain is
//! compared with what a job on that domain alone gains from the same starting model.

use std::{
    collections::BTreeMap,
    f64::consts::FRAC_PI_6,
    path::{Path, PathBuf},
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail, ensure};
use rayon::prelude::*;
use serde_json::{Value, json};
use udapose_engine::pose_error;
use udapose_lab::{atomic::write_atomic, datasets::syncar::SyncarSplit};

use crate::harness::{ServerProcess, estimate, git_commit, post_or_get, read_images, server_binary};
use crate::paired::Paired;
use crate::service::clients::Clients;

#[derive(clap::Args)]
pub struct ContinualArgs {
    /// The seed model directory (served as `car`).
    #[arg(long)]
    pub model: PathBuf,
    /// SynCar-OOD root.
    #[arg(long)]
    pub data: PathBuf,
    /// The domains, in order (repeats allowed).
    #[arg(long, default_value = "source,corrupt/fog,combined,corrupt/contrast,corrupt/fog,source")]
    pub sequence: String,
    /// Adapt images streamed per step (the first of the domain's adapt split).
    #[arg(long, default_value_t = 200)]
    pub images: usize,
    /// Test images per domain for Acc@π/6 after each step.
    #[arg(long, default_value_t = 300)]
    pub test_images: usize,
    /// Background estimate clients during the whole sequence.
    #[arg(long, default_value_t = 2)]
    pub clients: usize,
    /// Most seconds a job may take.
    #[arg(long, default_value_t = 3600)]
    pub job_timeout_s: u64,
    /// The server binary (default: next to this one).
    #[arg(long)]
    pub server: Option<PathBuf>,
    #[arg(long, default_value = "reports/continual.json")]
    pub out: PathBuf,
}

/// A domain's test images: bytes and true `[azimuth, elevation, theta]`.
struct TestSet {
    images: Vec<(Vec<u8>, [f64; 3])>,
}

impl TestSet {
    fn load(data: &Path, domain: &str, n: usize) -> Result<Self> {
        let split = SyncarSplit::open(data, domain, "test")?;
        let images = (0..split.len().min(n))
            .map(|i| {
                let s = split.load(i)?;
                let p = s.annotation.pose;
                let bytes = std::fs::read(&s.entry.image_path)
                    .with_context(|| format!("reading {}", s.entry.image_path.display()))?;
                Ok((bytes, [p.azimuth, p.elevation, p.theta]))
            })
            .collect::<Result<Vec<_>>>()?;
        ensure!(!images.is_empty(), "{domain}/test has no images");
        Ok(TestSet { images })
    }

    /// Per image, whether the server's active version gets it within π/6; errors when any
    /// estimate fails.
    fn right(&self, server: &ServerProcess) -> Result<Vec<bool>> {
        self.images
            .par_iter()
            .map(|(bytes, truth)| {
                let (status, body) = post_or_get(server.http, "POST", "/v1/pose/car", bytes)?;
                ensure!(status == 200, "estimate: {status} {body}");
                let v: Value = serde_json::from_str(&body)?;
                let p = &v["estimates"][0];
                let angles = ["azimuth", "elevation", "theta"].map(|k| p[k].as_f64().unwrap_or(f64::NAN));
                Ok(pose_error(Some(angles), *truth) < FRAC_PI_6)
            })
            .collect()
    }
}

/// Acc@π/6 from per-image flags.
fn share(right: &[bool]) -> f64 {
    right.iter().filter(|&&r| r).count() as f64 / right.len().max(1) as f64
}

pub fn run(args: &ContinualArgs) -> Result<()> {
    let started = Instant::now();
    let sequence: Vec<String> =
        args.sequence.split(',').map(str::trim).filter(|d| !d.is_empty()).map(Into::into).collect();
    ensure!(!sequence.is_empty(), "--sequence names no domain");
    let mut domains = sequence.clone();
    domains.sort();
    domains.dedup();
    let tests: BTreeMap<String, TestSet> = domains
        .iter()
        .map(|d| Ok((d.clone(), TestSet::load(&args.data, d, args.test_images)?)))
        .collect::<Result<_>>()?;
    let binary = server_binary(args.server.as_deref())?;
    let mut failed = 0;
    let mut rows = serde_json::Map::new();
    for (row, flags) in
        [("none", None), ("independent", Some(&["--no-regression-sets"][..])), ("continual", Some(&[][..]))]
    {
        eprintln!("row {row}");
        let (steps, failures) = run_row(args, &binary, &sequence, &tests, flags)?;
        failed += failures;
        rows.insert(row.into(), Value::Array(steps));
    }
    let continual = rows["continual"].as_array().cloned().unwrap_or_default();
    let report = json!({
        "commit": git_commit(),
        "model": args.model,
        "data": args.data,
        "sequence": sequence,
        "images_per_step": args.images,
        "test_images": args.test_images,
        "rows": rows,
        "forgetting_max": forgetting_max(&continual),
        "forgetting_worst": worst_forgetting(&continual),
        "forgetting_max_independent": forgetting_max(rows["independent"].as_array().map_or(&[][..], Vec::as_slice)),
        "gain_ratio_min": gain_ratio_min(&continual, false),
        "gain_ratio_min_beyond_noise": gain_ratio_min(&continual, true),
        "failed_requests": failed,
        "seconds": started.elapsed().as_secs_f64(),
    });
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), markdown(&report, args).as_bytes())?;
    eprintln!("wrote {} and its .md", args.out.display());
    Ok(())
}

/// One row: a fresh server, the sequence's jobs (none when `flags` is `None`), the accuracy
/// on every domain after each step; the steps and the failed background requests.
fn run_row(
    args: &ContinualArgs,
    binary: &Path,
    sequence: &[String],
    tests: &BTreeMap<String, TestSet>,
    flags: Option<&[&str]>,
) -> Result<(Vec<Value>, usize)> {
    let mut all_flags = vec!["--adapt-min-images", "1000000"];
    all_flags.extend(flags.unwrap_or_default());
    let (server, _) = ServerProcess::serve_model(binary, &args.model, "continual", &all_flags, true)?;
    let probe: Arc<Vec<Vec<u8>>> =
        Arc::new(tests.values().flat_map(|t| t.images.iter().take(4)).map(|(b, _)| b.clone()).collect());
    let clients = Clients::start(server.http, &probe, args.clients);
    let measure_all = |server: &ServerProcess| -> Result<BTreeMap<String, Vec<bool>>> {
        tests.iter().map(|(d, t)| Ok((d.clone(), t.right(server)?))).collect()
    };
    let accuracies = |right: &BTreeMap<String, Vec<bool>>| -> BTreeMap<String, f64> {
        right.iter().map(|(d, r)| (d.clone(), share(r))).collect()
    };
    let mut right = measure_all(&server)?;
    let mut steps = Vec::new();
    for (step, domain) in sequence.iter().enumerate() {
        let before = right.clone();
        let mut entry = json!({ "step": step + 1, "domain": domain, "acc_before": accuracies(&before) });
        if flags.is_none() {
            entry["gate"] = json!("none");
            entry["activated"] = json!(false);
        } else {
            let (job, seconds) = run_job(args, &server, domain)?;
            let state = job["state"].as_str().unwrap_or("").to_owned();
            eprintln!(
                "  step {} {domain}: {state} in {seconds:.0} s: {}",
                step + 1,
                job["reason"].as_str().unwrap_or("")
            );
            right = measure_all(&server)?;
            entry["job_id"] = job["job_id"].clone();
            entry["gate"] = json!(state);
            entry["reason"] = job["reason"].clone();
            entry["activated"] = json!(state == "ACTIVATED");
            entry["job_seconds"] = json!(seconds);
            let guarded: Vec<&Value> = job["last_event"]["gate"]
                .as_array()
                .map(|g| g.iter().filter(|c| c["name"].as_str().is_some_and(|n| n.contains('/'))).collect())
                .unwrap_or_default();
            entry["guarded_criteria"] = json!(guarded);
            entry["message"] = job["last_event"]["message"].clone();
            // What the job alone would have given on its domain: the candidate itself (not
            // the composite where it was kept as an expert).
            let candidate = job["version"].as_str().unwrap_or("");
            let active = server.get_json("/v1/models/car")?["version"].as_str().unwrap_or("").to_owned();
            entry["active_version"] = json!(active);
            let alone = if state == "ACTIVATED" && active == candidate {
                Some(right[domain].clone())
            } else if !candidate.is_empty() {
                Some(candidate_right(&server, candidate, &tests[domain])?)
            } else {
                None
            };
            entry["alone_acc"] = json!(alone.as_deref().map(share));
            // Whether the job alone would have gained beyond the noise of the test images, and
            // whether the step did: image by image against the starting model.
            let paired = |after: &[bool]| {
                let p = Paired::new(&before[domain], after);
                json!({ "lost": p.lost, "gained": p.gained, "mcnemar_z": p.z(), "significant": p.significant() })
            };
            entry["alone_paired"] = json!(alone.as_deref().map(paired));
            entry["step_paired"] = paired(&right[domain]);
        }
        entry["acc_pi_6"] = json!(accuracies(&right));
        // Per image, right (1) or not (0): the forgetting's paired statistic.
        entry["right"] = json!(
            right
                .iter()
                .map(|(d, r)| (d.clone(), r.iter().map(|&x| if x { '1' } else { '0' }).collect::<String>()))
                .collect::<BTreeMap<_, _>>()
        );
        steps.push(entry);
    }
    let failures = clients.stop().iter().filter(|r| r.answer.is_err()).count();
    Ok((steps, failures))
}

/// Uploads the domain's first `--images` adapt images, starts a job and waits for its end.
fn run_job(args: &ContinualArgs, server: &ServerProcess, domain: &str) -> Result<(Value, f64)> {
    let folder = args.data.join(domain).join("adapt/images/car");
    for image in read_images(&folder, args.images)? {
        let (status, body) = post_or_get(server.http, "POST", "/v1/adapt/car/images", &image)?;
        ensure!(status == 200, "uploading a target image: {status} {body}");
    }
    let started = Instant::now();
    let job = server.post_json("/v1/adapt/car/jobs", &json!({}))?;
    let id = job["job_id"].as_str().context("no job_id")?.to_owned();
    let deadline = started + Duration::from_secs(args.job_timeout_s);
    loop {
        let job = server.get_json(&format!("/v1/jobs/{id}"))?;
        if !matches!(job["state"].as_str(), Some("QUEUED" | "RUNNING" | "VALIDATING")) {
            return Ok((job, started.elapsed().as_secs_f64()));
        }
        if Instant::now() > deadline {
            bail!("job {id} did not end within {} s: {job}", args.job_timeout_s);
        }
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// Per-image flags of a version the gate refused: activated for the measurement, then the
/// version that was active before it is activated again.
fn candidate_right(server: &ServerProcess, version: &str, test: &TestSet) -> Result<Vec<bool>> {
    let active = server.get_json("/v1/models/car")?["version"].as_str().context("no active version")?.to_owned();
    let probe = &test.images[0].0;
    activate(server, version, probe)?;
    let right = test.right(server);
    activate(server, &active, probe)?;
    right
}

/// Activates `version` and waits until estimates of `probe` name it (workers swap between
/// batches).
fn activate(server: &ServerProcess, version: &str, probe: &[u8]) -> Result<()> {
    server.post_json("/v1/models/car/activate", &json!({ "version": version, "reason": "bench continual" }))?;
    let deadline = Instant::now() + Duration::from_secs(60);
    while estimate(server.http, probe).map_err(anyhow::Error::msg)? != version {
        ensure!(Instant::now() < deadline, "{version} never answered");
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(())
}

/// The largest drop, after any step, of a domain already adapted to below its best accuracy
/// since it was first a step's domain (0 with no drop).
fn forgetting_max(steps: &[Value]) -> f64 {
    worst_forgetting(steps).map_or(0.0, |w| w["drop"].as_f64().unwrap_or(f64::NAN))
}

/// Where [`forgetting_max`]'s drop happened: the domain, the step and the step of its best, and
/// McNemar's z of the change between them on the test images (null without a drop).
fn worst_forgetting(steps: &[Value]) -> Option<Value> {
    // Per seen domain: its best accuracy and the index of the step that gave it.
    let mut best: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    let mut worst: Option<(f64, String, usize, usize)> = None;
    for (i, s) in steps.iter().enumerate() {
        let Some(domain) = s["domain"].as_str() else { continue };
        let acc = |d: &str| s["acc_pi_6"][d].as_f64().unwrap_or(f64::NAN);
        best.entry(domain.into()).or_insert((f64::NEG_INFINITY, i));
        for (d, b) in best.iter_mut() {
            if acc(d) > b.0 {
                *b = (acc(d), i);
            }
            let drop = b.0 - acc(d);
            if drop > worst.as_ref().map_or(0.0, |w| w.0) {
                worst = Some((drop, d.clone(), i, b.1));
            }
        }
    }
    let (drop, domain, at, best_at) = worst?;
    let flags = |i: usize| -> Option<Vec<bool>> {
        Some(steps[i]["right"][&domain].as_str()?.chars().map(|c| c == '1').collect())
    };
    let z = flags(best_at).zip(flags(at)).map(|(b, a)| Paired::new(&b, &a).z());
    Some(json!({
        "domain": domain,
        "drop": drop,
        "step": steps[at]["step"],
        "best_step": steps[best_at]["step"],
        "mcnemar_z": z,
    }))
}

/// Over the steps whose job alone would have gained (its candidate above the starting
/// accuracy on the step's domain; with `beyond_noise`, by McNemar's z ≥ 1.96 on the test
/// images), the smallest ratio of the step's actual gain to that gain; null when no step's job
/// would have gained. A gain of one or two images of 300 is noise: a ratio to it says nothing.
fn gain_ratio_min(steps: &[Value], beyond_noise: bool) -> Value {
    let ratios: Vec<f64> = steps
        .iter()
        .filter_map(|s| {
            let d = s["domain"].as_str()?;
            let before = s["acc_before"][d].as_f64()?;
            let alone = s["alone_acc"].as_f64()? - before;
            let actual = s["acc_pi_6"][d].as_f64()? - before;
            let counted = alone > 0.0 && (!beyond_noise || s["alone_paired"]["significant"].as_bool()?);
            counted.then_some(actual / alone)
        })
        .collect();
    ratios.into_iter().reduce(f64::min).map_or(Value::Null, |r| json!(r))
}

fn markdown(report: &Value, args: &ContinualArgs) -> String {
    let domains: Vec<String> = {
        let mut d: Vec<String> =
            report["sequence"].as_array().into_iter().flatten().filter_map(|v| v.as_str().map(Into::into)).collect();
        d.sort();
        d.dedup();
        d
    };
    let mut md = format!(
        "# Continual online adaptation\n\n`udapose-bench continual --model {} --data {} --sequence {} --images {} \
         --test-images {}` (commit {}, {:.0} s).\n\nAcc@π/6 on each domain's test split after each step.\n\n",
        args.model.display(),
        args.data.display(),
        args.sequence,
        args.images,
        args.test_images,
        report["commit"].as_str().unwrap_or("?"),
        report["seconds"].as_f64().unwrap_or(0.0)
    );
    for row in ["none", "independent", "continual"] {
        md += &format!("## {row}\n\n| step | domain | gate | job s | alone |");
        for d in &domains {
            md += &format!(" {d} |");
        }
        md += "\n|---:|---|---|---:|---:|";
        md += &"---:|".repeat(domains.len());
        md += "\n";
        for s in report["rows"][row].as_array().into_iter().flatten() {
            let num = |v: &Value| v.as_f64().map_or("-".into(), |x| format!("{x:.3}"));
            md += &format!(
                "| {} | {} | {} | {} | {} |",
                s["step"],
                s["domain"].as_str().unwrap_or(""),
                s["gate"].as_str().unwrap_or(""),
                s["job_seconds"].as_f64().map_or("-".into(), |x| format!("{x:.0}")),
                num(&s["alone_acc"])
                    + &s["alone_paired"]["mcnemar_z"].as_f64().map_or(String::new(), |z| format!(" (z {z:+.1})"))
            );
            for d in &domains {
                md += &format!(" {} |", num(&s["acc_pi_6"][d]));
            }
            md += "\n";
        }
        md += "\n";
        for s in report["rows"][row].as_array().into_iter().flatten() {
            let step = format!("- step {} ({})", s["step"], s["domain"].as_str().unwrap_or(""));
            if let Some(reason) = s["reason"].as_str().filter(|r| !r.is_empty() && s["gate"] != "ACTIVATED") {
                md += &format!("{step}: {reason}\n");
            } else if let Some(m) = s["message"].as_str().filter(|m| m.contains("answering the images like its own")) {
                md += &format!("{step}: kept as an expert: {m}\n");
            }
        }
        md += "\n";
    }
    md += &format!(
        "forgetting_max (continual) {:.3} ({}), (independent) {:.3}; gain_ratio_min {} (over the steps whose job \
         alone gains beyond noise, McNemar z >= 1.96: {}); failed requests {}.\n",
        report["forgetting_max"].as_f64().unwrap_or(f64::NAN),
        worst_words(&report["forgetting_worst"]),
        report["forgetting_max_independent"].as_f64().unwrap_or(f64::NAN),
        report["gain_ratio_min"],
        report["gain_ratio_min_beyond_noise"],
        report["failed_requests"]
    );
    md
}

/// "occ-l1 at step 5, below its best at step 4 (McNemar z -2.1)".
fn worst_words(w: &Value) -> String {
    if w.is_null() {
        return "no drop".into();
    }
    let z = w["mcnemar_z"].as_f64().map_or(String::new(), |z| format!(" (McNemar z {z:+.1})"));
    format!(
        "{} at step {}, below its best at step {}{z}",
        w["domain"].as_str().unwrap_or("?"),
        w["step"],
        w["best_step"]
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(domain: &str, before: f64, after: f64, alone: f64, alone_z: f64) -> Value {
        json!({
            "domain": domain,
            "acc_before": { domain: before },
            "acc_pi_6": { domain: after },
            "alone_acc": alone,
            "alone_paired": { "mcnemar_z": alone_z, "significant": alone_z.abs() >= 1.96 },
        })
    }

    #[test]
    fn gain_ratio_counts_only_gains_beyond_noise_when_asked() {
        // A refused job that alone would have gained one image (z 1.0), and a kept one that
        // gains half of what it would alone (z 3.0).
        let steps = [step("fog", 0.5, 0.5, 0.503, 1.0), step("snow", 0.4, 0.45, 0.5, 3.0)];
        assert_eq!(gain_ratio_min(&steps, false), json!(0.0));
        let beyond = gain_ratio_min(&steps, true).as_f64().unwrap();
        assert!((beyond - 0.5).abs() < 1e-9, "{beyond}");
        let no_gain = [step("fog", 0.5, 0.5, 0.49, -1.0)];
        assert_eq!(gain_ratio_min(&no_gain, false), Value::Null);
    }

    #[test]
    fn forgetting_is_the_largest_drop_below_a_seen_domains_best() {
        let at = |step: u32, domain: &str, fog: f64, snow: f64| json!({ "step": step, "domain": domain, "acc_pi_6": { "fog": fog, "snow": snow } });
        // Snow is not yet seen at step 1, so its fall there does not count; fog's later fall does.
        let mut steps = [at(1, "fog", 0.8, 0.3), at(2, "snow", 0.75, 0.6), at(3, "snow", 0.7, 0.65)];
        assert!((forgetting_max(&steps) - 0.1).abs() < 1e-9);
        // With per-image flags: 10 images, 8 right at step 1, 7 at step 3 (one lost, none gained).
        steps[0]["right"] = json!({ "fog": "1111111100" });
        steps[2]["right"] = json!({ "fog": "0111111100" });
        let w = worst_forgetting(&steps).unwrap();
        assert_eq!(
            (w["domain"].as_str(), w["step"].clone(), w["best_step"].clone()),
            (Some("fog"), json!(3), json!(1))
        );
        assert_eq!(w["mcnemar_z"], json!(-1.0));
        assert_eq!(worst_forgetting(&steps[..1]), None);
    }
}
