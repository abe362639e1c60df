//! `udapose-lab report`: the SynCar-OOD report (BENCHMARK.md §6). Every stage — synth, source
//! training, and per domain the source evaluation, adaptation, oracles, global-filter ablation
//! and their evaluations — is this binary run as a subprocess whose output is cached on disk,
//! so an interrupted report resumes where it stopped and `--no-run` reports what is cached.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};
use udapose_lab::assets::category::Category;
use udapose_lab::datasets::syncar::SplitPaths;

use crate::plot;

mod acceptance;
mod commits;
mod outputs;
mod resumed;
mod seeds;
mod stats;

use stats::{f, gain, gap_closed, mean, mean_of, metrics, model_version};

/// Domains adapted in `standard` (BENCHMARK.md §5), in the order they run: the acceptance
/// domains first. `source` is adapted too, for the cost of adapting in-domain.
const DOMAINS: &[&str] = &[
    "source",
    "combined",
    "occ-l1",
    "corrupt/gaussian_noise",
    "corrupt/glass_blur",
    "corrupt/fog",
    "corrupt/contrast",
    "corrupt/speckle_noise",
    "shape",
    "texture",
    "context",
    "weather",
    "pose",
    "occ-l2",
    "extreme-l2",
];

/// Domains that also get the global-filter ablation, and whose gap closed the issue checks:
/// combined, occ-l1 and the 5 corruptions.
const ABLATION: &[&str] = DOMAINS.split_at(8).0.split_at(1).1;

/// Domains that also get the strong oracle (labels until the loss stops falling), the yardstick
/// of the adaptation issue's gap-closed targets: the ablation's, shape and pose.
fn strong_domains() -> Vec<&'static str> {
    ABLATION.iter().copied().chain(["shape", "pose"]).collect()
}

/// The strong oracle's settings: lr 1e-4, at least 10 passes, until a pass's loss is no longer
/// 1% below the best earlier one's.
const STRONG_FLAGS: &[&str] = &["--until-plateau", "--lr", "1e-4", "--min-passes", "10"];

/// Gap closed is n/a below this oracle − source difference (BENCHMARK.md §6).
const MIN_GAP: f64 = 0.05;

#[derive(clap::Args)]
pub struct Args {
    /// Benchmark profile: quick, standard or full.
    #[arg(long, default_value = "standard")]
    profile: String,
    /// The object category (its dataset, model and work folder by default).
    #[arg(long, value_enum, default_value = "car")]
    category: Category,
    /// SynCar-OOD root (default: data/syncar-ood-<profile>, -<category> after it for categories
    /// other than car; rendered when missing).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Source model (default: models/<category> for standard, else trained into the work folder).
    #[arg(long)]
    source: Option<PathBuf>,
    /// Where the stages cache their models and evaluations (default: data/report-<profile>,
    /// with -<category> as for --data).
    #[arg(long)]
    work: Option<PathBuf>,
    /// Domains to adapt (default: BENCHMARK.md §5's list).
    #[arg(long, value_delimiter = ',')]
    domains: Vec<String>,
    /// Domains that also get the global-filter ablation (default: combined, occ-l1, 5 corruptions).
    #[arg(long, value_delimiter = ',')]
    ablation: Vec<String>,
    /// Domains that also get the strong oracle (default: the ablation's, shape and pose).
    #[arg(long, value_delimiter = ',')]
    strong: Vec<String>,
    /// Write the report from the cached stages only; run nothing.
    #[arg(long)]
    no_run: bool,
    /// Report (JSON; a Markdown twin and a folder of PNGs of the same name are written next to
    /// it; default: reports/syncar-ood.json, reports/syncar-ood-<category>.json for the others).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Extra flags for every `adapt` run (e.g. "--max-rounds 4"), space-separated.
    #[arg(long, default_value = "")]
    adapt_flags: String,
    /// Adaptations per domain, seeds 0 (the `adapted` model) to N − 1: the report gives their
    /// mean and range.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    seeds: u64,
}

/// The source model and the models derived from it per domain.
#[derive(Clone, Copy, PartialEq)]
enum Variant {
    Source,
    /// Only the target BatchNorm statistics (AdaBN, 3DUDA's first step here): what the EM adds
    /// on top of it is the difference to `Adapted`.
    BatchnormOnly,
    Adapted,
    /// Labels, the adaptation's budget.
    Oracle,
    /// Labels, until the loss stops falling ([`STRONG_FLAGS`]).
    StrongOracle,
    Global,
}

