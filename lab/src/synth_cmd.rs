//! `udapose-lab synth`: renders SynCar-OOD into a directory, or preview sheets of it.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde_json::json;
use udapose_lab::assets::{Assets, DEFAULT_TORCS_DIR, SHAPE_CARS, SOURCE_CARS};
use udapose_lab::atomic::write_atomic;
use udapose_lab::datasets::syncar::{SplitPaths, write_syncar_annotation, write_syncar_list};
use udapose_lab::preview::{contact_sheet, draw_cuboid};
use udapose_lab::render::Renderer;
use udapose_lab::synth::{self, Domain, Profile, Sample, World, all_domains};

#[derive(clap::Args)]
pub struct Args {
    /// Size of the benchmark: quick (tests), standard (reported numbers on CPU), full (GPU).
    #[arg(long, value_enum, default_value = "quick")]
    profile: Profile,
    /// Output root (required unless --preview).
    #[arg(long, required_unless_present = "preview")]
    out: Option<PathBuf>,
    /// Seed of every random choice; the same seed gives byte-identical files.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Only these domains (comma-separated, e.g. source,combined,corrupt/fog).
    #[arg(long, value_delimiter = ',')]
    domains: Vec<String>,
    /// Write per-domain contact sheets with the ground-truth cuboid instead of a dataset.
    #[arg(long)]
    preview: bool,
    /// Where --preview writes its sheets.
    #[arg(long, default_value = "reports/syncar-preview")]
    preview_dir: PathBuf,
    /// Write the generation times to this Markdown report.
    #[arg(long)]
    report: Option<PathBuf>,
    /// TORCS data directory (Debian package torcs-data).
    #[arg(long, default_value = DEFAULT_TORCS_DIR)]
    torcs: PathBuf,
    /// Cache of converted meshes (default: $UDAPOSE_CACHE/assets, or ~/.cache/udapose/assets).
    #[arg(long)]
    asset_cache: Option<PathBuf>,
}

pub fn run(args: &Args) -> Result<()> {
    let cache = args.asset_cache.clone().unwrap_or_else(default_asset_cache);
    let assets = Assets::open(&args.torcs, &cache)?;
    let started = Instant::now();
    let (height, width) = args.profile.crop();
    let world = World::load(&assets, height).context("loading cars and backgrounds")?;
    eprintln!(
        "loaded {} cars, {} source and {} context backgrounds in {:.1} s",
        world.cars.len(),
        world.backgrounds.source.len(),
        world.backgrounds.context.len(),
        started.elapsed().as_secs_f64()
    );
    let domains = selected(&args.domains)?;
    if args.preview {
        return preview(&world, args, &domains);
    }
    let out = args.out.as_ref().expect("clap requires --out without --preview");
    let mut times = Vec::new();
    for domain in &domains {
        let t = Instant::now();
        for split in domain.splits {
            generate_split(&world, args, domain, split, out)?;
        }
        times.push((domain.name.clone(), t.elapsed().as_secs_f64()));
    }
    write_manifest(out, args, &world, &domains)?;
    let total = started.elapsed().as_secs_f64();
    eprintln!("SynCar-OOD {:?} written to {} in {total:.1} s", args.profile, out.display());
    if let Some(report) = &args.report {
        write_report(report, args, &times, total, (height, width))?;
    }
    Ok(())
}

fn default_asset_cache() -> PathBuf {
    let root = std::env::var_os("UDAPOSE_CACHE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").unwrap_or_default()).join(".cache").join("udapose"));
    root.join("assets")
}

fn selected(names: &[String]) -> Result<Vec<Domain>> {
    let all = all_domains();
    if names.is_empty() {
        return Ok(all);
    }
    names
        .iter()
        .map(|n| {
            all.iter().find(|d| &d.name == n).cloned().with_context(|| {
                let known: Vec<&str> = all.iter().map(|d| d.name.as_str()).collect();
                format!("unknown domain {n:?}; known: {}", known.join(", "))
            })
        })
        .collect()
}

