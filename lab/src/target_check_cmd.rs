//! `udapose-lab target-check`: what the service's target check reads for one model
//! (`GateConfig::min_target_fired`, README "Online adaptation"): the share of visible vertices
//! that fire to the unchanged model, on images of no object (colour fields and stripes,
//! [`udapose_lab::not_objects`]) and on the first images of each domain's `adapt` split, those
//! a job on that domain would stream. The check can refuse images of no object only where they
//! read below every real domain; reports/target-check.md.

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde_json::json;
use tch::Tensor;
use udapose_engine::adapt::{self, AdaptConfig, SOURCE_CHECK_IMAGES};
use udapose_engine::checkpoint::{self, Model};
use udapose_engine::runtime::RuntimeInfo;
use udapose_lab::datasets::syncar::SyncarSplit;
use udapose_lab::loader::{load_annotated, planar};
use udapose_lab::not_objects::colour_field;

use crate::eval_cmd::domains_present;

#[derive(clap::Args)]
pub struct Args {
    /// The model directory.
    #[arg(long)]
    model: PathBuf,
    /// SynCar-OOD root of the model's category (its `adapt` splits).
    #[arg(long)]
    data: Option<PathBuf>,
    /// The domains to read (default: every domain of --data but source).
    #[arg(long, value_delimiter = ',')]
    domains: Vec<String>,
    /// Write the readings here as JSON (also printed).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Store the threshold in the model's manifest (`min_target_fired`; its tensors and files
    /// stay as they are): halfway between the no-object reading and the lowest domain's.
    #[arg(long, requires = "data")]
    set: bool,
}

/// What the check reads on one set of images: the mean share of firing vertices and its
/// standard error over the images.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
struct Reading {
    mean: f64,
    se: f64,
}

impl Reading {
    fn of(ratios: &[f64]) -> Reading {
        let n = ratios.len() as f64;
        let mean = ratios.iter().sum::<f64>() / n;
        let var =
            if ratios.len() > 1 { ratios.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1.0) } else { 0.0 };
        Reading { mean, se: (var / n).sqrt() }
    }
}

/// Standard errors each reading keeps from the threshold's side: the gate's noise rule.
const SEPARATION_SE: f64 = 2.0;

