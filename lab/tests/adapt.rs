//! 3DUDA on the quick profile, end to end through `udapose-lab report`: adapt, oracle and the
//! global-filter ablation on `combined` (and adapt, oracle on `corrupt/fog`), their
//! evaluations, the report's schema and figures; plus the commands' clear errors.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

const LAB: &str = env!("CARGO_BIN_EXE_udapose-lab");

fn env_path(var: &str) -> PathBuf {
    PathBuf::from(std::env::var_os(var).unwrap_or_else(|| panic!("{var} is set by `make test`")))
}

fn lab(args: &[&str]) -> (bool, String) {
    let out = Command::new(LAB).args(args).output().expect("run udapose-lab");
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-adapt-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn read(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn digest(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap()))
        .collect();
    files.sort();
    files
}

/// `udapose-lab report` on the quick profile: `combined` (adapted, both oracles and the
/// ablation) and `corrupt/fog` (adapted and the same-budget oracle).
fn run_report(data: &Path, source: &Path, work: &Path, out: &Path) -> (bool, String) {
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (data, source, work, out) = (s(data), s(source), s(work), s(out));
    lab(&[
        "report",
        "--profile",
        "quick",
        "--data",
        &data,
        "--source",
        &source,
        "--work",
        &work,
        "--domains",
        "combined,corrupt/fog",
        "--ablation",
        "combined",
        "--strong",
        "combined",
        "--seeds",
        "2",
        "--out",
        &out,
    ])
}

#[test]
fn quick_report_adapts_combined_without_collapsing() {
    let (data, source) = (env_path("UDAPOSE_QUICK_DATA"), env_path("UDAPOSE_QUICK_MODEL"));
    let before = digest(&source);
    let work = tmp("report");
    let out = work.join("reports/syncar-ood.json");
    let (ok, log) = run_report(&data, &source, &work, &out);
    assert!(ok, "report failed:\n{log}");
    assert_eq!(before, digest(&source), "the source model directory changed");

    let report = read(&out);
    assert_eq!(report["profile"], "quick");
    // Every stage ran in this one process tree, so the report names one build for all its
    // outputs: the models of the three fine-tuned variants, the global filter and the second
    // seed, and their evaluations (round snapshots and the source model left out).
    let commits = report["stage_commits"].as_object().unwrap();
    assert_eq!(commits.keys().collect::<Vec<_>>(), [report["commit"].as_str().unwrap()], "{commits:?}");
    assert!(commits.values().all(|n| n.as_u64().unwrap() >= 10), "{commits:?}");
    let d = &report["domains"]["combined"];
    for v in ["source", "adapted", "oracle", "strong_oracle", "global_filter"] {
        let m = &d[v];
        assert_eq!(m["n"], 60, "{v}");
        for k in ["acc_pi_6", "acc_pi_18", "med_err_deg"] {
            assert!(m[k].is_number() && m[format!("{k}_ci")].is_array(), "{v}.{k}");
        }
    }
    // Gap closed = (adapted − source) / (oracle − source) on Acc@π/6, null when the oracle
    // gains less than the report's MIN_GAP (0.05).
    let acc = |v: &str| d[v]["acc_pi_6"].as_f64().unwrap();
    let gap = acc("oracle") - acc("source");
    if gap < 0.05 {
        assert!(d["gap_closed"].is_null(), "oracle gains {gap:.3}: {}", d["gap_closed"]);
    } else {
        let closed = d["gap_closed"].as_f64().unwrap();
        assert!((closed - (acc("adapted") - acc("source")) / gap).abs() < 1e-9, "gap closed {closed}");
        let ci: Vec<f64> = d["gap_closed_ci"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        assert!(ci.len() == 2 && ci[0] <= ci[1], "{ci:?}");
    }
    assert!(d["adapt_seconds"].as_f64().unwrap() > 0.0);

    // The fired-vertex ratio rises over the run, and the adapted model does not collapse: on
    // `combined` the quick model (retrained every run) moves a few images either way (CI saw
    // 34 → 28 of 60, when the test allowed 3), so adaptation must not be *significantly* worse
    // than the source: the paired 95% interval of adapted − source reaches 0. A collapse (α 0.5
    // on fog: −0.19; τ_r on quick: −0.15, reports/adapt-defaults.md) lies wholly below it.
    let manifest = read(&work.join("adapted/combined/manifest.json"));
    // Each round was snapshotted beside the model (to resume an interrupted stage), and the
    // snapshots went once the model was saved.
    for v in ["adapted", "oracle", "strong_oracle"] {
        assert!(!work.join(v).join(".combined.rounds").exists(), "{v}: round snapshots left behind");
    }
    assert!(manifest["training"]["run"]["resumed_after"].is_null());
    assert_eq!(report["resumed_stages"], serde_json::json!({}), "no stage was interrupted");
    let run = &manifest["training"]["run"];
    let (first, last) = (run["fired_ratio_before"].as_f64().unwrap(), run["fired_ratio_after"].as_f64().unwrap());
    assert!(last > first, "fired ratio {first:.3} → {last:.3}");
    let interval = |d: &Value, k: &str| -> [f64; 2] {
        let ci: Vec<f64> = d[k].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        [ci[0], ci[1]]
    };
    let [lo, hi] = interval(d, "adapt_gain_ci");
    let gain = d["adapt_gain"].as_f64().unwrap();
    assert!(lo <= gain && gain <= hi && (gain - (acc("adapted") - acc("source"))).abs() < 1e-9, "{d}");
    assert!(hi >= 0.0, "adapted − source {gain:+.3} [{lo:+.3}, {hi:+.3}] on combined: significantly worse");
    // Seed 0 is the adapted model; seed 1 its own run, whose accuracy the mean and range take in.
    let seeds: Vec<(u64, f64)> = d["seeds"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["seed"].as_u64().unwrap(), s["acc_pi_6"].as_f64().unwrap()))
        .collect();
    assert_eq!(seeds.iter().map(|s| s.0).collect::<Vec<_>>(), [0, 1], "{d}");
    assert_eq!(seeds[0].1, acc("adapted"));
    assert!(work.join("adapted_seed1/combined/manifest.json").is_file());
    let (a0, a1) = (seeds[0].1, seeds[1].1);
    assert!((d["seeds_mean"].as_f64().unwrap() - (a0 + a1) / 2.0).abs() < 1e-9, "{d}");
    assert_eq!(d["seeds_range"], serde_json::json!([a0.min(a1), a0.max(a1)]));
    let em = d["em_gain"].as_f64().unwrap();
    assert!((em - (acc("adapted") - d["batchnorm_only"]["acc_pi_6"].as_f64().unwrap())).abs() < 1e-9, "{d}");

    // Where the method reliably gains: fog. On today's quick model 19 → 33 of 60 images (+14,
    // paired interval [+0.07, +0.40]; BN only 33: all of it AdaBN, as on `standard`), with the
    // fixed-schedule solver as with the default (source 19 of 60 either way, refine_variants).
    // The +31 this test was first tuned on came from an earlier quick model. At least +10
    // images (1/6 of them), with the interval above 0: a collapse lies below the source.
    let fog = &report["domains"]["corrupt/fog"];
    let right = |v: &str| (fog[v]["acc_pi_6"].as_f64().unwrap() * 60.0).round() as i64;
    let [lo, _] = interval(fog, "adapt_gain_ci");
    assert!(
        right("adapted") >= right("source") + 10 && lo > 0.0,
        "fog: {} → {} of 60, {fog}",
        right("source"),
        right("adapted")
    );
    assert_eq!(manifest["training"]["source_version"], read(&source.join("manifest.json"))["version"]);

    // The oracle had the adaptation's budget; the strong one at least 10 passes, and gap closed
    // against it is computed as against the other.
    let oracle = read(&work.join("oracle/combined/manifest.json"));
    assert_eq!(oracle["training"]["backbone_steps"], manifest["training"]["backbone_steps"]);
    let strong = read(&work.join("strong_oracle/combined/manifest.json"));
    assert!(strong["training"]["run"]["rounds"].as_array().unwrap().len() >= 10, "{}", strong["training"]);
    let strong_gap = acc("strong_oracle") - acc("source");
    match d["gap_closed_strong"].as_f64() {
        Some(closed) => assert!((closed - (acc("adapted") - acc("source")) / strong_gap).abs() < 1e-9),
        None => assert!(strong_gap < 0.05, "strong oracle gains {strong_gap:.3} but no gap closed"),
    }
    assert!(report["domains"]["corrupt/fog"]["strong_oracle"].is_null(), "fog has no strong oracle here");

    let md = std::fs::read_to_string(out.with_extension("md")).unwrap();
    assert!(md.contains("| combined |") && md.contains("gap closed"));
    for png in ["fired-polar-combined.png", "errors-combined.png"] {
        let img = image::open(work.join("reports/syncar-ood").join(png)).unwrap();
        assert!(img.width() > 100 && img.height() > 100);
    }

    // Cached: a second run starts no stage and writes the same numbers.
    let (ok, log) = run_report(&data, &source, &work, &out);
    assert!(ok && !log.contains("=="), "{log}");
    assert_eq!(read(&out)["domains"], report["domains"]);
    std::fs::remove_dir_all(&work).unwrap();
}