/// Renders one split (skipping samples already written) and writes its list.
fn generate_split(world: &World, args: &Args, domain: &Domain, split: &str, out: &Path) -> Result<()> {
    let dirs = SplitPaths::new(out, &domain.name, split);
    dirs.create().with_context(|| format!("creating {}", dirs.images.display()))?;
    let n = args.profile.count(split);
    let bar = ProgressBar::new(n as u64).with_style(
        ProgressStyle::with_template("{prefix:>24} [{bar:30}] {pos}/{len} {elapsed} eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(format!("{}/{split}", domain.name));
    (0..n)
        .into_par_iter()
        .map_init(
            || Renderer::new(synth::SUPERSAMPLE),
            |renderer, i| -> Result<()> {
                let name = format!("{i:05}");
                let annotation = dirs.annotations.join(format!("{name}.npz"));
                if !annotation.exists() {
                    let mut rng = synth::sample_rng(args.seed, &domain.name, split, i);
                    let sample = synth::render_sample(world, renderer, args.profile, domain, &mut rng)
                        .with_context(|| format!("{}/{split}/{name}", domain.name))?;
                    write_sample(&dirs, &name, &sample)?;
                }
                bar.inc(1);
                Ok(())
            },
        )
        .collect::<Result<()>>()?;
    bar.finish_and_clear();
    let names: Vec<String> = (0..n).map(|i| format!("{i:05}.png")).collect();
    Ok(write_syncar_list(&dirs.list, &names)?)
}

/// The image first, the annotation last: an annotation on disk means a complete sample.
fn write_sample(dirs: &SplitPaths, name: &str, sample: &Sample) -> Result<()> {
    let mut png = Vec::new();
    sample.image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    write_atomic(&dirs.images.join(format!("{name}.png")), &png)?;
    Ok(write_syncar_annotation(&dirs.annotations.join(format!("{name}.npz")), &sample.annotation)?)
}

fn write_manifest(out: &Path, args: &Args, world: &World, domains: &[Domain]) -> Result<()> {
    let (height, width) = args.profile.crop();
    let counts: serde_json::Map<String, serde_json::Value> = domains
        .iter()
        .map(|d| {
            (
                d.name.clone(),
                json!(
                    d.splits
                        .iter()
                        .map(|s| (s.to_string(), args.profile.count(s)))
                        .collect::<std::collections::BTreeMap<_, _>>()
                ),
            )
        })
        .collect();
    let manifest = json!({
        "dataset": "SynCar-OOD",
        "profile": args.profile,
        "seed": args.seed,
        "crop": {"height": height, "width": width, "viewport": 3000.0 * height as f64 / 256.0},
        "counts": counts,
        "cars": {"source": SOURCE_CARS, "shape": SHAPE_CARS},
        "cuboid": {"min": world.cuboid.min, "max": world.cuboid.max},
        "backgrounds": {"source": world.backgrounds.source.len(), "context": world.backgrounds.context.len()},
        "assets": {"torcs-data": package_version("torcs-data"), "assimp-utils": package_version("assimp-utils")},
        "commit": git_commit(),
    });
    Ok(write_atomic(&out.join("manifest.json"), (serde_json::to_string_pretty(&manifest)? + "\n").as_bytes())?)
}

fn package_version(package: &str) -> String {
    command_output("dpkg-query", &["-W", "-f=${Version}", package]).unwrap_or_else(|| "unknown".into())
}

/// The commit the binary was built from (embedded by build.rs), not that of the directory the
/// command runs in.
pub fn git_commit() -> String {
    udapose_lab::BUILD_COMMIT.to_string()
}

fn command_output(program: &str, args: &[&str]) -> Option<String> {
    let out = std::process::Command::new(program).args(args).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Eight samples per domain (its test split, train for source) with the category cuboid drawn
/// on top: the same samples the dataset holds, since the generator is per sample.
fn preview(world: &World, args: &Args, domains: &[Domain]) -> Result<()> {
    std::fs::create_dir_all(&args.preview_dir)?;
    for domain in domains {
        let split = if domain.name == "source" { "train" } else { "test" };
        let images: Vec<image::RgbImage> = (0..8)
            .into_par_iter()
            .map_init(
                || Renderer::new(synth::SUPERSAMPLE),
                |renderer, i| -> Result<image::RgbImage> {
                    let mut rng = synth::sample_rng(args.seed, &domain.name, split, i);
                    let mut s = synth::render_sample(world, renderer, args.profile, domain, &mut rng)?;
                    draw_cuboid(&mut s.image, &world.cuboid, &s.annotation.pose.pose(), [255, 40, 40]);
                    Ok(s.image)
                },
            )
            .collect::<Result<_>>()?;
        let path = args.preview_dir.join(format!("{}.png", domain.name.replace('/', "-")));
        contact_sheet(&images, 4).save(&path).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

fn write_report(path: &Path, args: &Args, times: &[(String, f64)], total: f64, (h, w): (usize, usize)) -> Result<()> {
    if times.is_empty() {
        bail!("nothing was generated");
    }
    let threads = rayon::current_num_threads();
    let mut md = format!(
        "# SynCar-OOD generation\n\n`udapose-lab synth --profile {} --seed {}` ({h}×{w} crops, {threads} threads), commit `{}`: \
         **{total:.0} s** in all.\n\n| domain | seconds |\n|---|---:|\n",
        args.profile.name(),
        args.seed,
        git_commit()
    );
    for (d, s) in times {
        md.push_str(&format!("| {d} | {s:.1} |\n"));
    }
    // Other work on the machine slows generation down; say how busy it was.
    if let Ok(load) = std::fs::read_to_string("/proc/loadavg") {
        let load: Vec<&str> = load.split_whitespace().take(3).collect();
        md.push_str(&format!("\nLoad average (1, 5, 15 min) when it finished: {}.\n", load.join(", ")));
    }
    std::fs::write(path, md).with_context(|| format!("writing {}", path.display()))
}
