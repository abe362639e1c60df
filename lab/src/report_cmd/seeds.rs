//! Adaptation over seeds: seed 0 is the report's `adapted` model; seeds 1 … N − 1 are the same
//! `adapt` run with `--seed k` (the order of the images in the backbone step and whatever else
//! the seed draws), each evaluated like it. One seed's accuracy can be luck; the mean and the
//! range over seeds say how much of a gain the method makes reliably.

use std::path::PathBuf;

use anyhow::Result;
use serde_json::{Map, Value, json};

use super::{Report, read_evaluation, slug};

impl Report<'_> {
    fn seed_dir(&self, seed: u64, domain: &str) -> PathBuf {
        self.work.join(format!("adapted_seed{seed}")).join(slug(domain))
    }

    fn seed_eval(&self, seed: u64, domain: &str) -> PathBuf {
        self.work.join("eval").join(format!("adapted_seed{seed}")).join(format!("{}.json", slug(domain)))
    }

    /// The extra seeds' adaptations and their evaluations.
    pub(super) fn run_seeds(&mut self, domain: &str) -> Result<()> {
        for seed in 1..self.args.seeds {
            let (dir, eval) = (self.seed_dir(seed, domain), self.seed_eval(seed, domain));
            let k = seed.to_string();
            self.adapt_stage(&format!("adapt seed {seed} {domain}"), domain, &dir, &["--seed", &k])?;
            self.eval_stage(&format!("eval adapted seed {seed} {domain}"), domain, &dir, &eval)?;
        }
        Ok(())
    }

    /// `seeds` (`[{seed, acc_pi_6}]`, the seeds evaluated so far), `seeds_mean` and
    /// `seeds_range` of a domain's entry; `adapted` is seed 0's evaluation.
    pub(super) fn seeds_entry(&self, domain: &str, adapted: &Option<Value>) -> Map<String, Value> {
        let seed0 = adapted.as_ref().and_then(|e| e["acc_pi_6"].as_f64()).map(|a| (0, a));
        let others = (1..self.args.seeds).filter_map(|seed| {
            Some((seed, read_evaluation(&self.seed_eval(seed, domain), domain)?["acc_pi_6"].as_f64()?))
        });
        let accs: Vec<(u64, f64)> = seed0.into_iter().chain(others).collect();
        let values: Vec<f64> = accs.iter().map(|&(_, a)| a).collect();
        let mut entry = Map::new();
        entry.insert(
            "seeds".into(),
            json!(accs.iter().map(|&(seed, a)| json!({"seed": seed, "acc_pi_6": a})).collect::<Vec<_>>()),
        );
        let (lo, hi) = values.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &a| (lo.min(a), hi.max(a)));
        entry.insert("seeds_mean".into(), if values.is_empty() { Value::Null } else { json!(super::mean(&values)) });
        entry.insert("seeds_range".into(), if values.is_empty() { Value::Null } else { json!([lo, hi]) });
        entry
    }
}

/// The Markdown section: per domain with more than one seed evaluated, each seed's Acc@π/6, the
/// mean and the range, beside BN only (what the EM must beat on every seed).
pub(super) fn table(domains: &Map<String, Value>) -> String {
    let rows: Vec<String> = domains
        .iter()
        .filter(|(_, e)| e["seeds"].as_array().is_some_and(|s| s.len() > 1))
        .map(|(d, e)| {
            let seeds: Vec<String> = e["seeds"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|s| format!("{}: {:.3}", s["seed"], s["acc_pi_6"].as_f64().unwrap_or(f64::NAN)))
                .collect();
            let num = |v: &Value| v.as_f64().map_or("—".into(), |x| format!("{x:.3}"));
            format!(
                "| {d} | {} | {} | {} [{}, {}] |\n",
                num(&e["batchnorm_only"]["acc_pi_6"]),
                seeds.join(", "),
                num(&e["seeds_mean"]),
                num(&e["seeds_range"][0]),
                num(&e["seeds_range"][1]),
            )
        })
        .collect();
    if rows.is_empty() {
        return String::new();
    }
    format!(
        "\n## Adaptation over seeds\n\nAcc@π/6 of `adapt --seed k` (seed 0 is the table's *adapted*), their mean \
         and [min, max].\n\n| domain | BN only | seeds | mean [range] |\n|---|---:|---|---:|\n{}",
        rows.concat()
    )
}
