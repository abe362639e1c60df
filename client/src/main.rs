//! `udapose`: command-line client for a udapose server (gRPC).

use std::{
    io::Read,
    path::{Path, PathBuf},
};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use serde_json::{Value, json};
use udapose_client::{BoundingBox, Client, ClientOptions, ModelInfo, PoseEstimate};
use udapose_proto::v1::{EstimateRequest, EstimateResponse, estimate_request::Input};

/// Talk to a udapose pose-estimation server over gRPC.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    /// The server's gRPC address(es): `host:port` or `http(s)://host:port`, comma-separated to
    /// spread calls over replicas.
    #[arg(long, env = "UDAPOSE_ENDPOINT", default_value = "127.0.0.1:50051", global = true, value_delimiter = ',')]
    endpoint: Vec<String>,
    /// Bearer token.
    #[arg(long, env = "UDAPOSE_TOKEN", hide_env_values = true, global = true)]
    token: Option<String>,
    /// PEM CA certificate to trust for TLS (implies TLS).
    #[arg(long, value_name = "PEM", global = true)]
    ca_cert: Option<PathBuf>,
    /// Name to verify the server's certificate against (default: the endpoint's host).
    #[arg(long, global = true)]
    tls_domain: Option<String>,
    /// Retries of a call answered UNAVAILABLE (overloaded), with backoff.
    #[arg(long, default_value_t = 4, global = true)]
    retries: u32,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List the server's models: category, version being served, and whether it is ready.
    Models {
        /// Print JSON (`{"models": [...]}`) instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Describe one category's model (version, generation, backbone, crop, provenance).
    Describe { category: String },
    /// Estimate the pose in images: files, folders (their PNG/JPEG/WebP files), or `-` (stdin).
    Estimate {
        #[arg(long, default_value = "car")]
        category: String,
        /// A detection box `x0,y0,x1,y1` in image pixels (repeat for several objects); none:
        /// each image is the object's crop.
        #[arg(long, value_parser = parse_box)]
        bbox: Vec<BoundingBox>,
        /// One JSON object per image (as the HTTP API answers) instead of a table.
        #[arg(long)]
        json: bool,
        #[arg(required = true)]
        images: Vec<PathBuf>,
    },
}

#[tokio::main]
async fn main() -> Result<()> {
    let cli = Cli::parse();
    let ca_cert = match &cli.ca_cert {
        Some(p) => Some(std::fs::read(p).with_context(|| format!("reading {}", p.display()))?),
        None => None,
    };
    let options = ClientOptions {
        endpoints: cli.endpoint.clone(),
        token: cli.token.clone(),
        ca_cert,
        tls_domain: cli.tls_domain.clone(),
        retries: cli.retries,
        eager: cli.endpoint.len() == 1,
    };
    let client = Client::connect_with(options).await.context("connecting")?;
    match cli.command {
        Command::Models { json } => {
            let models = client.list_models().await.context("listing models")?;
            if json {
                println!("{}", models_json(&models));
            } else {
                print_table(&models);
            }
        }
        Command::Describe { category } => {
            let d = client.describe_model(&category).await.with_context(|| format!("describing {category}"))?;
            let manifest: Value = serde_json::from_str(&d.manifest_json).unwrap_or(Value::Null);
            let info = d.info.unwrap_or_default();
            let out = json!({
                "category": info.category, "version": info.version, "ready": info.ready,
                "generation": d.generation, "trained_as": d.trained_as, "backbone": d.backbone,
                "feature_dim": d.feature_dim, "vertices": d.vertices, "crop": [d.crop_height, d.crop_width],
                "cuboid": d.cuboid, "error": d.error, "manifest": manifest,
            });
            println!("{}", serde_json::to_string_pretty(&out)?);
        }
        Command::Estimate { category, bbox, json, images } => {
            estimate(&client, &category, &bbox, json, &images).await?
        }
    }
    Ok(())
}

async fn estimate(
    client: &Client,
    category: &str,
    boxes: &[BoundingBox],
    json: bool,
    inputs: &[PathBuf],
) -> Result<()> {
    let files = expand(inputs)?;
    let width = files.iter().map(|f| f.display().to_string().len() + 3).max().unwrap_or(0).max("IMAGE".len());
    if !json {
        println!(
            "{:width$}  {:>9}  {:>9}  {:>8}  {:>8}  {:>6}  VERSION",
            "IMAGE", "AZIMUTH", "ELEVATION", "THETA", "DISTANCE", "SCORE"
        );
    }
    let mut failed = 0;
    for file in &files {
        let name = file.display().to_string();
        let result = async {
            let bytes = read_input(file)?;
            let request = EstimateRequest {
                category: category.into(),
                input: Some(Input::Image(bytes)),
                boxes: boxes.to_vec(),
                frame_id: name.clone(),
                options: None,
            };
            client.estimate(request).await.map_err(anyhow::Error::from)
        }
        .await;
        match result {
            Ok(response) if json => println!("{}", response_json(&name, &response)),
            Ok(response) => print_rows(&name, &response, width),
            Err(e) => {
                failed += 1;
                eprintln!("{name}: {e:#}");
            }
        }
    }
    if failed > 0 {
        bail!("{failed} of {} images failed", files.len());
    }
    Ok(())
}