impl Variant {
    fn name(self) -> &'static str {
        match self {
            Variant::Source => "source",
            Variant::BatchnormOnly => "batchnorm_only",
            Variant::Adapted => "adapted",
            Variant::Oracle => "oracle",
            Variant::StrongOracle => "strong_oracle",
            Variant::Global => "global_filter",
        }
    }
}

const VARIANTS: [Variant; 6] = [
    Variant::Source,
    Variant::BatchnormOnly,
    Variant::Adapted,
    Variant::Oracle,
    Variant::StrongOracle,
    Variant::Global,
];

struct Report<'a> {
    args: &'a Args,
    data: PathBuf,
    source: PathBuf,
    work: PathBuf,
    out: PathBuf,
    timings: BTreeMap<String, f64>,
}

pub fn run(args: &Args) -> Result<()> {
    let suffix = match args.category {
        Category::Car => String::new(),
        other => format!("-{}", other.name()),
    };
    let data = args.data.clone().unwrap_or_else(|| PathBuf::from(format!("data/syncar-ood-{}{suffix}", args.profile)));
    let work = args.work.clone().unwrap_or_else(|| PathBuf::from(format!("data/report-{}{suffix}", args.profile)));
    let source = args.source.clone().unwrap_or_else(|| {
        if args.profile == "standard" {
            PathBuf::from("models").join(args.category.name())
        } else {
            work.join("source-model")
        }
    });
    std::fs::create_dir_all(&work)?;
    let timings = std::fs::read_to_string(work.join("timings.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default();
    let out = args.out.clone().unwrap_or_else(|| PathBuf::from(format!("reports/syncar-ood{suffix}.json")));
    let mut r = Report { args, data, source, work, out, timings };
    let domains: Vec<String> =
        if args.domains.is_empty() { DOMAINS.iter().map(|d| d.to_string()).collect() } else { args.domains.clone() };
    let ablation: Vec<String> =
        if args.ablation.is_empty() { ABLATION.iter().map(|d| d.to_string()).collect() } else { args.ablation.clone() };
    if !args.no_run {
        r.prepare()?;
        let strong: Vec<String> = if args.strong.is_empty() {
            strong_domains().into_iter().map(Into::into).collect()
        } else {
            args.strong.clone()
        };
        for d in &domains {
            r.run_domain(d, ablation.contains(d), strong.contains(d))?;
        }
    }
    r.write(&domains)
}

impl Report<'_> {
    /// The dataset and the source model.
    fn prepare(&mut self) -> Result<()> {
        if !self.data.join("manifest.json").is_file() {
            let (data, profile) = (self.data.display().to_string(), self.args.profile.clone());
            let category = self.args.category.name();
            self.stage(
                "synth",
                &self.data.clone(),
                &["synth", "--profile", &profile, "--category", category, "--out", &data],
            )?;
        }
        if !self.source.join("manifest.json").is_file() {
            let (data, out) = (self.data.display().to_string(), self.source.display().to_string());
            self.stage("source", &self.source.clone(), &["train", "--data", &data, "--out", &out, "--epochs", "2"])?;
        }
        Ok(())
    }

    fn model_dir(&self, v: Variant, domain: &str) -> PathBuf {
        match v {
            Variant::Source => self.source.clone(),
            _ => self.work.join(v.name()).join(slug(domain)),
        }
    }

    fn eval_file(&self, v: Variant, domain: &str) -> PathBuf {
        self.work.join("eval").join(v.name()).join(format!("{}.json", slug(domain)))
    }

    /// `adapt` from the source on `domain`'s adapt images into `out`, with `--adapt-flags` and
    /// then `more`.
    fn adapt_stage(&mut self, name: &str, domain: &str, out: &Path, more: &[&str]) -> Result<()> {
        let (src, out_s) = (self.source.display().to_string(), out.display().to_string());
        let images = SplitPaths::new(&self.data, domain, "adapt").images.display().to_string();
        let mut cmd = vec!["adapt", "--model", &src, "--images", &images, "--out", &out_s];
        let flags = self.args.adapt_flags.clone();
        cmd.extend(flags.split_whitespace());
        cmd.extend(more);
        self.stage(name, out, &cmd)
    }

    fn run_domain(&mut self, domain: &str, ablation: bool, strong: bool) -> Result<()> {
        let src = self.source.display().to_string();
        let images = SplitPaths::new(&self.data, domain, "adapt").images.display().to_string();
        let adapted = self.model_dir(Variant::Adapted, domain);
        self.adapt_stage(&format!("adapt {domain}"), domain, &adapted, &[])?;
        // α = 1 and no backbone step leave C and the weights as they were (adapt runs no round,
        // AdaptConfig::batchnorm_only): the model differs from the source by its BatchNorm
        // statistics alone.
        let bn = self.model_dir(Variant::BatchnormOnly, domain).display().to_string();
        let flags = ["--max-rounds", "1", "--no-backbone", "--alpha", "1"];
        let mut cmd = vec!["adapt", "--model", &src, "--images", &images, "--out", &bn];
        cmd.extend(flags);
        self.stage(&format!("batchnorm {domain}"), Path::new(&bn), &cmd)?;
        if domain != "source" {
            let oracle = self.model_dir(Variant::Oracle, domain);
            let split = self.data.join(domain).join("adapt").display().to_string();
            let (o, a) = (oracle.display().to_string(), adapted.display().to_string());
            self.stage(
                &format!("oracle {domain}"),
                &oracle,
                &["finetune", "--model", &src, "--data", &split, "--out", &o, "--budget-of", &a],
            )?;
            if strong && !self.saturated(domain)? {
                let strong = self.model_dir(Variant::StrongOracle, domain).display().to_string();
                let mut cmd = vec!["finetune", "--model", &src, "--data", &split, "--out", &strong];
                cmd.extend(STRONG_FLAGS);
                self.stage(&format!("strong oracle {domain}"), Path::new(&strong), &cmd)?;
            }
        }
        if ablation {
            let global = self.model_dir(Variant::Global, domain);
            self.adapt_stage(&format!("global {domain}"), domain, &global, &["--global-filter", "0.5"])?;
        }
        for v in VARIANTS {
            if self.model_dir(v, domain).join("manifest.json").is_file() {
                self.evaluate(v, domain)?;
            }
        }
        self.run_seeds(domain)
    }

    /// The `eval` stage of model `v` on `domain`'s test split.
    fn evaluate(&mut self, v: Variant, domain: &str) -> Result<()> {
        let (model, out) = (self.model_dir(v, domain), self.eval_file(v, domain));
        self.eval_stage(&format!("eval {} {domain}", v.name()), domain, &model, &out)
    }

    /// `eval` of `model` on `domain`'s test split into `out`.
    fn eval_stage(&mut self, name: &str, domain: &str, model: &Path, out: &Path) -> Result<()> {
        let (m, o, d) = (model.display().to_string(), out.display().to_string(), self.data.display().to_string());
        self.stage(name, out, &["eval", "--model", &m, "--data", &d, "--domains", domain, "--out", &o])
    }

    /// Whether the source model leaves less than [`MIN_GAP`] to gain on `domain` (its test
    /// split): no oracle can show a gap there, so the strong oracle's passes are not spent on it.
    fn saturated(&mut self, domain: &str) -> Result<bool> {
        self.evaluate(Variant::Source, domain)?;
        let acc = self.evaluation(Variant::Source, domain).map(|e| f(&e["acc_pi_6"]));
        Ok(acc.is_some_and(|a| a >= 1.0 - MIN_GAP))
    }

    /// Runs `udapose-lab ARGS` unless `output` exists; records its wall time.
    fn stage(&mut self, name: &str, output: &Path, args: &[&str]) -> Result<()> {
        if output.exists() {
            return Ok(());
        }
        if let Some(parent) = output.parent() {
            std::fs::create_dir_all(parent)?;
        }
        eprintln!("== {name}: udapose-lab {}", args.join(" "));
        let started = Instant::now();
        let exe = std::env::current_exe().context("locating udapose-lab")?;
        let status = Command::new(&exe)
            .args(args)
            .status()
            .with_context(|| format!("starting {} for stage {name}", exe.display()))?;
        if !status.success() {
            bail!("stage {name} failed ({status})");
        }
        let seconds = resumed::seconds(output).unwrap_or_else(|| started.elapsed().as_secs_f64());
        self.timings.insert(name.to_string(), seconds);
        let json = serde_json::to_string_pretty(&self.timings)? + "\n";
        udapose_lab::atomic::write_atomic(&self.work.join("timings.json"), json.as_bytes())?;
        Ok(())
    }

    fn evaluation(&self, v: Variant, domain: &str) -> Option<Value> {
        read_evaluation(&self.eval_file(v, domain), domain)
    }

    /// The Markdown report's title, explanation and table header.
    fn table_header(&self, stage_commits: &str) -> String {
        let min_acc = 1.0 - MIN_GAP;
        let (title, flag) = match self.args.category {
            Category::Car => (String::new(), String::new()),
            c => (format!(" ({})", c.name()), format!(" --category {}", c.name())),
        };
        format!(
            "# SynCar-OOD{title}: source vs 3DUDA vs oracle\n\n`udapose-lab report --profile {}{flag}` \
             (stages cached in `{}`), written at commit `{}` from stages run at {stage_commits}, {}. Source model \
             `{}`.\n\nAcc@π/6 per model with its 95% bootstrap interval (1000 resamples of the test images); \
             gap closed = (adapted − source)/(oracle − source) with a paired bootstrap interval, n/a where \
             oracle − source < {MIN_GAP}. With 300 test images an accuracy near 0.8 is known to about \
             ±0.045: differences inside the intervals are not improvements.\n\n\
             3DUDA here starts by replacing the backbone's BatchNorm statistics by the target images' own \
             (AdaBN, label-free; `--no-target-bn` turns it off); *BN only* is that step alone, so what the EM's \
             vertex and backbone updates add is adapted − BN only. The oracle gets the same step.\n\n\
             *EM gain* = adapted − BN only with its paired bootstrap interval. The *oracle* fine-tunes with \
             labels for the adaptation's own budget; the *strong oracle* with labels at lr 1e-4 until its loss on \
             the adapt split stops falling (≥ 10 passes); both leave out the vertices an occluder covers where the \
             data stores occluder masks; the strong oracle is not run where the source already scores ≥ {min_acc:.2} \
             (no gap of {MIN_GAP} can exist). *Gap* is closed against each.\n\n\
             | domain | source | BN only | adapted | oracle | strong oracle | global filter | gap (oracle) | gap (strong) | EM gain | MedErr src → adapted (°) | adapt s |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
            self.args.profile,
            self.work.display(),
            crate::synth_cmd::git_commit(),
            crate::eval_cmd::machine(),
            self.source.display(),
        )
    }

    /// One domain's report entry and its Markdown row.
    fn domain(&self, domain: &str) -> (Value, String) {
        let get = |v| self.evaluation(v, domain);
        let [s, b, a, o, so, g] = VARIANTS.map(get);
        let gap = |oracle: &Option<Value>| match (&s, &a, oracle) {
            (Some(s), Some(a), Some(o)) => gap_closed(s, a, o),
            _ => (None, None),
        };
        let (gap_same, gap_strong) = (gap(&o), gap(&so));
        // What the EM adds to AdaBN, and what the whole adaptation adds to the source.
        let (em, adapt) = (gain(&b, &a), gain(&s, &a));
        let seconds = |what: &str| self.timings.get(&format!("{what} {domain}")).copied();
        let mut entry = json!({
            "source": metrics(&s), "batchnorm_only": metrics(&b), "adapted": metrics(&a), "oracle": metrics(&o),
            "strong_oracle": metrics(&so), "global_filter": metrics(&g),
            "gap_closed": gap_same.0, "gap_closed_ci": gap_same.1,
            "gap_closed_strong": gap_strong.0, "gap_closed_strong_ci": gap_strong.1,
            "em_gain": em.0, "em_gain_ci": em.1, "adapt_gain": adapt.0, "adapt_gain_ci": adapt.1,
            "adapt_seconds": seconds("adapt"), "oracle_seconds": seconds("oracle"),
            "strong_oracle_seconds": seconds("strong oracle"), "global_seconds": seconds("global"),
        });
        entry.as_object_mut().expect("an object").extend(self.seeds_entry(domain, &a));
        let fired = |e: &Option<Value>| e.as_ref().and_then(|e| mean_of(&e["fired_ratios"]));
        entry["fired_ratio"] = json!({"source": fired(&s), "adapted": fired(&a)});
        let cell = |e: &Option<Value>| {
            e.as_ref().map_or("—".to_string(), |e| {
                format!("{:.3} [{:.3}, {:.3}]", f(&e["acc_pi_6"]), f(&e["acc_pi_6_ci"][0]), f(&e["acc_pi_6_ci"][1]))
            })
        };
        let gap_cell = |gap: (Option<f64>, Option<[f64; 2]>), oracle: &Option<Value>| match gap {
            (Some(x), Some([lo, hi])) => format!("{x:.2} [{lo:.2}, {hi:.2}]"),
            (Some(x), None) => format!("{x:.2}"),
            _ if s.is_some() && oracle.is_some() => "n/a".into(),
            _ => "—".into(),
        };
        let em_cell = match em {
            (Some(x), Some([lo, hi])) => format!("{x:+.3} [{lo:+.3}, {hi:+.3}]"),
            _ => "—".into(),
        };
        let med = |e: &Option<Value>| e.as_ref().map_or("—".into(), |e| format!("{:.1}", f(&e["med_err_deg"])));
        let row = format!(
            "| {domain} | {} | {} | {} | {} | {} | {} | {} | {} | {em_cell} | {} → {} | {} |\n",
            cell(&s),
            cell(&b),
            cell(&a),
            cell(&o),
            cell(&so),
            cell(&g),
            gap_cell(gap_same, &o),
            gap_cell(gap_strong, &so),
            med(&s),
            med(&a),
            seconds("adapt").map_or("—".into(), |x| format!("{x:.0}")),
        );
        (entry, row)
    }

    fn write(&self, domains: &[String]) -> Result<()> {
        let mut out = serde_json::Map::new();
        let outputs = outputs::list(&self.work);
        let stage_commits = commits::stages(&outputs);
        let mut md = self.table_header(&commits::markdown(&stage_commits));
        for domain in domains {
            let (entry, row) = self.domain(domain);
            md.push_str(&row);
            out.insert(domain.clone(), entry);
        }
        let resumed = resumed::stages(&self.work, &outputs);
        md.push_str(&resumed::markdown(&resumed));
        md.push_str(&acceptance::markdown(self.args.category, &out));
        md.push_str(&seeds::table(&out));
        if let (Some(s), Some(a)) =
            (self.evaluation(Variant::Source, "combined"), self.evaluation(Variant::Adapted, "combined"))
        {
            md.push_str(&self.figures(&s, &a)?);
        }
        let report = json!({
            "profile": self.args.profile,
            "commit": crate::synth_cmd::git_commit(),
            "machine": crate::eval_cmd::machine(),
            "source_model": self.source.display().to_string(),
            "model": model_version(&self.source),
            "data": self.data.display().to_string(),
            "domains": out,
            "stage_seconds": self.timings,
            "resumed_stages": resumed,
            "stage_commits": stage_commits,
        });
        udapose_lab::atomic::write_atomic(&self.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
        udapose_lab::atomic::write_atomic(&self.out.with_extension("md"), md.as_bytes())?;
        eprintln!("wrote {} and its .md", self.out.display());
        Ok(())
    }

    /// The paper's Fig. 1 and 7 for `combined`: fired-vertex ratio by azimuth and pose errors.
    fn figures(&self, s: &Value, a: &Value) -> Result<String> {
        let stem = self.out.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let dir = self.out.parent().unwrap_or(Path::new(".")).join(&stem);
        std::fs::create_dir_all(&dir)?;
        let v = |e: &Value, k: &str| -> Vec<f64> {
            e[k].as_array().map(|x| x.iter().filter_map(Value::as_f64).collect()).unwrap_or_default()
        };
        let (az, fs, fa) = (v(s, "azimuths_deg"), v(s, "fired_ratios"), v(a, "fired_ratios"));
        plot::polar_histograms(
            &dir.join("fired-polar-combined.png"),
            &[(&az, &fs, plot::BLUE), (&az, &fa, plot::ORANGE)],
            12,
        )?;
        let (es, ea) = (v(s, "errors_deg"), v(a, "errors_deg"));
        plot::histograms(&dir.join("errors-combined.png"), &[(&es, plot::BLUE), (&ea, plot::ORANGE)], 180.0, 18)?;
        Ok(format!(
            "\n## Figures (`combined` test split)\n\n\
             ![fired-vertex ratio by azimuth]({stem}/fired-polar-combined.png)\n\n\
             Share of each image's visible vertices (at its true pose) whose feature fires (cosine above the adaptation's threshold, 0.8 by default), mean per \
             30° azimuth sector (0° at the top, clockwise; rings at 0.25, 0.5, 0.75, 1): source model (blue, left, mean \
             {:.3}) and adapted model (orange, right, mean {:.3}). The paper's Fig. 1.\n\n\
             ![pose-error histogram]({stem}/errors-combined.png)\n\n\
             Rotation errors in 10° bins from 0° to 180°: source (blue) and adapted (orange); grey lines at quarters of \
             the tallest bar. The paper's Fig. 7.\n",
            mean(&fs),
            mean(&fa)
        ))
    }
}

/// `domain`'s entry of an `eval` output, if it was written.
fn read_evaluation(file: &Path, domain: &str) -> Option<Value> {
    let report: Value = serde_json::from_str(&std::fs::read_to_string(file).ok()?).ok()?;
    Some(report["domains"][domain].clone())
}

fn slug(domain: &str) -> String {
    domain.replace('/', "-")
}
