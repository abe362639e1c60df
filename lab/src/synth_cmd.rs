//! `udapose-lab synth`: renders SynCar-OOD into a directory, or preview sheets of it.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde_json::json;
use udapose_lab::assets::category::Category;
use udapose_lab::assets::{Assets, DEFAULT_TORCS_DIR};
use udapose_lab::atomic::write_atomic;
use udapose_lab::datasets::syncar::{SplitPaths, write_syncar_annotation, write_syncar_list};
use udapose_lab::preview::{contact_sheet, draw_cuboid, draw_segment};
use udapose_lab::render::Renderer;
use udapose_lab::synth::{self, Domain, Profile, Sample, World, all_domains};

#[derive(clap::Args)]
pub struct Args {
    /// Size of the benchmark: quick (tests), standard (reported numbers on CPU), full (GPU).
    #[arg(long, value_enum, default_value = "quick")]
    profile: Profile,
    /// The object category (all but car need `make assets-all`).
    #[arg(long, value_enum, default_value = "car")]
    category: Category,
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
    /// With --preview: also an orientation sheet, a row per model (4 azimuths, the canonical
    /// front marked), to check each model's front.
    #[arg(long, requires = "preview")]
    orientation: bool,
    /// Where --preview writes its sheets.
    #[arg(long, default_value = "reports/syncar-preview")]
    preview_dir: PathBuf,
    /// Write the generation times to this Markdown report.
    #[arg(long)]
    report: Option<PathBuf>,
    /// TORCS data directory (Debian package torcs-data).
    #[arg(long, default_value = DEFAULT_TORCS_DIR)]
    torcs: PathBuf,
    /// FlightGear data directory (Debian package flightgear-data-base): aeroplanes and buses.
    #[arg(long, default_value = udapose_lab::assets::flightgear::DEFAULT_DIR)]
    flightgear: PathBuf,
    /// Sweet Home 3D furniture libraries (Debian package sweethome3d-furniture).
    #[arg(long, default_value = udapose_lab::assets::sweethome::DEFAULT_DIR)]
    sweethome: PathBuf,
    /// Cache of converted meshes (default: $UDAPOSE_CACHE/assets, or ~/.cache/udapose/assets).
    #[arg(long)]
    asset_cache: Option<PathBuf>,
}

pub fn run(args: &Args) -> Result<()> {
    let cache = args.asset_cache.clone().unwrap_or_else(default_asset_cache);
    let mut assets = Assets::open(&args.torcs, &cache)?;
    assets.flightgear.clone_from(&args.flightgear);
    assets.sweethome.clone_from(&args.sweethome);
    let started = Instant::now();
    let (height, width) = args.profile.crop();
    let category = args.category.name();
    let world = World::load(&assets, args.category, height)
        .with_context(|| format!("loading the {category} models and backgrounds"))?;
    eprintln!(
        "loaded {} {category} models ({} source, {} shape), {} source and {} context backgrounds in {:.1} s",
        world.models.len(),
        world.catalogue.source.len(),
        world.catalogue.shape.len(),
        world.backgrounds.source.len(),
        world.backgrounds.context.len(),
        started.elapsed().as_secs_f64()
    );
    let domains = selected(&args.domains)?;
    if args.preview {
        if args.orientation {
            orientation_sheets(&world, args)?;
        }
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
    let dirs = SplitPaths::of_category(out, &domain.name, split, args.category.name());
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
        "category": args.category,
        "models": {"source": world.catalogue.source, "shape": world.catalogue.shape},
        "cuboid": {"min": world.cuboid.min, "max": world.cuboid.max},
        "backgrounds": {"source": world.backgrounds.source.len(), "context": world.backgrounds.context.len()},
        "assets": {
            "torcs-data": package_version("torcs-data"),
            "assimp-utils": package_version("assimp-utils"),
            "flightgear-data-base": package_version("flightgear-data-base"),
            "sweethome3d-furniture": package_version("sweethome3d-furniture"),
        },
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
        let path = args.preview_dir.join(format!("{}{}.png", sheet_prefix(args), domain.name.replace('/', "-")));
        contact_sheet(&images, 4).save(&path).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

/// Sheet names: `<domain>.png` for cars (as always), `<category>-<domain>.png` for the others.
fn sheet_prefix(args: &Args) -> String {
    match args.category {
        Category::Car => String::new(),
        other => format!("{}-", other.name()),
    }
}

/// One row per model (source models, then shape models, in catalogue order), one column per
/// azimuth (0°: the front; 45°; 90°: the left side, front to the left; 135°) at 20° elevation,
/// over grey, with the category cuboid and the canonical front (−y) as a green line from the
/// centre: on a correctly oriented model it points at the object's front in every column.
fn orientation_sheets(world: &World, args: &Args) -> Result<()> {
    let (height, width) = args.profile.crop();
    let background = image::RgbImage::from_pixel(width as u32, height as u32, image::Rgb([128, 128, 128]));
    let light = udapose_lab::render::Light { direction: [0.3, -0.5, 0.8], ambient: 0.45, diffuse: 0.6 };
    let camera = udapose_engine::Camera::for_crop(height, width)?;
    let images: Vec<image::RgbImage> = world
        .models
        .par_iter()
        .flat_map_iter(|(_, model)| (0..4).map(move |k| (model, k)))
        .map_init(
            || Renderer::new(synth::SUPERSAMPLE),
            |renderer, (model, k)| -> Result<image::RgbImage> {
                let angles = [k as f64 * std::f64::consts::FRAC_PI_4, 20f64.to_radians(), 0.0];
                let distance = udapose_engine::camera::fit_distance(model.mesh.vertices(), angles, &camera, 0.85)?;
                let pose = udapose_engine::Pose::new(angles[0], angles[1], angles[2], distance);
                let layer = renderer.render(model, None, &pose, height, width, &light)?;
                let (mut image, _) = layer.composite(&background);
                draw_cuboid(&mut image, &world.cuboid, &pose, [255, 40, 40]);
                draw_segment(&mut image, [0.0; 3], [0.0, -0.6, 0.0], &pose, [40, 220, 40]);
                Ok(image)
            },
        )
        .collect::<Result<_>>()?;
    std::fs::create_dir_all(&args.preview_dir)?;
    let path = args.preview_dir.join(format!("{}-orientation.png", args.category.name()));
    contact_sheet(&images, 4).save(&path).with_context(|| format!("writing {}", path.display()))?;
    eprintln!(
        "wrote {} (rows: {})",
        path.display(),
        world.models.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>().join(", ")
    );
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
