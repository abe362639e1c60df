//! `udapose-lab compare`: source models side by side (reports/source-models.json and .md).
//!
//! Accuracy per domain comes from each model's `udapose-lab eval` report on the test splits
//! (which also holds every image's true-pose fired ratio); this command adds what describes the
//! model itself and measures the costs of all models in one run, interleaved image by image so
//! that a machine's noise falls on all of them alike: backbone ms per crop and estimate ms per
//! image on one thread.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};
use tch::Tensor;
use udapose_engine::checkpoint::{self, Model};
use udapose_engine::estimator::{self, PoseSolver};
use udapose_engine::solver::SolverConfig;
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::load_sample;

#[derive(clap::Args)]
pub struct Args {
    /// NAME=MODEL_DIR=EVAL_JSON[,EVAL_JSON...]: a model and its `udapose-lab eval` reports on
    /// the test splits, a later report's domains replacing an earlier's (repeatable; the order is
    /// the report's).
    #[arg(long = "model", required = true)]
    models: Vec<String>,
    /// The name of the shipped model.
    #[arg(long)]
    shipped: String,
    /// SynCar-OOD root, for the timing images (source/test).
    #[arg(long)]
    data: PathBuf,
    /// Images timed per model.
    #[arg(long, default_value_t = 40)]
    timing_images: usize,
    #[arg(long, default_value = "reports/source-models.json")]
    out: PathBuf,
}

/// The domains whose true-pose fired ratio the report lists.
const FIRED_DOMAINS: [&str; 3] = ["source", "combined", "occ-l1"];

struct Entry {
    name: String,
    dir: PathBuf,
    model: Model,
    eval: Value,
    solver: PoseSolver,
}

pub fn run(args: &Args) -> Result<()> {
    let entries = args.models.iter().map(|spec| open(spec)).collect::<Result<Vec<_>>>()?;
    if !entries.iter().any(|e| e.name == args.shipped) {
        bail!("--shipped {} is none of the --model names", args.shipped);
    }
    let timings = time_models(&entries, &args.data, args.timing_images)?;
    let mut models = serde_json::Map::new();
    for (e, (backbone_ms, estimate_ms)) in entries.iter().zip(timings) {
        models.insert(e.name.clone(), describe(e, backbone_ms, estimate_ms)?);
    }
    let report = json!({
        "shipped": args.shipped,
        "commit": crate::synth_cmd::git_commit(),
        "machine": crate::eval_cmd::machine(),
        "timing": {"images": args.timing_images, "threads": 1, "split": "source/test"},
        "models": models,
    });
    udapose_lab::atomic::write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    udapose_lab::atomic::write_atomic(&args.out.with_extension("md"), markdown(&report, args).as_bytes())?;
    eprintln!("wrote {} and its .md", args.out.display());
    Ok(())
}

fn open(spec: &str) -> Result<Entry> {
    let parts: Vec<&str> = spec.splitn(3, '=').collect();
    let [name, dir, eval] = parts[..] else { bail!("--model {spec:?}: expected NAME=MODEL_DIR=EVAL_JSON") };
    let dir = PathBuf::from(dir);
    let model = checkpoint::load(&dir, tch::Device::Cpu).with_context(|| format!("loading {}", dir.display()))?;
    let mut domains = serde_json::Map::new();
    let mut sources = Vec::new();
    for file in eval.split(',') {
        let report: Value =
            serde_json::from_str(&std::fs::read_to_string(file).with_context(|| format!("reading {file}"))?)?;
        if report["split"] != "test" {
            bail!("{file}: an eval report of the test splits is needed, this one is of {}", report["split"]);
        }
        domains.extend(report["domains"].as_object().cloned().unwrap_or_default());
        sources.push(json!({"file": file, "commit": report["commit"]}));
    }
    let eval = json!({"domains": domains, "sources": sources});
    let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, model.manifest.crop, SolverConfig::default())?;
    Ok(Entry { name: name.to_string(), dir, model, eval, solver })
}