#[test]
fn adapt_and_finetune_explain_bad_arguments() {
    let (data, source) = (env_path("UDAPOSE_QUICK_DATA"), env_path("UDAPOSE_QUICK_MODEL"));
    let dir = tmp("bad");
    std::fs::create_dir_all(dir.join("empty")).unwrap();
    let s = source.to_str().unwrap();
    let out = dir.join("out");
    let o = out.to_str().unwrap();

    let (ok, log) = lab(&["adapt", "--model", s, "--images", dir.join("empty").to_str().unwrap(), "--out", o]);
    assert!(!ok && log.contains("holds no PNG, JPEG or WebP image"), "{log}");

    // Images of another size than the model's crop.
    let big = dir.join("big");
    std::fs::create_dir_all(&big).unwrap();
    image::RgbImage::new(320, 128).save(big.join("a.png")).unwrap();
    let (ok, log) = lab(&["adapt", "--model", s, "--images", big.to_str().unwrap(), "--out", o]);
    assert!(!ok && log.contains("320x128") && log.contains("160x64"), "{log}");

    // An existing output is never overwritten.
    let (ok, log) = lab(&["adapt", "--model", s, "--images", big.to_str().unwrap(), "--out", s]);
    assert!(!ok && log.contains("already exists"), "{log}");

    let split = data.join("combined/adapt");
    let (ok, log) = lab(&["finetune", "--model", s, "--data", split.to_str().unwrap(), "--out", o]);
    assert!(!ok && log.contains("--steps N, --budget-of ADAPTED_MODEL or --until-plateau"), "{log}");
    let plateau = ["--until-plateau", "--min-passes", "5", "--max-passes", "4"];
    let (ok, log) =
        lab(&[&["finetune", "--model", s, "--data", split.to_str().unwrap(), "--out", o], &plateau[..]].concat());
    assert!(!ok && log.contains("--min-passes is above --max-passes"), "{log}");
    let (ok, log) = lab(&["finetune", "--model", s, "--data", dir.to_str().unwrap(), "--out", o, "--steps", "1"]);
    assert!(!ok && log.contains("not a split directory"), "{log}");
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}
