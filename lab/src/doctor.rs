//! `udapose-lab doctor`: what this machine offers udapose.

use std::path::{Path, PathBuf};

use serde::Serialize;
use udapose_engine::runtime::RuntimeInfo;

#[derive(clap::Args)]
pub struct Args {
    /// Directory of shipped models (one `<category>/` per model).
    #[arg(long, default_value = "models")]
    models: PathBuf,
    /// Root of generated datasets (SynCar-OOD profiles live in `<data>/syncar-ood-<profile>`).
    #[arg(long, default_value = "data")]
    data: PathBuf,
    /// TORCS data directory (Debian package `torcs-data`), the source of SynCar-OOD's cars.
    #[arg(long, default_value = "/usr/share/games/torcs")]
    torcs: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct Report {
    runtime: RuntimeInfo,
    device: String,
    assets: Vec<Asset>,
}

#[derive(Serialize)]
struct Asset {
    name: &'static str,
    path: String,
    available: bool,
    detail: String,
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    let runtime = RuntimeInfo::detect();
    let report = Report { device: format!("{:?}", runtime.device()), runtime, assets: assets(args) };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    let r = &report.runtime;
    println!("torch            {}", r.torch_version);
    println!(
        "device           {} (CUDA available: {}, GPUs: {}, cuDNN: {})",
        report.device, r.cuda_available, r.cuda_devices, r.cudnn_available
    );
    println!(
        "threads          torch intra-op {}, inter-op {}, rayon {}, CPUs {}",
        r.torch_threads, r.torch_interop_threads, r.rayon_threads, r.cpus
    );
    for a in &report.assets {
        let mark = if a.available { "yes" } else { "no " };
        println!("{:<16} {mark}  {}  {}", a.name, a.path, a.detail);
    }
    Ok(())
}

fn assets(args: &Args) -> Vec<Asset> {
    let models = subdirs(&args.models).into_iter().filter(|d| d.join("manifest.json").is_file()).count();
    let datasets: Vec<String> = subdirs(&args.data)
        .into_iter()
        .filter(|d| d.join("manifest.json").is_file())
        .filter_map(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    let cars = subdirs(&args.torcs.join("cars")).len();
    vec![
        Asset {
            name: "models",
            path: args.models.display().to_string(),
            available: models > 0,
            detail: format!("{models} model(s) with a manifest"),
        },
        Asset {
            name: "datasets",
            path: args.data.display().to_string(),
            available: !datasets.is_empty(),
            detail: if datasets.is_empty() { "none generated yet".into() } else { datasets.join(", ") },
        },
        Asset {
            name: "torcs-data",
            path: args.torcs.display().to_string(),
            available: cars > 0,
            detail: if cars > 0 {
                format!("{cars} car(s)")
            } else {
                "not installed (Debian package torcs-data)".into()
            },
        },
        Asset {
            name: "assimp",
            path: which("assimp").map_or_else(|| "-".into(), |p| p.display().to_string()),
            available: which("assimp").is_some(),
            detail: "mesh converter (Debian package assimp-utils)".into(),
        },
    ]
}

fn subdirs(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .map(|rd| rd.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.is_dir()).collect())
        .unwrap_or_default()
}

fn which(program: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")
        .and_then(|paths| std::env::split_paths(&paths).map(|d| d.join(program)).find(|p| p.is_file()))
}