/// Median backbone ms per crop and estimate ms per image (backbone + solver) of each model, on
/// one thread, the models interleaved per image.
fn time_models(entries: &[Entry], data: &Path, n: usize) -> Result<Vec<(f64, f64)>> {
    let threads = tch::get_num_threads();
    tch::set_num_threads(1);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let split = SyncarSplit::open(data, "source", "test")?;
    let mut samples = vec![(Vec::new(), Vec::new()); entries.len()];
    for i in 0..n.min(split.len()) {
        let s = load_sample(&split, i)?;
        let image = Tensor::from_slice(&s.pixels).reshape([1, 3, s.height as i64, s.width as i64]);
        for (e, (backbone, total)) in entries.iter().zip(samples.iter_mut()) {
            let started = Instant::now();
            let features = estimator::features(&e.model.backbone, &image)?;
            let after_backbone = started.elapsed();
            let solver = &e.solver;
            pool.install(|| solver.solve(&features[0]))?;
            backbone.push(after_backbone.as_secs_f64() * 1e3);
            total.push(started.elapsed().as_secs_f64() * 1e3);
        }
    }
    tch::set_num_threads(threads);
    Ok(samples.into_iter().map(|(b, t)| (median(b), median(t))).collect())
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn describe(e: &Entry, backbone_ms: f64, estimate_ms: f64) -> Result<Value> {
    let m = &e.model.manifest;
    let params: i64 = e.model.vs.trainable_variables().iter().map(|t| t.numel() as i64).sum();
    let bytes: u64 = [checkpoint::BACKBONE_FILE, checkpoint::MESH_FILE, checkpoint::MANIFEST]
        .iter()
        .map(|f| file_size(&e.dir.join(f)))
        .sum();
    let tau: Vec<f64> = Vec::<f32>::try_from(&e.model.neural_mesh.tau)?.into_iter().map(f64::from).collect();
    let domains = e.eval["domains"].as_object().context("eval report without domains")?;
    let fired: BTreeMap<&str, Value> = FIRED_DOMAINS
        .iter()
        .map(|d| {
            let ratios: Vec<f64> = domains
                .get(*d)
                .and_then(|v| v["fired_ratios"].as_array())
                .map(|a| a.iter().filter_map(Value::as_f64).collect())
                .unwrap_or_default();
            (*d, if ratios.is_empty() { Value::Null } else { json!(mean(&ratios)) })
        })
        .collect();
    let keep = ["acc_pi_6", "acc_pi_6_ci", "acc_pi_18", "med_err_deg", "n"];
    let per_domain: serde_json::Map<String, Value> = domains
        .iter()
        .map(|(d, v)| (d.clone(), json!(keep.iter().map(|k| (*k, v[*k].clone())).collect::<BTreeMap<_, _>>())))
        .collect();
    Ok(json!({
        "arch": m.backbone.name(),
        "variant": m.backbone.lite_variant(),
        "version": m.version,
        "dir": e.dir.display().to_string(),
        "params": params,
        "bytes": bytes,
        "dtype": m.dtype,
        "backbone_ms": backbone_ms,
        "estimate_ms": estimate_ms,
        "tau_median": median(tau),
        "fired_true_pose": fired,
        "train_seconds": m.training["train_seconds"],
        "device": m.training["device"],
        "training_command": m.training["command"],
        "eval_reports": e.eval["sources"],
        "domains": per_domain,
    }))
}

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

fn acc(model: &Value, domain: &str) -> Option<f64> {
    model["domains"][domain]["acc_pi_6"].as_f64()
}

fn markdown(report: &Value, args: &Args) -> String {
    let models = report["models"].as_object().cloned().unwrap_or_default();
    let names: Vec<&String> = models.keys().collect();
    let cmd = args.models.iter().map(|m| format!("--model {m}")).collect::<Vec<_>>().join(" ");
    let mut md = format!(
        "# Source models side by side\n\n`udapose-lab compare {cmd} --shipped {} --data {}`, commit `{}`, {}. \
         Accuracy from each model's `udapose-lab eval` report on the 30 `test` splits (300 images each; \
         in brackets 95% bootstrap intervals); costs measured in this run on {} source crops, one thread, \
         models interleaved per image (medians).\n\nShipped: **{}**.\n\n",
        args.shipped,
        args.data.display(),
        report["commit"].as_str().unwrap_or("?"),
        report["machine"].as_str().unwrap_or("?"),
        args.timing_images,
        args.shipped
    );
    let row = |label: &str, f: &dyn Fn(&Value) -> String| {
        format!("| {label} | {} |\n", names.iter().map(|n| f(&models[*n])).collect::<Vec<_>>().join(" | "))
    };
    md += &format!(
        "| | {} |\n|---|{}\n",
        names.iter().map(|n| format!("`{n}`")).collect::<Vec<_>>().join(" | "),
        "---:|".repeat(names.len())
    );
    md += &row("arch", &|m| m["arch"].as_str().unwrap_or("?").to_string());
    md += &row("parameters", &|m| format!("{:.1} M", m["params"].as_f64().unwrap_or(0.0) / 1e6));
    md += &row("size on disk", &|m| {
        format!("{:.1} MB ({})", m["bytes"].as_f64().unwrap_or(0.0) / 1e6, m["dtype"].as_str().unwrap_or("?"))
    });
    md += &row("training", &|m| {
        format!("{:.0} s on {}", m["train_seconds"].as_f64().unwrap_or(0.0), m["device"].as_str().unwrap_or("?"))
    });
    md += &row("backbone ms / crop", &|m| format!("{:.1}", m["backbone_ms"].as_f64().unwrap_or(f64::NAN)));
    md += &row("estimate ms / image", &|m| format!("{:.1}", m["estimate_ms"].as_f64().unwrap_or(f64::NAN)));
    md += &row("τ_r median", &|m| format!("{:.3}", m["tau_median"].as_f64().unwrap_or(f64::NAN)));
    for d in FIRED_DOMAINS {
        md += &row(&format!("fired at true pose, {d}"), &|m| {
            format!("{:.3}", m["fired_true_pose"][d].as_f64().unwrap_or(f64::NAN))
        });
    }
    md += &row("source: Acc@π/6 / Acc@π/18 / MedErr", &|m| {
        let s = &m["domains"]["source"];
        format!(
            "{:.3} / {:.3} / {:.1}°",
            s["acc_pi_6"].as_f64().unwrap_or(f64::NAN),
            s["acc_pi_18"].as_f64().unwrap_or(f64::NAN),
            s["med_err_deg"].as_f64().unwrap_or(f64::NAN)
        )
    });
    md += &row("mean Acc@π/6, 29 shifted domains", &|m| {
        let shifted: Vec<f64> = m["domains"]
            .as_object()
            .map(|d| d.keys().filter(|k| *k != "source").filter_map(|k| acc(m, k)).collect())
            .unwrap_or_default();
        format!("{:.3} (n = {})", mean(&shifted), shifted.len())
    });
    md + &domain_table(&models, &names)
}

/// Acc@π/6 per domain (rows) and model (columns), with intervals.
fn domain_table(models: &serde_json::Map<String, Value>, names: &[&String]) -> String {
    let row = |label: &str, f: &dyn Fn(&Value) -> String| {
        format!("| {label} | {} |\n", names.iter().map(|n| f(&models[*n])).collect::<Vec<_>>().join(" | "))
    };
    let mut md = String::from("\n## Acc@π/6 per domain (test splits)\n\n");
    md += &format!(
        "| domain | {} |\n|---|{}\n",
        names.iter().map(|n| format!("`{n}`")).collect::<Vec<_>>().join(" | "),
        "---:|".repeat(names.len())
    );
    let domains: Vec<String> = models
        .values()
        .next()
        .and_then(|m| m["domains"].as_object())
        .map(|d| d.keys().cloned().collect())
        .unwrap_or_default();
    for d in &domains {
        md += &row(d, &|m| {
            let v = &m["domains"][d.as_str()];
            match (v["acc_pi_6"].as_f64(), v["acc_pi_6_ci"].as_array()) {
                (Some(a), Some(ci)) => format!(
                    "{a:.3} [{:.3}, {:.3}]",
                    ci[0].as_f64().unwrap_or(f64::NAN),
                    ci[1].as_f64().unwrap_or(f64::NAN)
                ),
                _ => "—".into(),
            }
        });
    }
    md
}
