//! `udapose`: command-line client for a udapose server (gRPC).

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use serde_json::json;
use udapose_client::{Client, ModelInfo};

/// Talk to a udapose pose-estimation server over gRPC.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    /// The server's gRPC address: `host:port` or `http://host:port`.
    #[arg(long, env = "UDAPOSE_ENDPOINT", default_value = "127.0.0.1:50051", global = true)]
    endpoint: String,
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
}

#[tokio::main]
async fn main() -> Result<()> {
    let cli = Cli::parse();
    let client = Client::connect(&cli.endpoint).await?;
    match cli.command {
        Command::Models { json } => {
            let models = client.list_models().await.context("listing models")?;
            if json {
                println!("{}", models_json(&models));
            } else {
                print_table(&models);
            }
        }
    }
    Ok(())
}

/// Same shape as the HTTP `GET /v1/models`; an empty version is `null`.
fn models_json(models: &[ModelInfo]) -> serde_json::Value {
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
