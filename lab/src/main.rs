//! `udapose-lab`: offline tools around the engine.

mod doctor;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "udapose-lab",
    version,
    about = "udapose offline tools: environment checks (more tools land with later issues)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the torch version, compute device, thread counts and which assets are available.
    Doctor(doctor::Args),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Doctor(args) => doctor::run(&args),
    }
}