pub fn run(args: &Args) -> Result<()> {
    let device = RuntimeInfo::detect().device();
    let model = checkpoint::load(&args.model, device).with_context(|| format!("loading {}", args.model.display()))?;
    let [h, w] = model.manifest.crop;
    let config = AdaptConfig::default();
    let fields: Vec<f32> =
        (0..SOURCE_CHECK_IMAGES).flat_map(|i| planar(&colour_field(i, w as u32, h as u32))).collect();
    let no_object = fired(&model, &fields, SOURCE_CHECK_IMAGES, &config)?;
    let mut domains = Vec::new();
    if let Some(data) = &args.data {
        for domain in domain_names(data, &args.domains)? {
            let (pixels, n) = adapt_images(data, &domain, SOURCE_CHECK_IMAGES)?;
            domains.push((domain, fired(&model, &pixels, n, &config)?));
        }
    }
    println!(
        "{} ({}), {} images per set: mean share of visible vertices that fire ± SE",
        model.manifest.version, model.manifest.category, SOURCE_CHECK_IMAGES
    );
    println!("{:.4} ± {:.4}\tno object (colour fields)", no_object.mean, no_object.se);
    for (set, r) in &domains {
        println!("{:.4} ± {:.4}\t{set}", r.mean, r.se);
    }
    let readings: Vec<Reading> = domains.iter().map(|d| d.1).collect();
    let threshold = threshold(no_object, &readings);
    match threshold {
        Some(t) => println!("threshold {t:.4}: halfway between no object and the lowest domain"),
        None if args.data.is_some() => {
            println!("no threshold: no object and the lowest domain are not {SEPARATION_SE} SE apart each")
        }
        None => {}
    }
    if let Some(out) = &args.out {
        let report = json!({
            "command": std::env::args().collect::<Vec<_>>().join(" "),
            "commit": crate::synth_cmd::git_commit(),
            "category": model.manifest.category,
            "version": model.manifest.version,
            "images": SOURCE_CHECK_IMAGES,
            "no_object": no_object,
            "domains": domains.iter().map(|(d, r)| (d.clone(), json!(r))).collect::<serde_json::Map<_, _>>(),
            "threshold": threshold,
        });
        udapose_lab::atomic::write_atomic(out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())
            .with_context(|| format!("writing {}", out.display()))?;
    }
    if args.set {
        let t = threshold.context("no threshold separates images of no object from the domains; nothing set")?;
        let mut manifest = model.manifest.clone();
        manifest.min_target_fired = Some(t);
        let path = args.model.join(checkpoint::MANIFEST);
        let json = serde_json::to_string_pretty(&manifest)? + "\n";
        udapose_lab::atomic::write_atomic(&path, json.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
        println!("set min_target_fired {t:.4} in {}", path.display());
    }
    Ok(())
}

/// Halfway between what images of no object read and the lowest domain's reading, as far from
/// each as the readings allow (4 decimals); `None` without domains, or where the two are not
/// [`SEPARATION_SE`] standard errors each from a common point (no threshold separates them
/// beyond noise).
fn threshold(no_object: Reading, domains: &[Reading]) -> Option<f64> {
    let lowest = domains.iter().copied().min_by(|a, b| a.mean.total_cmp(&b.mean))?;
    let apart = lowest.mean - SEPARATION_SE * lowest.se > no_object.mean + SEPARATION_SE * no_object.se;
    apart.then(|| ((no_object.mean + lowest.mean) / 2.0 * 1e4).round() / 1e4)
}

/// What the check reads on `n` planar images (the job's first images).
fn fired(model: &Model, pixels: &[f32], n: usize, config: &AdaptConfig) -> Result<Reading> {
    let [h, w] = model.manifest.crop;
    if pixels.len() != n * 3 * h * w {
        bail!("the images are not the model's {w}x{h} crop");
    }
    let images = Tensor::from_slice(pixels).reshape([n as i64, 3, h as i64, w as i64]);
    Ok(Reading::of(&adapt::source_fired(model, &images, config, &mut |_| ControlFlow::Continue(()))?))
}

/// The domains asked for, or every domain of `data` with an adapt split but source.
fn domain_names(data: &Path, asked: &[String]) -> Result<Vec<String>> {
    if !asked.is_empty() {
        return Ok(asked.to_vec());
    }
    let found: Vec<String> = domains_present(data, "adapt").into_iter().filter(|d| d != "source").collect();
    if found.is_empty() {
        bail!("{} holds no domain with an adapt split", data.display());
    }
    Ok(found)
}

/// The first `n` images of a domain's adapt split, planar.
fn adapt_images(data: &Path, domain: &str, n: usize) -> Result<(Vec<f32>, usize)> {
    let split = SyncarSplit::open(data, domain, "adapt").with_context(|| format!("opening {domain}/adapt"))?;
    let n = n.min(split.len());
    if n == 0 {
        bail!("{domain}/adapt has no image");
    }
    let mut pixels = Vec::new();
    for i in 0..n {
        pixels.extend(load_annotated(&split, i)?.0);
    }
    Ok((pixels, n))
}

#[cfg(test)]
mod tests {
    use super::{Reading, threshold};

    fn r(mean: f64, se: f64) -> Reading {
        Reading { mean, se }
    }

    #[test]
    fn the_threshold_sits_halfway_and_only_where_it_separates_beyond_noise() {
        assert_eq!(threshold(r(0.0, 0.0), &[r(0.6, 0.01), r(0.0433, 0.005), r(0.2, 0.02)]), Some(0.0217));
        assert_eq!(threshold(r(0.0322, 0.004), &[r(0.2292, 0.02), r(0.5, 0.01)]), Some(0.1307));
        // The lowest domain by its mean decides, and its noise counts: 0.1242 + 2·0.002 is above
        // 0.1312 − 2·0.004.
        assert_eq!(threshold(r(0.1242, 0.002), &[r(0.1312, 0.004), r(0.6, 0.01)]), None);
        assert_eq!(threshold(r(0.2, 0.0), &[r(0.6, 0.0), r(0.15, 0.0)]), None, "a domain reads lower");
        assert_eq!(threshold(r(0.0, 0.0), &[]), None);
    }

    #[test]
    fn a_reading_is_the_mean_and_its_standard_error() {
        let x = Reading::of(&[0.1, 0.3]);
        assert!((x.mean - 0.2).abs() < 1e-12 && (x.se - 0.1).abs() < 1e-12, "{x:?}");
        assert_eq!(Reading::of(&[0.5]), r(0.5, 0.0));
    }
}
