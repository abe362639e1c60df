//! `udapose-lab route`: can an image be matched, from its pixels alone, to the adaptation job
//! whose images it resembles? (issue 19's probe for per-domain experts; engine::signature.)
//!
//! Each domain stands for a job: its signature is fitted, label-free, on the first `--fit`
//! images of its `adapt` split (what a job streams); each `test` image is routed to the most
//! likely signature. The domain names score the routing; no model runs.
//!
//! A second table is what the service's experts use: each domain's [`Domain`] bound (fitted on
//! the same images at `--coverage`) and the share of every domain's test images it takes.

use std::path::PathBuf;

use anyhow::{Context, Result};
use rayon::prelude::*;
use udapose_engine::signature::{Domain, STATS, Signature, image_stats, route};
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::load_annotated;

#[derive(clap::Args)]
pub struct Args {
    /// SynCar-OOD root.
    #[arg(long)]
    data: PathBuf,
    /// The domains, one job each (e.g. source,occ-l1,corrupt/fog).
    #[arg(long, value_delimiter = ',', required = true)]
    domains: Vec<String>,
    /// Adapt images per signature.
    #[arg(long, default_value_t = 200)]
    fit: usize,
    /// The share of its own unseen images each domain's bound is set to take.
    #[arg(long, default_value_t = 0.95)]
    coverage: f64,
    /// The Markdown table (also printed).
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn run(args: &Args) -> Result<()> {
    let fitted = args.domains.iter().map(|d| stats(args, d, "adapt", args.fit)).collect::<Result<Vec<_>>>()?;
    let tests = args.domains.iter().map(|d| stats(args, d, "test", usize::MAX)).collect::<Result<Vec<_>>>()?;
    let signatures = (args.domains.iter().zip(&fitted))
        .map(|(d, s)| Signature::fit(s).with_context(|| format!("fitting {d}")))
        .collect::<Result<Vec<_>>>()?;
    let bounds = (args.domains.iter().zip(&fitted))
        .map(|(d, s)| Domain::fit(s, args.coverage).with_context(|| format!("fitting {d}")))
        .collect::<Result<Vec<_>>>()?;
    let signatures: Vec<&Signature> = signatures.iter().collect();
    let mut table = format!(
        "`udapose-lab route --data {} --domains {} --fit {}`\n\nRows: the test images' domain; columns: \
         where the router sends them (share of the row).\n\n| domain | {} | routed right |\n|---|{}\n",
        args.data.display(),
        args.domains.join(","),
        args.fit,
        args.domains.join(" | "),
        "---:|".repeat(args.domains.len() + 1)
    );
    for (own, (d, test)) in args.domains.iter().zip(&tests).enumerate() {
        let mut routed = vec![0usize; args.domains.len()];
        for s in test {
            if let Some(k) = route(&signatures, s) {
                routed[k] += 1;
            }
        }
        let share = |k: usize| routed[k] as f64 / test.len().max(1) as f64;
        let row: Vec<String> = (0..routed.len()).map(|k| format!("{:.3}", share(k))).collect();
        table += &format!("| {d} | {} | {:.3} |\n", row.join(" | "), share(own));
    }
    table += &format!(
        "\nEach domain's bound alone (`Domain`, coverage {}: what an expert takes). Rows: the test images' \
         domain; columns: the share each domain's bound takes.\n\n| domain | {} |\n|---|{}\n",
        args.coverage,
        args.domains.join(" | "),
        "---:|".repeat(args.domains.len())
    );
    for (d, test) in args.domains.iter().zip(&tests) {
        let row: Vec<String> = bounds
            .iter()
            .map(|b| {
                format!(
                    "{:.3}",
                    test.iter().filter(|s| b.accepts(s).is_some()).count() as f64 / test.len().max(1) as f64
                )
            })
            .collect();
        table += &format!("| {d} | {} |\n", row.join(" | "));
    }
    print!("{table}");
    if let Some(out) = &args.out {
        udapose_lab::atomic::write_atomic(out, table.as_bytes())
            .with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

/// The statistics of the first `limit` images of a split, in parallel.
fn stats(args: &Args, domain: &str, split: &str, limit: usize) -> Result<Vec<[f64; STATS]>> {
    let split = SyncarSplit::open(&args.data, domain, split)?;
    (0..split.len().min(limit))
        .into_par_iter()
        .map(|i| {
            let (pixels, annotation, _) = load_annotated(&split, i)?;
            let size = [annotation.pose.height, annotation.pose.width];
            Ok(image_stats(&pixels, size)?)
        })
        .collect()
}