/// Files as given; folders become their images (sorted); `-` is stdin.
fn expand(inputs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut images: Vec<PathBuf> = std::fs::read_dir(input)
                .with_context(|| format!("listing {}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| is_image(p))
                .collect();
            images.sort();
            if images.is_empty() {
                bail!("{} holds no PNG, JPEG or WebP files", input.display());
            }
            out.extend(images);
        } else {
            out.push(input.clone());
        }
    }
    Ok(out)
}

fn is_image(path: &Path) -> bool {
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg" | "webp"))
}

fn read_input(path: &Path) -> Result<Vec<u8>> {
    if path == Path::new("-") {
        let mut bytes = Vec::new();
        std::io::stdin().read_to_end(&mut bytes).context("reading stdin")?;
        return Ok(bytes);
    }
    std::fs::read(path).with_context(|| format!("reading {}", path.display()))
}

fn parse_box(s: &str) -> Result<BoundingBox, String> {
    let v: Vec<f64> =
        s.split(',').map(|x| x.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|e| e.to_string())?;
    match v.as_slice() {
        [x0, y0, x1, y1] => Ok(BoundingBox { x0: *x0, y0: *y0, x1: *x1, y1: *y1 }),
        _ => Err(format!("expected x0,y0,x1,y1, got {s:?}")),
    }
}

fn print_rows(name: &str, response: &EstimateResponse, width: usize) {
    for (i, p) in response.estimates.iter().enumerate() {
        let label = if response.estimates.len() > 1 { format!("{name}#{i}") } else { name.to_owned() };
        println!(
            "{label:width$}  {:>8.1}°  {:>8.1}°  {:>7.1}°  {:>8.3}  {:>6.3}  {}",
            p.azimuth_deg, p.elevation_deg, p.theta_deg, p.distance, p.score, p.model_version
        );
    }
}

/// The same shape as the HTTP API's answer, plus the image's name.
fn response_json(name: &str, r: &EstimateResponse) -> Value {
    let t = r.timings.unwrap_or_default();
    json!({
        "image": name,
        "model_version": r.model_version,
        "estimates": r.estimates.iter().map(pose_json).collect::<Vec<_>>(),
        "timings": {
            "decode_ms": t.decode_ms, "queue_ms": t.queue_ms, "crop_ms": t.crop_ms, "backbone_ms": t.backbone_ms,
            "solver_ms": t.solver_ms, "total_ms": t.total_ms, "batch_size": t.batch_size,
        },
    })
}

fn pose_json(p: &PoseEstimate) -> Value {
    let b = p.crop_box.unwrap_or_default();
    json!({
        "azimuth": p.azimuth, "elevation": p.elevation, "theta": p.theta,
        "azimuth_deg": p.azimuth_deg, "elevation_deg": p.elevation_deg, "theta_deg": p.theta_deg,
        "distance": p.distance, "rotation": p.rotation, "score": p.score,
        "hypotheses": p.hypotheses.iter().map(|h| json!({
            "azimuth": h.azimuth, "elevation": h.elevation, "theta": h.theta, "distance": h.distance, "score": h.score,
        })).collect::<Vec<_>>(),
        "crop_box": { "x0": b.x0, "y0": b.y0, "x1": b.x1, "y1": b.y1 },
        "cuboid": p.cuboid,
        "model_version": p.model_version,
    })
}

/// Same shape as the HTTP `GET /v1/models`; an empty version is `null`.
fn models_json(models: &[ModelInfo]) -> Value {
    let models: Vec<_> = models
        .iter()
        .map(|m| {
            let version = (!m.version.is_empty()).then_some(&m.version);
            json!({ "category": m.category, "version": version, "ready": m.ready })
        })
        .collect();
    json!({ "models": models })
}

fn print_table(models: &[ModelInfo]) {
    if models.is_empty() {
        println!("no models configured");
        return;
    }
    let width = models.iter().map(|m| m.category.len()).max().unwrap_or(0).max("CATEGORY".len());
    println!("{:width$}  {:5}  VERSION", "CATEGORY", "READY");
    for m in models {
        let ready = if m.ready { "yes" } else { "no" };
        let version = if m.version.is_empty() { "-" } else { &m.version };
        println!("{:width$}  {ready:5}  {version}", m.category);
    }
}
